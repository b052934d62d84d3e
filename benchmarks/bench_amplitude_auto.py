"""`--estimator auto` for an amplitude template without an outline (a template file): the
projections alone, the projections + optimiser, the earlier auto (chosen from the tracking error
the user states) and the auto now (the optimiser only where the projections' own phases have
wrapped, ``refine_below_coherence``), over tracking errors along z on both sides of lambda/4, on a
smooth and on a rough reference (every scatterer its own phase, +-90 degrees, and strength, +-30 %).

    python -m benchmarks.bench_amplitude_auto --z-mm 0.3,0.6,0.8,1.0,1.2,1.6 --seeds 1,2

Scenes: the paper's pair (reference 'A', target 'F' 10 degrees apart at 0.6 m), 0.2 mm x/y + the
given z tracking error, 15 dB; the template from the reference's exact points (the digital twin's
PSF template, no outline). Writes ``amplitude_auto.json`` (one record per scene) and prints a
markdown table (mean over the seeds per error).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def one_scene(z_m: float, rough: bool, seed: int) -> dict:
    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.estimators import estimator_settings
    from twinfocus.focus.pipeline import Bases, Reference, Truth
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.imaging.backprojection.numba_backend import subimage_basis
    from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario
    from twinfocus.twins.digital_twin.condition import digital_twin_reference

    sc = Scenario(
        error_sigma_m=(0.2e-3, 0.2e-3, z_m),
        snr_db=15,
        reference_roughness_deg=90.0 if rough else 0.0,
        reference_amplitude_spread=0.3 if rough else 0.0,
        seed=seed,
    )
    scan, _ = simulate_scenario(sc)
    rg, tg = scenario_grids(sc, 100)
    twin = digital_twin_reference(sc.scene().object("reference").surface_points(1e-3), scan.positions, scan.chirp, rg)
    rb = subimage_basis(scan.data, scan.positions, scan.chirp, rg)
    tb = subimage_basis(scan.data, scan.positions, scan.chirp, tg)
    truth = Truth.of_scan(scan, rg, tg)
    stated = float(np.linalg.norm(sc.error_sigma_m))  # what a user who knew the error would state
    old_auto = "projection" if stated <= scan.chirp.wavelength_m / 4 else "projection-refined"
    rec: dict = {"z_mm": z_m * 1e3, "rough": rough, "seed": seed, "old auto chose": old_auto}
    for name, est in (("projection", "projection"), ("projection-refined", "projection-refined"), ("auto", "auto")):
        out = FocusPlan.make(config=AutofocusConfig(**estimator_settings(est, False))).focus_bases(
            Bases(rb, tb, scan.positions, scan.chirp, rg, tg),
            Reference(template=twin.template),
            truth,
        )
        rec[name] = out.metrics["target_ssim_corrected"]
        rec[f"{name} time_s"] = out.timings_s["autofocus"]
        if name == "auto":
            rec["auto check"] = out.metrics["estimator"]["refine_check"]
    rec["old auto"] = rec[old_auto]
    rec["oracle phase"] = out.metrics["target_ssim_oracle_phase"]
    return rec


COLUMNS = ["projection", "projection-refined", "old auto", "auto", "oracle phase"]


def main(out_dir: str = "benchmarks/results", z_mm: str = "0.3,0.6,0.8,1.0,1.2,1.6", seeds: str = "1,2") -> list:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "amplitude_auto.json"
    records: list = []
    for rough in (False, True):
        for z in (float(v) * 1e-3 for v in z_mm.split(",")):
            for seed in (int(v) for v in seeds.split(",")):
                print(
                    f"[amplitude auto] {'rough' if rough else 'smooth'}, z {z * 1e3:.1f} mm, seed {seed}",
                    file=sys.stderr,
                    flush=True,
                )
                records.append(one_scene(z, rough, seed))
                path.write_text(json.dumps(records, indent=2))
    print(
        "| reference | z error (mm) | "
        + " | ".join(COLUMNS)
        + " | auto refined |\n|---|---|"
        + "---|" * (len(COLUMNS) + 1)
    )
    for rough in (False, True):
        for z in sorted({r["z_mm"] for r in records}):
            rs = [r for r in records if r["rough"] == rough and r["z_mm"] == z]
            cells = [f"{np.mean([r[c] for r in rs]):.3f}" for c in COLUMNS]
            refined = sum(r["auto check"]["refined"] for r in rs)
            print(f"| {'rough' if rough else 'smooth'} | {z:.1f} | " + " | ".join(cells) + f" | {refined}/{len(rs)} |")
    print("| all | | " + " | ".join(f"**{np.mean([r[c] for r in records]):.3f}**" for c in COLUMNS) + " | |")
    return records


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--z-mm", default="0.3,0.6,0.8,1.0,1.2,1.6")
    ap.add_argument("--seeds", default="1,2")
    a = ap.parse_args()
    main(a.out, a.z_mm, a.seeds)
