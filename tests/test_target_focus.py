"""The target's own focus check (twinfocus.focus.target_focus) against an injected quadratic phase, and
the confidence report's warning from it."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.focus.phase_ramp import aperture_polynomial
from twinfocus.focus.target_focus import defocus_gain_nats
from twinfocus.imaging.backprojection.numba_backend import subimage_basis
from twinfocus.imaging.grid import ImageGrid
from twinfocus.motion.trajectory import paper_raster, phase_centres
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
from twinfocus.simulation.if_simulator import simulate_if


@functools.cache
def points_scene() -> tuple[np.ndarray, np.ndarray]:
    """Sub-images (M, 24, 24) of three points at 0.3 m, seen on the true positions of a 4 x 30
    raster, and the positions' phase centres (M, 3): phase 0 focuses them."""
    centres = phase_centres(paper_raster(n_columns=4, n_rows=30, column_pitch_m=0.05, row_pitch_m=0.005),
                            mmwcas_virtual_array())  # fmt: skip
    points = np.array([(-0.01, 0.006, 0.3), (0.008, -0.004, 0.3), (0.0, 0.012, 0.3)])
    chirp = Chirp(n_samples=64)
    data = simulate_if(points, np.ones(3, complex), centres, chirp)
    grid = ImageGrid(-0.024, 0.024, -0.024, 0.024, 0.3, 24, 24)
    return subimage_basis(data, centres, chirp, grid), centres.mean(axis=1)


def test_the_aperture_polynomial_is_the_monomials_of_the_scaled_coordinates():
    c = np.array([[0.0, 0.0, 0.3], [0.2, 0.1, 0.3], [0.1, 0.3, 0.3], [0.4, 0.5, 0.3]])
    x, y = (c[:, 0] - c[:, 0].mean()) / 0.2, (c[:, 1] - c[:, 1].mean()) / 0.25
    np.testing.assert_allclose(aperture_polynomial(c, 2), np.stack([np.ones(4), y, x, y * y, x * y, x * x], 1))
    assert aperture_polynomial(c[:, :2], 3).shape == (4, 10)
    with pytest.raises(TwinFocusError, match="centres_m"):
        aperture_polynomial(c[:, 0], 2)


def test_a_focused_target_gains_little_and_an_injected_defocus_is_found():
    basis, centres = points_scene()
    gain, coef = defocus_gain_nats(basis, np.zeros(basis.shape[0]), centres)
    assert gain < 0.01 and np.abs(coef).max() < 0.3
    quadratic = aperture_polynomial(centres, 2)[:, 3:]
    for injected in (np.array([2.0, 0.0, 0.0]), np.array([0.0, 1.5, 0.0]), np.array([0.0, 0.0, -1.5])):
        gain, coef = defocus_gain_nats(basis, quadratic @ injected, centres)
        assert gain > 0.1
        np.testing.assert_allclose(coef, -injected, atol=0.3)  # it found the defocus that was put in


def test_the_check_refuses_a_phase_that_does_not_match_the_basis():
    basis, centres = points_scene()
    with pytest.raises(TwinFocusError, match="one phase per position"):
        defocus_gain_nats(basis, np.zeros(basis.shape[0] - 1), centres)


def test_the_report_warns_when_the_target_is_not_at_its_focus():
    from twinfocus.focus.pipeline import MAX_TARGET_DEFOCUS_GAIN_NATS, confidence_report

    pos = phase_centres(paper_raster(6, 10), mmwcas_virtual_array())
    ref = ImageGrid.from_roi([-0.15, 0.0, -0.11, 0.12, 0.6], 20)
    tgt = ImageGrid.from_roi([0.02, 0.13, -0.11, 0.12, 0.6], 20)
    fill = {"energy_inside": 0.9, "contrast": 2.0, "surface": "coherent"}

    def report(gain: float) -> dict:
        m = {"reference_outline": fill, "target_defocus": {"entropy_gain_nats": gain, "quadratic_rad": [0, 0, 0]}}
        return confidence_report(m, pos, Chirp(), ref, tgt, 0.5e-3)

    assert report(MAX_TARGET_DEFOCUS_GAIN_NATS - 0.02)["trusted"]
    flagged = report(MAX_TARGET_DEFOCUS_GAIN_NATS + 0.05)
    assert not flagged["trusted"] and flagged["target_defocus_gain_nats"] == MAX_TARGET_DEFOCUS_GAIN_NATS + 0.05
    (warning,) = flagged["warnings"]
    assert "not at its focus" in warning and "--template-scan" in warning
