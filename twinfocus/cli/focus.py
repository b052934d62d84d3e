"""``twinfocus focus SCAN.npz --reference-roi ... --target-roi ... (--template | --template-scan |
--digital-twin | --method) --out DIR`` (docs/architecture.md section 4)."""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

from twinfocus.errors import TwinFocusError
from twinfocus.focus import reference_search
from twinfocus.focus.estimators import REFERENCE_FREE_RUNGS
from twinfocus.focus.reference_search import candidate_score
from twinfocus.focus.settings import add_focus_options, preload_torch
from twinfocus.imaging.depth_search import DEFAULT_HALF_RANGE_M, parse_depth, range_to_search
from twinfocus.imaging.device import resolve_device
from twinfocus.imaging.grid import ImageGrid
from twinfocus.io.atomic import atomic_writer, output_folder, refuse_existing, write_bytes_atomic
from twinfocus.jobs.machine import require_memory
from twinfocus.jobs.progress import Progress
from twinfocus.option_types import REGION, finite_float, positive_float

if TYPE_CHECKING:
    from twinfocus.focus.plan import FocusPlan

#: bytes per radar position and pixel that a run holds at its peak: the two sub-image bases
#: (complex64, 8 B each) and the optimiser's copies of the reference basis (float32 [Re | Im]
#: twice, 16 B); measured peaks in docs/performance.md
_BYTES_PER_POSITION_PIXEL = 32


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scan", help="scan file (.npz) to focus")
    p.add_argument(
        "--reference-roi",
        **REGION,
        default=None,
        help="reference region (metres); without it, found from --digital-twin's cloud, --template's grid or "
        "--template-scan's look (metrics.json reference_search); needed with --method",
    )
    p.add_argument(
        "--target-roi",
        nargs="+",
        default=None,
        metavar="X0 X1 Y0 Y1 [Z | Z0:Z1]",
        help="target region (metres): with Z, focused there; with a range Z0:Z1, or without a depth (the "
        f"reference's +- {DEFAULT_HALF_RANGE_M} m), the depth where its corrected image is sharpest is searched "
        "for (metrics.json target_depth, depth_search.png); left out, the brightest object of the look at the "
        "scan apart from the reference (metrics.json boxes, look.png; twinfocus/focus/boxes.py)",
    )
    p.add_argument(
        "--refine-depth",
        nargs="?",
        type=positive_float,
        const=0.1,
        default=None,
        metavar="M",
        help="with a typed Z: search Z +- M metres (default 0.1) for the target's depth instead of trusting Z",
    )
    p.add_argument(
        "--volume",
        nargs=3,
        type=finite_float,
        default=None,
        metavar=("Z0", "Z1", "DZ"),
        help="also form the corrected 3-D volume over both regions' x/y box, --size x --size pixels, planes "
        "Z0..Z1 every DZ metres: volume.npy, volume.ply and volume.mcap (the voxels within 12 dB of the "
        "brightest, as a point cloud and as a Foxglove /volume/points), volume_mip.png, volume_depth.png",
    )
    p.add_argument(
        "--clock-search",
        action="store_true",
        help="search the radar-camera clock offset: each position re-sampled along its own leg of the sweep (legs "
        "cut where the time stamps, else the steps, jump; continued along the leg's velocity past its ends) at the "
        "offset that focuses --reference-roi best (metrics.json clock_search)",
    )
    _add_sources(p)
    p.add_argument(
        "--rig",
        metavar="RIG.json",
        help="with --digital-twin: the camera's offset from the radar (twinfocus rig) applied to the cloud first "
        "(metrics.json rig: its path and SHA-256); a rig of another board or camera is refused",
    )
    p.add_argument("--out", required=True, help="output folder (an existing one is refused without --overwrite)")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing --out (the files an earlier run wrote there; the folder's other files stay) "
        "and --save-template",
    )
    add_focus_options(p)  # the settings shared with the solver node: twinfocus/focus/settings.py
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


