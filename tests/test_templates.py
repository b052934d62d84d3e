"""twinfocus.twins.templates: the pure resamplers against a closed form, and the file reader's errors."""

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.grid import ImageGrid
from twinfocus.twins.templates import load_template, resample_support, resample_template, save_template


def _plane(x, y):
    return (
        5.0 + 30.0 * x[None, :] - 12.0 * y[:, None]
    )  # positive (an amplitude); bilinear resampling is exact on a plane


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


def test_a_digital_twins_outline_and_conditioning_travel_with_its_template_file(tmp_path):
    """The outline and the conditioning written with the template come back: the outline as it
    was on the same grid and as resample_support makes it on another, the conditioning as written;
    a file without them gives None for both; an outline that holds none of the region is named."""
    grid = ImageGrid(-0.05, 0.05, -0.02, 0.03, 0.6, 12, 9)
    yy, xx = np.meshgrid(grid.y_m, grid.x_m, indexing="ij")
    support = np.hypot(xx, yy - 0.005) < 0.025
    info = {"surface": "outline", "curved": True, "curvature_m": 0.0021, "warnings": ["noisy"]}
    image = np.random.default_rng(1).random(grid.shape)
    save_template(tmp_path / "d.npz", image, grid, support=support, info=info)
    back, outline, conditioning = load_template(tmp_path / "d.npz", grid, with_outline=True)
    np.testing.assert_allclose(back, image.astype(np.float32))
    assert outline.dtype == bool and np.array_equal(outline, support) and conditioning == info
    other = ImageGrid(-0.04, 0.04, -0.015, 0.025, 0.6, 7, 5)
    _, outline, _ = load_template(tmp_path / "d.npz", other, with_outline=True)
    assert np.array_equal(outline, resample_support(support, grid.x_m, grid.y_m, other))
    save_template(tmp_path / "a.npz", image, grid)
    assert load_template(tmp_path / "a.npz", grid, with_outline=True)[1:] == (None, None)
    with pytest.raises(TwinFocusError, match="template support is"):
        save_template(tmp_path / "bad.npz", image, grid, support=support[:, 1:])
    save_template(tmp_path / "empty.npz", image, grid, support=np.zeros(grid.shape, bool))
    with pytest.raises(TwinFocusError, match=r"empty.npz: the outline covers 0% of the reference region"):
        load_template(tmp_path / "empty.npz", grid, with_outline=True)
    arrays = {"image": image, "x_m": grid.x_m, "y_m": grid.y_m, "z_m": grid.z}
    for text, message in (
        ("{surface", "conditioning_json is not JSON"),
        ("[1, 2]", "conditioning_json must be a JSON object, got list"),
    ):
        np.savez(tmp_path / "info.npz", conditioning_json=np.asarray(text), **arrays)
        with pytest.raises(TwinFocusError, match=f"info.npz: {message}"):
            load_template(tmp_path / "info.npz", grid, with_outline=True)


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(z_m=0.7), "plane z = 0.700"),
        (dict(image=np.full((5, 6), np.nan)), "NaN"),
        (dict(image=np.ones((4, 6))), "does not match"),
        (dict(x_m=np.linspace(0.0, 0.1, 6)), "does not contain the reference region"),
        (dict(phase_rad=np.ones((2, 2))), "phase_rad"),
    ],
)
def test_what_does_not_fit_is_named(tmp_path, change, message):
    grid = ImageGrid(-0.04, 0.04, -0.02, 0.02, 0.5, 8, 4)
    args = dict(
        image=np.ones((5, 6)), x_m=np.linspace(-0.05, 0.05, 6), y_m=np.linspace(-0.03, 0.03, 5), z_m=0.5, phase_rad=None
    )
    args.update(change)
    with pytest.raises(TwinFocusError, match=message):
        resample_template(grid=grid, **args)
    # the file reader says the same, with the file's name first
    np.savez(tmp_path / "bad.npz", **{k: v for k, v in args.items() if v is not None})
    with pytest.raises(TwinFocusError, match=f"bad.npz: .*{message}"):
        load_template(tmp_path / "bad.npz", grid)


def test_an_outline_resampled_stays_a_mask_of_the_same_shape():
    """A disc's mask on a fine grid, resampled onto a coarser one that it covers: a bool mask equal
    to the disc drawn on the coarse grid itself, except on pixels within a fine pixel of its edge."""
    x, y = np.linspace(-0.1, 0.1, 201), np.linspace(-0.08, 0.08, 161)  # 1 mm pixels
    radius = 0.04

    def disc(xs, ys):
        return np.hypot(xs[None, :] - 0.01, ys[:, None] + 0.005) <= radius

    grid = ImageGrid(-0.07, 0.09, -0.06, 0.05, 0.5, 33, 23)
    out = resample_support(disc(x, y), x, y, grid)
    assert out.dtype == bool and out.shape == grid.shape
    edge = np.abs(np.hypot(grid.x_m[None, :] - 0.01, grid.y_m[:, None] + 0.005) - radius) < 1.5e-3
    want = disc(grid.x_m, grid.y_m)
    assert np.array_equal(out[~edge], want[~edge]) and 0 < edge.sum() < 0.2 * edge.size
    same = ImageGrid(-0.1, 0.1, -0.08, 0.08, 0.5, 161, 201)  # height, width
    assert np.array_equal(resample_support(disc(x, y), x, y, same), disc(x, y))


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(support=np.ones((4, 6), bool)), r"support \(4, 6\) does not match y_m \(5\) x x_m \(6\)"),
        (dict(support=np.ones((5, 6), np.uint8)), "support must be a bool mask, got uint8"),
        (dict(x_m=np.linspace(0.0, 0.1, 6)), "does not contain the reference region"),
    ],
)
def test_what_does_not_fit_an_outline_is_named(change, message):
    grid = ImageGrid(-0.04, 0.04, -0.02, 0.02, 0.5, 8, 4)
    args = dict(support=np.ones((5, 6), bool), x_m=np.linspace(-0.05, 0.05, 6), y_m=np.linspace(-0.03, 0.03, 5))
    args.update(change)
    with pytest.raises(TwinFocusError, match=message):
        resample_support(grid=grid, **args)
