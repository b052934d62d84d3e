"""``twinfocus calibrate``: a capture of one corner reflector -> the array's channel calibration.

    twinfocus calibrate corner_capture/ --range-m 0.6 --out cal.npz
    twinfocus convert scene_capture/ --trajectory poses.txt --calibration cal.npz --out scan.npz

CAPTURE is anything ``convert`` reads (an MMWCAS folder, a DCA1000 capture, with the same chirp
and layout options) or a scan file (.npz). Writes CAL.npz, its picture (CAL.png, or
--picture) and prints the quality figures (docs/calibration.md says how to read them).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

from twinfocus.cli import convert
from twinfocus.errors import TwinFocusError
from twinfocus.io.atomic import output_files
from twinfocus.option_types import non_negative_int, positive_float, positive_int
from twinfocus.outputs.calibration_pictures import save_calibration_png
from twinfocus.radar.board import load_board
from twinfocus.radar.calibration import find_corner, make_calibration, pair_array
from twinfocus.radar.fmcw import mmwcas_virtual_array
from twinfocus.radar.scan import Scan
from twinfocus.sensors.frames import frame_to_virtual_channels, mmwcas_antenna_positions_body_m

#: convert's options that have no meaning for a still capture of a corner.
_NOT_FOR_CALIBRATION = {
    "help",
    "capture",
    "trajectory",
    "trajectory_format",
    "pose_topic",
    "pose_frame",
    "extrinsics",
    "out",
    "mcap",
    "z0",
    "time_offset_s",
    "align",
    "reference_roi",
    "template_scan",
    "frame",
    "overwrite",
    "quiet",
    "keep_flagged",
    "calibration",
}


def _convert_parser() -> argparse.ArgumentParser:

    p = argparse.ArgumentParser(add_help=False)
    convert.add_arguments(p)
    return p


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", help="capture of one corner reflector: what `convert` reads, or a scan file (.npz)")
    p.add_argument("--range-m", type=positive_float, required=True, help="the corner's range from the radar, metres")
    p.add_argument("--out", required=True, help="calibration file to write (.npz)")
    p.add_argument("--picture", help="where to draw the calibration's picture (default: --out with .png)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out (and its picture)")
    p.add_argument(
        "--window-m",
        type=positive_float,
        default=0.25,
        help="search for the corner within +- this of --range-m (default 0.25)",
    )
    p.add_argument(
        "--reference-channel",
        type=non_negative_int,
        help="virtual channel whose phase and delay are zero (default the middle one)",
    )
    p.add_argument("--max-frames", type=positive_int, default=64, help="frames of the capture to average (default 64)")
    p.add_argument("--quiet", action="store_true")
    g = p.add_argument_group("capture layout and chirp (as `twinfocus convert`)")
    for action in _convert_parser()._actions:
        if action.dest not in _NOT_FOR_CALIBRATION:
            g._add_action(action)


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if out.suffix != ".npz":
        raise TwinFocusError(f"--out must name a .npz file, got {out}")
    picture = Path(args.picture) if args.picture else out.with_suffix(".png")
    with output_files({"--out": out, "--picture": picture}, args.overwrite):
        return _calibrate(args, out, picture)


def _calibrate(args: argparse.Namespace, out: Path, picture: Path) -> int:

    if not args.range_m > 0 or not args.window_m > 0:
        raise TwinFocusError(f"--range-m and --window-m must be positive, got {args.range_m} and {args.window_m}")
    if args.max_frames < 1:
        raise TwinFocusError(f"--max-frames must be at least 1, got {args.max_frames}")
    capture = Path(args.capture)
    if not capture.exists():
        raise TwinFocusError(f"{capture}: no such capture file or folder")
    say = (lambda *a: None) if args.quiet else (lambda msg: print(f"[calibrate] {msg}", file=sys.stderr))
    # The board a capture comes from (--board, as convert takes it): a calibration is refused on another.
    board = load_board(getattr(args, "board", None))
    array = mmwcas_virtual_array(board)
    if capture.suffix == ".npz":
        scan = Scan.load(capture)
        if scan.n_channels != array.n_channels:
            raise TwinFocusError(
                f"{capture}: the scan has {scan.n_channels} channels, the {board.name} array {array.n_channels}"
            )
        chirp = scan.chirp
        data = scan.data[: args.max_frames]
        centres = scan.positions[: args.max_frames]
        pairs = array
        peak = find_corner(data, chirp, args.range_m, args.window_m)
        origin = None
        say(f"scan {capture}: {data.shape[0]} positions x {data.shape[1]} channels")
    else:
        frames, chirp = _read_frames(args, capture, say)
        tx, rx = mmwcas_antenna_positions_body_m(array, board)
        pairs = pair_array(tx, rx)
        peak = find_corner(
            frame_to_virtual_channels(frames, chirp, args.range_m, pairs), chirp, args.range_m, args.window_m
        )
        # The near-field correction is exact at the corner's own range.
        data = frame_to_virtual_channels(frames, chirp, peak.range_m, pairs)
        centres = pairs.offsets_m
        origin = np.zeros(3)
        say(f"{capture}: {frames.shape[0]} frames x {pairs.n_channels} TX-RX pairs")
    cal, report = make_calibration(data, centres, chirp, peak, pairs, array, board.name, args.reference_channel, origin)
    cal.save(out)
    save_calibration_png(picture, cal, report)
    q = cal.quality
    say(
        f"corner at {q['corner_range_m']:.3f} m ({q['peak_snr_db']:.0f} dB); phase spread {q['phase_spread_before_deg']:.0f} "
        f"-> {q['residual_phase_deg_rms']:.1f} deg rms ({q['residual_from']}); peak sharpness "
        f"{q['peak_sharpness_before']:.2f} -> {q['peak_sharpness']:.2f}"
    )
    for w in quality_warnings(q):
        say(f"warning: {w}")
    print(json.dumps({"calibration": str(out), "picture": str(picture), **q}))
    return 0


def quality_warnings(q: dict) -> list[str]:
    """What in a calibration's quality figures says it should not be trusted (docs/calibration.md)."""
    out = []
    if q["residual_phase_deg_rms"] > 10:
        out.append(
            f"residual phase {q['residual_phase_deg_rms']:.1f} deg rms (over 10): noise, a moving corner or a second "
            "reflector; capture again"
        )
    if q["factorisation_residual_deg_rms"] > 15:
        out.append(
            f"the channels do not factor into per-TX x per-RX errors ({q['factorisation_residual_deg_rms']:.0f} deg rms): "
            "another reflector near the corner, or antenna positions that are not the board's"
        )
    return out


def _read_frames(args, capture: Path, say):
    """Up to --max-frames usable frames of a capture, complex64 (F, 12, 16, N), and its chirp."""

    cargs = _convert_parser().parse_args([str(capture), "--trajectory", "-", "--out", "unused.npz"])
    for k, v in vars(args).items():
        if hasattr(cargs, k) and k not in ("capture", "out", "quiet"):
            setattr(cargs, k, v)
    if convert._is_mmwcas(capture):
        cap, chirp, _ = convert._open_mmwcas(cargs, capture, say)
        source = lambda: cap.frames(loop=cargs.loop)
    else:
        cap, chirp, _, _ = convert._open_dca1000(cargs, capture, say)
        source = lambda: iter(cap.frames)
    with cap:
        for w in cap.warnings:
            say(f"warning: {w}")
        frames = [f.data for f in itertools.islice((f for f in source() if f.flags.usable), args.max_frames)]
    if not frames:
        raise TwinFocusError(f"{capture}: no usable frame")
    return np.stack(frames), chirp
