"""Plates and tools of a letter's size (twinfocus.scene.tools), in the paper's scene by name."""

import numpy as np
import pytest
from scipy import ndimage

from twinfocus.errors import TwinFocusError
from twinfocus.scene import OBJECT_SHAPES, paper_scene, shape_mask, shaped_object

H, P = 0.127, 0.127 / 400


def _holes(mask: np.ndarray) -> int:
    """Enclosed background regions: the background's components that do not touch the border."""
    labels, n = ndimage.label(~np.pad(mask, 1))
    return n - 1


def test_each_shape_has_its_area_height_and_holes():
    area = {s: shape_mask(s, H, P).sum() * P * P / H**2 for s in OBJECT_SHAPES}  # in units of H^2
    # closed forms: the plate 0.65 x 1 less its rounded corners (4 (1 - pi / 4) r^2, r = 0.1)
    assert area["plate"] == pytest.approx(0.65 - 4 * (1 - np.pi / 4) * 0.01, rel=0.01)
    assert area["disc"] == pytest.approx(np.pi * 0.4**2, rel=0.01)
    assert area["washer"] == pytest.approx(np.pi * (0.45**2 - 0.2**2), rel=0.01)
    # a ring has one hole, the key's bow one; the plate, the disc and the open wrench none
    assert {s: _holes(shape_mask(s, H, P)) for s in OBJECT_SHAPES} == {
        "plate": 0,
        "disc": 0,
        "washer": 1,
        "wrench": 0,
        "key": 1,
    }
    for s in OBJECT_SHAPES:
        m = shape_mask(s, H, P)
        assert ndimage.label(m)[1] == 1  # one piece
        assert m.shape[0] * P <= H + 2 * P  # no taller than a letter
    # the wrench's jaw: open at the top, between its two sides
    w = shape_mask("wrench", H, P)
    row = w[w.shape[0] // 10]
    assert not row[w.shape[1] // 2] and row[: w.shape[1] // 2].any() and row[w.shape[1] // 2 :].any()


def test_shapes_stand_in_for_letters_in_the_paper_scene():
    scene = paper_scene("washer", "key", separation_deg=10.0)
    ref, tgt = scene.object("reference"), scene.object("target")
    assert ref.mask.shape == shape_mask("washer").shape and tgt.mask.shape == shape_mask("key").shape
    assert ref.centre_m[0] < 0 < tgt.centre_m[0]
    pts, _ = ref.scatterers(rng=0)
    # every scatterer lies on the washer: none in its hole
    r = np.hypot(pts[:, 0] - ref.centre_m[0], pts[:, 1] - ref.centre_m[1])
    assert r.min() > 0.2 * H - 2e-3 and r.max() < 0.45 * H + 2e-3
    obj = shaped_object("disc", 0.05, (0.0, 0.0, 0.5), name="d")
    assert obj.name == "d" and obj.size_m[0] == pytest.approx(0.04, abs=2 * 0.05 / 400)
    with pytest.raises(TwinFocusError, match="unknown object shape 'hammer'"):
        shape_mask("hammer")
