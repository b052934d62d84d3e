"""The emulated ZED 2i bag (twinfocus.sensors.emulators.zed_bag) read back by the project's own
rosbag2 reader: the extrinsics put the radar back on the track it was made from, the camera's
clock leads the radar's by what was asked, and the cloud is the scene's points where ``focus``
places a bag's cloud, off by the offset given; one-line refusals."""

import numpy as np
import pytest

from twinfocus.motion.trajectory import Poses
from twinfocus.sensors.emulators.zed_bag import CLOUD_TOPIC, PAD_POSES, POSE_TOPIC, ball_points, main
from twinfocus.sensors.extrinsics import RadarCameraExtrinsics
from twinfocus.sensors.rosbag2_files import read_bag_poses
from twinfocus.sensors.trajectory_files import write_tum
from twinfocus.twins.digital_twin.template import load_points


def test_the_bag_puts_the_radar_back_on_its_track_and_the_cloud_where_it_was(tmp_path):
    cap = tmp_path / "cap"
    cap.mkdir()
    n = 12
    ts = 1_700_000_000_000_000_000 + np.arange(n) * 50_000_000
    track = np.stack([np.linspace(-0.05, 0.05, n), 0.002 * np.arange(n), np.zeros(n)], axis=1)
    write_tum(cap / "trajectory.txt", Poses(ts, track, np.tile([0.0, 0, 0, 1], (n, 1))))
    scene = np.array([[-0.04, 0.03, 0.6], [-0.02, 0.0, 0.6], [0.05, -0.01, 0.6]])
    np.save(cap / "scatterers.npy", scene)
    bag = tmp_path / "bag"
    assert main([str(cap), "--out", str(bag), "--lead-ms", "40", "--cloud-offset-mm", "1", "-2", "0.5"]) == 0

    poses, _ = read_bag_poses(bag, POSE_TOPIC)
    assert len(poses) == n + 2 * PAD_POSES
    assert poses.timestamps_ns[0] == ts[0] - 40_000_000 and poses.timestamps_ns[-1] == ts[-1] + 40_000_000
    radar = RadarCameraExtrinsics(translation_m=np.array([0.06, 0.08, 0.0])).radar_poses(poses)
    # in the first pose's axes (convert's aperture frame) the radar is back on its track
    r0 = radar.rotation_matrices()[0]
    back = (radar.position_m[PAD_POSES : PAD_POSES + n] - radar.position_m[PAD_POSES]) @ r0
    assert np.allclose(back, track - track[0], atol=1e-9)

    cloud = load_points(f"{bag}:{CLOUD_TOPIC}")
    want = ball_points(scene) + [0.001, -0.002, 0.0005]
    assert cloud.shape == want.shape and np.allclose(cloud, want, atol=1e-6)  # float32 in the message


def test_the_bags_cloud_camera_is_where_focus_places_it():
    from twinfocus.sensors.emulators.zed_bag import BAG_CLOUD_CAMERA_M
    from twinfocus.twins.digital_twin.camera import DEFAULT_LEFT_CAMERA_POSITION_M

    assert BAG_CLOUD_CAMERA_M == DEFAULT_LEFT_CAMERA_POSITION_M


def test_ball_points_ring_each_centre():
    pts = ball_points(np.array([[0.0, 0.0, 0.5]]))
    assert pts.shape == (7, 3) and np.allclose(pts.mean(axis=0), [0, 0, 0.5])


@pytest.mark.parametrize(
    "args,said", [(["--lead-ms", "nan"], "--lead-ms"), (["--lever-arm-mm", "0", "2000", "0"], "--lever-arm-mm")]
)
def test_bad_input_is_one_line(tmp_path, capsys, args, said):
    cap = tmp_path / "cap"
    cap.mkdir()
    write_tum(cap / "trajectory.txt", Poses(np.arange(3) * 10**8, np.zeros((3, 3)), np.tile([0.0, 0, 0, 1], (3, 1))))
    np.save(cap / "scatterers.npy", np.zeros((2, 3)))
    assert main([str(cap), "--out", str(tmp_path / "bag"), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and said in err[0] and not (tmp_path / "bag").exists()
    # an existing --out is refused, left as it was
    (tmp_path / "bag").mkdir()
    assert main([str(cap), "--out", str(tmp_path / "bag")]) == 2 and not any((tmp_path / "bag").iterdir())
