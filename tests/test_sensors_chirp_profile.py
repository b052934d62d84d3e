"""The capture's own chirp: TI's chirp profile (mmWave Studio JSON, Lua scripts, SDK .cfg) becomes
the scan's chirp, options override it with a note, and a capture taken with a non-default profile
images as the same scene simulated with that profile."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests import helpers
from tests.helpers import convert_capture
from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import Chirp, range_compress
from twinfocus.sensors.chirp_profile import profile_fields_from_lua, resolve_chirp
from twinfocus.sensors.ti_mmwcas import read_cascade_lua, read_studio_json, resolve_config

# A non-default profile in TI's units: 77 GHz start, 60 MHz/us, 6 us ADC start, 128 samples at
# 5 Msps (1.536 GHz sampled), idle 7 us, ramp end 35 us (the sampling ends at 31.6 us).
PROFILE = {
    "startFreqConst_GHz": 77.0,
    "idleTimeConst_usec": 7.0,
    "adcStartTimeConst_usec": 6.0,
    "rampEndTime_usec": 35.0,
    "freqSlopeConst_MHz_usec": 60.0,
    "numAdcSamples": 128,
    "digOutSampleRate": 5000.0,
}
TRUE_CHIRP = Chirp(f0_hz=77e9 + 60e12 * 6e-6, slope_hz_per_s=60e12, fs_hz=5e6, n_samples=128)


def studio_json(path, profile=PROFILE, tx_numbers=tuple(range(12, 0, -1)), period_ms=100.0):
    """An mmWave Studio JSON, every device with the same profile, one TX per chirp."""
    fixed = {"pfVcoSelect": "0x0", "txOutPowerBackoffCode": "0x0", "txPhaseShifter": "0x0", "txStartTime_usec": 0.0}
    helpers.studio_json(path, {**fixed, "rxGain_dB": "0x30", **profile}, tx_numbers, 1, period_ms)


CASCADE_LUA = """
-- Profile configuration
local profile_indx              =   0
local start_freq                =   77     -- GHz
local slope                     =   60     -- MHz/us
local idle_time                 =   7      -- us
local adc_start_time            =   6      -- us
local adc_samples               =   128    -- Number of samples per chirp
local sample_freq               =   5000   -- ksps
local ramp_end_time             =   35     -- us
local rx_gain                   =   48     -- dB
local nchirp_loops              =   1
local Inter_Frame_Interval      =   100    -- ms
-- ar1.ProfileConfig_mult(deviceMapOverall, 0, 76, 5, 5, 40, 0, 0, 0, 0, 0, 0, 120, 0, 256, 8000, 0, 0, 30)
if (0 == ar1.ProfileConfig_mult(deviceMapOverall, 0, start_freq, idle_time, adc_start_time, ramp_end_time,
                                0, 0, 0, 0, 0, 0, slope, 0, adc_samples, sample_freq, 0, 0, rx_gain)) then
    WriteToLog("Profile Configuration successful\\n", "green")
