"""The reference region found from what is known: a cloud with stray points, a template file's
grid, the one object of a physical twin's scan; and ``focus`` given only the twin and the
target's x/y box."""

import numpy as np
import pytest

from tests.helpers import REF_ROI, ROIS, SMALL_SCENE, TGT_ROI, cli, metrics, simulate
from twinfocus.errors import TwinFocusError
from twinfocus.focus.boxes import REGION_MARGIN_M as SCAN_MARGIN_M
from twinfocus.focus.reference_search import (
    REGION_MARGIN_M,
    candidate_score,
    region_from_cloud,
    region_from_scan,
    region_from_template_file,
)
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
from twinfocus.simulation.if_simulator import simulate_if


def test_region_of_a_cloud_ignores_stray_points_and_holes():
    rng = np.random.default_rng(0)
    n = 5000
    pts = np.stack([rng.uniform(-0.14, -0.02, n), rng.uniform(-0.06, 0.07, n), 0.6 + rng.normal(0, 1e-3, n)], axis=1)
    stray = rng.uniform([-0.5, -0.5, 0.2], [0.5, 0.5, 1.0], (20, 3))  # 0.4 % far outliers
    bad = np.full((5, 3), np.nan)
    roi, info = region_from_cloud(np.concatenate([pts, stray, bad]))
    want = (-0.14 - REGION_MARGIN_M, -0.02 + REGION_MARGIN_M, -0.06 - REGION_MARGIN_M, 0.07 + REGION_MARGIN_M)
    assert np.allclose(roi[:4], want, atol=0.003)
    assert roi[4] == pytest.approx(0.6, abs=1e-3)
    assert info["points"] == n + 20 and info["points_inside"] > 0.99 and info["depth_spread_m"] < 0.005
    with pytest.raises(TwinFocusError, match="finite points"):
        region_from_cloud(bad)
    with pytest.raises(TwinFocusError, match=r"\(N, 3\)"):
        region_from_cloud(np.zeros((4, 2)))
    with pytest.raises(TwinFocusError, match="in front"):
        region_from_cloud(pts * [1, 1, -1])


def test_region_of_a_template_file_is_its_grid():
    roi, info = region_from_template_file(np.linspace(-0.1, 0.0, 11), np.linspace(-0.05, 0.05, 7), 0.55)
    assert roi == pytest.approx((-0.1, 0.0, -0.05, 0.05, 0.55)) and info["source"] == "template file"


@pytest.mark.slow  # 2.5 s idle: out of make test-fast
def test_region_of_the_one_object_of_a_scan():
    ch = Chirp()
    va = mmwcas_virtual_array()
    # rows 2 mm apart, as a sweep's frames are: rows 5 mm apart put grating lobes 25 cm off, each
    # nearly as bright as the object
    pos = np.array([va.offsets_m + [cx, y, 0.0] for cx in (-0.03, 0.0, 0.03) for y in np.arange(-24.5, 25) * 0.002])
    # a 6 x 8 cm patch of scatterers 5 mm apart at 0.62 m, away from the aperture's axis
    xs, ys = np.meshgrid(np.arange(-0.12, -0.06 + 1e-9, 0.005), np.arange(0.0, 0.08 + 1e-9, 0.005))
    pts = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.62)], axis=1)
    amp = np.exp(2j * np.pi * np.random.default_rng(2).random(len(pts)))  # speckle
    data = simulate_if(pts, amp, pos, ch)
    roi, info = region_from_scan(data, pos, ch)
    assert roi[4] == pytest.approx(0.62, abs=0.1 * ch.range_resolution_m)
    # the box holds the patch, with at most 2.5 cm to spare on a side beyond the margin
    truth = (-0.12, -0.06, 0.0, 0.08)
    assert roi[0] < truth[0] < roi[0] + SCAN_MARGIN_M + 0.025
    assert roi[1] - SCAN_MARGIN_M - 0.025 < truth[1] < roi[1]
    assert roi[2] < truth[2] < roi[2] + SCAN_MARGIN_M + 0.025
    assert roi[3] - SCAN_MARGIN_M - 0.025 < truth[3] < roi[3]
    assert info["source"] == "physical twin scan" and info["object_energy_share"] > 0.9


