"""Space-variant correction (twinfocus.space_variant) against the exact per-point phase
(metrics.oracle_phase) and brute-force sums."""
import numpy as np
import pytest

from twinfocus.autofocus import form_image
from twinfocus.errors import TwinFocusError
from twinfocus.grid import ImageGrid
from twinfocus.metrics import oracle_phase
from twinfocus.motion import apply_position_errors, gaussian_errors
from twinfocus.radar import Chirp, mmwcas_virtual_array
from twinfocus.space_variant import fit_position_errors, form_image_space_variant, lines_of_sight, pixel_phases
from twinfocus.trajectory import paper_raster, phase_centres

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
