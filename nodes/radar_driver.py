"""Radar driver node: publishes ``radar/frame`` from a backend (simulation, scan file, hardware).

Backends are listed in :data:`nodes.runtime.backends.RADAR_BACKENDS` (``sim``: simulated scene,
``scan_file``: replay of a scan ``.npz``); hardware backends plug in there. Each sample becomes a
:class:`msgs.RadarFrame` carrying the chirp and the virtual channel offsets, so every frame is
self-describing (a log needs no side files).
"""

from __future__ import annotations

import sys

import numpy as np

from msgs import Header, RadarFrame
from nodes.runtime.backends import RADAR_BACKENDS, RadarSample
from nodes.runtime.driver import DriverNode
from nodes.runtime.node import run_node
from twinfocus.sensors.capture_to_scan import stream_gaps


class RadarDriver(DriverNode):
    """Publish radar frames from a backend."""

    NAME = "radar_driver"
    REGISTRY = RADAR_BACKENDS
    KIND = "radar"
    TOPIC = "radar/frame"

    def __init__(self, **kw):
        super().__init__(**kw)
        b = self.backend
        self.offsets = np.asarray(b.channel_offsets_m, dtype=np.float64)
        self.chirp = b.chirp

    def to_message(self, s: RadarSample) -> RadarFrame:
        c = self.chirp
        return RadarFrame(
            header=Header(stamp_ns=int(s.stamp_ns), frame_id="radar"),
            data=s.data,
            f0_hz=c.f0_hz,
            slope_hz_per_s=c.slope_hz_per_s,
            fs_hz=c.fs_hz,
            channel_offsets_m=self.offsets,
            scan_id=s.scan_id,
            index=int(s.index),
            last=bool(s.last),
            positions_true_m=s.positions_true_m,
            **_gap_fields(s.gaps),
        )


def _gap_fields(gaps) -> dict:
    """A backend's capture gaps as the RadarFrame fields (none: the fields' defaults)."""

    return {} if gaps is None else stream_gaps(*gaps)


def main(argv: list[str] | None = None) -> int:
    return run_node(RadarDriver, argv)


if __name__ == "__main__":
    sys.exit(main())
