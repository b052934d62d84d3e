"""The digital twin and the physical twin on a wide family of field scenes, and how far the
confidence report can be believed on them.

Every draw takes at random (from its own seed): the reference's shape and the target's (letters
with holes and without, 'O' a ring; plates and tools of a letter's size: a plate, a washer, a
wrench, a disc, a key), their separation (9-12 degrees; 16.3 under a hand's drift), the
reference's surface (a third each: smooth, as a plate or a letter cut from sheet metal, every
scatterer in phase; rough, each scatterer its own phase within +-90 degrees; speckled, each its
own phase anywhere on the circle; strengths +-30 % on all three) and a camera cloud as it comes
(1 mm noise, 25 % of the surface missing in patches, 2 % outliers, an offset of 2-3 mm in a random
direction). Conditions:

  paper: 0.5 mm z + 0.2 mm x/y tracking error, 15 dB;
  1 mm deeper: 1 mm z + 0.3 mm x/y, 10 dB, the target 10 cm deeper than the reference;
  1.6 mm: 1.6 mm z (every phase wraps) + 0.3 mm x/y, 15 dB;
  hand: a hand's drift, 0.8 mm per axis, and 0.15 degrees of array rotation, 15 dB.

Bench draws (seeds 1001 on, shapes of ``BENCH_SHAPES``) are what thresholds are chosen on;
held-out draws (seeds 2001 on, shapes of ``HELDOUT_SHAPES``, none shared) only check them.
Scans are smaller than the paper's 780 positions x 100 x 100 pixels: ``--rows`` (default 65 rows
of 6 columns, 390 positions) and ``--size`` (default 64 x 64 pixels per region).

Per draw, target SSIM against the image on the true positions: the digital twin as
``twinfocus focus --digital-twin`` runs it, the physical twin (its motion-stage scan, the
registered closed form and the drift fit where it helps), the reference's own true phase (one
phase per position) and the target's (the oracle); each twin's confidence report (trusted, its
warnings) and what it measured; and the field's reference-free autofocus on the target itself
(``--method sharpness``, ``entropy``, ``pga``), the baselines a twin has to beat, with their
confidence reports.

    python -m benchmarks.bench_dtwin_family --draws 30                         (bench draws, ~15 min)
    python -m benchmarks.bench_dtwin_family --draws 10 --heldout               (held-out draws)
    python -m benchmarks.bench_dtwin_family --draws 30 --resume                (more draws, added)
    python -m benchmarks.bench_dtwin_family --add-baselines [--heldout]     (baselines only, added)
    python -m benchmarks.bench_dtwin_family --add-defocus [--heldout]       (the target's focus check, added)
    python -m benchmarks.bench_dtwin_family --add-placement [--heldout]     (where the digital twin put the target, added)
    python -m benchmarks.bench_dtwin_family --add-cloud-parts 8 [--heldout] (the camera cloud's impairments one by one, added
                                                                            on the first 8 draws of each condition)
    python -m benchmarks.bench_dtwin_family --defocus-figure docs/figures/target_defocus.png
    python -m benchmarks.bench_dtwin_family --trust-summary     (the report's false trusts and alarms
                                                                 over both files: dtwin_family_trust.json)

(--minutes: no new seed is started after that long; the draws of every condition go seed by seed.)

Writes ``dtwin_family.json`` (``dtwin_family_heldout.json``) and prints the table of each twin per
condition (mean +- sd, worst) and the confidence report's false trust (trusted, below 0.90) and
false alarms (flagged, at or above 0.95).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

CONDITIONS = {
    "paper": dict(error_sigma_m=(0.2e-3, 0.2e-3, 0.5e-3), snr_db=15),
    "1 mm deeper": dict(error_sigma_m=(0.3e-3, 0.3e-3, 1.0e-3), snr_db=10, target_depth_offset_m=0.1),
    "1.6 mm": dict(error_sigma_m=(0.3e-3, 0.3e-3, 1.6e-3), snr_db=15),
    "hand": dict(error_model="hand", error_sigma_m=(0.8e-3,) * 3, snr_db=15, separation_deg=16.3),
}
#: the references' and targets' shapes: letters with holes (A, B, O: a ring, R, P, D, Q) and
#: without, plates and tools (twinfocus.scene.tools: a plate, a washer, a wrench; a disc, a key)
BENCH_SHAPES = (*"ABOFHTE", "plate", "washer", "wrench")
HELDOUT_SHAPES = (*"DPRQLKX", "disc", "key")
#: the bench's and the held-out draws' first seeds
BENCH_SEED, HELDOUT_SEED = 1001, 2001
#: the camera cloud's impairments: noise m, hole fraction, outlier fraction; its offset is drawn
CLOUD = (1e-3, 0.25, 0.02)
OFFSET_RANGE_M = (2e-3, 3e-3)
#: what a result must reach to count as good (a flag on it is a false alarm) and below which a
#: trusted one is a false trust
GOOD, POOR = 0.95, 0.90


#: the reference's surface: the Scenario's roughness (twinfocus.scene.scatterers.rough_amplitudes:
#: each scatterer's phase uniform within +-that many degrees; None: the scene's speckle, a phase
#: uniform over the whole circle)
SURFACES = {"smooth": 0.0, "rough": 90.0, "speckled": None}


def family_scenario(condition: str, seed: int, shapes: tuple, rows: int, surface: str | None = None) -> dict:
    """The Scenario keywords of one draw of ``condition``: shapes, separation and (unless
    ``surface`` is given, a key of ``SURFACES``) the reference's surface from ``seed``."""
    rng = np.random.default_rng([seed, 31])
    ref, tgt = rng.choice(list(shapes), 2, replace=False)
    separation = float(rng.uniform(9.0, 12.0))
    drawn = list(SURFACES)[min(int(rng.random() * len(SURFACES)), len(SURFACES) - 1)]
    surface = drawn if surface is None else surface
    if surface not in SURFACES:
        raise ValueError(f"surface must be one of {', '.join(SURFACES)}, got {surface!r}")
    kw = dict(
        reference=str(ref),
        target=str(tgt),
        separation_deg=separation,
        reference_roughness_deg=SURFACES[surface],
        reference_amplitude_spread=0.3,
        n_rows=rows,
        seed=seed,
    )
    return {**kw, **CONDITIONS[condition]}


