"""Cascade chirp layouts other than TI's default, read from the capture's mmWave Studio JSON or
given as options; device skew at any frame period; time-stamp units checked against the period;
the first frame of each capture slice."""

from __future__ import annotations

import numpy as np
import pytest

from tests import helpers
from tests.helpers import argv
from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import Chirp
from twinfocus.sensors.emulators.mmwcas_capture import write_mmwcas_capture
from twinfocus.sensors.frames import FrameFlag, frame_to_virtual_channels
from twinfocus.sensors.ti_mmwcas import MmwcasCapture, MmwcasConfig, read_studio_json, resolve_config

# Nine TX in TI numbering (1..12), in chirp order; TI's cascade numbers device d's TX b as 3 d + b + 1.
TX9 = [11, 3, 9, 1, 5, 12, 7, 2, 10]
N = 8


def studio_json(path, tx_numbers, n_loops=1, period_ms=33.333, n_samples=N):
    """An mmWave Studio JSON: per device, one rlChirpCfg_t per chirp."""
    helpers.studio_json(path, {"numAdcSamples": n_samples}, tx_numbers, n_loops, period_ms)


def _nine_tx_capture(folder, frames=4):
    tx = tuple(12 - n for n in TX9)
    cfg = MmwcasConfig(chirp=Chirp(n_samples=N), n_chirps=9, tx_of_chirp=tx, frame_period_s=0.033333)
    rng = np.random.default_rng(3)
    iq = rng.integers(-3000, 3000, size=(frames, 12, 16, N, 2), dtype=np.int16)
    fired = np.zeros(12, bool)
    fired[list(tx)] = True
    iq[:, ~fired] = 0  # TX that no chirp fires hold nothing
    ts = 1_000_000_000 + np.arange(frames) * 33_333_000
    write_mmwcas_capture(folder, iq, ts, cfg)
    return iq


def test_studio_json_gives_the_nine_tx_layout(tmp_path):
    studio_json(tmp_path / "cap.mmwave.json", TX9)
    got = read_studio_json(tmp_path / "cap.mmwave.json")
    assert got["tx_numbers"] == tuple(TX9) and got["n_loops"] == 1 and got["n_samples"] == N
    assert got["frame_period_s"] == pytest.approx(0.033333)


def test_nine_tx_capture_converts_with_its_layout_from_the_json(tmp_path, capsys):
    from twinfocus.cli import main
    from twinfocus.motion.trajectory import Poses
    from twinfocus.radar.scan import Scan
    from twinfocus.sensors.trajectory_files import write_tum

    iq = _nine_tx_capture(tmp_path / "cap")
    t = 10**18 + np.arange(9) * 20_000_000
    write_tum(
        tmp_path / "traj.txt",
        Poses(t, np.stack([np.arange(9) * 1e-3, np.zeros(9), np.zeros(9)], 1), np.tile([0.0, 0, 0, 1], (9, 1))),
    )
    args = argv("convert", tmp_path / "cap", "--trajectory", tmp_path / "traj.txt", "--out", tmp_path / "s.npz")
    args += argv("--n-samples", N, "--quiet")
    # Without the configuration the default 12-TX layout does not fit the frames.
    assert main(args) == 2 and "check n_samples, n_chirps and n_loops" in capsys.readouterr().err
    studio_json(tmp_path / "cap" / "cap.mmwave.json", TX9)
    assert main(args) == 0
    capsys.readouterr()
    scan = Scan.load(tmp_path / "s.npz")
    chirp = Chirp(n_samples=N)
    for m in range(4):
        frame = iq[m, ..., 0] + 1j * iq[m, ..., 1]
        np.testing.assert_allclose(scan.data[m], frame_to_virtual_channels(frame, chirp, 0.6), rtol=1e-6)
    # The same as an option, with no JSON.
    (tmp_path / "cap" / "cap.mmwave.json").unlink()
    assert main(args + ["--tx-order", ",".join(map(str, TX9)), "--out", str(tmp_path / "o.npz")]) == 0
    np.testing.assert_array_equal(Scan.load(tmp_path / "o.npz").data, scan.data)


@pytest.mark.parametrize("period_s", [0.1, 0.033333])
def test_slave_one_frame_late_is_flagged_at_any_period(tmp_path, period_s):
    frames = 6
    period_ns = int(round(period_s * 1e6)) * 1000
    iq = np.zeros((frames, 12, 16, 4, 2), np.int16)
    skew = np.zeros((frames, 4), np.int64)
    skew[3, 1] = period_ns  # slave1 wrote frame 3 one frame late
    cfg = MmwcasConfig(chirp=Chirp(n_samples=4), frame_period_s=period_s)
    write_mmwcas_capture(tmp_path, iq, 10**9 + np.arange(frames) * period_ns, cfg, device_skew_ns=skew)
    # Read with the default nominal period (0.1 s): the measured period decides.
    with MmwcasCapture(tmp_path, MmwcasConfig(chirp=Chirp(n_samples=4))) as cap:
        assert [bool(f & FrameFlag.DEVICE_SKEW) for f in cap.flags] == [False, False, False, True, False, False]


