"""Every figure a page marks as read from a file is what that file holds.

A page quotes a measured figure as ``0.987<!-- figure: benchmarks/results/core.json#trade_estimator[size=100,estimator=correlation].ssim -->``:
the number, then a comment naming the file (from the repository's root) and where in it the value
lies: dotted keys, ``[k=v,...]`` to pick the one row of a list whose fields have those values, and
over a list of records a mean, sd, min, ... (``hand.mean(default)``: benchmarks/page_tables.py's
:func:`lookup`, which the generated tables read with).
A key or value holding a space, dot, bracket, comma or ``=`` is percent-encoded as in a URL
(``summary.depth%205%20cm%20off.mean_ssim`` reads the key ``"depth 5 cm off"``).
The number must be the value rounded to the decimals shown. The scripts that write the files are
named on each page beside its figures.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from benchmarks.page_tables import lookup

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])
_MARKED = re.compile(r"(-?\d+(?:\.\d+)?)\s*(?:[a-zA-Z%]+)?<!-- figure: ([^#\s]+)#(\S+) -->")


def marked_figures() -> list[tuple[str, str, str, str]]:
    """(page, number as printed, file, where) for every marked figure of every page."""
    found = []
    for page in PAGES:
        for m in _MARKED.finditer(page.read_text(encoding="utf-8")):
            found.append((str(page.relative_to(ROOT)), m.group(1), m.group(2), m.group(3)))
    return found


def test_the_lookup_reads_rows_and_keys() -> None:
    data = {"t": [{"size": 50, "v": {"s": 1.25}}, {"size": 100, "v": {"s": 2.5}}]}
    assert lookup(data, "t[size=100].v.s") == 2.5
    with pytest.raises(KeyError):
        lookup(data, "t[size=75].v.s")


def test_the_lookup_reads_percent_encoded_keys_and_values() -> None:
    data = {"rows": {"depth 5 cm off": {"a.b": 0.25}}, "t": [{"row": "both found", "v": 1}, {"row": "both", "v": 2}]}
    assert lookup(data, "rows.depth%205%20cm%20off.a%2Eb") == 0.25
    assert lookup(data, "t[row=both%20found].v") == 1
    marker = _MARKED.search("0.25<!-- figure: f.json#rows.depth%205%20cm%20off.a%2Eb -->")
    assert marker is not None and lookup(data, marker.group(3)) == 0.25


def test_pages_mark_their_figures() -> None:
    assert len(marked_figures()) >= 10


@pytest.mark.parametrize(("page", "printed", "file", "where"), marked_figures())
def test_a_marked_figure_is_its_files(page: str, printed: str, file: str, where: str) -> None:
    value = float(lookup(json.loads((ROOT / file).read_text()), where))
    decimals = len(printed.split(".")[1]) if "." in printed else 0
    assert float(printed) == pytest.approx(round(value, decimals), abs=10 ** -(decimals + 3)), (
        f"{page} quotes {printed} for {file}#{where}, which holds {value}"
    )
