"""From radar frames and a camera trajectory to a scan: clocks, lever arm, virtual channels.

The steps of ``twinfocus convert``:

1. time alignment: the capture card's clock (MMWCAS: time since the DSP board booted) is not
   the camera's; frames are shifted by ``time_offset_ns`` and, with ``align="start"`` (or
   ``"auto"`` when the two clocks do not overlap at all), so that the first frame falls on
   the first pose. Frames outside the trajectory's time span are dropped (no extrapolation).
2. poses at the frame times (linear position, slerp orientation), camera -> radar through the
   extrinsics, then (``scene_frame="aperture"``, the default) re-expressed in the *aperture
   frame*: axes of the first radar pose (x along the array, y across, z boresight), origin at
   the mean radar position — the scene frame (docs/architecture.md section 4) for a radar swept facing the scene.
3. per frame, the 86 virtual channels (:func:`~twinfocus.sensors.frames.frame_to_virtual_channels`)
   and their phase centres (:func:`~twinfocus.motion.trajectory.phase_centres`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.io.documents import read_json
from twinfocus.motion.trajectory import Poses, matrix_to_quat, phase_centres
from twinfocus.radar.fmcw import Chirp, VirtualArray, mmwcas_virtual_array
from twinfocus.radar.scan import Scan
from twinfocus.sensors.extrinsics import RadarCameraExtrinsics
from twinfocus.sensors.frames import FrameFlag, RadarFrame, frame_to_virtual_channels


@dataclass
class ConversionReport:
    """What happened to the frames."""

    n_frames: int = 0
    n_used: int = 0
    n_flagged: int = 0
    n_outside: int = 0
    time_shift_ns: int = 0
    n_lost: int = 0
    n_zero_filled: int = 0
    n_device_skew: int = 0
    notes: list[str] = field(default_factory=list)

    def gaps(self) -> dict:
        """The capture's gaps as ``<scan>.capture.json`` records them (frames, by flag)."""
        return {
            "frames": self.n_frames,
            "frames_used": self.n_used,
            "frames_dropped_flagged": self.n_flagged,
            "frames_lost": self.n_lost,
            "frames_zero_filled": self.n_zero_filled,
            "frames_device_skew": self.n_device_skew,
        }


def stream_gaps(frames_lost: int, frames_zero_filled: int, bytes_lost: int) -> dict:
    """A capture board's stream gaps (the DCA1000 assembler's counts: frames of which no byte
    arrived, frames zero-filled, bytes missing) under the names of the ``capture`` entry of a
    focus's metrics: ``twinfocus convert`` records a capture's in ``<scan>.capture.json``, the
    solver node puts a live scan's in its metrics."""
    return {
        "frames_lost": int(frames_lost),
        "frames_zero_filled": int(frames_zero_filled),
        "bytes_lost": int(bytes_lost),
    }


def capture_report_path(scan_path) -> Path:
    """Where ``twinfocus convert`` records a scan's capture gaps: ``scan.npz`` -> ``scan.capture.json``."""
    p = Path(scan_path)
    return p.with_name(p.stem + ".capture.json")


def read_capture_report(scan_path) -> dict | None:
    """The capture gaps recorded beside a converted scan (None when the scan has none), for the
    metrics of a focus: frames, frames_used, frames_lost, frames_zero_filled, bytes_lost, ..."""
    p = capture_report_path(scan_path)
    if not p.is_file():
        return None
    try:
        return read_json(p)
    except ValueError:
        raise TwinFocusError(f"{p}: damaged capture report (not JSON)") from None


def align_times(
    radar_ns: np.ndarray, trajectory_ns: np.ndarray, time_offset_ns: int = 0, align: str = "auto"
) -> tuple[int, str | None]:
    """The shift to add to radar time stamps, and a note when it was chosen automatically.

    align : ``"none"`` (shift = time_offset_ns), ``"start"`` (first frame on the first pose,
    plus time_offset_ns), ``"auto"`` (``"start"`` only when the two time spans do not overlap).
    """
    radar_ns = np.asarray(radar_ns, np.int64)
    trajectory_ns = np.asarray(trajectory_ns, np.int64)
    if radar_ns.size == 0:
        raise TwinFocusError("no radar frames to align")
    if align not in ("none", "start", "auto"):
        raise TwinFocusError(f"align must be 'none', 'start' or 'auto', got {align!r}")
    shift = int(time_offset_ns)
    if align == "start":
        return int(trajectory_ns[0] - radar_ns[0]) + shift, None
    if align == "auto":
        lo, hi = radar_ns[0] + shift, radar_ns[-1] + shift
        if hi < trajectory_ns[0] or lo > trajectory_ns[-1]:
            s = int(trajectory_ns[0] - radar_ns[0]) + shift
            return s, (
                f"radar and trajectory clocks do not overlap (radar {radar_ns[0] * 1e-9:.3f}..{radar_ns[-1] * 1e-9:.3f} s, "
                f"trajectory {trajectory_ns[0] * 1e-9:.3f}..{trajectory_ns[-1] * 1e-9:.3f} s): the first frame was put on "
                f"the first pose (shift {s * 1e-9:+.3f} s); give --time-offset-s / --align none if the clocks are synchronised"
            )
    return shift, None


