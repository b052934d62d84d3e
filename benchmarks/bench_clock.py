"""The radar-camera clock found from the data, on zig-zag hand sweeps drawn from a family of scenes.

Each draw takes at random (from its seed): the reference's letter and the target's, their
separation (10-16.3 degrees), the hand's speed (0.15-0.25 m/s) and the tracking error (0.3-0.7 mm
per axis). Per clock offset (0, 15, 50, 100 ms; the camera's stamps run that much behind the
radar's): the camera's poses as it would report them at ``t + offset`` -- its track re-sampled
along each leg and, in the turn between columns where the scan keeps no frame, a smooth turn
(cubic from the leg's end to the next leg's start, their velocities matched) -- the offset found
by the range history (what ``convert --align scan`` does) and by the reference's focus
(``focus --clock-search``: the physical twin's image matched, the digital twin's image matched, and
the image's sharpness alone, what ``focus --digital-twin --clock-search`` uses), their residuals,
the searches' time, and the target SSIM of the physical twin (the reference's motion-stage scan)
and of the digital twin (the reference's points as a template) with the clock searched, without,
and with the clocks agreeing.

Bench draws (seeds 1001 on, letters ``BENCH_LETTERS``) are what the search was built on; held-out
draws (seeds 2001 on, letters ``HELDOUT_LETTERS``, none shared) only check it.

    python -m benchmarks.bench_clock [--draws 2] [--heldout] [--offsets-ms 0,15,50,100] [--out benchmarks/results]
    python -m benchmarks.bench_clock --heldout --draws 1 --start 1 --out tmp1      (one draw apart ...)
    python -m benchmarks.bench_clock --heldout --merge tmp0/clock_heldout.json tmp1/clock_heldout.json  (... joined)

Writes ``clock.json`` (``clock_heldout.json``); docs/sensors.md quotes them. Small on purpose (one
core, a few minutes a draw): the sizes are in the file.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from twinfocus.focus.autofocus import AutofocusConfig
from twinfocus.focus.estimators import estimator_settings
from twinfocus.focus.pipeline import Reference
from twinfocus.focus.plan import FocusPlan
from twinfocus.imaging.grid import ImageGrid
from twinfocus.sensors.clock_offset import (
    leg_starts,
    position_times_s,
    range_history_offset,
    resample_track,
    search_scan_clock,
)
from twinfocus.simulation.scenario import Scenario, scenario_grids, scenario_scatterers, simulate_scenario
from twinfocus.twins.digital_twin.template import psf_template
from twinfocus.twins.templates import template_from_scan

OFFSETS_S = (0.0, 0.015, 0.05, 0.1)
SEARCH_SIZE = 32
LEG_M = 0.258  # twinfocus.motion.trajectory.handheld_zigzag's column height
BENCH_LETTERS, HELDOUT_LETTERS = "ABOFHTE", "DPRQLKX"
BENCH_SEED, HELDOUT_SEED = 1001, 2001


def draw(seed: int, letters: str, columns: int, rows: int) -> tuple[Scenario, float]:
    """One scene of the family: (scenario, hand speed m/s)."""
    rng = np.random.default_rng(seed)
    ref, tgt = rng.choice(list(letters), 2, replace=False)
    sigma = float(rng.uniform(0.3e-3, 0.7e-3))
    sc = Scenario(
        reference=str(ref),
        target=str(tgt),
        separation_deg=float(rng.uniform(10.0, 16.3)),
        trajectory="zigzag",
        error_sigma_m=(sigma, sigma, sigma),
        n_columns=columns,
        n_rows=rows,
        seed=seed,
    )
    return sc, float(rng.uniform(0.15, 0.25))


def camera_positions(true: np.ndarray, tracked: np.ndarray, times_s: np.ndarray, at_s: np.ndarray) -> np.ndarray:
    """The tracked phase centres (M, K, 3) a camera reports at ``at_s`` (M,): the true track at
    those times (linear within a leg, a cubic Hermite turn between legs, straight on past the
    sweep's ends) plus the tracking error re-sampled there."""
    t = np.asarray(times_s, np.float64)
    starts = [*(int(v) for v in leg_starts(t, true)), len(t)]
    out = resample_track(t, true, at_s)
    for i in range(len(starts) - 1):
        b = starts[i + 1]
        v_end = (true[b - 1] - true[b - 2]) / (t[b - 1] - t[b - 2])
        if i == 0:  # before the first frame: the hand already moving along the first leg
            v0 = (true[1] - true[0]) / (t[1] - t[0])
            m = at_s < t[0]
            out[m] = true[0] + (at_s[m] - t[0])[:, None, None] * v0
        if b == len(t):  # after the last frame
            m = at_s > t[-1]
            out[m] = true[-1] + (at_s[m] - t[-1])[:, None, None] * v_end
            continue
        v_next = (true[b + 1] - true[b]) / (t[b + 1] - t[b])
        h = t[b] - t[b - 1]
        m = (at_s > t[b - 1]) & (at_s < t[b])
        s = ((at_s[m] - t[b - 1]) / h)[:, None, None]
        out[m] = (
            (2 * s**3 - 3 * s**2 + 1) * true[b - 1]
            + (s**3 - 2 * s**2 + s) * h * v_end
            + (-2 * s**3 + 3 * s**2) * true[b]
            + (s**3 - s**2) * h * v_next
        )
    return out + resample_track(t, tracked - true, at_s)


def _ssim(scan, rg, tg, template) -> float:
    cfg = AutofocusConfig(**estimator_settings("auto", np.iscomplexobj(template)))
    out = FocusPlan.make(method="twin", config=cfg).focus_scan(scan, rg, tg, Reference(template=template))
    return float(out.metrics["target_ssim_corrected"])


def run_draw(sc: Scenario, speed: float, size: int, offsets=OFFSETS_S, sharpness_search: bool = True) -> dict:
    period_s = LEG_M / (speed * sc.n_rows)
    import twinfocus.simulation.scenario as scenario_module

    poses_fn = scenario_module.scenario_poses
    scenario_module.scenario_poses = lambda s, frame_period_s=0.1, t0_ns=0: poses_fn(s, period_s, t0_ns)
    try:
        scan, stage = simulate_scenario(sc)
    finally:
        scenario_module.scenario_poses = poses_fn
    rg, tg = scenario_grids(sc, size)
    physical = template_from_scan(stage, rg, keep_phase=True)

    def stage_tpl(n):
        return template_from_scan(stage, ImageGrid.from_roi(sc.reference_roi(), n))

    ref_pts, ref_amps = scenario_scatterers(sc, reference_only=True)
    t = position_times_s(scan.timestamps_ns, scan.n_positions)
    synced = {
        "physical": _ssim(scan, rg, tg, physical),
        "digital": _ssim(scan, rg, tg, psf_template(ref_pts, scan.positions, scan.chirp, rg, ref_amps)),
    }
    rows_out = []
    for off in offsets:
        print(
            f"[clock] {sc.reference} -> {sc.target} seed {sc.seed}: offset {off * 1e3:g} ms",
            file=sys.stderr,
            flush=True,
        )
        late = replace(scan, positions=camera_positions(scan.positions_true, scan.positions, t, t + off))
        # convert's view: the camera's poses stamped off behind, the radar's frames at t
        centre = late.positions.mean(axis=1)
        try:
            rh = range_history_offset(late.data, late.chirp, t, t, centre)
            rh_found, rh_sigma = -rh.offset_s, rh.sigma_s
        except Exception as exc:  # noqa: BLE001 -- a refusal is a result here
            rh_found, rh_sigma = None, str(exc)
        row: dict = {
            "offset_ms": off * 1e3,
            "range_history_found_ms": None if rh_found is None else rh_found * 1e3,
            "range_history_sigma_ms": rh_sigma * 1e3 if isinstance(rh_sigma, float) else rh_sigma,
        }

        def dtw_tpl(n, positions=late.positions):
            return psf_template(ref_pts, positions, scan.chirp, ImageGrid.from_roi(sc.reference_roi(), n), ref_amps)

        searches = {"physical": stage_tpl, "digital": dtw_tpl}
        if sharpness_search:
            searches["sharpness"] = None
        found = {}
        for name, tpl in searches.items():
            t0 = time.perf_counter()
            # the search's 32 x 32 reference image, then the --size one (as focus --clock-search does)
            found[name], rec = search_scan_clock(late, sc.reference_roi(), SEARCH_SIZE, template=tpl, fine_size=size)
            row[f"{name}_found_ms"] = -rec["offset_s"] * 1e3
            row[f"{name}_residual_ms"] = (-rec["offset_s"] - off) * 1e3
            row[f"{name}_search_s"] = time.perf_counter() - t0
        row["physical_no_search"] = _ssim(late, rg, tg, physical)
        row["physical_clock_search"] = _ssim(found["physical"], rg, tg, physical)
        row["digital_no_search"] = _ssim(late, rg, tg, psf_template(ref_pts, late.positions, scan.chirp, rg, ref_amps))
        for name in ("digital", "sharpness") if sharpness_search else ("digital",):
            dtw = psf_template(ref_pts, found[name].positions, scan.chirp, rg, ref_amps)
            row[f"digital_clock_search{'' if name == 'digital' else '_by_sharpness'}"] = _ssim(found[name], rg, tg, dtw)
        rows_out.append(row)
        print(
            "  " + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()),
            file=sys.stderr,
            flush=True,
        )
    return {
        "scene": f"{sc.reference} -> {sc.target}",
        "seed": sc.seed,
        "separation_deg": sc.separation_deg,
        "tracking_error_mm": sc.error_sigma_m[0] * 1e3,
        "speed_m_per_s": speed,
        "frame_period_s": period_s,
        "positions": scan.n_positions,
        "channels": scan.n_channels,
        "samples": scan.chirp.n_samples,
        "synced": synced,
        "offsets": rows_out,
    }