end
"""


def test_studio_json_profile_is_the_chirp(tmp_path):
    studio_json(tmp_path / "c.mmwave.json")
    got = read_studio_json(tmp_path / "c.mmwave.json")
    assert got["profile"]["start_freq_ghz"] == 77.0 and got["profile"]["ramp_end_time_us"] == 35.0
    chirp, profile, notes = resolve_chirp(got["profile"], "c.mmwave.json")
    assert chirp == TRUE_CHIRP and notes == [] and profile.idle_time_us == 7.0
    # first sample 77.36 GHz; 1.536 GHz sampled; centre 77.36 + 0.768 GHz
    assert chirp.f0_hz == pytest.approx(77.36e9) and chirp.bandwidth_hz == pytest.approx(1.536e9)
    # An option wins over the configuration, with a note naming both values.
    chirp, _, notes = resolve_chirp(got["profile"], "c.mmwave.json", slope_hz_per_s=59e12)
    assert chirp.slope_hz_per_s == 59e12 and chirp.f0_hz == TRUE_CHIRP.f0_hz
    assert notes == ["--slope-hz-per-s 5.9e+13 overrides the capture configuration's 6e+13 (c.mmwave.json)"]
    # An option equal to the configuration's value says nothing.
    assert resolve_chirp(got["profile"], "c.mmwave.json", fs_hz=5e6)[2] == []


def test_lua_profile_both_forms(tmp_path):
    (tmp_path / "Cascade_Configuration_MIMO.lua").write_text(CASCADE_LUA)
    got = read_cascade_lua(tmp_path / "Cascade_Configuration_MIMO.lua")
    assert resolve_chirp(got["profile"], "lua")[0] == TRUE_CHIRP and got["n_samples"] == 128
    # The single-chip form with literal arguments.
    fields = profile_fields_from_lua(
        "ar1.ProfileConfig(0, 77, 7, 6, 35, 0, 0, 0, 0, 0, 0, 60, 0, 128, 5000, 0, 0, 30)", "s"
    )
    assert resolve_chirp(fields, "s")[0] == TRUE_CHIRP
    with pytest.raises(TwinFocusError, match="has 17 profile arguments"):
        profile_fields_from_lua("ar1.ProfileConfig(0, 77, 7, 6, 35, 0, 0, 0, 0, 0, 60, 0, 128, 5000, 0, 0, 30)", "s")
    with pytest.raises(TwinFocusError, match="'slope2' .* neither a number nor a variable"):
        profile_fields_from_lua(
            "ar1.ProfileConfig(0, 77, 7, 6, 35, 0, 0, 0, 0, 0, 0, slope2, 0, 128, 5000, 0, 0, 30)", "s"
        )


def test_profile_sampling_past_the_ramp_is_refused(tmp_path):
    studio_json(tmp_path / "c.mmwave.json", {**PROFILE, "rampEndTime_usec": 30.0})
    with pytest.raises(TwinFocusError, match=r"ADC samples until 31.6 us .* ramp ends at 30 us"):
        resolve_config(tmp_path, setup=tmp_path / "c.mmwave.json")


def test_sdk_cfg_profile_and_its_override():
    from twinfocus.sensors.emulators.rig import EMULATED_CFG
    from twinfocus.sensors.ti_cli import RadarCliConfig

    cfg = RadarCliConfig.from_cfg(EMULATED_CFG)
    chirp, profile, notes = resolve_chirp(cfg.profile().to_dict(), "radar.cfg", f0_hz=77e9)
    assert chirp.f0_hz == 77e9 and chirp.slope_hz_per_s == cfg.chirp().slope_hz_per_s and len(notes) == 1


def _scene_capture(tmp_path, frames=9):
    """A point scatterer seen by the cascade along a 4 cm sweep with TRUE_CHIRP, written as a
    TI capture (bistatic TX-RX paths, int16 I/Q), and its camera trajectory (aperture frame = world)."""
    from twinfocus.motion.trajectory import Poses
    from twinfocus.sensors.emulators.mmwcas_capture import write_mmwcas_capture
    from twinfocus.sensors.emulators.radar_scene import quantize_iq, simulate_mimo_frames
    from twinfocus.sensors.ti_mmwcas import MmwcasConfig
    from twinfocus.sensors.trajectory_files import write_tum

    target = np.array([[0.006, 0.004, 0.6]])
    y = np.linspace(-0.02, 0.02, frames)
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (frames, 1))
    t = 10**18 + np.arange(frames) * 100_000_000
    poses = Poses(t, np.stack([np.zeros(frames), y, np.zeros(frames)], axis=1), quat)
    iq = quantize_iq(simulate_mimo_frames(TRUE_CHIRP, poses, target))
    write_mmwcas_capture(
        tmp_path / "cap", iq, 5 * 10**9 + np.arange(frames) * 100_000_000, MmwcasConfig(chirp=TRUE_CHIRP)
    )
    write_tum(tmp_path / "traj.txt", poses)
    return target


def _image(data, positions, chirp, target):
    from twinfocus.imaging.backprojection.numba_backend import backproject
    from twinfocus.imaging.grid import ImageGrid

    grid = ImageGrid(-0.03, 0.04, -0.03, 0.04, float(target[0, 2]), 24, 24)
    return backproject(data, positions, chirp, grid)


def _ncc(a, b) -> float:
    return float(abs(np.vdot(a, b)) / (np.linalg.norm(a) * np.linalg.norm(b)))


def test_capture_with_its_profile_converts_and_images_as_that_profile(tmp_path, capsys):
    from twinfocus.cli import main
    from twinfocus.radar.scan import Scan
    from twinfocus.sensors.emulators.radar_scene import monostatic_if
    from twinfocus.simulation.if_simulator import simulate_if

    target = _scene_capture(tmp_path)
    args = ["convert", str(tmp_path / "cap"), "--trajectory", str(tmp_path / "traj.txt"), "--z0", "0.6", "--quiet"]
    # Without the configuration the frames are read with the default chirp (and the JSON's 128
    # samples given by hand): ranges and phases come out wrong.
    assert main(args + ["--out", str(tmp_path / "default.npz"), "--n-samples", "128"]) == 0
    studio_json(tmp_path / "cap" / "capture.mmwave.json")
    assert main(args + ["--out", str(tmp_path / "own.npz")]) == 0
    capsys.readouterr()
    own, default = Scan.load(tmp_path / "own.npz"), Scan.load(tmp_path / "default.npz")
    assert own.chirp == TRUE_CHIRP and default.chirp == Chirp(n_samples=128)
    record = json.loads((tmp_path / "own.capture.json").read_text())["chirp"]
    assert record["f0_hz"] == TRUE_CHIRP.f0_hz and record["profile"]["ramp_end_time_us"] == 35.0
    assert record["source"].endswith("capture.mmwave.json")

    # Range: each channel's profile peaks in the bin of its true range (8x zero padding).
    r_true = np.linalg.norm(own.positions - target[0], axis=-1)  # (M, K)
    for scan, right in ((own, True), (default, False)):
        prof = np.abs(range_compress(scan.data, scan.chirp, n_fft=8 * scan.chirp.n_samples))
        axis = scan.chirp.range_axis_m(8 * scan.chirp.n_samples)
        err = np.abs(axis[prof.argmax(axis=-1)] - r_true)
        bin_m = axis[1]
        # read with the default chirp a range R shows at R x (60/120) x (8/5): 12 cm short at 0.6 m
        assert (err.max() <= bin_m) if right else (np.median(err) > 4 * bin_m)
    # Phase: the channels equal the monostatic model of the scene with the profile's chirp.
    truth = monostatic_if(TRUE_CHIRP, own.positions, target)
    phase_err = np.angle(own.data * np.conj(truth))
    assert np.abs(phase_err).max() < 0.05  # rad: the near-field correction's residual at z0
    # Image: the same as the scene re-simulated with the profile at the scan's phase centres.
    resim = simulate_if(target, None, own.positions, TRUE_CHIRP)
    ref = _image(resim, own.positions, TRUE_CHIRP, target)
    img_own = _image(own.data, own.positions, own.chirp, target)
    img_default = _image(default.data, default.positions, default.chirp, target)
    assert _ncc(img_own, ref) > 0.99
    assert np.unravel_index(np.abs(img_own).argmax(), ref.shape) == np.unravel_index(np.abs(ref).argmax(), ref.shape)

    # Focusing gain (peak over the data's rms, relative to the re-simulated scene's): whole with
    # the capture's own chirp; read with the default chirp, the point is out of focus in range.
    def gain(img, data):
        return float(np.abs(img).max() / np.sqrt(np.mean(np.abs(data) ** 2)))

    g_ref = gain(ref, resim)
    assert gain(img_own, own.data) / g_ref > 0.97
    assert gain(img_default, default.data) / g_ref < 0.3


def test_convert_option_overrides_the_capture_profile_with_a_note(tmp_path, capsys):
    from twinfocus.radar.scan import Scan

    _scene_capture(tmp_path, frames=3)
    studio_json(tmp_path / "cap" / "capture.mmwave.json")
    rc = convert_capture(tmp_path, "--f0-hz 77e9")
    err = capsys.readouterr().err
    assert rc == 0 and "--f0-hz 7.7e+10 overrides the capture configuration's 7.736e+10" in err
    assert Scan.load(tmp_path / "s.npz").chirp == Chirp(77e9, 60e12, 5e6, 128)


def test_live_mmwcas_backend_takes_the_capture_profile(tmp_path, capfd):
    from nodes.runtime.backends import RADAR_BACKENDS, load_backend

    _scene_capture(tmp_path, frames=3)
    studio_json(tmp_path / "cap" / "capture.mmwave.json")
    cls = load_backend(RADAR_BACKENDS, "mmwcas", "radar")
    b = cls({"capture": str(tmp_path / "cap")})
    b.close()
    assert b.chirp == TRUE_CHIRP
    b = cls({"capture": str(tmp_path / "cap"), "fs_hz": 5.5e6})
    b.close()
    assert b.chirp == Chirp(TRUE_CHIRP.f0_hz, 60e12, 5.5e6, 128)
    assert "--fs-hz 5.5e+06 overrides the capture configuration's 5e+06" in capfd.readouterr().err
