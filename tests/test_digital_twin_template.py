"""Template simulation: the sub-pixel PSF convolution against a direct sum, the PSF template
against the exact point-scatterer model, the stereo-made template against the one from the true
points, depth slabs, alignment (registration, offset calibration, loss-based refinement)."""

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.metrics import display_image, ssim
from twinfocus.motion.trajectory import paper_raster, phase_centres
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
from twinfocus.scene import paper_scene
from twinfocus.twins.digital_twin.align import (
    RadarCameraCalibration,
    calibrate_offset,
    refine_template_shift_by_loss,
    register_translation,
    shift_image,
)
from twinfocus.twins.digital_twin.condition import digital_twin_template_from_file
from twinfocus.twins.digital_twin.template import (
    convolve_points,
    digital_twin_template,
    exact_template,
    load_points,
    psf_template,
)

ROI = (-0.15, 0.0, -0.11, 0.12, 0.6)


@pytest.fixture
def one_torch_thread():
    """Small autofocus runs: one torch thread (on a busy 2-core machine two threads wait on each
    other: measured 50x slower for a 120 x 40 x 40 basis)."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def small():
    """A thinned paper aperture (3 columns x 40 rows at 4 mm) and a 40 x 40 reference grid."""
    positions = phase_centres(paper_raster(3, 40, row_pitch_m=0.004), mmwcas_virtual_array())
    grid = ImageGrid.from_roi(ROI, 40)
    scene = paper_scene()
    pts, _ = scene.object("reference").scatterers(1.2e-3, 0, speckle=False)
    return positions, grid, Chirp(), scene, pts


def _corr(a, b):
    return float(np.corrcoef(np.ravel(a), np.ravel(b))[0, 1])


def test_convolve_points_matches_direct_sum():
    rng = np.random.default_rng(0)
    h, w, half = 30, 40, 14

    def psf(dr, dc):  # smooth (effectively band-limited) complex kernel
        return np.exp(-(dr**2 + dc**2) / (2 * 2.5**2) + 1j * (0.3 * dr + 0.2 * dc))

    off = np.arange(-half, half + 1)
    kernel = psf(off[:, None], off[None, :])
    rc = np.stack([rng.uniform(-3, h + 2, 60), rng.uniform(-3, w + 2, 60)], axis=1)
    wts = rng.normal(size=60) + 1j * rng.normal(size=60)
    got = convolve_points(rc, wts, kernel, (h, w))
    rr, cc = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    want = sum(wt * psf(rr - r, cc - c) for (r, c), wt in zip(rc, wts))
    assert np.abs(got - want).max() < 1e-3 * np.abs(want).max()


def test_psf_template_matches_exact_model(small):
    positions, grid, chirp, _, pts = small
    ex = exact_template(pts, positions, chirp, grid)
    ps = psf_template(pts, positions, chirp, grid)
    assert ps.shape == grid.shape and ps.dtype == np.float32
    assert _corr(ps, ex) > 0.97
    assert ssim(display_image(ps), display_image(ex)) > 0.95


def test_depth_slabs_follow_a_tilted_plate(small):
    positions, grid, chirp, _, pts = small
    tilted = pts.copy()
    tilted[:, 2] += 0.15 * (pts[:, 0] - pts[:, 0].mean())  # ~12 mm depth spread across the letter
    ex = exact_template(tilted, positions, chirp, grid)
    ps = psf_template(tilted, positions, chirp, grid, return_info=True)
    assert ps[1].n_slabs >= 3
    assert _corr(ps[0], ex) > 0.95


@pytest.mark.slow  # 2.7 s CPU (2 cores, load ~9): out of make test-fast
def test_stereo_template_matches_truth_template(small):
    from twinfocus.twins.digital_twin.pipeline import reference_from_stereo
    from twinfocus.twins.digital_twin.render import render_scene
    from twinfocus.twins.digital_twin.segment import box_from_scene_roi

    positions, grid, chirp, scene, pts = small
    r = render_scene(scene, seed=5)
    twin = reference_from_stereo(r.left, r.right, r.camera, box_from_scene_roi(ROI, r.camera))
    from_stereo = digital_twin_template(twin.points_m, positions, chirp, grid)
    from_truth = digital_twin_template(pts, positions, chirp, grid)
    assert _corr(from_stereo, from_truth) > 0.9
    assert ssim(display_image(from_stereo), display_image(from_truth)) > 0.9
    dy, dx, _ = register_translation(from_stereo, from_truth)
    assert np.hypot(dy, dx) < 0.5  # pixels (3.8 mm x 5.9 mm here)


def test_template_inputs_and_files(small, tmp_path):
    positions, grid, chirp, _, pts = small
    with pytest.raises(TwinFocusError, match="empty"):
        digital_twin_template(np.zeros((0, 3)), positions, chirp, grid)
    with pytest.raises(TwinFocusError, match="degenerate"):
        digital_twin_template(np.tile(pts[:1], (40, 1)), positions, chirp, grid)
    with pytest.raises(TwinFocusError, match=r"\(N, 3\)"):
        digital_twin_template(pts[:, :2], positions, chirp, grid)
    with pytest.raises(TwinFocusError, match="method"):
        digital_twin_template(pts, positions, chirp, grid, method="raytrace")
    with pytest.raises(TwinFocusError, match="no such point-cloud file"):
        load_points(tmp_path / "none.npy")
    bad = tmp_path / "bad.npy"
    np.save(bad, np.zeros((5, 2)))
    with pytest.raises(TwinFocusError, match="bad.npy"):
        load_points(bad)
    good = tmp_path / "pts.npy"
    np.save(good, pts)

    class _ScanLike:  # only the attributes the function reads
        pass

    scan = _ScanLike()
    scan.positions, scan.chirp = positions, chirp
    from twinfocus.twins.digital_twin.condition import digital_twin_reference

    # The file path conditions the cloud (twinfocus.twins.digital_twin.condition) before the template.
    a = digital_twin_template_from_file(good, scan, grid)
    np.testing.assert_array_equal(a, digital_twin_reference(pts, positions, chirp, grid).template)
    # On exact points the conditioned template is the raw points' template, up to re-sampling.
    assert _corr(a, digital_twin_template(pts, positions, chirp, grid)) > 0.95
    # The calibration's offset moves the template like moving the points.
    cal = RadarCameraCalibration(np.array([0.004, 0.0, 0.0]))
    cal.save(tmp_path / "cal.json")
    b = digital_twin_template_from_file(good, scan, grid, calibration=tmp_path / "cal.json")
    np.testing.assert_allclose(
        b, digital_twin_reference(pts + [0.004, 0, 0], positions, chirp, grid).template, rtol=1e-5, atol=1e-3 * b.max()
    )
    with pytest.raises(TwinFocusError, match="no such radar-camera calibration"):
        digital_twin_template_from_file(good, scan, grid, calibration=tmp_path / "missing.json")


def test_registration_recovers_sub_pixel_shift(small):
    positions, grid, chirp, _, pts = small
    tpl = psf_template(pts, positions, chirp, grid)
    for dy, dx in ((1.3, -2.6), (-0.4, 0.7)):
        moved = shift_image(tpl, dy, dx)
        ey, ex_, resp = register_translation(tpl, moved)
        assert abs(ey - dy) < 0.15 and abs(ex_ - dx) < 0.15 and resp > 0.9
        # and back
        back = register_translation(moved, tpl)
        assert abs(back[0] + dy) < 0.15 and abs(back[1] + dx) < 0.15


def test_offset_calibration_round_trip(small, tmp_path):
    positions, grid, chirp, _, pts = small
    focused = exact_template(pts, positions, chirp, grid)  # what the radar sees: the true place
    camera_pts = pts + [0.006, -0.009, 0.0]  # the camera put it 6 mm right, 9 mm up
    sim = psf_template(camera_pts, positions, chirp, grid)
    cal = calibrate_offset(sim, focused, grid)
    np.testing.assert_allclose(cal.offset_m, [-0.006, 0.009, 0.0], atol=1.0e-3)
    back = RadarCameraCalibration.load(cal.save(tmp_path / "cal.json"))
    np.testing.assert_array_equal(back.offset_m, cal.offset_m)
    with pytest.raises(TwinFocusError, match="do not correlate"):
        calibrate_offset(sim, np.random.default_rng(0).random(grid.shape), grid, min_response=0.5)


@pytest.mark.slow  # 2.4 s x
def test_refinement_by_loss_moves_template_back(small, one_torch_thread):
    from twinfocus.imaging.backprojection.numba_backend import subimage_basis
    from twinfocus.motion.tracking_errors import apply_position_errors, gaussian_errors
    from twinfocus.simulation.if_simulator import simulate_if

    positions, grid, chirp, _, pts = small
    rng = np.random.default_rng(3)
    data = simulate_if(pts, None, positions, chirp)
    tracked = apply_position_errors(positions, gaussian_errors(positions.shape[0], (0.0, 0.0, 0.3e-3), rng))
    basis = subimage_basis(data, tracked, chirp, grid)
    tpl = exact_template(pts, tracked, chirp, grid)
    _, (dy, dx), info = refine_template_shift_by_loss(basis, shift_image(tpl, 0.8, 0.0), iterations=60)
    assert -1.0 <= dy <= -0.3 and abs(dx) < 0.5
    assert len(info["losses"]) == 5
