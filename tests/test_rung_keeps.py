"""Every rung that keeps its fit whatever it gives says why, measured: its ``keeps_because``
(metrics.json ``model.rungs[].why``) quotes benchmarks/bench_rung_keeps.py's held-out figures,
and those figures are what benchmarks/results/rung_keeps.json holds (the way
tests/test_docs_figures.py checks the pages)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from twinfocus.focus.rungs import RUNGS, Rung

ROOT = Path(__file__).resolve().parents[1]
FILE = ROOT / "benchmarks" / "results" / "rung_keeps.json"
#: the figures a ``keeps_because`` quotes, in its order
FIGURES = ("kept", "draws", "gain_mean", "gain_min")
_NUMBER = re.compile(r"(?<![\w.])-?\d+(?:\.\d+)?")


def _measured() -> dict:
    return json.loads(FILE.read_text())["rungs"]


def test_the_rungs_that_always_keep_are_the_measured_ones():
    """A rung with a measured reason is one the file measures, and the file measures no other."""
    says = {name for name, cls in RUNGS.items() if cls.keeps_because != Rung.keeps_because}
    assert says == set(_measured())
    # a rung that keeps by the default rule (always) must say why, measured
    assert all(cls.keeps_because != Rung.keeps_because for cls in RUNGS.values() if cls.keep is Rung.keep)


@pytest.mark.parametrize("name", sorted(_measured()))
def test_a_rungs_keeps_because_quotes_its_files_figures(name):
    text = RUNGS[name].keeps_because
    assert "rung_keeps.json" in text
    printed = _NUMBER.findall(text)
    assert len(printed) == len(FIGURES), f"{name}: {text!r} quotes {printed}"
    for figure, key in zip(printed, FIGURES):
        value = float(_measured()[name][key])
        decimals = len(figure.split(".")[1]) if "." in figure else 0
        assert float(figure) == pytest.approx(round(value, decimals), abs=10 ** -(decimals + 3)), (
            f"{name} quotes {figure} for {key}, the file holds {value}"
        )
