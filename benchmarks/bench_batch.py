"""``twinfocus batch`` throughput: scans per minute against local Dask workers (1, 2), against the
shell loop of separate ``twinfocus focus`` processes it replaces, with the memory per worker and a
check that every item equals its separate run.

    PYTHONPATH=$PWD nice .venv/bin/python -m benchmarks.run --only batch
    PYTHONPATH=$PWD nice .venv/bin/python -m benchmarks.bench_batch [--items 20] [--workers 1,2]

Writes batch.json, batch.md and batch.png into the output folder.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REF = "-0.15 0.0 -0.11 0.12 0.6"
TGT = "0.02 0.13 -0.11 0.12 0.6"
#: A quarter-aperture scene (3 columns x 40 rows = 120 positions, 48 x 48 pixels): small enough that
#: three passes over 20 items fit a loaded 2-core machine; per-item overheads weigh more than at full size.
SCENE = ["--columns", "3", "--rows", "40"]
SIZE = "48"


def _twinfocus() -> list[str]:
    exe = Path(sys.executable).parent / "twinfocus"
    return (
        [str(exe)]
        if exe.exists()
        else [sys.executable, "-c", "import sys; from twinfocus.cli import main; sys.exit(main())"]
    )


def main(out_dir, items: int = 20, workers=(1, 2), scans: int = 4, loop: bool = True) -> dict:
    from twinfocus.cli.batch_jobs import run_batch

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="bench_batch."))
    tf = _twinfocus()
    for s in range(scans):
        subprocess.run(
            [
                *tf,
                "simulate",
                "--out",
                str(work / f"scan{s}.npz"),
                "--template-out",
                str(work / f"tpl{s}.npz"),
                *SCENE,
                "--seed",
                str(10 + s),
                "--quiet",
            ],
            check=True,
            stdout=subprocess.DEVNULL,
        )
    rows = [
        {
            "name": f"s{i:02d}",
            "scan": f"scan{i % scans}.npz",
            "template_scan": f"tpl{i % scans}.npz",
            "reference_roi": REF,
            "target_roi": TGT,
            "size": SIZE,
            "no_pictures": "true",
        }
        for i in range(items)
    ]
    manifest = work / "manifest.csv"
    with open(manifest, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    result = {
        "items": items,
        "distinct_scans": scans,
        "scene": " ".join(SCENE),
        "size": int(SIZE),
        "cpu_count": os.cpu_count(),
        "load_average_start": list(os.getloadavg()),
        "runs": [],
    }

    # The shell loop batch replaces: one `twinfocus focus` process per scan.
    t0 = time.perf_counter()
    for r in rows if loop else []:
        subprocess.run(
            [
                *tf,
                "focus",
                str(work / r["scan"]),
                "--reference-roi",
                *REF.split(),
                "--target-roi",
                *TGT.split(),
                "--size",
                SIZE,
                "--template-scan",
                str(work / r["template_scan"]),
                "--no-pictures",
                "--quiet",
                "--out",
                str(work / "loop" / r["name"]),
            ],
            check=True,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    sec = time.perf_counter() - t0
    if loop:
        result["runs"].append(
            {"mode": "separate focus processes", "workers": 1, "seconds": sec, "scans_per_min": 60 * items / sec}
        )
        print(f"[batch] separate focus processes: {sec:.1f} s, {60 * items / sec:.1f} scans/min", file=sys.stderr)

    for n in workers:
        out = work / f"w{n}"
        t0 = time.perf_counter()
        summary = run_batch(manifest, out, workers=n, resume=False)
        sec = time.perf_counter() - t0
        ok = [r for r in summary if r["status"] == "ok"]
        diff = (
            None
            if not loop
            else max(
                float(
                    np.abs(
                        np.load(out / "items" / r["name"] / "target.npy")
                        - np.load(work / "loop" / r["name"] / "target.npy")
                    ).max()
                    / np.abs(np.load(work / "loop" / r["name"] / "target.npy")).max()
                )
                for r in ok
            )
        )
        rss = [float(r["peak_rss_mb"]) for r in ok if r.get("peak_rss_mb")]
        run = {
            "mode": "twinfocus batch (local cluster)",
            "workers": n,
            "seconds": sec,
            "scans_per_min": 60 * items / sec,
            "ok": len(ok),
            "item_seconds_mean": float(np.mean([r["seconds"] for r in ok])),
            "peak_rss_mb_per_worker": max(rss) if rss else None,
            "max_rel_diff_vs_separate": diff,
        }
        result["runs"].append(run)
        print(
            f"[batch] {n} workers: {sec:.1f} s, {run['scans_per_min']:.1f} scans/min, peak RSS {run['peak_rss_mb_per_worker']:.0f} MB, "
            f"max rel. diff vs separate {diff}",
            file=sys.stderr,
        )
    result["load_average_end"] = list(os.getloadavg())
    shutil.rmtree(work, ignore_errors=True)
    (out_dir / "batch.json").write_text(json.dumps(result, indent=2))
    _write_md(out_dir / "batch.md", result)
    _write_png(out_dir / "batch.png", result)
    return result


def _write_md(path: Path, r: dict) -> None:
    lines = [
        f"# twinfocus batch throughput ({r['items']} items, {r['scene']}, {r['size']} x {r['size']} px, "
        f"{r['cpu_count']} cores, load average {r['load_average_start'][0]:.1f} at start)",
        "",
        "| mode | workers | wall (s) | scans / min | peak RSS per worker (MB) | max rel. diff vs separate |",
        "|---|---|---|---|---|---|",
    ]
    for run in r["runs"]:
        rss = run.get("peak_rss_mb_per_worker")
        diff = run.get("max_rel_diff_vs_separate")
        lines.append(
            f"| {run['mode']} | {run['workers']} | {run['seconds']:.1f} | {run['scans_per_min']:.1f} | "
            f"{'-' if rss is None else f'{rss:.0f}'} | {'-' if diff is None else f'{diff:.1e}'} |"
        )
    path.write_text("\n".join(lines) + "\n")


def _write_png(path: Path, r: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2))
    runs = [x for x in r["runs"] if x["mode"].startswith("twinfocus batch")]
    ax.plot([x["workers"] for x in runs], [x["scans_per_min"] for x in runs], "o-", label="twinfocus batch")
    loop = [x for x in r["runs"] if x["mode"].startswith("separate")]
    if loop:
        ax.axhline(loop[0]["scans_per_min"], color="0.5", ls="--", label="separate focus processes")
    ax.set_xlabel("local Dask workers")
    ax.set_ylabel("scans per minute")
    ax.set_xticks([x["workers"] for x in runs])
    ax.set_ylim(0, None)
    ax.set_title(f"{r['items']} scans, {r['cpu_count']} cores (loaded)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--items", type=int, default=20)
    ap.add_argument("--workers", default="1,2")
    ap.add_argument(
        "--no-loop", action="store_true", help="skip the separate-focus-processes baseline (and the comparison)"
    )
    a = ap.parse_args()
    main(a.out, items=a.items, workers=tuple(int(x) for x in a.workers.split(",")), loop=not a.no_loop)