def surface_of(kw: dict) -> str:
    """The name in ``SURFACES`` of a draw's Scenario keywords ``kw``."""
    return next(name for name, deg in SURFACES.items() if deg == kw["reference_roughness_deg"])


def draw_inputs(condition: str, seed: int, shapes: tuple, rows: int, size: int, surface: str | None = None) -> dict:
    """One draw's scan and what the digital twin is given: ``kw`` (its Scenario keywords),
    ``scan``, ``template_scan`` (the motion-stage scan), grids ``rg``/``tg``, ``twin`` (from the
    camera cloud as it comes), bases ``rb``/``tb``, ``truth`` (the :class:`~twinfocus.focus.pipeline.Truth` focus_bases is given) and
    ``upper_band`` (the reference's upper-band basis) and ``reference_points`` (its exact surface,
    float (N, 3) metres, what the camera cloud was made from)."""
    from twinfocus.focus.pipeline import Truth, upper_band_basis
    from twinfocus.imaging.backprojection.numba_backend import subimage_basis
    from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario
    from twinfocus.twins.digital_twin.camera_cloud import camera_cloud
    from twinfocus.twins.digital_twin.condition import digital_twin_reference

    kw = family_scenario(condition, seed, shapes, rows, surface)
    sc = Scenario(**kw)
    scan, tpl_scan = simulate_scenario(sc)
    rg, tg = scenario_grids(sc, size)
    rng = np.random.default_rng([seed, 14])
    surface = sc.scene().object("reference").surface_points(1e-3)
    cloud = camera_cloud(surface, *CLOUD, float(rng.uniform(*OFFSET_RANGE_M)), rng=rng)
    truth = Truth.of_scan(scan, rg, tg)
    return dict(
        kw=kw,
        scan=scan,
        template_scan=tpl_scan,
        rg=rg,
        tg=tg,
        twin=digital_twin_reference(cloud, scan.positions, scan.chirp, rg),
        rb=subimage_basis(scan.data, scan.positions, scan.chirp, rg),
        tb=subimage_basis(scan.data, scan.positions, scan.chirp, tg),
        truth=truth,
        upper_band=upper_band_basis(scan.data, scan.positions, scan.chirp, rg),
        reference_points=surface,
    )


def digital_twin_focus(d: dict, **config):
    """What `twinfocus focus --digital-twin CLOUD` runs on :func:`draw_inputs`' draw ``d``;
    ``config``: AutofocusConfig fields over the defaults."""
    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.estimators import estimator_settings
    from twinfocus.focus.pipeline import Bases, Reference
    from twinfocus.focus.plan import FocusPlan

    twin, scan = d["twin"], d["scan"]
    cfg = AutofocusConfig(**{**estimator_settings("auto", False, has_support=True), **config})
    return FocusPlan.make(config=cfg).focus_bases(
        Bases(d["rb"], d["tb"], scan.positions, scan.chirp, d["rg"], d["tg"], upper_band=d["upper_band"]),
        Reference(template=twin.template, support=twin.support, info=twin.info),
        d["truth"],
    )


