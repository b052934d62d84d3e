"""Run every benchmark (``benchmarks/bench_*.py``, each with ``main(out_dir)``) and collect the
figures in ``OUT/``: one JSON per area plus ``machine.json``.

    python -m benchmarks.run --out benchmarks/results [--only core,simulate]
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time
import traceback
from pathlib import Path

from twinfocus.jobs.machine import machine_info


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--only", default="", help="comma-separated areas (file names without bench_)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "machine.json").write_text(json.dumps(machine_info(), indent=2))
    here = Path(__file__).parent
    areas = sorted(p.stem[len("bench_") :] for p in here.glob("bench_*.py"))
    if args.only:
        wanted = set(args.only.split(","))
        areas = [a for a in areas if a in wanted]
    failed = []
    for area in areas:
        t0 = time.perf_counter()
        print(f"[bench] {area} ...", file=sys.stderr, flush=True)
        try:
            importlib.import_module(f"benchmarks.bench_{area}").main(out)
            print(f"[bench] {area} done in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        except Exception:  # one broken benchmark must not lose the others' figures
            traceback.print_exc()
            failed.append(area)
    if failed:
        print(f"[bench] failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    print(f"[bench] figures in {out}/", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
