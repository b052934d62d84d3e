"""Channel calibration from a corner reflector: the estimates against the errors injected into an
emulated MMWCAS array, `calibrate` and `convert --calibration` end to end on TI-format captures,
and the bad inputs refused in one line with nothing written."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.backprojection.numba_backend import backproject
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.metrics import image_ssim
from twinfocus.io.checksums import file_sha256
from twinfocus.motion.trajectory import Poses, paper_raster
from twinfocus.radar.array_errors import NONE, TYPICAL, draw_array_errors
from twinfocus.radar.calibration import (
    ChannelCalibration,
    channel_correction,
    find_corner,
    make_calibration,
    pair_array,
)
from twinfocus.radar.fmcw import C_M_PER_S, Chirp, mmwcas_virtual_array, uniform_virtual_array
from twinfocus.radar.scan import Scan
from twinfocus.sensors.emulators.mmwcas_capture import write_mmwcas_capture
from twinfocus.sensors.emulators.radar_scene import imperfect_mimo_frames, quantize_iq
from twinfocus.sensors.emulators.rig import demo_scatterers
from twinfocus.sensors.frames import frame_to_virtual_channels, mmwcas_antenna_positions_body_m
from twinfocus.sensors.ti_mmwcas import MmwcasConfig
from twinfocus.sensors.trajectory_files import write_tum

CHIRP = Chirp()


def _still(n: int) -> Poses:
    return Poses(np.arange(n, dtype=np.int64) * 100_000_000, np.zeros((n, 3)), np.tile([0.0, 0, 0, 1], (n, 1)))


def _capture(folder, poses: Poses, points, errors, snr_db=25.0, seed=0):
    """A TI-format MMWCAS capture of ``points`` through the array ``errors`` (+ its trajectory)."""
    frames = imperfect_mimo_frames(CHIRP, poses, np.asarray(points, float), errors, snr_db=snr_db, rng=seed)
    stamps = 123_456_789_000 + (poses.timestamps_ns - poses.timestamps_ns[0])
    write_mmwcas_capture(
        folder, quantize_iq(frames, headroom=0.9), stamps, MmwcasConfig(chirp=CHIRP, frame_period_s=0.1)
    )
    write_tum(folder / "trajectory.txt", poses)
    return folder


def _run(capsys, *argv):
    from twinfocus.cli import main

    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


# --- the estimate against the injected truth ----------------------------------------------------


def test_estimated_channel_errors_match_the_injected_ones():
    """Every one of the 192 TX-RX pairs: phase to a few degrees, amplitude to a few %, delay to a
    small fraction of a range bin, against the errors drawn into the emulated array."""
    errors = draw_array_errors(TYPICAL, 3)
    frames = imperfect_mimo_frames(CHIRP, _still(6), np.array([[0.0, 0.0, 0.6]]), errors, snr_db=20.0, rng=1)
    tx, rx = mmwcas_antenna_positions_body_m()
    pairs = pair_array(tx, rx)
    peak = find_corner(frame_to_virtual_channels(frames, CHIRP, 0.6, pairs), CHIRP, 0.6)
    data = frame_to_virtual_channels(frames, CHIRP, peak.range_m, pairs)
    cal, _ = make_calibration(data, pairs.offsets_m, CHIRP, peak, pairs, pairs, "test", origin_m=np.zeros(3))
    ref = cal.reference
    truth = errors.effective_pair_gain(CHIRP).ravel()
    truth_delay = errors.pair_delay_m().ravel()
    phase_err = np.degrees(np.angle(cal.gain * np.conj(truth * np.exp(-1j * np.angle(truth[ref])))))
    assert np.sqrt(np.mean(phase_err**2)) < 2.0 and np.abs(phase_err).max() < 5.0
    amp_truth = np.abs(truth) / np.sqrt(np.mean(np.abs(truth) ** 2))
    assert np.abs(np.abs(cal.gain) / amp_truth - 1).max() < 0.03
    delay_err = cal.delay_m - (truth_delay - truth_delay[ref])
    assert np.abs(delay_err).max() < 0.01 * CHIRP.range_resolution_m  # 0.4 mm of a 39 mm bin
    # The errors arise per TX and per RX: the factors explain the pairs.
    assert cal.quality["factorisation_residual_deg_rms"] < 2.0
    model_delay = cal.tx_delay_m[pairs.tx_index] + cal.rx_delay_m[pairs.rx_index]
    np.testing.assert_allclose(model_delay - model_delay[ref], truth_delay - truth_delay[ref], atol=0.3e-3)
    assert cal.quality["residual_phase_deg_rms"] < 3.0 and cal.quality["peak_sharpness"] > 0.99
    assert cal.quality["peak_sharpness_before"] < 0.6


def test_correction_undoes_a_channel_error_exactly():
    """The correction is the inverse of the error model G exp(+j 4 pi (f - fc) d / c)."""
    gain = np.array([0.5 * np.exp(1j * 2.0), 2.0 * np.exp(-1j * 0.3)])
    delay = np.array([3e-3, -5e-3])
    f = CHIRP.frequencies_hz - CHIRP.fc_hz
    err = gain[:, None] * np.exp(1j * 4 * np.pi * np.outer(delay, f) / C_M_PER_S)
    np.testing.assert_allclose(err * channel_correction(CHIRP, gain, delay), 1.0, atol=1e-5)


def test_perfect_array_draw_changes_nothing():
    errors = draw_array_errors(NONE, 5)
    clean = imperfect_mimo_frames(CHIRP, _still(1), np.array([[0.01, 0.0, 0.5]]), errors)
    from twinfocus.sensors.emulators.radar_scene import simulate_mimo_frames

    np.testing.assert_allclose(clean, simulate_mimo_frames(CHIRP, _still(1), np.array([[0.01, 0.0, 0.5]])), atol=1e-5)


# --- calibrate and convert, end to end on TI-format captures -------------------------------------


def _raster(rows: int) -> Poses:
    return paper_raster(3, rows, frame_period_s=0.05, t0_ns=1_700_000_000_000_000_000)


@pytest.fixture(scope="module")
def corner_and_scene(tmp_path_factory):
    """A corner capture and a short scene capture (6 frames) through one imperfect array: what
    the quick tests read. They check the channels and the refusals, not an image: the scene's
    120 frames (5 s to emulate) are made by ``captures``, for the tests that focus it."""
    root = tmp_path_factory.mktemp("calibration")
    errors = draw_array_errors(TYPICAL, 11)
    return {
        "root": root,
        "errors": errors,
        "corner": _capture(root / "corner", _still(8), [[0.0, 0.0, 0.6]], errors, seed=1),
        "scene": _capture(root / "short_scene", _raster(2), demo_scatterers(0.6), errors, seed=2),
    }


@pytest.fixture(scope="module")
def captures(corner_and_scene):
    """The corner capture, the scene on a 3 x 40 raster through the imperfect array and the
    same scene (same trajectory) through a perfect array, and the reference alone on the motion
    stage through both."""
    c = corner_and_scene
    root, errors, traj, pts = c["root"], c["errors"], _raster(40), demo_scatterers(0.6)
    return {
        **c,
        "traj": traj,
        "scene": _capture(root / "scene", traj, pts, errors, seed=2),
        "perfect": _capture(root / "perfect", traj, pts, draw_array_errors(NONE), seed=2),
        # The reference (the 'T') alone on the motion stage: the physical twin's capture.
        "stage": _capture(root / "stage", traj, pts[:11], errors, seed=3),
        "stage_perfect": _capture(root / "stage_perfect", traj, pts[:11], draw_array_errors(NONE), seed=3),
    }


@pytest.fixture(scope="module")
def good_calibration(corner_and_scene) -> Path:
    """The corner capture's calibration, made once by `twinfocus calibrate` (the file's path)."""
    from twinfocus.cli import main

    out = corner_and_scene["root"] / "good.npz"
    assert main(["calibrate", str(corner_and_scene["corner"]), "--range-m", "0.6", "--out", str(out), "--quiet"]) == 0
    return out


def _image(scan_path) -> np.ndarray:
    s = Scan.load(scan_path)
    grid = ImageGrid.from_roi((-0.1, 0.12, -0.06, 0.06, 0.6), (48, 88))
    return np.abs(backproject(s.data, s.positions, s.chirp, grid))


@pytest.mark.slow  # 56 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_calibrate_then_convert_images_like_the_perfect_array(captures, tmp_path, capsys):
    cap = captures
    cal = tmp_path / "cal.npz"
    rc, out, err = _run(capsys, "calibrate", cap["corner"], "--range-m", 0.6, "--out", cal, "--quiet")
    assert rc == 0, err
    quality = json.loads(out)
    assert quality["residual_phase_deg_rms"] < 5 and quality["peak_sharpness"] > 0.98
    assert abs(quality["corner_range_m"] - 0.6) < 0.01 and (tmp_path / "cal.png").stat().st_size > 10_000
    assert ChannelCalibration.load(cal).quality["residual_phase_deg_rms"] == quality["residual_phase_deg_rms"]

    def convert(capture, name, *extra):
        rc, _, err = _run(
            capsys,
            "convert",
            capture,
            "--trajectory",
            capture / "trajectory.txt",
            "--out",
            tmp_path / name,
            "--quiet",
            *extra,
        )
        assert rc == 0, err
        return err

    warned = convert(cap["scene"], "raw.npz")
    assert "warning: no --calibration" in warned and len(warned.strip().splitlines()) == 1
    assert "warning" not in convert(cap["scene"], "calibrated.npz", "--calibration", cal)
    convert(cap["perfect"], "perfect.npz")
    perfect = _image(tmp_path / "perfect.npz")
    calibrated = image_ssim(_image(tmp_path / "calibrated.npz"), perfect)
    raw = image_ssim(_image(tmp_path / "raw.npz"), perfect)
    assert calibrated > 0.98 and raw < 0.85, (calibrated, raw)
    record = json.loads(Scan.load(tmp_path / "calibrated.npz").calibration)
    assert record["file"] == "cal.npz" and record["sha256"] == file_sha256(cal)
    assert json.loads((tmp_path / "calibrated.capture.json").read_text())["calibration"] == record
    assert Scan.load(tmp_path / "raw.npz").calibration is None
    assert json.loads((tmp_path / "raw.capture.json").read_text())["calibration"] is None


# --- bad inputs: one line, exit 2, nothing written ------------------------------------------------


def _refused(rc, err, written, *phrases):
    lines = [ln for ln in err.strip().splitlines() if "error" in ln]
    assert rc == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert all(p in lines[0] for p in phrases), lines[0]
    assert not any(p.exists() for p in written), [p for p in written if p.exists()]


def test_no_bright_point_near_the_range_is_refused(corner_and_scene, tmp_path, capsys):
    out = tmp_path / "cal.npz"
    rc, _, err = _run(capsys, "calibrate", corner_and_scene["corner"], "--range-m", 2.0, "--out", out, "--quiet")
    _refused(rc, err, [out, tmp_path / "cal.png"], "no bright point near 2 m")


def test_two_corners_are_refused(tmp_path, capsys):
    cap = _capture(tmp_path / "two", _still(4), [[0.0, 0.0, 0.6], [0.02, 0.0, 0.75]], draw_array_errors(TYPICAL, 4))
    out = tmp_path / "cal.npz"
    rc, _, err = _run(capsys, "calibrate", cap, "--range-m", 0.65, "--out", out, "--quiet")
    _refused(rc, err, [out, tmp_path / "cal.png"], "two bright points")


@pytest.mark.parametrize(
    "edit, phrase",
    [
        ("array", "another array"),
        ("channels", "48 channels"),
        ("chirp", "another chirp (slope_hz_per_s"),
        # same channel count and layout, another board's name: convert passes the capture's board
        ("board", "was made on board 'another board'"),
    ],
)
def test_calibration_of_another_array_or_chirp_is_refused(
    corner_and_scene, good_calibration, tmp_path, capsys, edit, phrase
):
    cal = ChannelCalibration.load(good_calibration)
    if edit == "array":
        other = uniform_virtual_array(86, 1e-3)
        cal = replace(
            cal, array_fingerprint=__import__("twinfocus.radar.calibration").radar.calibration.array_fingerprint(other)
        )
    elif edit == "channels":
        cal = replace(cal, gain=cal.gain[:48], delay_m=cal.delay_m[:48])
    elif edit == "board":
        cal = replace(cal, board="another board")
    else:
        cal = replace(cal, chirp=Chirp(slope_hz_per_s=100e12))
    cal.save(tmp_path / "other.npz")
    scene = corner_and_scene["scene"]
    out = tmp_path / "scan.npz"
    rc, _, err = _run(
        capsys,
        "convert",
        scene,
        "--trajectory",
        scene / "trajectory.txt",
        "--out",
        out,
        "--calibration",
        tmp_path / "other.npz",
        "--quiet",
    )
    _refused(rc, err, [out, tmp_path / "scan.capture.json"], phrase)


def test_a_file_that_is_not_a_calibration_is_refused(tmp_path):
    np.savez(tmp_path / "x.npz", data=np.zeros(3))
    with pytest.raises(TwinFocusError, match="not a channel calibration file"):
        ChannelCalibration.load(tmp_path / "x.npz")


def test_calibrate_a_scan_file_of_the_corner(tmp_path, capsys):
    """The scan form of CAPTURE: a converted still capture of the corner (86 channels)."""
    errors = draw_array_errors(TYPICAL, 8)
    array = mmwcas_virtual_array()
    frames = imperfect_mimo_frames(CHIRP, _still(4), np.array([[0.0, 0.0, 0.6]]), errors, snr_db=25.0)
    data = frame_to_virtual_channels(frames, CHIRP, 0.6, array)
    pos = np.broadcast_to(array.offsets_m, (4, 86, 3)).copy()
    Scan(data, pos, CHIRP).save(tmp_path / "corner.npz")
    rc, out, err = _run(
        capsys, "calibrate", tmp_path / "corner.npz", "--range-m", 0.6, "--out", tmp_path / "c.npz", "--quiet"
    )
    assert rc == 0, err
    q = json.loads(out)
    assert q["channels_measured"] == 86 and q["residual_phase_deg_rms"] < 5 and q["peak_sharpness"] > 0.98


# --- focusing with autofocus: calibrated at the perfect array's level ----------------------------


@pytest.mark.slow
def test_autofocused_target_through_calibrated_array_matches_perfect_array():
    from twinfocus.evaluation.array_calibration import calibration_case

    r = calibration_case(seed=1, n_columns=2, n_rows=40, size=48)
    assert abs(r["calibrated"] - r["perfect"]) < 0.02, r
    assert r["uncalibrated"] < r["perfect"] - 0.2, r


# --- the simulator's imperfect array ---------------------------------------------------------------


def test_beam_pattern_follows_cos_power_and_fast_simulator_agrees():
    from twinfocus.simulation.if_simulator import simulate_if, simulate_if_exact

    q = TYPICAL.pattern_exponent
    assert np.cos(np.radians(30)) ** q == pytest.approx(0.5)  # half power 30 degrees off boresight
    pos = np.zeros((1, 1, 3))
    on, off = np.array([[0.0, 0.0, 0.6]]), np.array([[0.6 * np.tan(np.radians(40)), 0.0, 0.6]])
    ratio = (
        np.abs(simulate_if_exact(off, None, pos, CHIRP, pattern_exponent=q)).mean()
        / np.abs(simulate_if_exact(on, None, pos, CHIRP, pattern_exponent=q)).mean()
    )
    assert ratio == pytest.approx(np.cos(np.radians(40)) ** q, rel=1e-4)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-0.3, 0.3, 50), rng.uniform(-0.2, 0.2, 50), rng.uniform(0.5, 0.7, 50)])
    centres = np.stack(np.meshgrid(np.linspace(-0.1, 0.1, 4), np.linspace(-0.05, 0.05, 3), [0.0]), -1).reshape(3, 4, 3)
    exact = simulate_if_exact(pts, None, centres, CHIRP, pattern_exponent=q)
    fast = simulate_if(pts, None, centres, CHIRP, pattern_exponent=q)
    assert np.linalg.norm(fast - exact) / np.linalg.norm(exact) < 1e-3
    assert np.linalg.norm(exact - simulate_if_exact(pts, None, centres, CHIRP)) > 0.1 * np.linalg.norm(exact)


def test_iq_imbalance_makes_the_closed_form_image_tone():
    """Q' = g (sin psi I + cos psi Q) turns a tone into mu tone + nu conj(tone)."""
    from twinfocus.radar.array_errors import iq_imbalance

    g, psi = 10 ** (1 / 20), np.radians(2.0)
    tone = np.exp(1j * 0.3 * np.arange(64))[None]
    mu, nu = (1 + g * np.exp(1j * psi)) / 2, (1 - g * np.exp(-1j * psi)) / 2
    np.testing.assert_allclose(iq_imbalance(tone, [g], [psi]), mu * tone + nu * np.conj(tone), atol=1e-6)


