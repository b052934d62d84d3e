"""The target's depth from the scan: point scatterers at a known depth under injected phase
errors, and ``twinfocus focus`` without the target's depth on a simulated scene whose target
lies 8 cm behind the reference."""

import numpy as np
import pytest

from tests.helpers import REF_ROI, aperture, cli, metrics, points_scan
from twinfocus.errors import TwinFocusError
from twinfocus.imaging.depth_search import default_range, parse_depth, search_depth, sharpness_score
from twinfocus.radar.fmcw import Chirp
from twinfocus.simulation.scenario import Scenario, planar_object


def test_sharpness_prefers_the_concentrated_image_of_equal_energy():
    spread = np.ones((1, 4, 4)) / 4.0  # energy 1 over 16 pixels
    point = np.zeros((1, 4, 4))
    point[0, 1, 2] = 1.0  # energy 1 in one pixel
    assert sharpness_score(point)[0] == pytest.approx(1.0)
    assert sharpness_score(spread)[0] == pytest.approx(16 / 256)


@pytest.mark.slow  # 12 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
@pytest.mark.parametrize("depth", [0.57, 0.634])
def test_depth_of_a_flat_group_of_points_under_phase_errors(depth):
    ch = Chirp()
    pos = aperture(n_rows=20)
    pts = np.array([[0.01, 0.0, depth], [0.03, 0.02, depth], [0.02, -0.015, depth]])
    rng = np.random.default_rng(1)
    err = rng.uniform(-np.pi, np.pi, pos.shape[0])  # a phase error per position: the image is lost
    data = points_scan(ch, pos, pts, [1.0] * len(pts)) * np.exp(1j * err)[:, None, None].astype(np.complex64)
    box = (-0.01, 0.05, -0.03, 0.04)
    found = search_depth(data, pos, ch, box, (0.45, 0.8), -err, size=24)
    # to within a tenth of the range resolution (3.9 mm)
    assert abs(found.depth_m - depth) < 0.1 * ch.range_resolution_m
    assert not found.at_edge and found.contrast > 10
    assert found.coarse_z_m[0] == 0.45 and found.coarse_z_m[-1] == 0.8
    assert np.diff(found.coarse_z_m).max() <= 0.5 * ch.range_resolution_m + 1e-12
    assert found.fine_score.max() == pytest.approx(1.0)


def test_depth_words_and_default_range():
    assert parse_depth("0.6") == 0.6
    assert parse_depth("0.5:0.7") == (0.5, 0.7)
    for bad in ("0.7:0.5", "-0.1", "a", "0.5:", "0:0.5", "nan"):
        with pytest.raises(TwinFocusError):
            parse_depth(bad)
    assert default_range(0.6) == pytest.approx((0.35, 0.85))
    assert default_range(0.1)[0] > 0


@pytest.fixture(scope="module")
def deep(deep_scene):
    """conftest.py's scene with the target 8 cm deeper; the target's x/y box and its true depth."""
    sc = Scenario(target_depth_offset_m=0.08)
    return deep_scene, sc.target_roi(), float(planar_object(sc.scene(), "target").centre_m[2])


def _focus(d, out, target, *extra):
    rois = ("--reference-roi", *REF_ROI, "--target-roi", *target)
    options = "--size 48 --iterations 150 --space-variant off --quiet --no-cache"
    return cli("focus", d / "scan.npz", *rois, options, "--template-scan", d / "tpl.npz", "--out", out, *extra)


@pytest.mark.slow
def test_focus_finds_the_target_depth_and_matches_the_typed_result(deep, tmp_path):
    d, roi, truth_z = deep
    box = [f"{v:.4f}" for v in roi[:4]]
    assert _focus(d, tmp_path / "typed", box + [f"{truth_z}"]) == 0
    assert _focus(d, tmp_path / "found", box) == 0
    typed = metrics(tmp_path / "typed")
    found = metrics(tmp_path / "found")
    assert "target_depth" not in typed
    z = found["target_depth"]["depth_m"]
    assert abs(z - truth_z) < 0.1 * 0.039
    assert found["target_roi"][4] == pytest.approx(z)
    assert found["target_depth"]["range_m"] == pytest.approx([0.35, 0.85])
    assert abs(found["target_ssim_corrected"] - typed["target_ssim_corrected"]) < 0.01
    assert (tmp_path / "found" / "depth_search.png").is_file()
    # a typed depth 5 cm off, refined
    assert _focus(d, tmp_path / "refined", box + [f"{truth_z - 0.05}"], "--refine-depth") == 0
    refined = metrics(tmp_path / "refined")
    assert abs(refined["target_depth"]["depth_m"] - truth_z) < 0.1 * 0.039
    assert abs(refined["target_ssim_corrected"] - typed["target_ssim_corrected"]) < 0.01


@pytest.mark.parametrize(
    "target, extra, needle",
    [
        (["0.0", "0.1", "-0.1"], [], "X0 X1 Y0 Y1"),
        (["0.0", "0.1", "-0.1", "0.1", "0.7:0.5"], [], "Z0:Z1"),
        (["0.1", "0.0", "-0.1", "0.1"], [], "X0 < X1"),
        (["0.0", "0.1", "-0.1", "0.1", "0.6"], ["--refine-depth", "-0.1"], "--refine-depth"),
        (["0.0", "0.1", "-0.1", "0.1", "0.6"], ["--volume", "0.7", "0.5", "0.01"], "volume needs 0 < Z0 <= Z1"),
    ],
)
def test_bad_target_regions_are_refused_before_any_work(small_scene, tmp_path, capsys, target, extra, needle):
    # refused from the arguments alone: any scene does, and conftest.py's small one is made for
    # make test-fast's other focus tests anyway (the deep scene only for the slow ones: 1.9 s)
    d = small_scene
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("earlier result")
    try:  # --overwrite: the region's own error, not the existing folder's, is the one to read
        code = _focus(d, out, target, *extra, "--overwrite")
    except SystemExit as exc:  # refused while the options are read
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]
