import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.focus.autofocus import AutofocusConfig, no_correction, sharpness_autofocus, twin_autofocus
from twinfocus.imaging.backprojection.numba_backend import backproject, subimage_basis
from twinfocus.imaging.basis import form_image
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.metrics import image_ssim, oracle_phase, phase_error_rms
from twinfocus.motion.tracking_errors import apply_position_errors, drift_errors, gaussian_errors
from twinfocus.motion.trajectory import paper_raster, phase_centres
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
from twinfocus.simulation.if_simulator import add_thermal_noise, simulate_if

Z = 0.4
REF_GRID = ImageGrid(-0.075, -0.025, -0.025, 0.025, Z, 32, 32)
TGT_GRID = ImageGrid(0.025, 0.075, -0.025, 0.025, Z, 32, 32)


def _shape_points(centre_x, kind, rng):
    """A small extended object: an 'L' (reference) or a 'T' (target), points 2 mm apart."""
    s = np.arange(-0.016, 0.0161, 0.002)
    if kind == "L":
        pts = [(centre_x - 0.016, y) for y in s] + [(centre_x + x, 0.016) for x in s]
    else:
        pts = [(centre_x + x, -0.016) for x in s] + [(centre_x, y) for y in s]
    pts = np.array([(x, y, Z) for x, y in pts])
    amps = np.exp(2j * np.pi * rng.random(len(pts)))
    return pts, amps


def _scenario(sigma_z_m, seed=0, snr_db=None, smooth=False):
    """Jitter (independent per position) or smooth hand drift (correlation time 1 s = 10
    positions). Independent jitter also holds phase components that move energy far outside a
    small region of interest, where no region-limited method can see them; smooth drift does not."""
    rng = np.random.default_rng(seed)
    poses = paper_raster(n_columns=2, n_rows=36, column_pitch_m=0.08, row_pitch_m=0.003)
    true = phase_centres(poses, mmwcas_virtual_array())
    if smooth:
        err = drift_errors(poses.timestamps_ns, (0, 0, sigma_z_m), correlation_time_s=1.0, rng=rng)
    else:
        err = gaussian_errors(true.shape[0], (0, 0, sigma_z_m), rng)
    tracked = apply_position_errors(true, err)
    rp, ra = _shape_points(-0.05, "L", rng)
    tp, ta = _shape_points(0.05, "T", rng)
    ch = Chirp()
    data = simulate_if(np.vstack([rp, tp]), np.concatenate([ra, ta]), true, ch)
    if snr_db is not None:
        data = add_thermal_noise(data, snr_db, rng)
    return ch, data, true, tracked


@pytest.fixture(scope="module")
def scene_05mm():
    ch, data, true, tracked = _scenario(0.5e-3, smooth=True)
    ref_basis = subimage_basis(data, tracked, ch, REF_GRID)
    tgt_basis = subimage_basis(data, tracked, ch, TGT_GRID)
    template = np.abs(backproject(data, true, ch, REF_GRID))
    truth = backproject(data, true, ch, TGT_GRID)
    return ch, true, tracked, ref_basis, tgt_basis, template, truth


@pytest.mark.slow
def test_twin_autofocus_recovers_injected_phase_and_focuses_target(scene_05mm):
    ch, true, tracked, ref_basis, tgt_basis, template, truth = scene_05mm
    result = twin_autofocus(ref_basis, template, AutofocusConfig(iterations=300))
    before = image_ssim(tgt_basis.sum(0), truth)
    after = image_ssim(form_image(tgt_basis, result.phase_rad), truth)
    assert after > before + 0.05
    assert after > 0.9
    oracle = oracle_phase(true, tracked, TGT_GRID.centre_m, ch)
    uncorrected = phase_error_rms(np.zeros_like(oracle), oracle)
    assert uncorrected > 1.2  # 0.5 mm in range is 1.6 rad
    # recovered = injected up to a constant, within 0.5 rad r.m.s.
    assert phase_error_rms(result.phase_rad, oracle) < min(0.5, 0.3 * uncorrected)
    assert result.loss_history[-1] < result.loss_history[0]


