"""Gaps of an MMWCAS capture named: frames missing from all four devices (index time stamps that
jump by two or more frame periods) and frames the card wrote as zeros are counted, warned about,
recorded in ``<scan>.capture.json`` and carried by the live backend to the solver's metrics."""

from __future__ import annotations

import json

import numpy as np

from tests.helpers import convert_capture
from twinfocus.radar.fmcw import Chirp
from twinfocus.sensors.emulators.mmwcas_capture import write_mmwcas_capture
from twinfocus.sensors.frames import FrameFlag
from twinfocus.sensors.ti_mmwcas import MmwcasCapture, MmwcasConfig

N = 8
PERIOD_NS = 100_000_000
CFG = MmwcasConfig(chirp=Chirp(n_samples=N))


def _capture(folder, periods, zero=(), slice_index=0, bad_first_frame=True, seed=0):
    """Frames at the given multiples of the frame period (a missing multiple: a frame no device
    wrote), random non-zero samples except the frames in ``zero``."""
    periods = np.asarray(periods)
    iq = np.random.default_rng(seed).integers(1, 2000, size=(periods.size, 12, 16, N, 2), dtype=np.int16)
    iq[list(zero)] = 0
    write_mmwcas_capture(
        folder, iq, 10**9 + periods * PERIOD_NS, CFG, slice_index=slice_index, bad_first_frame=bad_first_frame
    )
    return iq


def test_frames_missing_from_every_device_are_counted(tmp_path):
    _capture(tmp_path / "one", [0, 1, 2, 4, 5, 6, 7])  # period 3 never written
    with MmwcasCapture(tmp_path / "one", CFG) as cap:
        assert len(cap) == 7 and cap.frames_missing == 1
        assert cap.frames_missing_before.tolist() == [0, 0, 0, 1, 1, 1, 1]
        assert any("1 frame(s) missing from every device" in w for w in cap.warnings)
        assert all(FrameFlag(int(f)) == FrameFlag.OK for f in cap.flags)  # the frames there are good
    _capture(tmp_path / "three", [0, 1, 4, 5, 6, 8, 9])  # 2, 3 and 7 missing
    with MmwcasCapture(tmp_path / "three", CFG) as cap:
        assert cap.frames_missing == 3 and cap.frames_missing_before.tolist() == [0, 0, 2, 2, 2, 3, 3]
    _capture(tmp_path / "none", range(7))
    with MmwcasCapture(tmp_path / "none", CFG) as cap:
        assert cap.frames_missing == 0 and not cap.warnings


def test_a_slave_alone_late_is_skew_not_a_missing_frame(tmp_path):
    iq = np.ones((5, 12, 16, N, 2), np.int16)
    skew = np.zeros((5, 4), np.int64)
    skew[2, 1] = PERIOD_NS  # slave1 one frame late on frame 2 only
    write_mmwcas_capture(tmp_path, iq, 10**9 + np.arange(5) * PERIOD_NS, CFG, device_skew_ns=skew)
    with MmwcasCapture(tmp_path, CFG) as cap:
        assert cap.frames_missing == 0 and FrameFlag(int(cap.flags[2])) == FrameFlag.DEVICE_SKEW


def test_dropping_each_slices_first_frame_is_not_a_gap(tmp_path):
    _capture(tmp_path, [0, 1, 2], slice_index=0)
    _capture(tmp_path, [3, 4, 5], slice_index=1, bad_first_frame=False, seed=1)
    with MmwcasCapture(tmp_path, CFG, skip_first_frame_of_each_slice=True) as cap:
        assert len(cap) == 5 and cap.frames_missing == 0


def test_all_zero_frames_are_flagged(tmp_path):
    _capture(tmp_path, range(6), zero=[2])
    with MmwcasCapture(tmp_path, CFG) as cap:
        assert [FrameFlag(int(f)) for f in cap.flags] == [FrameFlag.OK] * 2 + [FrameFlag.ZERO_FILLED] + [
            FrameFlag.OK
        ] * 3
        assert any("1 frame(s) hold only zeros on some device (frame 2)" in w for w in cap.warnings)
    # One device's share of a frame all zero is enough (the other three hold data).
    iq = np.random.default_rng(4).integers(1, 2000, size=(3, 12, 16, N, 2), dtype=np.int16)
    iq[1][:, [0, 1, 2, 3]] = 0  # array RX 0-3 are data channels 13-16: slave3's four RX
    write_mmwcas_capture(tmp_path / "dev", iq, 10**9 + np.arange(3) * PERIOD_NS, CFG)
    with MmwcasCapture(tmp_path / "dev", CFG) as cap:
        assert [FrameFlag(int(f)) for f in cap.flags] == [FrameFlag.OK, FrameFlag.ZERO_FILLED, FrameFlag.OK]


def test_convert_records_and_warns_the_gaps(tmp_path, capsys):
    from twinfocus.motion.trajectory import Poses
    from twinfocus.radar.scan import Scan
    from twinfocus.sensors.trajectory_files import write_tum

    _capture(tmp_path / "cap", [0, 1, 2, 4, 5, 6, 7], zero=[5])  # period 3 missing; frame 5 (period 6) zeros
    t = 10**18 + np.arange(9) * PERIOD_NS
    write_tum(
        tmp_path / "traj.txt",
        Poses(t, np.stack([np.arange(9) * 1e-3, np.zeros(9), np.zeros(9)], 1), np.tile([0.0, 0, 0, 1], (9, 1))),
    )
    rc = convert_capture(tmp_path, "--n-samples", N)
    out, err = capsys.readouterr()
    assert rc == 0
    assert "1 frame(s) missing from every device" in err and "hold only zeros on some device (frame 5)" in err
    summary = json.loads(out)
    report = json.loads((tmp_path / "s.capture.json").read_text())
    for got in (summary, report):
        assert (got["frames"], got["frames_used"] if "frames_used" in got else got["used"]) == (7, 6)
        assert got["frames_lost"] == 1 and got["frames_zero_filled"] == 1
    assert report["frames_dropped_flagged"] == 1
    assert Scan.load(tmp_path / "s.npz").n_positions == 6


def test_live_backend_carries_the_gaps(tmp_path):
    """The mmwcas radar backend gives each frame the capture's gaps so far, which the radar driver
    puts on radar/frame and the solver turns into each scan's metrics (tests/test_sensors_gaps.py)."""
    from nodes.runtime.backends import RADAR_BACKENDS, load_backend

    _capture(tmp_path / "cap", [0, 1, 2, 4, 5, 6, 7], zero=[5])
    b = load_backend(RADAR_BACKENDS, "mmwcas", "radar")({"capture": str(tmp_path / "cap"), "n_samples": N})
    try:
        got = [s.gaps for s in b.samples()]
    finally:
        b.close()
    # frame 5 (zeros) is not streamed; its count reaches the frames after it
    assert got == [(0, 0, 0), (0, 0, 0), (0, 0, 0), (1, 0, 0), (1, 0, 0), (1, 1, 0)]
