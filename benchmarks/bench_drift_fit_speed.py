"""The hand-held scan's drift + tilt fit against the reference's sub-image basis in the same run:
``focus_scan`` (``--model auto``, the closed-form estimator with a template with phase) on held-out
hand-drift draws of benchmarks/bench_handheld.py.

    python -m benchmarks.bench_drift_fit_speed --seeds 3 5 8    (writes benchmarks/results/drift_fit_speed.json)

Per draw: the pipeline's stage times (metrics ``timings_s``: ``space_variant`` is the drift + tilt
rung's fit and its held-out fits, ``reference_basis`` the reference's back-projection), their ratio,
the target SSIM against benchmarks/results/handheld.json's ``default`` for the same draw (the
same pipeline before this fit's speed-up), the fit's cost evaluations and whether torch was
imported; and the CPU seconds of the fits and of the reference's basis (this process's, all its
threads), the work, which the other jobs on a shared machine do not stretch as they stretch the
wall time. The machine's load average goes in too: read the ratios, not the seconds. Run it twice:
the first run in a fresh checkout also compiles numba's kernels (cache=True keeps them after).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from twinfocus.io.atomic import write_json_atomic

#: the held-out hand-drift scene of benchmarks/bench_handheld.py
HAND = dict(reference="H", target="S", separation_deg=16.3, snr_db=15, error_model="hand", error_sigma_m=(0.8e-3,) * 3)
HANDHELD = Path("benchmarks/results/handheld.json")


@contextlib.contextmanager
def _cpu_time_of(cpu: dict, reference_grid) -> Iterator[None]:
    """Adds to ``cpu`` the process CPU seconds of every drift fit (``fit``) and of the reference's
    sub-image basis (``basis``: the pipeline's back-projection onto ``reference_grid``)."""
    import twinfocus.focus.plan as pipeline
    import twinfocus.focus.space_variant as sv

    def timed(fn, key, only=None):
        def call(*args, **kwargs):
            if only is not None and not only(args):
                return fn(*args, **kwargs)
            c = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                cpu[key] += time.process_time() - c

        return call

    fit, basis = sv.fit_smooth_drift, pipeline.subimage_basis
    sv.fit_smooth_drift = timed(fit, "fit")  # the ladder imports it from the module when it runs
    pipeline.subimage_basis = timed(basis, "basis", lambda args: args[3] is reference_grid)
    try:
        yield
    finally:
        sv.fit_smooth_drift, pipeline.subimage_basis = fit, basis


def one_draw(seed: int) -> dict:
    """focus_scan on one draw: stage times, their ratio, target SSIM, the fit's record."""
    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.estimators import estimator_settings
    from twinfocus.focus.pipeline import Reference
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario
    from twinfocus.twins.templates import template_from_scan

    sc = Scenario(**HAND, seed=seed)
    scan, tpl_scan = simulate_scenario(sc)
    rg, tg = scenario_grids(sc, 100)
    tpl = template_from_scan(tpl_scan, rg, keep_phase=True)
    cfg = AutofocusConfig(**estimator_settings("correlation", True))
    load = os.getloadavg()
    cpu: dict[str, float] = {"fit": 0.0, "basis": 0.0}
    t0 = time.perf_counter()
    with _cpu_time_of(cpu, rg):
        out = FocusPlan.make(config=cfg).focus_scan(scan, rg, tg, Reference(template=tpl))
    wall = time.perf_counter() - t0
    timings = out.metrics["timings_s"]
    rungs = {e["rung"]: e for e in out.metrics["model"]["rungs"] if e["rung"] in ("drift", "tilt")}
    info = rungs.get("tilt", {}).get("info", {})
    before = None
    if HANDHELD.is_file():
        rows = json.loads(HANDHELD.read_text()).get("hand 0.8 mm + 0.15 deg", [])
        before = next((r["default"] for r in rows if r["seed"] == seed), None)
    ssim = out.metrics["target_ssim_corrected"]
    return {
        "seed": seed,
        "load_average_1_before": round(load[0], 2),
        "load_average_1_after": round(os.getloadavg()[0], 2),
        "wall_s": round(wall, 2),
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "fit_s": round(timings.get("space_variant", float("nan")), 3),
        "basis_s": round(timings["reference_basis"], 3),
        "fit_over_basis": round(timings.get("space_variant", float("nan")) / timings["reference_basis"], 2),
        # CPU seconds of this process (all its threads): the work, which other jobs' load does not stretch
        "fit_cpu_s": round(cpu["fit"], 3),
        "basis_cpu_s": round(cpu["basis"], 3),
        "fit_over_basis_cpu": round(cpu["fit"] / max(cpu["basis"], 1e-9), 2),
        "target_ssim": ssim,
        "target_ssim_before": before,
        "target_ssim_change": None if before is None else round(ssim - before, 4),
        "tilt_kept": bool(rungs.get("tilt", {}).get("kept", False)),
        "main_fit": {k: info.get(k) for k in ("iterations", "refine_iterations", "time_s")},
        "torch_imported": "torch" in sys.modules,
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[3])
    ap.add_argument("--out", default="benchmarks/results/drift_fit_speed.json")
    a = ap.parse_args(argv)
    draws = []
    for seed in a.seeds:
        print(f"[drift_fit_speed] draw {seed}", file=sys.stderr, flush=True)
        draws.append(one_draw(seed))
        print({k: draws[-1][k] for k in ("seed", "fit_s", "basis_s", "fit_over_basis", "fit_over_basis_cpu", "target_ssim",
                                           "target_ssim_change", "load_average_1_before")})  # fmt: skip
    doc = {
        "command": "python -m benchmarks.bench_drift_fit_speed --seeds " + " ".join(map(str, a.seeds)),
        "scene": {**HAND, "region_px": [100, 100]},
        "cpu_count": os.cpu_count(),
        "draws": draws,
        "summary": {
            "fit_over_basis_max": max(d["fit_over_basis"] for d in draws),
            "fit_over_basis_min": min(d["fit_over_basis"] for d in draws),
            "fit_over_basis_cpu_max": max(d["fit_over_basis_cpu"] for d in draws),
            "fit_over_basis_cpu_min": min(d["fit_over_basis_cpu"] for d in draws),
            "largest_ssim_loss": max((-(d["target_ssim_change"] or 0.0) for d in draws), default=0.0),
        },
        "note": "fit_s: the space_variant stage (the drift + tilt fit and its two held-out fits); basis_s: the "
        "reference's sub-image basis, the same run; target_ssim_before: handheld.json's default, same draw",
    }
    write_json_atomic(a.out, doc)
    return doc


if __name__ == "__main__":
    main()
