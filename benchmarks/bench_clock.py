"""The radar-camera clock found from the data, on zig-zag hand sweeps drawn from a family of scenes.

Each draw takes at random (from its seed): the reference's letter and the target's, their
separation (10-16.3 degrees), the hand's speed (0.15-0.25 m/s) and the tracking error (0.3-0.7 mm
per axis). Per clock offset (0, 15, 50, 100 ms; the camera's stamps run that much behind the
radar's): the camera's poses as it would report them at ``t + offset`` -- its track re-sampled
along each leg and, in the turn between columns where the scan keeps no frame, a smooth turn
(cubic from the leg's end to the next leg's start, their velocities matched) -- the offset found
by the range history (what ``convert --align scan`` does) and by the reference's focus
(``focus --clock-search``: the physical twin's image matched, the digital twin's image matched, and
the image's sharpness alone, what ``focus --digital-twin --clock-search`` uses; convert's focus
stage also on the reference region by each twin's template, ``convert --template-scan``), their residuals,
the searches' time, and the target SSIM of the physical twin (the reference's motion-stage scan)
and of the digital twin (the reference's points as a template) with the clock searched, without,
and with the clocks agreeing.

Bench draws (seeds 1001 on, letters ``BENCH_LETTERS``) are what the search was built on; held-out
draws (seeds 2001 on, letters ``HELDOUT_LETTERS``, none shared) only check it.

    python -m benchmarks.bench_clock [--draws 2] [--heldout] [--offsets-ms 0,15,50,100] [--out benchmarks/results]
    python -m benchmarks.bench_clock --heldout --draws 1 --start 1 --out tmp1      (one draw apart ...)
    python -m benchmarks.bench_clock --heldout --merge tmp0/clock_heldout.json tmp1/clock_heldout.json  (... joined)
    python -m benchmarks.bench_clock --convert-only --out tmp2                     (convert's rows alone ...)
    python -m benchmarks.bench_clock --merge benchmarks/results/clock.json tmp2/clock.json  (... laid over the file's)

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

from twinfocus.errors import TwinFocusError
from twinfocus.focus.autofocus import AutofocusConfig
from twinfocus.focus.estimators import estimator_settings
from twinfocus.focus.pipeline import Reference
from twinfocus.focus.plan import FocusPlan
from twinfocus.imaging.backprojection.numba_backend import backproject
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.metrics import image_sharpness
from twinfocus.sensors.clock_offset import (
    FOCUS_SIZE,
    leg_starts,
    on_track,
    position_times_s,
    range_history_offset,
    refine_by_focus,
    resample_track,
    search_scan_clock,
)
from twinfocus.simulation.scenario import Scenario, scenario_grids, scenario_scatterers, simulate_scenario
from twinfocus.twins.digital_twin.template import psf_template
from twinfocus.twins.templates import scan_template_on, template_from_scan

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


#: the camera's trajectory convert reads runs this long past the radar's first and last frames, s
CAMERA_PAD_S = 0.3
#: the score's curve around the truth (why 1 ms is reached or not): offsets this far each side, ms
CURVE_HALF_MS = 6


def camera_stamps(t: np.ndarray, period_s: float) -> np.ndarray:
    """The camera's pose stamps (S,) seconds: the frames' own (with agreeing clocks its poses are
    the scan's, tracking error and all), poses ``period_s`` apart through each turn where the scan
    keeps no frame, and :data:`CAMERA_PAD_S` before and after the sweep."""
    starts = [*(int(v) for v in leg_starts(t)), len(t)]
    turns = [np.arange(t[b - 1] + period_s, t[b] - period_s / 2, period_s) for b in starts[1:-1]]
    pad = np.arange(1, int(np.ceil(CAMERA_PAD_S / period_s)) + 1) * period_s
    return np.sort(np.concatenate([t[0] - pad, t, *turns, t[-1] + pad]))


def convert_row(sc: Scenario, scan, off: float, period_s: float, ssim, templates: dict | None = None) -> dict:
    """``convert --align scan`` on the draw: the camera's trajectory (:func:`camera_stamps`, the
    poses it reports there ``off`` late, :func:`camera_positions`) read as
    convert reads it -- the range history, its focus stage (:func:`refine_by_focus`, positions
    re-sampled on that trajectory), the scan converted again at the offset found -- and the
    converted scan's target SSIM through ``ssim(scan) -> {"physical": ., "digital": .}``. Also the
    score's curve at the truth +- :data:`CURVE_HALF_MS` ms, 1 ms apart, on the focus stage's region:
    its own best (the parabola's vertex), its r.m.s. scatter about the parabola, and how much the
    score and the image's amplitude change 1 and 3 ms off the truth. templates : twin name ->
    ``(positions_at, n) ->`` its template on the reference's n x n grid: the focus stage again on
    the reference region matched to it (``convert --template-scan``), that twin's SSIM after it
    (:func:`template_convert`)."""
    t = position_times_s(scan.timestamps_ns, scan.n_positions)
    stamps = camera_stamps(t, period_s)
    cam = camera_positions(scan.positions_true, scan.positions, t, stamps + off)  # (S, K, 3)
    t0 = time.perf_counter()
    rh = range_history_offset(scan.data, scan.chirp, t, stamps, cam.mean(axis=1))
    rh_s = time.perf_counter() - t0
    positions_at = on_track(stamps, cam, t)
    z = float(sc.reference_roi()[4])
    try:
        fine, rec = refine_by_focus(scan.data, scan.chirp, positions_at, rh, z)
        found, sigma, stage, region = fine.offset_s, fine.sigma_s, "focus", rec["region_m"]
    except TwinFocusError:
        found, sigma, stage, region = rh.offset_s, rh.sigma_s, "range_history", None
    seconds = time.perf_counter() - t0
    converted = replace(scan, positions=resample_track(stamps, cam, t + found))
    row: dict = {
        "convert_range_history_found_ms": -rh.offset_s * 1e3,
        "convert_range_history_sigma_ms": rh.sigma_s * 1e3,
        "convert_found_ms": -found * 1e3,
        "convert_residual_ms": (-found - off) * 1e3,
        "convert_sigma_ms": sigma * 1e3,
        "convert_stage": stage,
        "convert_clock_s": seconds,
        **{f"{k}_convert": v for k, v in ssim(converted).items()},
    }
    if region is not None:
        row.update(score_curve(scan, positions_at, region, -off))
    for name, tpl in (templates or {}).items():
        row.update(template_convert(sc, scan, (stamps, cam, t), rh, name, tpl, ssim, off, rh_s))
    return row


def template_convert(sc: Scenario, scan, track, rh, name: str, tpl, ssim, off: float, rh_s: float) -> dict:
    """convert's focus stage on the reference region scored by twin ``name``'s template (``tpl``:
    ``(positions_at, n) ->`` the template, given the positions at the range history's offset, as
    a digital twin would form it from the converted scan), the scan converted at the offset
    found and that twin's target SSIM: ``convert_<name>_template_*`` and ``<name>_convert_by_template``."""
    stamps, cam, t = track
    positions_at = on_track(stamps, cam, t)
    t0 = time.perf_counter()
    at_rh = positions_at(rh.offset_s)
    try:
        fine, rec = refine_by_focus(
            scan.data, scan.chirp, positions_at, rh, float(sc.reference_roi()[4]),
            region_m=sc.reference_roi(), template=lambda n: tpl(at_rh, n),
        )  # fmt: skip
        found, sigma, stage = fine.offset_s, fine.sigma_s, "focus"
    except TwinFocusError:
        found, sigma, stage = rh.offset_s, rh.sigma_s, "range_history"
    key = f"convert_{name}_template"
    return {
        f"{key}_found_ms": -found * 1e3,
        f"{key}_residual_ms": (-found - off) * 1e3,
        f"{key}_sigma_ms": sigma * 1e3,
        f"{key}_stage": stage,
        f"{key}_clock_s": rh_s + time.perf_counter() - t0,
        f"{name}_convert_by_template": ssim(replace(scan, positions=resample_track(stamps, cam, t + found)), (name,))[
            name
        ],
    }


def score_curve(scan, positions_at, region, truth_s: float) -> dict:
    """The focus stage's score (sharpness of the region's FOCUS_SIZE image) at the truth +- 1 ms
    steps: where its parabola peaks (ms off the truth), its r.m.s. scatter about the parabola, the
    drop 1 and 3 ms off the truth (mean of both sides), all as shares of the score at the truth;
    and the image's amplitude change there (r.m.s. difference over r.m.s.)."""
    grid = ImageGrid.from_roi(region, FOCUS_SIZE)
    ks = np.arange(-CURVE_HALF_MS, CURVE_HALF_MS + 1)
    images = [np.abs(backproject(scan.data, positions_at(truth_s + k * 1e-3), scan.chirp, grid)) for k in ks]
    score = np.array([image_sharpness(im) for im in images])
    mid = int(CURVE_HALF_MS)
    rel = score / score[mid]
    a, b, c = np.polyfit(ks.astype(float), rel, 2)
    noise = float(np.sqrt(np.mean((np.polyval([a, b, c], ks) - rel) ** 2)))

    def change(k: int) -> float:
        ref = images[mid]
        return float(np.mean([np.linalg.norm(images[mid + d] - ref) / np.linalg.norm(ref) for d in (-k, k)]))

    return {
        "curve_peak_off_truth_ms": float(-b / (2 * a)) if a < 0 else None,
        "curve_noise": noise,
        "curve_drop_1ms": float(1 - (rel[mid - 1] + rel[mid + 1]) / 2),
        "curve_drop_3ms": float(1 - (rel[mid - 3] + rel[mid + 3]) / 2),
        "image_change_1ms": change(1),
        "image_change_3ms": change(3),
    }


def search_row(sc: Scenario, late, off: float, size: int, ssim, stage_tpl, sharpness_search: bool) -> dict:
    """``focus --clock-search`` on the scan with the camera's clock ``late``'s: the range history on
    the scan's own positions, the searches (physical twin's, digital twin's and sharpness), their
    residuals and seconds, and the target SSIM without and with the search."""
    t = position_times_s(late.timestamps_ns, late.n_positions)
    # convert's view without a trajectory: the scan's own positions (no poses in the turns)
    try:
        rh = range_history_offset(late.data, late.chirp, t, t, late.positions.mean(axis=1))
        rh_found, rh_sigma = -rh.offset_s, rh.sigma_s
    except Exception as exc:  # noqa: BLE001 -- a refusal is a result here
        rh_found, rh_sigma = None, str(exc)
    row: dict = {
        "range_history_found_ms": None if rh_found is None else rh_found * 1e3,
        "range_history_sigma_ms": rh_sigma * 1e3 if isinstance(rh_sigma, float) else rh_sigma,
    }
    ref_pts, ref_amps = scenario_scatterers(sc, reference_only=True)

    def dtw_tpl(n, positions=late.positions):
        return psf_template(ref_pts, positions, late.chirp, ImageGrid.from_roi(sc.reference_roi(), n), ref_amps)

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
    plain = ssim(late)
    row["physical_no_search"], row["digital_no_search"] = plain["physical"], plain["digital"]
    row["physical_clock_search"] = ssim(found["physical"], ("physical",))["physical"]
    row["digital_clock_search"] = ssim(found["digital"], ("digital",))["digital"]
    if sharpness_search:
        row["digital_clock_search_by_sharpness"] = ssim(found["sharpness"], ("digital",))["digital"]
    return row


def run_draw(sc: Scenario, speed: float, size: int, offsets=OFFSETS_S, sharpness_search: bool = True,
             searches: bool = True) -> dict:  # fmt: skip
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

    stage_tpl = scan_template_on(stage, sc.reference_roi())
    ref_pts, ref_amps = scenario_scatterers(sc, reference_only=True)

    def digital_tpl(positions, n):
        return psf_template(ref_pts, positions, scan.chirp, ImageGrid.from_roi(sc.reference_roi(), n), ref_amps)

    templates = {"physical": lambda positions, n: stage_tpl(n), "digital": digital_tpl}
    t = position_times_s(scan.timestamps_ns, scan.n_positions)

    def ssim(s, which=("physical", "digital")) -> dict:
        """The target SSIM of scan ``s`` by each twin named (the digital twin's template from s's positions)."""
        out = {}
        if "physical" in which:
            out["physical"] = _ssim(s, rg, tg, physical)
        if "digital" in which:
            out["digital"] = _ssim(s, rg, tg, psf_template(ref_pts, s.positions, scan.chirp, rg, ref_amps))
        return out

    synced = ssim(scan)
    rows_out = []
    for off in offsets:
        print(
            f"[clock] {sc.reference} -> {sc.target} seed {sc.seed}: offset {off * 1e3:g} ms",
            file=sys.stderr,
            flush=True,
        )
        row: dict = {"offset_ms": off * 1e3, **convert_row(sc, scan, off, period_s, ssim, templates)}
        if searches:
            late = replace(scan, positions=camera_positions(scan.positions_true, scan.positions, t, t + off))
            row.update(search_row(sc, late, off, size, ssim, stage_tpl, sharpness_search))
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
    agreeing (synced - SSIM) of each twin, for convert's offset and for the searches (where run),
    the searches' mean time (s), and the score's curve at the truth (why 1 ms is or is not reached)."""
    out = {}
    for i, off in enumerate(d["offset_ms"] for d in draws[0]["offsets"]):
        rows = [d["offsets"][i] for d in draws]
        key = f"{off:g}_ms"
        out[key] = {
            "convert_worst_residual_ms": max(abs(r["convert_residual_ms"]) for r in rows),
            "convert_range_history_worst_error_ms": max(abs(r["convert_range_history_found_ms"] - off) for r in rows),
            "convert_physical_worst_loss": max(
                d["synced"]["physical"] - r["physical_convert"] for d, r in zip(draws, rows)
            ),
            "convert_digital_worst_loss": max(
                d["synced"]["digital"] - r["digital_convert"] for d, r in zip(draws, rows)
            ),
            "convert_mean_clock_s": float(np.mean([r["convert_clock_s"] for r in rows])),
            "convert_stages": sorted({r["convert_stage"] for r in rows}),
        }
        out[key].update(template_summary(draws, rows))
        curves = [r for r in rows if "curve_noise" in r]
        if curves:
            peaks = [abs(r["curve_peak_off_truth_ms"]) for r in curves if r["curve_peak_off_truth_ms"] is not None]
            out[key].update(
                curve_worst_peak_off_truth_ms=max(peaks, default=None),
                curve_worst_noise=max(r["curve_noise"] for r in curves),
                curve_least_drop_1ms=min(r["curve_drop_1ms"] for r in curves),
                curve_least_drop_3ms=min(r["curve_drop_3ms"] for r in curves),
                image_least_change_1ms=min(r["image_change_1ms"] for r in curves),
                image_least_change_3ms=min(r["image_change_3ms"] for r in curves),
            )
        if "physical_residual_ms" in rows[0]:
            out[key].update(search_summary(draws, rows, off))
    return out


def template_summary(draws: list[dict], rows: list[dict]) -> dict:
    """convert's focus stage by each twin's template (:func:`template_convert`), where every draw
    has it at this offset: its worst |residual| (ms), the twin's largest loss against the clocks
    agreeing, its mean time (s) and the stages that ended it."""
    out: dict = {}
    for name in ("physical", "digital"):
        key = f"convert_{name}_template"
        if not all(f"{key}_residual_ms" in r for r in rows):
            continue
        out[f"{key}_worst_residual_ms"] = max(abs(r[f"{key}_residual_ms"]) for r in rows)
        out[f"{key}_worst_loss"] = max(
            d["synced"][name] - r[f"{name}_convert_by_template"] for d, r in zip(draws, rows)
        )
        out[f"{key}_mean_clock_s"] = float(np.mean([r[f"{key}_clock_s"] for r in rows]))
        out[f"{key}_stages"] = sorted({r[f"{key}_stage"] for r in rows})
    return out


def search_summary(draws: list[dict], rows: list[dict], off: float) -> dict:
    """The searches' part of :func:`summary` at one offset."""
    out = {
        "physical_worst_residual_ms": max(abs(r["physical_residual_ms"]) for r in rows),
        "digital_worst_residual_ms": max(abs(r["digital_residual_ms"]) for r in rows),
        "physical_worst_loss": max(d["synced"]["physical"] - r["physical_clock_search"] for d, r in zip(draws, rows)),
        "digital_worst_loss": max(d["synced"]["digital"] - r["digital_clock_search"] for d, r in zip(draws, rows)),
        "mean_search_s": float(np.mean([r["physical_search_s"] for r in rows])),
        # the range history here reads the scan's own positions (no poses in the turns)
        "range_history_worst_error_ms": max(
            (abs(r["range_history_found_ms"] - off) for r in rows if r["range_history_found_ms"] is not None),
            default=None,
        ),
    }
    if "sharpness_residual_ms" in rows[0]:
        out["sharpness_worst_residual_ms"] = max(abs(r["sharpness_residual_ms"]) for r in rows)
        out["digital_by_sharpness_worst_loss"] = max(
            d["synced"]["digital"] - r["digital_clock_search_by_sharpness"] for d, r in zip(draws, rows)
        )
    return out


def main(out_dir="benchmarks/results", draws: int = 2, heldout: bool = False, columns: int = 3, rows: int = 130,
         size: int = 48, offsets=OFFSETS_S, start: int = 0, searches: bool = True) -> dict:  # fmt: skip
    t_start = time.perf_counter()
    first, letters = (HELDOUT_SEED, HELDOUT_LETTERS) if heldout else (BENCH_SEED, BENCH_LETTERS)
    results = []
    for k in range(start, start + draws):
        sc, speed = draw(first + k, letters, columns, rows)
        results.append(run_draw(sc, speed, size, offsets, searches=searches))
    return write(out_dir, results, heldout, {"columns": columns, "rows": rows}, size, time.perf_counter() - t_start)


def merge_into(old: list[dict], new: list[dict]) -> list[dict]:
    """The draws of ``old`` with each row of ``new``'s (the same seed and offset) laid over its
    own (a ``--convert-only`` run added to a file of the searches): rows and draws ``old`` lacks
    are added, the offsets in order."""
    by_seed = {d["seed"]: d for d in old}
    for d in new:
        if d["seed"] not in by_seed:
            by_seed[d["seed"]] = d
            continue
        mine = by_seed[d["seed"]]
        rows = {r["offset_ms"]: r for r in mine["offsets"]}
        for r in d["offsets"]:
            rows[r["offset_ms"]] = {**rows.get(r["offset_ms"], {}), **r}
        mine.update({k: v for k, v in d.items() if k != "offsets"})
        mine["offsets"] = [rows[k] for k in sorted(rows)]
    return [by_seed[k] for k in sorted(by_seed)]


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
    ap.add_argument("--convert-only", action="store_true", help="only convert's rows (no focus --clock-search)")
    a = ap.parse_args()
    if a.merge:
        # the first file's draws, each later file's rows laid over them (merge_into)
        docs = [json.loads(Path(f).read_text()) for f in a.merge]
        sizes = {k: docs[0]["sizes"][k] for k in ("columns", "rows")}
        runs: list[dict] = []
        for doc in docs:
            runs = merge_into(runs, doc["draws"])
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
        not a.convert_only,
    )
