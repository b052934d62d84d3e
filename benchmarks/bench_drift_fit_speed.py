"""Where the hand-held scan's drift + tilt fit spends its time, against the reference's sub-image
basis in the same run: ``focus_scan`` (``--model auto``, the closed-form estimator with a template
with phase) on one held-out hand-drift draw of benchmarks/bench_handheld.py, under cProfile.

    python -m benchmarks.bench_drift_fit_speed --seed 3      (writes benchmarks/results/drift_fit_speed.json)

Records the pipeline's stage times (metrics ``timings_s``), the ratio of the fit's stage
(``space_variant``) to ``reference_basis``, the target SSIM, and the fit's cost evaluations
(:meth:`twinfocus.space_variant._DriftMatch.value_and_gradients` calls), with the time inside the
fused numba pass (``_rotate``) and the rest of each evaluation (torch's products and Python).
The machine's load average goes in too: read the ratios, not the seconds. Run it twice: the
first run in a fresh checkout also compiles numba's kernels (cache=True keeps them after).
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import time

from twinfocus.atomic import write_json_atomic

#: the held-out hand-drift scene of benchmarks/bench_handheld.py
HAND = dict(reference="H", target="S", separation_deg=16.3, snr_db=15, error_model="hand", error_sigma_m=(0.8e-3,) * 3)


def _function_times(stats: pstats.Stats, name: str) -> tuple[int, float, float]:
    """(calls, own seconds, cumulative seconds) of the profiled functions called ``name``."""
    calls = own = cum = 0.0
    for (_, _, fn), (_, nc, tt, ct, _) in stats.stats.items():  # type: ignore[attr-defined]
        if fn == name:
            calls, own, cum = calls + nc, own + tt, cum + ct
    return int(calls), own, cum


def main(argv: list[str] | None = None) -> dict:
    from twinfocus.autofocus import AutofocusConfig
    from twinfocus.estimators import estimator_settings
    from twinfocus.focus_plan import FocusPlan
    from twinfocus.pipeline import Reference
    from twinfocus.scenario import Scenario, scenario_grids, simulate_scenario
    from twinfocus.templates import template_from_scan

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--out", default="benchmarks/results/drift_fit_speed.json")
    a = ap.parse_args(argv)
    sc = Scenario(**HAND, seed=a.seed)
    scan, tpl_scan = simulate_scenario(sc)
    rg, tg = scenario_grids(sc, 100)
    tpl = template_from_scan(tpl_scan, rg, keep_phase=True)
    cfg = AutofocusConfig(**estimator_settings("correlation", True))
    load_before = os.getloadavg()
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    out = FocusPlan.make(config=cfg).focus_scan(scan, rg, tg, Reference(template=tpl))
    prof.disable()
    wall = time.perf_counter() - t0
    stats = pstats.Stats(prof)
    timings = out.metrics["timings_s"]
    evals, eval_own, eval_cum = _function_times(stats, "value_and_gradients")
    rotate_calls, rotate_s, _ = _function_times(stats, "_rotate")
    # torch's import runs inside the fit's stage (fit_smooth_drift imports it on its first call)
    torch_import_s = sum(
        ct
        for (f, _, fn), (_, _, _, ct, _) in stats.stats.items()  # type: ignore[attr-defined]
        if fn == "<module>" and f.endswith(os.path.join("torch", "__init__.py"))
    )
    rungs = {e["rung"]: e for e in out.metrics["model"]["rungs"] if e["rung"] in ("drift", "tilt")}
    tilt_info = rungs.get("tilt", {}).get("info", {})
    doc = {
        "command": f"python -m benchmarks.bench_drift_fit_speed --seed {a.seed}",
        "scene": {**HAND, "seed": a.seed, "positions": int(scan.positions.shape[0]), "region_px": list(rg.shape)},
        "cpu_count": os.cpu_count(),
        "load_average_1_5_15_before": [round(v, 2) for v in load_before],
        "load_average_1_5_15_after": [round(v, 2) for v in os.getloadavg()],
        "wall_s_profiled": round(wall, 2),
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "space_variant_over_reference_basis": round(
            timings.get("space_variant", float("nan")) / timings["reference_basis"], 2
        ),
        "target_ssim_corrected": out.metrics["target_ssim_corrected"],
        "tilt_kept": bool(rungs.get("tilt", {}).get("kept", False)),
        "main_fit": {k: tilt_info.get(k) for k in ("iterations", "refine_iterations", "time_s")},
        "cost_evaluations": evals,
        "cost_evaluation_s": round(eval_cum, 2),
        "numba_pass_s": round(rotate_s, 2),
        "numba_pass_calls": rotate_calls,
        "rest_of_evaluation_s": round(eval_own, 2),
        "torch_import_s": round(torch_import_s, 2),
        "note": "rest_of_evaluation_s: inside value_and_gradients itself, i.e. torch's complex products "
        "(contributions @ x, half_rotated @ x) on one thread and the small ops; numba_pass_s: _rotate",
    }
    write_json_atomic(a.out, doc)
    print({k: doc[k] for k in ("timings_s", "space_variant_over_reference_basis", "target_ssim_corrected",
                               "cost_evaluations", "numba_pass_s", "rest_of_evaluation_s")})  # fmt: skip
    return doc


if __name__ == "__main__":
    main()
