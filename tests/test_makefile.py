"""The Makefile's comments quote the files its figures come from, and nothing older."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(("target", "name"), [("test-fast", "test_fast"), ("test", "test_suite")])
def test_the_test_targets_comments_say_what_their_files_say(target: str, name: str) -> None:
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    comment = " ".join(
        makefile[: makefile.index(f"\n{target}: $(STAMP)") + 1].rsplit("\n\n", 1)[-1].replace("#", " ").split()
    )
    measured = json.loads((ROOT / "benchmarks" / "results" / f"{name}.json").read_text())
    assert f"benchmarks/results/{name}.json" in comment
    m = re.search(
        r"([\d.]+) s wall for (\d+) tests \(([\d.]+) s of summed test durations\) at load ([\d.]+) -> ([\d.]+)", comment
    )
    assert m, comment
    assert float(m.group(1)) == measured["wall_s"] and int(m.group(2)) == measured["tests_collected"]
    assert float(m.group(3)) == measured["sum_of_durations_s"]
    assert [float(m.group(4)), float(m.group(5))] == [
        measured["load_average_1_5_15_before"][0],
        measured["load_average_1_5_15_after"][0],
    ]
    # the run passed, but for this test itself: the run that measures the suite checks the comment
    # it is about to replace
    assert all(f.startswith("tests/test_makefile.py::") for f in measured.get("failed", [])), measured["failed"]
    assert "two minutes" not in comment and "about" not in comment  # no estimate beside the measurement


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()  # PEP 503


def _pins() -> dict[str, str]:
    lines = (ROOT / "constraints.txt").read_text(encoding="utf-8").splitlines()
    pairs = (line.split("==") for line in lines if line and not line.startswith("#"))
    return {_canonical(name): version for name, version in pairs}


def test_the_installed_packages_are_the_measured_versions() -> None:
    """The environment the tests run in is the one constraints.txt records (make installs with it),
    and every package the project asks for, the test extra included, is pinned there: a figure
    measured with one OpenCV is not checked against another's letters."""
    from importlib import metadata

    from packaging.requirements import Requirement

    pins = _pins()
    asked = [Requirement(r) for r in metadata.requires("twinfocus") or []]
    unpinned = sorted({_canonical(r.name) for r in asked} - set(pins))
    assert not unpinned, f"constraints.txt pins no version of {unpinned}: rerun pip freeze into it"
    wrong = {}
    for name, version in pins.items():
        try:
            installed = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue  # pinned but not asked for on this platform
        if installed != version:
            wrong[name] = (installed, version)
    assert not wrong, f"installed != constraints.txt (installed, pinned): {wrong}; run make to reinstall"