def one_draw(condition: str, seed: int, shapes: tuple, rows: int, size: int) -> dict:
    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.drift_check import step_coherence
    from twinfocus.focus.estimators import estimator_settings
    from twinfocus.focus.outline_fill import outline_fill
    from twinfocus.focus.pipeline import Bases, Reference
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.imaging.basis import form_image
    from twinfocus.imaging.metrics import image_ssim, oracle_phase
    from twinfocus.twins.templates import template_from_scan

    d = draw_inputs(condition, seed, shapes, rows, size)
    kw, scan, tpl_scan, rg, tg, twin, rb, tb, truth = (
        d[k] for k in ("kw", "scan", "template_scan", "rg", "tg", "twin", "rb", "tb", "truth")
    )
    rec: dict = {
        "seed": seed,
        "reference": kw["reference"],
        "target": kw["target"],
        "surface": surface_of(kw),
        "separation_deg": round(kw["separation_deg"], 2),
    }
    dt = digital_twin_focus(d)
    # what `twinfocus focus --template-scan` runs
    pt = FocusPlan.make(config=AutofocusConfig(**estimator_settings("auto", True))).focus_bases(
        Bases.of_scan(scan, rb, tb, rg, tg),
        Reference(template=template_from_scan(tpl_scan, rg, keep_phase=True)),
        truth,
    )
    for name, out in (("digital", dt), ("physical", pt)):
        m, conf = out.metrics, out.metrics["confidence"]
        rec[name] = m["target_ssim_corrected"]
        rec[f"{name} trusted"] = conf["trusted"]
        rec[f"{name} warnings"] = conf["warnings"]
        rec[f"{name} confidence"] = {k: v for k, v in conf.items() if k not in ("warnings", "trusted")}
        rec[f"{name} time_s"] = out.timings_s["autofocus"] + out.timings_s.get("space_variant", 0.0)
        rec[f"{name} step_coherence"] = round(step_coherence(out.phase_rad), 4)
    # how the references on the true positions and the physical twin's fill the outline (what the
    # digital twin's is read against)
    rec["digital outline"] = dt.metrics["reference_outline"]
    rec["digital placement"] = placement(d, dt)
    rec["physical outline"] = outline_fill(pt.reference, twin.support)
    rec["truth outline"] = outline_fill(truth.reference, twin.support)
    rec["uncorrected"] = dt.metrics["target_ssim_uncorrected"]
    rec["oracle"] = dt.metrics["target_ssim_oracle_phase"]
    reference_true = oracle_phase(scan.positions_true, scan.positions, rg.centre_m, scan.chirp)
    rec["reference true phase"] = image_ssim(form_image(tb, reference_true), truth.target)
    rec.update(baselines(d))
    return rec


#: the sub-pixel shifts :func:`placement` tries on the target: +-3 px across y, +-2 px across x
#: (the estimate's misplacement lies across y, the axis one radar position does not resolve), 0.25 px apart
BEST_SHIFT_PX = (np.arange(-3.0, 3.01, 0.25), np.arange(-2.0, 2.01, 0.25))


def placement(d: dict, out) -> dict:
    """Where the digital twin put the target of :func:`draw_inputs`' draw ``d`` (``out``: its
    FocusOutputs), against the truth: ``error_mm`` (x, y), the image shift that the constant +
    linear part of its phase less the reference's true phase stands for; ``best_shift_ssim``, the
    target's SSIM once moved by the sub-pixel shift of ``BEST_SHIFT_PX`` that suits it best
    (``best_shift_px``, (dy, dx)): its focus apart from its place; and the estimate's
    ``phase_coherence_sqrt_m``, what the confidence report reads the wrapping from."""
    from twinfocus.focus.phase_ramp import fit_linear_phase
    from twinfocus.imaging.metrics import image_ssim, oracle_phase
    from twinfocus.imaging.subpixel import shift_image

    scan, rg, truth = d["scan"], d["rg"], d["truth"].target
    centres = scan.positions.mean(axis=1)
    true = oracle_phase(scan.positions_true, scan.positions, rg.centre_m, scan.chirp)
    _, coeffs = fit_linear_phase(
        np.angle(np.exp(1j * (out.phase_rad - true))), centres[:, :2], min_coherence_sqrt_m=0.0
    )
    # a ramp b across the aperture moves the image by b R / k (twinfocus.focus.autofocus.transfer_phase)
    error_m = coeffs[1:] * float(rg.z - centres[:, 2].mean()) * scan.chirp.wavelength_m / (4.0 * np.pi)
    scores = {
        (dy, dx): image_ssim(shift_image(out.target, dy, dx), truth)
        for dy in BEST_SHIFT_PX[0]
        for dx in BEST_SHIFT_PX[1]
    }
    best = max(scores, key=scores.get)
    return {
        "error_mm": [round(float(v) * 1e3, 2) for v in error_m],
        "best_shift_ssim": round(scores[best], 4),
        "best_shift_px": [float(best[0]), float(best[1])],
        "phase_coherence_sqrt_m": out.metrics["estimator"].get("phase_coherence_sqrt_m"),
    }


