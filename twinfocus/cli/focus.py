"""``twinfocus focus SCAN.npz --reference-roi ... --target-roi ... (--template | --template-scan |
--digital-twin | --method) --out DIR`` (docs/architecture.md section 4)."""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

from twinfocus.errors import TwinFocusError
from twinfocus.estimators import REFERENCE_FREE_RUNGS
from twinfocus.settings import add_focus_options, resolve_device

#: bytes per radar position and pixel that a run holds at its peak: the two sub-image bases
#: (complex64, 8 B each) and the optimiser's copies of the reference basis (float32 [Re | Im]
#: twice, 16 B); measured peaks in docs/performance.md
_BYTES_PER_POSITION_PIXEL = 32


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scan", help="scan file (.npz) to focus")
    p.add_argument(
        "--reference-roi",
        nargs=5,
        type=float,
        required=True,
        metavar=("X0", "X1", "Y0", "Y1", "Z"),
        help="reference region (metres)",
    )
    p.add_argument(
        "--target-roi",
        nargs=5,
        type=float,
        required=True,
        metavar=("X0", "X1", "Y0", "Y1", "Z"),
        help="target region (metres)",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--template",
        help="template file (.npz: image, x_m, y_m, z_m; a digital twin's, from twinfocus twin --out, also its "
        "outline and conditioning)",
    )
    src.add_argument("--template-scan", help="scan of the reference alone on accurate positions (physical twin)")
    src.add_argument("--digital-twin", help="reference point cloud (.npy, (N, 3) metres, scene frame)")
    src.add_argument(
        "--method", choices=REFERENCE_FREE_RUNGS + ("none",), help="reference-free autofocus or none (no template)"
    )
    p.add_argument("--out", required=True, help="output folder")
    add_focus_options(p)  # the settings shared with the solver node: twinfocus/settings.py
    p.add_argument(
        "--pictures",
        choices=("summary", "all", "none"),
        default="summary",
        help="summary: summary.png only (default, ~0.05 s); all: also one PNG per image, loss.png and "
        "phase.png (matplotlib, ~1-2 s more); none",
    )
    p.add_argument("--no-pictures", action="store_true", help="same as --pictures none")
    p.add_argument(
        "--no-cache",
        action="store_true",
        help="neither read nor write the template cache (a template scan's image or a digital twin's "
        "template is stored by the hash of its inputs, grid and back-projection options, in "
        "$TWINFOCUS_CACHE_DIR, else $XDG_CACHE_HOME/twinfocus, else ~/.cache/twinfocus)",
    )
    p.add_argument(
        "--save-template",
        metavar="PATH",
        help="also write the template used as a template file (.npz) that --template takes",
    )
    p.add_argument("--quiet", action="store_true", help="no progress output")


def _check_writable_target(path: str, option: str, folder: bool) -> None:
    """Refuse, before any work, an output that cannot be written: an existing file where a folder
    is due (or a folder where a file is due), or a place that cannot be written to."""
    p = Path(path)
    if p.exists() and folder and not p.is_dir():
        raise TwinFocusError(f"{option} {path}: is an existing file, not a folder")
    if p.is_dir() and not folder:
        raise TwinFocusError(f"{option} {path}: is a folder, not a file")
    anchor = p if p.is_dir() else p.parent
    while not anchor.exists():
        anchor = anchor.parent
    if not anchor.is_dir():
        raise TwinFocusError(f"{option} {path}: {anchor} is a file, not a folder")
    try:  # the real test (os.access says yes to root on a read-only file system)
        fd, probe = tempfile.mkstemp(prefix=".twinfocus-probe.", dir=anchor)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise TwinFocusError(f"{option} {path}: cannot write in {anchor} ({exc.strerror or exc})") from None


