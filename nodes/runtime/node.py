"""The node base class: parameters, publish/subscribe by topic, heartbeat, clean shutdown.

A node is one process (or, in tests, one thread) with one event loop::

    class Echo(Node):
        NAME = "echo"
        PARAMS = {**Node.PARAMS, "suffix": Param("!", "text to append")}

        def __init__(self, **kw):
            super().__init__(**kw)
            self.out = self.create_publisher("image/focused")
            self.create_subscription("radar/frame", self.on_frame)

        def on_frame(self, msg):      # called in the loop, one message at a time
            ...
            self.out.publish(result)

Start-up protocol (why no message is lost to ZeroMQ's slow-joiner drop):

1. ``starting``: the node connects (discovery through the broker's control endpoint),
   subscribes to its topics and to ``graph/status``, and finally to a private echo topic.
   Subscriptions travel in order over one connection, so when the echo subscription comes
   back to the node's own XPUB (through the broker), every earlier subscription is
   registered at the broker. Only that exact subscription counts: a subscriber of every topic
   (the recorder) covers the echo topic by prefix as soon as the node connects.
2. ``ready``: the node says so on ``graph/status`` (heartbeat, with the topics it publishes
   and subscribes) and waits until every node named in ``wait_for`` is ready too and, for each
   topic it publishes that one of them subscribes, the subscription has reached its own XPUB
   (from then on ZeroMQ will not filter that topic away). Messages that arrive meanwhile are
   queued, not handled.
3. ``running``: :meth:`on_start` runs, queued messages are handled, timers start.

A latched publisher (``create_publisher(topic, latched=True)``: the template) sends its latest
message again when a node that subscribes to it reports ready after it went out, so a node
started or restarted late still gets it.

Every subscriber counts messages per (topic, publisher) by ``header.seq`` and reports gaps on
stderr and in its heartbeat (``lost``). SIGINT/SIGTERM end the loop; :meth:`on_shutdown` runs,
a final ``stopped`` status goes out, the node waits for that status to come back through the
broker (proof the broker has read everything it published before) and queued outgoing messages
are flushed (both bounded by ``linger_s``).
"""

from __future__ import annotations

import argparse
import heapq
import itertools
import json
import os
import signal
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import zmq

from msgs import TOPIC_TYPES, BusMessage, MessageError, NodeStatus, decode_frames, encode_frames, now_ns
from nodes.runtime.bus import broker_endpoint, check_topic, discover, query_graph, topic_frame
from nodes.runtime.params import Param, describe, resolve
from twinfocus.errors import TwinFocusError

STATUS_TOPIC = "graph/status"
ENV_GRAPH_NODES = "TWINFOCUS_GRAPH_NODES"  # set by the launcher: every node of the launch file
ENV_LAUNCHED = "TWINFOCUS_LAUNCHED"  # set by the launcher: it prefixes output with node names
ENV_LAUNCHER_PID = "TWINFOCUS_LAUNCHER_PID"  # set by the launcher: its pid, our parent while it lives
READY_STATES = ("ready", "running")
WAIT_WORD_S = 5.0  # a node waiting for the graph says why after this long, then every twice that
GONE_STATES = ("stopping", "stopped", "error")  # a node that is ending no longer holds anyone up


