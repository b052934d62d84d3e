"""Channel calibration: the paper's scene focused (physical twin, autofocus on) through a perfect
array, through an imperfect one ('typical' magnitudes of twinfocus.radar.array_errors), and through the
imperfect one after a corner-reflector calibration, over draws of scene, tracking error and array.

    python -m benchmarks.bench_calibration [--draws 5] [--rows 50] [--size 64] [--out benchmarks/results]

Each draw: twinfocus.evaluation.array_calibration.calibration_case (2 raster columns x --rows rows,
86 channels, 256 samples; the paper's letters 'A' and 'F' at 0.6 m, 0.5 mm x/y/z tracking jitter,
10 dB; the corner capture 4 still frames at 20 dB). Target SSIM is scored against the perfect
array's image on the true positions. Writes ``calibration.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def run(draws: int = 5, rows: int = 50, size: int = 64) -> dict:
    from twinfocus.evaluation.array_calibration import calibration_case
    from twinfocus.radar.array_errors import TYPICAL

    records = []
    for seed in range(1, draws + 1):
        t0 = time.perf_counter()
        r = calibration_case(seed, TYPICAL, n_columns=2, n_rows=rows, size=size)
        r["seed"] = seed
        r["seconds"] = round(time.perf_counter() - t0, 1)
        records.append(r)
        print(
            f"[calibration] draw {seed}: " + ", ".join(f"{k} {v:.3f}" for k, v in r.items() if isinstance(v, float)),
            file=sys.stderr,
            flush=True,
        )
    keys = ("perfect", "uncalibrated", "calibrated")
    return {
        "command": f"python -m benchmarks.bench_calibration --draws {draws} --rows {rows} --size {size}",
        "scan": f"2 columns x {rows} rows x 86 channels x 256 samples; images {size} x {size}",
        "array_errors": TYPICAL.to_dict(),
        "mean_target_ssim": {k: round(float(np.mean([r[k] for r in records])), 4) for k in keys},
        "min_target_ssim": {k: round(float(np.min([r[k] for r in records])), 4) for k in keys},
        "mean_target_ssim_no_autofocus": {
            k: round(float(np.mean([r[f"{k}_no_autofocus"] for r in records])), 4) for k in keys
        },
        "draws": records,
        "note": "CPU seconds on a 2-core machine shared with other work",
    }


def main(out_dir=Path("benchmarks/results"), argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--draws", type=int, default=5)
    ap.add_argument("--rows", type=int, default=50)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--out", default=str(out_dir))
    args = ap.parse_args([] if argv is None else argv)
    result = run(args.draws, args.rows, args.size)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "calibration.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result["mean_target_ssim"]))
    return result


if __name__ == "__main__":
    main(argv=sys.argv[1:])
