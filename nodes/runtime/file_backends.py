"""File sources: radar frames from a scan file, poses from a TUM / EuRoC trajectory file.

* :class:`ScanFileRadar` replays the ``data`` rows of a scan ``.npz`` (docs/architecture.md section 4) at
  their ``timestamps_ns`` (or ``frame_period_s`` apart when the file has none). The scan's
  positions are *not* sent: positions are the synchronizer's job, from the poses. The virtual
  channel offsets are the MMWCAS array's when K = 86 (``array: mmwcas``), or those of the
  scan's first position about its centroid (``array: scan``; exact when that pose has the
  identity orientation, as in a motion-stage raster).
* :class:`TrajectoryFileVio` replays the poses of a TUM or EuRoC file
  (:func:`twinfocus.sensors.trajectory_files.read_trajectory`), shifted by ``time_offset_ns``
  onto the radar's clock.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from nodes.runtime.backends import PoseSample, RadarSample, check_unknown, option
from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import mmwcas_virtual_array
from twinfocus.radar.scan import Scan
from twinfocus.sensors.trajectory_files import read_trajectory


class ScanFileRadar:
    """Options: ``path`` (scan .npz, required), ``scan_id`` (default the file name),
    ``array`` ("mmwcas" | "scan"), ``frame_period_s`` (0.1, used when the file has no time
    stamps), ``t0_ns`` (0, first stamp then), ``send_truth`` (True: pass ``positions_true`` on)."""

    live = False

    def __init__(self, options: dict):
        where = "radar backend 'scan_file'"
        check_unknown(options, {"path", "scan_id", "array", "frame_period_s", "t0_ns", "send_truth"}, where)
        path = option(options, "path", None, str, where)
        self.scan = Scan.load(path)
        self.scan_id = str(option(options, "scan_id", str(path).rsplit("/", 1)[-1].removesuffix(".npz"), str, where))
        array = option(options, "array", "mmwcas", str, where)
        k = self.scan.n_channels
        if array == "mmwcas":
            offsets = mmwcas_virtual_array().offsets_m
            if offsets.shape[0] != k:
                raise TwinFocusError(
                    f"{path}: the scan has {k} channels, the MMWCAS array {offsets.shape[0]}; use array: scan"
                )
        elif array == "scan":
            first = self.scan.positions[0]
            offsets = first - first.mean(axis=0)
        else:
            raise TwinFocusError(f"{where}: array must be 'mmwcas' or 'scan', got {array!r}")
        self.channel_offsets_m = offsets
        self.chirp = self.scan.chirp
        if self.scan.timestamps_ns is not None:
            self.stamps = self.scan.timestamps_ns.astype(np.int64)
        else:
            period = option(options, "frame_period_s", 0.1, float, where)
            t0 = int(option(options, "t0_ns", 0, int, where))
            self.stamps = t0 + np.round(np.arange(self.scan.n_positions) * period * 1e9).astype(np.int64)
        self.send_truth = bool(option(options, "send_truth", True, bool, where))

    def samples(self) -> Iterator[RadarSample]:
        s = self.scan
        truth = s.positions_true if self.send_truth else None
        for m in range(s.n_positions):
            yield RadarSample(
                stamp_ns=int(self.stamps[m]),
                data=s.data[m].astype(np.complex64, copy=False),
                scan_id=self.scan_id,
                index=m,
                last=m == s.n_positions - 1,
                positions_true_m=None if truth is None else truth[m],
            )

    def close(self) -> None:
        pass


class TrajectoryFileVio:
    """Options: ``path`` (TUM or EuRoC file, required), ``format`` ("auto" | "tum" | "euroc"),
    ``time_offset_ns`` (0: added to every stamp), ``child_frame_id`` ("radar", or "camera" when
    the file tracks the camera and the synchronizer must apply the extrinsics)."""

    live = False
    frame_id = "scene"

    def __init__(self, options: dict):

        where = "VIO backend 'trajectory_file'"
        check_unknown(options, {"path", "format", "time_offset_ns", "child_frame_id"}, where)
        path = option(options, "path", None, str, where)
        self.poses = read_trajectory(path, option(options, "format", "auto", str, where))
        self.offset = int(option(options, "time_offset_ns", 0, int, where))
        self.child_frame_id = option(options, "child_frame_id", "radar", str, where)

    def samples(self) -> Iterator[PoseSample]:
        p = self.poses
        conf = p.confidence if p.confidence is not None else np.ones(len(p))
        for i in range(len(p)):
            yield PoseSample(int(p.timestamps_ns[i]) + self.offset, p.position_m[i], p.quat_xyzw[i], float(conf[i]))

    def close(self) -> None:
        pass
