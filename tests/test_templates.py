"""twinfocus.templates: the pure resampler against a closed form, and the file reader's errors."""
import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.grid import ImageGrid
from twinfocus.templates import load_template, resample_template, save_template


def _plane(x, y):
    return 5.0 + 30.0 * x[None, :] - 12.0 * y[:, None]  # positive (an amplitude); bilinear resampling is exact on a plane


def test_resample_is_exact_on_a_plane_and_keeps_the_phase():
    x, y = np.linspace(-0.1, 0.1, 41), np.linspace(-0.05, 0.08, 27)
    grid = ImageGrid(-0.07, 0.09, -0.04, 0.06, 0.5, 23, 17)
    amp, phase = _plane(x, y), 0.4 * _plane(x, y)
    out = resample_template(amp, x, y, 0.5, grid, phase_rad=phase)
    assert out.dtype == np.complex64 and out.shape == grid.shape
    want = _plane(grid.x_m, grid.y_m)
    # the complex image is resampled, so its magnitude is exact where the phase is near-linear over a pixel
    np.testing.assert_allclose(resample_template(amp, x, y, 0.5, grid), want, rtol=1e-5)
    np.testing.assert_allclose(np.abs(out), want, rtol=2e-3)
    np.testing.assert_allclose(np.angle(out * np.exp(-1j * 0.4 * want)), 0.0, atol=2e-3)


def test_same_grid_is_returned_as_is_and_the_reader_agrees(tmp_path):
    grid = ImageGrid(-0.05, 0.05, -0.02, 0.03, 0.6, 12, 9)
    img = np.random.default_rng(0).normal(size=grid.shape) * np.exp(1j * np.ones(grid.shape))
    direct = resample_template(np.abs(img), grid.x_m, grid.y_m, grid.z, grid, phase_rad=np.angle(img))
    np.testing.assert_allclose(direct, img.astype(np.complex64), rtol=1e-6)
    save_template(tmp_path / "t.npz", img, grid)
    np.testing.assert_allclose(load_template(tmp_path / "t.npz", grid), direct, rtol=1e-5)  # stored as float32


@pytest.mark.parametrize("change, message", [
    (dict(z_m=0.7), "plane z = 0.700"),
    (dict(image=np.full((5, 6), np.nan)), "NaN"),
    (dict(image=np.ones((4, 6))), "does not match"),
    (dict(x_m=np.linspace(0.0, 0.1, 6)), "does not contain the reference region"),
    (dict(phase_rad=np.ones((2, 2))), "phase_rad"),
])
def test_what_does_not_fit_is_named(tmp_path, change, message):
    grid = ImageGrid(-0.04, 0.04, -0.02, 0.02, 0.5, 8, 4)
    args = dict(image=np.ones((5, 6)), x_m=np.linspace(-0.05, 0.05, 6), y_m=np.linspace(-0.03, 0.03, 5), z_m=0.5,
                phase_rad=None)
    args.update(change)
    with pytest.raises(TwinFocusError, match=message):
        resample_template(grid=grid, **args)
    # the file reader says the same, with the file's name first
    np.savez(tmp_path / "bad.npz", **{k: v for k, v in args.items() if v is not None})
    with pytest.raises(TwinFocusError, match=f"bad.npz: .*{message}"):
        load_template(tmp_path / "bad.npz", grid)
