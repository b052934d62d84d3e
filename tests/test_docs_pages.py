"""The how-to pages whose commands run here run as written, and make the figures they quote.

Each page in ``RUNNABLE`` has its ```sh blocks run in order in an empty folder (as
``python -m benchmarks.docs_pages`` does); every block must succeed, and the SSIMs of what they
made must be those of the committed result file the page quotes from. tests/test_tutorial.py
does the same for the tutorial, with its printed lines.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.docs_pages import ROOT, output_figures, page_env, result_file, run_blocks

#: pages that make everything they use; the others need a device or a running graph and say so
RUNNABLE = ["docs/howto/many_scans.md", "docs/howto/digital_twin.md"]


def test_a_runnable_page_has_commands_and_a_result_file() -> None:
    for page in RUNNABLE:
        assert "```sh\n" in (ROOT / page).read_text(encoding="utf-8"), page
        assert result_file(ROOT / page).is_file(), f"run python -m benchmarks.docs_pages {page}"


@pytest.mark.slow
@pytest.mark.parametrize("page", RUNNABLE)
def test_the_page_runs_as_written(page: str, tmp_path: Path) -> None:
    work = tmp_path / "work"
    work.mkdir()
    runs = run_blocks(ROOT / page, work, page_env(tmp_path / "cache"))
    failed = [r for r in runs if r["returncode"] != 0]
    assert not failed, f"{page}: step failed:\n{failed[0]['block']}\n{failed[0]['printed'][-3000:]}"
    made = output_figures(work)
    committed = json.loads(result_file(ROOT / page).read_text())["outputs"]
    assert sorted(made) == sorted(committed)
    for folder, figures in committed.items():
        for key, value in figures.items():
            if "ssim" in key:
                assert made[folder][key] == pytest.approx(value, abs=0.005), f"{folder} {key}"
