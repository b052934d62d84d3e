"""``twinfocus simulate``: a simulated handheld scan of the paper's scene, and the reference's
motion-stage template scan."""
from __future__ import annotations

import argparse
import json
import sys
import time

from twinfocus.errors import TwinFocusError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, help="scan file to write (.npz)")
    p.add_argument("--template-out", help="also write the reference's motion-stage scan here (.npz)")
    p.add_argument("--reference", default="A", help="reference letter (default A)")
    p.add_argument("--target", default="F", help="target letter (default F)")
    p.add_argument("--distance", type=float, default=0.6, help="object distance, metres (default 0.6)")
    p.add_argument("--separation-deg", type=float, default=10.0, help="reference-target angle (default 10)")
    p.add_argument("--height", type=float, default=0.127, help="letter height, metres (default 0.127 = 5 in)")
    p.add_argument("--target-height", type=float, default=None, help="target letter height if different")
    p.add_argument("--reference-material", default="metal")
    p.add_argument("--target-material", default="metal")
    p.add_argument("--occluder", default=None, help="sheet in front of the target: polyester, paper, plastic, ...")
    p.add_argument("--clutter", action="store_true", help="add room clutter (weak and a few strong scatterers)")
    p.add_argument("--trajectory", choices=["raster", "zigzag"], default="raster")
    p.add_argument("--error-model", choices=["gaussian", "drift", "vio"], default="gaussian")
    p.add_argument("--error-sigma-mm", type=float, default=0.5, help="z (range) tracking error sigma, mm (default 0.5)")
    p.add_argument("--xy-error-sigma-mm", type=float, default=0.5, help="x and y tracking error sigma, mm (default 0.5)")
    p.add_argument("--snr-db", type=float, default=10.0, help="per-sample SNR in dB (default 10); 'inf' for none")
    p.add_argument("--no-speckle", action="store_true", help="all scatterers in phase")
    p.add_argument("--template-offset-mm", nargs=3, type=float, default=[1.0, 0.0, 0.0], metavar=("DX", "DY", "DZ"),
                   help="placement error of the reference in the template scan, mm (default 1 0 0)")
    p.add_argument("--range-step-mm", type=float, default=None, help="simulator range grid step (fidelity knob)")
    p.add_argument("--columns", type=int, default=6, help="raster columns (default 6)")
    p.add_argument("--rows", type=int, default=130, help="raster rows per column (default 130)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from twinfocus.progress import Progress
    from twinfocus.scenario import Scenario, simulate_scenario

    if not str(args.out).endswith(".npz"):
        raise TwinFocusError(f"--out must name a .npz file, got {args.out}")
    if args.error_sigma_mm < 0 or args.xy_error_sigma_mm < 0:
        raise TwinFocusError("error sigmas must be non-negative")
    snr = None if np.isinf(args.snr_db) else args.snr_db
    sc = Scenario(
        reference=args.reference, target=args.target, distance_m=args.distance, separation_deg=args.separation_deg,
        height_m=args.height, target_height_m=args.target_height, reference_material=args.reference_material,
        target_material=args.target_material, occluder=args.occluder, clutter=args.clutter,
        trajectory=args.trajectory, error_model=args.error_model,
        error_sigma_m=(args.xy_error_sigma_mm * 1e-3, args.xy_error_sigma_mm * 1e-3, args.error_sigma_mm * 1e-3),
        snr_db=snr, speckle=not args.no_speckle, template_offset_m=tuple(v * 1e-3 for v in args.template_offset_mm),
        range_step_m=None if args.range_step_mm is None else args.range_step_mm * 1e-3, seed=args.seed,
        n_columns=args.columns, n_rows=args.rows,
    )
    t0 = time.perf_counter()
    scan, template_scan = simulate_scenario(sc, progress=Progress("simulate", enabled=not args.quiet))
    scan.save(args.out)
    if args.template_out:
        template_scan.save(args.template_out)
    info = {
        "scan": str(args.out), "template_scan": args.template_out, "seconds": round(time.perf_counter() - t0, 2),
        "reference_roi": sc.reference_roi(), "target_roi": sc.target_roi(), "positions": scan.n_positions,
        "channels": scan.n_channels,
    }
    print(json.dumps(info), file=sys.stderr)
    return 0
