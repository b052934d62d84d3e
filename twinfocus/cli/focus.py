"""``twinfocus focus SCAN.npz --reference-roi ... --target-roi ... (--template | --template-scan |
--digital-twin | --method) --out DIR`` (DESIGN.md section 4)."""
from __future__ import annotations

import argparse
import sys

from twinfocus.errors import TwinFocusError
from twinfocus.estimators import ESTIMATORS


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scan", help="scan file (.npz) to focus")
    p.add_argument("--reference-roi", nargs=5, type=float, required=True, metavar=("X0", "X1", "Y0", "Y1", "Z"),
                   help="reference region (metres)")
    p.add_argument("--target-roi", nargs=5, type=float, required=True, metavar=("X0", "X1", "Y0", "Y1", "Z"),
                   help="target region (metres)")
    p.add_argument("--size", type=int, default=100, help="image size in pixels per side (default 100)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--template", help="template file (.npz: image, x_m, y_m, z_m)")
    src.add_argument("--template-scan", help="scan of the reference alone on accurate positions (physical twin)")
    src.add_argument("--digital-twin", help="reference point cloud (.npy, (N, 3) metres, scene frame)")
    src.add_argument("--method", choices=["sharpness", "none"], help="baseline without a template")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--iterations", type=int, default=300, help="optimiser iterations (default 300)")
    p.add_argument("--lr", type=float, default=5e-2, help="Adam learning rate (default 5e-2)")
    p.add_argument("--lr-min", type=float, default=1e-5, help="end of the cosine schedule (default 1e-5)")
    p.add_argument("--threshold-centre", type=float, default=0.4, help="soft threshold centre (default 0.4)")
    p.add_argument("--threshold-steepness", type=float, default=1.0, help="soft threshold steepness (default 1)")
    p.add_argument("--loss-steepness", type=float, default=None,
                   help="soft threshold steepness inside the optimiser's loss only (default: 5 with --estimator paper, "
                        "where it lifts a digital twin from 0.89 to 0.94 SSIM (docs/beyond.md); otherwise "
                        "--threshold-steepness, the source paper's)")
    p.add_argument("--precision", choices=["float32", "float64"], default="float32")
    p.add_argument("--device", default=None, help="torch device for back-projection and autofocus (default: cuda if present, else cpu)")
    p.add_argument("--oversample", type=int, default=16, help="range-profile oversampling for interpolation (default 16)")
    p.add_argument("--keep-phase-ramp", action="store_true",
                   help="transfer the optimiser's phase as is (the source paper); by default its constant + "
                        "linear-in-aperture part, which only moves the image, is removed first")
    p.add_argument("--basis-dtype", choices=["float32", "float16"], default="float32",
                   help="storage of the sub-image basis in the optimiser (float16: ~2x faster, same result)")
    p.add_argument("--estimator", choices=("auto",) + ESTIMATORS, default="auto",
                   help="how the phases are found from the reference (docs/beyond.md): 'paper' = the optimiser from zero; "
                        "'projection' = alternating projections onto the template's amplitude, no optimiser (any "
                        "template); 'projection-refined' = that, then the optimiser (best past lambda/4, where "
                        "phases wrap); 'registered' = the optimiser after moving the template to where the scan puts "
                        "the reference; 'correlation' = registered + closed-form per-position phase, no optimiser "
                        "(fastest); 'correlation-refined' = that, then the optimiser. The last three need the "
                        "template's phase (--template-scan, or a template file with phase_rad). auto: correlation "
                        "when the template has a phase; else projection, or projection-refined when "
                        "--tracking-error-mm exceeds lambda/4")
    p.add_argument("--projection-iterations", type=int, default=30,
                   help="alternating-projection steps of --estimator projection (default 30, ~3 ms each)")
    p.add_argument("--projection-restarts", type=int, default=0,
                   help="--estimator projection also from this many random starts, the best by the loss going on "
                        "(default 0; pays past lambda/4, ~0.1 s each at 780 x 100 x 100 on 2 cores)")
    p.add_argument("--coarse-iterations", type=int, default=0,
                   help="coarse-to-fine: this many optimiser iterations on blurred images before the full-resolution "
                        "ones (default 0: the paper's single stage)")
    p.add_argument("--tracking-error-mm", type=float, default=0.5,
                   help="tracker position error assumed by the confidence report (default 0.5 mm)")
    p.add_argument("--no-pictures", action="store_true", help="skip the PNG pictures")
    p.add_argument("--quiet", action="store_true", help="no progress output")


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import torch

    from twinfocus.autofocus import AutofocusConfig
    from twinfocus.estimators import estimator_settings
    from twinfocus.grid import ImageGrid
    from twinfocus.pipeline import focus_scan, write_outputs
    from twinfocus.progress import Progress
    from twinfocus.scan import Scan
    from twinfocus.templates import load_template, template_from_scan

    if args.size < 2:
        raise TwinFocusError(f"--size must be at least 2, got {args.size}")
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise TwinFocusError(f"--device {device}: no CUDA device is available")
    ref_grid = ImageGrid.from_roi(args.reference_roi, args.size)
    tgt_grid = ImageGrid.from_roi(args.target_roi, args.size)
    bp = {"oversample": args.oversample, "precision": args.precision}
    if device != "cpu":
        bp.update(backend="torch", device=device)
    progress = (lambda label: Progress(label, enabled=not args.quiet))

    scan = Scan.load(args.scan)
    template = None
    method = "twin"
    if args.template:
        template = load_template(args.template, ref_grid)
    elif args.template_scan:
        tpl_scan = Scan.load(args.template_scan)
        template = template_from_scan(tpl_scan, ref_grid, keep_phase=True, progress=progress("template"), **bp)
    elif args.digital_twin:
        from twinfocus.digital_twin.template import digital_twin_template_from_file

        template = digital_twin_template_from_file(args.digital_twin, scan, ref_grid, **bp)
    else:
        method = args.method
    has_phase = template is not None and np.iscomplexobj(template)
    chosen = {}
    if method == "twin":
        chosen = estimator_settings(args.estimator, has_phase, args.tracking_error_mm * 1e-3, scan.chirp.wavelength_m)
    if args.loss_steepness is not None:
        chosen["loss_steepness"] = args.loss_steepness
    cfg = AutofocusConfig(**{
        "iterations": args.iterations, "lr": args.lr, "lr_min": args.lr_min, "threshold_centre": args.threshold_centre,
        "threshold_steepness": args.threshold_steepness, "precision": args.precision, "basis_dtype": args.basis_dtype,
        "device": device, "projection_iterations": args.projection_iterations,
        "projection_restarts": args.projection_restarts, "coarse_iterations": args.coarse_iterations, **chosen})
    cfg.validate()

    outputs = focus_scan(scan, ref_grid, tgt_grid, template=template, method=method, config=cfg,
                         bp_options=bp, progress_factory=progress, remove_phase_ramp=not args.keep_phase_ramp,
                         tracking_error_m=args.tracking_error_mm * 1e-3)
    write_outputs(args.out, outputs, pictures=not args.no_pictures)
    m = outputs.metrics
    for warning in m["confidence"]["warnings"]:
        print(f"twinfocus focus: warning: {warning}", file=sys.stderr)
    if "target_ssim_corrected" in m:
        print(f"target SSIM: uncorrected {m['target_ssim_uncorrected']:.3f} -> {method} {m['target_ssim_corrected']:.3f} "
              f"(oracle phase {m['target_ssim_oracle_phase']:.3f})")
    print(f"wrote {args.out}/ (target.npy, phase.npy, metrics.json, pictures)", file=sys.stderr)
    return 0