#: the field's reference-free autofocus, run on the target itself as ``twinfocus focus --method``
#: runs it: the baselines beside the twins
BASELINES = ("sharpness", "entropy", "pga")


#: what :func:`cloud_parts` gives the digital twin instead of the camera cloud as it comes: each
#: impairment of ``CLOUD`` and ``OFFSET_RANGE_M`` alone, all of them but the holes, and two views
#: (two clouds with their own noise, holes and outliers, one rig offset, joined)
CLOUD_PARTS = ("exact", "noise only", "holes only", "offset only", "all but holes", "two views")


def cloud_parts(d: dict) -> dict:
    """The digital twin's target SSIM on :func:`draw_inputs`' draw ``d`` with each cloud of
    ``CLOUD_PARTS`` in place of the one the draw's camera gave: which impairment costs what. The
    offset is drawn anew (a length in ``OFFSET_RANGE_M``, a direction of its own); "two views" holds each point of the
    surface seen twice, so its holes are where both views lost the surface (a camera's holes from
    specular spots move with the view; those from a texture-less surface would not)."""
    from twinfocus.twins.digital_twin.camera_cloud import camera_cloud
    from twinfocus.twins.digital_twin.condition import digital_twin_reference

    seed, scan, rg, surface = d["kw"]["seed"], d["scan"], d["rg"], d["reference_points"]
    rng = np.random.default_rng([seed, 14, 1])
    direction = rng.normal(size=3)
    offset = float(rng.uniform(*OFFSET_RANGE_M)) * direction / np.linalg.norm(direction)
    noise, holes, outliers = CLOUD
    clouds = {
        "exact": (0.0, 0.0, 0.0, 0.0),
        "noise only": (noise, 0.0, 0.0, 0.0),
        "holes only": (0.0, holes, 0.0, 0.0),
        "offset only": (0.0, 0.0, 0.0, offset),
        "all but holes": (noise, 0.0, outliers, offset),
    }
    out = {}
    for name in CLOUD_PARTS:
        if name == "two views":
            cloud = np.vstack([camera_cloud(surface, *CLOUD, offset, rng=rng) for _ in range(2)])
        else:
            cloud = camera_cloud(surface, *clouds[name], rng=rng)
        twin = digital_twin_reference(cloud, scan.positions, scan.chirp, rg)
        out[name] = round(float(digital_twin_focus({**d, "twin": twin}).metrics["target_ssim_corrected"]), 4)
    return out


def baselines(d: dict) -> dict:
    """The reference-free methods on :func:`draw_inputs`' draw ``d``: each one's target SSIM
    (``sharpness``, ...), whether the confidence report trusts it and its warnings."""
    from twinfocus.focus.pipeline import Bases, Reference
    from twinfocus.focus.plan import FocusPlan

    out: dict = {}
    scan = d["scan"]
    for method in BASELINES:
        f = FocusPlan.make(method=method).focus_bases(
            Bases(d["rb"], d["tb"], scan.positions, scan.chirp, d["rg"], d["tg"]),
            Reference(),
            d["truth"],
        )
        out[method] = f.metrics["target_ssim_corrected"]
        out[f"{method} trusted"] = f.metrics["confidence"]["trusted"]
        out[f"{method} warnings"] = f.metrics["confidence"]["warnings"]
    return out


#: the digital twin's own warnings (twinfocus.focus.pipeline.outline_warnings), which ``trusted`` applies
#: anew from each record's measurements, so that records of an earlier run are read by the present rules
OWN_WARNINGS = (
    "matches its template poorly",
    "does not fill its outline",
    "not sure of the reference's phase",
    "the tracking drifted",
    "to a few radar positions",
    "not at its focus",
    "phases have wrapped",
)


