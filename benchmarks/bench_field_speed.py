"""The hand's drift + tilt fit (``twinfocus.focus.space_variant.fit_smooth_drift``) against an earlier
version of it, side by side on the same draws and the same inputs: time, the target's SSIM against
the image on the true positions, the drift's error against the true positions.

    python -m benchmarks.bench_field_speed --draws 2            (--seeds 3,5 picks the draws)
    python -m benchmarks.bench_field_speed --seeds 3,5,8 --threads 1
    python -m benchmarks.bench_field_speed --focus-profile --seeds 3   (a whole ``twinfocus focus``)
    python -m benchmarks.bench_field_speed --focus-profile --seeds 3,5 --models auto,fast
    python -m benchmarks.bench_field_speed --focus-profile --as-user --seeds 3,5,8,11 --models auto,fast
    python -m benchmarks.bench_field_speed --focus-profile --warm --seeds 3,5,8,11 --models auto,fast
    python -m benchmarks.run --only field_speed

Each draw is the hand-drift scene of ``benchmarks/bench_handheld.py`` ("hand 0.8 mm + 0.15 deg":
780 positions, 100 x 100 regions), focused by ``focus_bases`` with the space-variant fit on. The
fit's inputs are taken as the pipeline hands them over; the pipeline's own call is the current
fit's row, then the earlier version (``--baseline``, a git revision: its
``twinfocus/focus/space_variant.py``, loaded as it was) runs on the same inputs at once after it, so
both see the same load. With a CUDA device the current fit also runs there (after a warm-up fit)
and writes its own rows. Writes ``field_speed.json`` (records per draw: each fit's wall seconds
and the CPU seconds of all its threads, which vary less with the machine's load, the load average
around it, the settings) and prints a table. ``--focus-profile`` instead simulates the draw's scan
and stage scan with ``twinfocus simulate`` and focuses it with ``twinfocus focus`` (the reference's
and the target's regions of the scene, 100 x 100 pixels, no pictures, no template cache), once
per ``--models`` value, and writes every stage's time from its ``metrics.json``, the ladder's
time and the target's SSIM to ``field_focus_profile.json``; with ``--as-user`` the scan as
captured (no truth images) and the template from the cache, what a user waits for
(``field_focus_profile_as_user.json``); with ``--warm`` that in one long-lived process, as
``twinfocus batch``'s workers run scans, each after an untimed run of its own command
(``field_focus_profile_warm.json``). ``--threads 1`` runs everything on one thread (torch and
numba): the CPU seconds are then the fit's own work, barely touched by other processes on a busy
machine, and bound the wall time on an idle machine with more cores from above.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_handheld import CONDITIONS, draw_bases
from benchmarks.common import focus_argv
from twinfocus.focus import space_variant as sv
from twinfocus.focus.autofocus import AutofocusConfig
from twinfocus.focus.estimators import estimator_settings
from twinfocus.focus.pipeline import Bases, Reference, Truth, half_array_bases
from twinfocus.focus.plan import FocusPlan
from twinfocus.imaging import metrics
from twinfocus.jobs.machine import machine_info

#: the scene of bench_handheld's "hand 0.8 mm + 0.15 deg"
SCENE = CONDITIONS["hand 0.8 mm + 0.15 deg"]
#: the fit before its CPU kernel (gradients written out, torch's element-wise passes); d325d94 is
#: the one before that (autograd over the per-pixel model)
BASELINE = "2ec245c"


def load_baseline(rev: str):
    """``twinfocus/focus/space_variant.py`` as it was at git revision ``rev``, as a module (None when
    git or the revision is not there)."""
    try:
        src = subprocess.run(
            ["git", "show", f"{rev}:twinfocus/focus/space_variant.py"],
            capture_output=True,
            text=True,
            check=True,
            cwd=Path(__file__).resolve().parents[1],
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    path = Path(tempfile.mkdtemp()) / f"space_variant_{rev}.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location(f"space_variant_{rev}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    module.rev = rev
    return module


def one_draw(seed: int, baseline) -> dict:
    scan, rg, tg, tpl, rb, tb, truth_t, truth_r = draw_bases(SCENE, seed)
    halves = half_array_bases(scan.data, scan.positions, scan.chirp, rg, tg)()
    centres = scan.positions.mean(axis=1)
    true_drift = (scan.positions_true - scan.positions).mean(axis=1)[:, :2]  # the correction's sense

    def scored(label: str, fit, load_before: float, cpu_s: float) -> dict:
        phase, dp, tilt, info = fit
        img = sv.drift_image(
            tb, phase, dp, rg.centre_m, centres, tg, scan.chirp.wavelength_m, half_basis=halves[1], tilt_rad=tilt
        )
        e = dp[:, :2] - true_drift
        return {
            "fit": label,
            "time_s": info["time_s"],
            "cpu_s": cpu_s,
            "load_before": load_before,
            "load_after": os.getloadavg()[0],
            "match_before": info["match_before"],
            "match_after": info["match_after"],
            "target_ssim": metrics.image_ssim(img, truth_t),
            "drift_error_rms_mm": float(np.sqrt(((e - e.mean(axis=0)) ** 2).mean()) * 1e3),
            "iterations": [info["iterations"], info["refine_iterations"]],
            "device": info.get("device", "cpu"),
        }

    rows: list[dict] = []
    current = sv.fit_smooth_drift

    def timed(fit, *args, **kwargs):
        """(the fit's output, load average before, CPU seconds of this process: all its threads)"""
        load, cpu = os.getloadavg()[0], time.process_time()
        out = fit(*args, **kwargs)
        return out, load, time.process_time() - cpu

    def fit_and_compare(*args, **kwargs):
        out, load, cpu = timed(current, *args, **kwargs)
        rows.append(scored("current", out, load, cpu))
        kwargs.pop("progress", None)
        kwargs.pop("device", None)
        if kwargs.get("pixels") is None:
            kwargs.pop("pixels", None)  # an earlier version has no such argument; the whole fit needs none
        settings = kwargs.pop("settings", None)
        if settings is not None:  # earlier versions took the settings as keywords
            kwargs.update({k: v for k, v in vars(settings).items() if k != "row_cell_share"})
        if baseline is not None:
            # copies: an earlier version may scale its inputs in place (2ec245c did)
            copies = [np.array(a) if isinstance(a, np.ndarray) else a for a in args]
            if kwargs.get("half_basis") is not None:
                kwargs = {**kwargs, "half_basis": np.array(kwargs["half_basis"])}
            rows.append(scored(f"baseline {baseline.rev}", *timed(baseline.fit_smooth_drift, *copies, **kwargs)))
        try:
            import torch
        except ImportError:
            return out
        if torch.cuda.is_available():
            current(*args, **kwargs, device="cuda")  # warm-up: the CUDA context and kernels
            rows.append(
                scored(f"current on {torch.cuda.get_device_name()}", *timed(current, *args, **kwargs, device="cuda"))
            )
        return out

    sv.fit_smooth_drift = fit_and_compare  # the pipeline imports it from the module when it runs
    try:
        out = FocusPlan.make(
            config=AutofocusConfig(**estimator_settings("correlation", True)),
            phase_ramp="auto",
            space_variant="on",
        ).focus_bases(
            Bases(rb, tb, scan.positions, scan.chirp, rg, tg, half_bases=lambda: halves),
            Reference(template=tpl),
            Truth(truth_t, truth_r, scan.positions_true),
        )
    finally:
        sv.fit_smooth_drift = current
    return {
        "seed": seed,
        "pipeline_target_ssim": out.metrics["target_ssim_corrected"],
        "ceiling_target_phase": out.metrics["target_ssim_oracle_phase"],
        "fits": rows,
    }


def focus_profile(
    seed: int, work: Path, models: tuple[str, ...] = ("auto",), as_user: bool = False, warm: bool = False
) -> list[dict]:
    """``twinfocus simulate`` then ``twinfocus focus`` on one draw of the scene, as a user runs them,
    once per ``--model`` in ``models``: the stages' seconds (``metrics.json`` ``timings_s``), the
    drift fit's own (``space_variant_fit_s``), the ladder's (``model_s``: every rung, the half-array
    bases included), the rungs kept, the whole command's wall and CPU seconds, the target's SSIM.

    as_user : what a user in the field waits for instead: the scan as captured (no true positions,
    so no truth images are formed) and the template scan's image read from the template cache
    (filled by one untimed run first, in a cache of this draw's own); the target's SSIM is then
    scored here, from ``target.npy`` against the image on the true positions.

    warm (as_user as well): each ``focus`` run in this process, as ``twinfocus batch``'s workers and
    the live solver run scans one after another (``twinfocus.cli.focus.run``), after one untimed
    run of the same command: the start, the imports (torch's too), numba's kernels and the cache
    are paid once per process, not per scan. CPU seconds are then this process's own."""
    from twinfocus.imaging.backprojection.numba_backend import backproject
    from twinfocus.imaging.metrics import image_ssim
    from twinfocus.radar.scan import Scan
    from twinfocus.simulation.scenario import Scenario, scenario_grids

    rg, tg = scenario_grids(Scenario(**SCENE, seed=seed), 100)
    scan, stage = work / f"hand{seed}.npz", work / f"hand{seed}_stage.npz"
    exe = [str(Path(sys.executable).parent / "twinfocus")]  # the console script beside this interpreter
    subprocess.run(
        exe
        + [
            "simulate",
            "--out",
            str(scan),
            "--template-out",
            str(stage),
            "--reference",
            SCENE["reference"],
            "--target",
            SCENE["target"],
            "--separation-deg",
            str(SCENE["separation_deg"]),
            "--snr-db",
            str(SCENE["snr_db"]),
            "--error-model",
            SCENE["error_model"],
            "--error-sigma-mm",
            str(SCENE["error_sigma_m"][0] * 1e3),
            "--seed",
            str(seed),
            "--quiet",
        ],
        check=True,
    )
    roi = [[g.x0, g.x1, g.y0, g.y1, g.z] for g in (rg, tg)]
    env, truth = None, None
    if as_user:
        captured = Scan.load(scan)
        truth = backproject(captured.data, captured.positions_true, captured.chirp, tg)
        captured.positions_true = None
        scan = work / f"hand{seed}_captured.npz"
        captured.save(scan)
        env = {**os.environ, "TWINFOCUS_CACHE_DIR": str(work / f"cache{seed}")}

    def command(model: str, out: Path) -> list[str]:
        return focus_argv(
            scan,
            stage,
            roi[0],
            roi[1],
            100,
            "--model",
            model,
            "--out",
            str(out),
            "--no-pictures",
            *([] if as_user else ["--no-cache"]),
            "--quiet",
        )

    if as_user:  # the cache's first fill is not what a user waits for on later scans
        subprocess.run(exe + command("none", work / f"focus{seed}_warm"), check=True, env=env)
    runs = []
    for model in models:
        out = work / f"focus{seed}_{model}"
        cmd = command(model, out)
        if warm:
            from twinfocus.cli import focus
            from twinfocus.cli.batch_jobs import focus_parser

            os.environ.update(env or {})
            focus.run(focus_parser().parse_args(cmd[1:]))  # untimed: what a long-lived process has paid
            before, t0, load = os.times(), time.perf_counter(), os.getloadavg()[0]
            focus.run(focus_parser().parse_args(cmd[1:]))
            wall, after = time.perf_counter() - t0, os.times()
            cpu_s = (after.user + after.system) - (before.user + before.system)
        else:
            before, t0, load = os.times(), time.perf_counter(), os.getloadavg()[0]
            subprocess.run(exe + cmd, check=True, env=env)
            wall, after = time.perf_counter() - t0, os.times()
            cpu_s = (after.children_user + after.children_system) - (before.children_user + before.children_system)
        m = json.loads((out / "metrics.json").read_text())
        if truth is not None:
            m["target_ssim_corrected"] = image_ssim(np.load(out / "target.npy"), truth)
        runs.append(
            {
                "seed": seed,
                "model": model,
                "command": "twinfocus " + " ".join(cmd[:1] + ["SCAN", "--template-scan", "STAGE"] + cmd[4:]),
                "wall_s": wall,
                "cpu_s": cpu_s,
                "load_before": load,
                "timings_s": m["timings_s"],
                "model_s": m["model"]["time_s"],
                "kept": m["model"]["kept"],
                "space_variant_fit_s": (m.get("space_variant") or {}).get("time_s"),
                "target_ssim_corrected": m.get("target_ssim_corrected"),
                "as_user": as_user,
                "warm": warm,
            }
        )
    return runs


def main(
    out_dir: str | os.PathLike = "benchmarks/results",
    draws: int = 2,
    seeds: list[int] | None = None,
    baseline_rev: str = BASELINE,
    threads: int | None = None,
) -> dict:
    if threads is not None:
        import numba
        import torch

        torch.set_num_threads(threads)
        numba.set_num_threads(threads)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    baseline = load_baseline(baseline_rev)
    if baseline is None:
        print(f"[field_speed] revision {baseline_rev} not found: current fit only", file=sys.stderr)
    records = []
    for seed in seeds or list(range(1, draws + 1)):
        print(f"[field_speed] draw {seed}", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        records.append(one_draw(seed, baseline))
        print(f"[field_speed] draw {seed} done in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    result = {
        "command": "python -m benchmarks.bench_field_speed " + " ".join(sys.argv[1:]),
        "threads": threads,
        "scene": {k: list(v) if isinstance(v, tuple) else v for k, v in SCENE.items()},
        "n_positions": 780,
        "region_px": [100, 100],
        "machine": machine_info(),
        "draws": records,
    }
    (out_dir / "field_speed.json").write_text(json.dumps(result, indent=2))
    print(
        "| draw | fit | time s | CPU s | load | target SSIM | drift error mm | match after |\n"
        "|---|---|---|---|---|---|---|---|"
    )
    for r in records:
        for f in r["fits"]:
            print(
                f"| {r['seed']} | {f['fit']} | {f['time_s']:.1f} | {f['cpu_s']:.1f} | {f['load_before']:.0f} "
                f"| {f['target_ssim']:.4f} "
                f"| {f['drift_error_rms_mm']:.3f} | {f['match_after']:.5f} |"
            )
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--draws", type=int, default=2)
    ap.add_argument("--seeds", default=None, help="comma-separated draw seeds (instead of 1..draws)")
    ap.add_argument("--baseline", default=BASELINE, help="git revision of the fit to compare with")
    ap.add_argument("--threads", type=int, default=None, help="torch's and numba's threads (default: theirs)")
    ap.add_argument("--focus-profile", action="store_true", help="time a whole twinfocus focus per draw instead")
    ap.add_argument("--models", default="auto", help="with --focus-profile: comma-separated --model values")
    ap.add_argument(
        "--as-user",
        action="store_true",
        help="with --focus-profile: the scan as captured (no truth images) and the template from the cache",
    )
    ap.add_argument(
        "--warm",
        action="store_true",
        help="with --focus-profile (implies --as-user): each focus in this process after an untimed "
        "one, as twinfocus batch's workers and the solver run scans one after another",
    )
    a = ap.parse_args()
    if a.focus_profile:
        Path(a.out).mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory() as work:
            runs = [
                r
                for seed in ([int(s) for s in a.seeds.split(",")] if a.seeds else range(1, a.draws + 1))
                for r in focus_profile(seed, Path(work), tuple(a.models.split(",")), a.as_user or a.warm, a.warm)
            ]
        name = (
            "field_focus_profile_warm.json"
            if a.warm
            else "field_focus_profile_as_user.json"
            if a.as_user
            else "field_focus_profile.json"
        )
        (Path(a.out) / name).write_text(
            json.dumps(
                {
                    "command": "python -m benchmarks.bench_field_speed " + " ".join(sys.argv[1:]),
                    "scene": {k: list(v) if isinstance(v, tuple) else v for k, v in SCENE.items()},
                    "machine": machine_info(),
                    "runs": runs,
                },
                indent=2,
            )
        )
        for r in runs:
            slow = {k: round(v, 1) for k, v in r["timings_s"].items() if isinstance(v, (int, float)) and v > 1.0}
            print(
                f"draw {r['seed']} --model {r['model']}: {r['wall_s']:.1f} s wall, {r['cpu_s']:.0f} s CPU, ladder "
                f"{r['model_s']:.1f} s ({'/'.join(r['kept'])}), target SSIM {r['target_ssim_corrected']:.4f}; "
                f"stages over 1 s: {slow}"
            )
        sys.exit(0)
    main(a.out, a.draws, [int(s) for s in a.seeds.split(",")] if a.seeds else None, a.baseline, a.threads)