def _add_sources(p: argparse.ArgumentParser) -> None:
    """The reference's source: one of the template options, or a reference-free --method."""
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--template",
        nargs="+",
        metavar="TEMPLATE",
        help="template file (.npz: image, x_m, y_m, z_m; a digital twin's, from twinfocus twin --out, also its "
        "outline and conditioning); several: each a reference candidate, the best by the confidence report used "
        "(metrics.json reference_candidates)",
    )
    src.add_argument(
        "--template-scan",
        nargs="+",
        metavar="SCAN",
        help="scan of the reference alone on accurate positions (physical twin); several: candidates, as --template",
    )
    src.add_argument(
        "--digital-twin",
        nargs="+",
        metavar="CLOUD",
        help="reference point cloud (.npy, (N, 3) metres, scene frame; or BAG:TOPIC, a rosbag2's PointCloud2, "
        "docs/reference/file_formats.md); several: candidates, as --template",
    )
    src.add_argument(
        "--method",
        choices=REFERENCE_FREE_RUNGS + ("none",),
        help="without a template: the target's own sharpness, minimum entropy or phase-gradient autofocus "
        "(docs/reference_free.md), or no correction",
    )


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
    return require_memory(
        need,
        f"--size {size} ({n_positions} positions x {size} x {size} pixels x {_BYTES_PER_POSITION_PIXEL} B for the "
        "sub-image bases)",
        "choose a smaller --size",
        available,
    )


def target_region(values: list[str] | None) -> tuple[tuple[float, ...] | None, float | tuple[float, float] | None]:
    """``--target-roi``'s words -> (X0, X1, Y0, Y1) and the depth: Z, (Z0, Z1) or None; (None,
    None) when it was left out (the box is then found: twinfocus.focus.boxes)."""
    if values is None:
        return None, None
    if len(values) not in (4, 5):
        raise TwinFocusError(f"--target-roi takes X0 X1 Y0 Y1 and optionally Z or Z0:Z1, got {len(values)} values")
    try:
        box = tuple(float(v) for v in values[:4])
    except ValueError:
        raise TwinFocusError(
            f"--target-roi: X0 X1 Y0 Y1 must be numbers (metres), got {' '.join(values[:4])}"
        ) from None
    depth = parse_depth(values[4]) if len(values) == 5 else None
    ImageGrid.from_roi((*box, 1.0), 2)  # checks the box (a depth is checked by parse_depth)
    return box, depth


def volume_plan(args: argparse.Namespace, n_positions: int, n_channels: int, reference_roi=None, target_box=None):
    """The ``--volume`` grid over both regions' x/y box and what it will cost (checked against
    the memory available), or None without ``--volume``. reference_roi : the reference region
    when it was found rather than typed (before it is, the target's box stands in: the cost
    depends only on the pixel and plane counts)."""
    from twinfocus.imaging.volume import volume_cost, volume_grid  # lazy: numba (+2.1 s at import)

    if args.volume is None:
        return None
    box = target_box or target_region(args.target_roi)[0] or reference_roi or args.reference_roi or (0, 1, 0, 1)
    ref = reference_roi or args.reference_roi or (*box[:4], 1.0)
    plane = ImageGrid(
        min(box[0], ref[0]), max(box[1], ref[1]), min(box[2], ref[2]), max(box[3], ref[3]), 1.0, args.size, args.size
    )
    grid = volume_grid(plane, *args.volume)
    cost = volume_cost(grid, n_positions, n_channels)
    require_memory(
        cost["memory_bytes"] + _BYTES_PER_POSITION_PIXEL * n_positions * args.size**2,
        f"--volume ({' x '.join(map(str, grid.shape))} voxels) beside the sub-image bases",
        "choose a smaller --size or fewer planes",
        None,
    )
    return grid, cost


def _check_before_work(args: argparse.Namespace) -> dict[str, tuple[int, ...]]:
    """Everything that can be checked before loading or computing anything; returns the scan's
    array shapes (from the file's headers)."""
    from twinfocus.io.arrays import peek_npz_shapes  # lazy: twinfocus.io.arrays (+0.04 s on twinfocus focus --help)

    if args.size < 2:
        raise TwinFocusError(f"--size must be at least 2, got {args.size}")
    _check_writable_target(args.out, "--out", folder=True)
    refuse_existing(args.out, args.overwrite, "--out")
    if args.save_template:
        _check_writable_target(args.save_template, "--save-template", folder=False)
        refuse_existing(args.save_template, args.overwrite, "--save-template")
    shapes = peek_npz_shapes(args.scan)
    if "data" not in shapes or len(shapes["data"]) != 3:
        raise TwinFocusError(f"{args.scan}: not a scan file (no 3-D 'data' array)")
    for path in (args.template_scan or []) + (args.template or []):
        peek_npz_shapes(path)
    for path in args.digital_twin or []:
        from twinfocus.sensors.rosbag2_files import (
            split_bag_source,  # lazy: twinfocus.motion (+0.16 s on twinfocus focus --help)
        )

        if split_bag_source(path) is not None:
            continue  # a rosbag2's PointCloud2 topic: read (and checked) once the scan's time is known
        cloud = Path(path)
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
    target_region(args.target_roi)
    if (args.reference_roi is None or args.target_roi is None) and args.method:
        raise TwinFocusError("--method needs --reference-roi and --target-roi (the regions are found only with a twin)")
    if getattr(args, "rig", None) and not args.digital_twin:
        raise TwinFocusError("--rig needs --digital-twin (it moves the camera's cloud)")
    check_memory(shapes["data"][0], args.size)
    volume_plan(args, shapes["data"][0], shapes["data"][1])
    return shapes


