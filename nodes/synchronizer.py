"""Synchronizer node: pairs radar frames with poses by time stamp -> ``sar/measurement``.

For a radar frame stamped t it waits for poses on both sides of t, interpolates the pose
(linear in position, slerp in orientation: :meth:`twinfocus.motion.trajectory.Poses.interpolate`),
applies the camera-to-radar extrinsics when the poses are the camera's
(``child_frame_id == "camera"``), places the frame's virtual channels
(:func:`twinfocus.motion.trajectory.phase_centres`) and publishes the frame's samples with those
phase-centre positions, and the frame's capture gap counts (``frames_lost`` ...), which the
solver turns into each scan's ``capture`` metrics.

A frame is reported (stderr, heartbeat message) and dropped when it cannot be paired: it is
earlier than the first pose, the poses around it are more than ``max_pose_gap_s`` apart, or no
later pose arrives within ``max_wait_s`` of wall-clock time (the tracker stopped). Frames are
handled in arrival order.

End of scan: exactly one measurement of a scan carries ``last=True``, and it is the scan's
final published one, even when the scan's final frame cannot be paired: each measurement is
held back until the fate of the next frame is known (one frame of latency; a frame flagged
``last`` is sent at once).
"""

from __future__ import annotations

import sys
import time
from collections import deque

import numpy as np

from msgs import Header, Pose, RadarFrame, SarMeasurement
from nodes.runtime.node import Node, run_node
from nodes.runtime.params import Param
from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import Poses, phase_centres
from twinfocus.radar.fmcw import VirtualArray
from twinfocus.sensors.capture_to_scan import stream_gaps
from twinfocus.sensors.extrinsics import RadarCameraExtrinsics


