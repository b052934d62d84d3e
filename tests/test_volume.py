"""Corrected volumes: the phase applied to the samples equals the phase applied to the basis,
points land in the voxels where they are, the PLY reads back, and ``focus --volume`` writes
what it promises after checking what it will cost."""

import numpy as np
import pytest

from tests.helpers import REF_ROI, aperture, cli, metrics, points_scan
from twinfocus.cli.focus import volume_plan
from twinfocus.errors import TwinFocusError
from twinfocus.imaging.backprojection.numba_backend import subimage_basis
from twinfocus.imaging.basis import form_image
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.line_backprojection import TABLE_BYTES
from twinfocus.imaging.volume import (
    bright_voxels,
    corrected_data,
    corrected_image,
    projections,
    volume_cost,
    volume_grid,
)
from twinfocus.io.arrays import ply_bytes, read_ply_points
from twinfocus.radar.fmcw import Chirp


def test_phase_on_the_samples_equals_phase_on_the_basis():
    ch = Chirp()
    pos = aperture(n_rows=8)
    data = points_scan(ch, pos, [np.array([0.01, 0.0, 0.5])], [1.0])
    phase = np.random.default_rng(0).uniform(-np.pi, np.pi, pos.shape[0])
    grid = ImageGrid(-0.02, 0.04, -0.03, 0.03, 0.5, 9, 7)
    want = form_image(subimage_basis(data, pos, ch, grid), phase)
    got = corrected_image(data, pos, ch, grid, phase)
    assert np.abs(got - want).max() < 1e-4 * np.abs(want).max()
    with pytest.raises(TwinFocusError, match="one value per radar position"):
        corrected_data(data, phase[:-1])


def test_volume_grid_planes():
    plane = ImageGrid(-0.1, 0.1, -0.1, 0.1, 1.0, 4, 5)
    g = volume_grid(plane, 0.5, 0.7, 0.005)
    assert g.shape == (41, 4, 5) and g.z_m[0] == 0.5 and g.z_m[-1] == pytest.approx(0.7)
    assert volume_grid(plane, 0.5, 0.52, 0.03).shape[0] == 1
    for bad in ((0.7, 0.5, 0.01), (0.5, 0.7, 0.0), (0.0, 0.7, 0.01), (0.5, np.inf, 0.01)):
        with pytest.raises(TwinFocusError):
            volume_grid(plane, *bad)
    cost = volume_cost(g, n_positions=100, n_channels=86)
    assert cost["voxels"] == 41 * 20 and cost["memory_bytes"] == 64 * 41 * 20 + TABLE_BYTES
    assert cost["seconds_estimate"] == pytest.approx(1.1e-8 * 41 * 20 * 100 * 86)


def test_two_points_at_two_depths_land_in_their_voxels(tmp_path):
    ch = Chirp()
    pos = aperture(n_rows=16)
    pts = [np.array([-0.03, 0.01, 0.55]), np.array([0.03, -0.01, 0.65])]
    data = points_scan(ch, pos, pts, [1.0, 1.0])
    plane = ImageGrid(-0.06, 0.06, -0.04, 0.04, 1.0, 25, 17)  # 5 mm pixels
    grid = volume_grid(plane, 0.5, 0.7, 0.01)
    vol = corrected_image(data, pos, ch, grid, np.zeros(pos.shape[0]))
    assert vol.shape == grid.shape and vol.dtype == np.complex64
    mip, depth = projections(vol, grid)
    for p in pts:
        i, j = np.round(plane.index_of(p[0], p[1])).astype(int)
        assert depth[i, j] == pytest.approx(p[2], abs=0.0101)
        assert mip[i, j] > 0.5 * mip.max()
    assert np.isnan(depth).sum() > 0.5 * depth.size  # away from the points: blank
    cloud, values = bright_voxels(vol, grid, threshold_db=-3.0)
    assert 2 <= len(cloud) < 0.01 * vol.size and values.max() == pytest.approx(1.0)
    for p in pts:  # each point's brightest voxel is in the cloud, within a voxel of the point
        assert np.abs(cloud - p).max(axis=1).min() <= 0.0051
    (tmp_path / "v.ply").write_bytes(ply_bytes(cloud, values))
    back, vals = read_ply_points(tmp_path / "v.ply")
    assert np.array_equal(back, cloud) and np.array_equal(vals, values)
    o3d = pytest.importorskip("open3d")
    pc = o3d.io.read_point_cloud(str(tmp_path / "v.ply"))
    assert np.allclose(np.asarray(pc.points), cloud, atol=1e-6)


