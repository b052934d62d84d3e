"""The digital twin's default on field-like draws never used while building it: seeds 6-15 of the
field bench's scenes (benchmarks/bench_field_twin.py) and of variants of B (a cylinder and a bent
plate as the reference, 2 mm of z error), and a hand's drift (H / S), each with the camera cloud
(1 mm noise, 25 % holes, 2 % outliers, 2.5 mm offset) of a rough reference. Per draw, target SSIM:
the default before its outline was grown first ("before": ``outline_growth_rounds=0``, placed by
the band's halves where its phases wrapped), the default (docs/digital_twin.md), the default
placed by the truth (diagnostic), the physical twin (space-variant off) and the target's own phase.

    python -m benchmarks.heldout_field_twin            (~30 min on 2 cores; docs/digital_twin.md)
    python -m benchmarks.heldout_field_twin --figure docs/figures/band_halves.png   (one draw, ~30 s)

Not one of ``make bench``'s benchmarks (no ``bench_`` prefix): it checks a default on new draws
rather than measuring a knob. Writes ``field_twin_heldout.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from benchmarks.bench_field_twin import SCENES, field_draw

HAND = dict(reference="H", target="S", separation_deg=16.3, snr_db=15, error_model="hand", error_sigma_m=(0.8e-3,) * 3)
#: condition -> (scene keywords, seeds)
CONDITIONS = {
    "B": (SCENES["B"], range(6, 16)),
    "C": (SCENES["C"], range(6, 16)),
    "A": (SCENES["A"], range(6, 16)),
    "B cylinder": ({**SCENES["B"], "reference_shape": "cylinder"}, range(6, 11)),
    "B bent": ({**SCENES["B"], "reference_shape": "bent"}, range(6, 14)),
    "B 2 mm z": ({**SCENES["B"], "error_sigma_m": (0.3e-3, 0.3e-3, 2.0e-3)}, range(6, 12)),
    "hand drift H/S": (HAND, range(6, 16)),
}


def one_draw(kw: dict, seed: int) -> dict:
    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.estimators import estimator_settings
    from twinfocus.focus.phase_ramp import fit_linear_phase
    from twinfocus.focus.pipeline import Bases, Reference, Truth, upper_band_basis
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.imaging.basis import form_image
    from twinfocus.imaging.metrics import image_ssim, oracle_phase
    from twinfocus.twins.templates import template_from_scan

    d = field_draw(kw, seed)
    scan, tpl_scan, rg, tg, twin, rb, tb = d.scan, d.tpl_scan, d.rg, d.tg, d.twin, d.rb, d.tb
    truth = Truth.of_scan(scan, rg, tg)
    upper = upper_band_basis(scan.data, scan.positions, scan.chirp, rg)
    settings = estimator_settings("auto", False, has_support=True)
    rec: dict = {"seed": seed}
    for name, growth in (("before", {"outline_growth_rounds": 0}), ("default", {})):
        out = FocusPlan.make(config=AutofocusConfig(**settings, **growth)).focus_bases(
            Bases(rb, tb, scan.positions, scan.chirp, rg, tg, upper_band=upper),
            Reference(template=twin.template, support=twin.support, info=twin.info),
            truth,
        )
        rec[name] = out.metrics["target_ssim_corrected"]
        rec[f"{name} trusted"] = out.metrics["confidence"]["trusted"]
    rec["ranged coh"] = out.metrics["phase_ramp"].get("ramp_coherence_sqrt_m")
    rec["coh"] = out.metrics["estimator"].get("phase_coherence_sqrt_m")
    rec["shift"] = out.metrics["phase_ramp"]["implied_shift_m"]
    rec["removed"] = out.metrics["phase_ramp"]["removed"]
    rec["range errors time_s"] = out.timings_s.get("range_errors")
    rec["default time_s"] = out.timings_s["autofocus"]
    rec["growth_px"] = out.metrics["estimator"]["outline_ensemble"]["growth_px"]
    rec["oracle"] = out.metrics["target_ssim_oracle_phase"]
    # diagnostic: the default's image moved to where the reference really is
    reference_true = oracle_phase(scan.positions_true, scan.positions, rg.centre_m, scan.chirp)
    ramp, _ = fit_linear_phase(
        np.angle(np.exp(1j * (out.phase_rad - reference_true))), scan.positions.mean(axis=1)[:, :2]
    )
    rec["truth-placed"] = image_ssim(form_image(tb, out.phase_rad - ramp), truth.target)
    phys = FocusPlan.make(
        config=AutofocusConfig(**estimator_settings("correlation", True)),
        space_variant="off",
    ).focus_bases(
        Bases(rb, tb, scan.positions, scan.chirp, rg, tg),
        Reference(template=template_from_scan(tpl_scan, rg, keep_phase=True)),
        truth,
    )
    rec["physical"] = phys.metrics["target_ssim_corrected"]
    return rec


def figure(path: str | os.PathLike, seed: int = 2) -> None:
    """One draw of scene B (the bench's seed 2: the cloud's outline, not grown, put the reference
    6 mm off across y): each position's range error from the band's halves against the truth, and
    the target before and after the placement beside the image on the true positions."""
    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.band_delay import bright_pixels, position_range_errors_m
    from twinfocus.focus.estimators import estimator_settings
    from twinfocus.focus.pipeline import Bases, Reference, upper_band_basis
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.imaging.backprojection.numba_backend import backproject
    from twinfocus.imaging.basis import form_image
    from twinfocus.imaging.metrics import image_ssim, true_range_errors_m
    from twinfocus.io.png import pyplot

    d = field_draw(SCENES["B"], seed)
    scan, rg, tg, twin, rb, tb = d.scan, d.rg, d.tg, d.twin, d.rb, d.tb
    truth = backproject(scan.data, scan.positions_true, scan.chirp, tg)
    upper = upper_band_basis(scan.data, scan.positions, scan.chirp, rg)
    # the outline as the cloud gives it (no growth first): the picture shows the placement alone
    config = AutofocusConfig(**estimator_settings("auto", False, has_support=True), outline_growth_rounds=0)
    outs = {
        name: FocusPlan.make(config=config).focus_bases(
            Bases(rb, tb, scan.positions, scan.chirp, rg, tg, upper_band=band),
            Reference(template=twin.template, support=twin.support),
        )
        for name, band in (("before", None), ("placed", upper))
    }
    phase = outs["before"].phase_rad
    pixels = bright_pixels(form_image(rb, phase))
    high = upper(pixels)
    measured = position_range_errors_m(rb[:, pixels] - high, high, phase, scan.chirp)
    true = true_range_errors_m(scan.positions_true, scan.positions, rg.centre_m)
    plt = pyplot()
    fig, axes = plt.subplots(1, 4, figsize=(16, 4))
    ax = axes[0]
    ax.scatter((true - true.mean()) * 1e3, (measured - measured.mean()) * 1e3, s=3, alpha=0.5)
    lim = 3.5
    ax.plot([-lim, lim], [-lim, lim], "k--", lw=0.8)
    ax.set(
        xlim=(-lim, lim),
        ylim=(-lim, lim),
        xlabel="true range error (mm)",
        ylabel="from the band's halves (mm)",
        title=f"each position (corr {np.corrcoef(true, measured)[0, 1]:.2f})",
    )
    extent = [tg.x0 * 100, tg.x1 * 100, tg.y0 * 100, tg.y1 * 100]
    vmax = float(np.abs(truth).max())
    for ax, (img, title) in zip(
        axes[1:],
        (
            (truth, "target on the true positions"),
            (outs["before"].target, f"before: SSIM {image_ssim(outs['before'].target, truth):.3f}"),
            (outs["placed"].target, f"placed: SSIM {image_ssim(outs['placed'].target, truth):.3f}"),
        ),
    ):
        ax.imshow(np.abs(img), origin="lower", extent=extent, cmap="inferno", vmin=0, vmax=vmax)
        ax.set(title=title, xlabel="x (cm)", ylabel="y (cm)")
    shift = np.asarray(outs["placed"].metrics["phase_ramp"]["implied_shift_m"]) * 1e3
    fig.suptitle(
        f"scene B, camera cloud, seed {seed}: the placement moved the reference by ({shift[0]:+.1f}, {shift[1]:+.1f}) mm"
    )
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def trusted(rec: dict) -> bool:
    """Whether the confidence report trusts a record's default by the present rules: its verdict
    as recorded, and the placement check (``twinfocus.focus.pipeline.placement_warnings``, which flags
    every estimate whose phases have wrapped) applied anew to the coherences the record kept."""
    from twinfocus.focus.pipeline import placement_warnings

    return bool(rec["default trusted"]) and not placement_warnings(rec["coh"], rec["ranged coh"], bool(rec["removed"]))


def table(results: dict) -> str:
    ms = lambda a: f"{np.mean(a):.3f} ± {np.std(a):.3f}"  # noqa: E731
    lines = [
        "| condition | draws | before (outline not grown) | default | up / down (> 0.005) | default trusted (draws, their mean) "
        "| placed by the truth | physical twin | target's own phase |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for cond, recs in results.items():
        b = np.array([r["before"] for r in recs])
        d = np.array([r["default"] for r in recs])
        kept = [r["default"] for r in recs if trusted(r)]
        lines.append(
            f"| {cond} | {len(recs)} | {ms(b)} | {ms(d)} | {int((d - b > 0.005).sum())} / {int((b - d > 0.005).sum())} | "
            f"{len(kept)}" + (f", {np.mean(kept):.3f}" if kept else "") + " | "
            f"{ms([r['truth-placed'] for r in recs])} | {ms([r['physical'] for r in recs])} | {ms([r['oracle'] for r in recs])} |"
        )
    return "\n".join(lines)


def main(out_dir: str | os.PathLike = "benchmarks/results", only: str | None = None) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "field_twin_heldout.json"
    # --only replaces its condition in an earlier file, keeping the others
    results: dict = json.loads(path.read_text()) if only and path.is_file() else {}
    for cond, (kw, seeds) in CONDITIONS.items():
        if only and only != cond:
            continue
        results[cond] = []
        for seed in seeds:
            print(f"[held-out field twin] {cond}, seed {seed}", file=sys.stderr, flush=True)
            results[cond].append(one_draw(kw, seed))
            path.write_text(json.dumps(results, indent=1))
    print(table(results))
    return results


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--only", default=None, help="one condition's name")
    ap.add_argument("--figure", default=None, help="write this picture of one draw instead of the table")
    a = ap.parse_args()
    if a.figure:
        figure(a.figure)
    else:
        main(a.out, a.only)