class Synchronizer(Node):
    """Pair radar frames with interpolated poses."""

    NAME = "synchronizer"
    PARAMS = {
        **Node.PARAMS,
        "max_pose_gap_s": Param(0.2, "widest interval between two poses to interpolate across, seconds"),
        "max_wait_s": Param(2.0, "how long (wall clock) a frame waits for a later pose before it is reported unpaired"),
        "pose_buffer_s": Param(
            30.0,
            "pose history kept before the latest radar frame paired, seconds of stamps "
            "(poses ahead of the radar are all kept, so a fast tracker loses nothing)",
        ),
        "extrinsics": Param(
            {},
            "camera-to-radar transform for camera poses: {translation_m: [x,y,z], rotation_xyzw: [x,y,z,w]}",
            type="any",
        ),
    }

    def __init__(self, **kw):
        super().__init__(**kw)
        ext = self.params["extrinsics"] or {}
        if not isinstance(ext, dict):
            raise TwinFocusError(f"node {self.name!r}: parameter 'extrinsics' must be a mapping, got {ext!r}")
        self.extrinsics: RadarCameraExtrinsics | None = None
        if ext:
            self.extrinsics = RadarCameraExtrinsics.from_dict(ext, where=f"node {self.name!r} parameter 'extrinsics'")
        self.out = self.create_publisher("sar/measurement")
        self.create_subscription("vio/pose", self.on_pose)
        self.create_subscription("radar/frame", self.on_frame)
        self.stamps: deque[int] = deque()
        self.poses: deque[Pose] = deque()
        self.frames: deque[tuple[RadarFrame, float]] = deque()
        self.held: SarMeasurement | None = None
        self.held_since = 0.0
        self.paired = 0
        self.unpaired = 0

    def on_start(self) -> None:
        self.create_timer(0.05, self.try_pair)

    # -- inputs -------------------------------------------------------------------------------
    def on_pose(self, pose: Pose) -> None:
        t = pose.header.stamp_ns
        if self.stamps and t <= self.stamps[-1]:
            self.log(f"dropped a pose that is not newer than the last one (stamp {t} <= {self.stamps[-1]})")
            return
        if pose.child_frame_id == "camera" and self.extrinsics is None:
            raise TwinFocusError(
                f"node {self.name!r}: poses are the camera's (child_frame_id 'camera') but no 'extrinsics' parameter is set"
            )
        self.stamps.append(t)
        self.poses.append(pose)
        self.try_pair()

    def _prune(self, frame_stamp_ns: int) -> None:
        # Relative to the radar, not to the newest pose: a tracker running ahead of the radar
        # (replay or simulation as fast as possible) would otherwise lose the poses that the
        # radar frames still to come need.
        horizon = frame_stamp_ns - int(self.params["pose_buffer_s"] * 1e9)
        while len(self.stamps) > 2 and self.stamps[1] < horizon:
            self.stamps.popleft()
            self.poses.popleft()

    def on_frame(self, frame: RadarFrame) -> None:
        self.frames.append((frame, time.monotonic()))
        self.try_pair()

    # -- pairing ------------------------------------------------------------------------------
    def try_pair(self) -> None:
        max_wait = float(self.params["max_wait_s"])
        while self.frames:
            frame, arrived = self.frames[0]
            t = frame.header.stamp_ns
            waited = time.monotonic() - arrived
            if not self.stamps or t > self.stamps[-1]:
                if waited < max_wait:
                    break  # a later pose may still come
                why = "no pose received at all" if not self.stamps else f"no pose after it within {max_wait:g} s"
                self._decide(frame, None, why)
            elif t < self.stamps[0]:
                self._decide(
                    frame, None, f"it is earlier than the oldest pose kept ({(self.stamps[0] - t) / 1e9:.3f} s before)"
                )
            else:
                self._decide(frame, self._interpolate(frame), "")
                self._prune(t)
            self.frames.popleft()
        if self.held is not None and not self.frames and time.monotonic() - self.held_since > max_wait:
            self._send(self.held)  # the radar went quiet without marking the scan's end
            self.held = None

    def _interpolate(self, frame: RadarFrame) -> SarMeasurement | str:
        t = frame.header.stamp_ns
        stamps = np.fromiter(self.stamps, dtype=np.int64, count=len(self.stamps))
        i1 = int(np.searchsorted(stamps, t, side="left"))
        i0 = i1 if stamps[i1] == t else i1 - 1
        gap = int(stamps[i1] - stamps[i0])
        if gap > self.params["max_pose_gap_s"] * 1e9:
            return f"the poses around it are {gap / 1e9:.3f} s apart (max_pose_gap_s {self.params['max_pose_gap_s']:g})"
        p0, p1 = self.poses[i0], self.poses[i1]
        bracket = Poses(
            stamps[[i0, i1]],
            np.stack([p0.position_m, p1.position_m]),
            np.stack([p0.quat_xyzw, p1.quat_xyzw]),
        )
        pose = bracket.interpolate(np.array([t], dtype=np.int64))
        if p0.child_frame_id == "camera":
            assert self.extrinsics is not None, "on_pose refuses camera poses without extrinsics"
            pose = self.extrinsics.radar_poses(pose)
        k = frame.channel_offsets_m.shape[0]
        array = VirtualArray(frame.channel_offsets_m, np.zeros(k, int), np.zeros(k, int), np.zeros((k, 2)))
        positions = phase_centres(pose, array)[0]
        return SarMeasurement(
            header=Header(stamp_ns=t, frame_id=p0.header.frame_id or "scene"),
            data=frame.data,
            positions_m=positions,
            f0_hz=frame.f0_hz,
            slope_hz_per_s=frame.slope_hz_per_s,
            fs_hz=frame.fs_hz,
            scan_id=frame.scan_id,
            index=frame.index,
            last=frame.last,
            pose_gap_ns=gap,
            positions_true_m=frame.positions_true_m,
            **_gaps(frame),
        )

    def _decide(self, frame: RadarFrame, result: SarMeasurement | str | None, why: str) -> None:
        if isinstance(result, str):
            why, result = result, None
        if result is None:
            self.unpaired += 1
            self.status_message = f"paired {self.paired}, unpaired {self.unpaired}"
            self.log(
                f"cannot pair radar frame {frame.index} of scan {frame.scan_id!r} (stamp {frame.header.stamp_ns}): {why}"
            )
            if frame.last and self.held is not None and self.held.scan_id == frame.scan_id:
                self.held.last = True
                # the gaps counted up to the scan's end, not only up to the last frame paired
                for k, v in _gaps(frame).items():
                    setattr(self.held, k, v)
                self._send(self.held)
                self.held = None
            return
        self.paired += 1
        self.status_message = f"paired {self.paired}, unpaired {self.unpaired}"
        if self.held is not None:
            if self.held.scan_id != result.scan_id:
                self.held.last = True  # a new scan began: the old one ended unmarked
            self._send(self.held)
            self.held = None
        if result.last:
            self._send(result)
        else:
            self.held = result
            self.held_since = time.monotonic()

    def _send(self, m: SarMeasurement) -> None:
        self.out.publish(m)

    def on_shutdown(self) -> None:
        if self.frames:
            self.unpaired += len(self.frames)
            self.log(f"{len(self.frames)} radar frame(s) were still waiting for a later pose at shutdown")
            self.frames.clear()
        if self.held is not None and self._pub_sock is not None:
            self._send(self.held)
            self.held = None
        if self.paired or self.unpaired:
            self.log(f"paired {self.paired} radar frame(s), could not pair {self.unpaired}")


def _gaps(frame: RadarFrame) -> dict:
    """The frame's capture gaps (counts since the stream began), which its measurement carries on."""

    return stream_gaps(frame.frames_lost, frame.frames_zero_filled, frame.bytes_lost)


def main(argv: list[str] | None = None) -> int:
    return run_node(Synchronizer, argv)


if __name__ == "__main__":
    sys.exit(main())
