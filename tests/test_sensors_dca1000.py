"""DCA1000EVM protocol: byte-exact frames, a loss/reorder-tolerant assembler, and the host
against an emulated board on 127.0.0.1 with injected faults."""

from __future__ import annotations

import socket
import struct
import time

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.sensors.dca1000 import (
    Command,
    Dca1000,
    FrameAssembler,
    RawFrameLayout,
    decode_command,
    decode_data_header,
    encode_command,
    encode_data_packet,
    encode_response,
)
from twinfocus.sensors.emulators.fake_dca1000 import FakeDca1000, LinkFaults, pattern_frame
from twinfocus.sensors.frames import FrameFlag

# Emulators and clients must stop every thread they start (conftest.py).
pytestmark = pytest.mark.usefixtures("no_stray_threads")


def test_command_and_packet_bytes_match_the_user_guide():
    # SYSTEM_CONNECT with no body, as on the wire: 5A A5 | 09 00 | 00 00 | AA EE
    assert encode_command(Command.SYSTEM_CONNECT) == bytes.fromhex("5aa509000000aaee")
    # CONFIG_PACKET_DATA: 1470-byte packets, 25 us delay = 3125 ticks of 8 ns
    pkt = encode_command(Command.CONFIG_PACKET_DATA, struct.pack("<HHH", 1470, 3125, 0))
    assert pkt == bytes.fromhex("5aa50b000600be05350c0000aaee")
    assert decode_command(pkt) == (0x0B, bytes.fromhex("be05350c0000"))
    assert encode_response(Command.RECORD_START, 0) == bytes.fromhex("5aa505000000aaee")
    data = encode_data_packet(7, 0x0102_0304_0506, b"xy")
    assert data == bytes.fromhex("07000000060504030201") + b"xy"
    assert decode_data_header(data) == (7, 0x0102_0304_0506)
    for bad, msg in [
        (b"\x5a\xa5\x09\x00", "shorter"),
        (bytes.fromhex("5aa5090001000000aaee"), "announces"),
        (bytes.fromhex("5aa509000000aaef"), "footer"),
        (bytes.fromhex("00a509000000aaee"), "header"),
    ]:
        with pytest.raises(TwinFocusError, match=msg):
            decode_command(bad)


def test_layout_decodes_iiqq_order():
    """xWR16xx raw: per chirp, per RX, samples as I0 I1 Q0 Q1 I2 I3 Q2 Q3."""
    lay = RawFrameLayout(n_samples=4, n_rx=2, tx_of_chirp=(1, 0), n_loops=1)
    vals = []
    for c in range(2):
        for r in range(2):
            i = [100 * c + 10 * r + s for s in range(4)]
            q = [-(100 * c + 10 * r + s) - 1 for s in range(4)]
            vals += [i[0], i[1], q[0], q[1], i[2], i[3], q[2], q[3]]
    raw = struct.pack(f"<{len(vals)}h", *vals)
    dec = lay.decode(raw)
    for c in range(2):
        for r in range(2):
            for s in range(4):
                assert dec[0, c, r, s] == complex(100 * c + 10 * r + s, -(100 * c + 10 * r + s) - 1)
    mimo = lay.to_mimo(dec)
    np.testing.assert_array_equal(mimo[1], dec[0, 0])  # chirp 0 fired TX 1
    iq = np.stack([mimo.real, mimo.imag], -1).astype(np.int16)[None]
    assert lay.encode(iq) == raw


def _packets(stream: bytes, size: int):
    return [(k + 1, off, stream[off : off + size]) for k, off in enumerate(range(0, len(stream), size))]


def test_assembler_in_order_drop_reorder_duplicate_late():
    fb = 100
    stream = bytes(range(256))[:250] + bytes(range(250))  # 5 frames of 100 bytes
    pk = _packets(stream, 30)  # packets straddle frame boundaries
    asm = FrameAssembler(fb, reorder_window_bytes=60)
    out = []
    order = list(range(len(pk)))
    order.remove(4)  # packet seq 5 (bytes 120..150, frame 1) never arrives
    order[7], order[8] = order[8], order[7]  # two packets of frame 2/3 swapped
    for j in order:
        out += asm.push(*pk[j])
        if j == 10:
            out += asm.push(*pk[10])  # duplicate
    out += asm.push(*pk[4][:2], pk[4][2])  # packet 5 arrives far too late: frame 1 is gone
    out += asm.flush()
    assert [f.index for f in out] == [0, 1, 2, 3, 4]
    expect = np.frombuffer(stream, np.uint8).reshape(5, fb).copy()
    expect[1, 20:50] = 0
    for f in out:
        np.testing.assert_array_equal(np.frombuffer(f.raw, np.uint8), expect[f.index])
    assert out[1].flags == FrameFlag.ZERO_FILLED and out[1].missing_bytes == 30
    assert out[0].flags == FrameFlag.OK and out[4].flags == FrameFlag.OK
    assert any(f.flags & FrameFlag.REORDERED for f in out[2:4])
    st = asm.stats
    assert (st.duplicate_packets, st.late_packets, st.frames_zero_filled) == (1, 1, 1)


