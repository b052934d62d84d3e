"""Run nodes in one process for tests: a broker, nodes in threads, and a probe node.

::

    with local_broker() as endpoint:
        probe = Probe(endpoint, listen=["sar/measurement"], publish=["radar/frame", "vio/pose"],
                      wait_for=["synchronizer"])
        sync = Synchronizer(broker=endpoint)
        with running(sync, probe):
            probe.send("vio/pose", pose)           # thread-safe: sent from the probe's loop
            msgs = probe.wait_for("sar/measurement", count=3, timeout_s=10)

Each node runs its normal :meth:`~nodes.runtime.node.Node.spin` (start-up handshake, heartbeats,
sequence checks) in a thread; :func:`running` stops and joins them and fails if one crashed.
"""

from __future__ import annotations

import os
import queue
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from msgs import Header, Pose, RadarFrame
from nodes.runtime.bus import Broker, topic_frame
from nodes.runtime.node import Node


def patience(seconds: float) -> float:
    """An outer time bound for a wait, stretched by how busy the machine is.

    Waits end as soon as what they wait for happens; the bound only keeps a broken build from
    hanging. On a machine whose run queue is longer than its cores (another build, a CPU-bound
    process beside the tests) everything takes that many times longer, so the bound is multiplied
    by the 1-minute load per core (at least 1, at most 5), or by ``$TWINFOCUS_TEST_PATIENCE``.
    """
    given = os.environ.get("TWINFOCUS_TEST_PATIENCE")
    if given:
        return seconds * float(given)
    try:
        per_core = os.getloadavg()[0] / (os.cpu_count() or 1)
    except OSError:
        per_core = 1.0
    return seconds * min(5.0, max(1.0, per_core))


@contextmanager
def local_broker() -> Iterator[str]:
    """A broker on a free loopback port; yields its control endpoint."""
    b = Broker("tcp://127.0.0.1:0").start()
    try:
        yield b.endpoint
    finally:
        b.stop()


class Probe(Node):
    """Records what arrives on ``listen`` topics and publishes what the test hands it."""

    NAME = "probe"

    def __init__(
        self,
        broker: str,
        listen: Sequence[str] = (),
        publish: Sequence[str] = (),
        wait_for: Sequence[str] = (),
        name: str = "probe",
        **kw,
    ):
        params = {"wait_for": list(wait_for), "heartbeat_s": 0.2, **kw.pop("params", {})}
        super().__init__(name=name, params=params, broker=broker, **kw)
        self.received: dict[str, list] = {t: [] for t in listen}
        self.arrival: dict[str, list[float]] = {t: [] for t in listen}
        self._cond = threading.Condition()
        self._outbox: queue.Queue = queue.Queue()
        self.started = threading.Event()
        for t in listen:
            self.create_subscription(t, lambda msg, t=t: self._got(t, msg))
        for t in publish:
            self.create_publisher(t)

    def _got(self, topic: str, msg: Any) -> None:
        with self._cond:
            self.received[topic].append(msg)
            self.arrival[topic].append(time.monotonic())
            self._cond.notify_all()

    def on_start(self) -> None:
        self.create_timer(0.001, self._drain)
        self.started.set()

    def _drain(self) -> None:
        while True:
            try:
                topic, msg = self._outbox.get_nowait()
            except queue.Empty:
                return
            if isinstance(msg, list):  # already encoded (send_frames)
                self._send_frames([topic_frame(topic), *msg])
            else:
                self._publishers[topic].publish(msg)

    def send(self, topic: str, msg: Any) -> None:
        """Queue ``msg`` for publishing on ``topic`` (declared in ``publish``)."""
        self._outbox.put((topic, msg))

    def send_frames(self, topic: str, frames: list) -> None:
        """Queue already encoded frames (:func:`msgs.encode_frames`, then altered: a malformed
        message, as a faulty publisher sends one) for ``topic``, past the sender's validation."""
        self._outbox.put((topic, list(frames)))

    def sent_all(self, timeout_s: float = 10.0) -> bool:
        deadline = time.monotonic() + patience(timeout_s)
        while not self._outbox.empty() and time.monotonic() < deadline:
            time.sleep(0.005)
        return self._outbox.empty()

    def wait_for(self, topic: str, count: int = 1, timeout_s: float = 10.0, where=None) -> list:
        """Block until ``count`` messages (optionally matching ``where(msg)``) arrived on ``topic``
        (``timeout_s`` stretched by :func:`patience`)."""
        timeout_s = patience(timeout_s)
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                got = [m for m in self.received[topic] if where is None or where(m)]
                if len(got) >= count:
                    return got
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"{len(got)} of {count} message(s) on {topic} within {timeout_s:g} s")
                self._cond.wait(min(left, 0.1))