def defocus_gain(rec: dict) -> float | None:
    """The digital twin's ``target_defocus_gain_nats`` of a record: from its confidence report, or
    from ``--add-defocus`` for records made before the check; None where not measured."""
    return rec["digital confidence"].get(
        "target_defocus_gain_nats", (rec.get("digital target_defocus") or {}).get("entropy_gain_nats")
    )


def trusted(rec: dict, twin: str, target_focus: bool = True) -> bool:
    """Whether the confidence report trusts this record's ``twin`` result, by the report's present
    rules: the drift check (``twinfocus.focus.pipeline.drift_warnings``) and, for the digital twin, its own
    checks (``outline_warnings``: the reference's energy contrast over its outline unless the scan
    read it as speckled, the glint across the positions, the grown outlines' agreement, the
    target's own focus where the record measured it, the wrapping of its phases where the record
    kept their coherence) applied anew to the record's measurements,
    the report's other warnings as recorded."""
    from twinfocus.focus.pipeline import (
        MAX_TARGET_DEFOCUS_GAIN_NATS,
        drift_warnings,
        outline_warnings,
        placement_warnings,
    )

    digital = twin == "digital"
    conf = rec[f"{twin} confidence"]
    others = [w for w in rec[f"{twin} warnings"] if not any(k in w for k in OWN_WARNINGS)]
    # (records before the concentration was measured: None, the drift judged by its steps alone)
    own = drift_warnings(
        rec[f"{twin} step_coherence"], conf.get("phase_concentration"), digital, conf["separation_deg"]
    )
    if digital:
        fill = conf.get("reference_outline") or rec["digital outline"]
        own += outline_warnings(fill, conf.get("outline_agreement"))
        coherence = conf.get(
            "phase_coherence_sqrt_m", (rec.get("digital placement") or {}).get("phase_coherence_sqrt_m")
        )
        if coherence is None:  # a record from before the coherence was kept: its wrapping warning as recorded
            own += [w for w in rec["digital warnings"] if "phases have wrapped" in w]
        else:
            halves = conf.get("placement_by_band_halves") or {}
            own += placement_warnings(coherence, halves.get("ramp_coherence_sqrt_m"), bool(halves.get("removed")))
        gain = defocus_gain(rec) if target_focus else None
        if gain is not None and gain > MAX_TARGET_DEFOCUS_GAIN_NATS:
            own.append("the corrected target is not at its focus")
    return not others and not own


