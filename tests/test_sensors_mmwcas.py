"""TI MMWCAS cascade captures: TI's file layout read back exactly, bad files refused clearly,
and the MIMO frame -> virtual channel step checked against the radar model."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from tests.helpers import cli
from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import Poses
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
from twinfocus.sensors.emulators.mmwcas_capture import write_mmwcas_capture
from twinfocus.sensors.emulators.radar_scene import monostatic_if, simulate_mimo_frames
from twinfocus.sensors.frames import FrameFlag, frame_to_virtual_channels, mmwcas_antenna_positions_body_m
from twinfocus.sensors.ti_mmwcas import MmwcasCapture, MmwcasConfig, read_index

# TI's TI_Cascade_RX_ID (module_param.m): array RX i (ascending along the board) is data channel
# RX_ID[i], data channels 1-4 master, 5-8 slave1, 9-12 slave2, 13-16 slave3.
TI_RX_ID = [13, 14, 15, 16, 1, 2, 3, 4, 9, 10, 11, 12, 5, 6, 7, 8]
DEVICES = ["master", "slave1", "slave2", "slave3"]


def _idx_bytes(entries, num_idx=None, tag=0x746B6362, data_size=0):
    """An _idx.bin written field by field with struct, as TI's Bucket::Info / BuffIdx declare."""
    out = struct.pack("<IIIIQ", tag, 1, 0, len(entries) if num_idx is None else num_idx, data_size)
    for e in entries:
        out += struct.pack("<HHIHH4IIQQ", e.get("tag", 0x6469), 1, 0, 0, 0, 0, 0, 0, 0, e["size"], e["ts"], e["offset"])
    return out


def _value(dev, frame, loop, chirp, sample, rx, iq):
    """A distinct int16 for every field of a device frame (the 'truth' of the layout test)."""
    return np.int16(((dev * 7 + frame * 131 + loop * 17 + chirp * 29 + sample * 3 + rx * 5 + iq * 11) % 60000) - 30000)


def test_reader_follows_ti_layout_and_rx_order(tmp_path):
    """Device files written value by value in TI's order: RX fastest, sample, chirp, loop."""
    n, loops, n_frames = 4, 2, 3
    cfg = MmwcasConfig(chirp=Chirp(n_samples=n), n_loops=loops, tx_of_chirp=tuple(range(12)))
    fb = cfg.device_frame_bytes
    for d, dev in enumerate(DEVICES):
        data = bytearray()
        for f in range(n_frames):
            for lp in range(loops):
                for c in range(12):
                    for s in range(n):
                        for r in range(4):
                            data += struct.pack("<hh", _value(d, f, lp, c, s, r, 0), _value(d, f, lp, c, s, r, 1))
        (tmp_path / f"{dev}_0000_data.bin").write_bytes(bytes(data))
        entries = [{"size": fb, "ts": 1000 + 100_000 * f + d, "offset": f * fb} for f in range(n_frames)]
        (tmp_path / f"{dev}_0000_idx.bin").write_bytes(_idx_bytes(entries, data_size=len(data)))
    with MmwcasCapture(tmp_path, cfg, skip_first_frame=False) as cap:
        assert len(cap) == n_frames
        np.testing.assert_array_equal(cap.timestamps_ns, [(1000 + 100_000 * f) * 1000 for f in range(n_frames)])
        for f in range(n_frames):
            frame = cap.read_frame(f)  # (loops, 12 TX, 16 RX, n)
            for lp in range(loops):
                for tx in range(12):
                    for a in range(16):
                        d, r = divmod(TI_RX_ID[a] - 1, 4)
                        for s in range(n):
                            z = frame[lp, tx, a, s]
                            assert z.real == _value(d, f, lp, tx, s, r, 0)
                            assert z.imag == _value(d, f, lp, tx, s, r, 1)


def test_generator_round_trip_is_bit_exact_and_first_frame_dropped(tmp_path):
    rng = np.random.default_rng(3)
    cfg = MmwcasConfig(chirp=Chirp(n_samples=8), tx_of_chirp=(3, 1, 0, 2, 4, 5, 6, 7, 8, 11, 10, 9))
    iq = rng.integers(-32768, 32767, size=(5, 12, 16, 8, 2), dtype=np.int16, endpoint=True)
    ts = 7_000_000_000 + np.arange(5) * 100_000_000  # multiples of the microsecond tick
    write_mmwcas_capture(tmp_path, iq[:3], ts[:3], cfg, slice_index=0)
    write_mmwcas_capture(tmp_path, iq[3:], ts[3:], cfg, slice_index=1, bad_first_frame=False)
    with MmwcasCapture(tmp_path, cfg) as cap:
        assert len(cap) == 5 and cap.warnings == []
        np.testing.assert_array_equal(cap.timestamps_ns, ts)
        for i, fr in enumerate(cap.frames()):
            assert fr.flags == FrameFlag.OK
            np.testing.assert_array_equal(fr.data.real, iq[i, ..., 0])
            np.testing.assert_array_equal(fr.data.imag, iq[i, ..., 1])
    with MmwcasCapture(tmp_path, cfg, skip_first_frame=False) as cap:
        assert len(cap) == 6  # the garbage frame the card writes first is there when asked for
        assert cap.timestamps_ns[0] == ts[0] - 100_000_000


