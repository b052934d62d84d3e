"""Player node: publish an MCAP log's messages again (``twinfocus play``, ``ros2 bag play``-like).

Messages go out in log order, paced by their log times divided by ``rate`` (``rate:=0``: as
fast as the bus takes them), optionally ``loop``-ing, restricted to ``topics``, from
``start_offset_s`` after the first message. Like every node, the player waits until the graph
is ready before its first message, and it numbers ``seq`` afresh per topic, so subscribers
detect any loss on the replay itself. Logs cut short by a crash play up to their last
complete message. With ``exit_when_done`` (default) the node ends after the last message
(once ZeroMQ has handed everything to the broker).
"""

from __future__ import annotations

import dataclasses
import sys
import time

from msgs import MESSAGE_TYPES, MessageError
from msgs.mcap_log import LogReader
from nodes.node import Node, run_node
from nodes.params import REQUIRED, Param
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
        if not latched or self.start_ns <= self.reader.start_ns:
            return []
        last = {}
        for m in self.reader.messages(latched):
            if m.log_time_ns >= self.start_ns:
                break
            last[m.topic] = m
        return sorted(last.values(), key=lambda m: m.log_time_ns)

    def _begin_pass(self) -> None:
        import itertools

        self.passes += 1
        self._iter = itertools.chain(
            # Latched messages go out first, at the start's log time (no pause before them).
            ((dataclasses.replace(m, log_time_ns=self.start_ns)) for m in self._latched),
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
            try:
                msg = m.decode()
            except MessageError as exc:
                self.log(f"skipped a malformed message in the log: {exc}")
                continue
            self._publishers[m.topic].publish(msg)
            self.sent += 1
            budget -= 1
        self.call_later(0, self._step)

    def _end_of_pass(self) -> None:
        if self.params["loop"]:
            self._begin_pass()
            return
        self.log(f"end of log: published {self.sent} message(s)")
        self.status_message = f"done: {self.sent} messages"
        if self.params["exit_when_done"]:
            self.request_shutdown("end of log")


def main(argv: list[str] | None = None) -> int:
    return run_node(Player, argv)


if __name__ == "__main__":
    sys.exit(main())
