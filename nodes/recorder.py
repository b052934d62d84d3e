"""Recorder node: write topics to an MCAP log (``twinfocus record``, ``ros2 bag record``-like).

Subscribes to the listed topics (all but ``graph/...`` when none are listed) and appends every
message as it arrives (:class:`msgs.mcap_log.LogWriter`: unchunked, flushed per message, so a
killed recorder leaves a readable file). The log is written beside ``out`` (``OUT.PID.partial``)
and moved onto ``out`` when the recorder stops having recorded something: a recording over an
earlier log replaces it only then; a run that recorded nothing (no graph, a failed start)
leaves no file and the earlier log as it was; a killed recorder leaves the partial file. The radar configuration is stored as the ``radar``
metadata record when the first radar frame or SAR measurement arrives (:func:`radar_metadata`:
flat keys ``source_topic``, the chirp's ``f0_hz`` ``slope_hz_per_s`` ``fs_hz`` ``n_samples``,
``n_channels`` and, from a radar frame, ``channel_offsets_m``); the ``calibration`` parameter as
the ``calibration`` record, verbatim (the launch files give ``{extrinsics: T_camera_radar}``).
``twinfocus convert`` writes the same two records. On SIGINT/SIGTERM the file is closed with its
summary.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

from msgs import RadarFrame, SarMeasurement, encode, now_ns
from msgs.mcap_log import LogWriter
from nodes.node import Node, run_node
from nodes.params import REQUIRED, Param


def radar_metadata(topic: str, msg: RadarFrame | SarMeasurement) -> dict:
    """The ``radar`` metadata record of a log, from its first radar message on ``topic``.

    Flat: ``source_topic``, the chirp (:meth:`twinfocus.radar.Chirp.to_dict` keys), ``n_channels``
    and, for a :class:`msgs.RadarFrame`, ``channel_offsets_m`` ((K, 3) list, metres). The one
    convention of the recorder and ``twinfocus convert``: ``Chirp(**{k: meta[k] for k in
    ("f0_hz", "slope_hz_per_s", "fs_hz", "n_samples")})`` reads the chirp back from either.
    """
    meta = {"source_topic": topic, **msg.chirp().to_dict(), "n_channels": int(msg.data.shape[0])}
    if isinstance(msg, RadarFrame):
        meta["channel_offsets_m"] = np.asarray(msg.channel_offsets_m, np.float64).tolist()
    return meta


class Recorder(Node):
    """Record topics to an MCAP file."""

    NAME = "recorder"
    PARAMS = {
        **Node.PARAMS,
        "out": Param(REQUIRED, "MCAP file to write (refused if it exists, unless overwrite:=true)", type="str"),
        "topics": Param([], "topics to record; empty = every topic except graph/...", type="strs"),
        "include_graph": Param(False, "with no topic list, also record graph/... (heartbeats)"),
        "overwrite": Param(False, "replace an existing file"),
        "calibration": Param({}, "calibration to store in the log's metadata (mapping)", type="any"),
        "foxglove": Param(
            False,
            "also write Foxglove channels (images, poses, clouds, plots, log; nodes/foxglove_convert.py) so the file opens in Foxglove",
        ),
    }

    def __init__(self, **kw):
        super().__init__(**kw)
        self.writer = LogWriter(self.params["out"], overwrite=self.params["overwrite"], keep_empty=False)
        self._radar_done = False
        calib = self.params["calibration"]
        if calib:
            if not isinstance(calib, dict):
                from twinfocus.errors import TwinFocusError

                raise TwinFocusError(f"node {self.name!r}: parameter 'calibration' must be a mapping, got {calib!r}")
            self.writer.add_metadata("calibration", calib)
        self._foxglove = None
        if self.params["foxglove"]:
            from nodes.foxglove_convert import FoxgloveConverter

            self._foxglove = FoxgloveConverter()
        topics = self.params["topics"]
        if topics:
            for t in topics:
                self.create_subscription(t, lambda msg, t=t: self._record(t, msg))
        else:
            self.create_subscription("*", self._record)

    def _record(self, topic: str, msg: Any) -> None:
        if self._foxglove is not None:
            self._record_foxglove(topic, msg)
        if not self.params["topics"] and topic.startswith("graph/") and not self.params["include_graph"]:
            return
        if not self._radar_done and isinstance(msg, (RadarFrame, SarMeasurement)):
            self._radar_done = True
            self.writer.add_metadata("radar", radar_metadata(topic, msg))
        t = now_ns()
        self.writer.write_blob(topic, msg.TYPE, encode(msg), t, t, msg.header.seq)

    def _record_foxglove(self, topic: str, msg: Any) -> None:
        # graph/status feeds Foxglove's log channel even when the heartbeats themselves are not recorded
        for rec in self._foxglove.convert(topic, msg, now_ns()):
            rec.write_to(self.writer)

    def on_start(self) -> None:
        self.log(f"recording {', '.join(self.params['topics']) or 'all topics'} to {self.writer.path}")

    def on_shutdown(self) -> None:
        if not self.writer.close():
            self.log(
                f"recorded nothing; {self.writer.path} not written"
                + (" (the earlier log is kept)" if self.writer.path.exists() else "")
            )
            return
        total = sum(self.writer.counts.values())
        per = ", ".join(f"{t}: {n}" for t, n in sorted(self.writer.counts.items()))
        self.log(f"wrote {total} message(s) to {self.writer.path}" + (f" ({per})" if per else ""))


def main(argv: list[str] | None = None) -> int:
    return run_node(Recorder, argv)


if __name__ == "__main__":
    sys.exit(main())
