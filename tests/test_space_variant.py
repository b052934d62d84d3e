"""Space-variant correction (twinfocus.focus.space_variant) against the exact per-point phase
(metrics.oracle_phase) and brute-force sums."""

import os

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.focus.space_variant import fit_position_errors, lines_of_sight, pixel_phases
from twinfocus.imaging.basis import form_image, form_image_space_variant
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.metrics import oracle_phase
from twinfocus.motion.tracking_errors import apply_position_errors, gaussian_errors
from twinfocus.motion.trajectory import paper_raster, phase_centres
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array

Z = 0.6


@pytest.fixture(scope="module")
def geometry():
    true = phase_centres(paper_raster(n_columns=6, n_rows=40), mmwcas_virtual_array())
    tracked = apply_position_errors(true, gaussian_errors(true.shape[0], (0.5e-3,) * 3, np.random.default_rng(0)))
    half = np.deg2rad(20.0)
    refs = np.array([[-Z * np.tan(half), 0.0, Z], [Z * np.tan(half), 0.0, Z]])
    return Chirp(), true, tracked, refs


def _abs_error(phase, exact):
    """|wrapped phase - exact| per position after removing the best constant, radians."""
    d = np.angle(np.exp(1j * (phase - exact)))
    return np.abs(np.angle(np.exp(1j * (d - np.angle(np.exp(1j * d).mean())))))


def test_fit_from_two_references_predicts_the_phase_between_them(geometry):
    ch, true, tracked, refs = geometry
    phases = np.array([oracle_phase(true, tracked, p, ch) for p in refs])
    noisy = phases + np.random.default_rng(1).normal(0, 0.1, phases.shape)
    cm = tracked.mean(axis=1)
    d = fit_position_errors(noisy, np.ones_like(noisy), refs, cm, ch.wavelength_m, prior_sigma_m=0.5e-3, noise_rad=0.1)
    # the exact phase at points on the line through the references (the references see dp only
    # along it: a point off that line would also need dp across it)
    grid = ImageGrid(-0.1, 0.1, -0.001, 0.001, Z, 2, 5)
    ph = pixel_phases(noisy[0], d, refs[0], cm, grid, ch.wavelength_m)
    for i, j in [(0, 1), (0, 2), (1, 3), (1, 4)]:
        point = np.array([grid.x_m[j], grid.y_m[i], Z])
        exact = oracle_phase(true, tracked, point, ch)
        scalar_err, sv_err = _abs_error(noisy[0], exact), _abs_error(ph[:, i, j], exact)
        # one reference 10-20 deg away is off by this much
        assert np.median(scalar_err) > 0.18 and (scalar_err < 0.25).mean() < 0.65
        # the fit: right to the phase noise, except at the few positions (a 3-sigma error along
        # the references' baseline) whose phase difference wrapped past pi
        assert np.median(sv_err) < 0.1 and (sv_err < 0.25).mean() > 0.95


def test_no_information_across_the_line_of_sight_gives_no_correction(geometry):
    ch, true, tracked, refs = geometry
    # two references on one line of sight: their phases agree, the fit must stay at the prior (0)
    same = np.array([refs[0], refs[0] * 1.0000001])
    phases = np.tile(oracle_phase(true, tracked, refs[0], ch), (2, 1))
    cm = tracked.mean(axis=1)
    d = fit_position_errors(phases, np.ones_like(phases), same, cm, ch.wavelength_m, absolute=False)
    assert np.abs(d).max() < 1e-6
    # with the references' own phases, only the along-sight part is pinned
    d = fit_position_errors(phases, np.ones_like(phases), same, cm, ch.wavelength_m)
    u = lines_of_sight(cm, same[0])
    along = np.einsum("mc,mc->m", d, u)
    across = d - along[:, None] * u
    assert np.abs(along).max() > 1e-4 and np.abs(across).max() < 1e-3 * np.abs(along).max()


def test_per_pixel_image_equals_brute_force_and_reduces_to_the_scalar_image():
    rng = np.random.default_rng(2)
    basis = (rng.normal(size=(70, 5, 6)) + 1j * rng.normal(size=(70, 5, 6))).astype(np.complex64)
    ph = rng.uniform(-np.pi, np.pi, (70, 5, 6)).astype(np.float32)
    want = np.einsum("mhw,mhw->hw", basis.astype(np.complex128), np.exp(1j * ph.astype(np.float64)))
    assert np.allclose(form_image_space_variant(basis, ph), want, rtol=1e-4, atol=1e-4)
    flat = np.broadcast_to(ph[:, :1, :1], ph.shape)
    assert np.allclose(form_image_space_variant(basis, flat), form_image(basis, ph[:, 0, 0]), rtol=1e-4, atol=1e-4)
    with pytest.raises(TwinFocusError, match="match"):
        form_image_space_variant(basis, ph[:, :4])


def test_bad_inputs_are_named(geometry):
    ch, true, tracked, refs = geometry
    m = tracked.shape[0]
    with pytest.raises(TwinFocusError, match=">= 2 references"):
        fit_position_errors(np.zeros((1, m)), np.ones((1, m)), refs[:1], tracked.mean(axis=1), ch.wavelength_m)
    with pytest.raises(TwinFocusError, match="weights"):
        fit_position_errors(np.zeros((2, m)), -np.ones((2, m)), refs, tracked.mean(axis=1), ch.wavelength_m)