def test_timestamps_in_ns_are_named(tmp_path):
    cfg_ns = MmwcasConfig(chirp=Chirp(n_samples=4), timestamp_unit_ns=1)
    write_mmwcas_capture(tmp_path, np.zeros((5, 12, 16, 4, 2), np.int16), 10**9 + np.arange(5) * 100_000_000, cfg_ns)
    with pytest.raises(TwinFocusError, match=r"the stamps are in ns \(--timestamp-unit-ns 1\)"):
        MmwcasCapture(tmp_path, MmwcasConfig(chirp=Chirp(n_samples=4)))
    with MmwcasCapture(tmp_path, cfg_ns) as cap:
        np.testing.assert_array_equal(np.diff(cap.timestamps_ns), 100_000_000)


def test_first_frame_of_each_slice(tmp_path):
    cfg = MmwcasConfig(chirp=Chirp(n_samples=4))
    iq = (np.arange(6)[:, None, None, None, None] * np.ones((6, 12, 16, 4, 2))).astype(np.int16)
    ts = 10**9 + np.arange(6) * 100_000_000
    write_mmwcas_capture(tmp_path, iq[:3], ts[:3], cfg, slice_index=0)  # with the card's bad first frame
    write_mmwcas_capture(tmp_path, iq[3:], ts[3:], cfg, slice_index=1, bad_first_frame=False)
    with MmwcasCapture(tmp_path, cfg) as cap:
        assert [int(cap.read_frame(i)[0, 0, 0, 0].real) for i in range(len(cap))] == [0, 1, 2, 3, 4, 5]
    with MmwcasCapture(tmp_path, cfg, skip_first_frame_of_each_slice=True) as cap:
        assert [int(cap.read_frame(i)[0, 0, 0, 0].real) for i in range(len(cap))] == [0, 1, 2, 4, 5]


def cascade_lua(path, tx_numbers, loops=1, period_ms=33.333, n_samples=N):
    """A setup script in the form of TI's cascade Lua: Configure_Chirps(i) with one if-block per
    device, a comment table that must be ignored, and the frame variables."""
    lines = [
        "--[[ chirp | TX1 TX2 ... (TI's table)",
        "|  0 | 1 | 0 |",
        "--]]",
        f"nchirp_loops = {loops}",
        f"Inter_Frame_Interval = {period_ms} -- ms",
        "start_chirp_tx = 0",
        f"end_chirp_tx = {len(tx_numbers) - 1}",
        f"adc_samples = {n_samples}",
        "function Configure_Chirps(i)",
    ]
    for d in range(4):
        lines.append(f"    {'if' if d == 0 else 'elseif'} (i == {d + 1}) then")
        for c, n in enumerate(tx_numbers):
            en = ["1" if (n - 1) // 3 == d and (n - 1) % 3 == b else "0" for b in range(3)]
            lines.append(
                f"        if (0 == ar1.ChirpConfig_mult(dev_list[i], {c}, {c}, 0, 0, 0, 0, 0, {', '.join(en)})) then"
            )
            lines.append(
                f'            WriteToLog("Device "..i.." : Chirp {c} Configuration successful\\n", "green") end'
            )
    lines += ["    end", "end"]
    path.write_text("\n".join(lines) + "\n")


def test_nine_tx_capture_layout_from_the_cascade_lua(tmp_path, capsys):
    from twinfocus.sensors.ti_mmwcas import read_cascade_lua

    cascade_lua(tmp_path / "Cascade_Configuration_MIMO.lua", TX9)
    got = read_cascade_lua(tmp_path / "Cascade_Configuration_MIMO.lua")
    assert got["tx_numbers"] == tuple(TX9) and got["n_loops"] == 1 and got["n_samples"] == N
    assert got["frame_period_s"] == pytest.approx(0.033333)
    iq = _nine_tx_capture(tmp_path / "cap")
    (tmp_path / "Cascade_Configuration_MIMO.lua").rename(tmp_path / "cap" / "setup.lua")
    config, notes = resolve_config(tmp_path / "cap", Chirp(n_samples=N))
    assert config.tx_of_chirp == tuple(12 - n for n in TX9) and "setup.lua" in notes[0]
    with MmwcasCapture(tmp_path / "cap", config) as cap:
        for m in range(4):
            np.testing.assert_array_equal(cap.read_frame(m)[0], iq[m, ..., 0] + 1j * iq[m, ..., 1])
