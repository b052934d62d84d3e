"""Benches that share a rig: each set of scans draws ONE camera offset (a length in the family
bench's ``OFFSET_RANGE_M``, a random direction), calibrates it once with ``twinfocus rig``'s
measurement on one scan of a paper-protocol scene taken on accurate positions (its stage scan),
and focuses the set's other scans (benchmarks/bench_dtwin_family.py's conditions) with the
digital twin from their camera clouds, with and without the rig, beside the physical twin and the
digital twin's placement ceiling (its target's best SSIM over sub-pixel shifts).

    python -m benchmarks.bench_rig --draws 3 --rows 33 --size 48      (~15 min on 2 cores)
    python -m benchmarks.bench_rig --draws 3 --heldout                 (the held-out sets)
    python -m benchmarks.bench_rig --summarise benchmarks/results/rig.json   (the summary again)
    python -m benchmarks.bench_rig --calibrations 24 [--heldout]        (calibrations alone: each
        error against its stated sd, rig_calibration[_heldout].json)

With the rig, the focus places the reference on the calibrated cloud's outline
(:func:`twinfocus.focus.rig_placement.rig_placed`); each record keeps what that placement found
(``rig placement``), both results' confidence reports (trusted, warnings) and where each put the
target (``error_mm``). The summary adds the report's false trust (trusted, below 0.90) and false
alarms (flagged, at or above 0.95) with and without the rig.

Seeds: the build sets start at ``RIG_SEED`` (held-out shapes, seeds the family bench does not draw;
the placement was built on them: ``rig.json``), the held-out sets at ``HELDOUT_RIG_SEED`` (never
looked at while building: ``rig_heldout.json``). Prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from benchmarks.bench_dtwin_family import (
    CLOUD,
    HELDOUT_SHAPES,
    OFFSET_RANGE_M,
    digital_twin_focus,
    draw_inputs,
    placement,
    surface_of,
)

RIG_SEED = 3101
#: the held-out sets' first seed: never run while the rig's placement was built
HELDOUT_RIG_SEED = 3701
CONDITIONS = ("paper", "1 mm deeper", "1.6 mm")


def draw_rig(seed: int) -> np.ndarray:
    """The set's camera offset, float (3,) metres."""
    rng = np.random.default_rng([seed, 77])
    d = rng.normal(size=3)
    return float(rng.uniform(*OFFSET_RANGE_M)) * d / np.linalg.norm(d)


def calibrate(seed: int, offset: np.ndarray, rows: int, size: int, study: bool = False) -> dict:
    """The rig measured on the paper-protocol draw ``seed``'s scan (``rows`` rows) on its true
    positions, as a motion stage takes it. ``study``: the calibration study's record instead
    (:func:`calibration_record`: every spread, none refused, no depth search)."""
    from benchmarks.bench_dtwin_family import family_scenario
    from twinfocus.radar.scan import Scan
    from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario
    from twinfocus.twins.digital_twin.camera_cloud import camera_cloud
    from twinfocus.twins.digital_twin.rig import measure_rig

    kw = family_scenario("paper", seed, HELDOUT_SHAPES, rows)
    sc = Scenario(**kw)
    scan, _ = simulate_scenario(sc)
    stage = Scan(scan.data, scan.positions_true, scan.chirp)
    rg, _ = scenario_grids(sc, size)
    surface = sc.scene().object("reference").surface_points(1e-3)
    cloud = camera_cloud(surface, *CLOUD, offset, rng=np.random.default_rng([seed, 15]))
    if study:
        m = measure_rig(stage, cloud, rg, board="bench", camera=None, max_sd_px=np.inf, depth=False)
        return calibration_record(m, offset, {"seed": seed, "reference": kw["reference"], "surface": surface_of(kw)})
    m = measure_rig(stage, cloud, rg, board="bench", camera=None)
    return {
        "offset_m": m.rig.offset_m.tolist(),
        "sd_m": m.rig.sd_m.tolist(),
        "match": m.match,
        "error_mm": [round(float(v) * 1e3, 3) for v in (m.rig.offset_m + offset)],
    }