def _drifting_scan(fast_mm: float = 0.0) -> dict:
    """A rough extended reference and a target beside it, scanned with a smooth x/y drift (plus,
    with ``fast_mm``, a wander of that amplitude over 12 positions: faster than knots every 10
    can follow)."""
    from twinfocus.imaging.backprojection.numba_backend import backproject, subimage_basis
    from twinfocus.radar.fmcw import VirtualArray
    from twinfocus.simulation.if_simulator import simulate_if_exact

    ch = Chirp()
    k = 12
    array = VirtualArray(
        np.c_[np.linspace(0, 0.04, k), np.zeros(k), np.zeros(k)], np.zeros(k, int), np.zeros(k, int), np.zeros((k, 2))
    )
    tracked = phase_centres(paper_raster(n_columns=4, n_rows=60, row_pitch_m=0.003), array)
    t = np.arange(tracked.shape[0])
    drift = np.c_[0.8e-3 * np.sin(2 * np.pi * t / 80 + 0.3), 0.6e-3 * np.cos(2 * np.pi * t / 110), np.zeros_like(t)]
    drift[:, :2] += fast_mm * 1e-3 * np.c_[np.sin(2 * np.pi * t / 12), np.cos(2 * np.pi * t / 12 + 1.0)]
    true = tracked + drift[:, None, :]
    rng = np.random.default_rng(3)
    gx, gy = np.meshgrid(np.linspace(-0.13, -0.03, 6), np.linspace(-0.05, 0.05, 6))
    ref_pts = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, Z)]
    tgt_pts = np.array([[0.06, -0.03, Z], [0.08, 0.02, Z], [0.10, -0.01, Z], [0.07, 0.04, Z]])
    pts = np.r_[ref_pts, tgt_pts]
    amps = rng.uniform(0.7, 1.3, len(pts)) * np.exp(1j * rng.uniform(-np.pi / 2, np.pi / 2, len(pts)))  # rough
    data = simulate_if_exact(pts, amps, true, ch)
    rg = ImageGrid(-0.15, -0.01, -0.07, 0.07, Z, 32, 32)
    tg = ImageGrid(0.03, 0.13, -0.07, 0.07, Z, 24, 24)
    template = backproject(data, true, ch, rg)  # what a motion-stage scan of the reference gives
    scene = {"chirp": ch, "tracked": tracked, "true": true, "drift": drift, "rg": rg, "tg": tg, "template": template}
    bases = {
        "ref_basis": subimage_basis(data, tracked, ch, rg),
        "tgt_basis": subimage_basis(data, tracked, ch, tg),
        "ref_basis_true": subimage_basis(data, true, ch, rg),
        "tgt_basis_true": subimage_basis(data, true, ch, tg),
    }
    truth = {"truth_target": backproject(data, true, ch, tg), "truth_reference": backproject(data, true, ch, rg)}
    return {**scene, **bases, **truth}


def _fit_args(s):
    """fit_smooth_drift's inputs on ``s`` (a :func:`_drifting_scan`): the reference basis, the
    template, the closed form's phase (rad, per position), the aperture centres, the grid, the
    wavelength."""
    from twinfocus.focus.template_match import correlation_phase

    phi0 = correlation_phase(s["ref_basis"], s["template"])
    return (s["ref_basis"], s["template"], phi0, s["tracked"].mean(axis=1), s["rg"], s["chirp"].wavelength_m)


def _drift_error_m(s, dp):
    """rms of the fitted x/y drift ``dp`` (M, 3) less the injected one, each less its mean, m."""
    e = dp[:, :2] - s["drift"][:, :2]
    return float(np.sqrt(((e - e.mean(axis=0)) ** 2).mean()))


@pytest.fixture(scope="module")
def drifting_scan():
    return _drifting_scan()


@pytest.mark.slow  # 2.0 s x
def test_smooth_drift_fit_recovers_an_injected_drift_and_the_targets_phase(drifting_scan):
    from twinfocus.focus.space_variant import fit_smooth_drift
    from twinfocus.imaging.metrics import phase_error_rms

    s = drifting_scan
    args = _fit_args(s)
    phi0, centres = args[2], args[3]
    phase, dp, _, info = fit_smooth_drift(*args)
    assert info["match_after"] > info["match_before"]
    # the drift across the line of sight, in the correction's sense (true - tracked)
    for axis in (0, 1):
        assert np.corrcoef(dp[:, axis], s["drift"][:, axis])[0, 1] > 0.8
    # the phase the target needs, from the fit, against the scalar transfer
    k = 4 * np.pi / s["chirp"].wavelength_m
    du = lines_of_sight(centres, s["tg"].centre_m) - lines_of_sight(centres, s["rg"].centre_m)
    exact = oracle_phase(s["true"], s["tracked"], s["tg"].centre_m, s["chirp"])
    scalar_err = phase_error_rms(phi0, exact)
    fitted_err = phase_error_rms(phase + k * np.einsum("mc,mc->m", du, dp), exact)
    assert scalar_err > 0.4 and fitted_err < 0.4 * scalar_err


