"""``twinfocus render --out DIR [scene options as twinfocus simulate]``: what the tracking stereo
camera sees of the simulated scene -- left.png, right.png, camera.json (calibration and pose in the
scene frame) and truth.npz (left depth, labels) -- for ``twinfocus twin``."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from twinfocus.cli.simulate import add_layout_arguments, layout_kwargs
from twinfocus.errors import TwinFocusError
from twinfocus.jobs.machine import require_memory
from twinfocus.option_types import DISPLACEMENT, POINT, non_negative_float, non_negative_int, positive_int
from twinfocus.twins.digital_twin.camera import DEFAULT_LEFT_CAMERA_POSITION_M, StereoCamera, pose_matrix
from twinfocus.twins.digital_twin.render import render_memory_bytes, render_scene


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, help="output folder")
    add_layout_arguments(p)
    p.add_argument("--width", type=positive_int, default=1280, help="picture width (default 1280, ZED 2i HD720)")
    p.add_argument("--height-px", type=positive_int, default=720, help="picture height (default 720)")
    p.add_argument("--camera-position-mm", **POINT, help="left camera position in the scene frame (default -60 -80 0)")
    p.add_argument(
        "--extrinsic-error-mm",
        **DISPLACEMENT,
        default=[0.0, 0.0, 0.0],
        help="render from a camera this far from the pose written to camera.json (a mounting error)",
    )
    p.add_argument(
        "--noise-dn", type=non_negative_float, default=2.0, help="sensor noise, 8-bit grey levels (default 2)"
    )
    p.add_argument("--no-clutter", action="store_true", help="plain background instead of a cluttered one")
    p.add_argument("--seed", type=non_negative_int, default=0, help="textures, clutter and noise")


def run(args: argparse.Namespace) -> int:

    from twinfocus.simulation.scenario import Scenario  # lazy: numba, cv2 (+2.1 s at import)

    if args.noise_dn < 0:
        raise TwinFocusError(f"--noise-dn must be >= 0, got {args.noise_dn}")
    sc = Scenario(**layout_kwargs(args))
    _check_memory(sc.scene(), args.width, args.height_px)
    position = (
        DEFAULT_LEFT_CAMERA_POSITION_M
        if args.camera_position_mm is None
        else tuple(v * 1e-3 for v in args.camera_position_mm)
    )
    nominal = StereoCamera.zed2i(args.width, args.height_px, pose_matrix(None, position))
    true_cam = nominal.with_pose(pose_matrix(None, np.asarray(position) + np.asarray(args.extrinsic_error_mm) * 1e-3))
    rendering = render_scene(sc.scene(), true_cam, clutter=not args.no_clutter, noise_dn=args.noise_dn, seed=args.seed)
    rendering.camera = nominal  # camera.json holds what the user believes, not the hidden error
    paths = rendering.save(args.out)
    print(
        json.dumps(
            {k: str(v) for k, v in paths.items()}
            | {"reference_roi": list(sc.reference_roi()), "target_roi": list(sc.target_roi())}
        )
    )
    print(f"wrote {args.out}/ (left.png, right.png, camera.json, truth.npz)", file=sys.stderr)
    return 0


def _check_memory(scene, width: int, height: int) -> None:
    """Refuse, before anything is drawn, a rendering that cannot fit in memory."""

    require_memory(
        render_memory_bytes(scene, width, height),
        "this rendering",
        f"it holds a {width} x {height} picture and the objects' textures: use smaller letters (--height, metres) "
        "or a smaller picture (--width, --height-px)",
    )
