"""Every link, picture and path that README.md and docs/ name exists in the repository.

A fresh clone holds only what git tracks, so a path counts when git tracks it (or, for a folder,
tracks something under it); outside a git checkout the file system is asked instead.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Paths a page may name before the file exists (a page written ahead of its figure); the test
#: fails once an entry exists, so the list cannot go stale.
KNOWN_MISSING: set[str] = set()

_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
_CODE_PATH = re.compile(r"`((?:docs|benchmarks|launch)/[A-Za-z0-9_./-]+)`")
_FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def _markdown_files() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def _tracked() -> set[str] | None:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    files = {f for f in out.decode().split("\0") if f}
    return files | {str(p) for f in files for p in Path(f).parents if str(p) != "."}


def _exists(rel: str, tracked: set[str] | None) -> bool:
    rel = rel.rstrip("/")
    if tracked is None:
        return (ROOT / rel).exists()
    return rel in tracked


def _named_paths(md: Path, text: str | None = None) -> list[tuple[str, str]]:
    """(path relative to the repository root, as written) for every local link, picture and
    backticked docs/, benchmarks/ or launch/ path outside fenced code blocks of ``md`` (or of
    ``text``, read as if it were ``md``)."""
    text = _FENCE.sub("", md.read_text(encoding="utf-8") if text is None else text)
    out = []
    for target in _LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL or an anchor on this page
        path = target.split("#", 1)[0]
        resolved = (md.parent / path).resolve()
        out.append((resolved.relative_to(ROOT).as_posix() if resolved.is_relative_to(ROOT) else target, target))
    for path in _CODE_PATH.findall(text):
        if not any(c in path for c in "*{}<>") and "..." not in path:
            out.append((path, path))
    return out


@pytest.mark.parametrize("md", _markdown_files(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_named_path_exists(md: Path) -> None:
    tracked = _tracked()
    missing = [
        f"{written} -> {rel}"
        for rel, written in _named_paths(md)
        if rel not in KNOWN_MISSING and not _exists(rel, tracked)
    ]
    assert not missing, f"{md.relative_to(ROOT)} names paths not in the repository: {missing}"


def test_known_missing_are_still_missing() -> None:
    tracked = _tracked()
    present = sorted(p for p in KNOWN_MISSING if _exists(p, tracked))
    assert not present, f"{present} now exist: remove them from KNOWN_MISSING"


def test_the_walker_sees_links_pictures_and_code_paths() -> None:
    text = (
        "![p](images/x.png) [a](architecture.md#s) [w](https://x.org) [h](#top) `launch/sim.yaml`\n"
        "```\n[in code](nowhere.md)\n```\n`docs/results/raw/*.json` [up](../README.md)\n"
    )
    got = sorted(rel for rel, _ in _named_paths(ROOT / "docs" / "probe.md", text))
    assert got == ["README.md", "docs/architecture.md", "docs/images/x.png", "launch/sim.yaml"]
    assert not _exists("docs/images/x.png", _tracked())


def test_the_index_lists_every_page() -> None:
    """docs/README.md is the way in: every page under docs/ is linked from it, or from the page the
    index links that is named as the page's folder (reference/commands.md lists commands/*.md)."""
    index = ROOT / "docs" / "README.md"
    linked = {rel for rel, _ in _named_paths(index)}
    pages = {p.relative_to(ROOT).as_posix() for p in (ROOT / "docs").rglob("*.md") if p != index}
    for folder_page in [p for p in linked if p.endswith(".md") and (ROOT / p).with_suffix("").is_dir()]:
        linked |= {rel for rel, _ in _named_paths(ROOT / folder_page) if rel.startswith(folder_page[:-3] + "/")}
    assert not sorted(pages - linked), f"pages the index does not list: {sorted(pages - linked)}"
