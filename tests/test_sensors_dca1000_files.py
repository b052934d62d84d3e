"""DCA1000 capture files: every sample of a tagged capture lands where it belongs in each of the
forms users have (mmWave Studio raw, CLI reordered, CLI sequence-number records, _Raw_N splits),
and `twinfocus convert` turns one into the same scan as frames built from the tags directly.

The files are written here by a deliberately plain writer (Python loops over chirps, RX and
sample pairs, struct for the record headers), not by the reader's module."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from tests.helpers import cli
from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import Chirp
from twinfocus.sensors.dca1000 import RawFrameLayout
from twinfocus.sensors.dca1000_files import Dca1000FileCapture, capture_files, read_cli_json
from twinfocus.sensors.frames import FrameFlag

N, RX, CHIRPS = 4, 16, 12
# A non-trivial chirp order: chirp c fires TX TX_OF_CHIRP[c].
TX_OF_CHIRP = (3, 0, 7, 1, 11, 2, 9, 4, 10, 5, 8, 6)
LAYOUT = RawFrameLayout(N, RX, TX_OF_CHIRP, 1, 12)
FRAME_BYTES = CHIRPS * RX * N * 4


def tag(frame, chirp, rx, n):
    """(I, Q) of one sample: distinct for every (frame, chirp, rx, sample), Q never equal to I."""
    i = (frame * 997 + chirp * 131 + rx * 17 + n * 3) % 20000 - 10000
    return i, -i - 1 if i >= 0 else -i + 7


def stream_values(n_frames, form):
    """int16 values of the capture, written sample pair by sample pair in the named form."""
    out = []
    for f in range(n_frames):
        for c in range(CHIRPS):
            for r in range(RX):
                for n in range(0, N, 2):
                    (i0, q0), (i1, q1) = tag(f, c, r, n), tag(f, c, r, n + 1)
                    # LVDS 2-lane order I0 I1 Q0 Q1 (readDCA1000.m); the CLI's reorder gives I0 Q0 I1 Q1.
                    out += [i0, i1, q0, q1] if form == "raw" else [i0, q0, i1, q1]
    return struct.pack(f"<{len(out)}h", *out)


def expected_mimo(f):
    x = np.zeros((12, RX, N), np.complex64)
    for c in range(CHIRPS):
        for r in range(RX):
            for n in range(N):
                i, q = tag(f, c, r, n)
                x[TX_OF_CHIRP[c], r, n] = complex(i, q)
    return x


def write_records(path, stream: bytes, drop=(), swap=()):
    """Sequence-number records: u32 seq | u32 size | 48-bit byte count | payload, per 1456-byte packet."""
    packets = []
    for k, start in enumerate(range(0, len(stream), 1456)):
        payload = stream[start : start + 1456]
        packets.append(struct.pack("<II", k + 1, len(payload)) + start.to_bytes(6, "little") + payload)
    for k in swap:
        packets[k], packets[k + 1] = packets[k + 1], packets[k]
    path.write_bytes(b"".join(p for k, p in enumerate(packets) if k not in drop))


def _cli_json(path, lvds_mode, data_format, sequence_numbers):
    """The DCA1000 CLI's JSON with these fields written to ``path``, read back (read_cli_json)."""
    capture = {"sequenceNumberEnable": sequence_numbers}
    config = {"lvdsMode": lvds_mode, "dataFormatConfig": data_format, "captureConfig": capture}
    path.write_text(json.dumps({"DCA1000Config": config}))
    return read_cli_json(path)


@pytest.mark.parametrize("form", ["raw", "reordered"])
def test_every_sample_lands_in_place(tmp_path, form):
    (tmp_path / "adc_data.bin").write_bytes(stream_values(3, form))
    settings = None
    if form == "reordered":
        # A CLI JSON that omits reorderEnable: the CLI reorders then (cli_record_main.cpp).
        settings = _cli_json(tmp_path / "cf.json", 2, {"MSBToggle": 0}, sequence_numbers=0)
        assert settings.reorder
    cap = Dca1000FileCapture(tmp_path, LAYOUT, 0.05, "auto", settings)
    assert cap.format == form and len(cap.frames) == 3
    for f, fr in enumerate(cap.frames):
        np.testing.assert_array_equal(fr.data, expected_mimo(f))
        assert fr.stamp_ns == f * 50_000_000 and fr.flags == FrameFlag.OK


