"""Radar simulator benchmark: speed on the paper scene, error against the brute-force sum.

Writes ``simulate.json`` to the output folder:
- ``paper_scene``: time of :func:`twinfocus.simulation.if_simulator.simulate_if` for the default two-letter
  scene on the 780 x 86 raster with 256 samples (best of ``repeats`` after a warm-up), the
  number of scatterers and (phase centre, scatterer) pairs, and the brute-force time
  extrapolated from the small case;
- ``small_case``: brute-force time and the fast simulator's relative error on 3 positions x 86
  channels x 300 points (the tests' case);
- ``sweep``: relative error (small case) and paper-scene time against ``range_step_m`` and
  ``order``, with the a-priori bound (beta_max h / 2)^Q / Q!;
- ``cluttered``: the paper scene with room clutter (a deeper range span).

Run: ``python -m benchmarks.bench_simulate --out benchmarks/results``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from functools import partial
from pathlib import Path

import numpy as np

from twinfocus.motion.trajectory import paper_raster, phase_centres
from twinfocus.radar.fmcw import C_M_PER_S, Chirp, mmwcas_virtual_array
from twinfocus.scene import paper_scene
from twinfocus.simulation.if_simulator import DEFAULT_ORDER, DEFAULT_RANGE_STEP_M, simulate_if, simulate_if_exact


def _best_time(fn, repeats: int) -> tuple[float, float]:
    """(best wall seconds, CPU seconds of that run summed over threads) after a warm-up.

    The CPU time is the steadier figure on a shared machine: on an otherwise idle machine with
    T threads the wall time is about CPU / T.
    """
    fn()  # warm-up (JIT compile or cache load)
    best = (math.inf, math.inf)
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        run = (time.perf_counter() - w0, time.process_time() - c0)
        best = min(best, run)
    return best


def _rel_err(a, b) -> float:
    return float(np.linalg.norm(a.astype(np.complex128) - b) / np.linalg.norm(b))


def main(out_dir: str | os.PathLike = "benchmarks/results", repeats: int = 3) -> dict:
    load_at_start = os.getloadavg()[0]
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    chirp = Chirp()
    positions = phase_centres(paper_raster(), mmwcas_virtual_array())
    beta_max = 4 * np.pi * chirp.slope_hz_per_s * chirp.t_centre_s / C_M_PER_S

    # Small case (the tests'): 3 positions x 86 channels x 300 points around 0.6 m.
    rng = np.random.default_rng(0)
    small_pos = positions[[0, 400, 779]]
    pts = np.column_stack(
        [rng.uniform(-0.1, 0.1, 300), rng.uniform(-0.07, 0.07, 300), 0.6 + rng.uniform(-0.02, 0.02, 300)]
    )
    amp = np.exp(2j * np.pi * rng.random(300)) * rng.uniform(0.2, 1.0, 300)
    t0 = time.perf_counter()
    exact = simulate_if_exact(pts, amp, small_pos, chirp)
    t_exact_small = time.perf_counter() - t0
    small_pairs = small_pos.shape[0] * small_pos.shape[1] * pts.shape[0]

    scene = paper_scene()
    t0 = time.perf_counter()
    scene_pts, scene_amp = scene.scatterers(rng=0)
    t_scatterers = time.perf_counter() - t0
    pairs = positions.shape[0] * positions.shape[1] * scene_pts.shape[0]
    t_default, cpu_default = _best_time(lambda: simulate_if(scene_pts, scene_amp, positions, chirp), repeats)
    err_default = _rel_err(simulate_if(pts, amp, small_pos, chirp), exact)

    sweep = []
    for step in (1e-3, 2e-3, 4e-3, 8e-3, 16e-3):
        for order in (0, 1, 2, 3):
            q = order + 1
            row = {
                "range_step_m": step,
                "order": order,
                "relative_error": _rel_err(
                    simulate_if(pts, amp, small_pos, chirp, range_step_m=step, order=order), exact
                ),
                "bound_per_scatterer": float((beta_max * step / 2) ** q / math.factorial(q)),
            }
            if (step, order) in ((1e-3, 1), (4e-3, 2), (8e-3, 3)):
                row["paper_scene_s"], row["paper_scene_cpu_s"] = _best_time(
                    partial(simulate_if, scene_pts, scene_amp, positions, chirp, range_step_m=step, order=order), 1
                )
            sweep.append(row)

    cl_pts, cl_amp = paper_scene(clutter=True).scatterers(rng=0)
    t_clutter, cpu_clutter = _best_time(lambda: simulate_if(cl_pts, cl_amp, positions, chirp), 1)

    result = {
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "load_average_1min_at_start": load_at_start,
            "numba_threads": int(os.environ.get("NUMBA_NUM_THREADS", os.cpu_count() or 1)),
        },
        "defaults": {"range_step_m": DEFAULT_RANGE_STEP_M, "order": DEFAULT_ORDER},
        "paper_scene": {
            "n_scatterers": int(scene_pts.shape[0]),
            "n_elements": int(positions.shape[0] * positions.shape[1]),
            "n_samples": chirp.n_samples,
            "pairs": int(pairs),
            "scatterers_s": t_scatterers,
            "simulate_if_s": t_default,
            "simulate_if_cpu_s": cpu_default,
            "cpu_ns_per_pair": 1e9 * cpu_default / pairs,
            "exact_sum_s_extrapolated": t_exact_small * pairs / small_pairs,
        },
        "small_case": {
            "shape": list(exact.shape),
            "n_points": int(pts.shape[0]),
            "exact_s": t_exact_small,
            "relative_error_default": err_default,
        },
        "sweep": sweep,
        "cluttered": {
            "n_scatterers": int(cl_pts.shape[0]),
            "simulate_if_s": t_clutter,
            "simulate_if_cpu_s": cpu_clutter,
        },
    }
    (out_dir / "simulate.json").write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/results", help="output folder (default benchmarks/results)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(json.dumps(main(args.out, args.repeats), indent=2))