@contextmanager
def stop_signals_to(handler: Callable) -> Iterator[None]:
    """SIGINT and SIGTERM go to ``handler`` inside the block and to their earlier handlers after
    it; off the main thread (tests running a node or a launcher in a thread), where Python takes
    no signal handlers, the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)


class Shutdown(Exception):
    """Raised inside the loop to stop the node (carries the exit code)."""

    def __init__(self, code: int = 0, reason: str = ""):
        super().__init__(reason)
        self.code = code
        self.reason = reason


class Publisher:
    """Publishes one topic; sets ``header.seq`` (0, 1, 2, ...) on every message it sends.

    A ``latched`` publisher keeps its latest message and sends it again to every subscriber that
    becomes ready after it went out (a late or restarted node), as a ROS 2 transient-local topic.
    """

    def __init__(self, node: Node, topic: str, msg_type: type[BusMessage] | None, latched: bool = False):
        check_topic(topic)
        self.node = node
        self.topic = topic
        self.msg_type = msg_type or TOPIC_TYPES.get(topic)
        self._frame = topic_frame(topic)
        self.seq = 0
        self.latched = latched
        self.latest: Any = None
        # (node, pid) of the subscribers the latest message has reached (latched topics only)
        self.served: set[tuple[str, int]] = set()

    def publish(self, msg: Any) -> None:
        if self.msg_type is not None and not isinstance(msg, self.msg_type):
            raise TypeError(f"{self.topic} carries {self.msg_type.__name__}, not {type(msg).__name__}")
        msg.header.seq = self.seq
        self.seq += 1
        frames = encode_frames(msg, self.node.name)
        self.node._send_frames([self._frame, *frames])
        self.node._count(self.node._published, self.topic)
        if self.latched:
            self.latest = msg
            # Ready subscribers have their subscriptions at the broker; if any subscription
            # reached us the message left, so each of them got it. The others get it again
            # when their ready heartbeat arrives (Node._serve_latched).
            self.served = self.node._ready_subscribers(self.topic) if self.has_subscribers else set()

    @property
    def has_subscribers(self) -> bool:
        """Whether a subscription covering this topic has reached this node (ZeroMQ would
        otherwise drop the message at the source)."""
        return self.node._covered(self.topic)


class _Timer:
    __slots__ = ("period", "callback", "cancelled")

    def __init__(self, period: float | None, callback: Callable[[], Any]):
        self.period = period
        self.callback = callback
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True


class Node:
    """Base class of every node; see the module docstring for the life cycle."""

    NAME = "node"
    PARAMS: dict[str, Param] = {
        "wait_for": Param(
            [], "nodes that must be ready before this one starts (launcher: every node of the graph)", type="strs"
        ),
        "ready_timeout_s": Param(60.0, "give up (exit 1) if the graph is not ready after this long"),
        "heartbeat_s": Param(1.0, "period of the graph/status heartbeat, seconds"),
        "hwm": Param(0, "ZeroMQ high-water mark of this node's sockets; 0 = unlimited (nothing is dropped)"),
        "linger_s": Param(10.0, "how long to keep flushing queued outgoing messages at shutdown"),
    }
    #: parameters renamed since: old name -> what to write instead (given, they raise saying so)
    RENAMED_PARAMS: dict[str, str] = {}

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        # A subclass method named like one of the runtime's private ones would silently
        # replace it; refuse that when the class is defined.
        clash = sorted(
            n
            for n, v in vars(cls).items()
            if n.startswith("_") and not n.startswith("__") and callable(v) and n in _RUNTIME_PRIVATE
        )
        if clash:
            raise TypeError(f"{cls.__name__} redefines runtime method(s) {', '.join(clash)} of Node; rename them")

    def __init__(
        self,
        name: str | None = None,
        params: dict | None = None,
        argv: list[str] | tuple = (),
        broker: str | None = None,
        context: zmq.Context | None = None,
    ):
        self.name = name or self.NAME
        self.params = resolve(self.name, self.PARAMS, params, argv, self.RENAMED_PARAMS)
        if not self.params["wait_for"] and os.environ.get(ENV_GRAPH_NODES):
            self.params["wait_for"] = [n for n in os.environ[ENV_GRAPH_NODES].split(",") if n]
        self.broker = broker_endpoint(broker)
        # A context of its own: terminating it at shutdown is what makes ZeroMQ deliver what is
        # still queued (up to linger_s) before the process exits; a process that exits with
        # messages in its queues loses them.
        self._own_ctx = context is None
        self.ctx = context or zmq.Context()
        self.state = "starting"
        self.exit_code = 0
        self._prefix = "" if os.environ.get(ENV_LAUNCHED) else f"[{self.name}] "
        self._subs: dict[str, list[tuple[Callable, type | None]]] = {}
        self._wildcard: list[Callable] = []
        self._publishers: dict[str, Publisher] = {}
        self._pub_sock: zmq.Socket | None = None
        self._sub_sock: zmq.Socket | None = None
        self._seen_subs: set[bytes] = set()
        self._timers: list = []
        self._timer_ids = itertools.count()
        self._stop: Shutdown | None = None
        self._received: dict[str, int] = {}
        self._published: dict[str, int] = {}
        self._lost: dict[str, int] = {}
        self._last_seq: dict[tuple[str, str], int] = {}
        self._graph: dict[str, NodeStatus] = {}
        self._pending: deque = deque()
        self._latched_due: set[str] = set()  # latched topics a newly ready subscriber has not had
        self._next_heartbeat = 0.0
        self._status_pub: Publisher | None = None
        self._echo_topic = f"graph/echo/{self.name.lower().replace('-', '_')}_{os.getpid()}_{id(self) % 100000}"
        self.status_message = ""
        # The launcher is our parent; when it dies we are re-parented, which getppid() shows
        # even when the parent-death signal was missed (the launcher died before prctl ran).
        launcher = os.environ.get(ENV_LAUNCHER_PID, "")
        self._launcher_pid = int(launcher) if launcher.isdigit() else None

    # -- API for subclasses ------------------------------------------------------------------
    def log(self, text: str) -> None:
        try:
            print(f"{self._prefix}{text}", file=sys.stderr, flush=True)
        except (BrokenPipeError, ValueError):  # the launcher that read our output is gone
            pass

    def create_publisher(
        self, topic: str, msg_type: type[BusMessage] | None = None, latched: bool = False
    ) -> Publisher:
        """A publisher of ``topic``; ``latched``: its latest message also reaches subscribers that
        start later (the template, a configuration)."""
        if topic in self._publishers:
            return self._publishers[topic]
        pub = Publisher(self, topic, msg_type, latched)
        self._publishers[topic] = pub
        return pub

    def create_subscription(self, topic: str, callback: Callable, msg_type: type[BusMessage] | None = None) -> None:
        """Call ``callback(msg)`` for each message on ``topic``; ``topic="*"`` receives every
        topic and calls ``callback(topic, msg)``."""
        if topic == "*":
            self._wildcard.append(callback)
            if self._sub_sock is not None:
                self._sub_sock.setsockopt(zmq.SUBSCRIBE, b"")
            return
        check_topic(topic)
        self._subs.setdefault(topic, []).append((callback, msg_type or TOPIC_TYPES.get(topic)))
        if self._sub_sock is not None:
            self._sub_sock.setsockopt(zmq.SUBSCRIBE, topic_frame(topic))

    def create_timer(self, period_s: float, callback: Callable[[], Any]) -> _Timer:
        """Call ``callback()`` every ``period_s`` seconds (first call after one period)."""
        t = _Timer(float(period_s), callback)
        self._schedule(time.monotonic() + float(period_s), t)
        return t

    def call_later(self, delay_s: float, callback: Callable[[], Any]) -> _Timer:
        t = _Timer(None, callback)
        self._schedule(time.monotonic() + max(0.0, float(delay_s)), t)
        return t

    def on_start(self) -> None:
        """The graph is ready: start producing (drivers, player)."""

    def on_shutdown(self) -> None:
        """Release resources; called once, also after errors."""

    def request_shutdown(self, reason: str = "", code: int = 0) -> None:
        """Leave the loop after the current callback (e.g. a player at the end of its log)."""
        if self._stop is None:
            self._stop = Shutdown(code, reason)

    @property
    def graph(self) -> dict[str, NodeStatus]:
        """Latest heartbeat of every node heard from, by node name."""
        return self._graph

    def heartbeat_if_due(self) -> None:
        """Publish the heartbeat if its period is over (call it from long computations); ends a
        long computation at once (:class:`Shutdown`) when the launcher is gone."""
        if self.launcher_gone():
            raise Shutdown(1, "the launcher is gone")
        if time.monotonic() >= self._next_heartbeat:
            self._heartbeat()

    def read_heartbeats(self) -> dict[str, NodeStatus]:
        """Take in the heartbeats that have arrived (from inside a long callback or
        :meth:`on_shutdown`, where the loop does not run); other messages wait their turn.
        Returns :attr:`graph`."""
        if self._sub_sock is not None:
            self._poll(0, queue_only=True)
        return self._graph

    def launcher_gone(self) -> bool:
        """True when this node was started by a launcher that has died since."""
        return self._launcher_pid is not None and os.getppid() != self._launcher_pid

    # -- main loop ----------------------------------------------------------------------------
    def spin(self) -> int:
        """Run the node until shutdown; returns the exit code (0 ok, 1 crash, 2 user error)."""
        with stop_signals_to(self._on_signal):
            return self._spin()

    def _spin(self) -> int:
        try:
            self._connect()
            self._await_own_subscriptions()
            self.state = "ready"
            self._heartbeat()
            self._await_graph()
            self.state = "running"
            self._heartbeat()
            self.on_start()
            while self._pending and self._stop is None:
                self._dispatch(self._pending.popleft())
            self._loop()
        except Shutdown as exc:
            self._stop = exc
        except TwinFocusError as exc:
            self.log(f"error: {exc}")
            self._stop = Shutdown(2, str(exc))
        except Exception:
            self.log("crashed:\n" + traceback.format_exc().rstrip())
            self._stop = Shutdown(1, "crashed")
        finally:
            code = self._shutdown_node()
        return code

    def stop(self) -> None:
        """Thread-safe stop request (tests running a node in a thread)."""
        self.request_shutdown("stopped", 0)

    # -- internals ----------------------------------------------------------------------------
    def _on_signal(self, signum, frame) -> None:
        if self.launcher_gone():  # the parent-death signal: end even a long computation now
            self.request_shutdown("the launcher is gone", 1)
            if self.state == "running":
                raise Shutdown(1, "the launcher is gone")
        elif self._launcher_pid is not None:
            # Under a launcher, a signal is either its stop (the code no longer matters) or
            # someone else's: 128 + signal tells the launcher this is no finished job.
            self.request_shutdown(f"received {signal.Signals(signum).name}", 128 + int(signum))
        else:
            self.request_shutdown(f"received {signal.Signals(signum).name}", 0)

    def _connect(self) -> None:
        xsub, xpub = discover(self.broker, self.ctx, timeout_s=min(10.0, self.params["ready_timeout_s"]))
        hwm = int(self.params["hwm"])
        pub = self.ctx.socket(zmq.XPUB)
        pub.setsockopt(zmq.SNDHWM, hwm)
        pub.setsockopt(zmq.RCVHWM, 0)
        # With an unlimited HWM nothing is ever dropped; with a finite one we prefer ZeroMQ's
        # drop (reported downstream as a seq gap) to blocking the whole loop.
        pub.setsockopt(zmq.XPUB_NODROP, 1 if hwm == 0 else 0)
        pub.connect(xsub)
        sub = self.ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.RCVHWM, hwm)
        sub.connect(xpub)
        self._pub_sock, self._sub_sock = pub, sub
        self._status_pub = self.create_publisher(STATUS_TOPIC, NodeStatus)
        sub.setsockopt(zmq.SUBSCRIBE, topic_frame(STATUS_TOPIC))
        if self._wildcard:
            sub.setsockopt(zmq.SUBSCRIBE, b"")
        for topic in self._subs:
            sub.setsockopt(zmq.SUBSCRIBE, topic_frame(topic))
        # Last: its return proves the ones before it are registered at the broker.
        sub.setsockopt(zmq.SUBSCRIBE, topic_frame(self._echo_topic))
        self._poller = zmq.Poller()
        self._poller.register(sub, zmq.POLLIN)
        self._poller.register(pub, zmq.POLLIN)

    def _send_frames(self, frames: list) -> None:
        assert self._pub_sock is not None, "publishing before the node connected"
        try:
            self._pub_sock.send_multipart(frames, copy=False)
        except zmq.Again:  # only with a finite hwm and NODROP off: counts as a drop
            self._count(self._lost, "<send>")

    def _count(self, table: dict, topic: str, n: int = 1) -> None:
        table[topic] = table.get(topic, 0) + n

    def _read_subscriptions(self) -> None:
        assert self._pub_sock is not None, "polled before the node connected"
        while True:
            try:
                ev = self._pub_sock.recv(zmq.NOBLOCK)
            except zmq.Again:
                return
            if ev[:1] == b"\x01":
                self._seen_subs.add(ev[1:])
            elif ev[:1] == b"\x00":
                self._seen_subs.discard(ev[1:])

    def _covered(self, topic: str) -> bool:
        f = topic_frame(topic)
        return any(f.startswith(s) for s in self._seen_subs)

    def _wait_loop(self, done: Callable[[], bool], explain: Callable[[], str]) -> None:
        start = time.monotonic()
        deadline = start + float(self.params["ready_timeout_s"])
        next_word = start + WAIT_WORD_S
        while not done():
            if self._stop is not None:
                raise self._stop
            now = time.monotonic()
            if now > deadline:
                self.log(f"error: graph not ready after {self.params['ready_timeout_s']:g} s: {explain()}")
                raise Shutdown(1, "graph not ready")
            if now >= next_word:  # no silent wait: say what holds us up
                next_word = now + 2 * WAIT_WORD_S
                self.log(
                    f"waiting {now - start:.0f} s for the graph: {explain()} "
                    f"(giving up after {self.params['ready_timeout_s']:g} s)"
                )
            self._poll(min(100, self._ms_to_heartbeat()), queue_only=True)
            if time.monotonic() >= self._next_heartbeat:
                self._heartbeat()

    def _await_own_subscriptions(self) -> None:
        # Exactly our echo: a subscriber of every topic (recorder, bridge) covers the echo topic
        # by prefix long before our own subscriptions have reached the broker.
        echo = topic_frame(self._echo_topic)
        self._wait_loop(
            lambda: echo in self._seen_subs, lambda: "my subscriptions have not come back through the broker yet"
        )

    def _needed(self) -> tuple[list[str], list[str]]:
        """(nodes in wait_for not ready yet, my topics a ready node subscribes that have not reached me)."""
        missing_nodes = []
        missing_topics = []
        for n in self.params["wait_for"]:
            if n == self.name:
                continue
            st = self._graph.get(n)
            if st is not None and st.state in GONE_STATES:
                continue
            if st is None or st.state not in READY_STATES:
                missing_nodes.append(n)
                continue
            for topic in self._publishers:
                if topic == STATUS_TOPIC:
                    continue
                if (topic in st.subscribes or "*" in st.subscribes) and not self._covered(topic):
                    missing_topics.append(f"{topic} (for {n})")
        return missing_nodes, missing_topics

    def _await_graph(self) -> None:
        next_query = [0.0]

        def done():
            a, b = self._needed()
            if a and time.monotonic() >= next_query[0]:
                # Nodes that ended before we connected sent their last heartbeat to no one
                # but the broker: ask it.
                next_query[0] = time.monotonic() + 0.5
                for name, info in query_graph(self.broker, self.ctx).items():
                    if name in a and info.get("state") in GONE_STATES:
                        self._graph[name] = NodeStatus(node=name, state=info["state"])
                a, b = self._needed()
            return not a and not b

        def explain():
            a, b = self._needed()
            parts = []
            if a:
                parts.append("no ready heartbeat from " + ", ".join(a))
            if b:
                parts.append("subscriptions not yet propagated for " + ", ".join(b))
            return "; ".join(parts)

        self._wait_loop(done, explain)

    def _ms_to_heartbeat(self) -> int:
        return max(0, int((self._next_heartbeat - time.monotonic()) * 1000))

    def _heartbeat(self) -> None:
        period = float(self.params["heartbeat_s"])
        if self.state != "running":
            period = min(period, 0.2)  # start-up: let waiting peers see us quickly
        self._next_heartbeat = time.monotonic() + period
        if self._pub_sock is None or self._status_pub is None:
            return
        subs = sorted(self._subs) + (["*"] if self._wildcard else [])
        pubs = sorted(t for t in self._publishers if t != STATUS_TOPIC)
        st = NodeStatus(
            node=self.name,
            state=self.state,
            pid=os.getpid(),
            publishes=pubs,
            subscribes=subs,
            types={
                t: p.msg_type.TYPE for t, p in self._publishers.items() if p.msg_type is not None and t != STATUS_TOPIC
            },
            received=dict(self._received),
            published={k: v for k, v in self._published.items() if k != STATUS_TOPIC},
            lost=dict(self._lost),
            # stopped by a signal not the launcher's: every heartbeat from then on says so, so the
            # launcher names this node at once, not when (or after another node) it ends
            message=self._stop.reason if self._stop is not None and self._stop.code >= 128 else self.status_message,
        )
        st.header.stamp_ns = now_ns()
        self._status_pub.publish(st)

    def _poll(self, timeout_ms: int, queue_only: bool = False) -> None:
        events = dict(self._poller.poll(timeout_ms))
        if self._pub_sock in events:
            self._read_subscriptions()
        if self._sub_sock is not None and self._sub_sock in events:
            for _ in range(200):  # bounded batch, so timers and heartbeats still run
                try:
                    frames = self._sub_sock.recv_multipart(zmq.NOBLOCK, copy=False)
                except zmq.Again:
                    break
                if queue_only:
                    if not self._handle_graph(frames):
                        self._pending.append(frames)
                else:
                    self._dispatch(frames)
                if self._stop is not None:
                    break

    def _handle_graph(self, frames) -> bool:
        """Consume graph/status and echo messages; True if the message was one of those."""
        head = frames[0].bytes
        if head == topic_frame(STATUS_TOPIC):
            try:
                st, _ = decode_frames(frames[1:], NodeStatus, where=f"{STATUS_TOPIC}")
            except MessageError as exc:
                self.log(f"dropped a malformed heartbeat: {exc}")
                return True
            self._graph[st.node] = st
            if st.state in READY_STATES and st.node != self.name:
                self._latched_due.update(
                    p.topic
                    for p in self._publishers.values()
                    if p.latest is not None
                    and (p.topic in st.subscribes or "*" in st.subscribes)
                    and (st.node, st.pid) not in p.served
                )
            # Consumed here unless the node asked for heartbeats (recorder, monitors).
            return not self._wildcard and STATUS_TOPIC not in self._subs
        return False

    def _dispatch(self, frames) -> None:
        head = frames[0].bytes
        if not head.endswith(b"\0"):
            self.log(f"dropped a message with a malformed topic frame {head[:40]!r}")
            return
        if self._handle_graph(frames):
            return
        topic = head[:-1].decode(errors="replace")
        handlers = self._subs.get(topic, [])
        if not handlers and not self._wildcard:
            return  # e.g. our own echo topic
        expect = handlers[0][1] if handlers else TOPIC_TYPES.get(topic)
        try:
            msg, publisher = decode_frames(frames[1:], expect, where=f"{topic}")
        except MessageError as exc:
            self._count(self._lost, topic)
            self.log(f"dropped a malformed message: {exc}")
            return
        self._track_seq(topic, publisher, msg.header.seq)
        for cb, _ in handlers:
            cb(msg)
        for cb in self._wildcard:
            cb(topic, msg)

    def _track_seq(self, topic: str, publisher: str, seq: int) -> None:
        self._count(self._received, topic)
        key = (topic, publisher)
        last = self._last_seq.get(key)
        self._last_seq[key] = seq
        if last is None:
            if seq > 0 and topic != STATUS_TOPIC:
                if publisher in self.params["wait_for"]:
                    # Same graph: the publisher waited for us, so its first message was ours to get.
                    self._count(self._lost, topic, seq)
                    self.log(f"lost {seq} message(s) on {topic} from {publisher}: the first one received has seq {seq}")
                else:
                    self.log(
                        f"joined {topic} from {publisher or '?'} at seq {seq} (earlier messages were before we listened)"
                    )
            return
        if seq == last + 1:
            return
        if seq > last + 1:
            self._count(self._lost, topic, seq - last - 1)
            self.log(f"lost {seq - last - 1} message(s) on {topic} from {publisher or '?'} (seq {last} -> {seq})")
        else:
            self.log(f"seq on {topic} from {publisher or '?'} went back from {last} to {seq} (publisher restarted?)")

    def _schedule(self, due: float, timer: _Timer) -> None:
        heapq.heappush(self._timers, (due, next(self._timer_ids), timer))

    def _run_timers(self) -> None:
        now = time.monotonic()
        while self._timers and self._timers[0][0] <= now and self._stop is None:
            due, _, t = heapq.heappop(self._timers)
            if t.cancelled:
                continue
            if t.period is not None:
                # Fixed rate without drift; skip missed ticks after a long callback.
                nxt = due + t.period
                if nxt < now:
                    nxt = now + t.period
                self._schedule(nxt, t)
            t.callback()

    def _loop(self) -> None:
        while self._stop is None:
            while self._pending and self._stop is None:  # queued by read_heartbeats
                self._dispatch(self._pending.popleft())
            now = time.monotonic()
            wait = self._next_heartbeat - now
            if self._timers:
                wait = min(wait, self._timers[0][0] - now)
            # Bounded so a signal's flag is seen promptly.
            self._poll(int(max(0.0, min(wait, 0.1)) * 1000))
            if self._stop is None and self.launcher_gone():
                self.request_shutdown("the launcher is gone", 1)
                break
            self._run_timers()
            if self._latched_due:
                self._serve_latched()
            if time.monotonic() >= self._next_heartbeat:
                self._heartbeat()

    def _ready_subscribers(self, topic: str) -> set[tuple[str, int]]:
        return {
            (st.node, st.pid)
            for st in self._graph.values()
            if st.node != self.name and st.state in READY_STATES and (topic in st.subscribes or "*" in st.subscribes)
        }

    def _serve_latched(self) -> None:
        """Send each latched topic's latest message again for the subscribers that became ready
        after it went out, once their subscription has reached us (before that ZeroMQ would drop
        it here)."""
        for topic in sorted(self._latched_due):
            pub = self._publishers[topic]
            if not pub.has_subscribers:
                continue
            self._latched_due.discard(topic)
            new = self._ready_subscribers(topic) - pub.served
            if new:
                served = pub.served | new
                pub.publish(pub.latest)
                pub.served = served

    def _flush_through_broker(self) -> None:
        """Wait (up to ``linger_s``) until our final heartbeat comes back through the broker.

        One connection carries everything we published, in order, so its return proves the broker
        has read all of it. Closing before that can lose the tail: a socket closed with unread
        input (a subscription change from a peer that just left) is reset, not closed, and a reset
        makes the broker's kernel discard what it had received but not yet read.
        """
        if self._sub_sock is None or self._status_pub is None:
            return
        final_seq = self._status_pub.seq - 1
        deadline = time.monotonic() + float(self.params["linger_s"])
        while (left := deadline - time.monotonic()) > 0:
            events = dict(self._poller.poll(int(min(left, 0.1) * 1000)))
            if self._pub_sock in events:
                self._read_subscriptions()
            if self._sub_sock not in events:
                continue
            while True:
                try:
                    frames = self._sub_sock.recv_multipart(zmq.NOBLOCK, copy=False)
                except zmq.Again:
                    break
                if frames[0].bytes != topic_frame(STATUS_TOPIC):
                    continue  # shutting down: nothing else is handled any more
                try:
                    st, _ = decode_frames(frames[1:], NodeStatus, where=STATUS_TOPIC)
                except MessageError:
                    continue
                if st.node == self.name and st.pid == os.getpid() and st.header.seq >= final_seq:
                    return
        self.log(
            f"my last messages did not come back through the broker within linger_s={self.params['linger_s']:g} s; "
            "subscribers may miss the end of what I published"
        )

    def _shutdown_node(self) -> int:
        stop = self._stop or Shutdown(0, "")
        code = stop.code
        if self._pub_sock is not None and not self.launcher_gone():
            # Heartbeats may pause while on_shutdown works: tell the launcher's watch that the
            # silence that follows is an ending, not a hang.
            self.state = "stopping"
            try:
                self._heartbeat()
            except Exception:
                pass
        try:
            self.on_shutdown()
        except Exception:
            self.log("error during shutdown:\n" + traceback.format_exc().rstrip())
            code = code or 1
        self.state = "error" if code else "stopped"
        self.status_message = stop.reason
        orphan = self.launcher_gone()
        if orphan:  # the broker died with the launcher: nothing queued can be delivered
            self.log("the launcher is gone; stopping now")
        if self._pub_sock is not None:
            try:
                if not orphan:
                    self._heartbeat()
                    self._flush_through_broker()
            except Exception:
                pass
            self._pub_sock.close(linger=0 if orphan else int(float(self.params["linger_s"]) * 1000))
        if self._sub_sock is not None:
            self._sub_sock.close(linger=0)
        if self._own_ctx:
            self.ctx.term()  # returns once the queued messages are out (or linger_s is over)
        self.exit_code = code
        return code


_RUNTIME_PRIVATE = frozenset(
    n for n, v in vars(Node).items() if n.startswith("_") and not n.startswith("__") and callable(v)
)


# --- process entry point ---------------------------------------------------------------------


def run_node(cls: type[Node], argv: list[str] | None = None) -> int:
    """``python -m nodes.X [--name N] [--broker URL] [--params JSON] [name:=value ...]``."""

    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(
        prog=f"python -m {cls.__module__}",
        description=(cls.__doc__ or cls.NAME).strip().splitlines()[0],
        epilog="parameters (set as name:=value):\n" + describe(cls.PARAMS),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--name", default=cls.NAME, help=f"node name (default {cls.NAME})")
    parser.add_argument(
        "--broker", default=None, help="broker control endpoint (default $TWINFOCUS_BROKER or tcp://127.0.0.1:7447)"
    )
    parser.add_argument("--params", default=None, help="parameters as a JSON object (the launcher uses this)")
    parser.add_argument("assignments", nargs="*", metavar="name:=value")
    args = parser.parse_args(argv)
    try:
        given = json.loads(args.params) if args.params else None
        node = cls(name=args.name, params=given, argv=args.assignments, broker=args.broker)
    except (TwinFocusError, json.JSONDecodeError) as exc:
        print(f"{'' if os.environ.get(ENV_LAUNCHED) else args.name + ': '}error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # stopped while still starting (imports, scene set-up)
        return 130
    return node.spin()
