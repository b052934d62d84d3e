"""A volume formed by sub-arrays equals, plane by plane, the 2-D corrected image at that depth
(the direct back-projection) and the brute-force matched filter; channels off their line fall
back to the direct path."""

import numpy as np
import pytest

from tests.helpers import points_scan
from twinfocus.imaging import line_backprojection as lb
from twinfocus.imaging.backprojection.numba_backend import backproject, matched_filter_bruteforce
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.volume import corrected_image, volume_grid
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array


def _aperture(n_rows=12, pitch=0.006, columns=(-0.06, 0.0, 0.06), yaw_rad=0.0):
    va = mmwcas_virtual_array()
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.array(
        [
            (va.offsets_m - va.offsets_m.mean(axis=0)) @ rot.T + np.array([cx, y, 0.001 * cx])
            for cx in columns
            for y in (np.arange(n_rows) - (n_rows - 1) / 2) * pitch
        ]
    )


POINTS = [np.array([-0.03, 0.01, 0.55]), np.array([0.035, -0.012, 0.64]), np.array([0.0, 0.02, 0.6])]


@pytest.mark.parametrize("yaw", [0.0, 0.5])
def test_every_plane_of_the_volume_equals_the_2d_image_at_its_depth(yaw):
    ch = Chirp()
    pos = _aperture(yaw_rad=yaw)
    data = points_scan(ch, pos, POINTS, [1.0, 0.7, 0.5])
    phase = np.random.default_rng(1).uniform(-0.5, 0.5, pos.shape[0])
    grid = volume_grid(ImageGrid(-0.06, 0.06, -0.05, 0.05, 1.0, 48, 40), 0.52, 0.68, 0.01)
    assert lb.plan(pos, ch, grid) is not None  # the sub-array path is the one taken
    vol = corrected_image(data, pos, ch, grid, phase)
    assert vol.shape == grid.shape and vol.dtype == np.complex64
    peak = np.abs(vol).max()
    for d, z in enumerate(grid.z_m):
        plane = ImageGrid(*grid.plane.roi[:4], z=float(z), height=grid.plane.height, width=grid.plane.width)
        want = corrected_image(data, pos, ch, plane, phase)  # the 2-D focus: direct back-projection
        assert np.abs(vol[d] - want).max() < 5e-3 * peak, z


def test_sub_arrays_match_the_brute_force_matched_filter():
    ch = Chirp(n_samples=64, fs_hz=2e6)
    pos = _aperture(n_rows=3, columns=(-0.03, 0.03), yaw_rad=0.3)
    data = points_scan(ch, pos, POINTS[:2], [1.0, 0.8])
    grid = volume_grid(ImageGrid(-0.04, 0.05, -0.02, 0.02, 1.0, 7, 6), 0.54, 0.66, 0.02)
    frames = lb._line_frames(pos)
    line_plan = lb.LinePlan(ch, grid, frames, lb._box_extent(grid, frames[0], frames[1]), groups=4)
    got = lb.backproject_volume(data, pos, ch, grid, line_plan)
    want = matched_filter_bruteforce(data, pos, ch, grid.points()).reshape(grid.shape)
    assert np.abs(got - want).max() < 5e-3 * np.abs(want).max()


def test_channels_off_their_line_take_the_direct_path():
    ch = Chirp()
    pos = _aperture()
    grid = volume_grid(ImageGrid(-0.06, 0.06, -0.05, 0.05, 1.0, 48, 40), 0.52, 0.68, 0.01)
    bent = pos.copy()
    bent[5, 40, 1] += 1e-4  # one channel of one position 0.1 mm off the line
    assert lb.plan(bent, ch, grid) is None
    data = points_scan(ch, bent, POINTS, [1.0, 0.7, 0.5])
    got = corrected_image(data, bent, ch, grid, np.zeros(len(bent)))
    assert np.array_equal(got, backproject(data, bent, ch, grid))
    # a volume of a few voxels costs more by sub-arrays than directly: the direct path
    tiny = volume_grid(ImageGrid(-0.01, 0.01, -0.01, 0.01, 1.0, 2, 2), 0.55, 0.56, 0.01)
    assert lb.plan(pos, ch, tiny) is None
