"""The drift's and the tilt's keep rule (:func:`twinfocus.focus.ladder.heldout_verdict`: kept when the
held-out gain is above its noise, half the spread of the two folds' gains) against stricter rules,
judged by the target's SSIM (against its image on the true positions) on hand-held draws.

    python -m benchmarks.bench_space_variant_keep --draws 20    (writes space_variant_keep.json)
    python -m benchmarks.bench_space_variant_keep --draws 12 --columns 4 --rows 60 --size 40 --no-scans \
        --name space_variant_keep_4x60.json                     (and 3 x 40 at 40 px, 4 x 60 at 32 px)
    python -m benchmarks.bench_space_variant_keep --rejudge benchmarks/results/space_variant_keep.json

The rules (:data:`RULES`): gain > k x noise + floor, and gain > a share of the unmatched share
beneath (the gain relative to what was left to gain); ``--rejudge`` judges them again on a
result file's draws without focusing anything. docs/notes/2026-12-02-space-variant-keep.md quotes it.

Draws: the hand-held scene of benchmarks/bench_handheld.py (letters H and S, a hand's 0.8 mm
drift and 0.15 deg rotation, 15 dB) at a small size (``--columns`` x ``--rows`` positions,
``--size`` pixels a side), on build seeds of this bench's own (``BUILD_SEED`` on; no bench lists
them as held out), and the two short zigzag hand scans of the paper's default scene that showed the
rule keeping a rung that lowers the target (``SCANS``). Each draw's bases are formed once and
focused, with ``twinfocus focus``'s settings, by:

* ``phase``, ``drift``, ``tilt``: ``--model RUNG`` (the rung forced, those beneath by their rules);
* ``auto``: the default, whose tilt rung decides (the drift rung leaves its fit to the tilt when
  the half-array bases are there), its held-out evidence recorded;
* ``beneath``: ``--space-variant off`` (auto's rules, no drift or tilt): what auto gives when the
  tilt is not kept;
* ``drift_auto``: auto's ladder with the tilt off (an array without half-array bases): the drift
  rung's own held-out evidence.

The rules are then judged offline: a rule keeping the tilt gives ``tilt``'s target, dropping it
``beneath``'s (the drift rung likewise with ``drift``); a rung not fitted (the scalar phase leaves
less than the fit's threshold unmatched) is dropped by every rule. Per rule: the mean and the
least target SSIM, the draws where it keeps a rung that lowers the target and those where it
drops one that raises it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks.common import write_result

#: the hand-held scene of benchmarks/bench_handheld.py (its default regions)
HAND: dict = dict(
    reference="H", target="S", separation_deg=16.3, snr_db=15, error_model="hand", error_sigma_m=(0.8e-3,) * 3
)
#: this bench's build seeds (no bench draws or holds out seeds from here)
BUILD_SEED = 4101
#: the short zigzag hand scans of the paper's default scene (``twinfocus simulate --trajectory zigzag
#: --error-model hand``) on which the rule kept a rung that lowered the target
SCANS = {
    "3x40 seed 12": dict(columns=3, rows=40, seed=12, size=40),
    "2x30 seed 2": dict(columns=2, rows=30, seed=2, size=32),
}
SCAN_ROIS = ((-0.15, 0.0, -0.11, 0.12, 0.6), (0.02, 0.13, -0.11, 0.12, 0.6))
#: the rules: key -> (k, floor, share): kept when gain > k * noise + floor and gain > share x the
#: unmatched share beneath (the gain relative to what was left to gain; ``noise_x1``: the default)
RULES = {
    "noise_x1": (1.0, 0.0, 0.0),
    "noise_x1_5": (1.5, 0.0, 0.0),
    "noise_x2": (2.0, 0.0, 0.0),
    "noise_x3": (3.0, 0.0, 0.0),
    "noise_plus_0_005": (1.0, 0.005, 0.0),
    "noise_plus_0_01": (1.0, 0.01, 0.0),
    "noise_and_share_0_1": (1.0, 0.0, 0.1),
    "noise_and_share_0_2": (1.0, 0.0, 0.2),
    "never": (np.inf, 0.0, 0.0),
}


def draw_inputs(kind: str, seed: int, columns: int, rows: int, size: int) -> dict:
    """One draw: ``scan``, ``template`` (the stage scan's, with its phase, on ``rg``), the grids
    ``rg`` / ``tg``, the bases (:class:`twinfocus.focus.pipeline.Bases`, with the half-array bases)
    and ``truth``. kind : "hand" (:data:`HAND`, its default regions) or a key of :data:`SCANS`."""
    from twinfocus.focus.pipeline import Bases, Truth
    from twinfocus.imaging.backprojection.numba_backend import subimage_basis
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario
    from twinfocus.twins.templates import template_from_scan

    if kind == "hand":
        sc = Scenario(**HAND, n_columns=columns, n_rows=rows, seed=seed)
        rg, tg = scenario_grids(sc, size)
    else:
        sc = Scenario(trajectory="zigzag", error_model="hand", n_columns=columns, n_rows=rows, seed=seed)
        rg, tg = (ImageGrid.from_roi(roi, size) for roi in SCAN_ROIS)
    scan, tpl_scan = simulate_scenario(sc)
    template = template_from_scan(tpl_scan, rg, keep_phase=True)
    rb = subimage_basis(scan.data, scan.positions, scan.chirp, rg)
    tb = subimage_basis(scan.data, scan.positions, scan.chirp, tg)
    return dict(
        scan=scan, template=template, bases=Bases.of_scan(scan, rb, tb, rg, tg), truth=Truth.of_scan(scan, rg, tg)
    )


def _plans(template) -> dict:
    """The plans each draw is focused with (module docstring), ``twinfocus focus``'s settings."""
    from twinfocus.focus.plan import FocusPlan, ladder_modes
    from twinfocus.focus.rungs import RUNGS, LadderSettings
    from twinfocus.focus.settings import default_settings

    settings = {**default_settings(), "device": "cpu"}
    plans = {
        m: FocusPlan.from_settings({**settings, "model": m}).for_reference(template, None)
        for m in ("phase", "drift", "tilt", "auto")
    }
    plans["beneath"] = FocusPlan.from_settings({**settings, "space_variant": "off"}).for_reference(template, None)
    modes = {**ladder_modes(), "tilt": "off"}
    ladder = LadderSettings("auto", "auto", "auto", modes)
    plans["drift_auto"] = replace(plans["auto"], rungs=tuple(RUNGS[n].made_for(m, ladder) for n, m in modes.items()))
    return plans


def _evidence(section: dict, rung: str) -> dict | None:
    """The rung's held-out evidence (gain, noise, folds' gains), or None when it was not fitted."""
    entry: dict = next((e for e in section["rungs"] if e["rung"] == rung), {})
    held = entry.get("evidence", {}).get("heldout")
    if held is None:
        return {"fitted": False, "why": entry.get("why")}
    return {
        "fitted": True,
        "gain": held["gain"],
        "noise": held["noise"],
        "gain_over_noise": held["gain"] / max(held["noise"], 1e-12),
        "kept": held["kept"],
        "folds": [{k: f[k] for k in ("gain", "unmatched_before", "unmatched_after", "pixels")} for f in held["folds"]],
    }


def one_draw(kind: str, seed: int, columns: int, rows: int, size: int) -> dict:
    """Every plan of :func:`_plans` on one draw: the target SSIMs and the two rungs' evidence."""
    from twinfocus.focus.pipeline import Reference

    t0 = time.perf_counter()
    d = draw_inputs(kind, seed, columns, rows, size)
    rec: dict = {"draw": kind, "seed": seed, "columns": columns, "rows": rows, "size": size, "target_ssim": {}}
    for name, plan in _plans(d["template"]).items():
        out = plan.focus_bases(d["bases"], Reference(template=d["template"]), d["truth"])
        m = out.metrics
        rec["target_ssim"][name] = m["target_ssim_corrected"]
        rec["target_ssim"]["uncorrected"] = m["target_ssim_uncorrected"]
        if name == "auto":
            rec["auto_result"] = m["model"]["result"]
            rec["tilt"] = _evidence(m["model"], "tilt")
        elif name == "drift_auto":
            rec["drift"] = _evidence(m["model"], "drift")
    rec["time_s"] = round(time.perf_counter() - t0, 1)
    return rec


def keeps(evidence: dict, k: float, floor: float, share: float = 0.0) -> bool:
    """Whether the rule gain > k * noise + floor and gain > share * unmatched beneath (the folds'
    mean ``unmatched_before``) keeps a rung of this ``evidence``."""
    if not evidence["fitted"]:
        return False
    beneath = float(np.mean([f["unmatched_before"] for f in evidence["folds"]]))
    return bool(evidence["gain"] > k * evidence["noise"] + floor and evidence["gain"] > share * beneath)


def judge(records: list[dict]) -> dict:
    """Per rung (drift, tilt) and rule of :data:`RULES`: the target SSIM each draw gets, their mean
    and least, and the draws where the rule keeps a rung that lowers the target / drops one that
    raises it. The check: the default rule's tilt gives auto's target on every draw."""
    out: dict = {}
    for rung in ("drift", "tilt"):
        out[rung] = {}
        for rule, (k, floor, share) in RULES.items():
            ssims, hurt, missed = [], [], []
            for r in records:
                with_rung, without = r["target_ssim"][rung], r["target_ssim"]["beneath"]
                kept = keeps(r[rung], k, floor, share)
                ssims.append(with_rung if kept else without)
                label = f"hand {r['seed']}" if r["draw"] == "hand" else r["draw"]
                if kept and with_rung < without:
                    hurt.append(label)
                if not kept and with_rung > without:
                    missed.append(label)
            out[rung][rule] = {
                "mean_target_ssim": round(float(np.mean(ssims)), 4),
                "least_target_ssim": round(float(np.min(ssims)), 4),
                "kept": sum(keeps(r[rung], k, floor, share) for r in records),
                "keeps_a_rung_that_lowers": len(hurt),
                "keeps_lowering": hurt,
                "drops_a_rung_that_raises": len(missed),
                "drops_raising": missed,
            }
    out["best_of_two_mean"] = {
        rung: round(float(np.mean([max(r["target_ssim"][rung], r["target_ssim"]["beneath"]) for r in records])), 4)
        for rung in ("drift", "tilt")
    }
    return out


def outcomes(records: list[dict]) -> dict:
    """Per rung: the draws it lowers and those it raises (against ``beneath``), each with the
    mean target SSIM beneath it, the mean change and the mean and least held-out gain over its
    noise (over the draws it was fitted on): whether the evidence tells the two apart."""
    out: dict = {}
    for rung in ("drift", "tilt"):
        out[rung] = {}
        for side, sign in (("lowers", -1.0), ("raises", 1.0)):
            rs = [r for r in records if sign * (r["target_ssim"][rung] - r["target_ssim"]["beneath"]) > 0]
            ratios = [r[rung]["gain_over_noise"] for r in rs if r[rung]["fitted"]]
            out[rung][side] = {
                "draws": len(rs),
                "mean_beneath_ssim": round(float(np.mean([r["target_ssim"]["beneath"] for r in rs])), 4)
                if rs
                else None,
                "mean_change": round(
                    float(np.mean([r["target_ssim"][rung] - r["target_ssim"]["beneath"] for r in rs])), 4
                )
                if rs
                else None,
                "mean_gain_over_noise": round(float(np.mean(ratios)), 2) if ratios else None,
                "least_gain_over_noise": round(float(np.min(ratios)), 2) if ratios else None,
            }
    return out


def judged(doc: dict) -> dict:
    """``doc`` (a result with its ``draws``) with the rules judged on them: ``summary`` (all the
    draws), ``summary_hand_draws``, ``outcomes`` and the check ``default_rule_matches_auto`` (the
    default rule's tilt is auto's own rule: its judged targets must be auto's)."""
    records = doc["draws"]
    return {
        **doc,
        # the short scans among the draws (a file written with --no-scans has none)
        "scans": {k: v for k, v in doc.get("scans", {}).items() if any(r["draw"] == k for r in records)},
        "rules": {
            n: {"k": k if np.isfinite(k) else None, "floor": floor, "share": share}
            for n, (k, floor, share) in RULES.items()
        },
        "summary": judge(records),
        "summary_hand_draws": judge([r for r in records if r["draw"] == "hand"]),
        "outcomes": outcomes(records),
        "default_rule_matches_auto": all(
            abs(
                (r["target_ssim"]["tilt"] if keeps(r["tilt"], 1.0, 0.0) else r["target_ssim"]["beneath"])
                - r["target_ssim"]["auto"]
            )
            < 1e-9
            for r in records
        ),
    }


def table(summary: dict) -> str:
    """A markdown table of :func:`judge`'s summary."""
    lines = [
        "| rung | rule | kept | mean SSIM | least SSIM | keeps lowering | drops raising |",
        "|---|---|---|---|---|---|---|",
    ]
    for rung in ("drift", "tilt"):
        for rule, s in summary[rung].items():
            lines.append(
                f"| {rung} | {rule} | {s['kept']} | {s['mean_target_ssim']:.4f} | {s['least_target_ssim']:.4f} | "
                f"{s['keeps_a_rung_that_lowers']} | {s['drops_a_rung_that_raises']} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--draws", type=int, default=10)
    ap.add_argument("--columns", type=int, default=3)
    ap.add_argument("--rows", type=int, default=40)
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--no-scans", action="store_true", help="leave the two short scans (SCANS) out")
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--name", default="space_variant_keep.json", help="the result file's name in --out")
    ap.add_argument("--rejudge", metavar="FILE", help="judge the rules again on FILE's draws (no focusing)")
    a = ap.parse_args(argv)
    if a.rejudge:
        doc = judged(json.loads(Path(a.rejudge).read_text()))
        write_result(Path(a.rejudge).parent, Path(a.rejudge).name, doc)
        print(table(doc["summary"]))
        return doc
    load = [round(v, 2) for v in os.getloadavg()]
    jobs = [("hand", BUILD_SEED + i, a.columns, a.rows, a.size) for i in range(a.draws)]
    if not a.no_scans:
        jobs += [(name, s["seed"], s["columns"], s["rows"], s["size"]) for name, s in SCANS.items()]
    records = []
    for job in jobs:
        print(f"[space_variant_keep] {job[0]} seed {job[1]}", file=sys.stderr, flush=True)
        records.append(one_draw(*job))
        r = records[-1]
        print(
            {"seed": r["seed"], **{k: round(v, 3) for k, v in r["target_ssim"].items()}, "t": r["time_s"]},
            file=sys.stderr,
        )
    argv_text = " ".join(sys.argv[1:]) if argv is None else " ".join(argv)
    doc = judged(
        {
            "command": f"python -m benchmarks.bench_space_variant_keep {argv_text}".strip(),
            "scene": {**HAND, "columns": a.columns, "rows": a.rows, "size": a.size, "seeds_from": BUILD_SEED},
            "scans": SCANS,
            "load_average_before": load,
            "load_average_after": [round(v, 2) for v in os.getloadavg()],
            "cpu_count": os.cpu_count(),
            "draws": records,
        }
    )
    write_result(a.out, a.name, doc)
    print(table(doc["summary"]))
    return doc


if __name__ == "__main__":
    main()
