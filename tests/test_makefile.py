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