def check_memory(n_positions: int, size: int, available: int | None = None) -> int:
    """Refuse a run whose sub-image bases and optimiser copies (~32 B per position and pixel)
    cannot fit in the memory available; returns the estimate in bytes."""
    need = _BYTES_PER_POSITION_PIXEL * n_positions * size * size
    from twinfocus.machine import available_memory_bytes

    available = available_memory_bytes() if available is None else available
    if available is not None and need > available:
        raise TwinFocusError(
            f"--size {size} needs about {need / 2**30:.1f} GiB ({n_positions} positions x {size} x {size} pixels x "
            f"{_BYTES_PER_POSITION_PIXEL} B for the sub-image bases), {available / 2**30:.1f} GiB is available; "
            "choose a smaller --size"
        )
    return need


def _check_before_work(args: argparse.Namespace) -> dict[str, tuple[int, ...]]:
    """Everything that can be checked before loading or computing anything; returns the scan's
    array shapes (from the file's headers)."""
    from twinfocus.scan import peek_npz_shapes

    if args.size < 2:
        raise TwinFocusError(f"--size must be at least 2, got {args.size}")
    _check_writable_target(args.out, "--out", folder=True)
    if args.save_template:
        _check_writable_target(args.save_template, "--save-template", folder=False)
    shapes = peek_npz_shapes(args.scan)
    if "data" not in shapes or len(shapes["data"]) != 3:
        raise TwinFocusError(f"{args.scan}: not a scan file (no 3-D 'data' array)")
    if args.template_scan:
        peek_npz_shapes(args.template_scan)
    if args.template:
        peek_npz_shapes(args.template)
    if args.digital_twin:
        cloud = Path(args.digital_twin)
        if not cloud.is_file():
            raise TwinFocusError(f"--digital-twin {cloud}: no such file")
        with open(cloud, "rb") as f:
            magic = f.read(4)
        if magic == b"PK\x03\x04":
            raise TwinFocusError(
                f"--digital-twin {cloud}: is an .npz archive (a scan or template?); it takes a point "
                "cloud .npy, (N, 3) metres (use --template-scan for a motion-stage scan, --template "
                "for a template file)"
            )
    check_memory(shapes["data"][0], args.size)
    return shapes


def _template(args, scan, ref_grid, bp, progress, cache) -> tuple:
    """The reference template for the chosen source, through the cache: (template or None,
    cache status "hit" / "miss" / "off", or None when there is nothing to cache, the reference's
    outline bool (H, W) for a digital twin, else None, and for a digital twin what its cloud's
    conditioning chose and why (``DigitalTwinReference.info``), else None)."""
    from twinfocus.cache import digital_twin_key, template_scan_key
    from twinfocus.scan import Scan
    from twinfocus.templates import load_template, template_from_scan

    if args.template:
        # a digital twin's file (twinfocus twin --out, --save-template) carries its outline and conditioning
        template, support, info = load_template(args.template, ref_grid, with_outline=True)
        return template, None, support, info
    if args.template_scan:
        key = template_scan_key(args.template_scan, ref_grid, bp) if cache.enabled else None

        def compute():
            return template_from_scan(
                Scan.load(args.template_scan), ref_grid, keep_phase=True, progress=progress("template"), **bp
            )
    elif args.digital_twin:
        # one entry holds the template and the outline, stacked (2, H, W)
        key = (
            digital_twin_key(args.digital_twin, scan.positions, scan.chirp, ref_grid, bp) + "-outline"
            if cache.enabled
            else None
        )

        def compute():
            from twinfocus.digital_twin.condition import digital_twin_reference_from_file

            ref = digital_twin_reference_from_file(args.digital_twin, scan, ref_grid, **bp)
            import numpy as np

            return np.stack([ref.template, ref.support.astype(np.float32)]), ref.info
    else:
        return None, None, None, None
    support = info = None
    if args.digital_twin:
        stacked, info, status = cache.get_or_compute(key, ref_grid, compute, with_info=True)
        template, support = stacked[0], stacked[1] > 0.5
    else:
        template, status = cache.get_or_compute(key, ref_grid, compute)
    if status == "hit" and not args.quiet:
        print(f"[template] from the cache ({cache.path(key)})", file=sys.stderr)
    if cache.warning:
        print(f"twinfocus focus: warning: {cache.warning}", file=sys.stderr)
    return template, status, support, info


