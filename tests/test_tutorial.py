"""docs/tutorial.md as written: its ```sh blocks run in order in an empty folder, every file it
names comes out, the lines it shows are printed, and the confidence report it quotes is the one
the run writes."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from benchmarks.docs_pages import blocks
from tests.helpers import page_folder, run_page_blocks

ROOT = Path(__file__).resolve().parents[1]
TUTORIAL = ROOT / "docs" / "tutorial.md"
_OUTPUT_FILE = re.compile(r"`((?:[\w.-]+/)*[\w.-]+\.(?:npz|npy|json|png|bin|txt))`")


def named_outputs(text: str) -> list[str]:
    """The files the tutorial says a step writes: backticked relative paths outside docs/."""
    prose = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return sorted({p for p in _OUTPUT_FILE.findall(prose) if not p.startswith(("docs/", "images/", ".venv"))})


def test_the_parser_finds_the_steps() -> None:
    text = TUTORIAL.read_text(encoding="utf-8")
    sh = [body for lang, body in blocks(text) if lang == "sh"]
    assert any("twinfocus convert" in b for b in sh) and any("twinfocus focus" in b for b in sh)
    assert "focused/summary.png" in named_outputs(text) and "hand.npz" in named_outputs(text)


@pytest.mark.slow
def test_the_tutorial_runs_as_written(tmp_path: Path) -> None:
    text = TUTORIAL.read_text(encoding="utf-8")
    # `python` and `twinfocus` are the environment's, as after `source .venv/bin/activate`.
    work, env = page_folder(tmp_path, "tutorial")
    printed = "".join(r["printed"] for r in run_page_blocks(TUTORIAL, work, env))

    missing = [p for p in named_outputs(text) if not (work / p).is_file()]
    assert not missing, f"the tutorial names files its commands did not write: {missing}"

    shown = [body for lang, body in blocks(text) if lang in ("", "text")]
    lines = [
        ln.strip()
        for body in shown
        for ln in body.splitlines()
        if ln.startswith(("[convert]", "[calibrate]", "twinfocus focus:"))
    ]
    assert lines, "the tutorial shows no output line to check"
    for line in lines:
        assert line in printed, f"the tutorial shows a line the run did not print: {line}"

    quoted = next(json.loads(body) for lang, body in blocks(text) if lang == "text" and body.lstrip().startswith("{"))
    report = json.loads((work / "focused" / "metrics.json").read_text())["confidence"]
    assert report["trusted"] is quoted["trusted"] is True and report["warnings"] == quoted["warnings"] == []
    assert sorted(quoted) == sorted(report), "the tutorial's confidence block and the file's keys differ"
    for key in ("separation_deg", "transfer_bound_rad_max", "reference_match_ssim", "phase_concentration"):
        assert report[key] == pytest.approx(quoted[key], abs=0.01), key
    assert json.loads((work / "focused_2mm" / "metrics.json").read_text())["confidence"]["trusted"] is False

    # every key the run wrote is in the metrics.json reference
    written = json.loads((work / "focused" / "metrics.json").read_text())
    page = (ROOT / "docs" / "reference" / "metrics.md").read_text(encoding="utf-8")
    keys = [*written, *(f"confidence.{k}" for k in written["confidence"])]
    undocumented = [
        k for k in keys if f"`{k}`" not in page and f"`{k}." not in page and f"`{k.split('.')[-1]}`" not in page
    ]
    assert not undocumented, f"docs/reference/metrics.md does not describe {undocumented}"


def test_the_thresholds_the_tutorial_quotes_are_the_reports() -> None:
    from twinfocus.focus.pipeline import MIN_REFERENCE_MATCH, MIN_REFERENCE_MATCH_PHYSICAL

    text = " ".join(TUTORIAL.read_text(encoding="utf-8").split())
    assert f"warns below {MIN_REFERENCE_MATCH_PHYSICAL} for a physical twin's template" in text
    assert f"below {MIN_REFERENCE_MATCH} for a digital twin's" in text