def calibration_record(m, offset: np.ndarray, about: dict) -> dict:
    """One calibration of the study: the measurement ``m`` (a RigMeasurement) of the camera offset
    ``offset`` (float (3,) metres): its error and each spread (x, y, mm), the error over the
    stated sd, the measured spreads in pixels (the refusal rule's unit: :func:`refusals`) and
    whether ``twinfocus rig`` refuses it."""
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.twins.digital_twin.rig import MAX_SD_PX

    src = m.rig.source
    sy, sx = ImageGrid.from_roi(src["grid_roi"], tuple(src["grid_shape"])).spacing_m

    def mm(px: list) -> list:  # (dy, dx) pixels -> (x, y) mm
        return [round(px[1] * sx * 1e3, 3), round(px[0] * sy * 1e3, 3)]

    error = (m.rig.offset_m + offset)[:2] * 1e3
    parts = {k: mm(src["sd"][f"{k}_px"]) for k in ("positions", "cells", "cloud", "model")}
    sd = np.asarray(mm(src["sd"]["sd_px"]))
    return {
        **about,
        "camera_offset_m": offset.tolist(),
        "match": round(m.match, 4),
        "error_mm": [round(float(v), 3) for v in error],
        "sd_mm": sd.tolist(),
        "sd_parts_mm": parts,
        "ratio": [round(float(v), 3) for v in np.abs(error) / np.maximum(sd, 1e-9)],
        "ratio_positions_only": [round(float(v), 3) for v in np.abs(error) / np.maximum(parts["positions"], 1e-9)],
        "pixel_mm": [round(sx * 1e3, 4), round(sy * 1e3, 4)],
        "measured_px": [round(float(v), 4) for v in src["sd"]["measured_px"]],
        "positions_px": [round(float(v), 4) for v in src["sd"]["positions_px"]],
        "refused": bool(np.any(np.asarray(src["sd"]["measured_px"]) > MAX_SD_PX)),
    }


def calibration_summary(records: list) -> dict:
    """The study's summary per axis (x, y): the share of calibrations whose error is within 2 of
    the stated sd, the ratio's median, 90th percentile and largest, with the sd made now and with
    the positions' bootstrap alone; and the share ``twinfocus rig`` refuses under each."""
    out: dict = {"calibrations": len(records)}
    for key, name in (("ratio", "sd"), ("ratio_positions_only", "positions_only")):
        r = np.array([c[key] for c in records], float)
        out[name] = {
            axis: {
                "within_2sd": round(float(np.mean(r[:, i] <= 2.0)), 4),
                "ratio_median": round(float(np.median(r[:, i])), 3),
                "ratio_p90": round(float(np.quantile(r[:, i], 0.9)), 3),
                "ratio_max": round(float(r[:, i].max()), 3),
            }
            for i, axis in enumerate("xy")
        }
    err = np.abs([c["error_mm"] for c in records])
    out["error_mm_rms"] = [round(float(v), 3) for v in np.sqrt((err**2).mean(axis=0))]
    out["sd_mm_median"] = [round(float(v), 3) for v in np.median([c["sd_mm"] for c in records], axis=0)]
    out.update(refusals(records))
    return out


def _pixels(c: dict) -> tuple[np.ndarray, np.ndarray]:
    """A study record's measured spread and positions' bootstrap, float (2,) pixels (dy, dx); for a
    record written before they were kept, from its mm and its measuring grid's pixel (remade from
    its seed: the grid is the scenario's, no simulation needed)."""
    if "measured_px" in c:
        return np.asarray(c["measured_px"]), np.asarray(c["positions_px"])
    from benchmarks.bench_dtwin_family import family_scenario
    from twinfocus.simulation.scenario import Scenario, scenario_grids
    from twinfocus.twins.digital_twin.rig import measuring_grid

    rg, _ = scenario_grids(Scenario(**family_scenario("paper", c["seed"], HELDOUT_SHAPES, 65)), 48)
    sy, sx = np.asarray(measuring_grid(rg).spacing_m) * 1e3
    p = c["sd_parts_mm"]
    measured = np.sqrt(sum(np.square(p[k]) for k in ("positions", "cells", "cloud")))  # (x, y) mm
    return measured[::-1] / [sy, sx], np.asarray(p["positions"])[::-1] / [sy, sx]


