"""What the radar and VIO drivers share: a backend read in a background thread, paced output.

The backend's ``samples()`` iterator runs in a thread and fills a bounded queue (a slow
consumer holds the backend back instead of growing memory); the node's loop takes samples
from the queue and publishes them. A backend that is not ``live`` (file, simulation) is
paced by its time stamps divided by ``rate`` (``rate:=0``: as fast as possible): from the
backend's ``clock_start_ns`` when it has one (the stamp the node's start stands for; samples
stamped earlier, or simulated late, go out at once), else from its first sample's stamp.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Any

from nodes.runtime.backends import load_backend
from nodes.runtime.node import Node
from nodes.runtime.params import Param
from twinfocus.errors import TwinFocusError

_END = object()


class DriverNode(Node):
    """Base of the drivers; subclasses set REGISTRY, KIND and implement :meth:`to_message`."""

    REGISTRY: dict[str, str] = {}
    KIND = "driver"
    TOPIC = ""
    PARAMS = {
        **Node.PARAMS,
        "backend": Param("sim", "backend name (see nodes.runtime.backends) or module:Class", type="str"),
        "options": Param({}, "options for the backend (mapping)", type="any"),
        "rate": Param(1.0, "speed factor for file/simulated backends (paced by time stamps); 0 = as fast as possible"),
        "queue": Param(32, "samples buffered between the backend thread and the publisher"),
        "exit_when_done": Param(True, "end the node when the backend has no more samples"),
    }

    def __init__(self, **kw):
        super().__init__(**kw)
        if self.params["rate"] < 0:
            raise TwinFocusError(f"node {self.name!r}: rate must be >= 0, got {self.params['rate']}")
        options = self.params["options"] or {}
        if not isinstance(options, dict):
            raise TwinFocusError(f"node {self.name!r}: parameter 'options' must be a mapping, got {options!r}")
        cls = load_backend(self.REGISTRY, self.params["backend"], self.KIND)
        self.backend = cls(dict(options))
        self.pub = self.create_publisher(self.TOPIC)
        self._queue: queue.Queue = queue.Queue(maxsize=max(1, int(self.params["queue"])))
        self._thread_error: BaseException | None = None
        self._halt = threading.Event()
        self._held: Any = None
        self._t0: tuple[float, int] | None = None
        self.count = 0

    def to_message(self, sample: Any):
        raise NotImplementedError

    def on_start(self) -> None:
        start = getattr(self.backend, "clock_start_ns", None)
        if start is not None:
            # Simulated sensors on one clock, started with the graph: the tracker's poses from
            # before the radar's first frame go out at once (paced from its own first pose, every
            # pose, and so every measurement, came 0.5 s behind its radar frame), and a radar
            # whose first block of frames takes a while to simulate catches up instead of
            # running that much late all sweep.
            self._t0 = (time.monotonic(), int(start))
        t = threading.Thread(target=self._read, name=f"{self.name}-backend", daemon=True)
        t.start()
        self._reader = t
        self.log(f"{self.KIND} backend {self.params['backend']!r} started")
        self.call_later(0, self._pump)

    def _read(self) -> None:
        try:
            for sample in self.backend.samples():
                while not self._halt.is_set():
                    try:
                        self._queue.put(sample, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if self._halt.is_set():
                    return
        except BaseException as exc:  # handed to the node's loop
            self._thread_error = exc
        self._queue.put(_END)

    def _pump(self) -> None:
        rate = float(self.params["rate"])
        live = bool(getattr(self.backend, "live", False))
        for _ in range(100):
            sample = self._held
            self._held = None
            if sample is None:
                try:
                    sample = self._queue.get_nowait()
                except queue.Empty:
                    self.call_later(0.002, self._pump)
                    return
            if sample is _END:
                self._finished()
                return
            if not live and rate > 0:
                now = time.monotonic()
                if self._t0 is None:
                    self._t0 = (now, sample.stamp_ns)
                due = self._t0[0] + (sample.stamp_ns - self._t0[1]) / 1e9 / rate
                if due > now:
                    self._held = sample
                    self.call_later(due - now, self._pump)
                    return
            self.pub.publish(self.to_message(sample))
            self.count += 1
        self.call_later(0, self._pump)

    def _finished(self) -> None:
        if self._thread_error is not None:
            exc = self._thread_error
            if isinstance(exc, TwinFocusError):
                raise exc
            raise RuntimeError(f"{self.KIND} backend failed: {exc!r}") from exc
        self.log(f"{self.KIND} backend finished after {self.count} sample(s)")
        self.status_message = f"done: {self.count} samples"
        if self.params["exit_when_done"]:
            self.request_shutdown("backend finished")

    def on_shutdown(self) -> None:
        self._halt.set()
        try:
            self.backend.close()
        except Exception as exc:
            self.log(f"backend close failed: {exc!r}")
