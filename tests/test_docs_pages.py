"""The how-to pages run as written, in order, and make the figures they quote.

Each chain of ``RUNS`` has its pages' ```sh blocks run in order in one empty folder (as
``python -m benchmarks.docs_pages`` does, a page's ``<!-- after: ... -->`` prerequisites first);
every block must succeed, and every figure a page quotes from its own result file must be what
this run made, within the spread of a rerun: SSIMs within 0.005, counts and sizes within 10 %
(a graph's heartbeats and poses follow the clock), times not compared (they are the machine's).
tests/test_tutorial.py does the same for the tutorial, with its printed lines.

A how-to not listed here says on the page why its commands cannot run here (your own data or
device, or a session that runs until Ctrl-C); ``test_every_how_to_runs_or_says_why`` keeps
that true.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from benchmarks.docs_pages import ROOT, blocks, made, prerequisites, result_file
from tests.helpers import page_folder, run_page_blocks
from tests.test_docs_figures import lookup, marked_figures

#: chains of pages run in one folder each, in order: a later page uses what an earlier one made
RUNS = [
    ["docs/howto/many_scans.md"],
    ["docs/howto/digital_twin.md"],
    ["docs/howto/replay_log.md", "docs/howto/foxglove.md"],
    ["docs/howto/focus_handheld.md"],
    ["docs/howto/find_depth_and_volume.md"],
]
#: pages whose blocks a test of their own runs in order (it checks more than this runner does)
RUN_BY_OWN_TEST = {"docs/howto/your_own_rig.md": "tests/test_your_own_rig_page.py"}
RUNNABLE = [page for chain in RUNS for page in chain] + list(RUN_BY_OWN_TEST)
#: what a how-to that runs nothing here must say, in its own words, before the block it does not run
NOT_RUN = ("not run by the test suite", "the test suite does not run")
_COMMAND = re.compile(r"^\s*(?:\$\s*)?twinfocus [a-z][a-z-]*(?=\s|$)(?!:)", re.M)


def test_a_runnable_page_has_commands_and_a_result_file() -> None:
    for page in RUNNABLE:
        assert "```sh\n" in (ROOT / page).read_text(encoding="utf-8"), page
        assert result_file(ROOT / page).is_file(), f"run python -m benchmarks.docs_pages {page}"


def test_a_chain_runs_each_pages_prerequisites_first() -> None:
    for chain in RUNS:
        for i, page in enumerate(chain):
            assert all(p.relative_to(ROOT).as_posix() in chain[:i] for p in prerequisites(ROOT / page)), page


def test_every_how_to_runs_or_says_why() -> None:
    for own_test in RUN_BY_OWN_TEST.values():
        assert (ROOT / own_test).is_file(), own_test
    for page in sorted((ROOT / "docs" / "howto").glob("*.md")):
        rel = page.relative_to(ROOT).as_posix()
        text = page.read_text(encoding="utf-8")
        # a plain block's line "twinfocus CMD ..." is a command shown; "twinfocus CMD: ..." is what one printed
        commands = [body for lang, body in blocks(text) if lang == "" and _COMMAND.search(body)]
        runs_here = [body for lang, body in blocks(text) if lang == "sh"]
        assert not runs_here or rel in RUNNABLE, f"{rel} has ```sh blocks: list it in RUNS"
        if not commands:
            continue
        assert any(why in " ".join(text.split()) for why in NOT_RUN), (
            f"{rel} shows commands the tests do not run and does not say why: {commands[:1]}"
        )


def _quoted(page: str) -> list[tuple[str, str]]:
    """(number as printed, where) for each figure ``page`` marks from its own result file."""
    own = result_file(ROOT / page).relative_to(ROOT).as_posix()
    return [(printed, where) for p, printed, file, where in marked_figures() if p == page and file == own]


def _agrees(where: str, quoted: float, value: float) -> bool:
    if "timings_s" in where or "seconds" in where:
        return True
    if "ssim" in where:
        return abs(quoted - value) <= 0.005
    return abs(quoted - value) <= 0.1 * abs(quoted) + 1


@pytest.mark.slow
@pytest.mark.parametrize("chain", RUNS, ids=[" + ".join(Path(p).stem for p in c) for c in RUNS])
def test_the_pages_run_as_written_and_make_what_they_quote(chain: list[str], tmp_path: Path) -> None:
    work, env = page_folder(tmp_path)
    for page in chain:
        run_page_blocks(ROOT / page, work, env)
        now = made(work)
        committed = json.loads(result_file(ROOT / page).read_text())
        assert sorted(now["outputs"]) == sorted(committed["outputs"]), page
        assert sorted(now["logs"]) == sorted(committed["logs"]), page
        for printed, where in _quoted(page):
            value = float(lookup(now, where))
            assert _agrees(where, float(printed), value), f"{page} quotes {printed} for {where}; this run made {value}"
