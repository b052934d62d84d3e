"""Core benchmark: back-projection throughput, paper-configuration autofocus, and the
speed/accuracy trade of image size, iterations, basis precision, arithmetic precision and
range-profile oversampling. Writes ``core.json`` and ``core.md`` to the output folder.

    python -m benchmarks.bench_core --out benchmarks/results [--quick]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from twinfocus.autofocus import AutofocusConfig, form_image, twin_autofocus
from twinfocus.backprojection import backproject, backproject_points, matched_filter_bruteforce, subimage_basis
from twinfocus.estimators import ESTIMATORS, PHASE_ESTIMATORS, estimator_settings
from twinfocus.grid import ImageGrid
from twinfocus.metrics import image_ssim
from twinfocus.scenario import Scenario, scenario_grids, simulate_scenario
from twinfocus.templates import template_from_scan


def _best(fn, repeats=2):
    fn()
    best = np.inf
    out = None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def bench_backprojection(scan, grid, quick) -> list[dict]:
    pairs = scan.n_positions * scan.n_channels * grid.height * grid.width
    rows = []
    configs = [("numba", "float32", None), ("numba", "float64", None)]
    if not quick:
        configs.append(("torch", "float32", "cpu"))
    if torch.cuda.is_available():
        configs += [("torch", "float32", "cuda"), ("torch", "float64", "cuda")]
    for backend, precision, device in configs:
        kw = dict(backend=backend, precision=precision, device=device)
        t_img, _ = _best(lambda: backproject(scan.data, scan.positions, scan.chirp, grid, **kw), 1 if quick else 2)
        t_bas, _ = _best(lambda: subimage_basis(scan.data, scan.positions, scan.chirp, grid, **kw), 1 if quick else 2)
        rows.append({
            "backend": backend, "precision": precision, "device": device or "cpu", "pairs": pairs,
            "image_s": t_img, "image_pairs_per_s": pairs / t_img,
            "basis_s": t_bas, "basis_pairs_per_s": pairs / t_bas,
        })
        print(f"  BP {backend}/{precision}/{device or 'cpu'}: image {pairs / t_img:.3g} pairs/s, basis {pairs / t_bas:.3g} pairs/s")
    return rows


def bench_oversample(scan) -> list[dict]:
    """Interpolation error (vs the brute-force matched filter) and time per oversampling factor."""
    sub = slice(0, 780, 26)  # 30 positions, all channels
    pts = ImageGrid(-0.1, 0.0, -0.05, 0.05, 0.6, 12, 12).points()
    ref = matched_filter_bruteforce(scan.data[sub], scan.positions[sub], scan.chirp, pts)
    grid = ImageGrid(-0.15, 0.0, -0.11, 0.12, 0.6, 100, 100)
    rows = []
    for ov in (2, 4, 8, 16, 32):
        img = backproject_points(scan.data[sub], scan.positions[sub], scan.chirp, pts, oversample=ov, precision="float64")
        err = float(np.abs(img - ref).max() / np.abs(ref).max())
        t, _ = _best(lambda: backproject(scan.data, scan.positions, scan.chirp, grid, oversample=ov), 1)
        rows.append({"oversample": ov, "max_error_rel_peak": err, "image_s": t})
        print(f"  oversample {ov}: error {err:.2e}, {t:.2f} s")
    return rows


def _focus(scan, template_scan, sc, size, cfg, bp=None):
    bp = bp or {}
    rg, tg = scenario_grids(sc, size)
    t0 = time.perf_counter()
    rb = subimage_basis(scan.data, scan.positions, scan.chirp, rg, **bp)
    tb = subimage_basis(scan.data, scan.positions, scan.chirp, tg, **bp)
    t_basis = time.perf_counter() - t0
    tpl = template_from_scan(template_scan, rg, **bp)
    res = twin_autofocus(rb, tpl, cfg)
    truth = backproject(scan.data, scan.positions_true, scan.chirp, tg)
    return {
        "basis_s": t_basis, "autofocus_s": res.time_s,
        "ssim_uncorrected": image_ssim(tb.sum(0), truth),
        "ssim_corrected": image_ssim(form_image(tb, res.phase_rad), truth),
    }


def bench_estimators(scan, template_scan, sc, quick) -> list[dict]:
    """Each ``twinfocus focus --estimator`` on the default scene, with the template a physical twin
    gives (complex) for the estimators that need its phase and the amplitude a digital twin
    gives for the others: estimator seconds (registration + estimate, one run) and target SSIM
    with the phase ramp removed as ``focus`` does."""
    from twinfocus.evaluation.cases import transfer_phase

    rows = []
    for size in ((100,) if quick else (50, 100, 200)):
        rg, tg = scenario_grids(sc, size)
        rb = subimage_basis(scan.data, scan.positions, scan.chirp, rg)
        tb = subimage_basis(scan.data, scan.positions, scan.chirp, tg)
        tpl = template_from_scan(template_scan, rg, keep_phase=True)
        truth = backproject(scan.data, scan.positions_true, scan.chirp, tg)
        for name in ESTIMATORS:
            has_phase = name in PHASE_ESTIMATORS
            cfg = AutofocusConfig(basis_dtype="float16", **estimator_settings(name, has_phase))
            t, r = _best(lambda: twin_autofocus(rb, tpl if has_phase else np.abs(tpl), cfg), 1)
            ssim = image_ssim(form_image(tb, transfer_phase(r.phase_rad, scan.positions)), truth)
            rows.append({"size": size, "estimator": name, "template": "complex" if has_phase else "amplitude",
                         "seconds": t, "ssim": ssim})
            print(f"  {size} {name}: {t:.2f} s, SSIM {ssim:.3f}")
        del rb, tb
    return rows


def bench_projection_iterations(scan, template_scan, sc, quick) -> list[dict]:
    """``--estimator projection`` (amplitude template, no optimiser) against its step count on
    the default scene, 100 x 100: seconds and target SSIM (phase ramp removed as ``focus`` does)."""
    from twinfocus.evaluation.cases import transfer_phase

    rg, tg = scenario_grids(sc, 100)
    rb = subimage_basis(scan.data, scan.positions, scan.chirp, rg)
    tb = subimage_basis(scan.data, scan.positions, scan.chirp, tg)
    amplitude = template_from_scan(template_scan, rg)
    truth = backproject(scan.data, scan.positions_true, scan.chirp, tg)
    rows = []
    for steps in ((10, 30) if quick else (3, 10, 30, 100)):
        cfg = AutofocusConfig(**estimator_settings("projection", False), projection_iterations=steps)
        t, r = _best(lambda: twin_autofocus(rb, amplitude, cfg), 1 if quick else 2)
        ssim = image_ssim(form_image(tb, transfer_phase(r.phase_rad, scan.positions)), truth)
        rows.append({"projection_iterations": steps, "seconds": t, "ssim": ssim})
        print(f"  {steps} steps: {t:.2f} s, SSIM {ssim:.3f}")
    return rows


def main(out_dir, quick: bool = False) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    sc = Scenario()
    t0 = time.perf_counter()
    scan, template_scan = simulate_scenario(sc)
    res: dict = {"scenario": sc.to_dict(), "simulate_s": time.perf_counter() - t0, "torch_threads": torch.get_num_threads()}
    ref_grid, _ = scenario_grids(sc, 100)

    print("back-projection throughput (100 x 100 from 67,080 elements)")
    res["backprojection"] = bench_backprojection(scan, ref_grid, quick)
    if not quick:
        print("range-profile oversampling")
        res["oversample"] = bench_oversample(scan)

    print("autofocus, paper configuration (780 positions, 100 x 100, 300 iterations)")
    rb = subimage_basis(scan.data, scan.positions, scan.chirp, ref_grid)
    tpl = template_from_scan(template_scan, ref_grid)
    res["autofocus_paper"] = []
    for bd in ("float32", "float16"):
        t, r = _best(lambda: twin_autofocus(rb, tpl, AutofocusConfig(basis_dtype=bd)), 1 if quick else 2)
        res["autofocus_paper"].append({"basis_dtype": bd, "seconds": t, "final_loss": float(r.loss_history[-1])})
        print(f"  basis {bd}: {t:.2f} s")

    print("trade: estimator (template registration, closed-form phase; docs/beyond.md)")
    res["trade_estimator"] = bench_estimators(scan, template_scan, sc, quick)
    print("trade: projection steps (amplitude template, no optimiser)")
    res["trade_projection_iterations"] = bench_projection_iterations(scan, template_scan, sc, quick)

    print("trade: image size")
    res["trade_image_size"] = []
    for size in ((50, 100) if quick else (50, 75, 100, 200)):
        row = {"size": size, **_focus(scan, template_scan, sc, size, AutofocusConfig(basis_dtype="float16"))}
        res["trade_image_size"].append(row)
        print(f"  {size}: {row}")
    if not quick:
        print("trade: iterations")
        res["trade_iterations"] = []
        for it in (25, 50, 100, 200, 300, 500):
            row = {"iterations": it, **_focus(scan, template_scan, sc, 100, AutofocusConfig(iterations=it, basis_dtype="float16"))}
            res["trade_iterations"].append(row)
            print(f"  {it}: {row}")
        print("trade: precision")
        res["trade_precision"] = []
        for prec, bd in (("float32", "float16"), ("float32", "float32"), ("float64", "float32")):
            row = {"precision": prec, "basis_dtype": bd,
                   **_focus(scan, template_scan, sc, 100, AutofocusConfig(precision=prec, basis_dtype=bd), {"precision": prec})}
            res["trade_precision"].append(row)
            print(f"  {prec}/{bd}: {row}")
    (out_dir / "core.json").write_text(json.dumps(res, indent=2, default=float))
    (out_dir / "core.md").write_text(_markdown(res))
    return res


def _markdown(res: dict) -> str:
    lines = ["# Core benchmark", "", f"torch threads: {res['torch_threads']}; simulation of the scene: {res['simulate_s']:.1f} s", ""]
    # a section re-run alone on another day or machine says so here
    lines += [f"Note: {n}" for n in res.get("notes", [])] + ([""] if res.get("notes") else [])
    lines += ["## Back-projection, 100 x 100 from 67,080 elements", "", "| backend | precision | device | image s | image pairs/s | basis s | basis pairs/s |", "|---|---|---|---|---|---|---|"]
    for r in res["backprojection"]:
        lines.append(f"| {r['backend']} | {r['precision']} | {r['device']} | {r['image_s']:.2f} | {r['image_pairs_per_s']:.3g} | {r['basis_s']:.2f} | {r['basis_pairs_per_s']:.3g} |")
    if "oversample" in res:
        lines += ["", "## Range-profile oversampling (interpolation error vs brute force)", "", "| oversample | max error / peak | image s |", "|---|---|---|"]
        lines += [f"| {r['oversample']} | {r['max_error_rel_peak']:.2e} | {r['image_s']:.2f} |" for r in res["oversample"]]
    lines += ["", "## Autofocus, paper configuration (780 x 100 x 100, 300 iterations)", "", "| basis storage | seconds |", "|---|---|"]
    lines += [f"| {r['basis_dtype']} | {r['seconds']:.2f} |" for r in res["autofocus_paper"]]
    if "trade_estimator" in res:
        lines += ["", "## Trade: estimator (float16 basis; seconds = registration + estimate)", "",
                  "| size | estimator | template | seconds | target SSIM |", "|---|---|---|---|---|"]
        lines += [f"| {r['size']} | {r['estimator']} | {r.get('template', 'complex')} | {r['seconds']:.2f} | {r['ssim']:.3f} |"
                  for r in res["trade_estimator"]]
    if "trade_projection_iterations" in res:
        lines += ["", "## Trade: projection steps (`--estimator projection --projection-iterations N`, 100 x 100)", "",
                  "| steps | seconds | target SSIM |", "|---|---|---|"]
        lines += [f"| {r['projection_iterations']} | {r['seconds']:.2f} | {r['ssim']:.3f} |" for r in res["trade_projection_iterations"]]
    for key, label in (("trade_image_size", "size"), ("trade_iterations", "iterations"), ("trade_precision", "precision")):
        if key not in res:
            continue
        lines += ["", f"## Trade: {label}", "", f"| {label} | basis s | autofocus s | target SSIM uncorrected | target SSIM corrected |", "|---|---|---|---|---|"]
        for r in res[key]:
            name = r[label] if label != "precision" else f"{r['precision']} / basis {r['basis_dtype']}"
            lines.append(f"| {name} | {r['basis_s']:.2f} | {r['autofocus_s']:.2f} | {r['ssim_uncorrected']:.3f} | {r['ssim_corrected']:.3f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    main(a.out, a.quick)