def summary(draws: list[dict]) -> dict:
    """Per offset, over the draws: the worst |residual| (ms) and the largest loss against the clocks
    agreeing (synced - searched SSIM) of each twin, and the mean search time (s)."""
    out = {}
    for i, off in enumerate(d["offset_ms"] for d in draws[0]["offsets"]):
        rows = [d["offsets"][i] for d in draws]
        key = f"{off:g}_ms"
        out[key] = {
            "physical_worst_residual_ms": max(abs(r["physical_residual_ms"]) for r in rows),
            "digital_worst_residual_ms": max(abs(r["digital_residual_ms"]) for r in rows),
            "physical_worst_loss": max(
                d["synced"]["physical"] - r["physical_clock_search"] for d, r in zip(draws, rows)
            ),
            "digital_worst_loss": max(d["synced"]["digital"] - r["digital_clock_search"] for d, r in zip(draws, rows)),
            "mean_search_s": float(np.mean([r["physical_search_s"] for r in rows])),
            # convert's estimate here reads the scan's own positions (no poses in the turns)
            "range_history_worst_error_ms": max(
                (abs(r["range_history_found_ms"] - off) for r in rows if r["range_history_found_ms"] is not None),
                default=None,
            ),
        }
        if "sharpness_residual_ms" in rows[0]:
            out[key]["sharpness_worst_residual_ms"] = max(abs(r["sharpness_residual_ms"]) for r in rows)
            out[key]["digital_by_sharpness_worst_loss"] = max(
                d["synced"]["digital"] - r["digital_clock_search_by_sharpness"] for d, r in zip(draws, rows)
            )
    return out


