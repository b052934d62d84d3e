"""Player node: publish an MCAP log's messages again (``twinfocus play``, ``ros2 bag play``-like).

Messages go out in log order, paced by their log times divided by ``rate`` (``rate:=0``: as
fast as the bus takes them), optionally ``loop``-ing, restricted to ``topics``, from
``start_offset_s`` after the first message. Like every node, the player waits until the graph
is ready before its first message, and it numbers ``seq`` afresh per topic, so subscribers
detect any loss on the replay itself. Logs cut short by a crash play up to their last
complete message. With ``exit_when_done`` (default) the node ends after the last message
(once ZeroMQ has handed everything to the broker), with status 0: under a launcher the solver
judges the scan. ``twinfocus play`` exits 1 when the log lacked anything (:meth:`Player.loss`,
said in the ``end of log`` line).

Damage: the reader checks every chunk's CRC and skips what fails (named in the start line:
bytes, topics, time range); a message that does not decode, or a radar frame or measurement
whose samples hold NaN or inf (logs written before chunks had CRCs), is skipped and named too.
Nothing damaged is published. A message missing from the log shows as a gap in the ``seq``
numbers the log kept; radar frames (and measurements) published after such a gap carry the
frames missing so far in ``frames_lost`` (capture frames of which no byte arrived, since the
stream began), so the solver's ``capture.frames_lost`` metric and ``n_positions_missing`` count
them: a damaged frame costs that frame, not the scan.
"""

from __future__ import annotations

import dataclasses
import itertools
import sys
import time
from typing import Any

import numpy as np

from msgs import MESSAGE_TYPES, MessageError
from msgs.mcap_log import LogReader
from nodes.runtime.node import Node, run_node
from nodes.runtime.params import REQUIRED, Param
from twinfocus.errors import TwinFocusError