def _template(args, scan, ref_grid, bp, progress, cache, rig=None) -> tuple:
    """The reference template for the chosen source, through the cache: (template or None,
    cache status "hit" / "miss" / "off", or None when there is nothing to cache, the reference's
    outline bool (H, W) for a digital twin, else None, and for a digital twin what its cloud's
    conditioning chose and why (``DigitalTwinReference.info``), else None)."""
    from twinfocus.radar.scan import Scan  # lazy: twinfocus.io.arrays (+0.04 s on twinfocus focus --help)
    from twinfocus.twins.cache import (  # lazy: twinfocus.io.checksums (+0.03 s on twinfocus focus --help)
        digital_twin_key,
        template_scan_key,
    )
    from twinfocus.twins.templates import load_template, template_from_scan  # lazy: numba (+2.1 s at import)

    if args.template:
        # a digital twin's file (twinfocus twin --out, --save-template) carries its outline and conditioning
        template, support, info = load_template(args.template, ref_grid, with_outline=True)
        return template, None, support, info
    if args.template_scan:
        key = template_scan_key(args.template_scan, ref_grid, bp, cache.root) if cache.enabled else None

        def compute():
            return template_from_scan(
                Scan.load(args.template_scan), ref_grid, keep_phase=True, progress=progress("template"), **bp
            )
    elif args.digital_twin:
        # one entry holds the template and the outline, stacked (2, H, W)
        key = (
            digital_twin_key(args.digital_twin, scan.positions, scan.chirp, ref_grid, bp, root=cache.root)
            + "-outline"
            + (f"-rig{rig[1]['sha256'][:16]}" if rig else "")
            if cache.enabled
            else None
        )

        def compute():
            from twinfocus.twins.digital_twin.condition import (
                digital_twin_reference_from_file,  # lazy: open3d, scipy.ndimage (+4.3 s at import)
            )
            from twinfocus.twins.digital_twin.rig import (
                rig_reference_from_file,  # lazy: twinfocus.twins (+0.08 s on twinfocus focus --help)
            )

            if rig is not None:
                ref = rig_reference_from_file(args.digital_twin, scan, ref_grid, rig[0], **bp)
            else:
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


def _rig(args: argparse.Namespace, scan):
    """``--rig``: (the Rig, its metrics.json record) checked against the scan and cloud, or None."""
    if not getattr(args, "rig", None):
        return None
    from twinfocus.twins.digital_twin.rig import (
        load_rig_for,  # lazy: twinfocus.twins (+0.08 s on twinfocus focus --help)
    )

    return load_rig_for(args.rig, scan, args.digital_twin)


def _reference_region(args: argparse.Namespace, bp: dict, progress, rig=None) -> tuple[tuple, dict]:
    """The reference region: typed, or found from the twin (:mod:`twinfocus.focus.reference_search`)."""
    if args.reference_roi is not None:
        return tuple(args.reference_roi), {"source": "typed"}
    if args.digital_twin:
        from twinfocus.twins.digital_twin.template import (
            load_points,  # lazy: twinfocus.io.arrays (+0.07 s on twinfocus focus --help)
        )

        cloud = load_points(args.digital_twin, allow_non_finite=True)
        if rig is not None:
            cloud = cloud + rig[0].offset_m  # where the calibrated camera saw it
        return reference_search.region_from_cloud(cloud)
    if args.template:
        from twinfocus.io.arrays import load_npz  # lazy: twinfocus.io.arrays (+0.04 s on twinfocus focus --help)

        z = load_npz(args.template)
        if not all(k in z for k in ("x_m", "y_m", "z_m")):
            raise TwinFocusError(f"--template {args.template}: not a template file (no x_m, y_m, z_m)")
        return reference_search.region_from_template_file(z["x_m"], z["y_m"], float(z["z_m"]))
    from twinfocus.radar.scan import Scan  # lazy: twinfocus.io.arrays (+0.04 s on twinfocus focus --help)

    twin = Scan.load(args.template_scan)
    return reference_search.region_from_scan(
        twin.data, twin.positions, twin.chirp, bp_options=bp, progress_factory=progress
    )