def test_truncated_capture_keeps_complete_frames(tmp_path):
    cfg = MmwcasConfig(chirp=Chirp(n_samples=4))
    iq = np.ones((4, 12, 16, 4, 2), np.int16)
    write_mmwcas_capture(tmp_path, iq, np.arange(4) * 100_000_000, cfg)
    data = tmp_path / "slave2_0000_data.bin"
    data.write_bytes(data.read_bytes()[: 3 * cfg.device_frame_bytes + 10])  # cut inside frame 3 (incl. junk)
    idx = tmp_path / "master_0000_idx.bin"
    idx.write_bytes(idx.read_bytes()[:-20])  # last entry cut short
    with MmwcasCapture(tmp_path, cfg) as cap:
        assert len(cap) == 2  # frames 1, 2 of the written 0..4 (0 is the bad first frame, 3 cut)
        assert any("cut short" in w for w in cap.warnings)
        assert any("slave2" in w and "truncated" in w for w in cap.warnings)
        np.testing.assert_array_equal(cap.read_frame(1)[0].real, 1)


def test_device_skew_is_flagged(tmp_path):
    cfg = MmwcasConfig(chirp=Chirp(n_samples=4))
    skew = np.zeros((3, 4), np.int64)
    skew[1, 2] = 60_000_000  # slave2 late by more than half of the 100 ms period
    write_mmwcas_capture(
        tmp_path, np.ones((3, 12, 16, 4, 2), np.int16), np.arange(3) * 100_000_000, cfg, device_skew_ns=skew
    )
    with MmwcasCapture(tmp_path, cfg) as cap:
        assert [f.flags for f in cap.frames()] == [FrameFlag.OK, FrameFlag.DEVICE_SKEW, FrameFlag.OK]
        assert not FrameFlag.DEVICE_SKEW.usable


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda p: (p / "master_0000_idx.bin").write_bytes(b"\x00" * 10), "shorter than its 24-byte header"),
        (lambda p: (p / "master_0000_idx.bin").write_bytes(_idx_bytes([], tag=0x12345678)), "not a TI capture index"),
        (
            lambda p: (p / "slave3_0000_idx.bin").write_bytes(
                _idx_bytes([{"size": 1, "ts": 0, "offset": 0, "tag": 7}])
            ),
            "first index entry has tag",
        ),
        (lambda p: (p / "slave1_0000_data.bin").unlink(), "slave1_0000_data.bin: missing"),
        (
            lambda p: (p / "master_0000_idx.bin").write_bytes(_idx_bytes([{"size": 999, "ts": 0, "offset": 0}])),
            "configuration expects",
        ),
    ],
)
def test_malformed_captures_are_refused_clearly(tmp_path, damage, message):
    cfg = MmwcasConfig(chirp=Chirp(n_samples=4))
    write_mmwcas_capture(tmp_path, np.zeros((2, 12, 16, 4, 2), np.int16), np.arange(2) * 100_000_000, cfg)
    damage(tmp_path)
    with pytest.raises(TwinFocusError, match=message):
        MmwcasCapture(tmp_path, cfg)


def test_empty_folder_and_index_header_fields(tmp_path):
    with pytest.raises(TwinFocusError, match="no MMWCAS capture here"):
        MmwcasCapture(tmp_path)
    p = tmp_path / "x_idx.bin"
    p.write_bytes(_idx_bytes([{"size": 5, "ts": 42, "offset": 7}, {"size": 5, "ts": 43, "offset": 12}], num_idx=3))
    idx = read_index(p)
    assert idx.entries["timestamp"].tolist() == [42, 43] and idx.entries["offset"].tolist() == [7, 12]
    assert any("counts 3 frames" in w for w in idx.warnings)