def main(out_dir="benchmarks/results", draws: int = 2, heldout: bool = False, columns: int = 3, rows: int = 130,
         size: int = 48, offsets=OFFSETS_S, start: int = 0) -> dict:  # fmt: skip
    t_start = time.perf_counter()
    first, letters = (HELDOUT_SEED, HELDOUT_LETTERS) if heldout else (BENCH_SEED, BENCH_LETTERS)
    results = []
    for k in range(start, start + draws):
        sc, speed = draw(first + k, letters, columns, rows)
        results.append(run_draw(sc, speed, size, offsets))
    return write(out_dir, results, heldout, {"columns": columns, "rows": rows}, size, time.perf_counter() - t_start)


def write(out_dir, results: list[dict], heldout: bool, sizes: dict, size: int, seconds: float) -> dict:
    """Write ``clock.json`` (``clock_heldout.json``) of the draws' results; returns the document."""
    doc = {
        "sizes": {**sizes, "image": size, "search_image": SEARCH_SIZE},
        "heldout": heldout,
        "summary": summary(results),
        "draws": results,
        "seconds": seconds,
    }
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    from twinfocus.io.atomic import atomic_writer

    with atomic_writer(out / ("clock_heldout.json" if heldout else "clock.json"), "w") as f:
        f.write(json.dumps(doc, indent=2) + "\n")
    return doc


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--draws", type=int, default=2)
    ap.add_argument("--heldout", action="store_true", help="the held-out draws (a check of what the bench built)")
    ap.add_argument("--columns", type=int, default=3)
    ap.add_argument("--rows", type=int, default=130)
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--start", type=int, default=0, help="the first draw's index (draws run apart, then --merge)")
    ap.add_argument("--merge", nargs="+", metavar="JSON", help="write one file of these runs' draws (same sizes)")
    ap.add_argument("--offsets-ms", default=",".join(f"{v * 1e3:g}" for v in OFFSETS_S))
    a = ap.parse_args()
    if a.merge:
        docs = [json.loads(Path(f).read_text()) for f in a.merge]
        sizes = {k: docs[0]["sizes"][k] for k in ("columns", "rows")}
        runs = [d for doc in docs for d in doc["draws"]]
        write(a.out, runs, a.heldout, sizes, docs[0]["sizes"]["image"], sum(doc["seconds"] for doc in docs))
        sys.exit(0)
    main(
        a.out,
        a.draws,
        a.heldout,
        a.columns,
        a.rows,
        a.size,
        tuple(float(v) * 1e-3 for v in a.offsets_ms.split(",")),
        a.start,
    )