def table(results: dict) -> str:
    """Markdown: each twin per condition (mean +- sd, worst; draws the tool refused counted apart)
    and the confidence report's errors over every scored draw."""
    cols = ("digital", "physical", "reference true phase", "oracle")
    lines = [
        "| condition | draws | refused | digital twin | physical twin | reference's true phase | target's own phase |",
        "|---|---|---|---|---|---|---|",
    ]
    for cond, recs in results.items():
        scored = [r for r in recs if "refused" not in r]
        cells = [np.array([r[c] for r in scored]) for c in cols]
        lines.append(
            f"| {cond} | {len(scored)} | {len(recs) - len(scored)} | "
            + " | ".join(f"{v.mean():.3f} ± {v.std():.3f} (worst {v.min():.3f})" for v in cells)
            + " |"
        )
    lines += [
        "",
        "| condition | " + " | ".join(f"digital twin, {s} references" for s in SURFACES) + " |",
        "|---|" + "---|" * len(SURFACES),
    ]
    for cond, recs in results.items():
        cells = []
        for surface in SURFACES:
            v = np.array([r["digital"] for r in recs if "refused" not in r and r.get("surface") == surface])
            cells.append(f"{v.mean():.3f} ({len(v)} draws, worst {v.min():.3f})" if len(v) else "no draws")
        lines.append(f"| {cond} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "| condition | digital twin | " + " | ".join(f"`--method {m}`" for m in BASELINES) + " |",
        "|---|---|" + "---|" * len(BASELINES),
    ]
    for cond, recs in results.items():
        scored = [r for r in recs if "refused" not in r and all(m in r for m in BASELINES)]
        if not scored:
            continue
        cells = [np.array([r[c] for r in scored]) for c in ("digital", *BASELINES)]
        lines.append(
            f"| {cond} | " + " | ".join(f"{v.mean():.3f} ± {v.std():.3f} (worst {v.min():.3f})" for v in cells) + " |"
        )
    placed = {cond: [r for r in recs if "digital placement" in r] for cond, recs in results.items()}
    if any(placed.values()):
        lines += [
            "",
            "| condition | draws | digital twin | moved by its best shift: its focus "
            "| the target's place across y, off by (mm): median, 90th percentile, worst | across x |",
            "|---|---|---|---|---|---|",
        ]
        for cond, recs in placed.items():
            if not recs:
                continue
            ssim = np.array([r["digital"] for r in recs])
            moved = np.array([r["digital placement"]["best_shift_ssim"] for r in recs])
            off = np.abs(np.array([r["digital placement"]["error_mm"] for r in recs]))
            lines.append(
                f"| {cond} | {len(recs)} | {ssim.mean():.3f} | {moved.mean():.3f} | "
                + " | ".join(
                    f"{np.median(o):.1f}, {np.percentile(o, 90):.1f}, {o.max():.1f}" for o in (off[:, 1], off[:, 0])
                )
                + " |"
            )
    parted = {cond: [r for r in recs if "digital cloud parts" in r] for cond, recs in results.items()}
    if any(parted.values()):
        lines += [
            "",
            "| condition | draws | the cloud as it comes | " + " | ".join(CLOUD_PARTS) + " |",
            "|---|---|---|" + "---|" * len(CLOUD_PARTS),
        ]
        for cond, recs in parted.items():
            if not recs:
                continue
            cells = [np.array([r["digital"] for r in recs])]
            cells += [np.array([r["digital cloud parts"][k] for r in recs]) for k in CLOUD_PARTS]
            lines.append(
                f"| {cond} | {len(recs)} | " + " | ".join(f"{v.mean():.3f} (worst {v.min():.3f})" for v in cells) + " |"
            )
    lines += [
        "",
        "| twin | results | trusted (their worst) | trusted below 0.90 (false trust) | flagged at or above 0.95 (false alarm) |",
        "|---|---|---|---|---|",
    ]
    for r in trust_rows(results):
        worst = f" ({r['trusted_worst']:.3f})" if r["trusted"] else ""
        lines.append(
            f"| {r['twin']} | {r['results']} | {r['trusted']}{worst} | {r['false_trust']} ({r['false_trust_share']:.0%}) "
            f"| {r['false_alarm']} ({r['false_alarm_share']:.0%}) |"
        )
    return "\n".join(lines)


def trust_rows(results: dict) -> list[dict]:
    """Per twin and baseline over every scored record of ``results`` ({condition: [record]}): how many
    results, how many the confidence report trusts by its present rules (:func:`trusted`) and the
    worst of them, the false trusts (trusted, below ``POOR``) and the false alarms (flagged, at or
    above ``GOOD``)."""
    recs = [r for rs in results.values() if isinstance(rs, list) for r in rs if "refused" not in r]
    rows = []
    for twin in ("digital", "physical", *BASELINES):
        rs = [r for r in recs if twin in r]
        if not rs:
            continue

        def trust(r: dict, twin: str = twin) -> bool:
            return bool(r[f"{twin} trusted"]) if twin in BASELINES else trusted(r, twin)

        kept = [r[twin] for r in rs if trust(r)]
        poor = sum(r[twin] < POOR and trust(r) for r in rs)
        alarm = sum(r[twin] >= GOOD and not trust(r) for r in rs)
        rows.append(
            {
                "twin": twin,
                "results": len(rs),
                "trusted": len(kept),
                "trusted_worst": min(kept) if kept else None,
                "false_trust": poor,
                "false_trust_share": poor / len(rs),
                "false_alarm": alarm,
                "false_alarm_share": alarm / len(rs),
            }
        )
    return rows


def trust_summary(results_dir: str | os.PathLike = "benchmarks/results") -> Path:
    """Write ``dtwin_family_trust.json`` beside the two record files of ``results_dir``: their
    :func:`trust_rows` (``{"bench": [...], "held out": [...]}``, and per set both twins' false
    trusts and alarms together, in % too), the confidence report's present rules applied to the
    records as they are (no draw is run). Returns its path."""
    out = Path(results_dir)
    files = {"bench": "dtwin_family.json", "held out": "dtwin_family_heldout.json"}
    summary: dict = {name: trust_rows(json.loads((out / f).read_text())) for name, f in files.items()}
    for name in files:  # both twins together, shares in %
        twins = [r for r in summary[name] if r["twin"] in ("digital", "physical")]
        n = sum(r["results"] for r in twins)
        both = {k: sum(r[k] for r in twins) for k in ("false_trust", "false_alarm")}
        summary[f"{name}, both twins"] = {"results": n, **both, **{f"{k}_pct": 100 * v / n for k, v in both.items()}}
    path = out / "dtwin_family_trust.json"
    path.write_text(json.dumps(summary, indent=1) + "\n")
    return path


