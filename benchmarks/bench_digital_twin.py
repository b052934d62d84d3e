"""Digital twin benchmark: every stage's time, the quality of each stage against the simulator's
truth, the cheap (PSF) template against the exact one, and the autofocus result on the paper's
protocol with the template made from the rendered stereo pair.

Writes ``digital_twin.json`` to the output folder:
- ``stages_s``: render, rectify, disparity, segmentation, point cloud, template (PSF), template
  (exact), each best of ``repeats`` after a warm-up (plus the cold first template call);
- ``quality``: segmentation IoU, point-cloud distance to the true plane (mm), PSF template vs
  exact (SSIM of the soft-thresholded images the autofocus compares, SSIM of the max-normalised
  amplitudes, correlation) and speed-up;
- ``autofocus``: per trial (motion-error draw), target SSIM uncorrected / digital twin from stereo /
  digital twin from the true points / physical twin (motion-stage template scan), and the means.

Run: ``python -m benchmarks.bench_digital_twin --out benchmarks/results [--trials 2]``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def _best(fn, repeats: int):
    out = fn()  # warm-up (numba cache load, open3d import)
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main(out_dir: str | os.PathLike = "benchmarks/results", repeats: int = 3, trials: int = 2) -> dict:
    import torch

    from twinfocus.focus.autofocus import AutofocusConfig, twin_autofocus
    from twinfocus.imaging.backprojection.numba_backend import backproject, subimage_basis
    from twinfocus.imaging.basis import form_image
    from twinfocus.imaging.metrics import display_image, image_ssim, ssim
    from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario
    from twinfocus.twins.digital_twin.pipeline import reference_from_stereo
    from twinfocus.twins.digital_twin.render import render_scene
    from twinfocus.twins.digital_twin.segment import box_from_scene_roi, mask_iou
    from twinfocus.twins.digital_twin.template import exact_template, psf_template
    from twinfocus.twins.templates import template_from_scan

    load_at_start = os.getloadavg()[0]
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    sc = Scenario()
    rg, tg = scenario_grids(sc)
    scene = sc.scene()
    ref = scene.object("reference")

    # --- stages -------------------------------------------------------------------------------
    stages: dict[str, float] = {}
    stages["render"], r = _best(lambda: render_scene(scene, seed=1), 1)
    seed = box_from_scene_roi(sc.reference_roi(), r.camera)
    _, twin = _best(lambda: reference_from_stereo(r.left, r.right, r.camera, seed), 1)
    runs = [reference_from_stereo(r.left, r.right, r.camera, seed) for _ in range(repeats)]
    for key in runs[0].timings_s:
        stages[key] = min(run.timings_s[key] for run in runs)
    points = twin.points_m

    scan, template_scan = simulate_scenario(sc)
    t0 = time.perf_counter()
    psf_template(points, scan.positions, scan.chirp, rg)
    stages["template_psf_cold"] = time.perf_counter() - t0
    stages["template_psf"], tpl = _best(lambda: psf_template(points, scan.positions, scan.chirp, rg), repeats)
    t0 = time.perf_counter()
    tpl_exact = exact_template(points, scan.positions, scan.chirp, rg)
    stages["template_exact"] = time.perf_counter() - t0
    stages["twin_total_warm"] = sum(
        stages[k] for k in ("rectify", "disparity", "segmentation", "point_cloud", "template_psf")
    )

    dist = (points - ref.centre_m) @ ref.rotation[:, 2]
    quality = {
        "segmentation_iou": mask_iou(twin.mask, r.mask("reference")),
        "points": int(points.shape[0]),
        "surface": twin.cloud.surface,
        "plane_error_rms_mm": float(np.sqrt(np.mean(dist**2)) * 1e3),
        "plane_error_max_mm": float(np.abs(dist).max() * 1e3),
        "template_psf_vs_exact_ssim_display": ssim(display_image(tpl), display_image(tpl_exact)),
        "template_psf_vs_exact_ssim_amplitude": ssim(tpl / tpl.max(), tpl_exact / tpl_exact.max()),
        "template_psf_vs_exact_correlation": float(np.corrcoef(tpl.ravel(), tpl_exact.ravel())[0, 1]),
        "template_speedup": stages["template_exact"] / stages["template_psf"],
    }
    truth_pts, _ = ref.scatterers(1.2e-3, 0, speckle=False)
    tpl_truth = psf_template(truth_pts, scan.positions, scan.chirp, rg)
    quality["template_stereo_vs_truth_points_ssim_display"] = ssim(display_image(tpl), display_image(tpl_truth))

    # --- autofocus on the paper protocol ------------------------------------------------------
    cfg = AutofocusConfig()
    rows = []
    for trial in range(int(trials)):
        sct = replace(sc, seed=trial)
        scan, template_scan = (scan, template_scan) if trial == 0 else simulate_scenario(sct)
        rb = subimage_basis(scan.data, scan.positions, scan.chirp, rg)
        tb = subimage_basis(scan.data, scan.positions, scan.chirp, tg)
        truth = backproject(scan.data, scan.positions_true, scan.chirp, tg)
        row = {"trial": trial, "uncorrected": image_ssim(tb.sum(axis=0), truth)}
        templates = {
            "digital_twin_stereo": psf_template(points, scan.positions, scan.chirp, rg),
            "digital_twin_true_points": psf_template(truth_pts, scan.positions, scan.chirp, rg),
            "physical_twin": template_from_scan(template_scan, rg),
        }
        for name, t in templates.items():
            t0 = time.perf_counter()
            res = twin_autofocus(rb, t, cfg)
            row[name] = image_ssim(form_image(tb, res.phase_rad), truth)
            row[f"{name}_autofocus_s"] = time.perf_counter() - t0
        rows.append(row)
        print(
            f"[digital_twin] trial {trial}: " + ", ".join(f"{k} {v:.3f}" for k, v in row.items() if k != "trial"),
            flush=True,
        )
    means = {k: float(np.mean([row[k] for row in rows])) for k in rows[0] if k != "trial"}

    doc = {
        "scenario": {k: v for k, v in sc.to_dict().items() if k != "extra"},
        "stages_s": stages,
        "quality": quality,
        "autofocus": {"trials": rows, "mean": means},
        "torch_threads": torch.get_num_threads(),
        "load_average_at_start": load_at_start,
        "load_average_at_end": os.getloadavg()[0],
    }
    (out_dir / "digital_twin.json").write_text(json.dumps(doc, indent=2, default=float) + "\n")
    return doc


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--trials", type=int, default=2)
    a = ap.parse_args()
    print(json.dumps(main(a.out, a.repeats, a.trials)["autofocus"]["mean"], indent=2))