@pytest.mark.slow  # 1.9 s x
def test_focus_uses_the_space_variant_fit_only_when_the_data_ask_for_it(drifting_scan):
    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.estimators import estimator_settings
    from twinfocus.focus.pipeline import Bases, Reference, Truth
    from twinfocus.focus.plan import FocusPlan

    s = drifting_scan
    cfg = AutofocusConfig(**estimator_settings("correlation", True))

    def focus(tracked, ref_basis, tgt_basis, mode):
        return FocusPlan.make(config=cfg, space_variant=mode).focus_bases(
            Bases(ref_basis, tgt_basis, tracked, s["chirp"], s["rg"], s["tg"]),
            Reference(template=s["template"]),
            Truth(s["truth_target"], s["truth_reference"], s["true"]),
        )

    off = focus(s["tracked"], s["ref_basis"], s["tgt_basis"], "off")
    auto = focus(s["tracked"], s["ref_basis"], s["tgt_basis"], "auto")
    assert auto.metrics["space_variant"]["used"] and auto.drift_m is not None
    assert auto.metrics["target_ssim_corrected"] > off.metrics["target_ssim_corrected"] + 0.02
    assert auto.metrics["reference_residual"] < off.metrics["reference_residual"]
    # the scalar correction leaves the reference visibly unmatched, and the report says so
    assert not off.metrics["confidence"]["trusted"]
    assert any("unmatched" in w for w in off.metrics["confidence"]["warnings"])

    # no drift (the scan on its true positions): whatever auto decides, it finds no drift and
    # costs the target nothing
    exact = focus(s["true"], s["ref_basis_true"], s["tgt_basis_true"], "auto")
    if exact.drift_m is not None:
        assert np.sqrt((exact.drift_m**2).mean()) < 0.1e-3
    assert exact.metrics["target_ssim_corrected"] > 0.99
    assert exact.metrics["confidence"]["trusted"], (
        exact.metrics["confidence"]["warnings"],
        exact.metrics["space_variant"],
    )


def test_space_variant_bad_requests_are_named(drifting_scan):
    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.estimators import estimator_settings
    from twinfocus.focus.pipeline import Bases, Reference
    from twinfocus.focus.plan import FocusPlan

    s = drifting_scan
    args = (s["ref_basis"], s["tgt_basis"], s["tracked"], s["chirp"], s["rg"], s["tg"])
    with pytest.raises(TwinFocusError, match="space_variant must be one of"):
        FocusPlan.make(
            config=AutofocusConfig(**estimator_settings("correlation", True)),
            space_variant="sometimes",
        ).focus_bases(
            Bases(*args),
            Reference(template=s["template"]),
        )
    # "on" with an amplitude template: nothing to fit the drift to
    with pytest.raises(TwinFocusError, match="needs a template with phase"):
        FocusPlan.make(
            config=AutofocusConfig(**estimator_settings("projection", False)),
            space_variant="on",
        ).focus_bases(
            Bases(*args),
            Reference(template=np.abs(s["template"])),
        )
    # a half-array basis that is not the reference's shape
    from twinfocus.focus.space_variant import fit_smooth_drift

    centres = s["tracked"].mean(axis=1)
    with pytest.raises(TwinFocusError, match="half basis"):
        fit_smooth_drift(
            s["ref_basis"],
            s["template"],
            np.zeros(len(centres)),
            centres,
            s["rg"],
            s["chirp"].wavelength_m,
            half_basis=s["ref_basis"][:, :5],
        )
    from twinfocus.focus.space_variant import DriftFitSettings

    with pytest.raises(TwinFocusError, match="knot_energy_fraction"):
        DriftFitSettings(knot_energy_fraction=0.0)
    with pytest.raises(TwinFocusError, match="knot_spacing"):
        DriftFitSettings(knot_spacing=0)


@pytest.mark.slow  # 2.3 s (2 cores, idle): out of make test-fast (benchmarks/results/test_fast.json)
def test_per_position_refinement_follows_a_drift_faster_than_the_knots():
    from twinfocus.focus.space_variant import DriftFitSettings, fit_smooth_drift

    s = _drifting_scan(fast_mm=0.4)
    args = _fit_args(s)

    def drift_error_mm(dp):
        return _drift_error_m(s, dp) * 1e3

    _, knots_only, _, _ = fit_smooth_drift(*args, DriftFitSettings(refine_iterations=0))
    _, refined, _, info = fit_smooth_drift(*args)
    _, stiff, _, _ = fit_smooth_drift(*args, DriftFitSettings(smoothness_per_mm2=1.0))
    _, free, _, _ = fit_smooth_drift(*args, DriftFitSettings(smoothness_per_mm2=0.0))
    # knots every 10 positions cannot follow a 12-position wander; the per-position stage can
    assert drift_error_mm(refined) < 0.75 * drift_error_mm(knots_only)
    # a stiff penalty holds neighbours together: the wander stays out of the estimate; none lets
    # each position's noise in
    assert drift_error_mm(stiff) > 1.5 * drift_error_mm(refined)
    assert drift_error_mm(free) > 1.5 * drift_error_mm(refined)
    assert info["match_after"] > info["match_before"]
    # the stage stops once it has taken its gain: early, and near where every step gets it
    _, every_step, _, info_all = fit_smooth_drift(*args, DriftFitSettings(refine_stop=0.0))
    assert info_all["refine_iterations"] == 100 and 20 <= info["refine_iterations"] < 100
    assert drift_error_mm(refined) < 1.15 * drift_error_mm(every_step)