def _volume_metrics(grid, cost: dict, seconds: float) -> dict:
    p = grid.plane
    return {
        "roi": [p.x0, p.x1, p.y0, p.y1],
        "z_m": [grid.z0, grid.z1],
        "shape": list(grid.shape),
        "memory_bytes_estimate": cost["memory_bytes"],
        "seconds_estimate": cost["seconds_estimate"],
        "seconds": seconds,
    }


#: the volume's files beside write_outputs' (metrics.json "volume" "files" names them)
VOLUME_FILES = {"volume": "volume.npy", "points": "volume.ply", "foxglove": "volume.mcap"}
#: voxels within this many dB of the volume's brightest make its point clouds
VOLUME_THRESHOLD_DB = -12.0


def _write_where(out_dir, search, typed_depth, volume, grid, cloud, pictures: str) -> None:
    """Beside write_outputs' files: depth_search.png for a depth search, and for a volume
    :data:`VOLUME_FILES` (``cloud``: :func:`twinfocus.imaging.volume.bright_voxels`' points and values, as
    PLY and as a Foxglove point cloud on ``/volume/points``) and its two pictures (the data
    written atomically, into the fresh folder that becomes --out)."""
    import numpy as np

    if search is not None and pictures != "none":
        from twinfocus.outputs.depth_pictures import (
            depth_search_picture,  # lazy: twinfocus.io.png (+0.02 s on twinfocus focus --help)
        )

        with atomic_writer(Path(out_dir) / "depth_search.png") as f:
            depth_search_picture(f, search, typed_depth if isinstance(typed_depth, float) else None)
    if volume is None:
        return
    from nodes.foxglove_convert import write_point_cloud_log  # lazy: foxglove, mcap (+1.00 s on twinfocus focus --help)
    from twinfocus.imaging.volume import projections  # lazy: numba (+2.1 s at import)
    from twinfocus.io.arrays import ply_bytes  # lazy: twinfocus.io.arrays (+0.04 s on twinfocus focus --help)

    with atomic_writer(Path(out_dir) / VOLUME_FILES["volume"]) as f:
        np.save(f, volume.astype(np.complex64))
    write_bytes_atomic(Path(out_dir) / VOLUME_FILES["points"], ply_bytes(*cloud))
    write_point_cloud_log(Path(out_dir) / VOLUME_FILES["foxglove"], *cloud)
    if pictures != "none":
        from twinfocus.outputs.depth_pictures import (
            volume_pictures,  # lazy: twinfocus.io.png (+0.02 s on twinfocus focus --help)
        )

        volume_pictures(out_dir, *projections(volume, grid), grid)


def _found_region(args: argparse.Namespace, box, bp: dict, progress, rig, timings: dict) -> tuple[tuple, dict]:
    """The reference region (typed, or found from the twin and cut away from a typed target's box)
    and how it was found; the search's time into ``timings``."""
    from twinfocus.focus.boxes import cut_away  # lazy: twinfocus.focus.boxes (+0.14 s on twinfocus focus --help)

    t = time.perf_counter()
    reference_roi, reference_found = _reference_region(args, bp, progress, rig)
    if box is not None and reference_found["source"] != "typed":
        extent = reference_found.get("extent_m", reference_roi)
        reference_roi = (*cut_away(list(reference_roi[:4]), box, extent, box), reference_roi[4])
    if reference_found["source"] != "typed":
        timings["reference_search"] = time.perf_counter() - t
        if not args.quiet:
            print(
                f"[reference] region from the {reference_found['source']}: "
                + " ".join(f"{v:.3f}" for v in reference_roi),
                file=sys.stderr,
            )
    return reference_roi, reference_found


