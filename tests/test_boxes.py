"""The boxes found by the look (twinfocus/focus/boxes.py): against the objects' own extents in
simulated scenes, and ``focus`` with no box typed against the same scene's typed boxes."""

import json

import numpy as np
import pytest

from twinfocus.cli import main
from twinfocus.errors import TwinFocusError
from twinfocus.focus.boxes import REGION_MARGIN_M, Look, LookObject, choose, cut_away, look, objects_in, overlap
from twinfocus.imaging.grid import ImageGrid
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
from twinfocus.simulation.if_simulator import simulate_if
from twinfocus.simulation.scenario import Scenario, planar_object


def _patch(x0, x1, y0, y1, z, rng):
    xs, ys = np.meshgrid(np.arange(x0, x1 + 1e-9, 0.004), np.arange(y0, y1 + 1e-9, 0.004))
    pts = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)], axis=1)
    return pts, np.exp(2j * np.pi * rng.random(len(pts)))  # speckle


# 8 s idle (benchmarks/results/test_fast.json): out of make test-fast. The look's extent and depth of
# an object are checked quickly by tests/test_reference_search.py::test_region_of_the_one_object_of_a_scan,
# a target's region found from the look by tests/test_nodes_where.py.
@pytest.mark.slow
def test_look_finds_two_patches_at_their_extents_and_depths():
    ch = Chirp()
    va = mmwcas_virtual_array()
    # a dense 3-column raster (rows 2 mm apart, as a sweep's frames are)
    pos = np.array([va.offsets_m + [cx, y, 0.0] for cx in (-0.082, 0.0, 0.082) for y in np.arange(-19.5, 20) * 0.002])
    rng = np.random.default_rng(5)
    truth = [(-0.10, -0.04, -0.05, 0.04, 0.55), (0.01, 0.06, -0.03, 0.06, 0.65)]
    parts = [_patch(*t, rng) for t in truth]
    pts = np.concatenate([p for p, _ in parts])
    amp = np.concatenate([a for _, a in parts])
    seen = look(simulate_if(pts, amp, pos, ch), pos, ch)
    assert len(seen.objects) >= 2
    for t in truth:
        # the object of the look that overlaps the patch most: its extent within 1.5 cm (the 8 cm
        # aperture's resolution in y at these depths, lambda z / 2L, is 1.3-1.6 cm), its depth within 5 mm
        best = max(seen.objects, key=lambda o: overlap(o.extent_m, t[:4]))
        assert np.abs(np.subtract(best.extent_m, t[:4])).max() < 0.015
        assert best.depth_m == pytest.approx(t[4], abs=0.005)
    assert 0.95 < sum(o.share for o in seen.objects) <= 1.0 + 1e-9  # less what was too faint to keep


def test_an_objects_edges_are_where_its_blurred_edge_is_for_a_bright_and_a_faint_object():
    from scipy import ndimage

    # two flat plates, one 8 dB fainter than the other, blurred by a point response of 2 pixels
    # (8 mm: a letter's image at 0.6 m); the truth is the plates' own edges
    plane = ImageGrid(-0.128, 0.128, -0.128, 0.128, 0.6, 64, 64)
    xs, ys = np.meshgrid(plane.x_m, plane.y_m)
    truth = [(-0.08, -0.03, -0.04, 0.05, 1.0), (0.01, 0.07, -0.03, 0.04, 0.4)]
    img = np.zeros_like(xs)
    for x0, x1, y0, y1, a in truth:
        img += a * ((xs >= x0) & (xs < x1) & (ys >= y0) & (ys < y1))

    def sampled(c, lo, hi):  # a plate's edges as the pixels sample it: half a pixel beyond its outer pixels
        i = np.flatnonzero((c >= lo) & (c < hi))
        return c[i[0]] - (c[1] - c[0]) / 2, c[i[-1]] + (c[1] - c[0]) / 2

    found = objects_in(ndimage.gaussian_filter(img, 2.0), plane, 1.0)
    assert len(found) == 2
    for x0, x1, y0, y1, _ in truth:
        edges = (*sampled(plane.x_m, x0, x1), *sampled(plane.y_m, y0, y1))
        box = max((b for b, _ in found), key=lambda b: overlap(b, edges))
        # within 1.5 mm (0.4 pixel) of every edge, the faint plate's as the bright one's
        assert np.abs(np.subtract(box, edges)).max() < 0.0015, (box, edges)