@pytest.mark.slow  # 2.2 s (2 cores, idle): out of make test-fast (benchmarks/results/test_fast.json)
def test_the_fit_follows_the_arrays_tilt_with_the_half_array_basis():
    """A drift with the array tilting about its cross axis: each channel moves along the line of
    sight by tilt x its offset along the array. With the half-array basis the fit finds the halves'
    differential phase and the target comes out sharper than without it."""
    from twinfocus.focus.space_variant import array_half, fit_smooth_drift, tilted_basis
    from twinfocus.focus.template_match import correlation_phase
    from twinfocus.imaging.backprojection.numba_backend import backproject, subimage_basis
    from twinfocus.imaging.metrics import image_ssim
    from twinfocus.radar.fmcw import VirtualArray
    from twinfocus.simulation.if_simulator import simulate_if_exact

    ch = Chirp()
    k = 16
    offsets = np.c_[np.linspace(-0.04, 0.04, k), np.zeros(k), np.zeros(k)]
    array = VirtualArray(offsets, np.zeros(k, int), np.zeros(k, int), np.zeros((k, 2)))
    tracked = phase_centres(paper_raster(n_columns=4, n_rows=60, row_pitch_m=0.003), array)
    t = np.arange(tracked.shape[0])
    drift = np.c_[0.5e-3 * np.sin(2 * np.pi * t / 90), 0.4e-3 * np.cos(2 * np.pi * t / 70), np.zeros_like(t)]
    tilt_rad = 0.012 * np.sin(2 * np.pi * t / 60 + 0.5)  # 0.7 degrees: +-0.24 mm at the ends
    true = tracked + drift[:, None, :]
    true[:, :, 2] += tilt_rad[:, None] * offsets[None, :, 0]
    rng = np.random.default_rng(4)
    gx, gy = np.meshgrid(np.linspace(-0.13, -0.03, 6), np.linspace(-0.05, 0.05, 6))
    ref_pts = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, Z)]
    tgt_pts = np.array([[0.06, -0.03, Z], [0.08, 0.02, Z], [0.10, -0.01, Z], [0.07, 0.04, Z]])
    pts = np.r_[ref_pts, tgt_pts]
    amps = rng.uniform(0.7, 1.3, len(pts)) * np.exp(1j * rng.uniform(-np.pi / 2, np.pi / 2, len(pts)))
    data = simulate_if_exact(pts, amps, true, ch)
    rg = ImageGrid(-0.15, -0.01, -0.07, 0.07, Z, 32, 32)
    tg = ImageGrid(0.03, 0.13, -0.07, 0.07, Z, 24, 24)
    template = backproject(data, true, ch, rg)
    half = array_half(tracked)
    assert half.sum() == k // 2 and (offsets[half, 0] < 0).all()
    ref_basis, tgt_basis = subimage_basis(data, tracked, ch, rg), subimage_basis(data, tracked, ch, tg)
    ref_half = subimage_basis(data[:, half], tracked[:, half], ch, rg)
    tgt_half = subimage_basis(data[:, half], tracked[:, half], ch, tg)
    centres, lam = tracked.mean(axis=1), ch.wavelength_m
    phi0 = correlation_phase(ref_basis, template)
    truth = backproject(data, true, ch, tg)

    phase, dp, tilt, info = fit_smooth_drift(ref_basis, template, phi0, centres, rg, lam, half_basis=ref_half)
    assert info["tilt_fitted"]
    # the halves' centres sit -+20 mm from the middle: psi = k tilt 20 mm in the half's sense
    expected = -(4 * np.pi / lam) * tilt_rad * np.abs(offsets[half, 0]).mean()
    assert np.corrcoef(tilt, expected)[0, 1] > 0.8
    with_tilt = form_image_space_variant(
        tilted_basis(tgt_basis, tgt_half, tilt), pixel_phases(phase, dp, rg.centre_m, centres, tg, lam)
    )
    p0, d0, t0, info0 = fit_smooth_drift(ref_basis, template, phi0, centres, rg, lam)
    assert not info0["tilt_fitted"] and not t0.any()
    without = form_image_space_variant(tgt_basis, pixel_phases(p0, d0, rg.centre_m, centres, tg, lam))
    assert info["match_after"] > info0["match_after"]
    assert image_ssim(with_tilt, truth) > image_ssim(without, truth) + 0.01


