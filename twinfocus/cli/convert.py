"""``twinfocus convert``: a TI MMWCAS capture folder plus a trajectory file -> a scan file (+ MCAP log).

Example::

    twinfocus convert capture_dir --trajectory zed_poses.txt --extrinsics radar_camera.yaml \\
        --z0 0.6 --out scan.npz --mcap scan.mcap
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from twinfocus.errors import TwinFocusError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", help="MMWCAS capture folder (master_0000_data.bin, master_0000_idx.bin, slave1_..., ...)")
    p.add_argument("--trajectory", required=True, help="camera (VIO) trajectory file, TUM or EuRoC format")
    p.add_argument("--trajectory-format", choices=["auto", "tum", "euroc"], default="auto")
    p.add_argument("--extrinsics", help="camera-radar calibration (YAML); default identity (radar at the camera)")
    p.add_argument("--out", required=True, help="scan file to write (.npz)")
    p.add_argument("--mcap", help="also write an MCAP log (radar/frame and vio/pose) here")
    p.add_argument("--z0", type=float, default=0.6, help="range of the imaging plane for the multistatic correction, m (default 0.6)")
    p.add_argument("--time-offset-s", type=float, default=0.0, help="added to radar time stamps, seconds (default 0)")
    p.add_argument("--align", choices=["auto", "start", "none"], default="auto",
                   help="clock alignment: 'start' puts the first frame on the first pose; 'auto' does that only when "
                        "the clocks do not overlap (default)")
    p.add_argument("--frame", choices=["aperture", "world"], default="aperture",
                   help="'aperture' (default): axes of the first radar pose, origin at the mean radar position; "
                        "'world': the VIO world frame")
    p.add_argument("--keep-first-frame", action="store_true", help="keep the capture card's first frame (known bad)")
    p.add_argument("--keep-flagged", action="store_true", help="keep frames flagged as device-skewed")
    p.add_argument("--n-samples", type=int, default=256, help="ADC samples per chirp (default 256)")
    p.add_argument("--n-loops", type=int, default=1, help="chirp loops per frame (default 1)")
    p.add_argument("--loop", type=int, default=0, help="which loop of each frame to use (default 0)")
    p.add_argument("--f0-hz", type=float, default=76.6e9, help="frequency of the first ADC sample (default 76.6e9)")
    p.add_argument("--slope-hz-per-s", type=float, default=120e12, help="chirp slope (default 120e12)")
    p.add_argument("--fs-hz", type=float, default=8e6, help="ADC sample rate (default 8e6)")
    p.add_argument("--timestamp-unit-ns", type=int, default=1000,
                   help="nanoseconds per tick of the index files' time stamps (default 1000: microseconds)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --mcap file")
    p.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:
    from twinfocus.progress import Progress
    from twinfocus.radar import Chirp, mmwcas_virtual_array
    from twinfocus.sensors.capture_to_scan import scan_from_frames
    from twinfocus.sensors.extrinsics import RadarCameraExtrinsics
    from twinfocus.sensors.ti_mmwcas import MmwcasCapture, MmwcasConfig
    from twinfocus.sensors.trajectory_files import read_trajectory

    out = Path(args.out)
    if out.suffix != ".npz":
        raise TwinFocusError(f"--out must name a .npz file, got {out}")
    if args.mcap and Path(args.mcap).exists() and not args.overwrite:
        raise TwinFocusError(f"{args.mcap}: already exists; choose another name or pass --overwrite")
    if not args.z0 > 0:
        raise TwinFocusError(f"--z0 must be positive, got {args.z0}")
    chirp = Chirp(args.f0_hz, args.slope_hz_per_s, args.fs_hz, args.n_samples)
    config = MmwcasConfig(chirp=chirp, n_loops=args.n_loops, timestamp_unit_ns=args.timestamp_unit_ns)
    poses = read_trajectory(args.trajectory, args.trajectory_format)
    extrinsics = RadarCameraExtrinsics.load(args.extrinsics) if args.extrinsics else RadarCameraExtrinsics()
    say = (lambda *a: None) if args.quiet else (lambda msg: print(f"[convert] {msg}", file=sys.stderr))
    if not args.extrinsics:
        say("no --extrinsics: the radar is taken to sit at the camera (identity transform)")
    array = mmwcas_virtual_array()
    with MmwcasCapture(args.capture, config, skip_first_frame=not args.keep_first_frame) as cap:
        for w in cap.warnings:
            say(f"warning: {w}")
        if args.loop != 0:
            if not 0 <= args.loop < args.n_loops:
                raise TwinFocusError(f"--loop must be in 0..{args.n_loops - 1}, got {args.loop}")
            frames = list(cap.frames(loop=args.loop))
        else:
            frames = cap
        scan, radar_traj, report = scan_from_frames(
            frames, chirp, poses, args.z0, extrinsics, array,
            time_offset_ns=int(round(args.time_offset_s * 1e9)), align=args.align, scene_frame=args.frame,
            drop_flagged=not args.keep_flagged, progress=Progress("convert", enabled=not args.quiet),
        )
        for note in report.notes:
            say(note)
        scan.save(out)
        say(f"{report.n_used} of {report.n_frames} frames -> {out} ({scan.data.shape[0]} x {scan.data.shape[1]} x {scan.data.shape[2]})")
        if args.mcap:
            _write_mcap(Path(args.mcap), scan, radar_traj, array, chirp, extrinsics, Path(args.capture).name, args.overwrite)
            say(f"log -> {args.mcap}")
    print(json.dumps({"scan": str(out), "frames": report.n_frames, "used": report.n_used,
                      "dropped_outside": report.n_outside, "dropped_flagged": report.n_flagged,
                      "time_shift_s": report.time_shift_ns * 1e-9}))
    return 0


def _write_mcap(path: Path, scan, radar_traj, array, chirp, extrinsics, scan_id: str, overwrite: bool) -> None:
    """radar/frame per scan position and vio/pose per trajectory sample, in stamp order."""
    import numpy as np

    from msgs import Header, Pose, RadarFrame
    from msgs.mcap_log import LogWriter
    from nodes.recorder import radar_metadata

    t0, t1 = int(scan.timestamps_ns[0]), int(scan.timestamps_ns[-1])
    in_span = np.flatnonzero((radar_traj.timestamps_ns >= t0) & (radar_traj.timestamps_ns <= t1))
    events = [(int(radar_traj.timestamps_ns[i]), 0, "vio/pose", int(i)) for i in in_span]
    events += [(int(scan.timestamps_ns[m]), 1, "radar/frame", m) for m in range(scan.n_positions)]
    events.sort()
    seq = {"vio/pose": 0, "radar/frame": 0}

    def radar_frame(stamp: int, i: int) -> RadarFrame:
        return RadarFrame(header=Header(stamp, seq["radar/frame"], "radar"), data=scan.data[i], f0_hz=chirp.f0_hz,
                          slope_hz_per_s=chirp.slope_hz_per_s, fs_hz=chirp.fs_hz, channel_offsets_m=array.offsets_m,
                          scan_id=scan_id, index=i, last=i == scan.n_positions - 1)

    with LogWriter(path, overwrite=overwrite) as log:
        # The recorder's records (nodes.recorder.radar_metadata; calibration as launch/live.yaml
        # gives it), so a converted log reads back like a recorded one.
        log.add_metadata("radar", radar_metadata("radar/frame", radar_frame(int(scan.timestamps_ns[0]), 0)))
        log.add_metadata("calibration", {"extrinsics": extrinsics.to_dict()})
        for stamp, _, topic, i in events:
            if topic == "vio/pose":
                conf = 1.0 if radar_traj.confidence is None else float(radar_traj.confidence[i])
                msg = Pose(header=Header(stamp, seq[topic], "scene"), position_m=radar_traj.position_m[i],
                           quat_xyzw=radar_traj.quat_xyzw[i], confidence=conf, child_frame_id="radar")
            else:
                msg = radar_frame(stamp, i)
            seq[topic] += 1
            log.write(topic, msg, log_time_ns=stamp)
