"""rosbag2 recordings as the ZED ROS 2 wrapper writes them (its topic names and types), written
here by ``rosbags`` itself in MCAP and SQLite storage, read back by twinfocus.sensors.rosbag2_files:
poses equal the poses written, the cloud the points written (NaN rows kept), the stereo pair and
its CameraInfo; convert and focus through the commands; one-line refusals."""

import json
import subprocess
import sys

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from twinfocus.cli import main
from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import quat_to_matrix
from twinfocus.sensors.rosbag2_files import read_any_trajectory, read_bag_cloud, read_bag_poses, read_bag_stereo

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types
POSE, ODOM, CLOUD = "/zed/zed_node/pose", "/zed/zed_node/odom", "/zed/zed_node/point_cloud/cloud_registered"
LEFT, RIGHT = "/zed/zed_node/left/image_rect_color", "/zed/zed_node/right/image_rect_color"
# the optical axes in the ROS body frame (x forward, y left, z up), built here independently of the module
R_BODY_OPT = np.stack([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], axis=1)


def _header(ns, frame):
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame
    )


def _pose(p, q):
    g = "geometry_msgs/msg/"
    return T[g + "Pose"](
        position=T[g + "Point"](x=p[0], y=p[1], z=p[2]), orientation=T[g + "Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])
    )


def zigzag(n=24, t0=1_700_000_000_000_000_000):
    """A zig-zag path (ROS axes: y left, z up) with a slow yaw: stamps, positions, quaternions."""
    k = np.arange(n)
    y = 0.1 * np.abs(((k / 6.0) % 2) - 1)  # legs left and right
    pos = np.stack([0.002 * k, y, 0.01 * (k // 6)], axis=1)
    yaw = 0.02 * np.sin(k / 5)
    quat = np.stack([0 * yaw, 0 * yaw, np.sin(yaw / 2), np.cos(yaw / 2)], axis=1)
    return t0 + k * 33_333_333, pos, quat


def cloud_msg(points_ros, ns, frame="zed_left_camera_frame"):
    """An organised PointCloud2 as the ZED writes it: x y z rgb float32, point_step 16, 2 rows, NaN invalid."""
    n = points_ros.shape[0]
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4")])
    rec["x"], rec["y"], rec["z"] = points_ros.T
    rec["rgb"] = 1.0
    pf = T["sensor_msgs/msg/PointField"]
    fields = [pf(name=c, offset=4 * i, datatype=7, count=1) for i, c in enumerate(["x", "y", "z", "rgb"])]
    return T["sensor_msgs/msg/PointCloud2"](
        header=_header(ns, frame),
        height=2,
        width=n // 2,
        fields=fields,
        is_bigendian=False,
        point_step=16,
        row_step=16 * (n // 2),
        data=np.frombuffer(rec.tobytes(), np.uint8),
        is_dense=False,
    )


def image_msg(img, ns, frame):
    h, w, _ = img.shape
    bgra = np.concatenate([img, np.full((h, w, 1), 255, np.uint8)], axis=2)
    return T["sensor_msgs/msg/Image"](
        header=_header(ns, frame),
        height=h,
        width=w,
        encoding="bgra8",
        is_bigendian=0,
        step=4 * w,
        data=bgra.reshape(-1),
    )


def info_msg(ns, frame, w, h, f, tx):
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    k = np.array([f, 0, w / 2, 0, f, h / 2, 0, 0, 1.0])
    p = np.array([f, 0, w / 2, tx, 0, f, h / 2, 0, 0, 0, 1.0, 0])
    return T["sensor_msgs/msg/CameraInfo"](
        header=_header(ns, frame),
        height=h,
        width=w,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=k,
        r=np.eye(3).reshape(-1),
        p=p,
        binning_x=0,
        binning_y=0,
        roi=roi,
    )


def write_zed_bag(path, storage, stamps, pos, quat, clouds=(), pair=None):
    """The ZED wrapper's topics: pose, odom, tf (map -> odom identity, odom -> zed_camera_link), clouds, images."""
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        c = {
            topic: w.add_connection(topic, ty, typestore=TS)
            for topic, ty in [
                (POSE, "geometry_msgs/msg/PoseStamped"),
                (ODOM, "nav_msgs/msg/Odometry"),
                ("/tf", "tf2_msgs/msg/TFMessage"),
                (CLOUD, "sensor_msgs/msg/PointCloud2"),
                (LEFT, "sensor_msgs/msg/Image"),
                (RIGHT, "sensor_msgs/msg/Image"),
                ("/zed/zed_node/left/camera_info", "sensor_msgs/msg/CameraInfo"),
                ("/zed/zed_node/right/camera_info", "sensor_msgs/msg/CameraInfo"),
            ]
        }
        g = "geometry_msgs/msg/"

        def put(topic, ns, msg):
            w.write(c[topic], ns + 5_000_000, TS.serialize_cdr(msg, c[topic].msgtype))  # received 5 ms later

        for ns, p, q in zip(stamps.tolist(), pos, quat, strict=True):
            put(POSE, ns, T[g + "PoseStamped"](header=_header(ns, "map"), pose=_pose(p, q)))
            cov = T[g + "PoseWithCovariance"](pose=_pose(p, q), covariance=np.zeros(36))
            zero = T[g + "Vector3"](x=0.0, y=0.0, z=0.0)
            tw = T[g + "TwistWithCovariance"](twist=T[g + "Twist"](linear=zero, angular=zero), covariance=np.zeros(36))
            put(
                ODOM,
                ns,
                T["nav_msgs/msg/Odometry"](
                    header=_header(ns, "odom"), child_frame_id="zed_camera_link", pose=cov, twist=tw
                ),
            )
            tfs = [
                T[g + "TransformStamped"](
                    header=_header(ns, parent),
                    child_frame_id=child,
                    transform=T[g + "Transform"](
                        translation=T[g + "Vector3"](x=tp[0], y=tp[1], z=tp[2]),
                        rotation=T[g + "Quaternion"](x=tq[0], y=tq[1], z=tq[2], w=tq[3]),
                    ),
                )
                for parent, child, tp, tq in [
                    ("map", "odom", [0, 0, 0], [0, 0, 0, 1]),
                    ("odom", "zed_camera_link", p, q),
                ]
            ]
            put("/tf", ns, T["tf2_msgs/msg/TFMessage"](transforms=tfs))
        for ns, pts in clouds:
            put(CLOUD, int(ns), cloud_msg(pts, int(ns)))
        if pair is not None:
            ns, left, right, f, base = pair
            ns = int(ns)
            h, wd, _ = left.shape
            put(LEFT, ns, image_msg(left, ns, "zed_left_camera_optical_frame"))
            put(RIGHT, ns, image_msg(right, ns, "zed_right_camera_optical_frame"))
            put("/zed/zed_node/left/camera_info", ns, info_msg(ns, "zed_left_camera_optical_frame", wd, h, f, 0.0))
            put(
                "/zed/zed_node/right/camera_info",
                ns,
                info_msg(ns, "zed_right_camera_optical_frame", wd, h, f, -f * base),
            )
    return path


@pytest.fixture(params=["mcap", "sqlite3"])
def bag(request, tmp_path):
    stamps, pos, quat = zigzag()
    pts = np.random.default_rng(1).uniform(-0.2, 0.2, size=(40, 3)) + [0.6, 0, 0]
    pts[[3, 17, 30]] = np.nan  # invalid pixels, as the ZED writes them
    rng = np.random.default_rng(2)
    left, right = (rng.integers(0, 255, (12, 16, 3), dtype=np.uint8) for _ in range(2))
    path = write_zed_bag(
        tmp_path / f"run_{request.param}",
        request.param,
        stamps,
        pos,
        quat,
        clouds=[(stamps[2], pts), (stamps[20], pts * 2)],
        pair=(stamps[4], left, right, 20.0, 0.12),
    )
    return path, stamps, pos, quat, pts, left, right


@pytest.mark.parametrize("topic,frame", [(POSE, None), (ODOM, None), ("/tf", "zed_camera_link")])
def test_poses_read_equal_the_poses_written(bag, topic, frame):
    path, stamps, pos, quat, *_ = bag
    poses, where = read_bag_poses(path, topic, frame)
    assert np.array_equal(poses.timestamps_ns, stamps)
    assert np.array_equal(poses.position_m, pos)
    # the camera's optical axes: body rotation times the fixed body -> optical rotation
    for m in range(len(poses)):
        want = quat_to_matrix(quat[m] / np.linalg.norm(quat[m])) @ R_BODY_OPT
        assert np.allclose(poses.rotation_matrices()[m], want, atol=1e-12)
    assert "optical axes" in where and ("map" in where or "odom" in where)


def test_storage_file_alone_reads_as_the_folder(bag):
    path = bag[0]
    storage = next(p for p in path.iterdir() if p.suffix in (".mcap", ".db3"))
    a, _ = read_bag_poses(path, POSE)
    b, _ = read_bag_poses(storage, POSE)
    assert np.array_equal(a.position_m, b.position_m) and np.array_equal(a.quat_xyzw, b.quat_xyzw)


def test_cloud_equals_the_points_written(bag):
    path, stamps, _, _, pts, *_ = bag
    first = read_bag_cloud(path, CLOUD)
    want = np.stack([-pts[:, 1], -pts[:, 2], pts[:, 0]], axis=1).astype(np.float32).astype(np.float64)
    assert np.array_equal(np.isnan(first.points), np.isnan(want))
    assert np.array_equal(first.points[~np.isnan(want)], want[~np.isnan(want)])
    assert first.position == 0 and first.stamp_ns == stamps[2]
    late = read_bag_cloud(path, CLOUD, at_ns=int(stamps[18]))  # nearer the second message
    assert late.position == 1 and np.allclose(late.points[~np.isnan(want)], 2 * want[~np.isnan(want)], rtol=1e-6)


def test_stereo_pair_and_camera_info(bag):
    path, stamps, *_, left, right = bag
    st = read_bag_stereo(path, LEFT, RIGHT)
    assert st.stamp_ns == stamps[4] and np.array_equal(st.left, left) and np.array_equal(st.right, right)
    assert (st.left_model.fx, st.left_model.cx, st.left_model.width) == (20.0, 8.0, 16)
    assert st.left_model.tx_m == 0.0 and abs(st.right_model.tx_m - 0.12) < 1e-12


def test_refusals_are_one_line_and_name_the_pose_topics(bag):
    path = bag[0]
    for call, words in [
        (lambda: read_bag_poses(path, "/zed/zed_node/nope"), ["no topic /zed/zed_node/nope", POSE, ODOM, "/tf"]),
        (lambda: read_bag_poses(path, CLOUD), ["is sensor_msgs/msg/PointCloud2", POSE]),
        (lambda: read_any_trajectory(path), ["needs --pose-topic", POSE]),
        (lambda: read_bag_poses(path, "/tf"), ["several frames", "--pose-frame"]),
        (lambda: read_bag_cloud(path, POSE), ["not a PointCloud2", CLOUD]),
        (lambda: read_bag_poses(path.parent / "absent.mcap", POSE), ["no such rosbag2"]),
    ]:
        with pytest.raises(TwinFocusError) as e:
            call()
        msg = str(e.value)
        assert "\n" not in msg and all(w in msg for w in words), msg


def test_svo_through_pyzed_stand_in(monkeypatch, tmp_path):
    from test_sensors_zed import _fake_pyzed

    pkg, sl = _fake_pyzed(["OK", "SEARCHING", "OK"])
    monkeypatch.setitem(sys.modules, "pyzed", pkg)
    monkeypatch.setitem(sys.modules, "pyzed.sl", sl)
    (tmp_path / "rec.svo2").write_bytes(b"svo")
    poses, where = read_any_trajectory(tmp_path / "rec.svo2")
    assert len(poses) == 3 and "ZED recording" in where
    assert poses.confidence[1] == 0.0 and poses.confidence[0] > 0  # SEARCHING: no confidence


@pytest.mark.slow
def test_convert_and_focus_from_a_zed_bag(tmp_path, capsys):
    """A capture whose trajectory travels in a bag as the ZED writes it (ROS axes): convert from
    the bag equals convert from the TUM file; focus with the bag's cloud equals focus with the same
    points as .npy."""
    from twinfocus.radar.scan import Scan
    from twinfocus.scene import paper_scene
    from twinfocus.sensors.trajectory_files import read_tum
    from twinfocus.twins.digital_twin.camera import DEFAULT_LEFT_CAMERA_POSITION_M

    cap = tmp_path / "cap"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "twinfocus.sensors.emulators",
            "capture",
            str(cap),
            "--rows",
            "12",
            "--n-samples",
            "64",
            "--tracking-error-mm",
            "0.5",
        ],
        check=True,
        capture_output=True,
    )
    tum = read_tum(cap / "trajectory.txt")
    # the ZED's pose is its body frame's: the TUM (optical) rotation times the optical -> body rotation
    r_body = tum.rotation_matrices() @ R_BODY_OPT.T
    from twinfocus.motion.trajectory import matrix_to_quat

    q_body = np.array([matrix_to_quat(r) for r in r_body])
    ref = paper_scene().object("reference").surface_points(2e-3)
    opt = ref - np.asarray(DEFAULT_LEFT_CAMERA_POSITION_M)
    ros = opt @ R_BODY_OPT.T
    cloud = np.concatenate([ros, np.full((2, 3), np.nan)])
    if cloud.shape[0] % 2:
        cloud = np.concatenate([cloud, np.full((1, 3), np.nan)])
    bag = write_zed_bag(
        tmp_path / "run", "mcap", tum.timestamps_ns, tum.position_m, q_body, clouds=[(int(tum.timestamps_ns[0]), cloud)]
    )
    for name, traj in [
        ("tum", ["--trajectory", str(cap / "trajectory.txt")]),
        ("bag", ["--trajectory", str(bag), "--pose-topic", POSE]),
    ]:
        assert (
            main(["convert", str(cap), *traj, "--out", str(tmp_path / f"{name}.npz"), "--quiet", "--n-samples", "64"])
            == 0
        )
    a, b = Scan.load(tmp_path / "tum.npz"), Scan.load(tmp_path / "bag.npz")
    assert np.allclose(a.positions, b.positions, atol=1e-9) and np.array_equal(a.data, b.data)
    c32 = cloud.astype(np.float32).astype(np.float64)  # the bag holds float32, as the ZED writes
    np.save(
        tmp_path / "ref.npy",
        np.stack([-c32[:, 1], -c32[:, 2], c32[:, 0]], axis=1) + np.asarray(DEFAULT_LEFT_CAMERA_POSITION_M),
    )
    out = {}
    for name, src in [("npy", str(tmp_path / "ref.npy")), ("bag", f"{bag}:{CLOUD}")]:
        rc = main(
            [
                "focus",
                str(tmp_path / "bag.npz"),
                "--reference-roi",
                "-0.085",
                "0.005",
                "-0.045",
                "0.045",
                "0.6",
                "--target-roi",
                "0.035",
                "0.105",
                "-0.045",
                "0.045",
                "0.6",
                "--size",
                "16",
                "--digital-twin",
                src,
                "--out",
                str(tmp_path / name),
                "--no-pictures",
                "--quiet",
                "--device",
                "cpu",
                "--no-cache",
            ]
        )
        # the library's warning reaches the user as one printed line
        assert "warning: reference point cloud: dropped" in capsys.readouterr().err
        assert rc == 0
        out[name] = np.load(tmp_path / name / "phase.npy")
    assert np.allclose(out["npy"], out["bag"], atol=1e-9)
    assert json.loads((tmp_path / "bag" / "metrics.json").read_text())


def test_focus_refuses_a_wrong_cloud_topic_in_one_line(bag, tmp_path, capsys):
    from twinfocus.radar.fmcw import Chirp
    from twinfocus.radar.scan import Scan

    path = bag[0]
    pos = np.zeros((3, 2, 3))
    pos[:, :, 0] = np.arange(3)[:, None] * 1e-3
    Scan(np.ones((3, 2, 8), np.complex64), pos, Chirp(n_samples=8)).save(tmp_path / "s.npz")
    for src, words in [
        (f"{path}:{POSE}", ["is geometry_msgs/msg/PoseStamped", CLOUD]),
        (f"{path}:/nope", ["no topic /nope", CLOUD]),
    ]:
        rc = main(["focus", str(tmp_path / "s.npz"), "--digital-twin", src, "--target-roi", "0", "0.1", "0", "0.1",
                   "0.6", "--out", str(tmp_path / "o"), "--quiet"])  # fmt: skip
        err = capsys.readouterr().err
        assert rc == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
        assert all(w in err for w in words), err
        assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_twin_takes_the_stereo_pair_and_camera_info_from_a_bag(tmp_path):
    """`twin BAG:LEFT BAG:RIGHT` (CameraInfo from the bag, default ZED pose) gives the cloud that
    `twin left.png right.png --camera camera.json` gives for the same rendered pair."""
    from twinfocus.scene import paper_scene
    from twinfocus.twins.digital_twin.camera import StereoCamera
    from twinfocus.twins.digital_twin.render import render_scene

    cam = StereoCamera.zed2i(640, 360)
    r = render_scene(paper_scene(), cam, seed=3)
    r.save(tmp_path / "stereo")
    stamps, pos, quat = zigzag(4)
    f, w, h = cam.left.fx, cam.left.width, cam.left.height
    assert cam.left.cx == (w - 1) / 2
    bag = write_zed_bag(
        tmp_path / "run", "sqlite3", stamps, pos, quat, pair=(stamps[1], r.left, r.right, f, cam.baseline_m)
    )
    roi = ["-0.15", "0.0", "-0.11", "0.12", "0.6"]
    # the bag's CameraInfo puts the principal point at w/2 (as info_msg writes it): the same in camera.json
    from twinfocus.twins.digital_twin.camera import Intrinsics

    eye = Intrinsics(f, f, w / 2, h / 2, w, h)
    StereoCamera(eye, eye, np.eye(3), np.array([-cam.baseline_m, 0, 0]), cam.scene_from_left).save(
        tmp_path / "cam.json"
    )
    st = tmp_path / "stereo"
    common = ["--seed-roi", *roi, "--quiet"]
    assert main(["twin", str(st / "left.png"), str(st / "right.png"), "--camera", str(tmp_path / "cam.json"),
                 "--points-out", str(tmp_path / "png.npy"), *common]) == 0  # fmt: skip
    assert main(["twin", f"{bag}:{LEFT}", f"{bag}:{RIGHT}", "--points-out", str(tmp_path / "bag.npy"), *common]) == 0
    a, b = np.load(tmp_path / "png.npy"), np.load(tmp_path / "bag.npy")
    assert a.shape[0] > 100 and np.array_equal(a, b)
