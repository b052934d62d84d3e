"""Recorder node: write topics to an MCAP log (``twinfocus record``, ``ros2 bag record``-like).

Subscribes to the listed topics (all but ``graph/...`` when none are listed; then the nodes'
state changes on ``graph/status`` too, which ``twinfocus export`` turns into Foxglove's log) and
appends every message as it arrives (:class:`msgs.mcap_log.LogWriter`: a chunk with its CRC per
message, handed to the OS at once, so a killed recorder loses at most one message).

A log is replaced only by the log of a run that ended as planned. The recording is written
under a name that says partial (``OUT_STEM.partial-<UTC stamp>-<pid>.mcap`` beside ``out``)
and moved onto ``out`` only when the recorder stops at the planned end of its run
(:meth:`Recorder.unplanned_stop`): started by hand, on Ctrl-C or SIGTERM; under a launcher,
when the launcher stops the graph and no node had failed (last status ``error``), fallen
silent (no heartbeat for ``silent_s`` before the stop) or been named by the launcher as the
node that failed the run (stopped from outside, killed, crashed: :func:`nodes.runtime.bus.query_verdict`).
Any other stop (the launcher killed, a node failing or hanging, the recorder crashing) finishes the partial file and keeps it beside
the earlier log, which stays byte-identical, and says so in one line; a killed recorder leaves
the partial file as it was. A run that recorded nothing leaves no file. A full disk: one line,
the partial file deleted (it would keep the disk full), the earlier log kept.

The radar configuration is stored as the ``radar``
metadata record when the first radar frame or SAR measurement arrives (:func:`radar_metadata`:
flat keys ``source_topic``, the chirp's ``f0_hz`` ``slope_hz_per_s`` ``fs_hz`` ``n_samples``,
``n_channels`` and, from a radar frame, ``channel_offsets_m``); the ``calibration`` parameter as
the ``calibration`` record, verbatim (the launch files give ``{extrinsics: T_camera_radar}``).
``twinfocus convert`` writes the same two records.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from typing import Any

import numpy as np
import zmq

from msgs import NodeStatus, RadarFrame, SarMeasurement, encode, now_ns
from msgs.mcap_log import LogWriteError, LogWriter
from nodes.foxglove_convert import FoxgloveConverter
from nodes.runtime.bus import query_verdict
from nodes.runtime.node import ENV_LAUNCHER_PID, GONE_STATES, Node, run_node
from nodes.runtime.params import REQUIRED, Param
from twinfocus.errors import TwinFocusError


def radar_metadata(topic: str, msg: RadarFrame | SarMeasurement) -> dict:
    """The ``radar`` metadata record of a log, from its first radar message on ``topic``.

    Flat: ``source_topic``, the chirp (:meth:`twinfocus.radar.fmcw.Chirp.to_dict` keys), ``n_channels``
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
        "include_graph": Param(
            False, "with no topic list, record every graph/... message (heartbeats), not only state changes"
        ),
        "overwrite": Param(False, "replace an existing file"),
        "calibration": Param({}, "calibration to store in the log's metadata (mapping)", type="any"),
        "silent_s": Param(
            3.0, "a node not heard from for this long when the graph stops has hung: the log is kept as partial"
        ),
        "foxglove": Param(
            False,
            "also write Foxglove channels (images, poses, clouds, plots, log; nodes/foxglove_convert.py) so the file opens in Foxglove",
        ),
    }

    def __init__(self, **kw):
        super().__init__(**kw)
        # Every parameter is checked before the log file is opened: a refused start leaves no file.
        calib = self.params["calibration"] or {}
        if not isinstance(calib, dict):
            raise TwinFocusError(f"node {self.name!r}: parameter 'calibration' must be a mapping, got {calib!r}")
        self._foxglove = None
        if self.params["foxglove"]:
            self._foxglove = FoxgloveConverter(extrinsics=calib.get("extrinsics") or None)
        self._radar_done = False
        self._last_state: dict[str, tuple] = {}
        self._signalled_ns: int | None = None
        self._gone_at_signal: set[str] | None = None
        self._handlers: dict[int, Any] = {}
        self.writer = LogWriter(self.params["out"], overwrite=self.params["overwrite"], keep_empty=False)
        if calib:
            self.writer.add_metadata("calibration", calib)
        topics = self.params["topics"]
        if topics:
            for t in topics:
                self.create_subscription(t, lambda msg, t=t: self._record(t, msg))
        else:
            self.create_subscription("*", self._record)

    def _record(self, topic: str, msg: Any) -> None:
        if self._foxglove is not None:
            self._record_foxglove(self._foxglove, topic, msg)
        if not self.params["topics"] and topic.startswith("graph/") and not self.params["include_graph"]:
            if not (isinstance(msg, NodeStatus) and self._changed(msg)):
                return
        if not self._radar_done and isinstance(msg, (RadarFrame, SarMeasurement)):
            self._radar_done = True
            self.writer.add_metadata("radar", radar_metadata(topic, msg))
        t = now_ns()
        self.writer.write_blob(topic, msg.TYPE, encode(msg), t, t, msg.header.seq)

    def _changed(self, st: NodeStatus) -> bool:
        """Whether a heartbeat says something new about its node (state, message, losses)."""
        key = (st.state, st.message, tuple(sorted(st.lost.items())))
        if self._last_state.get(st.node) == key:
            return False
        self._last_state[st.node] = key
        return True

    def _record_foxglove(self, converter: FoxgloveConverter, topic: str, msg: Any) -> None:
        # graph/status feeds Foxglove's log channel even when the heartbeats themselves are not recorded
        for rec in converter.convert(topic, msg, now_ns()):
            rec.write_to(self.writer)

    def _note_signal(self, signum, frame) -> None:
        if self._signalled_ns is None:
            self._signalled_ns = now_ns()
            # The launcher stops the graph only after a failed node has ended: a node already
            # gone now ended before the stop; the nodes stopped with us are still running.
            self._gone_at_signal = {n for n, st in self.graph.items() if st.pid and not _running(st.pid)}
        self._handlers[signum](signum, frame)

    def _drain(self, budget_s: float = 1.0) -> None:
        """Record what already reached this node when it was stopped (and learn the nodes' last
        states from it): a node's final status may wait behind a backlog of frames."""
        if self._sub_sock is None:
            return
        end = time.monotonic() + budget_s
        while time.monotonic() < end:
            try:
                frames = self._sub_sock.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                return
            self._dispatch(frames)

    def unplanned_stop(self) -> str:
        """Why this recording did not end as its run planned ("" when it did): the recorder's own
        stop (a crash, a dead launcher) or, under a launcher, a node that had failed or fallen
        silent before the launcher stopped the graph. Failed: last status ``error`` stamped
        before the stop signal reached the recorder, and, when that error is itself a signal
        (``received SIGTERM``: the launcher stops every node that way too), the node's process
        already gone at that moment."""
        stop = self._stop
        code, reason = (stop.code, stop.reason) if stop is not None else (0, "")
        if self._launcher_died(wait_s=1.0 if code in (128 + signal.SIGTERM, 128 + signal.SIGINT) else 0.0):
            return "the launcher is gone"
        if code not in (0, 128 + signal.SIGTERM, 128 + signal.SIGINT):
            return f"the recorder stopped with {reason or f'exit status {code}'}"
        if not os.environ.get(ENV_LAUNCHER_PID):
            return ""  # started by hand: Ctrl-C or SIGTERM is how a recording ends
        others = {n: st for n, st in self.graph.items() if n != self.name}
        before = self._signalled_ns if self._signalled_ns is not None else now_ns()
        gone = self._gone_at_signal if self._gone_at_signal is not None else set(others)
        failed = [
            f"{n} ({st.message or 'error'})"
            for n, st in sorted(others.items())
            if st.state == "error"
            and (n in gone or (st.header.stamp_ns < before and not st.message.startswith("received SIG")))
        ]
        if failed:
            return f"node {', '.join(failed)} failed"
        # the launcher's own word: it names a node stopped from outside or killed (which sends
        # no last status) before it stops the graph
        verdict = query_verdict(self.broker, self.ctx)
        if verdict:
            return verdict
        # Measured against the newest heartbeat heard, not the clock: a recorder starved of CPU
        # hears every node late, a hung node is behind the others.
        newest = max((st.header.stamp_ns for st in self.graph.values()), default=0)
        limit = float(self.params["silent_s"]) * 1e9
        silent = [
            f"{n} (silent {(newest - st.header.stamp_ns) / 1e9:.1f} s)"
            for n, st in sorted(others.items())
            if st.state not in GONE_STATES and newest - st.header.stamp_ns > limit
        ]
        if silent:
            return f"node {', '.join(silent)} stopped answering"
        return ""

    def _launcher_died(self, wait_s: float) -> bool:
        """Whether the launcher that started this node has died, waiting up to ``wait_s`` for it.

        A launcher killed outright dies thread by thread: its children are first handed to a
        sibling thread of the same process and get their parent-death signal while it still
        stands, so a stop by signal looks like the launcher's planned stop for a moment. A
        launcher that stops its graph as planned outlives its nodes, so waiting costs a planned
        stop at most ``wait_s``."""
        pid = self._launcher_pid
        if pid is None:
            return False
        end = time.monotonic() + wait_s
        while True:
            if self.launcher_gone() or not _running(pid):
                return True
            if time.monotonic() >= end:
                return False
            time.sleep(0.02)

    def on_start(self) -> None:
        self.log(f"recording {', '.join(self.params['topics']) or 'all topics'} to {self.writer.path}")
        if threading.current_thread() is threading.main_thread():
            # When the stop signal came, to tell a node that failed before it from the nodes
            # the launcher stops with the same signal.
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._handlers[sig] = signal.getsignal(sig)
                signal.signal(sig, self._note_signal)

    def on_shutdown(self) -> None:
        w = self.writer
        if w.closed:  # a write failed (full disk): said so, partial deleted
            return
        if not self.launcher_gone():  # with the launcher gone the broker is gone too
            try:
                self._drain()
            except LogWriteError as exc:
                self.log(f"error: {exc}")
                return
        why = self.unplanned_stop()
        total = sum(w.counts.values())
        try:
            where = w.close(keep=not why)
        except LogWriteError as exc:
            self.log(f"error: {exc}")
            return
        earlier = f"{w.path} is the earlier log, unchanged" if w.path.exists() else f"{w.path} not written"
        if where is None:
            self.log(f"recorded nothing; {earlier}")
        elif why:
            self.log(f"stopped before the run ended as planned ({why}): kept {total} message(s) as {where}; {earlier}")
        else:
            per = ", ".join(f"{t}: {n}" for t, n in sorted(w.counts.items()))
            self.log(f"wrote {total} message(s) to {where} ({per})")


def _running(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie (Linux: /proc; elsewhere: exists)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[-1].split()[0] != "Z"
    except OSError:
        return True


def main(argv: list[str] | None = None) -> int:
    return run_node(Recorder, argv)


if __name__ == "__main__":
    sys.exit(main())