def refusals(records: list) -> dict:
    """The share of the study's calibrations ``twinfocus rig`` refuses: by its rule (the measured
    spread above ``MAX_SD_PX`` pixels), by the same spread above half a pixel (the rule's bound
    while the sd was the positions' bootstrap alone) and by that old rule on that old sd."""
    from twinfocus.twins.digital_twin.rig import MAX_SD_PX

    px = [_pixels(c) for c in records]
    return {
        "refused": round(float(np.mean([np.any(m > MAX_SD_PX) for m, _ in px])), 4),
        "refused_half_pixel": round(float(np.mean([np.any(m > 0.5) for m, _ in px])), 4),
        "refused_before": round(float(np.mean([np.any(b > 0.5) for _, b in px])), 4),
        "max_sd_px": MAX_SD_PX,
    }


def calibration_study(out: str, n: int, rows: int, size: int, heldout: bool = False) -> dict:
    """``--calibrations N``: N calibrations alone (no focusing), one per set's seed, each of its own
    camera offset, written to ``rig_calibration[_heldout].json`` with :func:`calibration_summary`."""
    first = HELDOUT_RIG_SEED if heldout else RIG_SEED
    if not heldout and first + 10 * n + 200 >= HELDOUT_RIG_SEED:
        raise ValueError(f"--calibrations {n}: the build seeds would reach the held-out ones ({HELDOUT_RIG_SEED})")
    path = Path(out) / ("rig_calibration" + ("_heldout" if heldout else "") + ".json")
    path.parent.mkdir(parents=True, exist_ok=True)
    res: dict = {"scan": {"calibration_positions": rows * 6, "pixels": size}, "calibrations": []}
    for k in range(n):
        seed = first + 10 * k
        c = calibrate(seed, draw_rig(seed), rows, size, study=True)
        res["calibrations"].append(c)
        print(f"[rig calibration] {seed} {c['reference']} {c['surface']}: error {c['error_mm']} mm, sd {c['sd_mm']} "
              f"(ratio {c['ratio']}, positions only {c['ratio_positions_only']})", file=sys.stderr, flush=True)  # fmt: skip
        res["summary"] = calibration_summary(res["calibrations"])  # after each: a stopped run keeps one
        path.write_text(json.dumps(res, indent=1, default=float))
    print(json.dumps(res["summary"], indent=1))
    return res


def focus_set(condition: str, seed: int, offset: np.ndarray, rig_offset: np.ndarray, rows: int, size: int) -> dict:
    """One scan of the set: the digital twin from its camera cloud without and with the rig
    (``twinfocus focus --digital-twin CLOUD [--rig RIG]``), its confidence report and placement
    ceiling each, and the physical twin."""
    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.estimators import estimator_settings
    from twinfocus.focus.pipeline import Bases, Reference
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.twins.digital_twin.camera_cloud import camera_cloud
    from twinfocus.twins.digital_twin.condition import digital_twin_reference
    from twinfocus.twins.digital_twin.rig import Rig, rig_reference
    from twinfocus.twins.templates import template_from_scan

    d = draw_inputs(condition, seed, HELDOUT_SHAPES, rows, size)
    scan, rg = d["scan"], d["rg"]
    cloud = camera_cloud(d["reference_points"], *CLOUD, offset, rng=np.random.default_rng([seed, 15]))
    rec: dict = {
        "seed": seed,
        "reference": d["kw"]["reference"],
        "target": d["kw"]["target"],
        "surface": surface_of(d["kw"]),
    }
    rig = Rig(rig_offset, np.zeros(3), "bench", None)
    for name in ("no rig", "rig"):
        d["twin"] = (
            digital_twin_reference(cloud, scan.positions, scan.chirp, rg)
            if name == "no rig"
            else rig_reference(cloud, scan, rg, rig)
        )
        out = digital_twin_focus(d)
        conf = out.metrics["confidence"]
        rec[name] = round(out.metrics["target_ssim_corrected"], 4)
        rec[f"{name} trusted"] = conf["trusted"]
        rec[f"{name} warnings"] = conf["warnings"]
        where = placement(d, out)
        rec[f"{name} ceiling"] = where["best_shift_ssim"]
        rec[f"{name} error_mm"] = where["error_mm"]
        if "rig_placement" in conf:
            rec["rig placement"] = conf["rig_placement"]
    pt = FocusPlan.make(config=AutofocusConfig(**estimator_settings("auto", True))).focus_bases(
        Bases.of_scan(scan, d["rb"], d["tb"], rg, d["tg"]),
        Reference(template=template_from_scan(d["template_scan"], rg, keep_phase=True)),
        d["truth"],
    )
    rec["physical"] = round(pt.metrics["target_ssim_corrected"], 4)
    return rec


