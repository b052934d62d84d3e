"""Run a docs page's commands as written and write what they produced, for the page to quote.

    python -m benchmarks.docs_pages docs/howto/speed_or_accuracy.md     # -> benchmarks/results/pages/howto_speed_or_accuracy.json

A page's ```sh blocks run in order in one empty folder (``--work`` keeps it), with the
environment's ``twinfocus`` and ``python`` first on PATH, as after ``source .venv/bin/activate``.
The result file holds each block's exit status and seconds, and, for every folder the commands
left a ``metrics.json`` in, its numeric figures (top level and ``confidence``). A page quotes
them with figure markers (tests/test_docs_figures.py checks each against this file); the
tests run the pages' blocks the same way (tests/test_tutorial.py, tests/test_docs_pages.py).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from twinfocus.atomic import write_text_atomic

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "pages"
_BLOCK = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)


def blocks(text: str) -> list[tuple[str, str]]:
    """(language, body) of every fenced block of a markdown ``text``, in order."""
    return [(m.group(1), m.group(2)) for m in _BLOCK.finditer(text)]


def page_env(cache_dir: Path) -> dict[str, str]:
    """The environment a reader has after activating the venv, with this checkout's code first."""
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONPATH"] = f"{ROOT}{os.pathsep}{env.get('PYTHONPATH', '')}"
    env["TWINFOCUS_CACHE_DIR"] = str(cache_dir)
    return env


def run_blocks(page: Path, work: Path, env: dict[str, str]) -> list[dict]:
    """Run every ```sh block of ``page`` in ``work``, in order; stop at the first that fails.
    Returns one record per block run: its text, exit status, seconds and what it printed."""
    runs = []
    for lang, body in blocks(page.read_text(encoding="utf-8")):
        if lang != "sh":
            continue
        t0 = time.perf_counter()
        run = subprocess.run(
            ["bash", "-euo", "pipefail", "-c", body], cwd=work, env=env, capture_output=True, text=True
        )
        runs.append(
            {
                "block": body,
                "returncode": run.returncode,
                "seconds": round(time.perf_counter() - t0, 2),
                "printed": run.stdout + run.stderr,
            }
        )
        if run.returncode != 0:
            break
    return runs


def _numbers(d: dict) -> dict:
    return {k: v for k, v in d.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}


def output_figures(work: Path) -> dict[str, dict]:
    """For every folder under ``work`` holding a metrics.json: its numeric figures, the
    confidence report's numeric figures and ``trusted``, keyed by the folder's relative path."""
    out = {}
    for metrics_file in sorted(work.rglob("metrics.json")):
        m = json.loads(metrics_file.read_text())
        figures = _numbers(m)
        if isinstance(m.get("confidence"), dict):
            figures["confidence"] = {**_numbers(m["confidence"]), "trusted": m["confidence"].get("trusted")}
        if isinstance(m.get("timings_s"), dict):
            figures["timings_s"] = _numbers(m["timings_s"])
        out[metrics_file.parent.relative_to(work).as_posix()] = figures
    return out


def result_file(page: Path) -> Path:
    """Where the figures of ``page`` (a path under docs/) are written."""
    rel = page.resolve().relative_to(ROOT / "docs").with_suffix("")
    return RESULTS / ("_".join(rel.parts) + ".json")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pages", nargs="+", type=Path, help="docs pages whose ```sh blocks to run")
    parser.add_argument("--work", type=Path, help="run in this folder and keep it (default: a temporary one)")
    args = parser.parse_args(argv)
    failed = 0
    for page in args.pages:
        with tempfile.TemporaryDirectory() as tmp:
            work = args.work or Path(tmp) / "work"
            work.mkdir(parents=True, exist_ok=True)
            runs = run_blocks(page, work, page_env(Path(tmp) / "cache"))
            record = {
                "page": page.resolve().relative_to(ROOT).as_posix(),
                "command": f"python -m benchmarks.docs_pages {page}",
                "machine": {"processor": platform.processor() or platform.machine(), "cpus": os.cpu_count()},
                "blocks": [{k: r[k] for k in ("block", "returncode", "seconds")} for r in runs],
                "outputs": output_figures(work),
            }
        out = result_file(page)
        write_text_atomic(out, json.dumps(record, indent=2) + "\n")
        bad = [r for r in runs if r["returncode"] != 0]
        print(f"{page}: {len(runs)} block(s) run, {len(bad)} failed -> {out.relative_to(ROOT)}")
        if bad:
            failed += 1
            print(bad[0]["printed"][-3000:])
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
