"""Core benchmark: back-projection throughput, paper-configuration autofocus, the speed/accuracy
trade of estimator, image size, iterations, basis precision, arithmetic precision and range-profile
oversampling, how cost grows with positions / channels / pixels / iterations (log-log slopes), and
``twinfocus focus`` end to end (wall time against its stages, template cache, memory peaks).
Writes ``core.json`` and ``core.md`` to the output folder (docs/performance.md reads them).

    python -m benchmarks.bench_core --out benchmarks/results [--quick] [--sections scaling,end_to_end]

``--sections`` re-runs only those sections and keeps the others' figures from the existing
``core.json`` (a note in core.md says which were re-run when).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import focus_argv
from twinfocus.focus.autofocus import AutofocusConfig, twin_autofocus
from twinfocus.focus.estimators import ESTIMATORS, PHASE_ESTIMATORS, estimator_settings
from twinfocus.imaging.backprojection.numba_backend import (
    backproject,
    backproject_points,
    matched_filter_bruteforce,
    subimage_basis,
)
from twinfocus.imaging.basis import form_image
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.metrics import image_ssim
from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario
from twinfocus.twins.digital_twin.condition import digital_twin_reference
from twinfocus.twins.templates import template_from_scan


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
    rows = []
    configs = [("numba", "float32", None), ("numba", "float64", None)]
    if not quick:
        configs.append(("torch", "float32", "cpu"))
    if torch.cuda.is_available():
        configs += [("torch", "float32", "cuda"), ("torch", "float64", "cuda")]
    for backend, precision, device in configs:
        kw = dict(backend=backend, precision=precision, device=device)
        # the torch CPU back-end is ~30x slower: a tenth of the positions gives its pairs/s
        sub = slice(0, None, 10) if (backend, device) == ("torch", "cpu") else slice(None)
        data, positions = scan.data[sub], scan.positions[sub]
        pairs = data.shape[0] * data.shape[1] * grid.height * grid.width
        t_img, _ = _best(partial(backproject, data, positions, scan.chirp, grid, **kw), 1 if quick else 2)
        t_bas, _ = _best(partial(subimage_basis, data, positions, scan.chirp, grid, **kw), 1 if quick else 2)
        rows.append(
            {
                "backend": backend,
                "precision": precision,
                "device": device or "cpu",
                "pairs": pairs,
                "image_s": t_img,
                "image_pairs_per_s": pairs / t_img,
                "basis_s": t_bas,
                "basis_pairs_per_s": pairs / t_bas,
            }
        )
        print(
            f"  BP {backend}/{precision}/{device or 'cpu'}: image {pairs / t_img:.3g} pairs/s, basis {pairs / t_bas:.3g} pairs/s"
        )
    return rows


def bench_oversample(scan) -> list[dict]:
    """Interpolation error (vs the brute-force matched filter) and time per oversampling factor."""
    sub = slice(0, 780, 26)  # 30 positions, all channels
    pts = ImageGrid(-0.1, 0.0, -0.05, 0.05, 0.6, 12, 12).points()
    ref = matched_filter_bruteforce(scan.data[sub], scan.positions[sub], scan.chirp, pts)
    grid = ImageGrid(-0.15, 0.0, -0.11, 0.12, 0.6, 100, 100)
    rows = []
    for ov in (2, 4, 8, 16, 32):
        img = backproject_points(
            scan.data[sub], scan.positions[sub], scan.chirp, pts, oversample=ov, precision="float64"
        )
        err = float(np.abs(img - ref).max() / np.abs(ref).max())
        t, _ = _best(partial(backproject, scan.data, scan.positions, scan.chirp, grid, oversample=ov), 1)
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
        "basis_s": t_basis,
        "autofocus_s": res.time_s,
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
    for size in (100,) if quick else (50, 100, 200):
        rg, tg = scenario_grids(sc, size)
        rb = subimage_basis(scan.data, scan.positions, scan.chirp, rg)
        tb = subimage_basis(scan.data, scan.positions, scan.chirp, tg)
        tpl = template_from_scan(template_scan, rg, keep_phase=True)
        truth = backproject(scan.data, scan.positions_true, scan.chirp, tg)
        # the outline estimator's outline: a digital twin from the reference's own points
        support = digital_twin_reference(
            sc.scene().object("reference").surface_points(1e-3), scan.positions, scan.chirp, rg
        ).support
        aperture = scan.positions.mean(axis=1)[:, :2]
        for name in ESTIMATORS:
            has_phase = name in PHASE_ESTIMATORS
            outline = name == "outline"
            cfg = AutofocusConfig(basis_dtype="float16", **estimator_settings(name, has_phase, has_support=outline))
            template = tpl if has_phase else np.abs(tpl)
            t, r = _best(
                partial(twin_autofocus, rb, template, cfg, support=support if outline else None, aperture_m=aperture), 1
            )
            ssim = image_ssim(form_image(tb, transfer_phase(r.phase_rad, scan.positions)), truth)
            rows.append(
                {
                    "size": size,
                    "estimator": name,
                    "template": "complex" if has_phase else "amplitude",
                    "seconds": t,
                    "ssim": ssim,
                }
            )
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
    for steps in (10, 30) if quick else (3, 10, 30, 100):
        cfg = AutofocusConfig(**estimator_settings("projection", False), projection_iterations=steps)
        t, r = _best(partial(twin_autofocus, rb, amplitude, cfg), 1 if quick else 2)
        ssim = image_ssim(form_image(tb, transfer_phase(r.phase_rad, scan.positions)), truth)
        rows.append({"projection_iterations": steps, "seconds": t, "ssim": ssim})
        print(f"  {steps} steps: {t:.2f} s, SSIM {ssim:.3f}")
    return rows


def _slope(xs, ys) -> float:
    """Least-squares slope of log(y) against log(x): the exponent of the growth."""
    return float(np.polyfit(np.log(xs), np.log(ys), 1)[0])


def bench_scaling(scan, template_scan, sc, quick) -> dict:
    """Seconds of the sub-image basis (numba, float32), the closed-form estimator (correlation) and
    the optimiser (paper, seconds per iteration over 25) against positions M, channels K, pixels H x W, and of the
    optimiser against its iterations; with each log-log slope (1 = linear)."""
    rg100, _ = scenario_grids(sc, 100)
    tpl_full = template_from_scan(template_scan, rg100, keep_phase=True)
    reps = 1

    def measure(data, positions, grid, tpl):
        t_basis, rb = _best(lambda: subimage_basis(data, positions, scan.chirp, grid), reps)
        t_cf, _ = _best(
            lambda: twin_autofocus(rb, tpl, AutofocusConfig(**estimator_settings("correlation", True))), reps
        )
        # 25 iterations: the cost per iteration is constant (slope against iterations below)
        t_opt, _ = _best(
            lambda: twin_autofocus(rb, np.abs(tpl), AutofocusConfig(iterations=25, basis_dtype="float16")), 1
        )
        return {"basis_s": t_basis, "correlation_s": t_cf, "optimiser_per_iteration_s": t_opt / 25}

    out: dict = {"positions": [], "channels": [], "pixels": [], "iterations": []}
    for m in (195, 390, 780):
        idx = np.linspace(0, scan.n_positions - 1, m).astype(int)
        out["positions"].append({"n": m, **measure(scan.data[idx], scan.positions[idx], rg100, tpl_full)})
        print(f"  M={m}: {out['positions'][-1]}")
    for k in (22, 43, 86):
        idx = np.linspace(0, scan.n_channels - 1, k).astype(int)
        out["channels"].append({"n": k, **measure(scan.data[:, idx], scan.positions[:, idx], rg100, tpl_full)})
        print(f"  K={k}: {out['channels'][-1]}")
    for size in (50, 100, 200):
        rg, _ = scenario_grids(sc, size)
        out["pixels"].append(
            {
                "n": size * size,
                **measure(scan.data, scan.positions, rg, template_from_scan(template_scan, rg, keep_phase=True)),
            }
        )
        print(f"  P={size}^2: {out['pixels'][-1]}")
    rb = subimage_basis(scan.data, scan.positions, scan.chirp, rg100)
    for it in (12, 25, 50, 100):
        cfg = AutofocusConfig(iterations=it, basis_dtype="float16")
        t, _ = _best(partial(twin_autofocus, rb, np.abs(tpl_full), cfg), 1)
        out["iterations"].append({"n": it, "optimiser_s": t})
        print(f"  iterations={it}: {t:.2f} s")
    slopes = {}
    for axis in ("positions", "channels", "pixels"):
        rows = out[axis]
        for key in ("basis_s", "correlation_s", "optimiser_per_iteration_s"):
            slopes[f"{key[:-2]} vs {axis}"] = _slope([r["n"] for r in rows], [r[key] for r in rows])
    slopes["optimiser vs iterations"] = _slope(
        [r["n"] for r in out["iterations"]], [r["optimiser_s"] for r in out["iterations"]]
    )
    out["slopes"] = slopes
    return out


def _bases(scan, grids, bp: dict) -> tuple:
    """The sub-image basis of ``scan`` on each grid, with the back-projection settings ``bp``."""
    return tuple(subimage_basis(scan.data, scan.positions, scan.chirp, g, **bp) for g in grids)


def bench_estimator_precision(scan, template_scan, sc, quick) -> list[dict]:
    """The trade users choose from: estimator x arithmetic precision x image size, seconds of the
    bases (both regions) + the estimate, and target SSIM (phase ramp removed as ``focus`` does)."""
    from twinfocus.evaluation.cases import transfer_phase

    rows = []
    for size in (50, 100):
        rg, tg = scenario_grids(sc, size)
        truth = backproject(scan.data, scan.positions_true, scan.chirp, tg)
        for precision in ("float32", "float64"):
            bp = {"precision": precision}
            t_basis, (rb, tb) = _best(partial(_bases, scan, (rg, tg), bp), 1)
            tpl = template_from_scan(template_scan, rg, keep_phase=True, **bp)
            for name in ("correlation", "projection", "registered", "paper"):
                has_phase = name in PHASE_ESTIMATORS
                cfg = AutofocusConfig(precision=precision, **estimator_settings(name, has_phase))
                template = tpl if has_phase else np.abs(tpl)
                t, r = _best(partial(twin_autofocus, rb, template, cfg), 1)
                ssim = image_ssim(form_image(tb, transfer_phase(r.phase_rad, scan.positions)), truth)
                rows.append(
                    {
                        "size": size,
                        "precision": precision,
                        "estimator": name,
                        "bases_s": t_basis,
                        "estimate_s": t,
                        "ssim": ssim,
                    }
                )
                print(f"  {size} {precision} {name}: bases {t_basis:.2f} s, estimate {t:.2f} s, SSIM {ssim:.3f}")
            del rb, tb
    return rows


# Peak memory of a child as its own /proc/self/status VmHWM: the rusage maxrss of a forked child
# counts the parent's memory at the fork (Linux keeps the pre-exec high-water mark).
_PEAK = "print('VmHWM', open('/proc/self/status').read().split('VmHWM:')[1].split()[0], file=sys.stderr)"


def _peak_mb(stderr: str) -> float:
    return float(stderr.rsplit("VmHWM", 1)[1].split()[0]) / 1024


def _run_focus(argv: list[str], env: dict) -> dict:
    """One ``twinfocus focus`` in a fresh process: wall seconds and its peak resident memory."""
    t = time.perf_counter()
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            f"import sys; from twinfocus.cli import main; rc = main(); {_PEAK}; sys.exit(rc)",
            *argv,
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise RuntimeError(f"focus failed: {proc.stderr}")
    return {"wall_s": wall, "peak_rss_mb": _peak_mb(proc.stderr)}


def bench_end_to_end(scan, template_scan, sc, quick) -> dict:
    """``twinfocus focus --template-scan`` on the default scene (780 x 86, 100 x 100) as a user
    runs it, in fresh processes: import time, the first run (template computed and cached), the
    second (template from the cache), wall time against the sum of the stages in metrics.json, and
    each process's peak memory; then the solver node's numerical work (bases built in batches of
    20 positions as measurements arrive, then :meth:`twinfocus.focus.plan.FocusPlan.focus_bases`) in a fresh
    process, for its peak memory."""
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        scan.save(d / "scan.npz")
        template_scan.save(d / "tpl.npz")
        env = {
            **os.environ,
            "TWINFOCUS_CACHE_DIR": str(d / "cache"),
            "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH", "")]),
        }
        imports = []
        for _ in range(3):
            t = time.perf_counter()
            subprocess.run(
                [sys.executable, "-c", "import twinfocus.cli.focus, twinfocus.focus.pipeline"], env=env, check=True
            )
            imports.append(time.perf_counter() - t)
        heavy = subprocess.run(
            [
                sys.executable,
                "-c",
                "import sys, twinfocus.cli.focus, twinfocus.focus.pipeline; "
                "print(','.join(m for m in ('torch', 'matplotlib', 'open3d', 'scipy') if m in sys.modules))",
            ],
            env=env,
            check=True,
            capture_output=True,
            text=True,
        ).stdout.strip()
        args = focus_argv(d / "scan.npz", d / "tpl.npz", sc.reference_roi(), sc.target_roi(), 100, "--quiet")
        runs = {}
        for name, extra in (
            ("first (template computed)", []),
            ("second (template cached)", []),
            ("second, all pictures", ["--pictures", "all"]),
        ):
            r = _run_focus([*args, "--out", str(d / "out"), *extra], env)
            m = json.loads((d / "out" / "metrics.json").read_text())
            r.update(
                stages_s=m["timings_s"],
                stages_sum_s=sum(m["timings_s"].values()),
                template_cache=m.get("template_cache"),
            )
            r["wall_over_stages"] = r["wall_s"] / r["stages_sum_s"]
            runs[name] = r
            print(
                f"  {name}: wall {r['wall_s']:.2f} s, stages {r['stages_sum_s']:.2f} s, peak {r['peak_rss_mb']:.0f} MB"
            )
        solver_code = (
            "import numpy as np; from twinfocus.radar.scan import Scan; from twinfocus.simulation.scenario import Scenario, scenario_grids; "
            "from twinfocus.imaging.backprojection.numba_backend import subimage_basis; from twinfocus.focus.plan import FocusPlan; "
            "from twinfocus.focus.pipeline import Bases, Reference; "
            "from twinfocus.focus.autofocus import AutofocusConfig; from twinfocus.focus.estimators import estimator_settings; "
            "from twinfocus.twins.templates import template_from_scan; "
            f"s = Scan.load({str(d / 'scan.npz')!r}); t = Scan.load({str(d / 'tpl.npz')!r}); rg, tg = scenario_grids(Scenario(), 100); "
            "tpl = template_from_scan(t, rg, keep_phase=True); del t; ref, tgt = [], []; "
            "[(ref.append(subimage_basis(s.data[i:i+20], s.positions[i:i+20], s.chirp, rg)), "
            "tgt.append(subimage_basis(s.data[i:i+20], s.positions[i:i+20], s.chirp, tg))) for i in range(0, s.n_positions, 20)]; "
            "FocusPlan.make(config=AutofocusConfig(**estimator_settings('correlation', True))).focus_bases("
            "Bases(np.concatenate(ref), np.concatenate(tgt), s.positions, s.chirp, rg, tg), Reference(tpl)); "
            f"import sys; {_PEAK}"
        )
        solver_mb = _peak_mb(
            subprocess.run(
                [sys.executable, "-c", solver_code], env=env, check=True, capture_output=True, text=True
            ).stderr
        )
        print(f"  solver-node work: peak {solver_mb:.0f} MB")
    return {
        "import_s": min(imports),
        "heavy_modules_imported": heavy.split(",") if heavy else [],
        "runs": runs,
        "solver_peak_rss_mb": solver_mb,
        "scan_mb": scan.data.nbytes / 2**20,
    }


SECTIONS = (
    "backprojection",
    "oversample",
    "autofocus_paper",
    "trade_estimator",
    "trade_projection_iterations",
    "trade_image_size",
    "trade_iterations",
    "trade_precision",
    "trade_estimator_precision",
    "scaling",
    "end_to_end",
)


def main(out_dir, quick: bool = False, sections: tuple[str, ...] | None = None) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    want = set(sections or SECTIONS)
    if want - set(SECTIONS):
        raise SystemExit(
            f"unknown section(s) {', '.join(sorted(want - set(SECTIONS)))}; choose from {', '.join(SECTIONS)}"
        )
    res: dict = {}
    if sections and (out_dir / "core.json").is_file():
        res = json.loads((out_dir / "core.json").read_text())
        res["notes"] = [n for n in res.get("notes", []) if not any(f"`{x}`" in n for x in want)]
        cpu = (
            next(
                (ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")),
                platform.machine(),
            )
            if Path("/proc/cpuinfo").exists()
            else platform.machine()
        )
        res["notes"].append(
            f"sections {', '.join(f'`{x}`' for x in sorted(want))} re-run alone on "
            f"{datetime.date.today().isoformat()} ({os.cpu_count()}-core {cpu}, shared with other work)"
        )
    sc = Scenario()
    t0 = time.perf_counter()
    scan, template_scan = simulate_scenario(sc)
    res.update(
        {"scenario": sc.to_dict(), "simulate_s": time.perf_counter() - t0, "torch_threads": torch.get_num_threads()}
    )
    ref_grid, _ = scenario_grids(sc, 100)

    if "backprojection" in want:
        print("back-projection throughput (100 x 100 from 67,080 elements)")
        res["backprojection"] = bench_backprojection(scan, ref_grid, quick)
    if "oversample" in want and not quick:
        print("range-profile oversampling")
        res["oversample"] = bench_oversample(scan)

    if "autofocus_paper" in want:
        print("autofocus, paper configuration (780 positions, 100 x 100, 300 iterations)")
        rb = subimage_basis(scan.data, scan.positions, scan.chirp, ref_grid)
        tpl = template_from_scan(template_scan, ref_grid)
        res["autofocus_paper"] = []
        for bd in ("float32", "float16"):
            t, r = _best(partial(twin_autofocus, rb, tpl, AutofocusConfig(basis_dtype=bd)), 1 if quick else 2)
            res["autofocus_paper"].append({"basis_dtype": bd, "seconds": t, "final_loss": float(r.loss_history[-1])})
            print(f"  basis {bd}: {t:.2f} s")
        del rb

    def section(key: str, what: str, bench: Callable) -> None:
        """The section ``key`` when asked for: says ``what`` and runs ``bench`` on the scene."""
        if key in want:
            print(what)
            res[key] = bench(scan, template_scan, sc, quick)

    section(
        "trade_estimator",
        "trade: estimator (template registration, closed-form phase; docs/beyond.md)",
        bench_estimators,
    )
    section(
        "trade_projection_iterations",
        "trade: projection steps (amplitude template, no optimiser)",
        bench_projection_iterations,
    )
    section("trade_estimator_precision", "trade: estimator x precision x size", bench_estimator_precision)

    if "trade_image_size" in want:
        print("trade: image size")
        res["trade_image_size"] = []
        for size in (50, 100) if quick else (50, 75, 100, 200):
            row = {"size": size, **_focus(scan, template_scan, sc, size, AutofocusConfig(basis_dtype="float16"))}
            res["trade_image_size"].append(row)
            print(f"  {size}: {row}")
    if "trade_iterations" in want and not quick:
        print("trade: iterations")
        res["trade_iterations"] = []
        for it in (25, 50, 100, 200, 300, 500):
            row = {
                "iterations": it,
                **_focus(scan, template_scan, sc, 100, AutofocusConfig(iterations=it, basis_dtype="float16")),
            }
            res["trade_iterations"].append(row)
            print(f"  {it}: {row}")
    if "trade_precision" in want and not quick:
        print("trade: precision")
        res["trade_precision"] = []
        for prec, bd in (("float32", "float16"), ("float32", "float32"), ("float64", "float32")):
            row = {
                "precision": prec,
                "basis_dtype": bd,
                **_focus(
                    scan, template_scan, sc, 100, AutofocusConfig(precision=prec, basis_dtype=bd), {"precision": prec}
                ),
            }
            res["trade_precision"].append(row)
            print(f"  {prec}/{bd}: {row}")
    section("scaling", "scaling: cost against positions, channels, pixels, iterations", bench_scaling)
    section("end_to_end", "end to end: twinfocus focus in fresh processes", bench_end_to_end)
    # the machine is shared: say how loaded it was while each section ran (1-minute average)
    res.setdefault("load_average", {}).update({x: round(os.getloadavg()[0], 1) for x in want if x in res})
    (out_dir / "core.json").write_text(json.dumps(res, indent=2, default=float))
    (out_dir / "core.md").write_text(_markdown(res))
    return res


#: the sections that are one table each, in the report's order: result key -> (title, column
#: headers, one record's row)
_TABLES: dict[str, tuple[str, tuple[str, ...], Callable[[dict], str]]] = {
    "oversample": (
        "Range-profile oversampling (interpolation error vs brute force)",
        ("oversample", "max error / peak", "image s"),
        lambda r: f"| {r['oversample']} | {r['max_error_rel_peak']:.2e} | {r['image_s']:.2f} |",
    ),
    "autofocus_paper": (
        "Autofocus, paper configuration (780 x 100 x 100, 300 iterations)",
        ("basis storage", "seconds"),
        lambda r: f"| {r['basis_dtype']} | {r['seconds']:.2f} |",
    ),
    "trade_estimator": (
        "Trade: estimator (float16 basis; seconds = registration + estimate)",
        ("size", "estimator", "template", "seconds", "target SSIM"),
        lambda r: (
            f"| {r['size']} | {r['estimator']} | {r.get('template', 'complex')} | {r['seconds']:.2f} | "
            f"{r['ssim']:.3f} |"
        ),
    ),
    "trade_projection_iterations": (
        "Trade: projection steps (`--estimator projection --projection-iterations N`, 100 x 100)",
        ("steps", "seconds", "target SSIM"),
        lambda r: f"| {r['projection_iterations']} | {r['seconds']:.2f} | {r['ssim']:.3f} |",
    ),
    "trade_estimator_precision": (
        "Trade: estimator x precision x size (seconds: both bases; the estimate; target SSIM)",
        ("size", "precision", "estimator", "bases s", "estimate s", "target SSIM"),
        lambda r: (
            f"| {r['size']} | {r['precision']} | {r['estimator']} | {r['bases_s']:.2f} | "
            f"{r['estimate_s']:.2f} | {r['ssim']:.3f} |"
        ),
    ),
}


def _table(title: str, columns: tuple[str, ...]) -> list[str]:
    """A markdown section's first lines: a blank line, ``## title``, a blank line, the table's
    header of ``columns`` and its rule (the rows follow)."""
    return ["", f"## {title}", "", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]


def _markdown(res: dict) -> str:
    lines = [
        "# Core benchmark",
        "",
        f"torch threads: {res['torch_threads']}; simulation of the scene: {res['simulate_s']:.1f} s",
        "",
    ]
    # a section re-run alone on another day or machine says so here
    lines += [f"Note: {n}" for n in res.get("notes", [])] + ([""] if res.get("notes") else [])
    if res.get("load_average"):
        lines += [
            "Load average (1 min, 2 cores) at the end of each section: "
            + ", ".join(f"{k} {v}" for k, v in res["load_average"].items()),
            "",
        ]
    if "backprojection" in res:  # a section run alone into a new folder has only itself
        lines += [
            "## Back-projection, 100 x 100 from 67,080 elements",
            "",
            "| backend | precision | device | image s | image pairs/s | basis s | basis pairs/s |",
            "|---|---|---|---|---|---|---|",
        ]
    for r in res.get("backprojection", []):
        lines.append(
            f"| {r['backend']} | {r['precision']} | {r['device']} | {r['image_s']:.2f} | "
            f"{r['image_pairs_per_s']:.3g} | {r['basis_s']:.2f} | {r['basis_pairs_per_s']:.3g} |"
        )
    for key, (title, columns, row) in _TABLES.items():
        if key in res:
            lines += _table(title, columns) + [row(r) for r in res[key]]
    if "scaling" in res:
        sc_ = res["scaling"]
        lines += _table(
            "Scaling (seconds; default scene subsampled)",
            ("axis", "n", "basis s", "correlation s", "optimiser s per iteration"),
        )
        for axis in ("positions", "channels", "pixels"):
            lines += [
                f"| {axis} | {r['n']} | {r['basis_s']:.2f} | {r['correlation_s']:.3f} | {r['optimiser_per_iteration_s']:.3f} |"
                for r in sc_[axis]
            ]
        lines += [f"| iterations | {r['n']} | | | {r['optimiser_s']:.2f} |" for r in sc_["iterations"]]
        lines += ["", "| log-log slope | exponent |", "|---|---|"]
        lines += [f"| {k} | {v:.2f} |" for k, v in sc_["slopes"].items()]
    if "end_to_end" in res:
        e = res["end_to_end"]
        lines += [
            "",
            "## `twinfocus focus` end to end (780 x 86, 100 x 100, --template-scan, fresh processes)",
            "",
            f"Imports of `twinfocus.cli.focus` + `twinfocus.focus.pipeline`: {e['import_s']:.2f} s (heavy modules loaded: "
            f"{', '.join(e['heavy_modules_imported']) or 'none'}).",
            "",
            "| run | wall s | sum of stages s | wall / stages | template | peak memory MB | stages s |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, r in e["runs"].items():
            stages = ", ".join(f"{k} {v:.2f}" for k, v in r["stages_s"].items())
            lines.append(
                f"| {name} | {r['wall_s']:.2f} | {r['stages_sum_s']:.2f} | {r['wall_over_stages']:.2f} | "
                f"{r['template_cache']} | {r['peak_rss_mb']:.0f} | {stages} |"
            )
        lines += [
            "",
            f"Solver node's numerical work (bases in batches of 20 positions, then `focus_bases`): peak "
            f"{e['solver_peak_rss_mb']:.0f} MB (scan data {e['scan_mb']:.0f} MB).",
        ]
    for key, label in (
        ("trade_image_size", "size"),
        ("trade_iterations", "iterations"),
        ("trade_precision", "precision"),
    ):
        if key not in res or not res[key]:
            continue
        lines += _table(
            f"Trade: {label}",
            (label, "basis s", "autofocus s", "target SSIM uncorrected", "target SSIM corrected"),
        )
        for r in res[key]:
            name = r[label] if label != "precision" else f"{r['precision']} / basis {r['basis_dtype']}"
            lines.append(
                f"| {name} | {r['basis_s']:.2f} | {r['autofocus_s']:.2f} | {r['ssim_uncorrected']:.3f} | {r['ssim_corrected']:.3f} |"
            )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--sections", default="", help=f"comma-separated, of: {', '.join(SECTIONS)} (default: all)")
    a = ap.parse_args()
    main(a.out, a.quick, tuple(x for x in a.sections.split(",") if x) or None)