def _focus_with(args: argparse.Namespace, scan, box, typed_depth, plan: FocusPlan, progress) -> dict:
    """Everything ``focus`` does with one reference (``args`` names one template source) under
    ``plan`` (:class:`~twinfocus.focus.plan.FocusPlan`, made from the settings): its region (typed
    or found), its template, the target's depth when it is searched, the focused outputs. Returns
    a dict of them (``outputs``, ``search``, ``template``, ``support``, ``twin_info``,
    ``ref_grid``, ``method``, ``boxes``, ``typed_depth``)."""
    from twinfocus.focus import boxes  # lazy: twinfocus.focus.boxes (+0.14 s on twinfocus focus --help)
    from twinfocus.focus.pipeline import Reference  # lazy: numba, scipy.fft (+2.1 s at import)
    from twinfocus.focus.plan import Target  # lazy: numba, scipy.fft (+2.1 s at import)
    from twinfocus.twins.cache import TemplateCache  # lazy: twinfocus.io.checksums (+0.03 s on twinfocus focus --help)

    timings: dict[str, float] = {}
    bp = dict(plan.bp_options)
    rig = _rig(args, scan)  # checked against the scan and the cloud before any work
    reference_roi, reference_found = _found_region(args, box, bp, progress, rig, timings)
    ref_grid = ImageGrid.from_roi(reference_roi, args.size)
    depth_range = range_to_search(typed_depth, args.refine_depth, ref_grid.z)
    if (args.template_scan or args.template) and plan.needs.torch:
        preload_torch()  # a template with phase: the ladder may fit a drift, with torch
    t = time.perf_counter()
    template, cache_status, support, twin_info = _template(
        args, scan, ref_grid, bp, progress, TemplateCache(enabled=not args.no_cache), rig
    )
    timings["template"] = time.perf_counter() - t
    plan = plan.for_reference(template, support)
    reference = Reference(template, support, twin_info)
    found_boxes = seen = None
    if box is None:
        t = time.perf_counter()
        extent = reference_found.get("extent_m", reference_roi)
        found_boxes, seen = boxes.find_target(
            plan.focuser(ref_grid, reference), scan, reference_roi, extent, reference_found["source"], bp, progress
        )
        timings["boxes"] = time.perf_counter() - t
        box, typed_depth = found_boxes.target_roi[:4], found_boxes.target_roi[4]
        depth_range = range_to_search(typed_depth, args.refine_depth, ref_grid.z)
        if not args.quiet:
            print(found_boxes.line(), file=sys.stderr)
    target = Target(tuple(box), typed_depth if isinstance(typed_depth, float) else None, depth_range, args.size)
    outputs, search = plan.focus_target(scan, ref_grid, reference, target)
    outputs.metrics["reference_search"] = {**reference_found, "roi": list(reference_roi)}
    if found_boxes is not None:
        outputs.metrics["boxes"] = found_boxes.info
    outputs.timings_s = {**timings, **outputs.timings_s}
    if cache_status is not None:
        outputs.metrics["template_cache"] = cache_status
    if rig is not None:  # the file applied and how far it moved the reference
        outputs.metrics["rig"] = {**rig[1], **((twin_info or {}).get("rig") or {})}
    return {
        "outputs": outputs,
        "search": search,
        "template": template,
        "support": support,
        "twin_info": twin_info,
        "ref_grid": ref_grid,
        "method": plan.method,
        "boxes": (found_boxes, seen) if found_boxes is not None else None,
        "typed_depth": typed_depth,
    }


def _candidates(args: argparse.Namespace) -> list[tuple[str | None, argparse.Namespace]]:
    """One (path, args naming that one template source) per reference candidate; (None, args)
    for a baseline."""
    for option in ("template", "template_scan", "digital_twin"):
        paths = getattr(args, option)
        if paths:
            return [(path, argparse.Namespace(**{**vars(args), option: path})) for path in paths]
    return [(None, args)]


def _clock_template(args: argparse.Namespace):
    """--clock-search's template: n -> the first --template-scan's image on the n x n reference
    grid, else None (the image's sharpness)."""
    if not args.template_scan or args.reference_roi is None:
        return None
    from twinfocus.radar.scan import Scan  # lazy: twinfocus.io.arrays (+0.04 s on twinfocus focus --help)
    from twinfocus.twins.templates import scan_template_on  # lazy: numba (+2.1 s at import)

    return scan_template_on(Scan.load(args.template_scan[0]), args.reference_roi)


