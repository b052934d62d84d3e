"""Stereo camera model and renderer: file round trip, projection against the rendered truth,
rectification of a rotated pair checked through depth against the true surface."""

import json

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.scene import Scene, card
from twinfocus.twins.digital_twin.camera import Intrinsics, StereoCamera, pose_matrix, transform_points
from twinfocus.twins.digital_twin.render import render_scene
from twinfocus.twins.digital_twin.segment import Seed
from twinfocus.twins.digital_twin.stereo import check_pair, depth_from_disparity


def _rot_y(deg):
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def test_zed2i_defaults_and_json_round_trip(tmp_path):
    cam = StereoCamera.zed2i()
    assert cam.size == (1280, 720) and cam.baseline_m == pytest.approx(0.120)
    assert cam.is_rectified
    odd = StereoCamera(
        Intrinsics(701.9, 701.7, 641.3, 344.2, 1280, 720, (-0.175, 0.028, 6.7e-5, -1.5e-4, 0.0)),
        Intrinsics(701.0, 701.1, 633.5, 359.3, 1280, 720, (-0.173, 0.027, 1.6e-4, 1.0e-5, 0.0)),
        _rot_y(0.36),
        np.array([-0.11998, 2.6e-5, 1.6e-5]),
        pose_matrix(_rot_y(2.0), (0.01, -0.02, 0.003)),
    )
    path = odd.save(tmp_path / "camera.json")
    back = StereoCamera.load(path)
    assert back.to_dict() == odd.to_dict()  # JSON floats round-trip exactly
    assert not back.is_rectified
    assert oct(path.stat().st_mode & 0o777) != oct(0o600)


def test_camera_errors(tmp_path):
    eye = Intrinsics(700, 700, 639.5, 359.5, 1280, 720)
    with pytest.raises(TwinFocusError, match="same size"):
        StereoCamera(eye, Intrinsics(700, 700, 319.5, 179.5, 640, 360))
    with pytest.raises(TwinFocusError, match="baseline"):
        StereoCamera(eye, eye, np.eye(3), np.zeros(3))
    with pytest.raises(TwinFocusError, match="no such camera"):
        StereoCamera.load(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"left": {}}))
    with pytest.raises(TwinFocusError, match="bad.json"):
        StereoCamera.load(bad)
    with pytest.raises(TwinFocusError, match="same size"):
        check_pair(np.zeros((720, 1280, 3), np.uint8), np.zeros((720, 1279, 3), np.uint8))


def test_rendered_truth_matches_projection():
    # A card facing the camera: its depth along the optical axis is its z minus the camera's z,
    # and its centre projects (pinhole formula, written out here) onto the truth mask's centroid.
    centre = np.array([0.03, 0.02, 0.55])
    cam = StereoCamera.zed2i(640, 360)
    r = render_scene(Scene([card(centre, name="reference")]), cam, seed=1)
    m = r.mask("reference")
    cam_pt = centre - cam.scene_from_left[:3, 3]
    f = cam.left.fx
    u = f * cam_pt[0] / cam_pt[2] + cam.left.cx
    v = f * cam_pt[1] / cam_pt[2] + cam.left.cy
    ys, xs = np.nonzero(m)
    assert abs(xs.mean() - u) < 0.5 and abs(ys.mean() - v) < 0.5
    np.testing.assert_allclose(r.depth_left[m], cam_pt[2], atol=1e-6)
    # area: 85.6 x 53.98 mm at that depth, in pixels
    expected = (0.0856 * f / cam_pt[2]) * (0.05398 * f / cam_pt[2])
    assert m.sum() == pytest.approx(expected, rel=0.03)
    assert r.left.shape == (360, 640, 3) and r.left.dtype == np.uint8


def test_rectification_of_a_verged_pair_gives_true_depth():
    # The right eye is turned by 1 degree and both eyes have distortion: unrectified, rows do not
    # correspond. After cv2 rectification the card's reconstructed points must lie on its plane.
    from twinfocus.twins.digital_twin.pipeline import reference_from_stereo
    from twinfocus.twins.digital_twin.pointcloud import PointCloudConfig

    eye_l = Intrinsics(350, 350, 319.5, 179.5, 640, 360, (-0.05, 0.01, 0, 0, 0))
    eye_r = Intrinsics(352, 351, 322.0, 181.0, 640, 360, (-0.04, 0.01, 0, 0, 0))
    cam = StereoCamera(eye_l, eye_r, _rot_y(1.0), np.array([-0.12, 0.0, 0.0]), pose_matrix(None, (-0.06, 0.0, 0.0)))
    centre = np.array([-0.02, 0.0, 0.5])
    scene = Scene([card(centre, name="reference")])
    # The renderer draws ideal pinhole views; distortion is applied by warping with OpenCV's model.
    import cv2

    ideal = StereoCamera(
        Intrinsics(350, 350, 319.5, 179.5, 640, 360),
        Intrinsics(352, 351, 322.0, 181.0, 640, 360),
        _rot_y(1.0),
        np.array([-0.12, 0.0, 0.0]),
        cam.scene_from_left,
    )
    r = render_scene(scene, ideal, seed=2, noise_dn=1.0)

    def distort(img, eye):
        # For each distorted pixel find the undistorted pixel it comes from.
        uu, vv = np.meshgrid(np.arange(eye.width, dtype=np.float32), np.arange(eye.height, dtype=np.float32))
        pts = np.stack([uu.ravel(), vv.ravel()], 1).reshape(-1, 1, 2)
        und = cv2.undistortPoints(pts, eye.K, np.asarray(eye.dist), P=eye.K).reshape(eye.height, eye.width, 2)
        return cv2.remap(img, und[..., 0], und[..., 1], cv2.INTER_LINEAR)

    left, right = distort(r.left, eye_l), distort(r.right, eye_r)
    seed = Seed.box(295, 140, 400, 220)
    twin = reference_from_stereo(left, right, cam, seed, cloud_config=PointCloudConfig(voxel_m=None))
    z_err = twin.points_m[:, 2] - centre[2]
    assert np.sqrt(np.mean(z_err**2)) < 2e-3
    lo, hi = twin.points_m.min(axis=0), twin.points_m.max(axis=0)
    assert (hi - lo)[0] == pytest.approx(0.0856, abs=0.004) and (hi - lo)[1] == pytest.approx(0.05398, abs=0.004)
    np.testing.assert_allclose(twin.points_m[:, :2].mean(axis=0), centre[:2], atol=2e-3)


def test_depth_from_disparity_closed_form():
    d = np.array([[140.0, 0.0], [np.nan, 70.0]], np.float32)
    z = depth_from_disparity(d, 700.0, 0.12)
    assert z[0, 0] == pytest.approx(0.6) and z[1, 1] == pytest.approx(1.2)
    assert np.isnan(z[0, 1]) and np.isnan(z[1, 0])


def test_transform_points_inverse():
    t = pose_matrix(_rot_y(17.0), (0.1, -0.2, 0.3))
    p = np.random.default_rng(0).normal(size=(10, 3))
    np.testing.assert_allclose(transform_points(np.linalg.inv(t), transform_points(t, p)), p, atol=1e-12)
