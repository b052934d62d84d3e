"""``twinfocus rig --scan CALIB.npz --digital-twin CLOUD.npy --reference-roi X0 X1 Y0 Y1 Z --out
rig.json``: measure the camera's offset from the radar once, from one scan on accurate positions
(a motion-stage scan) of a scene holding an object the camera's cloud shows
(:mod:`twinfocus.twins.digital_twin.rig`). ``focus``/``twin``/``batch`` take the file as ``--rig``.

Everything is measured before anything is written; the rig file and the picture are written
atomically.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.grid import ImageGrid
from twinfocus.io.images import write_image_atomic
from twinfocus.radar.board import load_board
from twinfocus.radar.scan import Scan
from twinfocus.twins.digital_twin.rig import camera_identity, measure_rig, overlay_picture, scan_board
from twinfocus.twins.digital_twin.template import load_points


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scan", required=True, help="scan on accurate positions (motion stage) holding the object")
    p.add_argument("--digital-twin", required=True, metavar="CLOUD", help="the camera's cloud of the object (.npy)")
    p.add_argument("--reference-roi", required=True, nargs=5, type=float, metavar=("X0", "X1", "Y0", "Y1", "Z"),
                   help="region (metres) holding the object")  # fmt: skip
    p.add_argument("--out", required=True, help="rig file to write (.json)")
    p.add_argument("--board", help="board file (YAML) the scan was taken with (default: the scan's, else TI's EVM)")
    p.add_argument("--camera-id", help="the camera's identity (default: CLOUD.json's 'camera', else none)")
    p.add_argument("--picture", help="the cloud's outline over the radar image before/after (PNG; default OUT.png)")
    p.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:

    if not str(args.out).endswith(".json"):
        raise TwinFocusError(f"--out must name a .json file, got {args.out}")
    picture = args.picture or str(Path(args.out).with_suffix(".png"))
    scan = Scan.load(args.scan)
    if args.board:
        board = load_board(args.board).name
    else:
        board = scan_board(scan)
    camera = args.camera_id or camera_identity(args.digital_twin)
    points = load_points(args.digital_twin, allow_non_finite=True)
    grid = ImageGrid.from_roi(args.reference_roi, 48)
    try:
        m = measure_rig(scan, points, grid, board=board, camera=camera)
    except TwinFocusError as exc:
        raise TwinFocusError(f"rig not measured: {exc}") from None
    m.rig.source.update({"scan": str(args.scan), "cloud": str(args.digital_twin)})
    m.rig.save(args.out)
    write_image_atomic(picture, overlay_picture(m.image, m.outline_before, m.outline_after))
    off, sd = m.rig.offset_m * 1e3, m.rig.sd_m * 1e3
    if not args.quiet:
        print(
            "twinfocus rig: camera offset from the radar "
            + ", ".join(f"{a} {o:+.2f} +- {s:.2f} mm" for a, o, s in zip("xyz", off, sd))
            + f" (match {m.match:.2f}; rotation not measured) -> {args.out}, {picture}",
            file=sys.stderr,
        )
    print(json.dumps({"offset_m": m.rig.offset_m.tolist(), "sd_m": m.rig.sd_m.tolist(), "match": m.match,
                      "board": board, "camera": camera, "rig": str(args.out), "picture": picture}))  # fmt: skip
    return 0