def to_aperture_frame(poses: Poses, rotation: np.ndarray, origin_m: np.ndarray) -> Poses:
    """Poses re-expressed in the frame with axes ``rotation`` (3, 3) (columns: its x, y, z in
    the old frame) and origin ``origin_m`` (3,): p' = R^T (p - o), R' = R^T R_pose."""
    r0 = np.asarray(rotation, np.float64)
    p0 = np.asarray(origin_m, np.float64)
    pos = (poses.position_m - p0) @ r0
    rot = np.einsum("ji,mjk->mik", r0, poses.rotation_matrices())
    return Poses(poses.timestamps_ns, pos, matrix_to_quat(rot), poses.confidence)


def scan_from_frames(
    frames: Iterable[RadarFrame],
    chirp: Chirp,
    camera_poses: Poses,
    z0_m: float,
    extrinsics: RadarCameraExtrinsics | None = None,
    array: VirtualArray | None = None,
    time_offset_ns: int = 0,
    align: str = "auto",
    scene_frame: str = "aperture",
    drop_flagged: bool = True,
    progress: Callable[[int, int], None] | None = None,
    frames_missing: int = 0,
) -> tuple[Scan, Poses, ConversionReport]:
    """Build a :class:`~twinfocus.radar.scan.Scan` from radar frames and camera poses.

    frames : a sequence or iterable of :class:`RadarFrame`; an :class:`~twinfocus.sensors.ti_mmwcas.MmwcasCapture`
        is read lazily (one frame in memory at a time).
    frames_missing : frames the capture knows were never written (an MMWCAS capture's time-stamp
        jumps), counted with the lost ones.
    Returns (scan, radar poses of the trajectory in the scan's frame, report). The scan's
    ``timestamps_ns`` are the frames' aligned stamps (the trajectory's clock).
    """
    array = mmwcas_virtual_array() if array is None else array
    extrinsics = extrinsics or RadarCameraExtrinsics()
    if scene_frame not in ("aperture", "world"):
        raise TwinFocusError(f"scene_frame must be 'aperture' or 'world', got {scene_frame!r}")
    if hasattr(frames, "timestamps_ns") and hasattr(frames, "flags") and hasattr(frames, "__getitem__"):
        # A capture that knows its stamps and flags up front: frames are read one at a time.
        stamps = np.asarray(frames.timestamps_ns, np.int64)
        flag_list = [FrameFlag(int(f)) for f in frames.flags]
    else:
        frames = list(frames)
        stamps = np.array([f.stamp_ns for f in frames], np.int64)
        flag_list = [f.flags for f in frames]
    report = ConversionReport(n_frames=len(stamps))
    report.n_lost = sum(1 for f in flag_list if f & FrameFlag.LOST) + int(frames_missing)
    report.n_zero_filled = sum(1 for f in flag_list if f & FrameFlag.ZERO_FILLED and not f & FrameFlag.LOST)
    report.n_device_skew = sum(1 for f in flag_list if f & FrameFlag.DEVICE_SKEW)
    if stamps.size == 0:
        raise TwinFocusError("the capture holds no frames")
    shift, note = align_times(stamps, camera_poses.timestamps_ns, time_offset_ns, align)
    report.time_shift_ns = shift
    if note:
        report.notes.append(note)
    t = stamps + shift
    inside = (t >= camera_poses.timestamps_ns[0]) & (t <= camera_poses.timestamps_ns[-1])
    usable = np.array([f.usable for f in flag_list]) if drop_flagged else np.ones(stamps.size, bool)
    report.n_outside = int((~inside).sum())
    report.n_flagged = int((inside & ~usable).sum())
    keep = np.flatnonzero(inside & usable)
    if report.n_outside:
        report.notes.append(f"{report.n_outside} frame(s) fall outside the trajectory's time span and were dropped")
    if report.n_flagged:
        report.notes.append(f"{report.n_flagged} flagged frame(s) (zero-filled, lost or device skew) were dropped")
    if keep.size == 0:
        raise TwinFocusError(
            "no frame falls inside the trajectory's time span: check --time-offset-s / --align "
            f"(frames {t[0] * 1e-9:.3f}..{t[-1] * 1e-9:.3f} s, poses "
            f"{camera_poses.timestamps_ns[0] * 1e-9:.3f}..{camera_poses.timestamps_ns[-1] * 1e-9:.3f} s)"
        )
    radar_traj = extrinsics.radar_poses(camera_poses)
    at_frames = radar_traj.interpolate(t[keep])
    if scene_frame == "aperture":
        r0 = at_frames.rotation_matrices()[0]
        o = at_frames.position_m.mean(axis=0)
        at_frames = to_aperture_frame(at_frames, r0, o)
        radar_traj = to_aperture_frame(radar_traj, r0, o)
    data = np.empty((keep.size, array.n_channels, chirp.n_samples), np.complex64)
    for i, m in enumerate(keep):
        data[i] = frame_to_virtual_channels(frames[int(m)].data, chirp, z0_m, array)
        if progress is not None:
            progress(i + 1, keep.size)
    report.n_used = int(keep.size)
    scan = Scan(data=data, positions=phase_centres(at_frames, array), chirp=chirp, timestamps_ns=t[keep])
    return scan, radar_traj, report
