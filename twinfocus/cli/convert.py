"""``twinfocus convert``: a TI capture plus a trajectory file -> a scan file (+ MCAP log).

The capture is an MMWCAS cascade folder (``master_0000_idx.bin`` ...) or a DCA1000 capture
(``adc_data.bin`` from mmWave Studio, the DCA1000EVM CLI's ``<prefix>_Raw_N.bin``; see
:mod:`twinfocus.sensors.dca1000_files`). Example::

    twinfocus convert capture_dir --trajectory zed_poses.txt --extrinsics radar_camera.yaml \\
        --z0 0.6 --out scan.npz --mcap scan.mcap
    twinfocus convert adc_data.bin --cfg radar.cfg --dca-json cf.json --trajectory poses.txt --out scan.npz

Beside the scan, ``<out>.capture.json`` records the capture's gaps (frames lost, zero-filled,
bytes lost, frames dropped as flagged) for the metrics of a later ``focus``.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

import numpy as np

from msgs import Header, Pose, RadarFrame
from msgs.mcap_log import LogWriter
from nodes.recorder import radar_metadata
from twinfocus.errors import TwinFocusError
from twinfocus.io.atomic import output_files
from twinfocus.jobs.progress import Progress
from twinfocus.motion.trajectory import phase_centres
from twinfocus.option_types import REGION, finite_float, non_negative_int, positive_float, positive_int
from twinfocus.radar.board import load_board
from twinfocus.radar.calibration import apply_calibration, calibration_for
from twinfocus.radar.fmcw import mmwcas_virtual_array
from twinfocus.sensors.capture_to_scan import capture_report_path, scan_from_frames, stream_gaps
from twinfocus.sensors.chirp_profile import chirp_record, resolve_chirp
from twinfocus.sensors.clock_offset import (
    FOCUS_SCORE_WORDS,
    on_track,
    range_history_offset,
    refine_by_focus,
    tracker_floor_s,
)
from twinfocus.sensors.dca1000 import RawFrameLayout
from twinfocus.sensors.dca1000_files import Dca1000FileCapture, find_cli_json, read_cli_json
from twinfocus.sensors.extrinsics import RadarCameraExtrinsics
from twinfocus.sensors.rosbag2_files import read_any_trajectory
from twinfocus.sensors.ti_cli import RadarCliConfig
from twinfocus.sensors.ti_mmwcas import MmwcasCapture, find_capture_setup, resolve_config


def add_arguments(p: argparse.ArgumentParser) -> None:
    _add_input_arguments(p)
    _add_chirp_arguments(p)
    _add_cascade_arguments(p)
    _add_dca1000_arguments(p)
    _add_clock_arguments(p)
    p.add_argument(
        "--board",
        help="board file (YAML) of the radar's antenna layout (default: TI's MMWCAS-RF-EVM, "
        "twinfocus/radar/boards/mmwcas_rf_evm.yaml; docs/real_array.md)",
    )
    p.add_argument("--quiet", action="store_true")


def _add_input_arguments(p: argparse.ArgumentParser) -> None:
    """The capture, the trajectory and how the two are put together; the outputs."""
    p.add_argument(
        "capture",
        help="MMWCAS capture folder (master_0000_data.bin, master_0000_idx.bin, slave1_..., ...), "
        "or a DCA1000 capture (adc_data.bin, <prefix>_Raw_0.bin, or their folder)",
    )
    p.add_argument(
        "--trajectory",
        required=True,
        help="camera (VIO) trajectory: TUM or EuRoC file, a rosbag2 (folder, .mcap, .db3; with --pose-topic) "
        "or a ZED SDK .svo/.svo2 (needs pyzed)",
    )
    p.add_argument("--pose-topic", help="with a rosbag2 --trajectory: the pose topic, e.g. /zed/zed_node/pose")
    p.add_argument("--pose-frame", help="with a tf2_msgs/TFMessage --pose-topic: the child frame to follow")
    p.add_argument("--trajectory-format", choices=["auto", "tum", "euroc"], default="auto")
    p.add_argument("--extrinsics", help="camera-radar calibration (YAML); default identity (radar at the camera)")
    p.add_argument(
        "--out", required=True, help="scan file to write (.npz; an existing one is refused without --overwrite)"
    )
    p.add_argument("--mcap", help="also write an MCAP log (radar/frame and vio/pose) here")
    p.add_argument(
        "--z0",
        type=positive_float,
        default=0.6,
        help="range of the imaging plane for the multistatic correction, m (default 0.6)",
    )
    p.add_argument(
        "--time-offset-s", type=finite_float, default=0.0, help="added to radar time stamps, seconds (default 0)"
    )
    p.add_argument(
        "--align",
        choices=["scan", "start", "none", "auto"],
        default=None,
        help="clock alignment: 'scan' (default) finds the radar-camera clock offset from the data (the brightest "
        "static scatterer's range history against the trajectory, refined by the sharpness of the scan's brightest "
        "region on the trajectory's poses) and applies it, falling back to 'auto' with a warning when the data "
        "cannot tell; 'start' puts the first frame on the first pose; 'none' trusts the "
        "stamps (plus --time-offset-s); 'auto' is 'start' only when the clocks do not overlap",
    )
    p.add_argument(
        "--frame",
        choices=["aperture", "world"],
        default="aperture",
        help="'aperture' (default): axes of the first radar pose, origin at the mean radar position; "
        "'world': the VIO world frame",
    )
    p.add_argument("--keep-first-frame", action="store_true", help="keep the capture card's first frame (known bad)")
    p.add_argument("--keep-flagged", action="store_true", help="keep frames flagged as device-skewed")


def _add_chirp_arguments(p: argparse.ArgumentParser) -> None:
    """The chirp and the index files' clock when the capture's configuration does not say; the calibration."""
    p.add_argument(
        "--n-samples",
        type=positive_int,
        help="ADC samples per chirp (default: the capture's configuration, else 256)",
    )
    p.add_argument("--n-loops", type=positive_int, help="chirp loops per frame (default: the configuration's, else 1)")
    p.add_argument("--loop", type=non_negative_int, default=0, help="which loop of each frame to use (default 0)")
    p.add_argument(
        "--f0-hz",
        type=positive_float,
        help="frequency of the first ADC sample (default: the configuration's start + slope x ADC start, else 76.6e9)",
    )
    p.add_argument(
        "--slope-hz-per-s", type=positive_float, help="chirp slope (default: the configuration's, else 120e12)"
    )
    p.add_argument("--fs-hz", type=positive_float, help="ADC sample rate (default: the configuration's, else 8e6)")
    p.add_argument(
        "--timestamp-unit-ns",
        type=positive_int,
        default=1000,
        help="nanoseconds per tick of the index files' time stamps (default 1000: microseconds)",
    )
    p.add_argument(
        "--overwrite", action="store_true", help="replace existing output files (--out, its .capture.json, --mcap)"
    )
    p.add_argument(
        "--calibration",
        help="channel calibration to apply (.npz from `twinfocus calibrate`); without one a warning is printed",
    )


def _add_cascade_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "cascade chirp and layout (read from the capture's mmWave Studio JSON / Lua setup when there; "
        "the chirp options above override it, with a note)"
    )
    g.add_argument(
        "--setup",
        help="the capture's configuration: mmWave Studio JSON (*.mmwave.json) or cascade setup Lua "
        "(default: one found in the capture folder, or a .mmwave.json in its parent)",
    )
    g.add_argument(
        "--tx-order",
        help="TxToEnable of the cascade scripts: TX numbers 1..12 in chirp order, comma separated "
        "(default: from the capture's configuration, else 12,11,...,1)",
    )
    g.add_argument(
        "--frame-period-s",
        type=positive_float,
        help="frame period, s (default: from the configuration; MMWCAS 0.1, DCA1000 the .cfg's frameCfg)",
    )
    g.add_argument(
        "--drop-first-frame-of-each-slice",
        action="store_true",
        help="drop the first frame of every capture slice _0000, _0001, ... as TI's cascade processing does "
        "(default: only the capture's first)",
    )


def _add_dca1000_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("DCA1000 capture files")
    g.add_argument("--cfg", help="mmWave SDK .cfg the radar ran (chirp, frame layout, frame period)")
    g.add_argument(
        "--dca-json",
        help="DCA1000EVM CLI JSON the capture was recorded with (reorderEnable, MSBToggle, lvdsMode); "
        "default: a *.json beside the capture holding DCA1000Config",
    )
    g.add_argument(
        "--dca-format",
        choices=["auto", "raw", "reordered", "records"],
        default="auto",
        help="byte layout: 'raw' I0 I1 Q0 Q1 (mmWave Studio adc_data.bin), 'reordered' I0 Q0 I1 Q1 (CLI with "
        "reorderEnable), 'records' (CLI sequence-number records); 'auto' (default) tells them apart",
    )
    g.add_argument(
        "--dca-layout",
        choices=["mmwcas", "cfg"],
        default="mmwcas",
        help="'mmwcas' (default): 12 chirps = TX 0..11 x 16 RX as the emulated rig streams; 'cfg': from --cfg",
    )


def _add_clock_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("the focus stage of --align scan (default: the sharpness of the scan's brightest region)")
    g.add_argument(
        "--reference-roi",
        **REGION,
        default=None,
        help="the region (metres, in the scan's frame) whose focus picks the clock offset; with --template-scan "
        "scored by its match to the template, else by its sharpness",
    )
    g.add_argument(
        "--template-scan",
        help="a motion-stage scan of the reference (.npz, physical twin): its image on --reference-roi is the "
        "template the focus stage matches (a sharper peak than the sharpness', docs/sensors_clock.md)",
    )


def _is_mmwcas(path: Path) -> bool:
    return path.is_dir() and any(path.glob("master_*_idx.bin"))


def run(args: argparse.Namespace) -> int:

    out = Path(args.out)
    if out.suffix != ".npz":
        raise TwinFocusError(f"--out must name a .npz file, got {out}")
    outputs = {"--out": out, "--out's capture report": capture_report_path(out), "--mcap": args.mcap}
    with output_files(outputs, args.overwrite):  # refused or locked before any work
        return _convert(args, out)


def _convert(args: argparse.Namespace, out: Path) -> int:
    from twinfocus.evaluation.runner import write_json_atomic  # lazy: numba, scipy.fft, cv2 (+2.1 s at import)

    if not args.z0 > 0:
        raise TwinFocusError(f"--z0 must be positive, got {args.z0}")
    if args.template_scan and args.reference_roi is None:
        raise TwinFocusError("--template-scan needs --reference-roi (the region its image is matched on)")
    capture = Path(args.capture)
    if not capture.exists():
        raise TwinFocusError(f"{capture}: no such capture file or folder")
    board = load_board(args.board)
    poses, poses_read = read_any_trajectory(args.trajectory, args.trajectory_format, args.pose_topic, args.pose_frame)
    extrinsics = RadarCameraExtrinsics.load(args.extrinsics) if args.extrinsics else RadarCameraExtrinsics()
    say = (lambda *a: None) if args.quiet else (lambda msg: print(f"[convert] {msg}", file=sys.stderr))
    say(poses_read)
    if not args.extrinsics:
        say("no --extrinsics: the radar is taken to sit at the camera (identity transform)")
    array = mmwcas_virtual_array(board)
    gaps: dict = {}
    if _is_mmwcas(capture):
        cap, chirp, chirp_record = _open_mmwcas(args, capture, say)
    else:
        cap, chirp, gaps, chirp_record = _open_dca1000(args, capture, say)
    with cap:
        for w in cap.warnings:
            say(f"warning: {w}")
        if args.loop != 0 and _is_mmwcas(capture):
            if not 0 <= args.loop < cap.config.n_loops:
                raise TwinFocusError(f"--loop must be in 0..{cap.config.n_loops - 1}, got {args.loop}")
            frames = list(cap.frames(loop=args.loop))
        else:
            frames = cap if _is_mmwcas(capture) else cap.frames
        convert = functools.partial(
            scan_from_frames,
            frames,
            chirp,
            poses,
            args.z0,
            extrinsics,
            array,
            scene_frame=args.frame,
            drop_flagged=not args.keep_flagged,
            progress=Progress("convert", enabled=not args.quiet),
            frames_missing=getattr(cap, "frames_missing", 0),
        )
        offset_ns = int(round(args.time_offset_s * 1e9))
        align = args.align or "scan"
        scan, radar_traj, report = convert(time_offset_ns=offset_ns, align="auto" if align == "scan" else align)
        clock = None
        if align == "scan":
            scan, radar_traj, report, clock = _align_by_scan(convert, scan, radar_traj, report, args, say, array)
        for note in report.notes:
            say(note)
        calibration = _calibrate(args, scan, array, board.name, say)
        scan.save(out)
        gaps = {**report.gaps(), **gaps}
        write_json_atomic(
            capture_report_path(out),
            {
                "capture": str(capture),
                **gaps,
                "chirp": chirp_record,
                "board": board.to_dict(),
                "calibration": calibration,
                "clock": clock,
            },
        )
        say(
            f"{report.n_used} of {report.n_frames} frames -> {out} ({scan.data.shape[0]} x {scan.data.shape[1]} x {scan.data.shape[2]})"
        )
        if args.mcap:
            _write_mcap(Path(args.mcap), scan, radar_traj, array, chirp, extrinsics, capture.name, args.overwrite)
            say(f"log -> {args.mcap}")
    print(
        json.dumps(
            {
                "scan": str(out),
                "frames": report.n_frames,
                "used": report.n_used,
                "dropped_outside": report.n_outside,
                "dropped_flagged": report.n_flagged,
                "time_shift_s": report.time_shift_ns * 1e-9,
                "clock": clock,
                **gaps,
            }
        )
    )
    return 0


#: the least clock offset the default --align scan applies from the range history alone, s (a typed
#: --align scan applies any; the focus stage's offset is applied whenever it found one)
DEFAULT_MIN_APPLIED_OFFSET_S = 0.025
#: the default --align scan applies the focus stage's offset past this many of its sigmas
FOCUS_APPLIED_SIGMAS = 2.0


def _align_by_scan(convert, scan, radar_traj, report, args, say, array):
    """``--align scan``: the clock offset from the first conversion's data (the range history),
    refined by the focus of the scan re-sampled on the camera's trajectory, then the conversion
    again with it applied. Returns (scan, radar trajectory, report, the estimate's record or None)."""

    t0 = int(radar_traj.timestamps_ns[0])
    try:
        est = range_history_offset(
            scan.data,
            scan.chirp,
            (scan.timestamps_ns - t0) * 1e-9,
            (radar_traj.timestamps_ns - t0) * 1e-9,
            radar_traj.position_m,
            fit_rate=True,
        )
    except TwinFocusError as exc:
        if args.align == "scan":  # asked for by name: the user wants to know it failed
            raise
        say(f"warning: {exc}; the clocks were aligned as --align auto does")
        return scan, radar_traj, report, None
    say(est.line())
    record = {**est.to_dict(), "stage": "range_history", "range_history": est.to_dict(), "focus": None}

    # the frames' stamps + dt on the camera's trajectory: its own poses through the turns
    positions_at = on_track(
        (radar_traj.timestamps_ns - t0) * 1e-9, phase_centres(radar_traj, array), (scan.timestamps_ns - t0) * 1e-9
    )
    fine = None
    try:
        fine, focus = refine_by_focus(
            scan.data,
            scan.chirp,
            positions_at,
            est,
            args.z0,
            progress=Progress("clock", enabled=not args.quiet),
            floor_s=tracker_floor_s((radar_traj.timestamps_ns - t0) * 1e-9, radar_traj.position_m),
            region_m=args.reference_roi,
            template=_focus_template(args),
        )
        record.update(offset_s=fine.offset_s, sigma_s=fine.sigma_s, method="focus", stage="focus", focus=focus)
        x0, x1, y0, y1, _ = focus["region_m"]
        # By default an offset within two sigma of the first alignment is left (a stage's pose file on
        # the radar's clock, clocks started together): applied, it would move the scan by noise.
        held = args.align is None and not abs(fine.offset_s) > FOCUS_APPLIED_SIGMAS * fine.sigma_s
        say(
            f"clock offset {fine.offset_s * 1e3:+.2f} +- {fine.sigma_s * 1e3:.2f} ms (the range history's refined by "
            f"{FOCUS_SCORE_WORDS[focus['score'], args.reference_roi is not None]}, x {x0:+.3f}..{x1:+.3f} y {y0:+.3f}..{y1:+.3f} m, "
            f"{focus['images_formed']} images, {focus['seconds']:.1f} s) -- "
            + ("not applied (within two sigma of the first alignment)" if held else "applied")
        )
        if held:
            return (
                scan,
                radar_traj,
                report,
                {**record, "applied_shift_s": report.time_shift_ns * 1e-9, "applied": False},
            )
    except TwinFocusError as exc:
        say(f"warning: {exc}; the range history's offset stands")
    if (
        fine is None
        and args.align is None
        and not abs(est.offset_s) > max(3 * est.sigma_s, DEFAULT_MIN_APPLIED_OFFSET_S)
    ):
        # By default only an offset the range history is sure of is applied: on an extended scene it
        # is good to about 10-15 ms (docs/sensors.md), less than the start alignment usually is.
        say("the range history's offset not applied (below what it resolves; focus --clock-search refines)")
        return scan, radar_traj, report, {**record, "applied_shift_s": report.time_shift_ns * 1e-9, "applied": False}
    if fine is None:
        say("the range history's offset applied")
    shift = int(round(record["offset_s"] * 1e9))
    scan, radar_traj, report = convert(time_offset_ns=report.time_shift_ns + shift, align="none")
    return scan, radar_traj, report, {**record, "applied_shift_s": report.time_shift_ns * 1e-9, "applied": True}


def _focus_template(args):
    """The focus stage's template: ``n ->`` --template-scan's image on the n x n --reference-roi grid, else None."""
    if not args.template_scan:
        return None
    from twinfocus.radar.scan import Scan  # lazy: twinfocus.io.arrays
    from twinfocus.twins.templates import scan_template_on  # lazy: numba (+2.1 s at import)

    return scan_template_on(Scan.load(args.template_scan), args.reference_roi)


def _calibrate(args, scan, array, board: str, say) -> dict | None:
    """Apply --calibration to the scan in place (refused when it was made on another board, array or
    chirp); its record (file, SHA-256), or None with a warning."""
    if not args.calibration:
        print(
            "[convert] warning: no --calibration: the channels' own phase, gain and delay errors stay in the data "
            "(make one with `twinfocus calibrate`, docs/calibration.md)",
            file=sys.stderr,
        )
        return None

    correction, record = calibration_for(args.calibration, scan.chirp, array, board)
    scan.data = apply_calibration(scan.data, correction)
    scan.calibration = json.dumps(record)
    say(f"channel calibration {record['file']} applied (sha256 {record['sha256'][:12]})")
    return record


def _open_mmwcas(args, capture: Path, say):

    config, notes = resolve_config(
        capture,
        f0_hz=args.f0_hz,
        slope_hz_per_s=args.slope_hz_per_s,
        fs_hz=args.fs_hz,
        n_samples=args.n_samples,
        n_loops=args.n_loops,
        tx_order=args.tx_order,
        frame_period_s=args.frame_period_s,
        timestamp_unit_ns=args.timestamp_unit_ns,
        setup=args.setup,
    )
    for n in notes:
        say(n)
    cap = MmwcasCapture(
        capture,
        config,
        skip_first_frame=not args.keep_first_frame,
        skip_first_frame_of_each_slice=args.drop_first_frame_of_each_slice,
    )
    setup = args.setup or find_capture_setup(capture)
    return cap, config.chirp, chirp_record(config.chirp, config.profile, setup)


class _Closing:
    """A DCA1000 file capture in the ``with`` form the MMWCAS capture has."""

    def __init__(self, cap):
        self.cap = cap
        self.frames = cap.frames
        self.warnings = cap.warnings

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None


def _open_dca1000(args, capture: Path, say):

    period = args.frame_period_s
    if args.cfg:
        cli_cfg = RadarCliConfig.from_cfg(args.cfg)
        cli_cfg.check_stream_format()
        chirp, profile, notes = resolve_chirp(
            cli_cfg.profile().to_dict(), args.cfg, args.f0_hz, args.slope_hz_per_s, args.fs_hz, args.n_samples
        )
        for n in notes:
            say(n)
        period = period or cli_cfg.frame_period_s
        layout = (
            cli_cfg.raw_layout()
            if args.dca_layout == "cfg"
            else RawFrameLayout(chirp.n_samples, 16, tuple(range(12)), 1, 12)
        )
    else:
        if args.dca_layout == "cfg":
            raise TwinFocusError("--dca-layout cfg needs --cfg (the mmWave SDK .cfg the radar ran)")
        chirp, profile, _ = resolve_chirp({}, None, args.f0_hz, args.slope_hz_per_s, args.fs_hz, args.n_samples)
        layout = RawFrameLayout(chirp.n_samples, 16, tuple(range(12)), args.n_loops or 1, 12)
    if not period:
        raise TwinFocusError(f"{capture}: a DCA1000 capture holds no time stamps; give --frame-period-s or --cfg")
    n_tx = layout.n_tx
    assert n_tx is not None  # RawFrameLayout.__post_init__ fills it in
    if n_tx < 12 or layout.n_rx < 16:
        raise TwinFocusError(
            f"the frames have {n_tx} TX x {layout.n_rx} RX; the 86 virtual channels of the MMWCAS "
            "array need 12 x 16 (--dca-layout mmwcas for the emulated rig)"
        )
    json_path = args.dca_json or find_cli_json(capture)
    settings = read_cli_json(json_path) if json_path else None
    if json_path and not args.dca_json:
        say(f"DCA1000 CLI settings from {json_path}")
    cap = Dca1000FileCapture(capture, layout, period, args.dca_format, settings, loop=args.loop)
    say(
        f"DCA1000 capture read as '{cap.format}' ({len(cap.frames)} frames of {layout.frame_bytes} bytes, "
        f"frame period {period * 1e3:g} ms)"
    )
    st = cap.stats
    gaps = stream_gaps(st.frames_lost, st.frames_zero_filled, st.lost_bytes)
    if st.frames_lost or st.frames_zero_filled:
        say(
            f"capture gaps: {st.frames_lost} frame(s) lost, {st.frames_zero_filled} zero-filled, {st.lost_bytes} bytes lost"
        )
    return _Closing(cap), chirp, gaps, chirp_record(chirp, profile if args.cfg else None, args.cfg)


def _write_mcap(path: Path, scan, radar_traj, array, chirp, extrinsics, scan_id: str, overwrite: bool) -> None:
    """radar/frame per scan position and vio/pose per trajectory sample, in stamp order."""

    t0, t1 = int(scan.timestamps_ns[0]), int(scan.timestamps_ns[-1])
    in_span = np.flatnonzero((radar_traj.timestamps_ns >= t0) & (radar_traj.timestamps_ns <= t1))
    events = [(int(radar_traj.timestamps_ns[i]), 0, "vio/pose", int(i)) for i in in_span]
    events += [(int(scan.timestamps_ns[m]), 1, "radar/frame", m) for m in range(scan.n_positions)]
    events.sort()
    seq = {"vio/pose": 0, "radar/frame": 0}

    def radar_frame(stamp: int, i: int) -> RadarFrame:
        return RadarFrame(
            header=Header(stamp, seq["radar/frame"], "radar"),
            data=scan.data[i],
            f0_hz=chirp.f0_hz,
            slope_hz_per_s=chirp.slope_hz_per_s,
            fs_hz=chirp.fs_hz,
            channel_offsets_m=array.offsets_m,
            scan_id=scan_id,
            index=i,
            last=i == scan.n_positions - 1,
        )

    with LogWriter(path, overwrite=overwrite) as log:
        # The recorder's records (nodes.recorder.radar_metadata; calibration as launch/live.yaml
        # gives it), so a converted log reads back like a recorded one.
        log.add_metadata("radar", radar_metadata("radar/frame", radar_frame(int(scan.timestamps_ns[0]), 0)))
        log.add_metadata("calibration", {"extrinsics": extrinsics.to_dict()})
        for stamp, _, topic, i in events:
            msg: Pose | RadarFrame
            if topic == "vio/pose":
                conf = 1.0 if radar_traj.confidence is None else float(radar_traj.confidence[i])
                msg = Pose(
                    header=Header(stamp, seq[topic], "scene"),
                    position_m=radar_traj.position_m[i],
                    quat_xyzw=radar_traj.quat_xyzw[i],
                    confidence=conf,
                    child_frame_id="radar",
                )
            else:
                msg = radar_frame(stamp, i)
            seq[topic] += 1
            log.write(topic, msg, log_time_ns=stamp)