@contextmanager
def running(*nodes: Node, start_timeout_s: float = 30.0, stop_timeout_s: float = 30.0) -> Iterator[tuple[Node, ...]]:
    """Spin ``nodes`` in threads; on exit stop them, join, and raise if one failed (the time
    limits stretched by :func:`patience`)."""
    start_timeout_s, stop_timeout_s = patience(start_timeout_s), patience(stop_timeout_s)
    codes: dict[str, int] = {}
    threads = []
    for n in nodes:
        t = threading.Thread(target=lambda n=n: codes.__setitem__(n.name, n.spin()), name=f"node-{n.name}", daemon=True)
        t.start()
        threads.append(t)
    try:
        probes = [n for n in nodes if isinstance(n, Probe)]
        deadline = time.monotonic() + start_timeout_s
        for p in probes:
            if not p.started.wait(max(0.0, deadline - time.monotonic())):
                raise TimeoutError(f"probe {p.name!r} did not start within {start_timeout_s:g} s (graph not ready)")
        yield nodes
    finally:
        for n in nodes:
            n.stop()
        for t in threads:
            t.join(stop_timeout_s)
    stuck = [t.name for t in threads if t.is_alive()]
    if stuck:
        raise RuntimeError(f"node thread(s) did not stop: {', '.join(stuck)}")
    failed = {k: v for k, v in codes.items() if v != 0}
    if failed:
        raise RuntimeError(f"node(s) failed: {failed}")


def write_driver_messages(writer, radar, vio, data, chirp, array) -> None:
    """Write to an open :class:`msgs.mcap_log.LogWriter` what the drivers would have published for
    one scan, in the order it would have arrived: each pose 5 ms and each radar frame 20 ms after
    its stamp. radar, vio : :class:`twinfocus.motion.trajectory.Poses` (radar frames, tracker poses);
    data : complex (M, K, N) IF samples; array : the virtual array (its ``offsets_m``)."""

    events = [(int(t) + 5_000_000, "vio/pose", i) for i, t in enumerate(vio.timestamps_ns)]
    events += [(int(t) + 20_000_000, "radar/frame", m) for m, t in enumerate(radar.timestamps_ns)]
    for log_t, topic, i in sorted(events):
        msg: Pose | RadarFrame
        if topic == "vio/pose":
            msg = Pose(
                header=Header(int(vio.timestamps_ns[i]), i, "scene"),
                position_m=vio.position_m[i],
                quat_xyzw=vio.quat_xyzw[i],
            )
        else:
            msg = RadarFrame(
                header=Header(int(radar.timestamps_ns[i]), i, "radar"),
                data=data[i],
                f0_hz=chirp.f0_hz,
                slope_hz_per_s=chirp.slope_hz_per_s,
                fs_hz=chirp.fs_hz,
                channel_offsets_m=array.offsets_m,
                scan_id="run",
                index=i,
                last=i == len(radar.timestamps_ns) - 1,
            )
        writer.write(topic, msg, log_time_ns=log_t)