def test_assembler_whole_frame_lost_and_resync():
    asm = FrameAssembler(100, reorder_window_bytes=0, max_gap_frames=4)
    out = asm.push(1, 0, b"\x01" * 100)
    out += asm.push(2, 300, b"\x02" * 100)  # frames 1 and 2 missing entirely
    assert [(f.index, f.flags) for f in out] == [
        (0, FrameFlag.OK),
        (1, FrameFlag.ZERO_FILLED | FrameFlag.LOST),
        (2, FrameFlag.ZERO_FILLED | FrameFlag.LOST),
        (3, FrameFlag.OK),
    ]
    out = asm.push(3, 100 * 1000, b"\x03" * 100)  # corrupt / restarted byte count: skip, do not emit 996 frames
    assert [f.index for f in out] == [1000] and asm.stats.frames_skipped == 996
    asm.push(200_000, 100 * 1001, b"\x04" * 50)  # half a frame, then the board restarts from 1
    out = asm.push(1, 0, b"\x05" * 100)
    assert [(f.index, f.flags) for f in out] == [(1001, FrameFlag.ZERO_FILLED), (0, FrameFlag.OK)]
    assert out[1].raw == b"\x05" * 100


def _host():
    return Dca1000(board_addr=("127.0.0.1", 9), host_ip="127.0.0.1", config_port=0, data_port=0, timeout_s=1.0)


def test_loopback_stream_with_injected_loss_and_reordering():
    lay = RawFrameLayout(n_samples=64, n_rx=4, tx_of_chirp=(0, 1, 2), n_loops=2)  # 6144-byte frames
    n_frames = 40
    drop = {3, 50, 51, 120}
    with (
        _host() as host,
        FakeDca1000(
            lay,
            n_frames=n_frames,
            frame_period_s=0.002,
            faults=LinkFaults(drop_packets=drop, swap_packets={10, 77, 150}, duplicate_packets={60}),
        ) as board,
    ):
        host.board_addr = board.config_addr
        board.host_data_addr = host.data_addr
        host.setup(packet_delay_us=25)
        assert host.fpga_version() == (2, 9, False)
        host.start_record()
        frames = list(host.frames(lay, loop=1, max_frames=n_frames, idle_timeout_s=1.0))
        host.stop_record()
        assert board.commands[:3] == [Command.SYSTEM_CONNECT, Command.CONFIG_FPGA_GEN, Command.CONFIG_PACKET_DATA]
    assert len(frames) == n_frames
    fb = lay.frame_bytes
    hit = {(s - 1) * 1456 // fb for s in drop} | {((s - 1) * 1456 + 1455) // fb for s in drop}
    for k, fr in enumerate(frames):
        truth = lay.to_mimo(lay.decode(pattern_frame(k, lay)), loop=1)
        if k in hit:
            assert fr.flags & FrameFlag.ZERO_FILLED, k
            assert not fr.flags.usable
        else:
            assert fr.flags.usable, (k, fr.flags)
            np.testing.assert_array_equal(fr.data, truth)
    assert sum(bool(f.flags & FrameFlag.REORDERED) for f in frames) >= 2
    stamps = [f.stamp_ns for f in frames]
    assert stamps == sorted(stamps)
    assert host.stats.duplicate_packets == 1 and host.stats.reordered_packets == 3


def test_stream_that_stops_mid_frame_does_not_stall():
    lay = RawFrameLayout(n_samples=64, n_rx=4, tx_of_chirp=(0,))
    with (
        _host() as host,
        FakeDca1000(lay, n_frames=3, frame_period_s=None, faults=LinkFaults(drop_packets={3})) as board,
    ):
        board.host_data_addr = host.data_addr
        board.start_streaming()
        t0 = time.monotonic()
        frames = list(host.frames(lay, idle_timeout_s=0.5, flush_after_s=0.1))
        elapsed = time.monotonic() - t0
    # 3 frames of 1024 bytes in 3 packets; packet 3 (the last, frame 2's tail) is lost: frame 2 comes
    # out zero-filled by the idle flush instead of being waited for.
    assert [bool(f.flags & FrameFlag.ZERO_FILLED) for f in frames] == [False, False, True]
    assert elapsed < 3.0


def test_board_refusal_and_silence_are_clear_errors():
    lay = RawFrameLayout(n_samples=4, n_rx=1, tx_of_chirp=(0,))
    with _host() as host, FakeDca1000(lay) as board:
        host.board_addr = board.config_addr
        with pytest.raises(TwinFocusError, match="refused CONFIG_FPGA_GEN"):
            host.command(Command.CONFIG_FPGA_GEN, b"\x01\x02")  # 2-byte body, the board wants 6
    silent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    silent.bind(("127.0.0.1", 0))
    try:
        with Dca1000(
            board_addr=silent.getsockname(), host_ip="127.0.0.1", config_port=0, data_port=0, timeout_s=0.2
        ) as host:
            with pytest.raises(TwinFocusError, match="did not answer SYSTEM_CONNECT"):
                host.connect()
    finally:
        silent.close()
    with pytest.raises(TwinFocusError, match="cannot bind"):
        Dca1000(host_ip="203.0.113.7", config_port=0, data_port=0)  # an address this host does not have