def _args(**kw):
    import argparse

    base = dict(
        volume=[0.5, 0.7, 0.005],
        target_roi=["0.0", "0.1", "-0.1", "0.1"],
        reference_roi=[-0.15, 0.0, -0.11, 0.12, 0.6],
        size=100,
    )
    return argparse.Namespace(**{**base, **kw})


def test_volume_plan_covers_both_regions_and_refuses_what_cannot_fit(monkeypatch):
    grid, cost = volume_plan(_args(), n_positions=780, n_channels=86)
    assert grid.shape == (41, 100, 100)
    assert (grid.plane.x0, grid.plane.x1, grid.plane.y0, grid.plane.y1) == (-0.15, 0.1, -0.11, 0.12)
    assert cost["memory_bytes"] == 64 * 41 * 100 * 100 + TABLE_BYTES
    import twinfocus.jobs.machine

    monkeypatch.setattr(twinfocus.jobs.machine, "available_memory_bytes", lambda: 100 * 2**20)
    with pytest.raises(TwinFocusError, match="--volume"):
        volume_plan(_args(size=200), n_positions=780, n_channels=86)
    assert volume_plan(_args(volume=None), 780, 86) is None


@pytest.mark.slow
def test_focus_writes_the_volume(deep_scene, tmp_path):
    d, out = deep_scene, tmp_path / "out"
    rois = ("--reference-roi", *REF_ROI, "--target-roi 0.016 0.103 -0.0785 0.0785 0.68")
    options = "--size 40 --iterations 150 --space-variant off --quiet --no-cache"
    volume = "--volume 0.55 0.73 0.01"
    assert cli("focus", d / "scan.npz", *rois, options, "--template-scan", d / "tpl.npz", "--out", out, volume) == 0
    vol = np.load(out / "volume.npy")
    m = metrics(out)["volume"]
    assert vol.shape == tuple(m["shape"]) == (19, 40, 40) and vol.dtype == np.complex64
    for name in ("volume.ply", "volume_mip.png", "volume_depth.png"):
        assert (out / name).is_file()
    assert m["files"] == {"volume": "volume.npy", "points": "volume.ply", "foxglove": "volume.mcap"}
    assert m["sub_arrays"] is None or m["sub_arrays"] >= 1
    from mcap.reader import make_reader

    with open(out / "volume.mcap", "rb") as f:  # one cloud of the PLY's points on /volume/points
        summary = make_reader(f).get_summary()
    (channel,) = summary.channels.values()
    assert channel.topic == "/volume/points" and summary.statistics.channel_message_counts[channel.id] == 1
    assert m["points"] == len(read_ply_points(out / "volume.ply")[0]) > 0
    # the reference letter (x < 0) is brightest near 0.60 m, the target (x > 0.016) near 0.68 m
    plane = ImageGrid(*m["roi"], z=1.0, height=40, width=40)
    z = np.linspace(*m["z_m"], vol.shape[0])
    mag = np.abs(vol)
    left, right = plane.x_m < -0.01, plane.x_m > 0.02
    assert z[mag[:, :, left].max(axis=(1, 2)).argmax()] == pytest.approx(0.60, abs=0.011)
    assert z[mag[:, :, right].max(axis=(1, 2)).argmax()] == pytest.approx(0.68, abs=0.011)
    cloud, _ = read_ply_points(out / "volume.ply")
    assert len(cloud) > 0 and cloud[:, 2].min() >= 0.55 - 1e-6
    # a run without --volume into the same folder (--overwrite) leaves no volume of the earlier result
    assert cli("focus", d / "scan.npz", *rois, "--size 16 --method none --out", out, "--quiet --overwrite") == 0
    assert not [p.name for p in out.glob("volume*")]
