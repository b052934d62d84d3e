"""TUM and EuRoC trajectory files: the published layouts read correctly, round trips bit-exact,
confidence carried, bad files refused with the line."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers import assert_refuses
from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import Poses
from twinfocus.sensors.trajectory_files import read_euroc, read_trajectory, read_tum, write_euroc, write_tum

# Lines in the layout of TUM RGB-D groundtruth.txt (timestamp tx ty tz qx qy qz qw); values illustrative.
TUM_SAMPLE = """# ground truth trajectory
# file: 'rgbd_dataset_freiburg1_xyz.bag'
# timestamp tx ty tz qx qy qz qw
1305031098.6659 1.3563 0.6305 1.6380 0.6132 0.5962 -0.3311 -0.3986
1305031098.6758 1.3543 0.6306 1.6360 0.6129 0.5966 -0.3316 -0.3980
"""

# Lines in the layout of EuRoC state_groundtruth_estimate0/data.csv (17 columns, quaternion w first); values illustrative.
EUROC_SAMPLE = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
    "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]\n"
    "1403636580838555648,4.688319,-1.786938,0.783338,0.534108,-0.153029,-0.827383,-0.082152,"
    "-0.027876,0.033207,0.800006,-0.003172,0.021267,0.078502,-0.025266,0.136696,0.075593\n"
    "1403636580843555328,4.688177,-1.786770,0.787350,0.534640,-0.152990,-0.826976,-0.082863,"
    "-0.029272,0.033185,0.806432,-0.003172,0.021267,0.078502,-0.025266,0.136696,0.075593\n"
)


def test_reads_the_published_tum_layout(tmp_path):
    p = tmp_path / "groundtruth.txt"
    p.write_text(TUM_SAMPLE)
    poses = read_tum(p)
    assert poses.timestamps_ns.tolist() == [1305031098665900000, 1305031098675800000]
    np.testing.assert_allclose(poses.position_m[1], [1.3543, 0.6306, 1.6360])
    q = np.array([0.6132, 0.5962, -0.3311, -0.3986])
    np.testing.assert_allclose(poses.quat_xyzw[0], q / np.linalg.norm(q))
    assert poses.confidence is None
    assert read_trajectory(p).timestamps_ns[0] == poses.timestamps_ns[0]


def test_reads_the_published_euroc_layout(tmp_path):
    p = tmp_path / "data.csv"
    p.write_text(EUROC_SAMPLE)
    poses = read_euroc(p)
    assert poses.timestamps_ns.tolist() == [1403636580838555648, 1403636580843555328]
    np.testing.assert_allclose(poses.position_m[0], [4.688319, -1.786938, 0.783338])
    q = np.array([-0.153029, -0.827383, -0.082152, 0.534108])  # (x, y, z, w) from w-first columns
    np.testing.assert_allclose(poses.quat_xyzw[0], q / np.linalg.norm(q))
    assert read_trajectory(p).position_m.shape == (2, 3)


def _poses(with_conf=True):
    rng = np.random.default_rng(4)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    t = 1_700_000_000_123_456_789 + np.cumsum(rng.integers(1, 20_000_000, 50))
    return Poses(t, rng.normal(size=(50, 3)) * 0.3, q, rng.uniform(0, 1, 50) if with_conf else None)


@pytest.mark.parametrize("write, read", [(write_tum, read_tum), (write_euroc, read_euroc)])
def test_round_trip_is_exact_and_keeps_confidence(tmp_path, write, read):
    poses = _poses()
    back = read(write(tmp_path / "traj.txt", poses))
    np.testing.assert_array_equal(back.timestamps_ns, poses.timestamps_ns)
    np.testing.assert_array_equal(back.position_m, poses.position_m)
    np.testing.assert_array_equal(back.confidence, poses.confidence)
    np.testing.assert_allclose(back.quat_xyzw, poses.quat_xyzw, rtol=0, atol=1e-15)
    plain = read(write(tmp_path / "plain.txt", poses, confidence=False))
    assert plain.confidence is None


@pytest.mark.parametrize(
    "text, message",
    [
        ("1.0 0 0 0 0 0 0\n", "line 1: a TUM pose has 8 values"),
        ("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1 0.5\n", "line 2: 9 values where earlier lines have 8"),
        ("1.0 0 0 0 0 0 0 1\n0.5 0 0 0 0 0 0 1\n", "non-decreasing"),
        ("1.0 0 0 0 0 0 0 2\n", "unit quaternions"),
        ("abc 0 0 0 0 0 0 1\n", "line 1: time stamp 'abc' is not a number"),
        ("1.0 0 x 0 0 0 0 1\n", "line 1: expected numbers"),
        ("# only a comment\n", "no poses"),
    ],
)
def test_bad_tum_files_are_refused(tmp_path, text, message):
    assert_refuses(read_tum, tmp_path / "t.txt", text, message)


def test_bad_euroc_files_are_refused(tmp_path):
    p = tmp_path / "d.csv"
    p.write_text("#timestamp [ns],p_RS_R_x [m]\n1.5,0,0,0,1,0,0,0\n")
    with pytest.raises(TwinFocusError, match="integer nanoseconds"):
        read_euroc(p)
    p.write_text("100,0,0,0,1,0\n")
    with pytest.raises(TwinFocusError, match="line 1: expected at least 8"):
        read_euroc(p)
    with pytest.raises(TwinFocusError, match="unknown trajectory format"):
        read_trajectory(p, "kitti")
