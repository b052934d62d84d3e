"""DCA1000EVM capture board: its UDP command protocol and raw-ADC stream, loss-tolerant.

Protocol as implemented (little-endian; DCA1000EVM Data Capture Card User's Guide, SPRUIJ4,
section 5, and TI's ``ReferenceCode/DCA1000`` sources; details and sources in ``docs/sensors.md``):

- Config port (board 4096, host 4096): a command is ``u16 0xA55A | u16 code | u16 length |
  body | u16 0xEEAA`` (on the wire ``5A A5 .. .. .. AA EE``); the board answers
  ``0xA55A | code | u16 status | 0xEEAA`` with status 0 = success.
- Data port (host 4098): each datagram is ``u32 sequence number`` (from 1) | ``48-bit byte count``
  (bytes of the stream sent before this packet) | payload (up to 1456 bytes). The byte stream is
  the radar's LVDS output: frames back to back, not aligned to packets.

:class:`FrameAssembler` places each payload by its byte count, so lost packets leave zeros in
the frame they belonged to (flagged :attr:`FrameFlag.ZERO_FILLED`), reordered packets land where
they belong (flagged :attr:`FrameFlag.REORDERED`), and a frame is given out once it is complete
or the stream has moved a reorder window past it — the reader never waits on a packet that
will not come.

Raw frame layout (xWR16xx/18xx/68xx, 16-bit complex, LVDS 2-lane, as in TI's ``readDCA1000.m``):
for each loop, each chirp, each RX: N complex samples stored as I0 I1 Q0 Q1 I2 I3 Q2 Q3 ...
"""

from __future__ import annotations

import enum
import select
import socket
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.sensors.frames import FrameFlag, RadarFrame

HEADER = 0xA55A
FOOTER = 0xEEAA
CONFIG_PORT = 4096
DATA_PORT = 4098
BOARD_IP = "192.168.33.180"
HOST_IP = "192.168.33.30"
#: Data-packet header: u32 sequence number, 48-bit byte count.
DATA_HEADER_BYTES = 10
#: Largest UDP data packet the board sends (``MAX_BYTES_PER_PACKET``) and its payload.
MAX_PACKET_BYTES = 1470
MAX_PAYLOAD_BYTES = 1456
#: Record packet delay is given in FPGA clock ticks of 8 ns (``FPGA_CLK_PERIOD_IN_NANO_SEC``).
FPGA_CLK_PERIOD_NS = 8
#: Largest command body the board accepts.
MAX_COMMAND_BODY = 504


class Command(enum.IntEnum):
    """Command codes (``rf_api.h``: ``*_CMD_CODE``)."""

    RESET_FPGA = 0x01
    RESET_AR_DEV = 0x02
    CONFIG_FPGA_GEN = 0x03
    CONFIG_EEPROM = 0x04
    RECORD_START = 0x05
    RECORD_STOP = 0x06
    PLAYBACK_START = 0x07
    PLAYBACK_STOP = 0x08
    SYSTEM_CONNECT = 0x09
    SYSTEM_ERROR = 0x0A
    CONFIG_PACKET_DATA = 0x0B
    CONFIG_DATA_MODE_AR_DEV = 0x0C
    INIT_FPGA_PLAYBACK = 0x0D
    READ_FPGA_VERSION = 0x0E


# --- command frames ---------------------------------------------------------------------------


def encode_command(code: int, body: bytes = b"") -> bytes:
    """A command datagram: 0xA55A | code | len(body) | body | 0xEEAA."""
    body = bytes(body)
    if len(body) > MAX_COMMAND_BODY:
        raise TwinFocusError(f"DCA1000 command body is {len(body)} bytes; the board accepts at most {MAX_COMMAND_BODY}")
    return struct.pack("<HHH", HEADER, int(code), len(body)) + body + struct.pack("<H", FOOTER)


def decode_command(packet: bytes) -> tuple[int, bytes]:
    """(code, body) of a command datagram; malformed ones raise :class:`TwinFocusError`."""
    if len(packet) < 8:
        raise TwinFocusError(f"DCA1000 command is {len(packet)} bytes, shorter than the 8 of header and footer")
    header, code, length = struct.unpack_from("<HHH", packet)
    if header != HEADER:
        raise TwinFocusError(f"DCA1000 command header is 0x{header:04x}, expected 0x{HEADER:04x}")
    if len(packet) != 8 + length:
        raise TwinFocusError(f"DCA1000 command announces a {length}-byte body but the datagram holds {len(packet) - 8}")
    (footer,) = struct.unpack_from("<H", packet, 6 + length)
    if footer != FOOTER:
        raise TwinFocusError(f"DCA1000 command footer is 0x{footer:04x}, expected 0x{FOOTER:04x}")
    return code, bytes(packet[6 : 6 + length])