def run(args: argparse.Namespace) -> int:
    t_run = time.perf_counter()
    shapes = _check_before_work(args)
    # held for the whole run: a second run on this --out refuses at once; the folder appears whole
    with output_folder(args.out, args.overwrite, "--out") as out_dir:
        return _run(args, shapes, out_dir, t_run)


def _saved_template_path(args: argparse.Namespace, out_dir: Path) -> Path:
    """Where --save-template is written: inside --out it goes into the folder being built."""
    path = Path(args.save_template)
    if path.resolve().parent == Path(args.out).resolve():
        return out_dir / path.name
    return path


def _form_volume(
    args: argparse.Namespace, shapes: dict, scan, outputs, ref_grid: ImageGrid, bp: dict, progress, timings: dict
):
    """``--volume``: the corrected volume (:func:`twinfocus.imaging.volume.corrected_image` with the
    outputs' phase), its bright voxels and its grid, its figures into ``outputs.metrics["volume"]``
    and its time into ``timings``; (None, None, None) without ``--volume``."""
    from twinfocus.imaging.volume import bright_voxels, corrected_image  # lazy: numba (+2.1 s at import)

    volume, cloud = None, None
    plan = volume_plan(args, shapes["data"][0], shapes["data"][1], ref_grid.roi, outputs.target_grid.roi[:4])
    sub_arrays = None
    if plan is not None and bp.get("device", "cpu") == "cpu" and args.precision == "float32":
        from twinfocus.imaging.line_backprojection import plan as line_plan  # lazy: numba (+2.1 s at import)
        from twinfocus.imaging.volume import volume_cost  # lazy: numba (+2.1 s at import)

        # the scan's positions decide whether the volume is formed by sub-arrays, and so its time
        sub_arrays = line_plan(scan.positions, scan.chirp, plan[0])
        plan = (plan[0], volume_cost(plan[0], scan.data.shape[0], scan.data.shape[1], sub_arrays))
    if plan is not None:
        if not args.quiet:
            print(
                f"[volume] {' x '.join(map(str, plan[0].shape))} voxels: about "
                f"{plan[1]['memory_bytes'] / 2**20:.0f} MiB and {plan[1]['seconds_estimate']:.0f} s on the CPU",
                file=sys.stderr,
            )
        t, cpu = time.perf_counter(), time.process_time()
        volume = corrected_image(
            scan.data, scan.positions, scan.chirp, plan[0], outputs.phase_rad, progress=progress("volume"), **bp
        )
        timings["volume"] = time.perf_counter() - t
        outputs.metrics["volume"] = {
            **_volume_metrics(plan[0], plan[1], timings["volume"]),
            # on a busy machine the steadier figure: about the wall time x the threads when idle
            "cpu_seconds": time.process_time() - cpu,
            # sub-arrays per radar position (twinfocus.imaging.line_backprojection); null: back-projected directly
            "sub_arrays": sub_arrays.groups if sub_arrays is not None else None,
        }
        cloud = bright_voxels(volume, plan[0], VOLUME_THRESHOLD_DB)
        outputs.metrics["volume"].update(
            files=dict(VOLUME_FILES), points=len(cloud[0]), points_threshold_db=VOLUME_THRESHOLD_DB
        )
    return volume, cloud, plan[0] if plan else None


def _best_candidate(args: argparse.Namespace, candidates: list, scan, box, typed_depth, plan: FocusPlan, progress):
    """Each reference candidate (:func:`_candidates`) focused (:func:`_focus_with`), the best by
    the confidence report (:func:`twinfocus.focus.reference_search.candidate_score`): (its result, its
    index, every candidate's record for metrics.json ``reference_candidates``)."""
    results, listed = [], []
    for path, cand_args in candidates:
        if len(candidates) > 1 and not args.quiet:
            print(f"[reference] candidate {path}", file=sys.stderr)
        r = _focus_with(cand_args, scan, box, typed_depth, plan, progress)
        conf = r["outputs"].metrics["confidence"]
        results.append(r)
        listed.append(
            {
                "path": path,
                "reference_roi": list(r["ref_grid"].roi),
                "score": candidate_score(conf),
                "reference_match_ssim": conf.get("reference_match_ssim"),
                "warnings": len(conf["warnings"]),
                "target_roi": list(r["outputs"].target_grid.roi),
                # known only for a simulated scan: how the choice fared
                "target_ssim_corrected": r["outputs"].metrics.get("target_ssim_corrected"),
            }
        )
    best = max(range(len(results)), key=lambda i: listed[i]["score"])
    return results[best], best, listed


