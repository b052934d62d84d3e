"""Cloud conditioning (twinfocus.twins.digital_twin.condition) against clouds of known truth: exact
surfaces impaired by camera_cloud, so the right surface, outline and removed points are known."""

import json
import warnings

import numpy as np
import pytest
from scipy.interpolate import griddata

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.grid import ImageGrid
from twinfocus.motion.trajectory import paper_raster, phase_centres
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
from twinfocus.simulation.scenario import Scenario
from twinfocus.twins.digital_twin.camera_cloud import camera_cloud
from twinfocus.twins.digital_twin.condition import (
    CloudWarning,
    ConditionConfig,
    condition_cloud,
    digital_twin_reference,
    support_on_grid,
)


def _case(shape="plane"):
    sc = Scenario(reference_shape=shape)
    grid = ImageGrid.from_roi(sc.reference_roi(), 100)
    exact = sc.scene().object("reference").surface_points(0.5e-3)
    return grid, exact


def _depth_error(points, exact):
    """|z| of each point off the exact surface at its x, y (nearest exact sample), metres."""
    return np.abs(points[:, 2] - griddata(exact[:, :2], exact[:, 2], points[:, :2], method="nearest"))


@pytest.mark.parametrize(
    "shape,surface,tol_mm", [("plane", "plane", 0.15), ("cylinder", "smooth", 0.35), ("bent", "smooth", 0.6)]
)
def test_surface_model_fits_the_true_surface(shape, surface, tol_mm):
    grid, exact = _case(shape)
    # The field-like scene B's camera: 1 mm depth noise, 0.3 mm across, a quarter missing, 3 % outliers.
    cloud = camera_cloud(exact[::4], (0.3e-3, 0.3e-3, 1e-3), 0.25, 0.03, 0.0, rng=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CloudWarning)  # nothing here deserves a warning
        r = condition_cloud(cloud, grid)
    assert r.surface == surface, r.info["surface_reason"]
    assert r.info["curved"] == (shape != "plane")  # what the confidence report reads
    err = _depth_error(r.points_m, exact)
    # Raw points are off by 1 mm sd (3 rad of phase); the model by far less.
    assert np.mean(err) < tol_mm * 1e-3
    assert np.mean(_depth_error(cloud, exact)) > 0.7e-3
    assert abs(r.info["noise_sd_m"] - 1e-3) < 0.2e-3  # measured noise = the noise put in
    json.dumps(r.info)  # goes into metrics.json as it is


def test_outliers_removed_and_outline_recovered():
    grid, exact = _case()
    truth = support_on_grid(exact, grid)
    cloud, t = camera_cloud(exact[::4], (0.3e-3, 0.3e-3, 1e-3), 0.0, 0.05, 0.0, rng=2, return_truth=True)
    r = condition_cloud(cloud, grid)
    removed = r.info["isolated_outliers"] + r.info["surface_outliers"]
    assert removed >= 0.9 * t["outlier"].sum()
    # Model points stay on the reference: within a cell (2 mm) + noise, except in concave corners
    # that the outline's closing (6 mm radius) rounds off.
    from scipy.spatial import cKDTree

    d, _ = cKDTree(exact[:, :2]).query(r.points_m[:, :2])
    assert np.percentile(d, 95) < 2.5e-3 and np.percentile(d, 99) < 3.5e-3 and d.max() < 6e-3
    s = support_on_grid(r.points_m, grid)
    iou = (s & truth).sum() / (s | truth).sum()
    assert iou > 0.85
    # The letter's counter (a large enclosed hole, ~9 cm2) is kept, not filled as a camera hole.
    from scipy import ndimage

    counter = ndimage.binary_fill_holes(truth) & ~truth
    # (its rim is narrowed by the outline's dilation and rounded corners; filled, it would be all covered)
    assert counter.sum() > 100 and (s & counter).sum() < 0.4 * counter.sum()


def test_camera_holes_are_filled_when_enclosed():
    from twinfocus.scene import card

    obj = card((-0.07, 0.0, 0.6))
    grid = ImageGrid.from_roi((-0.13, -0.01, -0.05, 0.05, 0.6), 80)
    exact = obj.surface_points(1e-3)
    truth = support_on_grid(exact, grid)
    # One 2 cm hole in the middle of the card: an enclosed camera hole.
    hole = np.hypot(exact[:, 0] + 0.07, exact[:, 1]) < 0.01
    r = condition_cloud(exact[~hole] + np.random.default_rng(0).normal(size=(int((~hole).sum()), 3)) * 0.5e-3, grid)
    s = support_on_grid(r.points_m, grid)
    assert (s & truth).sum() / (s | truth).sum() > 0.9
    assert r.info["holes_filled_fraction"] > 0.02


