"""``twinfocus twin LEFT RIGHT --camera CAMERA.json --seed-... --points-out POINTS.npy
[--scan SCAN.npz --reference-roi X0 X1 Y0 Y1 Z --out TEMPLATE.npz]``: the digital twin of the
reference, from a stereo pair (and a seed) to its point cloud and amplitude template.

POINTS.npy holds the cloud in the radar's scene frame, with the radar-camera calibration's offset
already applied when one is given or measured: ``twinfocus focus --digital-twin POINTS.npy``
takes it as it is.

With ``--calibrate-scan`` (a scan of the scene on accurate positions) it also makes the one-time
radar-camera offset calibration (``--calibration-out``); ``--calibration`` applies a stored one.
Every output is computed before anything is written, and each file is written atomically.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import time

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.grid import ImageGrid
from twinfocus.io.atomic import write_bytes_atomic, write_text_atomic
from twinfocus.io.images import read_image, write_image_atomic
from twinfocus.option_types import REGION, finite_float, positive_float, positive_int
from twinfocus.radar.scan import Scan
from twinfocus.sensors.rosbag2_files import read_bag_stereo, split_bag_source
from twinfocus.twins.digital_twin.align import RadarCameraCalibration, calibrate_offset
from twinfocus.twins.digital_twin.camera import Intrinsics, StereoCamera
from twinfocus.twins.digital_twin.rig import Rig, scan_board
from twinfocus.twins.digital_twin.segment import Seed, box_from_scene_roi, load_segmenter
from twinfocus.twins.digital_twin.template import digital_twin_template


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "left",
        help="left picture (PNG/JPEG, rectified or as calibrated), or BAG:TOPIC, a rosbag2's sensor_msgs/Image "
        "(e.g. run_bag:/zed/zed_node/left/image_rect_color)",
    )
    p.add_argument("right", help="right picture, same size (or BAG:TOPIC with the left's bag)")
    p.add_argument(
        "--camera",
        help="stereo calibration and camera pose (camera.json); with a BAG:TOPIC pair, default: the CameraInfo "
        "beside each image topic and the default ZED pose (a camera.json given there lends only its pose)",
    )
    seed = p.add_mutually_exclusive_group(required=True)
    seed.add_argument("--seed-point", nargs=2, type=finite_float, metavar=("U", "V"), help="a pixel on the reference")
    seed.add_argument(
        "--seed-box",
        nargs=4,
        type=finite_float,
        metavar=("X0", "Y0", "X1", "Y1"),
        help="pixel box around the reference",
    )
    seed.add_argument(
        "--seed-roi", **REGION, help="radar region (metres) holding the reference, projected into the picture"
    )
    seed.add_argument("--seed-nearest", action="store_true", help="the nearest sizeable object (beware occluders)")
    p.add_argument(
        "--segmenter",
        default="classical",
        help="classical (default), sam2:CHECKPOINT[:CONFIG] or sam:CHECKPOINT[:TYPE]",
    )
    p.add_argument("--surface", choices=["auto", "plane", "raw"], default="auto", help="surface model (default auto)")
    p.add_argument(
        "--voxel-mm",
        type=positive_float,
        default=None,
        help="point spacing; default: half the radar's resolution from --scan, else 1.0 mm",
    )
    p.add_argument("--points-out", required=True, help="reference point cloud to write (.npy, (N, 3) metres)")
    p.add_argument("--mask-out", help="also write the reference mask (PNG)")
    p.add_argument("--scan", help="scan file whose aperture the template is simulated for")
    p.add_argument("--reference-roi", **REGION, help="reference region (metres) of the template")
    p.add_argument("--size", type=positive_int, default=100, help="template size in pixels per side (default 100)")
    p.add_argument(
        "--out", help="template file to write (.npz: image, x_m, y_m, z_m, the outline and the conditioning)"
    )
    p.add_argument("--template-method", choices=["psf", "exact"], default="psf", help="psf (fast, default) or exact")
    p.add_argument(
        "--incoherent",
        action="store_true",
        help="a rough reference: outline-only model, template of the mean speckle amplitude",
    )
    p.add_argument("--support-out", help="with --out: also write the reference's outline on the grid (PNG)")
    p.add_argument("--calibration", help="radar-camera offset calibration to apply (JSON)")
    p.add_argument("--rig", help="rig file (twinfocus rig): the camera's offset from the radar to apply")
    p.add_argument("--calibrate-scan", help="scan on accurate positions: measure the radar-camera offset")
    p.add_argument("--calibration-out", help="where to write the measured calibration (JSON)")
    p.add_argument("--report", help="write stage timings and counts here (JSON)")
    p.add_argument("--quiet", action="store_true")


def _check_args(args) -> None:
    if args.out and not (args.scan and args.reference_roi):
        raise TwinFocusError("--out (a template) needs --scan and --reference-roi")
    if args.calibrate_scan and not (args.reference_roi and args.calibration_out):
        raise TwinFocusError("--calibrate-scan needs --reference-roi and --calibration-out")
    if args.calibration_out and not args.calibrate_scan:
        raise TwinFocusError("--calibration-out needs --calibrate-scan")
    if args.support_out and not args.out:
        raise TwinFocusError("--support-out needs --out (the template's grid)")
    if args.out and not str(args.out).endswith(".npz"):
        raise TwinFocusError(f"--out must name a .npz file, got {args.out}")
    if not str(args.points_out).endswith(".npy"):
        raise TwinFocusError(f"--points-out must name a .npy file, got {args.points_out}")
    if args.voxel_mm is not None and not args.voxel_mm > 0:
        raise TwinFocusError(f"--voxel-mm must be positive, got {args.voxel_mm}")
    if args.size < 2:
        raise TwinFocusError(f"--size must be at least 2, got {args.size}")


def _pair_from_bag(args):
    """(StereoCamera, left, right) from a rosbag2's rectified Image pair and their CameraInfo."""

    left_src, right_src = split_bag_source(args.left), split_bag_source(args.right)
    assert left_src is not None, "called for a --left of the form BAG:TOPIC"
    if right_src is None or right_src.path != left_src.path:
        raise TwinFocusError(f"{args.right}: with a bag's left image, the right must be BAG:TOPIC of the same bag")
    pair = read_bag_stereo(left_src.path, left_src.topic, right_src.topic, left_src.at_ns)
    eyes = [Intrinsics(m.fx, m.fy, m.cx, m.cy, m.width, m.height) for m in (pair.left_model, pair.right_model)]
    baseline = pair.right_model.tx_m - pair.left_model.tx_m
    base = StereoCamera.load(args.camera) if args.camera else StereoCamera.zed2i(eyes[0].width, eyes[0].height)
    return (
        StereoCamera(eyes[0], eyes[1], np.eye(3), np.array([-baseline, 0.0, 0.0]), base.scene_from_left),
        pair.left,
        pair.right,
    )


