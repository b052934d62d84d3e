"""twinfocus.imaging.subpixel against closed forms: a quadratic's vertex, whole-pixel shifts as rolls."""

from __future__ import annotations

import numpy as np
import pytest

from twinfocus.imaging.subpixel import parabola_vertex, shift_image


@pytest.mark.parametrize("x0", [-0.4, -0.1, 0.0, 0.25, 0.49])
@pytest.mark.parametrize("a", [-2.0, 3.0])  # a maximum and a minimum
def test_parabola_vertex_is_exact_on_a_quadratic(x0, a):
    f = lambda x: a * (x - x0) ** 2 + 1.5  # noqa: E731
    assert parabola_vertex(f(-1.0), f(0.0), f(1.0)) == pytest.approx(x0, abs=1e-12)


def test_parabola_vertex_on_a_line_and_beyond_the_limit():
    assert parabola_vertex(1.0, 2.0, 3.0) == 0.0
    # vertex of 0.1 (x - 3)^2 lies at +3: clipped to the limit asked for
    f = lambda x: 0.1 * (x - 3.0) ** 2  # noqa: E731
    assert parabola_vertex(f(-1.0), f(0.0), f(1.0), limit=1.0) == 1.0


def test_whole_pixel_shift_is_a_zero_filled_roll():
    rng = np.random.default_rng(3)
    img = (rng.standard_normal((12, 14)) + 1j * rng.standard_normal((12, 14))).astype(np.complex64)
    moved = shift_image(img, 2, -3)
    expect = np.zeros_like(img)
    expect[2:, :-3] = img[:-2, 3:]
    assert moved.dtype == np.complex64
    np.testing.assert_allclose(moved, expect, atol=1e-5)


def test_non_negative_image_stays_non_negative():
    img = np.zeros((9, 9), np.float32)
    img[4, 4] = 1.0  # a spike: the cubic spline overshoots below zero beside it
    moved = shift_image(img, 0.5, 0.3)
    assert moved.dtype == np.float32 and moved.min() >= 0.0 and moved.max() > 0.2
