"""``twinfocus bench where``: each way focus finds what is not typed, as a row against typed."""

import json

import pytest

from twinfocus.evaluation.where import ROWS, summarise, where_markdown


def _rec(row, ssim, seed, **extra):
    return {"row": row, "ssim": ssim, "seconds": 1.0, "reference": "A", "target": "C", "seed": seed, **extra}


def test_rows_are_read_against_the_typed_regions_of_the_same_scene():
    records = [
        _rec("typed", 0.9, 0),
        _rec("typed", 0.8, 1),
        _rec("depth found", 0.85, 0, depth_error_m=-0.002),
        _rec("depth found", 0.8, 1, depth_error_m=0.004),
        _rec("best of two twins", 0.9, 0, right_twin=True),
        _rec("best of two twins", 0.5, 1, right_twin=False),
    ]
    s = summarise(records)
    assert list(s) == ["typed", "depth found", "best of two twins"]
    assert s["depth found"]["minus_typed"] == pytest.approx(-0.025) and s["depth found"][
        "depth_error_mm"
    ] == pytest.approx(3.0)
    assert s["best of two twins"]["right_twin"] == 0.5 and s["best of two twins"]["minus_typed"] == pytest.approx(-0.15)
    md = where_markdown(
        {
            "scenes": 2,
            "pairs": [["A", "C"]],
            "settings": {"columns": 3, "rows": 40, "size": 48},
            "command": "twinfocus bench where",
            "summary": s,
        }
    )
    assert "| depth found |" in md and "-0.025" in md and "50%" in md


@pytest.mark.slow
def test_bench_where_quick_writes_a_row_for_each(tmp_path):
    from twinfocus.cli import main

    assert main(["bench", "where", "--quick", "--out", str(tmp_path), "--quiet"]) == 0
    doc = json.loads((tmp_path / "raw" / "where.json").read_text())
    assert list(doc["summary"]) == list(ROWS)
    s = doc["summary"]
    # the depth is found within a centimetre from the box alone and from a typed depth 5 cm off
    assert s["depth found"]["depth_error_mm"] < 10 and s["depth 5 cm off"]["depth_error_mm"] < 10
    assert s["both found"]["depth_error_mm"] < 10
    assert s["best of two twins"]["right_twin"] == 1.0
    assert s["depth found"]["minus_typed"] > -0.02
    assert (tmp_path / "report.md").read_text().count("\n| ") == len(ROWS) + 1
    assert main(["bench", "where", "--report-only", "--out", str(tmp_path), "--markdown", str(tmp_path / "r.md")]) == 0
    assert (tmp_path / "r.md").read_text() == (tmp_path / "report.md").read_text()