def test_tilted_basis_is_the_halves_phased_apart():
    from twinfocus.focus.space_variant import array_half, tilted_basis

    rng = np.random.default_rng(2)
    b = (rng.normal(size=(5, 3, 4)) + 1j * rng.normal(size=(5, 3, 4))).astype(np.complex64)
    left = (rng.normal(size=(5, 3, 4)) + 1j * rng.normal(size=(5, 3, 4))).astype(np.complex64)
    psi = rng.uniform(-1, 1, 5)
    expected = left * np.exp(1j * psi)[:, None, None] + (b - left) * np.exp(-1j * psi)[:, None, None]
    np.testing.assert_allclose(tilted_basis(b, left, psi), expected, atol=1e-5)
    np.testing.assert_allclose(tilted_basis(b, left, np.zeros(5)), b, atol=1e-6)
    with pytest.raises(TwinFocusError, match="do not fit"):
        tilted_basis(b, left[:4], psi)
    with pytest.raises(TwinFocusError, match="no extent"):
        array_half(np.zeros((3, 4, 3)))


@pytest.mark.parametrize("kernel", ["numba", "torch"])
@pytest.mark.parametrize("tilted", [True, False])
def test_the_drift_fits_gradients_are_those_of_the_per_pixel_model(kernel, tilted, monkeypatch):
    """The fit's correlation and its gradients (written out, not traced) against autograd on the
    model as written: exact lines of sight per pixel, float64, the tilted basis or the plain one;
    the CPU's numpy + numba match and the torch code other devices run, both on the CPU here (the
    line-of-sight polynomial at degree 4, within 2e-5 rad of the exact lines of sight: the test is
    of the gradients' algebra)."""
    import torch

    from twinfocus.focus import space_variant as sv

    monkeypatch.setattr(sv, "LINE_OF_SIGHT_DEGREE", 4)

    rng = np.random.default_rng(5)
    m, h, w = 40, 9, 11
    lam = Chirp().wavelength_m
    grid = ImageGrid(-0.12, 0.02, -0.07, 0.07, Z, h, w)
    b, half = (rng.normal(size=(2, m, h, w)) + 1j * rng.normal(size=(2, m, h, w))).astype(np.complex64)
    tpl = (rng.normal(size=(h, w)) + 1j * rng.normal(size=(h, w))).astype(np.complex64)
    centres = np.c_[rng.uniform(-0.2, 0.2, m), rng.uniform(-0.13, 0.13, m), np.zeros(m)]
    phase, dp, tilt = rng.normal(size=m), rng.normal(size=(m, 2)) * 1e-3, rng.normal(size=m) * 0.1

    b_before = b.copy()
    q, u = sv._line_of_sight_polynomial(centres, grid, lam)
    cls = sv._CpuDriftMatch if kernel == "numba" else sv._TorchDriftMatch
    match = cls(b, half if tilted else None, tpl, q, u, "cpu")
    f32 = [phase, dp, tilt if tilted else None]
    k = 4 * np.pi / lam
    a = k * (lines_of_sight(centres, grid.points()) - lines_of_sight(centres, grid.centre_m)[:, None, :])[..., :2]
    some = rng.uniform(size=h * w) < 0.4  # the knots' stage's pixels: any subset
    for pixels, objective in ((np.ones(h * w, bool), match), (some, match.on(some))):
        corr, g_phase, g_dp, g_tilt = objective.value_and_gradients(*f32)
        ph, d, ps = (torch.tensor(v, dtype=torch.float64, requires_grad=True) for v in (phase, dp, tilt))
        theta = ph[:, None] + (torch.from_numpy(a[:, pixels]) * d[:, None, :]).sum(-1)
        bt, ht = (torch.from_numpy(v.reshape(m, -1)[:, pixels].astype(np.complex128)) for v in (b, half))
        e = bt * torch.exp(-1j * ps)[:, None] + 2j * torch.sin(ps)[:, None] * ht if tilted else bt
        image = (e * torch.exp(1j * theta)).sum(0)
        t = torch.from_numpy(tpl.reshape(-1)[pixels].astype(np.complex128))
        want = torch.vdot(t, image).real / (torch.linalg.vector_norm(image) * torch.linalg.vector_norm(t))
        want.backward()
        assert abs(corr - float(want.detach())) < 1e-5
        assert (g_tilt is not None) == tilted
        for got, exact in ((g_phase, ph.grad), (g_dp, d.grad)) + (((g_tilt, ps.grad),) if tilted else ()):
            np.testing.assert_allclose(got, exact.numpy(), rtol=0, atol=1e-3 * float(exact.abs().max()))
    # the basis is read, never scaled or written in place (the pipeline forms its images after)
    np.testing.assert_array_equal(b, b_before)


def test_the_fit_recovers_the_drift_on_the_bright_pixels_as_on_every_pixel(drifting_scan):
    """Against the injected drift (0.8 / 0.6 mm amplitude): the fit with every pixel in both
    stages comes within 0.05 mm rms of it on this scene; with the knots' stage on the template's
    bright pixels (the default) it stays within 10 % of that."""
    from twinfocus.focus.space_variant import DriftFitSettings, fit_smooth_drift

    s = drifting_scan
    args = _fit_args(s)

    _, every, _, info_every = fit_smooth_drift(*args, DriftFitSettings(knot_energy_fraction=1.0))
    _, bright, _, info = fit_smooth_drift(*args)
    assert _drift_error_m(s, every) < 0.05e-3
    assert _drift_error_m(s, bright) < 1.1 * _drift_error_m(s, every)
    assert info["knot_pixels"] < 0.5 * info_every["knot_pixels"] == 0.5 * s["rg"].shape[0] * s["rg"].shape[1]
    assert info["device"] == "cpu" and info["match_after"] > 0.999


