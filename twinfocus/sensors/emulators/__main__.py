"""``python -m twinfocus.sensors.emulators``: run the emulated radar, or write a simulated capture."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import Poses, paper_raster
from twinfocus.radar.array_errors import array_error_levels, draw_array_errors
from twinfocus.radar.fmcw import Chirp
from twinfocus.sensors.emulators.mmwcas_capture import write_mmwcas_capture
from twinfocus.sensors.emulators.radar_scene import imperfect_mimo_frames, quantize_iq, simulate_mimo_frames
from twinfocus.sensors.emulators.rig import N_REFERENCE_SCATTERERS, EmulatedRadar, demo_scatterers
from twinfocus.sensors.ti_mmwcas import MmwcasConfig
from twinfocus.sensors.trajectory_files import write_tum


def _radar(args) -> int:
    traj = paper_raster(args.columns, args.rows, args.column_pitch, args.row_pitch, frame_period_s=args.period)
    host, port = args.host_data.rsplit(":", 1)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with EmulatedRadar(
        traj,
        host_data_addr=(host, int(port)),
        config_port=args.config_port,
        sync_file=args.sync_file,
        loss=args.loss,
        reorder=args.reorder,
    ) as rig:
        link = Path(args.cli_link) if args.cli_link else None
        if link is not None:
            link.unlink(missing_ok=True)
            link.symlink_to(rig.cli_port)
        print(
            f"emulated radar: CLI {link or rig.cli_port}, DCA1000 config port {rig.config_addr[0]}:{rig.config_addr[1]}, "
            f"data to {host}:{port}, {len(traj)} frames, sync file {rig.sync_file}",
            file=sys.stderr,
            flush=True,
        )
        try:
            stop.wait()
        finally:
            if link is not None:
                link.unlink(missing_ok=True)
    return 0


def _capture(args) -> int:
    chirp = Chirp(n_samples=args.n_samples)
    cfg = MmwcasConfig(chirp=chirp, frame_period_s=args.period)
    # Capture card clock (since DSP boot, microseconds) and camera clock (epoch) differ, as in real life.
    card_t0 = 123_456_789_000
    traj = paper_raster(
        args.columns,
        args.rows,
        args.column_pitch,
        args.row_pitch,
        frame_period_s=args.period,
        t0_ns=1_700_000_000_000_000_000,
    )
    if args.corner is not None:
        # A still radar facing one corner reflector on its axis: a calibration capture.
        traj = Poses(
            traj.timestamps_ns[: args.frames], np.zeros((args.frames, 3)), np.tile([0.0, 0, 0, 1], (args.frames, 1))
        )
        pts = np.array([[0.0, 0.0, args.corner]])
    else:
        pts = demo_scatterers(args.z)
        if args.reference_only:
            pts = pts[:N_REFERENCE_SCATTERERS]
    if args.array_errors == "none":
        frames = simulate_mimo_frames(chirp, traj, pts)
    else:
        errors = draw_array_errors(array_error_levels(args.array_errors), args.array_seed)
        frames = imperfect_mimo_frames(chirp, traj, pts, errors, snr_db=args.snr_db, rng=args.array_seed + 1)
    # Leakage and DC can exceed the scene's own full scale: the imperfect array's is its peak.
    iq = quantize_iq(frames, full_scale=float(len(pts)) if args.array_errors == "none" else None, headroom=0.9)
    stamps = card_t0 + (traj.timestamps_ns - traj.timestamps_ns[0])
    out = Path(args.folder)
    write_mmwcas_capture(out, iq, stamps, cfg)
    if args.tracking_error_mm > 0:
        # The camera's track, not the radar's true path: what a hand-held capture's trajectory file holds.
        noise = np.random.default_rng(args.seed).normal(scale=args.tracking_error_mm * 1e-3, size=traj.position_m.shape)
        traj = replace(traj, position_m=traj.position_m + noise)
    write_tum(out / "trajectory.txt", traj)
    np.save(out / "scatterers.npy", pts)
    print(f"wrote {len(traj)} frames to {out} and its trajectory to {out / 'trajectory.txt'}", file=sys.stderr)
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m twinfocus.sensors.emulators", description=__doc__)
    sub = p.add_subparsers(dest="what", required=True)
    r = sub.add_parser("radar", help="run the emulated radar CLI + DCA1000 until interrupted")
    r.add_argument("--config-port", type=int, default=4096, help="emulated board's config port on 127.0.0.1")
    r.add_argument("--host-data", default="127.0.0.1:4098", help="host data address ip:port")
    r.add_argument("--cli-link", help="make this symlink point at the CLI pseudo-terminal")
    r.add_argument("--sync-file", help="write the wall-clock start of frame 0 here")
    r.add_argument("--loss", type=float, default=0.0)
    r.add_argument("--reorder", type=float, default=0.0)
    for q in (r, sub.add_parser("capture", help="write a simulated MMWCAS capture folder + trajectory.txt")):
        q.add_argument("--columns", type=int, default=3)
        q.add_argument("--rows", type=int, default=40)
        q.add_argument("--column-pitch", type=float, default=0.082)
        q.add_argument("--row-pitch", type=float, default=0.002)
        q.add_argument("--period", type=float, default=0.05)
    c = sub.choices["capture"]
    c.add_argument("folder")
    c.add_argument("--n-samples", type=int, default=256)
    c.add_argument("--z", type=float, default=0.6)
    c.add_argument(
        "--tracking-error-mm",
        type=float,
        default=0.0,
        help="Gaussian error per axis of the trajectory file's positions, mm (default 0: the true path)",
    )
    c.add_argument("--seed", type=int, default=0, help="seed of the tracking error")
    c.add_argument("--reference-only", action="store_true", help="only the reference (the T), as on a motion stage")
    c.add_argument("--corner", type=float, help="instead of the scene: one corner reflector at this range, radar still")
    c.add_argument("--frames", type=int, default=8, help="with --corner: frames to capture (default 8)")
    c.add_argument(
        "--array-errors", choices=["none", "typical"], default="none", help="the array as hardware is (default none)"
    )
    c.add_argument("--array-seed", type=int, default=0, help="draw of the array's errors (default 0)")
    c.add_argument("--snr-db", type=float, default=None, help="with --array-errors: per-sample SNR (default none)")
    args = p.parse_args(argv)
    try:
        return _radar(args) if args.what == "radar" else _capture(args)
    except TwinFocusError as exc:
        print(f"emulators: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
