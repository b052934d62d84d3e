"""Reference segmentation: IoU against the renderer's truth mask on several scenes (letters, with
an occluder, card, disc; cluttered backgrounds), bad seeds, and the SAM-family plug-in (with
test doubles standing in for the sam2 package, which is not installed here)."""

import sys
import types

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.scene import Scene, card, disc, paper_scene
from twinfocus.twins.digital_twin.pipeline import reference_from_stereo
from twinfocus.twins.digital_twin.render import render_scene
from twinfocus.twins.digital_twin.segment import (
    ClassicalSegmenter,
    PredictorSegmenter,
    Seed,
    box_from_scene_roi,
    load_segmenter,
    mask_iou,
)


def _roi_of(obj, margin=0.01):
    c = obj.corners_m()
    return (
        c[:, 0].min() - margin,
        c[:, 0].max() + margin,
        c[:, 1].min() - margin,
        c[:, 1].max() + margin,
        float(obj.centre_m[2]),
    )


SCENES = {
    "letters": lambda: paper_scene("A", "F"),
    "letters_behind_cloth": lambda: paper_scene("K", "P", occluder="polyester"),
    "card": lambda: Scene([card((-0.05, 0.01, 0.6), name="reference")]),
    "disc": lambda: Scene([disc(0.04, (-0.05, 0.0, 0.55), name="reference")]),
}
# Measured over 16 renders (4 scenes x seeds 4-7): IoU mean 0.954, lowest 0.909 (a K); these
# scenes at seed 1 give 0.955, 0.956, 0.975, 0.981 (docs/digital_twin.md).
MIN_IOU = {"letters": 0.90, "letters_behind_cloth": 0.90, "card": 0.93, "disc": 0.93}


@pytest.fixture(scope="module", params=sorted(SCENES))
def rendered(request):
    scene = SCENES[request.param]()
    return request.param, scene, render_scene(scene, seed=1)


def test_iou_against_rendered_truth(rendered):
    name, scene, r = rendered
    ref = scene.object("reference")
    seed = box_from_scene_roi(_roi_of(ref), r.camera)
    twin = reference_from_stereo(r.left, r.right, r.camera, seed)
    assert mask_iou(twin.mask, r.mask("reference")) >= MIN_IOU[name]


@pytest.mark.slow  # 1.4 s x
def test_the_twin_is_the_same_whatever_ran_before_and_on_any_thread():
    """GrabCut's colour models start from OpenCV's per-thread random generator and the plane is a
    RANSAC's: both are seeded, so a serial run and a Dask worker's thread build the same twin of
    one scene (tests/test_batch.py compares their records exactly)."""
    import threading

    import cv2

    scene = paper_scene("A", "F")
    r = render_scene(scene, seed=1)
    seed = box_from_scene_roi(_roi_of(scene.object("reference")), r.camera)
    first = reference_from_stereo(r.left, r.right, r.camera, seed)
    got = {}

    def elsewhere():
        cv2.randu(np.empty(1000, np.float32), 0, 1)  # moves this thread's generator on
        got["twin"] = reference_from_stereo(r.left, r.right, r.camera, seed)

    t = threading.Thread(target=elsewhere)
    t.start()
    t.join()
    assert np.array_equal(first.mask, got["twin"].mask) and np.array_equal(first.points_m, got["twin"].points_m)


@pytest.mark.slow  # 2.0 s (2 cores, idle): out of make test-fast (benchmarks/results/test_fast.json)
def test_point_seed_and_depth_only_fallback():
    scene = SCENES["card"]()
    r = render_scene(scene, seed=4)
    truth = r.mask("reference")
    ys, xs = np.nonzero(truth)
    twin = reference_from_stereo(r.left, r.right, r.camera, Seed.point(xs.mean(), ys.mean()))
    assert mask_iou(twin.mask, truth) >= 0.93
    # Without the right picture the segmenter falls back to depth + GrabCut: still the card.
    seg = ClassicalSegmenter()
    m = seg(r.left, Seed.point(xs.mean(), ys.mean()), twin.depth_m)
    assert mask_iou(m, truth) >= 0.85


def test_no_object_at_the_seed():
    depth = np.full((120, 160), np.nan, np.float32)
    depth[40:80, 50:110] = 0.6  # one object; the rest has no depth
    img = np.zeros((120, 160, 3), np.uint8)
    seg = ClassicalSegmenter()
    with pytest.raises(TwinFocusError, match="no object at the seed"):
        seg(img, Seed.point(10, 10), depth)
    with pytest.raises(TwinFocusError, match="outside"):
        seg(img, Seed.point(500, 10), depth)
    with pytest.raises(TwinFocusError, match="no object in the seed box"):
        seg(img, Seed.box(0, 0, 30, 30), depth)
    with pytest.raises(TwinFocusError, match="holds no valid pixel"):
        seg(img, Seed.nearest(), np.full((120, 160), np.nan, np.float32))
    # A wall filling the picture is not an object.
    with pytest.raises(TwinFocusError, match="covers"):
        seg(img, Seed.point(80, 60), np.full((120, 160), 1.5, np.float32))
    # The one object is found from a box and as the nearest surface.
    for s in (Seed.box(40, 30, 120, 90), Seed.nearest()):
        m = ClassicalSegmenter(config=type(seg.config)(refine="none"))(img, s, depth)
        assert m.sum() == 40 * 60 and m[40:80, 50:110].all()