def run(args: argparse.Namespace) -> int:
    from twinfocus.twins.digital_twin.pipeline import reference_from_stereo  # lazy: open3d (+4.3 s at import)
    from twinfocus.twins.digital_twin.pointcloud import PointCloudConfig  # lazy: open3d (+4.3 s at import)

    _check_args(args)
    say = (lambda *a: None) if args.quiet else (lambda *a: print("twinfocus twin:", *a, file=sys.stderr))
    t_all = time.perf_counter()

    camera, left, right = _stereo_pair(args)
    scan = Scan.load(args.scan) if args.scan else None
    calib_offset = _calibration_offset(args, scan)
    grid = ImageGrid.from_roi(args.reference_roi, args.size) if args.reference_roi else None
    seed = _seed(args, camera)
    voxel = _voxel_m(args, scan, grid)
    segmenter = load_segmenter(args.segmenter)
    say(f"segmenting and reconstructing the reference (seed: {seed.kind}, voxel {voxel * 1e3:.2f} mm)")
    twin = reference_from_stereo(
        left,
        right,
        camera,
        seed,
        segmenter=segmenter,
        cloud_config=PointCloudConfig(surface=args.surface, voxel_m=voxel),
    )
    points = twin.points_m
    report = {"seed": {"kind": seed.kind, "values": list(seed.values)}, **twin.summary(), "voxel_m": voxel}
    timings = dict(twin.timings_s)

    calibration = None
    if args.calibrate_scan:
        calibration = _calibrate(args, points, grid, say, timings)
        calib_offset = calibration.offset_m
        report["calibration_offset_m"] = calibration.offset_m.tolist()

    # The cloud as the radar sees it: the calibration's offset applied (what focus --digital-twin takes).
    points_radar = points if calib_offset is None else points + calib_offset
    ref = None
    if args.out:
        ref = _reference(args, points_radar, scan, grid, say, timings)
        report["conditioning"] = ref.info
    timings["total"] = time.perf_counter() - t_all
    report["timings_s"] = {k: round(v, 4) for k, v in timings.items()}

    _write_outputs(args, points_radar, twin, calibration, ref, grid, report)
    say(
        f"{points.shape[0]} points ({twin.cloud.surface} surface), stages "
        + ", ".join(f"{k} {v:.2f}s" for k, v in timings.items())
    )
    print(
        json.dumps(
            {
                "points": int(points.shape[0]),
                "points_out": str(args.points_out),
                "template": args.out,
                "timings_s": report["timings_s"],
            }
        )
    )
    return 0


def _stereo_pair(args: argparse.Namespace):
    """(StereoCamera, left, right) from a bag's image topics or from picture files and --camera."""
    if split_bag_source(args.left) is not None:
        camera, left, right = _pair_from_bag(args)
    elif not args.camera:
        raise TwinFocusError("--camera (camera.json) is needed with picture files")
    else:
        camera = StereoCamera.load(args.camera)
        left, right = read_image(args.left), read_image(args.right)
    if left.shape != right.shape:
        raise TwinFocusError(
            f"{args.left} is {left.shape[1]}x{left.shape[0]} but {args.right} is {right.shape[1]}x{right.shape[0]}: "
            "a stereo pair must have one size"
        )
    return camera, left, right