def test_virtual_channels_match_monostatic_model_of_a_point_target():
    """Bistatic pairs (R_tx + R_rx) -> 86 channels ~ a co-located TX/RX at each pair's midpoint."""
    chirp = Chirp(n_samples=64)
    va = mmwcas_virtual_array()
    z0 = 0.6
    target = np.array([[0.01, -0.005, z0]])
    pose = Poses(np.array([0]), np.array([[0.002, 0.003, 0.0]]), np.array([[0.0, 0.0, 0.0, 1.0]]))
    frame = simulate_mimo_frames(chirp, pose, target)[0]
    # brute-force check of the simulator itself on one pair
    tx, rx = mmwcas_antenna_positions_body_m()
    p_tx, p_rx = tx[5] + pose.position_m[0], rx[9] + pose.position_m[0]
    path = np.linalg.norm(target[0] - p_tx) + np.linalg.norm(target[0] - p_rx)
    np.testing.assert_allclose(frame[5, 9], np.exp(1j * chirp.wavenumbers_rad_per_m * path), atol=2e-6)

    virt = frame_to_virtual_channels(frame, chirp, z0)
    centres = va.offsets_m + pose.position_m[0]
    truth = monostatic_if(chirp, centres, target)
    phase_err = np.angle(virt * np.conj(truth))
    assert virt.shape == (86, 64)
    assert np.abs(phase_err).max() < 0.05  # rad: the near-field correction holds near z0
    raw_err = np.angle(frame[va.tx_index, va.rx_index] * np.conj(truth))
    assert np.abs(raw_err).max() > 1.0  # without it the pairs are far off (the test can fail)


def _small_capture(tmp_path, n=16, frames=6):
    chirp = Chirp(n_samples=n)
    cfg = MmwcasConfig(chirp=chirp)
    rng = np.random.default_rng(1)
    iq = rng.integers(-2000, 2000, size=(frames, 12, 16, n, 2), dtype=np.int16)
    card_ts = 5_000_000_000 + np.arange(frames) * 100_000_000
    write_mmwcas_capture(tmp_path / "cap", iq, card_ts, cfg)
    return chirp, iq


def test_convert_cli_writes_scan_and_mcap(tmp_path, capsys):
    from msgs.mcap_log import LogReader
    from twinfocus.motion.trajectory import quat_to_matrix
    from twinfocus.radar.scan import Scan
    from twinfocus.sensors.trajectory_files import write_tum

    chirp, iq = _small_capture(tmp_path)
    # Camera trajectory on another clock, 2 poses per frame, moving in x and turning slightly.
    t = 1_700_000_000_000_000_000 + np.arange(13) * 50_000_000
    pos = np.stack([np.arange(13) * 0.001, np.zeros(13), 0.01 * np.ones(13)], axis=1)
    ang = np.arange(13) * 0.002
    quat = np.stack([np.zeros(13), np.sin(ang / 2), np.zeros(13), np.cos(ang / 2)], axis=1)
    write_tum(tmp_path / "traj.txt", Poses(t, pos, quat, np.linspace(0.5, 1.0, 13)))
    (tmp_path / "ext.yaml").write_text("translation_m: [0.0, 0.05, -0.01]\nrotation_xyzw: [0, 0, 0, 1]\n")
    capture = (tmp_path / "cap", "--trajectory", tmp_path / "traj.txt", "--extrinsics", tmp_path / "ext.yaml")
    outputs = ("--out", tmp_path / "scan.npz", "--mcap", tmp_path / "log.mcap")
    rc = cli("convert", *capture, *outputs, "--n-samples 16 --frame world --quiet")
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 6 and summary["used"] == 6
    scan = Scan.load(tmp_path / "scan.npz")
    # Frame m falls on pose 2m (clocks aligned at the start): radar = camera pose . T_camera_radar.
    va = mmwcas_virtual_array()
    for m in range(6):
        r = quat_to_matrix(quat[2 * m])
        radar_origin = pos[2 * m] + r @ np.array([0.0, 0.05, -0.01])
        np.testing.assert_allclose(scan.positions[m], radar_origin + va.offsets_m @ r.T, atol=1e-12)
        frame = iq[m, ..., 0] + 1j * iq[m, ..., 1]
        np.testing.assert_allclose(scan.data[m], frame_to_virtual_channels(frame, chirp, 0.6), rtol=1e-6)
    np.testing.assert_array_equal(scan.timestamps_ns, t[0:12:2])
    log = LogReader(tmp_path / "log.mcap")
    assert log.counts == {"radar/frame": 6, "vio/pose": 11} and log.metadata["radar"]["n_channels"] == 86


def test_convert_cli_errors_are_one_line(tmp_path, capsys):

    _small_capture(tmp_path)
    out = ("--out", tmp_path / "s.npz")
    rc = cli("convert", tmp_path / "cap", "--trajectory", tmp_path / "missing.txt", *out, "--n-samples 16")
    err = capsys.readouterr().err
    assert rc == 2 and "missing.txt: no such trajectory file" in err and "Traceback" not in err
    (tmp_path / "t.txt").write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n")
    rc = cli("convert", tmp_path / "cap", "--trajectory", tmp_path / "t.txt", *out, "--n-samples 32 --quiet")
    assert rc == 2 and "configuration expects" in capsys.readouterr().err