# --- SAM-family plug-in: test doubles ----------------------------------------------------------------


class FakeSamPredictor:
    """TEST DOUBLE for a SAM-style predictor: records its inputs and returns three candidate masks
    (a wrong one with a low score, the box/point's rectangle with the best score, an empty one)."""

    def __init__(self):
        self.image = None
        self.calls = []

    def set_image(self, rgb):
        self.image = np.array(rgb)

    def predict(self, point_coords=None, point_labels=None, box=None, multimask_output=True):
        self.calls.append(
            {
                "point_coords": point_coords,
                "point_labels": point_labels,
                "box": box,
                "multimask_output": multimask_output,
            }
        )
        h, w = self.image.shape[:2]
        good = np.zeros((h, w), bool)
        if box is not None:
            x0, y0, x1, y1 = (int(v) for v in box)
        else:
            u, v = (int(c) for c in point_coords[0])
            x0, y0, x1, y1 = u - 5, v - 5, u + 5, v + 5
        good[y0:y1, x0:x1] = True
        wrong = np.ones((h, w), bool)
        return np.stack([wrong, good, np.zeros((h, w), bool)]), np.array([0.2, 0.9, 0.1]), None


def test_predictor_segmenter_prompts_and_picks_best_mask():
    img = np.zeros((60, 80, 3), np.uint8)
    img[..., 0] = 255  # blue in BGR: the predictor must receive it as RGB (blue last)
    fake = FakeSamPredictor()
    seg = PredictorSegmenter(fake)
    m = seg(img, Seed.box(10, 20, 30, 40))
    assert m.sum() == 20 * 20 and m[20:40, 10:30].all()
    assert fake.image[0, 0].tolist() == [0, 0, 255]
    assert fake.calls[-1]["box"].tolist() == [10, 20, 30, 40] and fake.calls[-1]["point_coords"] is None
    m = seg(img, Seed.point(40, 30))
    assert m[25:35, 35:45].all() and m.sum() == 100
    assert fake.calls[-1]["point_labels"].tolist() == [1]
    with pytest.raises(TwinFocusError, match="SAM-style"):
        PredictorSegmenter(object())


def test_load_segmenter_sam2_through_the_package_api(tmp_path, monkeypatch):
    """The loading code calls sam2's real entry points; a TEST DOUBLE package stands in for sam2."""
    ckpt = tmp_path / "sam2.1_hiera_tiny.pt"
    ckpt.write_bytes(b"not real weights")
    built = {}

    def build_sam2(config, checkpoint, device="cuda"):
        built.update(config=config, checkpoint=checkpoint, device=device)
        return "model"

    class SAM2ImagePredictor(FakeSamPredictor):
        def __init__(self, model):
            super().__init__()
            built["predictor_model"] = model

    pkg = types.ModuleType("sam2")
    mod_build = types.ModuleType("sam2.build_sam")
    mod_build.build_sam2 = build_sam2
    mod_pred = types.ModuleType("sam2.sam2_image_predictor")
    mod_pred.SAM2ImagePredictor = SAM2ImagePredictor
    monkeypatch.setitem(sys.modules, "sam2", pkg)
    monkeypatch.setitem(sys.modules, "sam2.build_sam", mod_build)
    monkeypatch.setitem(sys.modules, "sam2.sam2_image_predictor", mod_pred)

    seg = load_segmenter(f"sam2:{ckpt}")
    assert built == {
        "config": "configs/sam2.1/sam2.1_hiera_t.yaml",
        "checkpoint": str(ckpt),
        "device": "cpu",
        "predictor_model": "model",
    }
    m = seg(np.zeros((50, 50, 3), np.uint8), Seed.box(5, 5, 25, 15))
    assert m.sum() == 20 * 10
    load_segmenter(f"sam2:{ckpt}:my/config.yaml")
    assert built["config"] == "my/config.yaml"


def test_load_segmenter_errors(tmp_path, monkeypatch):
    assert isinstance(load_segmenter("classical"), ClassicalSegmenter)
    with pytest.raises(TwinFocusError, match="unknown segmenter"):
        load_segmenter("magic")
    with pytest.raises(TwinFocusError, match="not found"):
        load_segmenter(f"sam2:{tmp_path / 'none.pt'}")
    ckpt = tmp_path / "sam2.1_hiera_small.pt"
    ckpt.write_bytes(b"x")
    monkeypatch.setitem(sys.modules, "sam2", None)  # makes `import sam2` fail
    monkeypatch.setitem(sys.modules, "sam2.build_sam", None)
    with pytest.raises(TwinFocusError, match="not installed"):
        load_segmenter(f"sam2:{ckpt}")
