"""Camera-radar extrinsics: composition checked with 4 x 4 matrices, the calibration file, and
the two measuring aids (rigid fit on reflectors, image offset of twin vs measured image)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers import assert_refuses
from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import Poses, quat_from_rotvec, quat_to_matrix
from twinfocus.sensors.extrinsics import RadarCameraExtrinsics, fit_rigid_transform, image_offset_m


def _hom(r, t):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, t
    return m


def test_radar_poses_compose_like_homogeneous_matrices():
    rng = np.random.default_rng(0)
    ext = RadarCameraExtrinsics(quat_to_matrix(quat_from_rotvec([0.1, -0.2, 0.05])), [0.02, 0.085, -0.01])
    q = quat_from_rotvec(rng.normal(size=(5, 3)) * 0.3)
    cam = Poses(np.arange(5), rng.normal(size=(5, 3)), q, np.linspace(0.2, 1.0, 5))
    radar = ext.radar_poses(cam)
    for m in range(5):
        want = _hom(quat_to_matrix(q[m]), cam.position_m[m]) @ _hom(ext.rotation, ext.translation_m)
        got = _hom(radar.rotation_matrices()[m], radar.position_m[m])
        np.testing.assert_allclose(got, want, atol=1e-12)
    np.testing.assert_array_equal(radar.confidence, cam.confidence)
    back = ext.inverse()
    np.testing.assert_allclose(
        _hom(back.rotation, back.translation_m) @ _hom(ext.rotation, ext.translation_m), np.eye(4), atol=1e-12
    )


def test_calibration_file_forms_agree_and_round_trip(tmp_path):
    r = quat_to_matrix(quat_from_rotvec([0.0, 0.0, np.pi / 2]))  # 90 deg about z
    forms = {
        "q.yaml": "translation_m: [0.01, 0.02, 0.03]\nrotation_xyzw: [0, 0, 0.7071067811865476, 0.7071067811865476]\n",
        "m.yaml": "translation_m: [0.01, 0.02, 0.03]\nrotation_matrix: [[0, -1, 0], [1, 0, 0], [0, 0, 1]]\n",
        "rpy.yaml": "translation_m: [0.01, 0.02, 0.03]\nrotation_rpy_deg: [0, 0, 90]\n",
    }
    for name, text in forms.items():
        (tmp_path / name).write_text(text)
        ext = RadarCameraExtrinsics.load(tmp_path / name)
        np.testing.assert_allclose(ext.rotation, r, atol=1e-12)
    saved = RadarCameraExtrinsics.load(ext.save(tmp_path / "out.yaml"))
    np.testing.assert_allclose(saved.rotation, ext.rotation, atol=1e-15)
    np.testing.assert_array_equal(saved.translation_m, ext.translation_m)


@pytest.mark.parametrize(
    "text, message",
    [
        ("translation_m: [10, 85, 0]\n", "not millimetres"),
        ("translation_m: [0, 0, 0]\nrotation_matrix: [[1, 0, 0], [0, 1, 0], [0, 0, -1]]\n", "not a proper rotation"),
        ("translation_m: [0, 0, 0]\nrotation_xyzw: [0, 0, 0, 2]\n", "unit quaternion"),
        ("translation_m: [0, 0, 0]\nrotaton_xyzw: [0, 0, 0, 1]\n", "unknown key.*rotaton_xyzw"),
        ("rotation_xyzw: [0, 0, 0, 1]\n", "missing translation_m"),
        ("translation_m: [0, 0]\n", "3 finite numbers"),
        ("translation_m: [a, 0, 0]\n", "must be numbers"),
        ("translation_m: [0, 0, 0]\nrotation_xyzw: [0, 0, 0, 1]\nrotation_rpy_deg: [0, 0, 0]\n", "give one rotation"),
    ],
)
def test_bad_calibration_files_are_refused(tmp_path, text, message):
    assert_refuses(RadarCameraExtrinsics.load, tmp_path / "e.yaml", text, message)


def test_rigid_fit_recovers_a_known_transform():
    rng = np.random.default_rng(1)
    r = quat_to_matrix(quat_from_rotvec([0.05, 0.3, -0.1]))
    t = np.array([0.03, -0.08, 0.01])
    pts = rng.uniform(-0.3, 0.3, (6, 3)) + [0, 0, 0.6]
    noisy = pts @ r.T + t + rng.normal(scale=2e-4, size=pts.shape)
    r_fit, t_fit, rms = fit_rigid_transform(pts, noisy)
    assert np.abs(r_fit - r).max() < 2e-3 and np.abs(t_fit - t).max() < 1e-3 and rms < 5e-4
    with pytest.raises(TwinFocusError, match="collinear"):
        fit_rigid_transform(np.outer(np.arange(4), [1.0, 0, 0]), np.outer(np.arange(4), [0, 1.0, 0]))


def test_image_offset_finds_a_subpixel_shift():
    x = np.linspace(-0.1, 0.1, 81)  # 2.5 mm pixels
    y = np.linspace(-0.05, 0.08, 53)
    xx, yy = np.meshgrid(x, y)

    def blob(cx, cy):
        return np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 0.006**2)) + 0.5 * np.exp(
            -((xx - cx - 0.03) ** 2 + (yy - cy) ** 2) / (2 * 0.004**2)
        )

    dx, dy = image_offset_m(blob(0.0, 0.01), blob(0.0071, 0.0046), x, y)
    assert abs(dx - 0.0071) < 4e-4 and abs(dy + 0.0054) < 4e-4


def test_translation_fix_from_an_image_shift():
    """An image is formed from assumed radar positions; the shift of an object's image is the
    assumed minus the true position. Feeding that shift back recovers the true lever arm."""
    r_wc = quat_to_matrix(quat_from_rotvec([0.0, 0.0, 0.3]))  # camera rolled about its axis
    cam = Poses(
        np.arange(3),
        np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.02, 0.0, 0.0]]),
        np.tile(quat_from_rotvec([0.0, 0.0, 0.3]), (3, 1)),
    )
    r_cr = quat_to_matrix(quat_from_rotvec([0.0, 0.1, 0.0]))
    true = RadarCameraExtrinsics(r_cr, [0.01, 0.08, -0.005])
    wrong = RadarCameraExtrinsics(r_cr, [0.013, 0.075, -0.005])
    shift_world = wrong.radar_poses(cam).position_m[0] - true.radar_poses(cam).position_m[0]
    shift_aperture = (r_wc @ r_cr).T @ shift_world  # the image axes are the radar's
    fixed = wrong.corrected_by_image_offset(*shift_aperture)
    np.testing.assert_allclose(fixed.translation_m, true.translation_m, atol=1e-15)
