"""Run a docs page's commands as written and write what they produced, for the page to quote.

    python -m benchmarks.docs_pages docs/howto/speed_or_accuracy.md     # -> benchmarks/results/pages/howto_speed_or_accuracy.json

A page's ```sh blocks run in order in one empty folder (``--work`` keeps it), with the
environment's ``twinfocus`` and ``python`` first on PATH, as after ``source .venv/bin/activate``.
A page that goes on from another's files says so in a line ``<!-- after: OTHER.md -->`` (a path
relative to the page); OTHER's blocks then run first in the same folder.
The result file holds each block's exit status and seconds, for every folder the commands
left a ``metrics.json`` in its numeric figures (top level, and the numbers and flags of each
section such as ``confidence``, ``timings_s`` or ``space_variant``), and for every MCAP log
they left (keyed by its path without ``.mcap``) its size and messages per topic. A page quotes
them with figure markers (tests/test_docs_figures.py checks each against this file); the
tests run the pages' blocks the same way and compare what the run made with the figures the
page quotes (tests/test_tutorial.py, tests/test_docs_pages.py). Times are the machine's the
file names, under whatever else it ran: a page quotes them as such, or as ratios.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from twinfocus.io.atomic import write_text_atomic
from twinfocus.jobs.machine import machine_info

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "pages"
_BLOCK = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
_AFTER = re.compile(r"<!-- after: (\S+\.md) -->")


def blocks(text: str) -> list[tuple[str, str]]:
    """(language, body) of every fenced block of a markdown ``text``, in order."""
    return [(m.group(1), m.group(2)) for m in _BLOCK.finditer(text)]


def prerequisites(page: Path) -> list[Path]:
    """The pages whose blocks must run before ``page``'s, in order (each one's own first)."""
    before: list[Path] = []
    for name in _AFTER.findall(page.read_text(encoding="utf-8")):
        other = (page.parent / name).resolve()
        before += [p for p in [*prerequisites(other), other] if p not in before]
    return before


def page_env(cache_dir: Path) -> dict[str, str]:
    """The environment a reader has after activating the venv, with this checkout's code first."""
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONPATH"] = f"{ROOT}{os.pathsep}{env.get('PYTHONPATH', '')}"
    env["TWINFOCUS_CACHE_DIR"] = str(cache_dir)
    return env


def run_page(page: Path, work: Path, env: dict[str, str]) -> list[dict]:
    """Run the blocks of ``page``'s prerequisites, then its own (``run_blocks``); the records are
    ``page``'s blocks only, or the failed prerequisite's."""
    for before in prerequisites(page):
        runs = run_blocks(before, work, env)
        if any(r["returncode"] != 0 for r in runs):
            return runs
    return run_blocks(page, work, env)


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
    """For every folder under ``work`` holding a metrics.json: its numeric figures and, for each
    section (a dict: ``confidence``, ``timings_s``, ``space_variant``, ...), its numbers and
    flags, keyed by the folder's relative path."""
    out = {}
    for metrics_file in sorted(work.rglob("metrics.json")):
        m = json.loads(metrics_file.read_text())
        figures: dict = _numbers(m)
        for key, section in m.items():
            if isinstance(section, dict):
                flags = {k: v for k, v in section.items() if isinstance(v, bool)}
                if numbers := {**_numbers(section), **flags}:
                    figures[key] = numbers
        out[metrics_file.parent.relative_to(work).as_posix()] = figures
    return out


def log_figures(work: Path) -> dict[str, dict]:
    """For every MCAP log under ``work``, keyed by its relative path without ``.mcap`` (figure
    markers split their keys at dots): ``bytes``, ``kilobytes`` (1000 bytes), ``messages`` and
    ``topics`` (topic -> messages), from the log's summary."""
    from mcap.reader import make_reader

    out = {}
    for log in sorted(work.rglob("*.mcap")):
        with open(log, "rb") as f:
            summary = make_reader(f).get_summary()
        if summary is None or summary.statistics is None:  # a log without its summary: unfinished
            continue
        topic = {c.id: c.topic for c in summary.channels.values()}
        size = log.stat().st_size
        out[log.relative_to(work).with_suffix("").as_posix()] = {
            "bytes": size,
            "kilobytes": round(size / 1000, 1),
            "messages": summary.statistics.message_count,
            "topics": {topic[k]: n for k, n in sorted(summary.statistics.channel_message_counts.items())},
        }
    return out


def made(work: Path) -> dict[str, dict]:
    """What the commands left in ``work``: ``outputs`` (metrics.json figures) and ``logs``."""
    return {"outputs": output_figures(work), "logs": log_figures(work)}


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
            load = os.getloadavg()
            runs = run_page(page, work, page_env(Path(tmp) / "cache"))
            record = {
                "page": page.resolve().relative_to(ROOT).as_posix(),
                "command": f"python -m benchmarks.docs_pages {page}",
                "machine": {
                    **machine_info(),
                    "load_average_1_5_15_before": [round(v, 2) for v in load],
                    "load_average_1_5_15_after": [round(v, 2) for v in os.getloadavg()],
                },
                "blocks": [{k: r[k] for k in ("block", "returncode", "seconds")} for r in runs],
                "seconds": round(sum(r["seconds"] for r in runs), 2),
                **made(work),
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