def _run(args: argparse.Namespace, shapes: dict, out_dir: Path, t_run: float) -> int:
    # the numerics load here, once a focus runs: `focus --help` and the refusals before any work
    # take 1.0 s instead of 4.0 s with them in the module's header (load 25, 2 cores)
    from twinfocus.focus.output_files import write_outputs  # lazy: numba, scipy.fft (+2.1 s at import)
    from twinfocus.focus.plan import FocusPlan  # lazy: numba, scipy.fft (+2.1 s at import)
    from twinfocus.radar.scan import Scan  # lazy: twinfocus.io.arrays (+0.04 s on twinfocus focus --help)

    pictures = "none" if args.no_pictures else args.pictures
    device = resolve_device(args.device)
    bp = {"oversample": args.oversample, "precision": args.precision}
    if device != "cpu":
        bp.update(backend="torch", device=device)
    progress = lambda label: Progress(label, enabled=not args.quiet)
    box, typed_depth = target_region(args.target_roi)
    # made once for every candidate: a template source focuses with the twin, else --method
    method = "twin" if args.template or args.template_scan or args.digital_twin else args.method
    plan = FocusPlan.from_settings({**vars(args), "device": device}, method, bp_options=bp, progress_factory=progress)

    t = time.perf_counter()
    scan = Scan.load(args.scan)
    if args.digital_twin:
        from twinfocus.twins.digital_twin.template import (
            pin_bag_clouds,  # lazy: twinfocus.io.arrays (+0.07 s on twinfocus focus --help)
        )

        args.digital_twin = pin_bag_clouds(args.digital_twin, scan.timestamps_ns, quiet=args.quiet)
    load_s = time.perf_counter() - t
    clock = None
    if args.clock_search:
        from twinfocus.sensors.clock_offset import (  # lazy: twinfocus.imaging.metrics (+0.08 s on twinfocus focus --help)
            clock_search_line,
            search_scan_clock,
        )

        scan, clock = search_scan_clock(
            scan, args.reference_roi, 32, bp, template=_clock_template(args), fine_size=args.size
        )
        if not args.quiet:
            print(clock_search_line(clock), file=sys.stderr)
    candidates = _candidates(args)
    chosen, best, listed = _best_candidate(args, candidates, scan, box, typed_depth, plan, progress)
    outputs, search, template = chosen["outputs"], chosen["search"], chosen["template"]
    support, twin_info, ref_grid, method = chosen["support"], chosen["twin_info"], chosen["ref_grid"], chosen["method"]
    if len(candidates) > 1:
        outputs.metrics["reference_candidates"] = {"chosen": best, "candidates": listed}
        if not args.quiet:
            print(f"[reference] chose {listed[best]['path']} (score {listed[best]['score']:.3f})", file=sys.stderr)
    timings = {"load_scan": load_s, **outputs.timings_s}
    outputs.timings_s = timings
    outputs.metrics["timings_s"] = timings
    from twinfocus.sensors.capture_to_scan import (
        read_capture_report,  # lazy: twinfocus.imaging.subpixel (+0.20 s on twinfocus focus --help)
    )

    if clock is not None:
        outputs.metrics["clock_search"] = clock
    gaps = read_capture_report(args.scan)  # written by `twinfocus convert` beside a real capture
    if gaps:
        outputs.metrics["capture"] = gaps
    if args.save_template and template is not None:
        from twinfocus.twins.templates import save_template  # lazy: numba (+2.1 s at import)

        save_template(_saved_template_path(args, out_dir), template, ref_grid, support=support, info=twin_info)
    volume, cloud, volume_grid = _form_volume(args, shapes, scan, outputs, ref_grid, bp, progress, timings)
    t = time.perf_counter()
    write_outputs(out_dir, outputs, pictures=pictures)
    _write_where(out_dir, search, chosen["typed_depth"], volume, volume_grid, cloud, pictures)
    if chosen["boxes"] is not None and pictures != "none":
        from twinfocus.focus.boxes import (
            look_picture,  # lazy: twinfocus.focus.boxes (+0.14 s on twinfocus focus --help)
        )

        with atomic_writer(Path(out_dir) / "look.png") as f:
            look_picture(f, chosen["boxes"][1], chosen["boxes"][0])
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