def encode_response(code: int, status: int) -> bytes:
    """The board's answer: 0xA55A | code | status | 0xEEAA."""
    return struct.pack("<HHHH", HEADER, int(code), int(status) & 0xFFFF, FOOTER)


def decode_response(packet: bytes) -> tuple[int, int]:
    """(code, status) of a board answer."""
    if len(packet) != 8:
        raise TwinFocusError(f"DCA1000 answer is {len(packet)} bytes, expected 8")
    header, code, status, footer = struct.unpack("<HHHH", packet)
    if header != HEADER or footer != FOOTER:
        raise TwinFocusError(
            f"DCA1000 answer has header 0x{header:04x} / footer 0x{footer:04x}, expected 0xa55a / 0xeeaa"
        )
    return code, status


def encode_data_packet(sequence: int, byte_count: int, payload: bytes) -> bytes:
    """A data datagram: u32 sequence | 48-bit byte count | payload."""
    if not 0 <= byte_count < 1 << 48:
        raise TwinFocusError(f"byte count {byte_count} does not fit 48 bits")
    return struct.pack("<IIH", sequence & 0xFFFFFFFF, byte_count & 0xFFFFFFFF, byte_count >> 32) + bytes(payload)


def decode_data_header(packet) -> tuple[int, int]:
    """(sequence number, byte count) of a data datagram."""
    if len(packet) < DATA_HEADER_BYTES:
        raise TwinFocusError(f"DCA1000 data packet is {len(packet)} bytes, shorter than its 10-byte header")
    seq, lo, hi = struct.unpack_from("<IIH", packet)
    return seq, lo | (hi << 32)


# --- raw frame layout -------------------------------------------------------------------------