def test_reordered_file_read_as_raw_is_wrong(tmp_path):
    """The trap: a CLI file cut into frames as if it were Studio's raw form."""
    (tmp_path / "adc_data.bin").write_bytes(stream_values(1, "reordered"))
    cap = Dca1000FileCapture(tmp_path, LAYOUT, 0.05, "raw")
    assert not np.array_equal(cap.frames[0].data, expected_mimo(0))


def test_split_files_and_records_with_lost_and_swapped_packets(tmp_path):
    stream = stream_values(4, "raw")
    whole = tmp_path / "whole.bin"
    # Packet 2 (bytes 2912..4367) is lost: the end of frame 0 and the start of frame 1 are zero;
    # packets 6 and 7 arrive swapped (frames 2 and 3, complete).
    write_records(whole, stream, drop={2}, swap={6})
    data = whole.read_bytes()
    cut = 3 * (14 + 1456)  # the CLI cuts split files at record / packet boundaries
    (tmp_path / "adc_data_Raw_0.bin").write_bytes(data[:cut])
    (tmp_path / "adc_data_Raw_1.bin").write_bytes(data[cut:])
    whole.unlink()
    assert [p.name for p in capture_files(tmp_path / "adc_data_Raw_1.bin")] == [
        "adc_data_Raw_0.bin",
        "adc_data_Raw_1.bin",
    ]
    cap = Dca1000FileCapture(tmp_path, LAYOUT, 0.05)
    assert cap.format == "records" and len(cap.frames) == 4
    want = bytearray(stream)
    want[2 * 1456 : 3 * 1456] = bytes(1456)
    for f in (0, 1):
        raw = bytes(want[f * FRAME_BYTES : (f + 1) * FRAME_BYTES])
        np.testing.assert_array_equal(cap.frames[f].data, LAYOUT.to_mimo(LAYOUT.decode(raw)))
        assert cap.frames[f].flags & FrameFlag.ZERO_FILLED and not cap.frames[f].flags.usable
    for f in (2, 3):
        np.testing.assert_array_equal(cap.frames[f].data, expected_mimo(f))
        assert cap.frames[f].flags.usable
    assert cap.stats.frames_zero_filled == 2 and cap.stats.lost_bytes == 1456 and cap.stats.frames_lost == 0
    assert cap.stats.reordered_packets == 1


