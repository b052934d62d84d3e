"""Reference-free autofocus against the twins on the default scene: target SSIM and time of no
correction, sharpness, minimum entropy, phase-gradient autofocus and the physical twin, per draw,
each as ``twinfocus focus`` runs it (:meth:`twinfocus.focus.plan.FocusPlan.focus_bases`, default settings).

    python -m benchmarks.run --only reference_free   (or: python -m benchmarks.bench_reference_free --draws 3)

The default scene is the paper's: letters A and F at 0.6 m, 780 radar positions (6 columns x 130
rows), 0.5 mm x/y/z jitter, speckle, 10 dB per-sample SNR, 100 x 100 pixels. Writes
``reference_free.json`` (one record per draw, and the mean and sd per method) and prints a markdown
table; docs/reference_free.md quotes it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from twinfocus.focus.autofocus import AutofocusConfig
from twinfocus.focus.estimators import estimator_settings
from twinfocus.focus.pipeline import Bases, Reference, Truth
from twinfocus.focus.plan import FocusPlan
from twinfocus.imaging.backprojection.numba_backend import subimage_basis
from twinfocus.simulation.scenario import PAPER_IMAGE_SIZE, Scenario, scenario_grids, simulate_scenario
from twinfocus.twins.templates import template_from_scan

METHODS = ("none", "sharpness", "entropy", "pga", "physical twin")


def one_draw(seed: int, size: int) -> dict:
    sc = Scenario(seed=seed)
    scan, tpl_scan = simulate_scenario(sc)
    rg, tg = scenario_grids(sc, size)
    rb = subimage_basis(scan.data, scan.positions, scan.chirp, rg)
    tb = subimage_basis(scan.data, scan.positions, scan.chirp, tg)
    bases, truth = Bases.of_scan(scan, rb, tb, rg, tg), Truth.of_scan(scan, rg, tg)
    rec: dict = {"seed": seed}
    for method in METHODS:
        template, cfg = None, AutofocusConfig()
        if method == "physical twin":
            template = template_from_scan(tpl_scan, rg, keep_phase=True)
            cfg = AutofocusConfig(**estimator_settings("auto", True))
        t0 = time.perf_counter()
        out = FocusPlan.make(method="twin" if template is not None else method, config=cfg).focus_bases(
            bases, Reference(template=template), truth
        )
        rec[method] = {"target_ssim": out.metrics["target_ssim_corrected"], "time_s": time.perf_counter() - t0}
    rec["oracle phase"] = {"target_ssim": out.metrics["target_ssim_oracle_phase"], "time_s": 0.0}
    return rec


def main(out_dir: str | os.PathLike = "benchmarks/results", draws: int = 3, size: int = PAPER_IMAGE_SIZE) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    records = []
    for seed in range(1, draws + 1):
        print(f"[reference_free] draw {seed}/{draws}", file=sys.stderr, flush=True)
        records.append(one_draw(seed, size))
    summary = {}
    for method in (*METHODS, "oracle phase"):
        ssim = [r[method]["target_ssim"] for r in records]
        secs = [r[method]["time_s"] for r in records]
        summary[method] = {
            "target_ssim_mean": float(np.mean(ssim)),
            "target_ssim_sd": float(np.std(ssim)),
            "time_s_mean": float(np.mean(secs)),
        }
    doc = {
        "scene": "default (paper) scene: A and F at 0.6 m, 780 positions, 0.5 mm x/y/z jitter, speckle, 10 dB",
        "size_px": size,
        "draws": draws,
        "command": f"python -m benchmarks.bench_reference_free --draws {draws} --size {size}",
        "summary": summary,
        "records": records,
    }
    (out_dir / "reference_free.json").write_text(json.dumps(doc, indent=2))
    print("| method | target SSIM (mean ± sd) | time (s) |\n|---|---|---|")
    for method, s in summary.items():
        print(f"| {method} | {s['target_ssim_mean']:.3f} ± {s['target_ssim_sd']:.3f} | {s['time_s_mean']:.1f} |")
    return doc


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--draws", type=int, default=3)
    ap.add_argument("--size", type=int, default=PAPER_IMAGE_SIZE)
    a = ap.parse_args()
    main(a.out, a.draws, a.size)