class Player(Node):
    """Replay an MCAP log onto the bus."""

    NAME = "player"
    PARAMS = {
        **Node.PARAMS,
        "log": Param(REQUIRED, "MCAP file to play", type="str"),
        "rate": Param(1.0, "speed factor on the log's timing; 0 = as fast as possible"),
        "loop": Param(False, "start again at the end"),
        "topics": Param([], "topics to play; empty = all except graph/...", type="strs"),
        "start_offset_s": Param(0.0, "skip this many seconds from the start of the log"),
        "latched_topics": Param(
            ["twin/template"],
            "topics whose latest message before start_offset_s is played first "
            "(as a latched / transient-local topic: a template published at the start)",
            type="strs",
        ),
        "exit_when_done": Param(True, "end the node after the last message"),
    }

    def __init__(self, **kw):
        super().__init__(**kw)
        p = self.params
        if p["rate"] < 0:
            raise TwinFocusError(f"node {self.name!r}: rate must be >= 0 (0 = as fast as possible), got {p['rate']}")
        if p["start_offset_s"] < 0:
            raise TwinFocusError(f"node {self.name!r}: start_offset_s must be >= 0, got {p['start_offset_s']}")
        self.reader = LogReader(p["log"])
        if self.reader.start_ns is None:
            raise TwinFocusError(f"{p['log']}: the log holds no messages")
        topics = p["topics"] or [t for t in self.reader.channels if not t.startswith("graph/")]
        missing = [t for t in topics if t not in self.reader.channels]
        topics = [t for t in topics if t in self.reader.channels]
        if not topics:
            raise TwinFocusError(
                f"{p['log']}: none of the topics {', '.join(missing)} is in the log; it has {', '.join(sorted(self.reader.channels))}"
            )
        if missing:
            self.log(f"not in the log, skipped: {', '.join(missing)}")
        self.topics = topics
        for t in topics:
            type_name = self.reader.channels[t]
            self.create_publisher(t, MESSAGE_TYPES.get(type_name))
        self.start_ns = self.reader.start_ns + int(round(p["start_offset_s"] * 1e9))
        self.sent = 0
        self.passes = 0
        self.skipped = 0  # messages that did not decode or held NaN / inf
        self.missing: dict[str, int] = {}  # topic -> messages missing from the log (seq gaps)
        self._last_logged_seq: dict[str, int] = {}

    def on_start(self) -> None:
        r = self.reader
        self._latched = self._latched_before_start()
        n = len(self._latched) + sum(1 for _ in r.messages(self.topics, start_ns=self.start_ns))
        note = "" if r.complete else f" ({r.condition})"
        offset = f" from {self.params['start_offset_s']:g} s in" if self.params["start_offset_s"] else ""
        latched = f" (with {len(self._latched)} latched from before it)" if self._latched else ""
        self.log(
            f"playing {n} message(s){latched} on {', '.join(self.topics)} from {r.path}{offset} "
            f"at rate {self.params['rate']:g}{note}"
        )
        self._begin_pass()

    def _latched_before_start(self) -> list:
        """The latest message of each latched topic logged before the start offset."""
        latched = [t for t in self.params["latched_topics"] if t in self.topics]
        if not latched or self.reader.start_ns is None or self.start_ns <= self.reader.start_ns:
            return []
        last = {}
        for m in self.reader.messages(latched):
            if m.log_time_ns >= self.start_ns:
                break
            last[m.topic] = m
        return sorted(last.values(), key=lambda m: m.log_time_ns)

    def _begin_pass(self) -> None:

        self.passes += 1
        self._last_logged_seq = {}
        self._iter = itertools.chain(
            # Latched messages go out first, at the start's log time (no pause before them),
            # with sequence -1: they stand outside the stream whose gaps are counted.
            ((dataclasses.replace(m, log_time_ns=self.start_ns, sequence=-1)) for m in self._latched),
            self.reader.messages(self.topics, start_ns=self.start_ns),
        )
        self._wall0 = time.monotonic()
        self._log0: int | None = None
        self._held = None
        self.call_later(0, self._step)

    def _step(self) -> None:
        rate = float(self.params["rate"])
        budget = 200  # messages per callback at full speed, so heartbeats keep flowing
        while budget > 0 and self._stop is None:
            m = self._held or next(self._iter, None)
            self._held = None
            if m is None:
                self._end_of_pass()
                return
            if self._log0 is None:
                self._log0 = m.log_time_ns
            if rate > 0:
                due = self._wall0 + (m.log_time_ns - self._log0) / 1e9 / rate
                wait = due - time.monotonic()
                if wait > 0:
                    self._held = m
                    self.call_later(wait, self._step)
                    return
            msg = self._sound(m)
            if msg is None:
                continue
            self._publishers[m.topic].publish(msg)
            self.sent += 1
            budget -= 1
        self.call_later(0, self._step)

    def _sound(self, m) -> Any:
        """The decoded message, with the frames missing so far in ``frames_lost``; None (said
        in a line) when it is damaged."""
        try:
            msg = m.decode()
        except MessageError as exc:
            self.skipped += 1
            self.log(f"skipped a damaged message in the log: {exc}")
            return None
        data = getattr(msg, "data", None)
        if isinstance(data, np.ndarray) and data.dtype.kind in "fc" and not np.isfinite(data).all():
            self.skipped += 1
            self.log(
                f"skipped a damaged message in the log: {m.topic} seq {m.sequence} at "
                f"{(m.log_time_ns - self.reader.start_ns) / 1e9:.3f} s into the log: its samples hold NaN or inf"
            )
            return None
        if m.sequence >= 0:
            last = self._last_logged_seq.get(m.topic)
            self._last_logged_seq[m.topic] = m.sequence
            if last is not None and m.sequence > last + 1:
                gap = m.sequence - last - 1
                self.missing[m.topic] = self.missing.get(m.topic, 0) + gap
                self.log(
                    f"{m.topic}: {gap} message(s) missing from the log before seq {m.sequence} "
                    f"({(m.log_time_ns - self.reader.start_ns) / 1e9:.3f} s into the log)"
                )
        lost = self.missing.get(m.topic, 0)
        if lost and hasattr(msg, "frames_lost"):
            msg = dataclasses.replace(msg, frames_lost=int(msg.frames_lost) + lost)
        return msg

    def _end_of_pass(self) -> None:
        if self.params["loop"]:
            self._begin_pass()
            return
        note = self.loss()
        self.log(f"end of log: published {self.sent} message(s)" + (f"; {note}" if note else ""))
        self.status_message = f"done: {self.sent} messages" + (f"; {note}" if note else "")
        if self.params["exit_when_done"]:
            self.request_shutdown("end of log")

    def loss(self) -> str:
        """What the played log lacked, in one line ("" when it was whole): the messages missing
        (seq gaps) or damaged per topic, and, for a log cut short, the last message of each
        topic played (whatever came after it is not in the file and cannot be counted)."""
        lost = {t: n for t, n in self.missing.items() if n}
        parts = []
        if lost or self.skipped:
            part = "missing from the log or damaged: " + ", ".join(f"{t}: {n}" for t, n in sorted(lost.items()))
            parts.append(part + (f" ({self.skipped} skipped as damaged)" if self.skipped else ""))
        r = self.reader
        if not r.footer:
            last = ", ".join(f"{t} seq {n}" for t, n in sorted(self._last_logged_seq.items()))
            parts.append(
                f"the log is cut at byte {r.valid_bytes} of {r.size}: nothing after {last or 'its start'} "
                "(what came after the cut cannot be counted)"
            )
        elif not r.complete and not lost and not self.skipped:  # damage that left no gap to count
            parts.append(r.condition)
        return "; ".join(parts)


def main(argv: list[str] | None = None) -> int:
    return run_node(Player, argv)


if __name__ == "__main__":
    sys.exit(main())
