"""The API reference (`make api-docs`) builds from the docstrings and has a page for every module."""

from __future__ import annotations

import html
import importlib
import os
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import twinfocus
from twinfocus.io.atomic import atomic_writer

ROOT = Path(__file__).resolve().parents[1]


def _listed(module: str) -> bool:
    parent, _, name = module.rpartition(".")
    listed = getattr(importlib.import_module(parent), "__all__", None)
    return listed is None or name in listed


@pytest.mark.slow
def test_the_api_reference_builds(tmp_path: Path) -> None:
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    pdoc = Path(sys.executable).with_name("pdoc")
    run = subprocess.run(
        [str(pdoc), "-o", str(tmp_path), "twinfocus", "msgs", "nodes"], env=env, capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr[-2000:]
    # pdoc documents a package's submodules unless its __all__ leaves them out (twinfocus.scene
    # re-exports its names instead), and no __main__.
    modules = [
        m.name
        for m in pkgutil.walk_packages(twinfocus.__path__, "twinfocus.")
        if not m.name.endswith("__main__") and _listed(m.name)
    ]
    missing = [m for m in modules if not (tmp_path / (m.replace(".", "/") + ".html")).is_file()]
    assert not missing, f"no API page for {missing}"
    # The docstring's words reach the page (pdoc renders ``code`` as markup, so the first words).
    page = " ".join(html.unescape((tmp_path / "twinfocus" / "io" / "atomic.html").read_text(encoding="utf-8")).split())
    assert " ".join(atomic_writer.__doc__.split()[:5]) in page