def _seen(*objects):
    plane = ImageGrid(-0.3, 0.3, -0.3, 0.3, 0.6, 4, 4)
    return Look(np.zeros((4, 4), np.float32), plane, [], [LookObject(e, z, s) for e, z, s in objects])


def test_choose_takes_the_twins_object_as_the_reference_and_the_brightest_other_as_the_target():
    ref_ext = (-0.09, -0.014, -0.064, 0.064, 0.6)
    seen = _seen(
        ((-0.095, -0.01, -0.07, 0.07), 0.6, 0.45),  # the reference as the look sees it
        ((0.02, 0.085, -0.06, 0.066), 0.62, 0.40),  # the target
        ((-0.2, -0.15, 0.2, 0.25), 0.5, 0.15),  # something dimmer
    )
    ref_roi = (-0.105, 0.001, -0.079, 0.079, 0.6)
    b = choose(seen, ref_roi, ref_ext, "physical twin scan")
    assert b.info["reference"]["look_object"] == 1 and b.info["target"]["look_object"] == 2
    assert b.target_roi == pytest.approx((0.02 - REGION_MARGIN_M, 0.085 + REGION_MARGIN_M, -0.075, 0.081, 0.62))
    assert b.info["target"]["share"] == pytest.approx(0.40 / 0.55, abs=1e-3)
    assert b.info["sure"] == "yes" and "[boxes]" in b.line()
    # nothing besides the reference: refused with a line that says what to type
    with pytest.raises(TwinFocusError, match="--target-roi"):
        choose(_seen(((-0.095, -0.01, -0.07, 0.07), 0.6, 1.0)), ref_roi, ref_ext, "typed")


def test_a_grown_region_stops_at_the_other_region():
    # the target's region grown 1.5 cm reaches into a wide typed reference region: cut at its edge
    keep = [-0.15, 0.03, -0.11, 0.12]
    cut = cut_away([0.009, 0.096, -0.078, 0.078], keep, (0.024, 0.081, -0.063, 0.063), (-0.09, -0.014, -0.064, 0.064))
    assert cut == pytest.approx([0.03, 0.096, -0.078, 0.078]) and overlap(cut, keep) == 0.0
    # objects that overlap each other: nothing to part them by, left as it was
    assert cut_away([0, 1, 0, 1], [0.5, 2, 0.5, 2], (0, 1, 0, 1), (0.5, 2, 0.5, 2)) == [0, 1, 0, 1]


@pytest.mark.slow
def test_focus_with_no_box_typed_finds_both_letters_and_matches_the_typed_boxes(tmp_path):
    d = tmp_path
    sim = ["--columns", "3", "--rows", "40", "--seed", "3", "--quiet"]
    assert main(["simulate", "--out", str(d / "scan.npz"), "--template-out", str(d / "tpl.npz"), *sim]) == 0
    common = [str(d / "scan.npz"), "--template-scan", str(d / "tpl.npz"), "--size", "48", "--iterations", "150",
              "--space-variant", "off", "--quiet", "--no-cache"]  # fmt: skip
    typed = ["--reference-roi", "-0.15", "0.0", "-0.11", "0.12", "0.6", "--target-roi", "0.02", "0.13", "-0.11",
             "0.12", "0.6"]  # fmt: skip
    assert main(["focus", *common, *typed, "--out", str(d / "typed")]) == 0
    assert main(["focus", *common, "--out", str(d / "found")]) == 0
    t = json.loads((d / "typed" / "metrics.json").read_text())
    f = json.loads((d / "found" / "metrics.json").read_text())
    scene = Scenario().scene()
    for role in ("reference", "target"):
        obj = planar_object(scene, role)
        c = obj.corners_m()
        letter = (c[:, 0].min(), c[:, 0].max(), c[:, 1].min(), c[:, 1].max())
        roi = f[f"{role}_roi"]
        out = [letter[0] - roi[0], roi[1] - letter[1], letter[2] - roi[2], roi[3] - letter[3]]
        assert min(out) >= 0, (role, out)  # holds the letter
        # and not much more: the margin, and the extent within the small scan's 1.5 cm resolution in y
        assert max(out) <= REGION_MARGIN_M + 0.015, (role, out)
        assert roi[4] == pytest.approx(float(obj.centre_m[2]), abs=0.005)
    assert overlap(f["reference_roi"][:4], f["target_roi"][:4]) == 0.0
    assert f["boxes"]["reference"]["source"] == "physical twin scan"
    assert (d / "found" / "look.png").is_file()
    assert f["target_ssim_corrected"] == pytest.approx(t["target_ssim_corrected"], abs=0.02)