def test_method_without_reference_region_is_refused(tmp_path, capsys):
    scan = tmp_path / "scan.npz"
    np.savez(scan, data=np.zeros((2, 2, 4), np.complex64))
    rc = cli("focus", scan, "--target-roi 0 0.1 0 0.1 0.6 --method none --out", tmp_path / "o", "--quiet")
    assert rc == 2
    assert "--reference-roi" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_focus_from_the_twin_and_an_xy_box_alone_matches_typed_regions(deep_scene, tmp_path):
    d, scan = tmp_path, deep_scene / "scan.npz"
    options = "--size 48 --iterations 150 --space-variant off --quiet --no-cache"
    common = (options, "--template-scan", deep_scene / "tpl.npz")
    box = "--target-roi 0.016 0.103 -0.0785 0.0785"
    assert cli("focus", scan, "--reference-roi", *REF_ROI, box, "0.68 --out", d / "typed", *common) == 0
    assert cli("focus", scan, box, "--out", d / "found", *common) == 0
    typed = metrics(d / "typed")
    found = metrics(d / "found")
    assert typed["reference_search"] == {"source": "typed", "roi": [-0.15, 0.0, -0.11, 0.12, 0.6]}
    where = found["reference_search"]
    assert where["source"] == "physical twin scan" and where["roi"] == found["reference_roi"]
    assert where["roi"][4] == pytest.approx(0.6, abs=0.004)
    assert found["target_depth"]["depth_m"] == pytest.approx(0.68, abs=0.004)
    assert found["target_ssim_corrected"] > typed["target_ssim_corrected"] - 0.01


def test_candidate_score_puts_trusted_references_first():
    trusted = {"reference_match_ssim": 0.7, "warnings": []}
    warned = {"reference_match_ssim": 0.99, "warnings": ["the transfer is not to be trusted"]}
    assert candidate_score(trusted) == pytest.approx(0.7)
    assert candidate_score(warned) == pytest.approx(-0.01)
    assert candidate_score({"reference_match_ssim": None, "warnings": []}) == 0.0
    # a drift seen through the right twin's estimate is the scan's, not the candidate's: a wrong
    # twin, whose estimate is noise, must not outrank it for escaping that warning
    drifted = {"reference_match_ssim": 0.98, "warnings": ["residual", "the tracking drifted"], "drift_warnings": 1}
    wrong = {"reference_match_ssim": 0.84, "warnings": ["residual"]}
    assert candidate_score(drifted) == pytest.approx(-0.02)
    assert candidate_score(drifted) > candidate_score(wrong)


@pytest.mark.slow
def test_of_two_template_scans_the_one_of_the_reference_is_chosen(small_scene, tmp_path):
    d, right = tmp_path, small_scene / "tpl.npz"
    # a motion-stage scan of another letter where the reference stands: the wrong twin
    assert (
        cli("simulate --quiet --out", d / "other.npz", "--template-out", d / "b.npz", "--reference B", *SMALL_SCENE)
        == 0
    )
    options = "--size 48 --iterations 150 --space-variant off --quiet --no-cache"
    twins = ("--template-scan", d / "b.npz", right)
    assert cli("focus", small_scene / "scan.npz", *ROIS, options, *twins, "--out", d / "out") == 0
    m = metrics(d / "out")
    cands = m["reference_candidates"]
    assert [c["path"] for c in cands["candidates"]] == [str(d / "b.npz"), str(right)]
    assert cands["chosen"] == 1
    a, b = cands["candidates"][1], cands["candidates"][0]
    assert a["score"] > b["score"] and a["target_ssim_corrected"] > b["target_ssim_corrected"]
    assert m["target_ssim_corrected"] == a["target_ssim_corrected"]


@pytest.mark.slow
def test_focus_with_the_reference_region_from_its_cloud_matches_the_typed_region(tmp_path):
    d = simulate(tmp_path, *SMALL_SCENE, "--reference-cloud-out", tmp_path / "cloud.npy")
    common = ("--target-roi", *TGT_ROI, "--size 48 --digital-twin", d / "cloud.npy", "--quiet --no-cache")
    assert cli("focus", d / "scan.npz", "--reference-roi", *REF_ROI, "--out", d / "typed", *common) == 0
    assert cli("focus", d / "scan.npz", "--out", d / "found", *common) == 0
    typed = metrics(d / "typed")
    found = metrics(d / "found")
    where = found["reference_search"]
    assert where["source"] == "digital twin cloud" and where["points_inside"] > 0.95
    assert where["roi"][4] == pytest.approx(0.6, abs=0.005)
    assert found["target_ssim_corrected"] > typed["target_ssim_corrected"] - 0.01