def summary(records: list, key: str) -> dict:
    v = np.array([r[key] for r in records], float)
    return {
        "mean": round(float(v.mean()), 4),
        "sd": round(float(v.std(ddof=1)) if v.size > 1 else 0.0, 4),
        "worst": round(float(v.min()), 4),
        "n": int(v.size),
    }


#: what a result must reach to count as good (a flag on it is a false alarm) and below which a
#: trusted one is a false trust (the family bench's lines)
GOOD, POOR = 0.95, 0.90


def trust_errors(records: list, key: str) -> dict:
    """The confidence report's errors on the ``key`` results ("no rig" or "rig") of ``records``:
    trusted below ``POOR`` (false trust) and flagged at or above ``GOOD`` (false alarm)."""
    n = len(records)
    trusted = [r for r in records if r[f"{key} trusted"]]
    false_trust = sum(r[key] < POOR for r in trusted)
    false_alarm = sum(r[key] >= GOOD and not r[f"{key} trusted"] for r in records)
    return {
        "results": n,
        "trusted": len(trusted),
        "false_trust": false_trust,
        "false_alarm": false_alarm,
        "false_trust_rate": round(false_trust / max(n, 1), 4),
        "false_alarm_rate": round(false_alarm / max(n, 1), 4),
    }


KEYS = ("no rig", "rig", "physical", "no rig ceiling", "rig ceiling")
#: the summary's names of the conditions and columns (no spaces or dots: docs quote them by path)
NAMES = {
    "paper": "paper",
    "1 mm deeper": "deeper_1mm",
    "1.6 mm": "wrapped_1p6mm",
    "no rig": "no_rig",
    "rig": "rig",
    "physical": "physical",
    "no rig ceiling": "no_rig_ceiling",
    "rig ceiling": "rig_ceiling",
}


def summarise(res: dict) -> dict:
    """The result file's summary: per condition mean, sd, worst of every column of ``KEYS``; the
    confidence report's errors with and without the rig over every scan; the rig placements."""
    out: dict = {
        NAMES[cond]: {NAMES[key]: summary([s["scans"][cond] for s in res["sets"]], key) for key in KEYS}
        for cond in CONDITIONS
    }
    recs = [s["scans"][cond] for s in res["sets"] for cond in CONDITIONS]
    out["confidence"] = {NAMES[key]: trust_errors(recs, key) for key in ("no rig", "rig")}
    placed = [r["rig placement"] for r in recs if "rig placement" in r]
    moved = np.abs([p["moved_m"] for p in placed if p["placed"]] or [[0.0, 0.0]]) * 1e3
    out["rig_placement"] = {
        "scans": len(placed),
        "placed": sum(p["placed"] for p in placed),
        "moved_mm_median": [round(float(v), 2) for v in np.median(moved, axis=0)],
        "moved_mm_max": [round(float(v), 2) for v in moved.max(axis=0)],
    }
    return out


def table(res: dict) -> str:
    s = res["summary"]
    lines = [
        "| condition | digital twin, no rig | digital twin, rig | physical twin | ceiling (best over shifts), no rig | ceiling, rig |",
        "|---|---|---|---|---|---|",
    ]
    for cond in CONDITIONS:
        cell = {k: f"{v['mean']:.3f} +- {v['sd']:.3f} (worst {v['worst']:.3f})" for k, v in s[NAMES[cond]].items()}
        lines.append(
            f"| {cond} | {cell['no_rig']} | {cell['rig']} | {cell['physical']} | {cell['no_rig_ceiling']} | {cell['rig_ceiling']} |"
        )
    for key, c in s["confidence"].items():
        lines.append(
            f"\n{key}: {c['trusted']}/{c['results']} trusted, false trust {c['false_trust']} ({c['false_trust_rate']:.0%}), "
            f"false alarm {c['false_alarm']} ({c['false_alarm_rate']:.0%})"
        )
    return "\n".join(lines)


