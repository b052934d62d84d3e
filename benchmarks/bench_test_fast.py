"""How long ``make test-fast`` (or, with ``--all``, ``make test``) takes: runs pytest with
``--durations=0`` once, as the Makefile does, and writes the wall time, the sum of the per-test
durations (setup + call + teardown, which add up whatever else the machine runs), the number of
tests collected and the slowest tests.

    python -m benchmarks.bench_test_fast                    (writes benchmarks/results/test_fast.json)
    python -m benchmarks.bench_test_fast --all              (writes benchmarks/results/test_suite.json)
    python -m benchmarks.bench_test_fast tests/test_x.py    (only those files: a quick check)

The machine's load average before and after goes in the file too: on a shared machine the wall
time is the upper bound and the sum of the durations the figure to read.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from pathlib import Path

from twinfocus.io.atomic import write_json_atomic

#: one line of pytest's ``--durations`` report: "12.34s call     tests/test_x.py::test_y[p]"
_DURATION = re.compile(r"^\s*(\d+(?:\.\d+)?)s\s+(setup|call|teardown)\s+(\S.*?)\s*$")
#: pytest's summary line, e.g. "412 passed, 3 skipped, 120 deselected in 101.2s"
_SUMMARY = re.compile(r"=+ (.*\d+ (?:passed|failed|error|errors).*?) in [\d.]+s")
_SELECTION = ["-m", "not slow"]
#: how ``make test`` runs the whole suite: two pytest-xdist workers, one file each at a time
_WHOLE = ["-n", "2", "--dist", "loadfile"]


def _pytest(args: list[str]) -> tuple[int, str]:
    """Run pytest in a subprocess (this interpreter, this environment): its exit code and stdout."""
    # as the Makefile runs it: with the bytecode and pytest's rewritten tests cached
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    proc = subprocess.run([sys.executable, "-m", "pytest", *args], capture_output=True, text=True, check=False, env=env)
    return proc.returncode, proc.stdout + proc.stderr


def collected(paths: list[str], selection: list[str]) -> int:
    """The number of tests ``selection`` (pytest arguments) selects (``--collect-only``)."""
    _, out = _pytest(["--collect-only", "-q", "-p", "no:cacheprovider", *selection, *paths])
    return sum(1 for line in out.splitlines() if "::" in line and not line.startswith(" "))


def parse_durations(out: str) -> list[dict]:
    """Per-test durations from pytest's ``--durations=0 -vv`` report, setup/call/teardown summed per
    test, slowest first: ``[{"test": nodeid, "s": seconds, "phases": {...}}, ...]``."""
    per: dict[str, dict[str, float]] = {}
    for line in out.splitlines():
        m = _DURATION.match(line)
        if m:
            per.setdefault(m.group(3), {})[m.group(2)] = float(m.group(1))
    rows = [{"test": k, "s": round(sum(v.values()), 3), "phases": v} for k, v in per.items()]
    return sorted(rows, key=lambda r: -r["s"])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("paths", nargs="*", help="test files (default: the whole test suite, as make test-fast)")
    ap.add_argument("--all", action="store_true", help="the whole suite as make test runs it, slow tests included")
    ap.add_argument(
        "--out", default=None, help="default: benchmarks/results/test_fast.json (test_suite.json with --all)"
    )
    ap.add_argument("--top", type=int, default=25, help="how many of the slowest tests to keep in the file")
    a = ap.parse_args(argv)
    selection, run_as = ([], _WHOLE) if a.all else (_SELECTION, [])
    target = "test" if a.all else "test-fast"
    a.out = a.out or f"benchmarks/results/{'test_suite' if a.all else 'test_fast'}.json"
    n = collected(a.paths, selection)
    load_before = os.getloadavg()
    t0 = time.perf_counter()
    # -vv: pytest otherwise hides durations under 5 ms, which would leave the sum short
    rc, out = _pytest(["-q", "-vv", "-p", "no:cacheprovider", "--durations=0", *selection, *run_as, *a.paths])
    wall = time.perf_counter() - t0
    load_after = os.getloadavg()
    rows = parse_durations(out)
    summary = _SUMMARY.findall(out)
    doc = {
        "command": " ".join(["python -m pytest", *(repr(x) if " " in x else x for x in selection + run_as)])
        + " --durations=0"
        + "".join(" " + p for p in a.paths),
        "what": f"make {target}: wall time, and the sum of per-test durations (setup+call+teardown)",
        "cpu_count": os.cpu_count(),
        "load_average_1_5_15_before": [round(v, 2) for v in load_before],
        "load_average_1_5_15_after": [round(v, 2) for v in load_after],
        "exit_code": rc,
        "summary": summary[-1] if summary else None,
        "failed": sorted({m.group(1) for m in re.finditer(r"^(?:FAILED|ERROR) (\S+)", out, re.M)}),
        "tests_collected": n,
        "tests_timed": len(rows),
        "wall_s": round(wall, 1),
        "sum_of_durations_s": round(sum(r["s"] for r in rows), 1),
        "slowest": rows[: a.top],
    }
    write_json_atomic(a.out, doc)
    print(
        f"[{target}] {n} tests, wall {wall:.1f} s (load {load_before[0]:.1f} -> {load_after[0]:.1f} on "
        f"{os.cpu_count()} cores), sum of durations {doc['sum_of_durations_s']} s; {doc['summary']}"
    )
    for r in rows[:15]:
        print(f"  {r['s']:7.2f} s  {r['test']}")
    print(f"[{target}] wrote {Path(a.out)}")
    return 0 if rc == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