def defocus_figure(path: str | os.PathLike, results_dir: str | os.PathLike = "benchmarks/results") -> None:
    """A picture of the target's focus check: for each digital-twin result that the report's other
    checks trust, its target SSIM against the entropy a quadratic still takes off the target
    (``target_defocus_gain_nats``), bench and held-out draws, with the threshold and the false
    trust and false alarm lines."""
    from twinfocus.focus.pipeline import MAX_TARGET_DEFOCUS_GAIN_NATS
    from twinfocus.io.png import pyplot

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.2, 3.6))
    for name, marker, colour in (
        ("dtwin_family.json", "o", "tab:blue"),
        ("dtwin_family_heldout.json", "^", "tab:orange"),
    ):
        results = json.loads((Path(results_dir) / name).read_text())
        results.pop("scan", None)
        points = []
        for rec in (r for rs in results.values() for r in rs if "refused" not in r):
            gain = defocus_gain(rec)
            if gain is not None and trusted(rec, "digital", target_focus=False):
                points.append((rec["digital"], gain))
        x, y = np.array(points).T
        label = "bench draws" if "heldout" not in name else "held-out draws"
        ax.plot(x, y, marker, color=colour, ms=5, alpha=0.8, label=f"{label} ({len(points)})")
    ax.axhline(MAX_TARGET_DEFOCUS_GAIN_NATS, color="tab:red", lw=1, label="flagged above")
    ax.axvspan(0.0, POOR, color="tab:red", alpha=0.06)
    ax.axvline(GOOD, color="tab:green", lw=1, ls="--")
    ax.set_xlim(0.45, 1.0)
    ax.set_xlabel("target SSIM (below 0.90 shaded: trusting it is a false trust)", fontsize=8)
    ax.set_ylabel("entropy a quadratic still takes off (nats)", fontsize=8)
    ax.set_title("digital twin: results the other checks trust", fontsize=9)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _wants(rec: dict, defocus: bool, placement_: bool, baselines_: bool, parts: bool = False) -> bool:
    """Whether an earlier record lacks what an ``--add-*`` pass adds: the target's focus check (on
    the digital-twin results the other checks trust: where it can change the verdict), the
    digital twin's placement (every result), the baselines, the cloud's parts."""
    if parts:
        return "digital cloud parts" not in rec
    if baselines_:
        return not all(m in rec for m in BASELINES)
    if placement_:
        return "digital placement" not in rec
    return (
        "target_defocus_gain_nats" not in rec["digital confidence"]
        and "digital target_defocus" not in rec
        and trusted(rec, "digital")
    )