def main(
    out: str,
    draws: int,
    rows: int,
    size: int,
    calibration_rows: int = 65,
    truth_rig: bool = False,
    heldout: bool = False,
) -> dict:
    name = "rig" + ("_truth" if truth_rig else "") + ("_heldout" if heldout else "")
    path = Path(out) / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    first = HELDOUT_RIG_SEED if heldout else RIG_SEED
    res: dict = {
        "scan": {"positions": rows * 6, "pixels": size, "calibration_positions": calibration_rows * 6},
        "seeds": "held-out (never looked at while building)" if heldout else "build (looked at while building)",
        "sets": [],
    }
    from twinfocus.errors import TwinFocusError

    for k in range(draws):
        seed = first + 10 * k
        offset = draw_rig(seed)
        print(f"[rig bench] set {k}: camera offset {np.round(offset * 1e3, 2)} mm", file=sys.stderr, flush=True)
        refused = []
        # a refused calibration is what a user is told: scan the calibration object again (the
        # next paper-protocol draw of the set), up to three times
        for attempt in range(3):
            try:
                cal = calibrate(seed + 100 * attempt, offset, calibration_rows, size)
                break
            except TwinFocusError as exc:
                refused.append(str(exc))
                print(f"[rig bench] set {k}: calibration refused: {exc}", file=sys.stderr, flush=True)
        else:
            raise RuntimeError(f"set {k}: every calibration refused: {refused}")
        s = {"camera_offset_m": offset.tolist(), "calibration": {**cal, "refused_before": refused}, "scans": {}}
        for i, cond in enumerate(CONDITIONS):
            print(f"[rig bench] set {k}: {cond}", file=sys.stderr, flush=True)
            # --truth-rig: the exact offset instead of the measured one (what a perfect rig would give)
            rig_offset = -offset if truth_rig else np.asarray(cal["offset_m"])
            s["scans"][cond] = focus_set(cond, seed + 1 + i, offset, rig_offset, rows, size)
            r = s["scans"][cond]
            print(
                f"[rig bench]   no rig {r['no rig']} ({r['no rig trusted']}), rig {r['rig']} ({r['rig trusted']}), "
                f"physical {r['physical']}, placement {r.get('rig placement')}",
                file=sys.stderr,
                flush=True,
            )
        res["sets"].append(s)
        path.write_text(json.dumps(res, indent=1, default=float))
    res["summary"] = summarise(res)
    path.write_text(json.dumps(res, indent=1, default=float))
    print(table(res))
    return res


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--draws", type=int, default=2, help="sets of scans (one rig each)")
    ap.add_argument("--rows", type=int, default=33, help="scan rows of 6 columns (the paper: 130)")
    ap.add_argument("--size", type=int, default=48, help="pixels per side of each region (the paper: 100)")
    ap.add_argument("--calibration-rows", type=int, default=65, help="rows of the calibration's stage scan")
    ap.add_argument("--truth-rig", action="store_true", help="apply the exact offset (rig_truth.json): a perfect rig")
    ap.add_argument(
        "--heldout", action="store_true", help="the held-out sets (rig_heldout.json), never looked at while building"
    )
    ap.add_argument("--summarise", metavar="FILE", help="only (re)write FILE's summary from its records")
    ap.add_argument(
        "--calibrations",
        type=int,
        metavar="N",
        help="only calibrate: N rigs, each its error against its stated sd (rig_calibration[_heldout].json)",
    )
    a = ap.parse_args()
    if a.calibrations:
        calibration_study(a.out, a.calibrations, a.calibration_rows, a.size, a.heldout)
        sys.exit(0)
    if a.summarise:
        res = json.loads(Path(a.summarise).read_text())
        if "calibrations" in res:  # a --calibrations study
            res["summary"] = calibration_summary(res["calibrations"])
            Path(a.summarise).write_text(json.dumps(res, indent=1, default=float))
            print(json.dumps(res["summary"], indent=1))
            sys.exit(0)
        res["summary"] = summarise(res)
        Path(a.summarise).write_text(json.dumps(res, indent=1, default=float))
        print(table(res))
        sys.exit(0)
    main(a.out, a.draws, a.rows, a.size, a.calibration_rows, a.truth_rig, a.heldout)