@pytest.mark.slow  # 3 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_simulate_array_errors_switch(tmp_path, capsys):
    """--array-errors typical changes the data, not the scene's draws; none is the perfect array;
    a knob alone adds only its effect (leakage: a tone at the antennas' separation, near zero range)."""
    common = ["simulate", "--columns", "1", "--rows", "3", "--snr-db", "inf", "--quiet"]
    scans = {}
    for name, extra in {
        "perfect": [],
        "typical": ["--array-errors", "typical"],
        "leak": ["--leakage-db", "10"],
    }.items():
        rc, _, err = _run(
            capsys, *common, "--out", tmp_path / f"{name}.npz", "--template-out", tmp_path / f"t{name}.npz", *extra
        )
        assert rc == 0, err
        scans[name] = Scan.load(tmp_path / f"{name}.npz")
    p, t, leak = scans["perfect"], scans["typical"], scans["leak"]
    np.testing.assert_array_equal(p.positions, t.positions)
    assert np.linalg.norm(t.data - p.data) > 0.5 * np.linalg.norm(p.data)
    from twinfocus.radar.fmcw import range_compress

    extra = np.abs(range_compress(leak.data - p.data, CHIRP, window="hann")).mean(axis=(0, 1))
    assert CHIRP.range_axis_m()[np.argmax(extra)] < 0.15
    rc, _, err = _run(capsys, *common, "--out", tmp_path / "x.npz", "--beamwidth-deg", "200")
    _refused(rc, err, [tmp_path / "x.npz"], "beamwidth_deg")


