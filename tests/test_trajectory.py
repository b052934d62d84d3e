import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import (
    HandMotion,
    Poses,
    handheld_zigzag,
    matrix_to_quat,
    paper_raster,
    phase_centres,
    quat_from_rotvec,
    quat_multiply,
    quat_to_matrix,
    slerp,
)
from twinfocus.radar.board import default_board
from twinfocus.radar.fmcw import mmwcas_virtual_array


def _axis_angle_quat(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([axis * np.sin(angle / 2), [np.cos(angle / 2)]])


def _rodrigues(axis, angle):
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def _random_quats(rng, n):
    q = rng.standard_normal((n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_quat_to_matrix_closed_forms():
    t = 0.7
    c, s = np.cos(t), np.sin(t)
    rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    ry = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    np.testing.assert_allclose(quat_to_matrix(_axis_angle_quat([0, 0, 1], t)), rz, atol=1e-14)
    np.testing.assert_allclose(quat_to_matrix(_axis_angle_quat([1, 0, 0], t)), rx, atol=1e-14)
    np.testing.assert_allclose(quat_to_matrix(_axis_angle_quat([0, 1, 0], t)), ry, atol=1e-14)
    np.testing.assert_allclose(quat_to_matrix([0, 0, 0, 1]), np.eye(3), atol=0)
    axis, angle = [0.3, -1.2, 0.5], 2.1
    np.testing.assert_allclose(quat_to_matrix(_axis_angle_quat(axis, angle)), _rodrigues(axis, angle), atol=1e-14)


def test_matrix_quat_round_trip_every_pivot():
    rng = np.random.default_rng(1)
    q = _random_quats(rng, 500)
    # Rotations by ~180 degrees about each axis exercise every branch of Shepperd's method.
    q = np.concatenate([q, [[1, 0, 0, 1e-9], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    back = matrix_to_quat(quat_to_matrix(q))
    assert np.all(back[:, 3] >= 0)
    sign = np.where(q[:, 3] < 0, -1.0, 1.0)[:, None]
    # q and -q are the same rotation; compare the rotations and the canonical sign.
    np.testing.assert_allclose(quat_to_matrix(back), quat_to_matrix(q), atol=1e-12)
    far = np.abs(q[:, 3]) > 1e-6
    np.testing.assert_allclose(back[far], (q * sign)[far], atol=1e-12)


def test_quat_multiply_composes_rotations():
    rng = np.random.default_rng(2)
    a, b = _random_quats(rng, 50), _random_quats(rng, 50)
    np.testing.assert_allclose(quat_to_matrix(quat_multiply(a, b)), quat_to_matrix(a) @ quat_to_matrix(b), atol=1e-12)


def test_quat_from_rotvec_matches_rodrigues_and_tiny_angles():
    axis, angle = np.array([1.0, 2.0, -0.5]), 0.9
    v = axis / np.linalg.norm(axis) * angle
    np.testing.assert_allclose(quat_to_matrix(quat_from_rotvec(v)), _rodrigues(axis, angle), atol=1e-14)
    tiny = np.array([1e-12, -2e-12, 3e-12])
    q = quat_from_rotvec(tiny)
    np.testing.assert_allclose(q, [5e-13, -1e-12, 1.5e-12, 1.0], atol=1e-20)


def test_slerp_closed_form_about_one_axis():
    axis = np.array([0.2, 0.9, -0.4])
    q0 = _axis_angle_quat(axis, 0.3)
    q1 = _axis_angle_quat(axis, 1.5)
    t = np.array([0.0, 0.25, 0.5, 1.0])
    out = slerp(q0[None], q1[None], t)
    expected = np.stack([_axis_angle_quat(axis, 0.3 + ti * 1.2) for ti in t])
    np.testing.assert_allclose(out, expected, atol=1e-12)
    # The short way round: -q1 is the same rotation and must give the same path.
    np.testing.assert_allclose(quat_to_matrix(slerp(q0, -q1, 0.5)), quat_to_matrix(expected[2]), atol=1e-12)
    # Nearly equal quaternions fall back to normalised lerp without NaN.
    q2 = _axis_angle_quat(axis, 0.3 + 1e-12)
    assert np.isfinite(slerp(q0, q2, 0.5)).all()


def test_poses_validation_errors():
    ts = np.array([0, 1, 2], dtype=np.int64)
    pos = np.zeros((3, 3))
    q = np.tile([0.0, 0, 0, 1], (3, 1))
    Poses(ts, pos, q)
    with pytest.raises(TwinFocusError, match="position_m"):
        Poses(ts, np.zeros((3, 2)), q)
    with pytest.raises(TwinFocusError, match="NaN"):
        Poses(ts, np.array([[0, 0, 0], [np.nan, 0, 0], [0, 0, 0]]), q)
    with pytest.raises(TwinFocusError, match="unit"):
        Poses(ts, pos, q * 2)
    with pytest.raises(TwinFocusError, match="non-decreasing"):
        Poses(np.array([0, 2, 1]), pos, q)
    with pytest.raises(TwinFocusError, match="integer"):
        Poses(ts.astype(float), pos, q)
    with pytest.raises(TwinFocusError, match="confidence"):
        Poses(ts, pos, q, confidence=np.array([0.5, 1.5, 0.2]))
    with pytest.raises(TwinFocusError, match="empty"):
        Poses(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 4)))


def test_poses_interpolate_linear_and_slerp():
    axis = [0, 0, 1]
    p = Poses(
        np.array([0, 1_000_000_000]),
        np.array([[0.0, 0, 0], [1.0, 2.0, -4.0]]),
        np.stack([_axis_angle_quat(axis, 0.0), _axis_angle_quat(axis, 1.0)]),
        confidence=np.array([1.0, 0.0]),
    )
    mid = p.interpolate(np.array([-5, 250_000_000, 2_000_000_000]))
    np.testing.assert_allclose(mid.position_m[1], [0.25, 0.5, -1.0])
    np.testing.assert_allclose(mid.quat_xyzw[1], _axis_angle_quat(axis, 0.25), atol=1e-12)
    np.testing.assert_allclose(mid.confidence, [1.0, 0.75, 0.0])
    # Outside the span the end poses are held.
    np.testing.assert_allclose(mid.position_m[0], [0, 0, 0])
    np.testing.assert_allclose(mid.position_m[2], [1.0, 2.0, -4.0])


def test_paper_raster_geometry():
    p = paper_raster()
    assert len(p) == 780
    x, y, z = p.position_m.T
    np.testing.assert_allclose(np.unique(np.round(x, 9)), (np.arange(6) - 2.5) * 0.082, atol=1e-12)
    assert y.min() == pytest.approx(-0.129) and y.max() == pytest.approx(0.129)
    np.testing.assert_allclose(z, 0.0)
    cols = p.position_m.reshape(6, 130, 3)
    for c in range(6):
        dy = np.diff(cols[c, :, 1])
        np.testing.assert_allclose(np.abs(dy), 0.002, atol=1e-12)
        # Serpentine: up the even columns, down the odd ones.
        assert np.all(dy > 0) if c % 2 == 0 else np.all(dy < 0)
    np.testing.assert_array_equal(np.diff(p.timestamps_ns), 100_000_000)
    np.testing.assert_allclose(p.quat_xyzw, np.tile([0, 0, 0, 1.0], (780, 1)))


def test_handheld_zigzag_coverage_and_seed():
    a = handheld_zigzag(rng=3)
    b = handheld_zigzag(rng=3)
    c = handheld_zigzag(rng=4)
    assert len(a) == 780
    np.testing.assert_array_equal(a.position_m, b.position_m)
    assert not np.allclose(a.position_m, c.position_m)
    cols = a.position_m.reshape(6, 130, 3)
    for k in range(6):
        y = cols[k, :, 1]
        assert abs(y.min() + 0.129) < 1e-12 and abs(y.max() - 0.129) < 1e-12
        assert np.all(np.diff(y) > 0) if k % 2 == 0 else np.all(np.diff(y) < 0)
        # The hand stays near its column (wander of a few mm, not the 82 mm pitch).
        assert np.abs(cols[k, :, 0] - (k - 2.5) * 0.082).max() < 0.02
    # Uneven speed: row spacing varies, mean matches the raster's 2 mm.
    dy = np.abs(np.diff(cols[:, :, 1], axis=1))
    assert dy.std() > 0.1 * dy.mean()
    assert dy.mean() == pytest.approx(0.258 / 129)
    np.testing.assert_allclose(np.linalg.norm(a.quat_xyzw, axis=1), 1.0, atol=1e-12)
    assert np.all(np.diff(a.timestamps_ns) > 0)
    flat = handheld_zigzag(rng=3, motion=HandMotion(tilt_deg=0.0, lateral_wander_m=0.0, depth_wander_m=0.0))
    np.testing.assert_allclose(flat.quat_xyzw[:, :3], 0.0, atol=0)


def test_phase_centres_mmwcas_pitch_and_rotation():
    arr = mmwcas_virtual_array()
    assert arr.n_channels == 86
    quarter = default_board().design_wavelength_m / 4
    pos = np.array([[0.1, -0.2, 0.05], [0.0, 0.0, 0.0]])
    q = np.stack([[0, 0, 0, 1.0], _axis_angle_quat([0, 0, 1], np.pi / 2)])
    c = phase_centres(Poses(np.array([0, 1]), pos, q), arr)
    assert c.shape == (2, 86, 3)
    # Identity pose: a line along x at pitch lambda/4 centred on the pose position.
    x = np.sort(c[0, :, 0])
    np.testing.assert_allclose(np.diff(x), quarter, atol=1e-12)
    np.testing.assert_allclose(c[0].mean(axis=0), pos[0], atol=1e-12)
    np.testing.assert_allclose(c[0, :, 1:], np.broadcast_to(pos[0, 1:], (86, 2)), atol=1e-12)
    # 90 degrees about boresight: the line now runs along y at the same pitch.
    np.testing.assert_allclose(np.diff(np.sort(c[1, :, 1])), quarter, atol=1e-12)
    np.testing.assert_allclose(c[1, :, 0], 0.0, atol=1e-12)
    with pytest.raises(TwinFocusError):
        phase_centres(pos, arr)
