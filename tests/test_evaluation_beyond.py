"""``twinfocus bench beyond --quick`` end to end: every twin variant runs on the same draws, the
report has its tables and goals, and ``--resume`` keeps what is done. Its own file (the slowest
test of the suite) so that ``make test``'s workers (``--dist loadfile``) run it beside
tests/test_evaluation.py's quick paper benchmark, not after it."""

from __future__ import annotations

import json

import pytest

from twinfocus.cli import main as cli_main


@pytest.mark.slow
def test_beyond_quick_end_to_end(tmp_path):
    """``twinfocus bench beyond --quick``: every variant runs on the same draws, the closed-form
    estimate improves on no correction, the report has its tables and the goals, and
    ``--resume`` keeps what is done."""
    from twinfocus.evaluation.beyond import DRIFT_METHODS, METHODS, ROW_NAMES, SV_ROWS

    out = tmp_path / "beyond"
    assert cli_main(["bench", "beyond", "--quick", "--out", str(out), "--quiet"]) == 0
    err = json.loads((out / "raw" / "beyond_error.json").read_text())
    for cond in ("0.5 mm x/y/z", "1.6 mm z"):
        rec = {r["method"]: r for r in err["records"] if r["condition"] == cond}
        assert set(rec) == set(METHODS) and all(r["status"] == "ok" for r in rec.values())
        assert rec["physical-correlation"]["ssim"] > rec["none"]["ssim"] + 0.05
        assert rec["physical-correlation"]["autofocus_s"] < rec["physical"]["autofocus_s"]
    drift = {r["method"]: r for r in err["records"] if r["condition"].startswith("1.6 mm z drift")}
    assert set(drift) == set(DRIFT_METHODS) and all(r["status"] == "ok" for r in drift.values())
    sv = json.loads((out / "raw" / "beyond_space_variant.json").read_text())
    rows = {r["row"]: r["ssim"] for r in sv["records"]}
    # quick scans (240 positions, 32 x 32) are too coarse for the fit to pay: only the plumbing
    # here; tests/test_space_variant.py checks the fit against exact phases
    assert set(rows) == set(SV_ROWS) and rows["ceiling-target"] > rows["none"] + 0.1
    md = (out / "report.md").read_text()
    for heading in ("## Tracking error", "## Reference-target angular separation", "## Space-variant", "## The goals"):
        assert heading in md
    assert "kept from an earlier run" not in md
    # every variant has its row, the smoothness prior only in the drift column
    assert all(ROW_NAMES[m] in md for m in METHODS + DRIFT_METHODS if m != "none")
    smooth_row = next(line for line in md.splitlines() if line.startswith(f"| {ROW_NAMES['digital-smooth']} |"))
    assert smooth_row.count(" - |") >= 2
    before = (out / "raw" / "beyond_error.json").stat().st_mtime_ns
    assert cli_main(["bench", "beyond", "--quick", "--out", str(out), "--quiet", "--resume"]) == 0
    assert (out / "raw" / "beyond_error.json").stat().st_mtime_ns == before
