"""The message bus: one XSUB/XPUB proxy (the broker) and the topic framing every node uses.

Wiring (docs/architecture.md section 4, docs/node_graph.md):

* The broker binds one **well-known control endpoint** (default ``tcp://127.0.0.1:7447``,
  loopback only) and two data sockets on free ports of the same interface: an XSUB that
  publishers connect to and an XPUB that subscribers connect to, joined by ``zmq.proxy``.
  A node asks the control endpoint for the two data ports (discovery), so nothing but the
  control endpoint has to be agreed on.
* A message is a multipart ZeroMQ message ``[topic + b"\\0", envelope, buffers...]``. ZeroMQ
  filters by byte prefix; ending the topic frame with NUL and subscribing to ``topic + b"\\0"``
  makes the filter an exact match (``radar/frame`` never receives ``radar/frame_raw``).
  Subscribing to ``b""`` receives every topic (recorder, ``topic echo``).
* Nodes publish through an XPUB socket, not a PUB, so they *see* the subscriptions that
  reach them: that is how a publisher knows its messages will not be filtered away before
  anyone listens (ZeroMQ's slow-joiner drop), see :mod:`nodes.runtime.node`.
* High-water marks are 0 (unlimited) on the data path by default and the XPUBs set
  ``XPUB_NODROP``, so under load messages queue instead of being dropped silently; a node may
  ask for a finite ``hwm`` and then any drop shows up as a ``seq`` gap at the subscriber.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time
import uuid
from urllib.parse import urlsplit

import zmq

from msgs import MessageError, NodeStatus, decode_frames
from twinfocus.errors import TwinFocusError

DEFAULT_BROKER = "tcp://127.0.0.1:7447"
STATUS_FRAME = b"graph/status\0"
ENV_BROKER = "TWINFOCUS_BROKER"


def broker_endpoint(explicit: str | None = None) -> str:
    """The control endpoint: ``explicit``, else ``$TWINFOCUS_BROKER``, else the loopback default."""
    return explicit or os.environ.get(ENV_BROKER) or DEFAULT_BROKER


def topic_frame(topic: str) -> bytes:
    """First frame of a message on ``topic`` (exact-match filtering: topic + NUL)."""
    check_topic(topic)
    return topic.encode() + b"\0"


def check_topic(topic: str) -> None:
    """Topics are ``/``-separated lower_snake tokens (``radar/frame``, ``graph/status``)."""
    tokens = topic.split("/")
    ok = bool(topic) and all(t and all(c.islower() or c.isdigit() or c == "_" for c in t) for t in tokens)
    if not ok:
        raise TwinFocusError(f"bad topic name {topic!r}: use '/'-separated lower_snake tokens, e.g. 'radar/frame'")


def _host_port(endpoint: str) -> tuple[str, int]:
    u = urlsplit(endpoint)
    if u.scheme != "tcp" or not u.hostname or u.port is None:
        raise TwinFocusError(f"broker endpoint must look like tcp://HOST:PORT, got {endpoint!r}")
    return u.hostname, u.port


class Broker:
    """The XSUB/XPUB proxy plus its discovery endpoint, run in two background threads.

    ``Broker("tcp://127.0.0.1:0")`` picks a free control port (see :attr:`endpoint` after
    :meth:`start`). Binding to a non-loopback address is allowed but must be asked for.
    """

    def __init__(self, endpoint: str | None = None, context: zmq.Context | None = None):
        self.requested = broker_endpoint(endpoint)
        self.host, self.port = _host_port(self.requested)
        self.ctx = context or zmq.Context.instance()
        self.endpoint = ""
        self.xsub_port = 0
        self.xpub_port = 0
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._threads: list[threading.Thread] = []
        # unique per broker: id(self) can be reused by the next broker before ZeroMQ has released
        # the previous one's inproc name ("Address already in use")
        self._ctrl_addr = f"inproc://broker-steer-{uuid.uuid4().hex}"
        self._graph: dict[str, dict] = {}  # latest heartbeat of every node, for late joiners
        self._graph_lock = threading.Lock()
        self._verdict = ""  # why the launcher stops the graph as a failed run (empty: it does not)

    # -- lifecycle --------------------------------------------------------------------------
    def start(self, timeout_s: float = 5.0) -> Broker:
        steer = self.ctx.socket(zmq.PAIR)
        steer.bind(self._ctrl_addr)
        self._steer = steer
        t = threading.Thread(target=self._proxy_thread, name="broker-proxy", daemon=True)
        t.start()
        self._threads.append(t)
        if not self._ready.wait(timeout_s) or self._error:
            self.stop()
            raise TwinFocusError(f"broker could not start on {self.requested}: {self._error}")
        self._ready.clear()
        t = threading.Thread(target=self._control_thread, name="broker-control", daemon=True)
        t.start()
        self._threads.append(t)
        if not self._ready.wait(timeout_s) or self._error:
            self.stop()
            raise TwinFocusError(f"broker could not bind its control endpoint {self.requested}: {self._error}")
        return self

    def stop(self) -> None:
        self._stop.set()
        try:
            self._steer.send(b"TERMINATE")
        except Exception:
            pass
        for t in self._threads:
            t.join(timeout=5)
        try:
            self._steer.close(linger=0)
        except Exception:
            pass

    def __enter__(self) -> Broker:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- threads ----------------------------------------------------------------------------
    def _proxy_thread(self) -> None:
        try:
            xsub = self.ctx.socket(zmq.XSUB)
            xpub = self.ctx.socket(zmq.XPUB)
            steer = self.ctx.socket(zmq.PAIR)
            steer.connect(self._ctrl_addr)
            for s in (xsub, xpub):
                s.setsockopt(zmq.SNDHWM, 0)
                s.setsockopt(zmq.RCVHWM, 0)
                s.setsockopt(zmq.LINGER, 0)
            xpub.setsockopt(zmq.XPUB_NODROP, 1)
            self.xsub_port = xsub.bind_to_random_port(f"tcp://{self.host}")
            self.xpub_port = xpub.bind_to_random_port(f"tcp://{self.host}")
        except Exception as exc:  # reported by start()
            self._error = exc
            self._ready.set()
            return
        self._ready.set()
        try:
            zmq.proxy_steerable(xsub, xpub, None, steer)
        except zmq.ContextTerminated:
            pass
        finally:
            for s in (xsub, xpub, steer):
                s.close(linger=0)

    def _control_thread(self) -> None:
        try:
            rep = self.ctx.socket(zmq.REP)
            rep.setsockopt(zmq.LINGER, 0)
            if self.port == 0:
                port = rep.bind_to_random_port(f"tcp://{self.host}")
            else:
                rep.bind(f"tcp://{self.host}:{self.port}")
                port = self.port
            self.endpoint = f"tcp://{self.host}:{port}"
        except Exception as exc:
            self._error = exc
            self._ready.set()
            return
        # The broker listens to the heartbeats itself, so a node that starts late still learns
        # which nodes have already come and gone (their last status is kept).
        status = self.ctx.socket(zmq.SUB)
        status.setsockopt(zmq.LINGER, 0)
        status.setsockopt(zmq.SUBSCRIBE, STATUS_FRAME)
        status.connect(f"tcp://{self.host}:{self.xpub_port}")
        self._ready.set()
        endpoints = json.dumps({"xsub_port": self.xsub_port, "xpub_port": self.xpub_port, "pid": os.getpid()}).encode()
        poller = zmq.Poller()
        poller.register(rep, zmq.POLLIN)
        poller.register(status, zmq.POLLIN)
        try:
            while not self._stop.is_set():
                events = dict(poller.poll(100))
                if status in events:
                    self._read_status(status)
                if rep in events:
                    request = rep.recv()
                    if request == b"graph":
                        with self._graph_lock:
                            rep.send(json.dumps(self._graph).encode())
                    elif request == b"verdict":
                        rep.send(self._verdict.encode())
                    else:
                        rep.send(endpoints)
        finally:
            rep.close(linger=0)
            status.close(linger=0)

    def _read_status(self, sock: zmq.Socket) -> None:

        while True:
            try:
                frames = sock.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            try:
                st, _ = decode_frames(frames[1:], NodeStatus)
            except MessageError:
                continue
            with self._graph_lock:
                self._graph[st.node] = {
                    "state": st.state,
                    "subscribes": st.subscribes,
                    "publishes": st.publishes,
                    "pid": st.pid,
                    "message": st.message,
                    "published": dict(st.published),
                    "heard_s": time.monotonic(),  # when it arrived: the launcher's hang watch
                }

    def heartbeats(self) -> dict[str, dict]:
        """A copy of the latest heartbeat of every node heard from (``state``, ``pid``,
        ``message``, ``heard_s``: ``time.monotonic()`` when it arrived), by node name."""
        with self._graph_lock:
            return {k: dict(v) for k, v in self._graph.items()}

    def fail(self, reason: str) -> None:
        """Mark the run failed (``reason``, one line) before the launcher stops the graph, so the
        nodes that end with it (the recorder) can tell a failed run from a planned stop:
        :func:`query_verdict`."""
        self._verdict = reason or "failed"


def _ask(endpoint: str, ctx: zmq.Context, request: bytes, timeout_s: float) -> bytes | None:
    """One request to the broker's control socket; its answer, or None when it does not answer in
    time."""
    req = ctx.socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    req.connect(endpoint)
    try:
        req.send(request)
        return req.recv() if req.poll(int(timeout_s * 1000)) else None
    finally:
        req.close(linger=0)


def query_verdict(endpoint: str, ctx: zmq.Context, timeout_s: float = 0.5) -> str | None:
    """Why the launcher stops the graph as a failed run; "" for no failure (so far), None when the
    broker does not answer in time."""
    answer = _ask(endpoint, ctx, b"verdict", timeout_s)
    return None if answer is None else answer.decode(errors="replace")


def query_graph(endpoint: str, ctx: zmq.Context, timeout_s: float = 0.5) -> dict[str, dict]:
    """The broker's record of every node's last heartbeat ({} if it does not answer in time)."""
    answer = _ask(endpoint, ctx, b"graph", timeout_s)
    return {} if answer is None else json.loads(answer)


def discover(endpoint: str, ctx: zmq.Context, timeout_s: float, stream=None) -> tuple[str, str]:
    """Ask the broker at ``endpoint`` for its data endpoints -> (xsub, xpub) to connect to.

    Retries until ``timeout_s`` (the launcher may still be starting the broker). When the first
    half second brings no answer it says once, on ``stream`` (default stderr), that it is
    waiting for a broker at ``endpoint``, so a node or command started with no graph running
    does not sit silent until it gives up.
    """
    host, _ = _host_port(endpoint)
    start = time.monotonic()
    deadline = start + timeout_s
    said = False
    while True:
        req = ctx.socket(zmq.REQ)
        req.setsockopt(zmq.LINGER, 0)
        req.connect(endpoint)
        try:
            req.send(b"endpoints")
            # short first wait: a launcher's broker answers in milliseconds
            first = 0.5 if not said and time.monotonic() - start < 0.5 else 1.0
            if req.poll(int(min(first, max(0.05, deadline - time.monotonic())) * 1000)):
                info = json.loads(req.recv())
                return f"tcp://{host}:{info['xsub_port']}", f"tcp://{host}:{info['xpub_port']}"
        finally:
            req.close(linger=0)
        if time.monotonic() >= deadline:
            raise TwinFocusError(
                f"no broker answered at {endpoint} within {timeout_s:g} s: start the graph with `twinfocus launch` "
                f"(or `python -m nodes.runtime.bus`), or name the running broker with --broker tcp://HOST:PORT or "
                f"${ENV_BROKER} (broker:=tcp://HOST:PORT for a node started by hand)"
            )
        if not said:
            said = True
            out = stream if stream is not None else sys.stderr
            print(
                f"waiting for a broker at {endpoint} (up to {timeout_s:g} s; is the graph running? another "
                f"broker: --broker tcp://HOST:PORT or ${ENV_BROKER})",
                file=out,
                flush=True,
            )


def main(argv: list[str] | None = None) -> int:
    """``python -m nodes.runtime.bus [ENDPOINT]``: a broker alone, for nodes started by hand."""

    ap = argparse.ArgumentParser(prog="python -m nodes.runtime.bus", description="Run the message broker until Ctrl-C.")
    ap.add_argument(
        "endpoint", nargs="?", default=None, help=f"control endpoint (default $TWINFOCUS_BROKER or {DEFAULT_BROKER})"
    )
    args = ap.parse_args(argv)
    try:
        broker = Broker(args.endpoint).start()
    except TwinFocusError as exc:
        print(f"broker: error: {exc}")
        return 2
    print(
        f"broker on {broker.endpoint} (data ports {broker.xsub_port}, {broker.xpub_port}); Ctrl-C stops it", flush=True
    )
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
    broker.stop()
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main())
