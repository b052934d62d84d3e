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
#: a word every phrase above holds: a line without one is not matched against the patterns (the
#: search reads megabytes of result files; the substring test is many times quicker than the regex)
_KEYWORDS = (
    "issue",
    "brief",
    "session",
    "round",
    "agent",
    "engineer",
    "helper",
    "coordinator",
    "reviewer",
    "requester",
    "filed by",
    "user's report",
    "stop",
    "lesson",
    "done when",
    "deliverable",
    "gpu",
    "larger machine",
)


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
        low = line.lower()
        if not any(k in low for k in _KEYWORDS):
            continue
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


@pytest.mark.parametrize(("name", "pattern"), PHRASES)
def test_every_phrase_holds_a_keyword(name: str, pattern: str) -> None:
    """A phrase's every alternative must hold a keyword, or the quick test would skip its lines."""
    depth, alternatives, start = 0, [], 0
    for k, ch in enumerate(pattern):  # split at the top level's "|" only
        depth += {"(": 1, ")": -1}.get(ch, 0)
        if ch == "|" and depth == 0:
            alternatives.append(pattern[start:k])
            start = k + 1
    for alternative in [*alternatives, pattern[start:]]:
        assert any(k in alternative.lower() for k in _KEYWORDS), (name, alternative)


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


# --- user pages: what to type and what comes out, not when or on which machine it was measured ---

#: Pages that carry the evidence (dated runs, machines, draw-by-draw histories): the development
#: notes and the generated benchmark reports. Every other page under docs/, and README, is a user page.
EVIDENCE = ("docs/notes.md", "docs/notes/", "docs/results.md", "docs/results/", "docs/beyond.md", "docs/beyond/")

#: (name, pattern): what a user page leaves to the evidence pages, case-insensitive.
USER_PAGE_PHRASES: list[tuple[str, str]] = [
    (
        "a date",
        r"\b20\d\d-[01]\d-[0-3]\d\b|\b(january|february|march|april|may|june|july|august|september|"
        r"october|november|december) 20\d\d\b",
    ),
    ("a machine's name", r"\b\d+-core VMs?\b"),
    ("a version's history", r"\bcommit [0-9a-f]{7,40}\b"),
    ("the draws a method was built on", r"\bbench draws\b|\bheld-out draws\b"),
]
_USER_PATTERN = re.compile("|".join(f"(?P<u{i}>{p})" for i, (_, p) in enumerate(USER_PAGE_PHRASES)), re.I)
#: a markdown link's target: a page may link a dated note, it does not carry it
_LINK_TARGET = re.compile(r"\]\([^)]*\)")


def user_pages() -> list[Path]:
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return [p for p in pages if not p.relative_to(ROOT).as_posix().startswith(EVIDENCE)]


def find_user_page_phrases(text: str) -> list[tuple[int, str, str]]:
    """(line number, kind, the words found) for each phrase of ``text`` a user page leaves out."""
    hits = []
    for lineno, line in enumerate(text.splitlines(), 1):
        for m in _USER_PATTERN.finditer(_LINK_TARGET.sub("]()", line)):
            kind = USER_PAGE_PHRASES[int(next(k for k, v in m.groupdict().items() if v is not None)[1:])][0]
            hits.append((lineno, kind, m.group(0)))
    return hits


def test_user_pages_leave_dates_machines_and_histories_to_the_evidence() -> None:
    pages = user_pages()
    assert len(pages) > 30 and ROOT / "docs" / "tutorial.md" in pages
    found = [
        f"{p.relative_to(ROOT)}:{lineno}: {kind}: {words!r}"
        for p in pages
        for lineno, kind, words in find_user_page_phrases(p.read_text(encoding="utf-8"))
    ]
    assert not found, "on user pages (move it to docs/notes/ or a benchmark report and link it):\n" + "\n".join(found)


@pytest.mark.parametrize(
    "line",
    [
        "measured on 2026-11-27 with the bench",
        "as of November 2026",
        "on the shared 2-core VM while other work ran",
        "| before (commit 6d93d06), `launch sim` |",
        "0.94 on the bench draws, 0.93 on the held-out draws",
    ],
)
def test_each_kind_of_user_page_phrase_is_caught(line: str) -> None:
    assert find_user_page_phrases(line)


def test_a_link_to_a_dated_note_is_not_a_date() -> None:
    assert not find_user_page_phrases("how it grew: [notes](notes/2026-11-28.md#how-the-field-benches-grew)")


def test_no_page_is_over_30_kb() -> None:
    big = [
        f"{p.relative_to(ROOT)}: {p.stat().st_size / 1000:.1f} kB"
        for p in [ROOT / "README.md", *(ROOT / "docs").rglob("*.md")]
        if p.stat().st_size > 30_000
    ]
    assert not big, "pages over 30 kB (split them; a user reads a page in minutes):\n" + "\n".join(big)
