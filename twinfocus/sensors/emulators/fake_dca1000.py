"""An emulated DCA1000EVM on loopback: answers the UDP command protocol and streams frames.

Commands (config port) are answered as the board does (``0xA55A | code | status | 0xEEAA``),
with bodies checked for the documented sizes; RECORD_START begins streaming to the host's data
address once the (emulated) radar is running, RECORD_STOP ends it. The stream is the frames'
bytes back to back, cut into packets of ``u32 sequence | 48-bit byte count | <= 1456 bytes``.

Faults to inject (:class:`LinkFaults`): ``drop_packets`` (sequence numbers never sent),
``swap_packets`` (packet s goes out after s + 1), ``duplicate_packets``, and random ``loss`` /
``reorder`` probabilities.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.sensors.dca1000 import (
    MAX_PAYLOAD_BYTES,
    Command,
    RawFrameLayout,
    decode_command,
    encode_data_packet,
    encode_response,
)

#: Status the emulated board reports for READ_FPGA_VERSION: version 2.9, record mode.
FPGA_VERSION_STATUS = 2 | (9 << 7)
_BODY_SIZES = {Command.CONFIG_FPGA_GEN: 6, Command.CONFIG_PACKET_DATA: 6}


def pattern_frame(index: int, layout: RawFrameLayout) -> bytes:
    """A deterministic test frame: int16 values (index * 7919 + position) mod 65536, signed."""
    v = (np.arange(layout.frame_values, dtype=np.int64) + index * 7919) % 65536
    return (v - 32768).astype("<i2").tobytes()


@dataclass(frozen=True)
class LinkFaults:
    """The faults the emulated board injects into its data stream.

    drop_packets : sequence numbers never sent; swap_packets : sequence numbers that go out after
    the next packet; duplicate_packets : sequence numbers sent twice; loss, reorder : the
    probability that any other packet is dropped / held back one packet; seed : the random
    stream's seed (``numpy.random.default_rng``) for ``loss`` and ``reorder``."""

    drop_packets: Collection[int] = ()
    swap_packets: Collection[int] = ()
    duplicate_packets: Collection[int] = ()
    loss: float = 0.0
    reorder: float = 0.0
    seed: int | None = 0


