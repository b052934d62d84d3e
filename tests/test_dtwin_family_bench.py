"""The family bench's placement measure (benchmarks/bench_dtwin_family.py), which docs/digital_twin_field.md
quotes: against an injected misplacement and an injected image shift."""

from types import SimpleNamespace

import numpy as np

from benchmarks.bench_dtwin_family import placement
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.metrics import oracle_phase
from twinfocus.imaging.subpixel import shift_image
from twinfocus.radar.fmcw import Chirp


def test_placement_reads_an_injected_ramp_as_its_shift_and_finds_an_injected_image_shift():
    rng = np.random.default_rng(5)
    chirp = Chirp()
    # 12 x 10 positions 4 mm apart, 3 channels each along x, tracked to 0.3 mm
    gx, gy = np.meshgrid(np.arange(12) * 4e-3, np.arange(10) * 4e-3)
    centres = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    channels = np.array([[-2e-3, 0, 0], [0, 0, 0], [2e-3, 0, 0]])
    tracked = centres[:, None, :] + channels[None]
    true = tracked + rng.normal(0, 0.3e-3, tracked.shape)
    grid = ImageGrid.from_roi([-0.03, 0.03, -0.03, 0.03, 0.6], 32)
    yy, xx = np.mgrid[:32, :32]
    truth = (np.exp(-((yy - 16.0) ** 2 + (xx - 14.0) ** 2) / 20.0) * np.exp(1j * 0.3 * xx)).astype(np.complex64)
    # the truth's phase plus a ramp that stands for a known image shift (b R / k)
    slope = np.array([-6.0, 9.0])  # rad/m across x, y
    range_m = 0.6
    shift_m = slope * range_m * chirp.wavelength_m / (4 * np.pi)
    phase = oracle_phase(true, tracked, grid.centre_m, chirp) + (centres[:, :2] - centres[:, :2].mean(0)) @ slope + 0.7
    d = {
        "scan": SimpleNamespace(positions=tracked, positions_true=true, chirp=chirp),
        "rg": grid,
        "truth": SimpleNamespace(target=truth),
    }
    out = SimpleNamespace(
        phase_rad=phase, target=shift_image(truth, 1.0, -0.5), metrics={"estimator": {"phase_coherence_sqrt_m": 3.2}}
    )
    got = placement(d, out)
    assert np.allclose(got["error_mm"], shift_m * 1e3, atol=0.01)
    assert got["best_shift_px"] == [-1.0, 0.5] and got["best_shift_ssim"] > 0.99
    assert got["phase_coherence_sqrt_m"] == 3.2


def test_cloud_parts_gives_each_impairment_alone_and_two_views_under_one_offset(monkeypatch):
    from scipy.spatial import cKDTree

    import benchmarks.bench_dtwin_family as bench
    import twinfocus.twins.digital_twin.condition as condition
    from twinfocus.simulation.scenario import Scenario

    # seed 1003's offset lies mostly along z, across the reference's plane, where a view shows it
    kw = bench.family_scenario("paper", 1003, bench.BENCH_SHAPES, 65)
    surface = Scenario(**kw).scene().object("reference").surface_points(1e-3)
    seen = {}

    def twin(cloud, positions, chirp, grid):
        seen[bench.CLOUD_PARTS[len(seen)]] = np.asarray(cloud)
        return SimpleNamespace(cloud=cloud)

    monkeypatch.setattr(condition, "digital_twin_reference", twin)
    monkeypatch.setattr(
        bench,
        "digital_twin_focus",
        lambda d: SimpleNamespace(metrics={"target_ssim_corrected": float(len(d["twin"].cloud))}),
    )
    d = {"kw": kw, "scan": SimpleNamespace(positions=None, chirp=None), "rg": None, "reference_points": surface}
    got = bench.cloud_parts(d)
    assert list(got) == list(bench.CLOUD_PARTS) == list(seen)
    n = surface.shape[0]
    assert np.array_equal(seen["exact"], surface)
    # one impairment each: the noise moves every point (1 mm per axis) and drops none; the holes
    # drop a quarter and move none; the offset moves all by one vector of the drawn length
    noise = seen["noise only"] - surface
    assert seen["noise only"].shape == surface.shape and 0.8e-3 < noise.std() < 1.2e-3
    holes = seen["holes only"]
    assert abs(holes.shape[0] - 0.75 * n) <= 1 and cKDTree(surface).query(holes)[0].max() < 1e-12
    offset = seen["offset only"] - surface
    assert np.allclose(offset, offset[0]) and 2e-3 <= np.linalg.norm(offset[0]) <= 3e-3
    assert abs(offset[0, 2]) > 2e-3
    # two views: twice the kept points and their outliers, each view moved by that one offset
    two = seen["two views"]
    assert abs(two.shape[0] - 2 * 0.75 * n * 1.02) < 0.02 * n
    for view in (two[: two.shape[0] // 2], two[two.shape[0] // 2 :]):
        assert abs(np.median(view[:, 2]) - np.median(surface[:, 2]) - offset[0, 2]) < 0.3e-3