def _calibration_offset(args: argparse.Namespace, scan: Scan | None) -> np.ndarray | None:
    """The radar-camera offset (3,) metres of --calibration or --rig (checked against the scan's board), or None."""
    calib_offset = None
    if args.calibration:
        calib_offset = RadarCameraCalibration.load(args.calibration).offset_m
    if getattr(args, "rig", None):
        if args.calibration:
            raise TwinFocusError("give --rig or --calibration, not both")

        rig = Rig.load(args.rig)
        if scan is not None:
            rig.check(scan_board(scan), None, args.rig)
        calib_offset = rig.offset_m
    return calib_offset


def _seed(args: argparse.Namespace, camera) -> Seed:
    """Where the segmenter starts: --seed-point, --seed-box, --seed-roi, else the nearest object."""
    if args.seed_point:
        return Seed.point(*args.seed_point)
    if args.seed_box:
        return Seed.box(*args.seed_box)
    if args.seed_roi:
        return box_from_scene_roi(args.seed_roi, camera)
    return Seed.nearest()


def _voxel_m(args: argparse.Namespace, scan: Scan | None, grid: ImageGrid | None) -> float:
    """The cloud's voxel, metres: --voxel-mm, else the radar's point spacing on the grid, else 1 mm."""
    from twinfocus.twins.digital_twin.pointcloud import radar_point_spacing  # lazy: open3d (+4.3 s at import)

    if args.voxel_mm is not None:
        return args.voxel_mm * 1e-3
    if scan is not None and grid is not None:
        return radar_point_spacing(scan.chirp.wavelength_m, scan.positions, grid.centre_m)
    return 1.0e-3


def _calibrate(args: argparse.Namespace, points: np.ndarray, grid: ImageGrid | None, say, timings: dict):
    """The radar-camera offset fitted on --calibrate-scan (accurate positions): the cloud's
    simulated image against the measured one. Adds its seconds to ``timings``."""
    from twinfocus.imaging.backprojection.numba_backend import backproject  # lazy: numba (+2.1 s at import)

    assert grid is not None  # _check_args: --calibrate-scan needs --reference-roi
    cal_scan = Scan.load(args.calibrate_scan)
    pos = cal_scan.positions_true if cal_scan.positions_true is not None else cal_scan.positions
    say("calibrating the radar-camera offset against the accurate-position scan")
    t = time.perf_counter()
    measured = np.abs(backproject(cal_scan.data, pos, cal_scan.chirp, grid))
    sim = digital_twin_template(
        points, pos, cal_scan.chirp, grid, method=args.template_method, coherent=not args.incoherent
    )
    calibration = calibrate_offset(sim, measured, grid)
    calibration.source.update({"calibrate_scan": str(args.calibrate_scan)})
    timings["calibration"] = time.perf_counter() - t
    return calibration


def _reference(
    args: argparse.Namespace, points_radar: np.ndarray, scan: Scan | None, grid: ImageGrid | None, say, timings: dict
):
    """The conditioned digital-twin reference (template, outline, info) of the radar-frame cloud
    over the scan's phase centres. Adds its seconds to ``timings``."""
    from twinfocus.twins.digital_twin.condition import (  # lazy: open3d, scipy.ndimage (+4.3 s at import)
        ConditionConfig,
        digital_twin_reference,
    )

    assert scan is not None and grid is not None  # _check_args: --out needs --scan and --reference-roi
    say(
        f"conditioning the cloud and simulating the template ({args.template_method}) over "
        f"{scan.n_positions} x {scan.n_channels} phase centres"
    )
    t = time.perf_counter()
    # --incoherent: a rough reference, whose radar texture no camera sees: its outline alone.
    ref = digital_twin_reference(
        points_radar,
        scan.positions,
        scan.chirp,
        grid,
        method=args.template_method,
        config=ConditionConfig(surface="outline" if args.incoherent else "auto"),
    )
    say(f"surface model: {ref.surface} ({ref.info['surface_reason']})")
    timings["template"] = time.perf_counter() - t
    return ref


def _write_outputs(args: argparse.Namespace, points_radar: np.ndarray, twin, calibration, ref, grid, report: dict):
    """Everything is computed: write the outputs (each atomically)."""
    buf = io.BytesIO()
    np.save(buf, points_radar.astype(np.float64))
    write_bytes_atomic(args.points_out, buf.getvalue())
    if args.mask_out:
        write_image_atomic(args.mask_out, twin.mask.astype(np.uint8) * 255)
    if calibration is not None:
        calibration.save(args.calibration_out)
    if ref is not None:
        from twinfocus.twins.templates import save_template  # lazy: numba (+2.1 s at import)

        assert grid is not None  # a template is made only on a grid
        # the outline and the conditioning travel with it: focus --template runs the outline estimator
        save_template(args.out, ref.template, grid, support=ref.support, info=ref.info)
        if args.support_out:
            write_image_atomic(args.support_out, ref.support.astype(np.uint8) * 255)
    if args.report:
        write_text_atomic(args.report, json.dumps(report, indent=2, default=float) + "\n")