@pytest.mark.slow
def test_twin_autofocus_with_independent_jitter_focuses_target():
    ch, data, true, tracked = _scenario(0.5e-3, seed=1)
    ref_basis = subimage_basis(data, tracked, ch, REF_GRID)
    tgt_basis = subimage_basis(data, tracked, ch, TGT_GRID)
    truth = backproject(data, true, ch, TGT_GRID)
    result = twin_autofocus(ref_basis, np.abs(backproject(data, true, ch, REF_GRID)))
    assert image_ssim(form_image(tgt_basis, result.phase_rad), truth) > max(
        0.9, image_ssim(tgt_basis.sum(0), truth) + 0.1
    )
    oracle = oracle_phase(true, tracked, TGT_GRID.centre_m, ch)
    assert phase_error_rms(result.phase_rad, oracle) < 0.6 * phase_error_rms(np.zeros_like(oracle), oracle)


@pytest.mark.slow  # 24 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_float16_basis_gives_the_same_answer(scene_05mm):
    _, _, _, ref_basis, tgt_basis, template, truth = scene_05mm
    cfg32 = AutofocusConfig(iterations=100)
    cfg16 = AutofocusConfig(iterations=100, basis_dtype="float16")
    a = twin_autofocus(ref_basis, template, cfg32)
    b = twin_autofocus(ref_basis, template, cfg16)
    assert phase_error_rms(a.phase_rad, b.phase_rad) < 0.05
    assert (
        abs(
            image_ssim(form_image(tgt_basis, a.phase_rad), truth)
            - image_ssim(form_image(tgt_basis, b.phase_rad), truth)
        )
        < 0.01
    )


def test_smoothness_penalty_is_the_mean_squared_chord():
    import torch

    from twinfocus.focus.autofocus import smoothness_penalty

    rng = np.random.default_rng(2)
    phi = rng.uniform(-np.pi, np.pi, 50)
    want = np.mean(np.abs(np.exp(1j * phi[1:]) - np.exp(1j * phi[:-1])) ** 2)
    assert float(smoothness_penalty(torch.from_numpy(phi))) == pytest.approx(want, rel=1e-12)
    # wrap-safe: a full turn between neighbours costs nothing, a constant costs nothing
    assert float(smoothness_penalty(torch.tensor([0.0, 2 * np.pi, 4 * np.pi]))) == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(TwinFocusError, match="smoothness_weight"):
        AutofocusConfig(smoothness_weight=-1.0).validate()


@pytest.mark.slow
def test_smoothness_prior_smooths_the_estimate_of_a_smooth_drift(scene_05mm):
    import torch

    from twinfocus.focus.autofocus import smoothness_penalty

    ch, true, tracked, ref_basis, tgt_basis, template, truth = scene_05mm
    plain = twin_autofocus(ref_basis, template, AutofocusConfig(iterations=150))
    smooth = twin_autofocus(ref_basis, template, AutofocusConfig(iterations=150, smoothness_weight=0.05))
    pen = lambda r: float(smoothness_penalty(torch.from_numpy(r.phase_rad)))
    assert pen(smooth) < pen(plain)
    # the injected drift is smooth, so the prior costs the target nothing that matters
    assert image_ssim(form_image(tgt_basis, smooth.phase_rad), truth) > 0.9


@pytest.mark.slow  # 4 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_wrapping_errors_of_2mm_stay_finite():
    ch, data, true, tracked = _scenario(2e-3, seed=4, snr_db=0.0)
    ref_basis = subimage_basis(data, tracked, ch, REF_GRID)
    template = np.abs(backproject(data, true, ch, REF_GRID))
    result = twin_autofocus(ref_basis, template, AutofocusConfig(iterations=60))
    assert np.isfinite(result.phase_rad).all() and np.isfinite(result.loss_history).all()
    assert np.isfinite(result.image).all()