def run(args: argparse.Namespace) -> int:
    t_run = time.perf_counter()
    import numpy as np

    from twinfocus.autofocus import AutofocusConfig
    from twinfocus.cache import TemplateCache
    from twinfocus.estimators import estimator_settings
    from twinfocus.grid import ImageGrid
    from twinfocus.pipeline import focus_scan, write_outputs
    from twinfocus.progress import Progress
    from twinfocus.scan import Scan

    pictures = "none" if args.no_pictures else args.pictures
    _check_before_work(args)
    device = resolve_device(args.device)
    ref_grid = ImageGrid.from_roi(args.reference_roi, args.size)
    tgt_grid = ImageGrid.from_roi(args.target_roi, args.size)
    bp = {"oversample": args.oversample, "precision": args.precision}
    if device != "cpu":
        bp.update(backend="torch", device=device)
    progress = lambda label: Progress(label, enabled=not args.quiet)
    timings: dict[str, float] = {}

    t = time.perf_counter()
    scan = Scan.load(args.scan)
    timings["load_scan"] = time.perf_counter() - t
    t = time.perf_counter()
    template, cache_status, support, twin_info = _template(
        args, scan, ref_grid, bp, progress, TemplateCache(enabled=not args.no_cache)
    )
    timings["template"] = time.perf_counter() - t
    method = "twin" if template is not None else args.method
    has_phase = template is not None and np.iscomplexobj(template)
    tracking_error_m = args.tracking_error_mm * 1e-3
    chosen = {}
    if method == "twin":
        chosen = estimator_settings(args.estimator, has_phase, has_support=support is not None, model=args.model)
    if args.loss_steepness is not None:
        chosen["loss_steepness"] = args.loss_steepness
    cfg = AutofocusConfig.from_settings({**vars(args), "device": device}, **chosen)  # validated

    outputs = focus_scan(
        scan,
        ref_grid,
        tgt_grid,
        template=template,
        support=support,
        reference_info=twin_info,
        method=method,
        config=cfg,
        bp_options=bp,
        progress_factory=progress,
        model=args.model,
        phase_ramp=args.phase_ramp,
        space_variant=args.space_variant,
        tracking_error_m=tracking_error_m,
    )
    outputs.timings_s = {**timings, **outputs.timings_s}
    outputs.metrics["timings_s"] = outputs.timings_s
    if cache_status is not None:
        outputs.metrics["template_cache"] = cache_status
    from twinfocus.sensors.capture_to_scan import read_capture_report

    gaps = read_capture_report(args.scan)  # written by `twinfocus convert` beside a real capture
    if gaps:
        outputs.metrics["capture"] = gaps
    if args.save_template and template is not None:
        from twinfocus.templates import save_template

        save_template(args.save_template, template, ref_grid, support=support, info=twin_info)
    t = time.perf_counter()
    write_outputs(args.out, outputs, pictures=pictures)
    t_write = time.perf_counter() - t
    m = outputs.metrics
    for warning in m["confidence"]["warnings"]:
        print(f"twinfocus focus: warning: {warning}", file=sys.stderr)
    if "target_ssim_corrected" in m:
        print(
            f"target SSIM: uncorrected {m['target_ssim_uncorrected']:.3f} -> {method} {m['target_ssim_corrected']:.3f} "
            f"(oracle phase {m['target_ssim_oracle_phase']:.3f})"
        )
    if not args.quiet:
        stages = ", ".join(f"{k} {v:.2f}" for k, v in outputs.timings_s.items())
        print(
            f"[focus] {time.perf_counter() - t_run:.2f} s after start-up: {stages}, writing {t_write:.2f} (s)",
            file=sys.stderr,
        )
    saved = f", template {args.save_template}" if args.save_template and template is not None else ""
    print(f"wrote {args.out}/ (target.npy, phase.npy, metrics.json, pictures: {pictures}{saved})", file=sys.stderr)
    return 0