@dataclass(frozen=True)
class RawFrameLayout:
    """How one radar frame sits in the LVDS byte stream (16-bit complex, non-interleaved).

    n_samples : ADC samples per chirp (even); n_rx : receive channels enabled;
    tx_of_chirp : TX index fired by each chirp of a loop (0-based, order of the radar's TX);
    n_loops : loops per frame; n_tx : number of TX (default ``max(tx_of_chirp) + 1``).
    """

    n_samples: int
    n_rx: int
    tx_of_chirp: tuple[int, ...]
    n_loops: int = 1
    n_tx: int | None = None

    def __post_init__(self) -> None:
        if int(self.n_samples) < 2 or int(self.n_samples) % 2:
            raise TwinFocusError(
                f"n_samples must be an even number >= 2 (samples travel in I/Q pairs), got {self.n_samples}"
            )
        if int(self.n_rx) < 1 or int(self.n_loops) < 1 or not self.tx_of_chirp:
            raise TwinFocusError("a frame layout needs at least one RX, one loop and one chirp")
        tx = tuple(int(t) for t in self.tx_of_chirp)
        object.__setattr__(self, "tx_of_chirp", tx)
        n_tx = max(tx) + 1 if self.n_tx is None else int(self.n_tx)
        if min(tx) < 0 or max(tx) >= n_tx:
            raise TwinFocusError(f"tx_of_chirp {tx} names TX outside 0..{n_tx - 1}")
        object.__setattr__(self, "n_tx", n_tx)

    @property
    def n_chirps(self) -> int:
        return len(self.tx_of_chirp)

    @property
    def frame_values(self) -> int:
        return int(self.n_loops) * self.n_chirps * int(self.n_rx) * int(self.n_samples) * 2

    @property
    def frame_bytes(self) -> int:
        return 2 * self.frame_values

    def decode(self, raw) -> np.ndarray:
        """Raw frame bytes (or int16 values) -> complex64 (n_loops, n_chirps, n_rx, N)."""
        x = np.frombuffer(raw, dtype="<i2") if isinstance(raw, (bytes, bytearray, memoryview)) else np.asarray(raw)
        if x.size != self.frame_values:
            raise TwinFocusError(f"raw frame holds {x.size} int16 values, the layout expects {self.frame_values}")
        # (.., pair, [I I Q Q]) -> (.., pair, sample-in-pair, [I Q]) -> float32 pairs -> complex64
        x = x.reshape(self.n_loops, self.n_chirps, self.n_rx, self.n_samples // 2, 2, 2).swapaxes(-1, -2)
        return (
            x.astype(np.float32, order="C")
            .view(np.complex64)
            .reshape(self.n_loops, self.n_chirps, self.n_rx, self.n_samples)
        )

    def to_mimo(self, decoded: np.ndarray, loop: int | None = 0) -> np.ndarray:
        """(n_loops, n_chirps, n_rx, N) -> complex64 (n_tx, n_rx, N) of one loop (None: mean)."""
        x = decoded.mean(axis=0).astype(np.complex64) if loop is None else decoded[int(loop)]
        tx = self.tx_of_chirp
        n_tx = self.n_tx
        assert n_tx is not None  # __post_init__ always fills it in
        if len(set(tx)) == len(tx):
            if tx == tuple(range(n_tx)):
                return np.ascontiguousarray(x)
            out = np.zeros((n_tx, self.n_rx, self.n_samples), np.complex64)
            out[list(tx)] = x
            return out
        # A TX that fires more than once in a loop (e.g. for Doppler) is averaged.
        out = np.zeros((n_tx, self.n_rx, self.n_samples), np.complex64)
        count = np.zeros(n_tx)
        for c, t in enumerate(tx):
            out[t] += x[c]
            count[t] += 1
        fired = count > 0
        out[fired] /= count[fired][:, None, None]
        return out

    def encode(self, mimo_iq: np.ndarray) -> bytes:
        """int16 (n_loops, n_tx, n_rx, N, 2) (I, Q) -> the frame's bytes on the LVDS stream."""
        x = np.asarray(mimo_iq)
        want = (self.n_loops, self.n_tx, self.n_rx, self.n_samples, 2)
        if x.shape != want or x.dtype != np.int16:
            raise TwinFocusError(f"frame I/Q must be int16 {want}, got {x.dtype} {x.shape}")
        chirps = x[:, list(self.tx_of_chirp)]  # (L, C, R, N, 2)
        pairs = chirps.reshape(self.n_loops, self.n_chirps, self.n_rx, self.n_samples // 2, 2, 2)
        # (.., pair, sample-in-pair, iq) -> (.., pair, iq, sample-in-pair): I0 I1 Q0 Q1
        return np.ascontiguousarray(pairs.swapaxes(-1, -2)).astype("<i2").tobytes()


# --- frame assembly ---------------------------------------------------------------------------


@dataclass
class AssemblerStats:
    packets: int = 0
    bytes: int = 0
    reordered_packets: int = 0
    duplicate_packets: int = 0
    late_packets: int = 0
    lost_bytes: int = 0
    frames: int = 0
    frames_zero_filled: int = 0
    frames_lost: int = 0
    frames_skipped: int = 0


#: Sequence numbers this far below the highest seen (and not awaited) mean the board restarted.
_RESTART_SEQ_GAP = 100_000
#: How many skipped sequence numbers are remembered as possibly arriving late.
_MAX_TRACKED_MISSING = 4096


@dataclass
class _Pending:
    buf: bytearray
    filled: int = 0
    first_recv_ns: int | None = None
    reordered: bool = False


@dataclass
class AssembledFrame:
    index: int
    raw: bytes
    flags: FrameFlag
    missing_bytes: int
    first_recv_ns: int | None


class FrameAssembler:
    """Rebuild frames from DCA1000 data packets placed by their byte counts.

    frame_bytes : bytes per frame; reorder_window_bytes : how far the stream may run past a
    frame's end before the frame is given out incomplete (default 64 packets' worth);
    max_gap_frames : a byte count that jumps further than this many frames ahead (a corrupt
    header, a long outage) resynchronises instead of emitting that many lost frames; sequence
    numbers that start again from low values (a restarted board) start the assembly afresh.

    A packet is new when its sequence number is above every one seen, late (reordered) when it
    is one that was skipped over, and a duplicate otherwise.
    """

    def __init__(self, frame_bytes: int, reorder_window_bytes: int | None = None, max_gap_frames: int = 64):
        if int(frame_bytes) < 1:
            raise TwinFocusError(f"frame_bytes must be positive, got {frame_bytes}")
        self.frame_bytes = int(frame_bytes)
        self.window = 64 * MAX_PAYLOAD_BYTES if reorder_window_bytes is None else int(reorder_window_bytes)
        self.max_gap_frames = int(max_gap_frames)
        self.next_emit = 0
        self.high_byte = 0
        self.max_seq = 0
        self.pending: dict[int, _Pending] = {}
        self._missing: set[int] = set()  # sequence numbers skipped over, still expected late
        self.stats = AssemblerStats()

    def push(self, seq: int, byte_count: int, payload, recv_ns: int | None = None) -> list[AssembledFrame]:
        """Add one packet; return the frames it completes (or pushes out of the window)."""
        fb = self.frame_bytes
        n = len(payload)
        st = self.stats
        st.packets += 1
        if n == 0:
            return []
        start = int(byte_count)
        end = start + n
        out: list[AssembledFrame] = []
        if seq + _RESTART_SEQ_GAP < self.max_seq and seq not in self._missing:
            # Sequence numbers started again: the board was restarted. Start afresh.
            out += self.flush()
            self._restart(seq, start)
        elif start >= self.high_byte and start // fb > self.next_emit + self.max_gap_frames:
            # A jump far ahead (corrupt byte count, long outage): hand out what is pending and
            # continue from there instead of emitting thousands of empty frames.
            out += self.flush()
            st.frames_skipped += start // fb - self.next_emit
            self._restart(seq, start)
        # Sequence numbers tell new, late (reordered) and repeated packets apart.
        if seq > self.max_seq:
            if self.max_seq and seq > self.max_seq + 1:
                if seq - self.max_seq - 1 <= _MAX_TRACKED_MISSING:
                    self._missing.update(range(self.max_seq + 1, seq))
                if len(self._missing) > 4 * _MAX_TRACKED_MISSING:
                    self._missing = set(sorted(self._missing)[-_MAX_TRACKED_MISSING:])
            self.max_seq = seq
            reordered = False
        elif seq in self._missing:
            self._missing.discard(seq)
            reordered = True
            st.reordered_packets += 1
        else:
            st.duplicate_packets += 1
            return out
        if end <= self.next_emit * fb:
            st.late_packets += 1
            return out
        st.bytes += n
        f0 = start // fb
        if f0 >= self.next_emit and (end - 1) // fb == f0:
            # The usual case: the packet lies inside one frame still being filled.
            p = self.pending.get(f0) or self._pending(f0)
            off = start - f0 * fb
            p.buf[off : off + n] = payload
            p.filled += n
            if p.first_recv_ns is None:
                p.first_recv_ns = recv_ns
            if reordered:
                p.reordered = True
        else:
            mv = memoryview(payload)
            for f in range(max(f0, self.next_emit), (end - 1) // fb + 1):
                lo = max(start, f * fb)
                hi = min(end, (f + 1) * fb)
                p = self._pending(f)
                p.buf[lo - f * fb : hi - f * fb] = mv[lo - start : hi - start]
                p.filled += hi - lo
                if p.first_recv_ns is None:
                    p.first_recv_ns = recv_ns
                p.reordered |= reordered
        if end > self.high_byte:
            self.high_byte = end
        out += self._emit_ready()
        return out

    def _restart(self, seq: int, start: int) -> None:
        self.pending.clear()
        self._missing.clear()
        self.next_emit = start // self.frame_bytes
        self.high_byte = start
        self.max_seq = seq - 1

    def flush(self, up_to_byte: int | None = None) -> list[AssembledFrame]:
        """Give out every frame that holds data up to ``up_to_byte`` (default all seen)."""
        limit = self.high_byte if up_to_byte is None else int(up_to_byte)
        last = -(-limit // self.frame_bytes)  # frames [next_emit, last) have started
        out = []
        while self.next_emit < last:
            out.append(self._emit(self.next_emit))
        return out

    def _pending(self, f: int) -> _Pending:
        p = self.pending.get(f)
        if p is None:
            p = _Pending(bytearray(self.frame_bytes))
            self.pending[f] = p
        return p

    def _emit_ready(self) -> list[AssembledFrame]:
        out = []
        fb = self.frame_bytes
        while True:
            f = self.next_emit
            p = self.pending.get(f)
            if p is not None and p.filled >= fb:
                out.append(self._emit(f))
            elif self.high_byte >= (f + 1) * fb + self.window:
                out.append(self._emit(f))
            else:
                return out

    def _emit(self, f: int) -> AssembledFrame:
        p = self.pending.pop(f, None)
        self.next_emit = f + 1
        st = self.stats
        st.frames += 1
        if p is None:
            st.frames_lost += 1
            st.lost_bytes += self.frame_bytes
            return AssembledFrame(
                f, bytes(self.frame_bytes), FrameFlag.ZERO_FILLED | FrameFlag.LOST, self.frame_bytes, None
            )
        missing = self.frame_bytes - p.filled
        flags = FrameFlag.OK
        if missing:
            flags |= FrameFlag.ZERO_FILLED
            st.frames_zero_filled += 1
            st.lost_bytes += missing
        if p.reordered:
            flags |= FrameFlag.REORDERED
        return AssembledFrame(f, bytes(p.buf), flags, missing, p.first_recv_ns)


# --- the host side ----------------------------------------------------------------------------


class Dca1000:
    """Talk to a DCA1000EVM and receive its raw ADC stream.

    Parameters
    ----------
    board_addr : (ip, port) of the board's config port (default 192.168.33.180:4096).
    host_ip : local address to bind (default 192.168.33.30, the board's fixed host).
    config_port, data_port : local ports (4096 / 4098; 0 picks a free port, for emulators).
    timeout_s : how long to wait for a command's answer.
    recv_buffer_bytes : requested kernel receive buffer of the data socket (bursts of a
        frame arrive faster than Python reads them).
    """

    def __init__(
        self,
        board_addr: tuple[str, int] = (BOARD_IP, CONFIG_PORT),
        host_ip: str = HOST_IP,
        config_port: int = CONFIG_PORT,
        data_port: int = DATA_PORT,
        timeout_s: float = 1.0,
        recv_buffer_bytes: int = 16 << 20,
    ):
        self.board_addr = (str(board_addr[0]), int(board_addr[1]))
        self.timeout_s = float(timeout_s)
        self._cfg = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._data = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._cfg.bind((host_ip, int(config_port)))
            self._data.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, int(recv_buffer_bytes))
            self._data.bind((host_ip, int(data_port)))
        except OSError as exc:
            self.close()
            raise TwinFocusError(
                f"cannot bind the DCA1000 host sockets on {host_ip} (config port {config_port}, data port {data_port}): "
                f"{exc.strerror or exc}; is the Ethernet interface set to {host_ip}, or another capture running?"
            ) from None
        self._cfg.settimeout(self.timeout_s)
        self.stats = AssemblerStats()

    @property
    def data_addr(self) -> tuple[str, int]:
        """Where the board must send data packets (host ip, data port)."""
        return self._data.getsockname()

    @property
    def config_addr(self) -> tuple[str, int]:
        return self._cfg.getsockname()

    def __enter__(self) -> Dca1000:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        for s in (self._cfg, self._data):
            try:
                s.close()
            except OSError:
                pass

    # -- commands ------------------------------------------------------------------------------

    def command(self, code: Command, body: bytes = b"", check: bool = True) -> int:
        """Send one command, return the board's status (raises on non-zero when ``check``)."""
        self._cfg.sendto(encode_command(code, body), self.board_addr)
        deadline = time.monotonic() + self.timeout_s
        while True:
            try:
                packet, _ = self._cfg.recvfrom(2048)
            except TimeoutError:
                raise TwinFocusError(
                    f"DCA1000 at {self.board_addr[0]}:{self.board_addr[1]} did not answer {Command(code).name} "
                    f"within {self.timeout_s:g} s (powered, cabled, host address {self.config_addr[0]}?)"
                ) from None
            try:
                got, status = decode_response(packet)
            except TwinFocusError:
                got, status = -1, 0
            if got == int(code):
                break
            if time.monotonic() > deadline:
                raise TwinFocusError(f"DCA1000 answered other commands but not {Command(code).name}")
        if check and status != 0:
            raise TwinFocusError(f"DCA1000 refused {Command(code).name} (status {status})")
        return status

    def connect(self) -> None:
        """SYSTEM_CONNECT: check the board is there."""
        self.command(Command.SYSTEM_CONNECT)

    def fpga_version(self) -> tuple[int, int, bool]:
        """(major, minor, playback mode) from READ_FPGA_VERSION."""
        v = self.command(Command.READ_FPGA_VERSION, check=False)
        return v & 0x7F, (v >> 7) & 0x7F, bool(v & 0x4000)

    def configure_fpga(self, lvds_lanes: int = 2, log_mode_raw: bool = True) -> None:
        """CONFIG_FPGA_GEN: raw mode, 2- or 4-lane LVDS, capture, Ethernet stream, 16 bit."""
        if lvds_lanes not in (2, 4):
            raise TwinFocusError(f"lvds_lanes must be 2 (xWR16xx/18xx/68xx) or 4 (xWR12xx/14xx), got {lvds_lanes}")
        body = struct.pack("<6B", 1 if log_mode_raw else 2, 1 if lvds_lanes == 4 else 2, 1, 2, 3, 30)
        self.command(Command.CONFIG_FPGA_GEN, body)

    def configure_record(self, packet_delay_us: float = 25.0) -> None:
        """CONFIG_PACKET_DATA: maximum packet size and the delay between packets."""
        ticks = int(packet_delay_us * 1000 / FPGA_CLK_PERIOD_NS)
        if not 0 < ticks < 1 << 16:
            raise TwinFocusError(f"packet delay {packet_delay_us} us is out of range (5..500 us)")
        self.command(Command.CONFIG_PACKET_DATA, struct.pack("<HHH", MAX_PACKET_BYTES, ticks, 0))

    def start_record(self) -> None:
        self.command(Command.RECORD_START)

    def stop_record(self) -> None:
        self.command(Command.RECORD_STOP)

    def setup(self, lvds_lanes: int = 2, packet_delay_us: float = 25.0) -> None:
        """The usual sequence before recording: connect, FPGA config, packet config."""
        self.connect()
        self.configure_fpga(lvds_lanes)
        self.configure_record(packet_delay_us)

    # -- data ----------------------------------------------------------------------------------

    def frames(
        self,
        layout: RawFrameLayout,
        loop: int | None = 0,
        max_frames: int | None = None,
        idle_timeout_s: float | None = 2.0,
        flush_after_s: float = 0.2,
        frame_period_s: float | None = None,
        reorder_window_bytes: int | None = None,
        stop=None,
    ) -> Iterator[RadarFrame]:
        """Yield :class:`RadarFrame` (host receive time, complex64 (n_tx, n_rx, N), flags).

        Frames come out in stream order, complete or zero-filled and flagged; a frame whose
        packets are all lost comes out all zeros, flagged LOST. When no packet arrives for
        ``flush_after_s`` the frames started so far are given out; after ``idle_timeout_s``
        (None: never) the iterator ends. ``stop`` (a ``threading.Event``) ends it early.
        Statistics accumulate in :attr:`stats`.
        """
        asm = FrameAssembler(layout.frame_bytes, reorder_window_bytes)
        self.stats = asm.stats
        buf = bytearray(65536)
        mv = memoryview(buf)
        sock = self._data
        # Non-blocking reads while packets flow (one system call per packet); select() only when
        # the queue is empty, to wait without spinning.
        sock.setblocking(False)
        poll_s = min(0.05, flush_after_s)
        last_packet = time.monotonic()
        flushed = True
        given = 0
        last_stamp: int | None = None
        period_ns = None if frame_period_s is None else int(frame_period_s * 1e9)
        while max_frames is None or given < max_frames:
            if stop is not None and stop.is_set():
                return
            try:
                n = sock.recv_into(buf)
            except BlockingIOError:
                if select.select([sock], [], [], poll_s)[0]:
                    continue
                idle = time.monotonic() - last_packet
                ready = []
                if not flushed and idle >= flush_after_s:
                    ready = asm.flush()
                    flushed = True
                elif idle_timeout_s is not None and idle >= idle_timeout_s:
                    return
            else:
                if n < DATA_HEADER_BYTES:
                    continue
                now = time.time_ns()
                last_packet = time.monotonic()
                flushed = False
                seq, lo, hi = struct.unpack_from("<IIH", buf)
                ready = asm.push(seq, lo | (hi << 32), mv[DATA_HEADER_BYTES:n], now)
            for fr in ready:
                stamp = fr.first_recv_ns
                if stamp is None:
                    stamp = (last_stamp or time.time_ns()) + (period_ns or 0)
                last_stamp = stamp
                data = layout.to_mimo(layout.decode(fr.raw), loop)
                yield RadarFrame(int(stamp), data, fr.flags)
                given += 1
                if max_frames is not None and given >= max_frames:
                    return