def main(
    out_dir: str | os.PathLike = "benchmarks/results",
    draws: int = 3,
    heldout: bool = False,
    rows: int = 65,
    size: int = 64,
    only: str | None = None,
    minutes: float | None = None,
    resume: bool = False,
    add_baselines: bool = False,
    add_defocus: bool = False,
    add_placement: bool = False,
    add_cloud_parts: int = 0,
) -> dict:
    from twinfocus.errors import TwinFocusError

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / ("dtwin_family_heldout.json" if heldout else "dtwin_family.json")
    first, shapes = (HELDOUT_SEED, HELDOUT_SHAPES) if heldout else (BENCH_SEED, BENCH_SHAPES)
    adding = add_baselines or add_defocus or add_placement or add_cloud_parts > 0
    results: dict = json.loads(path.read_text()) if (only or resume or adding) and path.is_file() else {}
    results.pop("scan", None)
    if adding:
        # the same seeds draw the same scans: only what is added is measured, the records kept
        for cond, recs in results.items():
            for rec in recs:
                if add_cloud_parts and rec["seed"] >= first + add_cloud_parts:
                    continue
                if "refused" in rec or not _wants(rec, add_defocus, add_placement, add_baselines, add_cloud_parts > 0):
                    continue
                print(f"[dtwin family] adding: {cond}, seed {rec['seed']}", file=sys.stderr, flush=True)
                d = draw_inputs(cond, rec["seed"], shapes, rows, size)
                if add_cloud_parts:
                    rec["digital cloud parts"] = cloud_parts(d)
                elif add_baselines:
                    rec.update(baselines(d))
                else:
                    out = digital_twin_focus(d)
                    now = out.metrics["target_ssim_corrected"]
                    if abs(now - rec["digital"]) > 5e-3:  # BLAS and numba versions: ~1e-3
                        # the focus check decides the record's verdict, so it must be the record's
                        # run; the placement describes the run it measured, which it names
                        if add_defocus:
                            raise RuntimeError(
                                f"{cond}, seed {rec['seed']}: the digital twin now gives {now:.4f}, "
                                f"the record {rec['digital']:.4f}"
                            )
                        print(
                            f"[dtwin family] {cond}, seed {rec['seed']}: the digital twin now gives {now:.4f}, "
                            f"the record {rec['digital']:.4f}",
                            file=sys.stderr,
                            flush=True,
                        )
                    if add_defocus:
                        rec["digital target_defocus"] = out.metrics["target_defocus"]
                    if add_placement:
                        rec["digital placement"] = {**placement(d, out), "target_ssim": round(now, 4)}
                path.write_text(
                    json.dumps({"scan": {"positions": rows * 6, "pixels": size}, **results}, indent=1, default=float)
                )
        print(table(results))
        return results
    conditions = [c for c in CONDITIONS if not only or only == c]
    for cond in conditions:
        results[cond] = results.get(cond, []) if resume else []
    start = time.monotonic()
    # seed by seed across the conditions, so that a run cut short by ``minutes`` has as many
    # draws of each
    for seed in range(first, first + draws):
        if minutes is not None and time.monotonic() - start > 60.0 * minutes:
            print(
                f"[dtwin family] {minutes} minutes spent: stopping after {seed - first} draws per condition",
                file=sys.stderr,
            )
            break
        for cond in conditions:
            if any(r["seed"] == seed for r in results[cond]):
                continue
            print(f"[dtwin family{', held out' if heldout else ''}] {cond}, seed {seed}", file=sys.stderr, flush=True)
            try:
                results[cond].append(one_draw(cond, seed, shapes, rows, size))
            except TwinFocusError as e:
                # what a user would be told instead of a result (counted, not scored)
                kw = family_scenario(cond, seed, shapes, rows)
                results[cond].append(
                    {"seed": seed, "reference": kw["reference"], "target": kw["target"], "refused": str(e)}
                )
            path.write_text(
                json.dumps({"scan": {"positions": rows * 6, "pixels": size}, **results}, indent=1, default=float)
            )
    path.write_text(json.dumps({"scan": {"positions": rows * 6, "pixels": size}, **results}, indent=1, default=float))
    print(table(results))
    return results


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--draws", type=int, default=3, help="draws per condition")
    ap.add_argument("--heldout", action="store_true", help="the held-out draws (other shapes, other seeds)")
    ap.add_argument("--rows", type=int, default=65, help="scan rows of 6 columns (the paper: 130)")
    ap.add_argument("--size", type=int, default=64, help="pixels per side of each region (the paper: 100)")
    ap.add_argument("--only", default=None, help="one condition's name (replaces it in an earlier file)")
    ap.add_argument("--minutes", type=float, default=None, help="start no new seed after this many minutes")
    ap.add_argument("--resume", action="store_true", help="keep the draws an earlier run of this file holds")
    ap.add_argument(
        "--add-baselines",
        action="store_true",
        help="add the reference-free baselines to an earlier file's records (the twins are not rerun)",
    )
    ap.add_argument(
        "--add-defocus",
        action="store_true",
        help="measure the target's focus check on an earlier file's trusted digital-twin results",
    )
    ap.add_argument(
        "--add-placement",
        action="store_true",
        help="measure where the digital twin put the target (against the truth) on an earlier file's records",
    )
    ap.add_argument(
        "--add-cloud-parts",
        type=int,
        default=0,
        metavar="N",
        help="on the first N draws of each condition of an earlier file, the digital twin with each of "
        "the camera cloud's impairments alone (and two views joined)",
    )
    ap.add_argument(
        "--defocus-figure",
        default=None,
        help="draw the target's focus check from --out's two files into this picture (no draws run)",
    )
    ap.add_argument(
        "--trust-summary",
        action="store_true",
        help="write dtwin_family_trust.json: the report's present rules over --out's two files (no draws run)",
    )
    a = ap.parse_args()
    if a.trust_summary:
        print(trust_summary(a.out))
        sys.exit(0)
    if a.defocus_figure:
        defocus_figure(a.defocus_figure, a.out)
        sys.exit(0)
    main(
        a.out,
        a.draws,
        a.heldout,
        a.rows,
        a.size,
        a.only,
        a.minutes,
        a.resume,
        a.add_baselines,
        a.add_defocus,
        a.add_placement,
        a.add_cloud_parts,
    )
