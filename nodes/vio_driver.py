"""VIO driver node: publishes ``vio/pose`` from a backend (simulated tracker, trajectory file,
hardware).

Backends are listed in :data:`nodes.runtime.backends.VIO_BACKENDS` (``sim``: the scene's true trajectory
with a ZED-like error model, ``trajectory_file``: TUM / EuRoC files); hardware backends plug in
there.
"""

from __future__ import annotations

import sys

from msgs import Header, Pose
from nodes.runtime.backends import VIO_BACKENDS, PoseSample
from nodes.runtime.driver import DriverNode
from nodes.runtime.node import run_node


class VioDriver(DriverNode):
    """Publish tracked poses from a backend."""

    NAME = "vio_driver"
    REGISTRY = VIO_BACKENDS
    KIND = "VIO"
    TOPIC = "vio/pose"

    def to_message(self, s: PoseSample) -> Pose:
        b = self.backend
        return Pose(
            header=Header(stamp_ns=int(s.stamp_ns), frame_id=getattr(b, "frame_id", "scene")),
            position_m=s.position_m,
            quat_xyzw=s.quat_xyzw,
            confidence=float(s.confidence),
            child_frame_id=getattr(b, "child_frame_id", "radar"),
        )


def main(argv: list[str] | None = None) -> int:
    return run_node(VioDriver, argv)


if __name__ == "__main__":
    sys.exit(main())
