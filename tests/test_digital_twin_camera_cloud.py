import numpy as np
import pytest
from scipy.spatial import cKDTree

from twinfocus.errors import TwinFocusError
from twinfocus.scene import rectangle
from twinfocus.twins.digital_twin.camera_cloud import OUTLIER_MARGIN_M, camera_cloud


def _plate(spacing=1e-3):
    return rectangle(0.12, 0.10, (-0.05, 0.0, 0.6)).surface_points(spacing)


def test_noise_sd_per_axis_matches_request():
    p = _plate()
    sd = np.array([0.5e-3, 0.8e-3, 2e-3])
    cloud, truth = camera_cloud(p, sd, 0.0, 0.0, 0.0, rng=1, return_truth=True)
    err = cloud - p[truth["kept"]] - truth["offset_m"]
    np.testing.assert_allclose(err.std(axis=0), sd, rtol=0.05)
    np.testing.assert_allclose(err.mean(axis=0), 0.0, atol=1e-4)


@pytest.mark.parametrize("holes", [0.1, 0.25, 0.4])
def test_hole_fraction_is_surface_missing_in_patches(holes):
    p = _plate()
    cloud = camera_cloud(p, 0.0, holes, 0.0, 0.0, rng=2)
    # Independent measure: surface points with no cloud point within half the spacing.
    d, _ = cKDTree(cloud).query(p)
    missing = d > 0.5e-3
    assert abs(missing.mean() - holes) < 0.005
    # In patches, not scattered: most missing points have missing neighbours on all sides.
    _, idx = cKDTree(p).query(p[missing], k=5)
    assert missing[idx[:, 1:]].mean() > 0.85


def test_outlier_fraction_and_spread():
    p = _plate()
    cloud, truth = camera_cloud(p, 0.0, 0.0, 0.05, 0.0, rng=3, return_truth=True)
    # Independent count: points farther than 3 mm from the exact surface.
    d, _ = cKDTree(p).query(cloud)
    far = d > 3e-3
    assert abs(far.mean() - 0.05) < 0.01  # a few outliers land near the plate by chance
    out = cloud[truth["outlier"]]
    lo, hi = p.min(0) - OUTLIER_MARGIN_M, p.max(0) + OUTLIER_MARGIN_M
    assert np.all(out >= lo) and np.all(out <= hi)
    assert out[:, 2].std() > 0.005  # spread in depth too, not on the plate


def test_offset_length_and_vector():
    p = _plate()
    cloud = camera_cloud(p, 0.0, 0.0, 0.0, 2.5e-3, rng=4)
    shift = cloud - p
    np.testing.assert_allclose(np.linalg.norm(shift, axis=1), 2.5e-3, rtol=1e-9)
    assert np.allclose(shift, shift[0])  # rigid
    v = np.array([1e-3, -2e-3, 0.5e-3])
    np.testing.assert_allclose(camera_cloud(p, 0.0, 0.0, 0.0, v, rng=4) - p, np.broadcast_to(v, p.shape), atol=1e-12)


def test_seeded_and_bad_inputs():
    p = _plate(3e-3)
    np.testing.assert_array_equal(camera_cloud(p, rng=7), camera_cloud(p, rng=7))
    for kw in (
        {"hole_fraction": 1.0},
        {"outlier_fraction": 0.6},
        {"noise_m": -1e-3},
        {"offset_m": [1, 2]},
        {"noise_m": float("nan")},
    ):
        with pytest.raises(TwinFocusError):
            camera_cloud(p, **kw)
    with pytest.raises(TwinFocusError, match="NaN"):
        camera_cloud(np.array([[0, 0, np.nan]]))