@pytest.mark.slow  # 2.3 s (2 cores, idle): out of make test-fast (benchmarks/results/test_fast.json)
def test_baselines_run(scene_05mm):
    _, _, _, _, tgt_basis, _, truth = scene_05mm
    none = no_correction(tgt_basis)
    np.testing.assert_allclose(none.image, tgt_basis.sum(0), rtol=1e-5, atol=1e-3 * np.abs(tgt_basis.sum(0)).max())
    sharp = sharpness_autofocus(tgt_basis, AutofocusConfig(iterations=50))
    inten0 = np.abs(none.image) ** 2
    inten1 = np.abs(sharp.image) ** 2
    # the baseline does what it says: the target gets sharper by its own measure
    assert (inten1**2).sum() / inten1.sum() ** 2 > (inten0**2).sum() / inten0.sum() ** 2


def test_bad_templates_and_shapes_are_refused(scene_05mm):
    _, _, _, ref_basis, _, template, _ = scene_05mm
    with pytest.raises(TwinFocusError, match="empty"):
        twin_autofocus(ref_basis, np.zeros_like(template))
    with pytest.raises(TwinFocusError, match="constant"):
        twin_autofocus(ref_basis, np.ones_like(template))
    with pytest.raises(TwinFocusError, match="template is"):
        twin_autofocus(ref_basis, template[:-1])
    bad = template.copy()
    bad[0, 0] = np.inf
    with pytest.raises(TwinFocusError, match="NaN or inf"):
        twin_autofocus(ref_basis, bad)
    with pytest.raises(TwinFocusError, match="iterations"):
        twin_autofocus(ref_basis, template, AutofocusConfig(iterations=0))
    with pytest.raises(TwinFocusError, match="one value per radar position"):
        form_image(ref_basis, np.zeros(3))


def test_linear_phase_fit_recovers_ramp_through_wrapping():
    from twinfocus.focus.autofocus import fit_linear_phase, transfer_phase

    rng = np.random.default_rng(7)
    poses = paper_raster()
    ap = poses.position_m[:, :2]
    # 0.3 rad jitter on top of a ramp of several turns across the aperture
    a, bx, by = 1.3, 17.0, -21.0  # |bx| < pi / 82 mm: unaliased on the raster's columns
    jitter = rng.normal(0, 0.3, ap.shape[0])
    phase = np.angle(np.exp(1j * (a + ap @ np.array([bx, by]) + jitter)))
    ramp, coeffs = fit_linear_phase(phase, ap)
    np.testing.assert_allclose(coeffs[1:], [bx, by], atol=0.5)
    left, info = transfer_phase(phase, ap, 0.6, 3.9e-3, "remove")
    assert info["removed"] and phase_error_rms(left, jitter) < 0.05
    with pytest.raises(TwinFocusError, match="aperture_m"):
        fit_linear_phase(phase, ap[:10])


@pytest.mark.parametrize(
    "shift_mm, registered, mode, removed",
    [
        (1.0, False, "auto", True),  # a misplaced template's ramp: taken out
        (-2.5, False, "auto", True),
        (8.0, False, "auto", False),  # no template is 8 mm off: tracking error, transferred
        (1.0, True, "auto", False),  # registration already took the misplacement out
        (8.0, False, "remove", True),
        (1.0, False, "keep", False),
    ],
)
def test_transfer_phase_removes_only_what_a_misplaced_template_explains(shift_mm, registered, mode, removed):
    from twinfocus.focus.autofocus import transfer_phase

    rng = np.random.default_rng(3)
    ap = paper_raster().position_m[:, :2]
    lam, r = 3.9e-3, 0.6
    # an image shift d at range R is the aperture ramp k d / R, k = 4 pi / lambda
    slope = 4 * np.pi / lam * shift_mm * 1e-3 / r
    rest = rng.normal(0, 0.3, ap.shape[0])
    phase = np.angle(np.exp(1j * (0.4 + slope * ap[:, 0] + rest)))
    out, info = transfer_phase(phase, ap, r, lam, mode, registered)
    assert info["removed"] is removed
    np.testing.assert_allclose(info["implied_shift_m"][0], shift_mm * 1e-3, atol=0.15e-3)
    if removed:
        assert phase_error_rms(out, rest) < 0.05
    else:
        np.testing.assert_array_equal(out, phase)
    with pytest.raises(TwinFocusError, match="phase ramp mode"):
        transfer_phase(phase, ap, r, lam, "sometimes")
