"""The Makefile's comments quote the files its figures come from, and nothing older."""

from __future__ import annotations

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_test_fast_comment_says_what_its_file_says() -> None:
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    comment = " ".join(
        makefile[: makefile.index("test-fast: $(STAMP)")].rsplit("\n\n", 1)[-1].replace("#", " ").split()
    )
    measured = json.loads((ROOT / "benchmarks" / "results" / "test_fast.json").read_text())
    assert "benchmarks/results/test_fast.json" in comment
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
    assert "two minutes" not in comment and "about" not in comment  # no estimate beside the measurement
