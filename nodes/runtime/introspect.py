"""Introspection nodes behind ``twinfocus topic list|echo|hz`` (``ros2 topic`` alike).

``list`` reads the nodes' heartbeats (each names the topics it publishes, with their types,
and subscribes), so it also shows topics nobody is publishing on right now. ``echo`` prints
messages (arrays summarised by dtype, shape and range). ``hz`` prints the rate, the spread of
the intervals and the bandwidth once per window.
"""

from __future__ import annotations

import time
from typing import Any, TextIO

import numpy as np

from msgs import TOPIC_TYPES
from msgs.schema import field_specs
from nodes.runtime.node import STATUS_TOPIC, Node


class _Monitor(Node):
    """A node that never makes others wait and starts listening at once."""

    def __init__(self, out: TextIO, **kw):
        super().__init__(**kw)
        self.params["wait_for"] = []
        self.out = out

    def _emit(self, text: str) -> None:
        self.out.write(text + "\n")
        self.out.flush()


class TopicList(_Monitor):
    NAME = "topic_list"

    def __init__(self, out: TextIO, duration_s: float = 1.5, verbose: bool = False, **kw):
        super().__init__(out, **kw)
        self.duration_s = duration_s
        self.verbose = verbose

    def on_start(self) -> None:
        self.call_later(self.duration_s, self._report)

    def _report(self) -> None:
        topics: dict[str, dict[str, Any]] = {}
        for node, st in sorted(self.graph.items()):
            if node == self.name or st.state in ("stopped", "error"):
                continue
            for t in st.publishes:
                e = topics.setdefault(t, {"type": "", "pub": [], "sub": [], "count": 0})
                e["type"] = st.types.get(t, e["type"])
                e["pub"].append(node)
                e["count"] += st.published.get(t, 0)
            for t in st.subscribes:
                if t == "*":
                    continue
                topics.setdefault(t, {"type": "", "pub": [], "sub": [], "count": 0})["sub"].append(node)
        if not topics:
            self._emit("(no topics: no node heartbeat heard; is a graph running on this broker?)")
        width = max((len(t) for t in topics), default=0)
        for t in sorted(topics):
            e = topics[t]
            known = TOPIC_TYPES.get(t)
            line = f"{t.ljust(width)}  [{e['type'] or (known.TYPE if known else '?')}]"
            if self.verbose:
                line += f"  published {e['count']}  publishers: {', '.join(e['pub']) or '-'}  subscribers: {', '.join(e['sub']) or '-'}"
            self._emit(line)
        self.request_shutdown("done")


def summarise(msg: Any) -> str:
    """A readable multi-line view of a message, arrays as dtype, shape and range."""
    h = msg.header
    lines = [f"type: {msg.TYPE}", f"header: {{stamp_ns: {h.stamp_ns}, seq: {h.seq}, frame_id: {h.frame_id!r}}}"]
    for name, spec in field_specs(type(msg)):
        v = getattr(msg, name)
        if spec.kind == "array" and v is not None:
            if v.size == 0:
                desc = "empty"
            elif np.iscomplexobj(v):
                a = np.abs(v)
                desc = f"|.| in [{a.min():.4g}, {a.max():.4g}]"
            else:
                desc = f"in [{v.min():.4g}, {v.max():.4g}]"
            if v.size <= 8:
                desc = np.array2string(v, precision=6, separator=", ").replace("\n", "")
            lines.append(f"{name}: {v.dtype.name} {tuple(v.shape)} {desc}")
        else:
            lines.append(f"{name}: {v!r}")
    return "\n".join(lines)


class TopicEcho(_Monitor):
    NAME = "topic_echo"

    def __init__(self, out: TextIO, topic: str, count: int = 0, **kw):
        super().__init__(out, **kw)
        self.topic = topic
        self.count = count
        self.seen = 0
        self.create_subscription(topic, self._on_msg)

    def on_start(self) -> None:
        self.call_later(3.0, self._check_publishers)

    def _check_publishers(self) -> None:
        # Say so rather than wait in silence when nobody publishes the topic.
        if self.seen:
            return
        published = sorted({t for st in self.graph.values() for t in st.publishes})
        if self.topic not in published:
            self.log(
                f"no node publishes {self.topic!r} (yet); published now: {', '.join(published) or 'nothing'}; "
                "waiting (Ctrl-C to stop)"
            )

    def _on_msg(self, msg: Any) -> None:
        self._emit(summarise(msg) + "\n---")
        self.seen += 1
        if self.count and self.seen >= self.count:
            self.request_shutdown("done")


class TopicHz(_Monitor):
    NAME = "topic_hz"

    def __init__(self, out: TextIO, topic: str, window_s: float = 1.0, duration_s: float = 0.0, **kw):
        super().__init__(out, **kw)
        self.topic = topic
        self.window_s = window_s
        self.duration_s = duration_s
        self.times: list[float] = []
        self.nbytes = 0
        self.create_subscription(topic, self._on_msg)

    def on_start(self) -> None:
        self.t0 = time.monotonic()
        self.create_timer(self.window_s, self._report)
        if self.duration_s > 0:
            self.call_later(self.duration_s, lambda: self.request_shutdown("done"))

    def _on_msg(self, msg: Any) -> None:
        self.times.append(time.monotonic())
        self.nbytes += sum(
            getattr(msg, n).nbytes
            for n, s in field_specs(type(msg))
            if s.kind == "array" and getattr(msg, n) is not None
        )

    def _report(self) -> None:
        t = np.asarray(self.times)
        if t.size < 2:
            self._emit(f"{self.topic}: {t.size} message(s) so far, no rate yet")
            return
        dt = np.diff(t)
        span = t[-1] - t[0]
        self._emit(
            f"{self.topic}: average rate {(t.size - 1) / span:.3f} Hz over {t.size} msgs; "
            f"interval min {dt.min() * 1e3:.2f} ms max {dt.max() * 1e3:.2f} ms std {dt.std() * 1e3:.2f} ms; "
            f"array payload {self.nbytes / max(span, 1e-9) / 1e6:.3f} MB/s"
        )


__all__ = ["TopicList", "TopicEcho", "TopicHz", "summarise", "STATUS_TOPIC"]