class FakeDca1000:
    """The emulated board.

    Parameters
    ----------
    layout : the raw frame layout streamed (changed by :meth:`sensor_start` with a config).
    frame_source : ``f(index, layout) -> bytes`` of one frame (default :func:`pattern_frame`).
    host_data_addr : where to send data packets (the host's data socket); settable later.
    frame_period_s : pause between frames (None or 0: as fast as possible, or at ``rate``).
    rate_bytes_per_s : pace the stream at this byte rate instead of per frame.
    n_frames : stop after this many frames (None: until RECORD_STOP / close).
    faults : the faults injected into the stream (:class:`LinkFaults`; default none).
    sensor_running : whether the radar is emitting (an emulated CLI toggles it).
    on_stream_start : called with the wall-clock time (ns) at which frame 0 leaves.
    """

    def __init__(
        self,
        layout: RawFrameLayout,
        frame_source: Callable[[int, RawFrameLayout], bytes] | None = None,
        host_data_addr: tuple[str, int] | None = None,
        frame_period_s: float | None = 0.1,
        rate_bytes_per_s: float | None = None,
        n_frames: int | None = None,
        faults: LinkFaults = LinkFaults(),
        payload_bytes: int = MAX_PAYLOAD_BYTES,
        sensor_running: bool = True,
        bind_ip: str = "127.0.0.1",
        config_port: int = 0,
        on_stream_start: Callable[[int], None] | None = None,
    ):
        self.layout = layout
        self.frame_source = frame_source or pattern_frame
        self.host_data_addr = host_data_addr
        self.frame_period_s = frame_period_s
        self.rate = rate_bytes_per_s
        self.n_frames = n_frames
        self.drop = set(int(s) for s in faults.drop_packets)
        self.swap = set(int(s) for s in faults.swap_packets)
        self.dup = set(int(s) for s in faults.duplicate_packets)
        self.loss = float(faults.loss)
        self.reorder = float(faults.reorder)
        self._rng = np.random.default_rng(faults.seed)
        self.payload_bytes = int(payload_bytes)
        self.sensor_running = bool(sensor_running)
        self.commands: list[int] = []
        self.sent_packets = 0
        self.dropped = 0
        self.frames_sent = 0
        self.stream_start_ns: int | None = None
        self.on_stream_start = on_stream_start
        self.done = threading.Event()
        self._recording = False
        self._cfg = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._cfg.bind((bind_ip, int(config_port)))
        self._cfg.settimeout(0.05)
        self._data = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._stop = threading.Event()
        self._stream_stop = threading.Event()
        self._stream: threading.Thread | None = None
        self._lock = threading.Lock()
        self._server = threading.Thread(target=self._serve, name="fake-dca1000-config", daemon=True)
        self._server.start()

    @property
    def config_addr(self) -> tuple[str, int]:
        """(ip, port) of the emulated board's config port."""
        return self._cfg.getsockname()

    def __enter__(self) -> FakeDca1000:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop streaming and answering; join the threads; close the sockets."""
        self._stop.set()
        self._stop_stream()
        self._server.join(timeout=2.0)
        for s in (self._cfg, self._data):
            s.close()

    # -- radar side (driven by an emulated CLI) ------------------------------------------------

    def sensor_start(self, config=None) -> None:
        """The radar starts chirping (with a parsed CLI ``config``, its layout is used)."""
        with self._lock:
            if config is not None:
                self.layout = config.raw_layout()
                if self.frame_period_s:
                    self.frame_period_s = config.frame_period_s
            self.sensor_running = True
            self._maybe_start_stream()

    def sensor_stop(self) -> None:
        with self._lock:
            self.sensor_running = False
        self._stop_stream()

    # -- config port ---------------------------------------------------------------------------

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                packet, addr = self._cfg.recvfrom(2048)
            except (TimeoutError, OSError):
                continue
            try:
                code, body = decode_command(packet)
            except TwinFocusError:
                continue  # the real board ignores garbage
            self.commands.append(code)
            status = self._handle(code, body)
            try:
                self._cfg.sendto(encode_response(code, status), addr)
            except OSError:
                pass

    def _handle(self, code: int, body: bytes) -> int:
        try:
            cmd = Command(code)
        except ValueError:
            return 1
        if cmd in _BODY_SIZES and len(body) != _BODY_SIZES[cmd]:
            return 1
        if cmd == Command.READ_FPGA_VERSION:
            return FPGA_VERSION_STATUS
        if cmd == Command.CONFIG_PACKET_DATA:
            size, _delay, _ = struct.unpack("<HHH", body)
            if not 64 <= size <= 1470:
                return 1
            self.payload_bytes = min(MAX_PAYLOAD_BYTES, (size - 10) // 8 * 8)
            return 0
        if cmd == Command.RECORD_START:
            if self.host_data_addr is None:
                return 1
            with self._lock:
                self._recording = True
                self._maybe_start_stream()
            return 0
        if cmd == Command.RECORD_STOP:
            with self._lock:
                self._recording = False
            self._stop_stream()
            return 0
        return 0

    # -- data stream ---------------------------------------------------------------------------

    def start_streaming(self) -> None:
        """Start the stream now (without RECORD_START), e.g. for benchmarks."""
        with self._lock:
            self._recording = True
            self._maybe_start_stream()

    def _maybe_start_stream(self) -> None:
        if self._recording and self.sensor_running and (self._stream is None or not self._stream.is_alive()):
            self._stream_stop.clear()
            self.done.clear()
            self._stream = threading.Thread(target=self._run_stream, name="fake-dca1000-stream", daemon=True)
            self._stream.start()

    def _stop_stream(self) -> None:
        self._stream_stop.set()
        t = self._stream
        if t is not None and t is not threading.current_thread():
            t.join(timeout=5.0)

    def _run_stream(self) -> None:
        dest = self.host_data_addr
        seq = 0
        byte_count = 0
        pending = b""
        held: list[bytes] = []
        t0 = time.monotonic()
        self.stream_start_ns = time.time_ns()
        if self.on_stream_start is not None:
            self.on_stream_start(self.stream_start_ns)
        k = 0
        try:
            while not self._stream_stop.is_set() and (self.n_frames is None or k < self.n_frames):
                # Make the frame first, then wait for its slot: frame k leaves at t0 + k * period
                # however long it took to make (receive time stamps stay on the schedule).
                frame = self.frame_source(k, self.layout)
                if len(frame) != self.layout.frame_bytes:
                    raise TwinFocusError(
                        f"frame source gave {len(frame)} bytes, layout needs {self.layout.frame_bytes}"
                    )
                if self.rate:
                    target = t0 + byte_count / self.rate
                elif self.frame_period_s:
                    target = t0 + k * self.frame_period_s
                else:
                    target = 0.0
                delay = target - time.monotonic()
                if delay > 0 and self._stream_stop.wait(delay):
                    break
                pending += frame
                last = self.n_frames is not None and k == self.n_frames - 1
                cut = len(pending) if last else len(pending) // self.payload_bytes * self.payload_bytes
                for off in range(0, cut, self.payload_bytes):
                    payload = pending[off : off + self.payload_bytes]
                    seq += 1
                    packet = encode_data_packet(seq, byte_count, payload)
                    byte_count += len(payload)
                    if seq in self.drop or (self.loss and self._rng.random() < self.loss):
                        self.dropped += 1
                        continue
                    if seq in self.swap or (self.reorder and self._rng.random() < self.reorder):
                        held.append(packet)
                        continue
                    self._send(packet, dest)
                    if seq in self.dup:
                        self._send(packet, dest)
                    while held:
                        self._send(held.pop(0), dest)
                pending = pending[cut:]
                k += 1
                self.frames_sent = k
            for packet in held:
                self._send(packet, dest)
        finally:
            self.done.set()

    def _send(self, packet: bytes, dest) -> None:
        try:
            self._data.sendto(packet, dest)
            self.sent_packets += 1
        except OSError:
            pass