def test_too_noisy_for_phase_falls_back_to_outline_and_forced_models():
    grid, exact = _case("cylinder")
    # A sparse (3 mm) cloud with 4 mm noise: the curved surface is not known to within a radian.
    sparse = exact[::36]
    cloud = sparse + np.random.default_rng(3).normal(size=sparse.shape) * 4e-3
    r = condition_cloud(cloud, grid)
    assert r.surface == "outline" and "rad" in r.info["surface_reason"]
    assert r.info["model_phase_sd_rad"] > 1.0
    f = condition_cloud(exact[::4], grid, config=ConditionConfig(surface="outline"))
    assert f.surface == "outline" and f.info["surface_reason"] == "asked for"
    with pytest.raises(TwinFocusError, match="surface model"):
        condition_cloud(exact, grid, config=ConditionConfig(surface="mesh"))


def _aperture():
    return phase_centres(paper_raster(3, 40, row_pitch_m=0.004), mmwcas_virtual_array())


def test_reference_result_template_support_offset():
    grid, exact = _case()
    grid = ImageGrid.from_roi(grid.roi, 40)
    pos, chirp = _aperture(), Chirp()
    cloud = camera_cloud(exact[::4], 0.5e-3, 0.1, 0.01, 0.0, rng=4)
    ref = digital_twin_reference(cloud, pos, chirp, grid)
    assert ref.template.shape == ref.support.shape == grid.shape and ref.support.dtype == bool
    assert ref.template.dtype == np.float32
    # The template's energy lies on the support (the outline the mask says).
    inside = (ref.template[ref.support] ** 2).sum() / (ref.template**2).sum()
    assert inside > 0.7
    assert ref.info["template_coherent"] is True and ref.surface == "plane"
    json.dumps(ref.info)
    # A calibration offset moves the conditioned points by exactly that offset.
    off = np.array([0.003, -0.002, 0.001])
    moved = digital_twin_reference(cloud, pos, chirp, grid, offset_m=off)
    np.testing.assert_allclose(moved.cloud.points_m.mean(0) - ref.cloud.points_m.mean(0), off, atol=2e-4)
    outline = digital_twin_reference(cloud, pos, chirp, grid, config=ConditionConfig(surface="outline"))
    assert outline.info["template_coherent"] is False


# --- stability at the extremes -----------------------------------------------------------------------


def test_ten_points_is_a_clear_error():
    grid, exact = _case()
    with pytest.raises(TwinFocusError, match="only 10 finite points"):
        condition_cloud(exact[:10], grid)


def test_cloud_entirely_outside_the_region_is_a_clear_error():
    grid, exact = _case()
    with pytest.raises(TwinFocusError, match="entirely outside the reference region"):
        condition_cloud(exact + [0.5, 0.0, 0.0], grid)
    # millimetres instead of metres: also outside, and the message suggests units
    with pytest.raises(TwinFocusError, match="units"):
        condition_cloud(exact * 1000.0, grid)


def test_points_on_a_line_is_a_clear_error():
    grid, _ = _case()
    t = np.linspace(0, 0.1, 500)
    line = np.stack([-0.12 + t, np.zeros_like(t), np.full_like(t, 0.6)], axis=1)
    with pytest.raises(TwinFocusError, match="degenerate"):
        condition_cloud(line, grid)


def test_nan_rows_are_dropped_with_a_warning_and_do_not_change_the_result():
    grid, exact = _case()
    cloud = camera_cloud(exact[::4], 0.5e-3, 0.1, 0.0, 0.0, rng=5)
    bad = cloud.copy()
    bad[::50, 1] = np.nan
    bad[7, 2] = np.inf
    n_bad = int((~np.isfinite(bad).all(1)).sum())
    with pytest.warns(CloudWarning, match=f"dropped {n_bad} of {bad.shape[0]} rows"):
        r = condition_cloud(bad, grid)
    assert r.info["non_finite_rows"] == n_bad and len(r.warnings) == 1
    clean = condition_cloud(bad[np.isfinite(bad).all(1)], grid)
    np.testing.assert_array_equal(r.points_m, clean.points_m)
    with pytest.raises(TwinFocusError, match="finite points"), pytest.warns(CloudWarning):
        condition_cloud(np.full((100, 3), np.nan), grid)


@pytest.mark.slow  # 2.7 s CPU (2 cores, load ~9): out of make test-fast
def test_million_points_thinned_same_answer():
    grid, exact = _case()
    rng = np.random.default_rng(6)
    big = exact[rng.integers(0, exact.shape[0], 1_000_000)] + rng.normal(size=(1_000_000, 3)) * 1e-3
    r = condition_cloud(big, grid)
    assert r.info["input_points"] == 1_000_000 and r.info["subsampled_to"] == ConditionConfig().max_points
    assert r.surface == "plane" and abs(r.info["noise_sd_m"] - 1e-3) < 0.1e-3
    assert np.mean(_depth_error(r.points_m, exact)) < 0.05e-3


def test_not_a_cloud():
    grid, _ = _case()
    for bad in (np.zeros((5, 2)), np.zeros((0, 3)), np.array([["a", "b", "c"]])):
        with pytest.raises(TwinFocusError):
            condition_cloud(bad, grid)