def test_live_radar_backend_applies_the_calibration(corner_and_scene, good_calibration, tmp_path, capsys):
    """The radar driver's ``calibration`` option gives the channels `convert --calibration` gives;
    one of another chirp is refused; none warns."""
    from nodes.runtime.backends import RADAR_BACKENDS, load_backend

    captures = corner_and_scene
    cal = ChannelCalibration.load(good_calibration)
    cls = load_backend(RADAR_BACKENDS, "mmwcas", "radar")
    b = cls({"capture": str(captures["scene"]), "calibration": str(good_calibration)})
    try:
        first = next(iter(b.samples()))
        raw = b.capture.read_frame(b.frames[0])[0]
    finally:
        b.close()
    expected = frame_to_virtual_channels(raw, CHIRP, 0.6) * cal.correction()
    np.testing.assert_allclose(first.data, expected, rtol=1e-5, atol=1e-3)
    replace(cal, chirp=Chirp(fs_hz=10e6)).save(tmp_path / "other.npz")
    with pytest.raises(TwinFocusError, match="another chirp"):
        cls({"capture": str(captures["scene"]), "calibration": str(tmp_path / "other.npz")})
    capsys.readouterr()
    cls({"capture": str(captures["scene"])}).close()
    assert "warning: no 'calibration'" in capsys.readouterr().err