def test_the_cpu_kernel_and_the_torch_code_fit_the_same_drift(drifting_scan, monkeypatch):
    """The whole fit (200 Adam steps) with the CPU's fused numba pass and with the torch code that
    other devices run: float32 round-off apart, and both within 0.06 mm rms of the injected drift
    (0.8 / 0.6 mm amplitude)."""
    from twinfocus.focus import space_variant as sv

    s = drifting_scan
    args = _fit_args(s)

    p_numba, d_numba, _, i_numba = sv.fit_smooth_drift(*args)
    monkeypatch.setattr(sv, "_CpuDriftMatch", sv._TorchDriftMatch)  # torch's code, on the CPU
    p_torch, d_torch, _, i_torch = sv.fit_smooth_drift(*args)
    assert abs(i_torch["match_after"] - i_numba["match_after"]) < 1e-4
    assert np.sqrt(((d_torch - d_numba) ** 2).mean()) < 0.01e-3
    assert np.abs(np.angle(np.exp(1j * (p_torch - p_numba)))).max() < 0.05
    assert _drift_error_m(s, d_numba) < 0.06e-3 and _drift_error_m(s, d_torch) < 0.06e-3


@pytest.mark.slow  # 3 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_a_busy_cpu_fits_on_one_thread_and_finds_the_same_drift(drifting_scan, monkeypatch):
    """BLAS's part of the fit runs on one thread; at a load average of the cores or more numba's
    too; the threads are given back as they were, and the drift is the same either way. The CPU's
    fit never imports torch."""
    import subprocess
    import sys

    import numba
    from threadpoolctl import threadpool_info

    from twinfocus.focus import space_variant as sv

    s = drifting_scan
    args = _fit_args(s)
    cores = os.cpu_count() or 1
    threads = numba.get_num_threads()

    def blas_threads():
        return max(p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas")

    blas = blas_threads()

    def fit(load):
        monkeypatch.setattr(sv.os, "getloadavg", lambda: (load, 0.0, 0.0))
        seen = []
        _, dp, _, info = sv.fit_smooth_drift(
            *args, progress=lambda *_: seen.append((blas_threads(), numba.get_num_threads()))
        )
        assert (blas_threads(), numba.get_num_threads()) == (blas, threads)
        return dp, info, set(seen)

    d_idle, i_idle, seen_idle = fit(0.0)
    d_busy, i_busy, seen_busy = fit(float(cores))
    assert seen_idle == {(1, threads)} and i_idle["threads"] == threads
    assert seen_busy == {(1, 1)} and i_busy["threads"] == 1
    assert abs(i_busy["match_after"] - i_idle["match_after"]) < 1e-4
    assert np.sqrt(((d_busy - d_idle) ** 2).mean()) < 0.01e-3
    code = (
        "import sys, numpy as np; from twinfocus.imaging.grid import ImageGrid; from twinfocus.focus.space_variant import "
        "fit_smooth_drift; g = ImageGrid(-0.01, 0.01, -0.01, 0.01, 0.3, 4, 4); rng = np.random.default_rng(0); "
        "b = (rng.normal(size=(20, 4, 4)) + 1j).astype(np.complex64); c = np.c_[np.linspace(0, 0.1, 20), "
        "np.zeros((20, 2))]; fit_smooth_drift(b, b.sum(0), np.zeros(20), c, g, 0.004, half_basis=b); "
        "sys.exit('torch' in sys.modules)"
    )
    assert subprocess.run([sys.executable, "-c", code], timeout=120).returncode == 0


@pytest.mark.gpu
def test_the_drift_fit_on_cuda_matches_the_cpu(drifting_scan):
    """The same code on both devices: float32 round-off apart, through 200 Adam steps."""
    from twinfocus.focus.space_variant import fit_smooth_drift

    s = drifting_scan
    args = _fit_args(s)
    p_cpu, d_cpu, _, i_cpu = fit_smooth_drift(*args, device="cpu")
    p_gpu, d_gpu, _, i_gpu = fit_smooth_drift(*args, device="cuda")
    assert i_gpu["device"].startswith("cuda")
    assert abs(i_gpu["match_after"] - i_cpu["match_after"]) < 1e-4
    assert np.sqrt(((d_gpu - d_cpu) ** 2).mean()) < 0.01e-3
    assert np.abs(np.angle(np.exp(1j * (p_gpu - p_cpu)))).max() < 0.05


def test_drift_image_is_the_brute_force_sum_over_positions_and_pixels():
    """drift_image against the sum written out: every position's exact line of sight to every
    pixel, its phase, the tilted basis, added up in complex128 (with and without the tilt)."""
    from twinfocus.focus.space_variant import drift_image

    rng = np.random.default_rng(5)
    m, grid, lam = 7, ImageGrid(-0.05, 0.03, -0.04, 0.02, Z, 5, 6), Chirp().wavelength_m
    centres = np.c_[rng.uniform(-0.1, 0.1, (m, 2)), rng.uniform(-0.01, 0.01, m)]
    b = (rng.normal(size=(m,) + grid.shape) + 1j * rng.normal(size=(m,) + grid.shape)).astype(np.complex64)
    left = (rng.normal(size=(m,) + grid.shape) + 1j * rng.normal(size=(m,) + grid.shape)).astype(np.complex64)
    phase0, dp, psi = rng.uniform(-3, 3, m), rng.normal(0, 1e-3, (m, 3)), rng.uniform(-0.3, 0.3, m)
    point0 = np.array([0.01, -0.02, Z])
    k = 4 * np.pi / lam
    expected, untilted = np.zeros(grid.shape, complex), np.zeros(grid.shape, complex)
    for i in range(m):
        u0 = (point0 - centres[i]) / np.linalg.norm(point0 - centres[i])
        for r, y in enumerate(grid.y_m):
            for c, x in enumerate(grid.x_m):
                d = np.array([x, y, Z]) - centres[i]
                rot = np.exp(1j * (phase0[i] + k * (d / np.linalg.norm(d) - u0) @ dp[i]))
                e = left[i, r, c] * np.exp(1j * psi[i]) + (b[i, r, c] - left[i, r, c]) * np.exp(-1j * psi[i])
                expected[r, c] += e * rot
                untilted[r, c] += b[i, r, c] * rot
    got = drift_image(b, phase0, dp, point0, centres, grid, lam, half_basis=left, tilt_rad=psi)
    assert got.dtype == np.complex64 and got.shape == grid.shape
    np.testing.assert_allclose(got, expected, atol=2e-5 * np.abs(expected).max())
    np.testing.assert_allclose(drift_image(b, phase0, dp, point0, centres, grid, lam), untilted,
                               atol=2e-5 * np.abs(untilted).max())  # fmt: skip
    with pytest.raises(TwinFocusError, match="tilt needs both"):
        drift_image(b, phase0, dp, point0, centres, grid, lam, half_basis=left)


def test_the_fits_adam_steps_as_torchs_adam():
    """The drift fit's Adam (numpy) against torch.optim.Adam on the same gradients: the same
    parameters after every step, for two groups at their own steps."""
    import torch

    from twinfocus.focus.space_variant import _Adam

    rng = np.random.default_rng(6)
    a0, b0 = rng.normal(size=(4, 2)), rng.normal(size=5)
    mine = [a0.copy(), b0.copy()]
    ref = [torch.tensor(a0), torch.tensor(b0)]
    opt_mine = _Adam(mine, [0.01, 0.2])
    opt_ref = torch.optim.Adam([{"params": [ref[0]], "lr": 0.01}, {"params": [ref[1]], "lr": 0.2}])
    for _ in range(6):
        grads = [rng.normal(size=p.shape) for p in mine]
        for q, g in zip(ref, grads):
            q.grad = torch.tensor(g)
        opt_mine.step(grads)
        opt_ref.step()
        for p, q in zip(mine, ref):
            np.testing.assert_allclose(p, q.numpy(), rtol=0, atol=1e-12)
    assert not np.array_equal(mine[0], a0)


def test_a_fit_on_some_pixels_is_the_fit_with_the_others_zeroed(drifting_scan):
    """``pixels`` (the held-out fits') against zeroing the other pixels in the basis and the
    template: the same knots' pixels, drift, phase and match, float32 round-off apart."""
    from twinfocus.focus.space_variant import DriftFitSettings, fit_smooth_drift
    from twinfocus.focus.template_match import correlation_phase

    s = drifting_scan
    centres, lam = s["tracked"].mean(axis=1), s["chirp"].wavelength_m
    phi0 = correlation_phase(s["ref_basis"], s["template"])
    mask = np.zeros(s["rg"].shape, bool)
    mask[::2, :] = True
    mask[1::4, 1::2] = True  # not a plain stripe pattern
    short = DriftFitSettings(iterations=40, refine_iterations=20)
    zeroed = fit_smooth_drift(s["ref_basis"] * mask, s["template"] * mask, phi0, centres, s["rg"], lam, short)
    masked = fit_smooth_drift(s["ref_basis"], s["template"], phi0, centres, s["rg"], lam, short, pixels=mask)
    assert masked[3]["knot_pixels"] == zeroed[3]["knot_pixels"] < mask.sum()
    np.testing.assert_allclose(masked[1], zeroed[1], atol=2e-7)
    np.testing.assert_allclose(masked[0], zeroed[0], atol=1e-4)
    assert abs(masked[3]["match_after"] - zeroed[3]["match_after"]) < 1e-5
    with pytest.raises(TwinFocusError, match="pixels must be"):
        fit_smooth_drift(
            s["ref_basis"], s["template"], phi0, centres, s["rg"], lam, pixels=np.zeros(s["rg"].shape, bool)
        )


def test_a_warm_started_fit_reaches_the_cold_fits_phase(drifting_scan):
    """The solver node fits a sweep's drift as its positions arrive and, after the last, refines
    from there (fit_smooth_drift's ``start``): from a fit on the first 220 of the 240 positions,
    30 + 30 steps on the whole scan (against the cold fit's 100 + up to 100) give the target the
    cold fit's phase within 0.15 rad rms (measured 0.11; a fit on part of the aperture against the
    whole one's template is pulled a little off, so not to the last digit), well inside the scalar
    transfer's error."""
    from twinfocus.focus.space_variant import DriftFitSettings, fit_smooth_drift
    from twinfocus.imaging.metrics import phase_error_rms

    s = drifting_scan
    args = _fit_args(s)
    basis, template, phi0, centres, grid, wavelength = args
    k = 4 * np.pi / wavelength
    du = lines_of_sight(centres, s["tg"].centre_m) - lines_of_sight(centres, grid.centre_m)

    def target_phase(fit):
        return fit[0] + k * np.einsum("mc,mc->m", du, fit[1])

    exact = oracle_phase(s["true"], s["tracked"], s["tg"].centre_m, s["chirp"])
    cold = fit_smooth_drift(*args)
    part = fit_smooth_drift(basis[:220], template, phi0[:220], centres[:220], grid, wavelength)
    warm = fit_smooth_drift(*args, DriftFitSettings(iterations=30, refine_iterations=30), start=part[3]["end_state"])
    assert warm[3]["warm_start_positions"] == 220 and cold[3]["warm_start_positions"] == 0
    # where the cold fit begins, on the same pixels, for the caller to judge the start by
    assert warm[3]["match_cold_start"] == pytest.approx(cold[3]["match_before"], rel=0, abs=1e-9)
    assert cold[3]["match_cold_start"] == cold[3]["match_before"]
    assert warm[3]["cost_evaluations"] < 0.4 * cold[3]["cost_evaluations"]
    assert phase_error_rms(target_phase(warm), target_phase(cold)) < 0.15
    assert phase_error_rms(target_phase(warm), exact) < 0.4 * phase_error_rms(phi0, exact)

    # the state carries the whole fit: started from the cold fit's own end, no step moves nothing
    again = fit_smooth_drift(*args, DriftFitSettings(iterations=0, refine_iterations=0), start=cold[3]["end_state"])
    np.testing.assert_allclose(again[0], cold[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(again[1], cold[1], rtol=0, atol=1e-15)
    # a start with other knots, or of a longer scan, is refused by name
    with pytest.raises(TwinFocusError, match="warm start"):
        fit_smooth_drift(*args, DriftFitSettings(knot_spacing=20), start=cold[3]["end_state"])
    with pytest.raises(TwinFocusError, match="warm start"):
        fit_smooth_drift(basis[:100], template, phi0[:100], centres[:100], grid, wavelength, start=part[3]["end_state"])


def test_a_warm_start_that_ends_below_the_cold_start_is_fitted_again_cold(drifting_scan):
    """The drift rung with a start from a fit of the sweep's first part: kept when its fit ends
    above where a cold fit begins; fitted again from the start when it ends below (every knot
    moved 1.5 mm across x): then the ladder's target is the cold ladder's, bit for
    bit, and the metrics name the refused start."""
    import dataclasses

    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.estimators import estimator_settings
    from twinfocus.focus.ladder import DriftStarts
    from twinfocus.focus.pipeline import Bases, Reference
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.focus.space_variant import fit_smooth_drift

    s = drifting_scan
    basis, template, phi0, centres, grid, wavelength = _fit_args(s)
    part = fit_smooth_drift(basis[:200], template, phi0[:200], centres[:200], grid, wavelength)[3]["end_state"]
    plan = FocusPlan.make(config=AutofocusConfig(**estimator_settings("correlation", True)), space_variant="on")

    def focus(start):
        starts = None if start is None else DriftStarts({"drift": start})  # WARM_FIT's steps
        bases = Bases(s["ref_basis"], s["tgt_basis"], s["tracked"], s["chirp"], s["rg"], s["tg"], drift_starts=starts)
        return plan.focus_bases(bases, Reference(template=s["template"]))

    cold = focus(None)
    kept = focus(part)
    assert kept.metrics["space_variant"]["warm_start_positions"] == 200
    assert "warm_start_refused" not in kept.metrics["space_variant"]
    off = focus(dataclasses.replace(part, knots_m=part.knots_m + np.array([1.5e-3, 0.0])))
    refused = off.metrics["space_variant"]["warm_start_refused"]
    assert refused["positions"] == 200 and refused["match_after"] < refused["match_cold_start"]
    np.testing.assert_array_equal(off.target, cold.target)
    assert (
        off.metrics["space_variant"]["residual_space_variant"]
        == cold.metrics["space_variant"]["residual_space_variant"]
    )


def test_drift_starts_give_warm_steps_only_to_a_fit_with_a_start():
    from twinfocus.focus.ladder import DriftStarts

    starts = DriftStarts(warm={"iterations": 10, "refine_iterations": 10})
    held = {"iterations": 50, "refine_iterations": 0}
    assert starts.settings("tilt", {}) == {}
    starts.states["tilt"] = object()
    assert starts.settings("tilt", {}) == {"iterations": 10, "refine_iterations": 10}
    # fewer steps than the warm ones are kept (a held-out fit's knots-only stage)
    assert starts.settings("tilt", held) == {"iterations": 10, "refine_iterations": 0}