def test_long_record_capture_with_an_early_hole(tmp_path):
    """More frames than the assembler's resynchronisation distance (64) after a holed frame."""
    n = 70
    stream = b"".join(struct.pack("<h", (k * 7) % 30000) for k in range(n * FRAME_BYTES // 2))
    write_records(tmp_path / "adc_data_Raw_0.bin", stream, drop={1})
    cap = Dca1000FileCapture(tmp_path, LAYOUT, 0.05, "records")
    assert len(cap.frames) == n and cap.stats.frames_skipped == 0
    assert [f.usable for f in (fr.flags for fr in cap.frames)] == [False] + [True] * (n - 1)
    for f in (1, n - 1):
        want = LAYOUT.to_mimo(LAYOUT.decode(stream[f * FRAME_BYTES : (f + 1) * FRAME_BYTES]))
        np.testing.assert_array_equal(cap.frames[f].data, want)


def test_cli_json_settings_and_refusals(tmp_path):
    s = _cli_json(tmp_path / "a.json", 1, {"reorderEnable": 0}, sequence_numbers=1)
    assert (s.reorder, s.sequence_numbers, s.lvds_lanes) == (False, True, 4)
    (tmp_path / "adc_data.bin").write_bytes(stream_values(1, "raw"))
    with pytest.raises(TwinFocusError, match="4 LVDS lanes"):
        Dca1000FileCapture(tmp_path, LAYOUT, 0.05, "auto", s)
    (tmp_path / "b.json").write_text('{"DCA1000Config": {"dataFormatConfig": {"reorderEnable": "yes"}}}')
    with pytest.raises(TwinFocusError, match="reorderEnable must be 0 or 1"):
        read_cli_json(tmp_path / "b.json")
    (tmp_path / "empty").mkdir()
    with pytest.raises(TwinFocusError, match="no DCA1000 capture here"):
        capture_files(tmp_path / "empty")


def test_msb_toggle_is_taken_off(tmp_path):
    raw = np.frombuffer(stream_values(1, "reordered"), "<i2")
    toggled = (raw.view("<u2") + np.uint16(0x8000)).astype("<u2")  # the CLI adds 0x8000 (recorddatarecv.cpp)
    (tmp_path / "adc_data.bin").write_bytes(toggled.tobytes())
    (tmp_path / "cf.json").write_text(
        json.dumps({"DCA1000Config": {"dataFormatConfig": {"reorderEnable": 1, "MSBToggle": 1}}})
    )
    cap = Dca1000FileCapture(tmp_path, LAYOUT, 0.05, "auto", read_cli_json(tmp_path / "cf.json"))
    np.testing.assert_array_equal(cap.frames[0].data, expected_mimo(0))


def test_convert_gives_the_scan_of_the_frames(tmp_path, capsys):
    """convert on a CLI file == scan_from_frames on frames built from the tags (the live path's step)."""
    from twinfocus.motion.trajectory import Poses
    from twinfocus.radar.scan import Scan
    from twinfocus.sensors.capture_to_scan import read_capture_report, scan_from_frames
    from twinfocus.sensors.frames import RadarFrame
    from twinfocus.sensors.trajectory_files import write_tum

    n_frames = 5
    stream = stream_values(n_frames, "raw")
    # Packet 3 (bytes 4368..5823) lost: inside frame 1 (bytes 3072..6143), which is zero-filled and
    # must be dropped from the scan.
    write_records(tmp_path / "adc_data_Raw_0.bin", stream, drop={3})
    t = 1_000_000_000 + np.arange(11) * 25_000_000
    pos = np.stack([np.arange(11) * 0.001, np.zeros(11), np.zeros(11)], axis=1)
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (11, 1))
    poses = Poses(t, pos, quat)
    write_tum(tmp_path / "traj.txt", poses)
    raw = tmp_path / "adc_data_Raw_0.bin"
    options = ("--n-samples", N, "--frame-period-s 0.05 --quiet")
    rc = cli("convert", raw, "--trajectory", tmp_path / "traj.txt", "--out", tmp_path / "scan.npz", *options)
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["frames"] == n_frames and out["used"] == n_frames - 1 and out["frames_zero_filled"] == 1
    assert out["bytes_lost"] == 1456
    # The convert's default layout is the emulated rig's (chirp c = TX c): rebuild with that.
    plain = RawFrameLayout(N, RX, tuple(range(12)), 1, 12)
    frames = [
        RadarFrame(
            f * 50_000_000,
            plain.to_mimo(plain.decode(stream[f * FRAME_BYTES : (f + 1) * FRAME_BYTES])),
            FrameFlag.ZERO_FILLED if f == 1 else FrameFlag.OK,
        )
        for f in range(n_frames)
    ]
    chirp = Chirp(76.6e9, 120e12, 8e6, N)
    want, _, _ = scan_from_frames(frames, chirp, poses, 0.6)
    got = Scan.load(tmp_path / "scan.npz")
    np.testing.assert_array_equal(got.data, want.data)
    np.testing.assert_allclose(got.positions, want.positions)
    gaps = read_capture_report(tmp_path / "scan.npz")
    assert gaps["frames_zero_filled"] == 1 and gaps["bytes_lost"] == 1456 and gaps["frames_dropped_flagged"] == 1