@pytest.mark.slow
def test_captured_scene_calibrated_focuses_like_the_perfect_array(captures, tmp_path, capsys):
    """TI-format captures end to end, autofocus on, the same tracking errors: a scene through an
    imperfect array, converted with the calibration from a corner capture of that array, focuses
    to within 0.02 SSIM of the same scene through a perfect array; uncalibrated far below."""
    from twinfocus.focus.pipeline import Reference
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.twins.templates import template_from_scan

    cap, traj = captures, captures["traj"]
    tracked = Poses(
        traj.timestamps_ns,
        traj.position_m + np.random.default_rng(5).normal(0, 0.5e-3, traj.position_m.shape),
        traj.quat_xyzw,
    )
    write_tum(tmp_path / "tracked.txt", tracked)
    rc, _, err = _run(capsys, "calibrate", cap["corner"], "--range-m", 0.6, "--out", tmp_path / "c.npz", "--quiet")
    assert rc == 0, err

    def convert(capture, trajectory, *extra) -> Scan:
        # the emulated clocks agree: the scans compared differ by their array alone (the default
        # --align scan's focus stage put this point scene's clock 45-53 ms off, outside its two
        # sigma, with and without the calibration: docs/sensors_clock.md's known limits)
        out = tmp_path / f"s{len(list(tmp_path.glob('s*.npz')))}.npz"
        argv = ("convert", capture, "--trajectory", trajectory, "--out", out, "--align", "start", "--quiet", *extra)
        rc, _, err = _run(capsys, *argv)
        assert rc == 0, err
        return Scan.load(out)

    true_traj = cap["scene"] / "trajectory.txt"
    calib = ("--calibration", tmp_path / "c.npz")
    ref_grid = ImageGrid.from_roi((-0.09, 0.01, -0.05, 0.05, 0.6), 40)
    tgt_grid = ImageGrid.from_roi((0.03, 0.11, -0.05, 0.05, 0.6), 40)
    truth_scan = convert(cap["perfect"], true_traj)
    truth = backproject(truth_scan.data, truth_scan.positions, truth_scan.chirp, tgt_grid)
    variants = {
        "perfect": (convert(cap["perfect"], tmp_path / "tracked.txt"), convert(cap["stage_perfect"], true_traj)),
        "uncalibrated": (convert(cap["scene"], tmp_path / "tracked.txt"), convert(cap["stage"], true_traj)),
        "calibrated": (
            convert(cap["scene"], tmp_path / "tracked.txt", *calib),
            convert(cap["stage"], true_traj, *calib),
        ),
    }
    score = {}
    for name, (scan, stage) in variants.items():
        template = template_from_scan(stage, ref_grid, keep_phase=True)
        try:
            image = FocusPlan.make().focus_scan(scan, ref_grid, tgt_grid, Reference(template=template)).target
        except TwinFocusError:  # the smeared reference is not recognised: the user has the raw image
            image = backproject(scan.data, scan.positions, scan.chirp, tgt_grid)
        score[name] = image_ssim(image, truth)
    assert abs(score["calibrated"] - score["perfect"]) < 0.02, score
    assert score["uncalibrated"] < score["perfect"] - 0.2, score
