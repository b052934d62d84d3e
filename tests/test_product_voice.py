"""The product speaks only of itself: README, docs, code, tests and benchmarks never say how or by
whom they were made (a ticket number, "the brief", "this round", "other agents", ...).

A user reads ``docs/`` and the code's comments to learn what the product does; a reference to a
ticket or to the circumstances of a change means nothing to them. Each phrase below is one a
reader cannot act on; a line that needs such a word for a real reason can be rephrased.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Where the product's own words live.
SEARCHED = ["README.md", "docs", "twinfocus", "nodes", "msgs", "launch", "tests", "benchmarks"]
SUFFIXES = {".md", ".py", ".yaml", ".yml", ".json", ".toml", ".txt"}

#: (name, pattern): phrases about the making of the product, case-insensitive.
PHRASES: list[tuple[str, str]] = [
    ("ticket number", r"\bissues?\s*#?\d+"),
    ("a ticket", r"\bthe issue\b|\bthe issue's\b|\bthis issue\b"),
    ("the brief", r"\bthe brief\b"),
    ("a work session", r"\b(this|that|the first|another|each|an earlier|a later) session\b"),
    ("other sessions", r"\bsessions' (jobs|work)\b|\bother sessions\b"),
    ("a work round", r"\b(this|that|the last|an earlier|the previous) round\b"),
    ("who made it", r"\b(other|another|\d+) (agents?|engineers?|helpers?)\b|\bagents\b"),
    ("the one who asked", r"\bthe (coordinator|reviewer|requester)\b|\bfiled by\b|\bthe user's report\b"),
    ("a stopping point", r"\bthis stop\b|\btried this stop\b"),
    ("a diary's lesson", r"\bthe lesson of\b"),
    ("a to-do list", r"\bdone when\b|\bdeliverables?\b"),
    ("what the writer lacked", r"\bno gpu (in|on) this\b|\bno larger machine (in|on) this\b"),
]
_PATTERN = re.compile("|".join(f"(?P<p{i}>{p})" for i, (_, p) in enumerate(PHRASES)), re.I)


def _files() -> list[Path]:
    me = Path(__file__).resolve()
    out: list[Path] = []
    for name in SEARCHED:
        path = ROOT / name
        found = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
        out += [p for p in found if p.suffix in SUFFIXES and p.resolve() != me and "__pycache__" not in p.parts]
    return out


def find_phrases(text: str) -> list[tuple[int, str, str]]:
    """(line number, phrase kind, the words found) for each making-of phrase in ``text``."""
    hits = []
    for lineno, line in enumerate(text.splitlines(), 1):
        for m in _PATTERN.finditer(line):
            kind = PHRASES[int(next(k for k, v in m.groupdict().items() if v is not None)[1:])][0]
            hits.append((lineno, kind, m.group(0)))
    return hits


def test_no_file_speaks_of_how_the_product_was_made() -> None:
    files = _files()
    assert len(files) > 100, "the search found too few files to mean anything"
    found = [
        f"{p.relative_to(ROOT)}:{lineno}: {kind}: {words!r}"
        for p in files
        for lineno, kind, words in find_phrases(p.read_text(encoding="utf-8", errors="replace"))
    ]
    assert not found, "phrases about how the product was made:\n" + "\n".join(found)


@pytest.mark.parametrize(
    "line",
    [
        "the rough scenes of issue 14 (docs/simulation.md)",
        "Live graph latency (Issue #17 item 4)",
        "The brief asked for Dask unless another engine serves better.",
        "untested here, no GPU in this session",
        "while 7 other agents loaded it",
        "The last row is the lesson of this round.",
        "shared with other sessions' jobs",
        "the first session removes it only while the phases are coherent",
    ],
)
def test_each_kind_of_making_of_phrase_is_caught(line: str) -> None:
    assert find_phrases(line)


@pytest.mark.parametrize(
    "line",
    [
        "each node as a child process (its own session and a parent-death signal)",
        "unless another address is asked for",
        "the paper's five error draws per pair (round-robin over workers)",
        "the brightest pixels, rounded to the grid",
        "a Foxglove client's session sees the latest message",
    ],
)
def test_the_products_own_words_pass(line: str) -> None:
    assert not find_phrases(line)
