"""An emulated capture's camera as a ZED 2i records it: a rosbag2 of the ZED ROS 2 wrapper's topics.

    python -m twinfocus.sensors.emulators.zed_bag hand --out hand_zed --lead-ms 60 --cloud-offset-mm 2 -3 0

reads what ``python -m twinfocus.sensors.emulators capture hand`` wrote (``hand/trajectory.txt``,
the radar's track as a tracker saw it, on the radar's clock, and ``hand/scatterers.npy``, the
scene) and writes the bag a ZED 2i bolted beside the radar would have recorded (MCAP storage,
written by ``rosbags``). The camera rides ``--lever-arm-mm`` from the radar (the radar's origin
in the left camera's axes, ``translation_m`` of an extrinsics file; default 60 80 0: the camera
6 cm left of and 8 cm above the radar, where ``focus`` places a bag's cloud,
:data:`twinfocus.twins.digital_twin.camera.DEFAULT_LEFT_CAMERA_POSITION_M`), so ``convert`` needs that
extrinsics file to put the radar back on its path.

- ``/zed/zed_node/pose`` (``geometry_msgs/PoseStamped``, frame ``map``, ROS axes: x forward,
  y left, z up), one pose per radar frame. The camera's clock runs ``--lead-ms`` ahead of the
  radar's: it started that much earlier, standing still, and stopped that much later, so the
  first pose is not the first radar frame's (``convert --align start`` is that far off;
  ``--align scan`` measures it);
- ``/zed/zed_node/point_cloud/cloud_registered`` (``sensor_msgs/PointCloud2``, frame
  ``zed_left_camera_frame``, x y z rgb float32), one message at the sweep's middle: the
  reference's points as the camera saw them from where the lever arm puts it, shifted by
  ``--cloud-offset-mm`` (the camera's uncalibrated offset from the radar, x y z in the scene's
  axes, mm; what ``twinfocus rig`` measures).

The reference is the capture's first :data:`~twinfocus.sensors.emulators.rig.N_REFERENCE_SCATTERERS`
scatterers (the T); ``--reference-only`` captures hold only those.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import matrix_to_quat, quat_to_matrix
from twinfocus.sensors.emulators.rig import N_REFERENCE_SCATTERERS
from twinfocus.sensors.rosbag2 import R_BODY_OPTICAL
from twinfocus.sensors.trajectory_files import read_tum

POSE_TOPIC = "/zed/zed_node/pose"
CLOUD_TOPIC = "/zed/zed_node/point_cloud/cloud_registered"
#: where ``focus`` places a bag's cloud's camera in the scene frame, metres: the digital twin's
#: default left camera, twinfocus.twins.digital_twin.camera.DEFAULT_LEFT_CAMERA_POSITION_M (not imported:
#: the sensors sit below the digital twin; tests/test_zed_bag_emulator.py checks they agree)
BAG_CLOUD_CAMERA_M = (-0.06, -0.08, 0.0)
#: poses the camera records before the radar's first frame and after its last
PAD_POSES = 4
#: the camera sees each of the scene's metal balls as a small disc of points facing it: this
#: radius (metres) and this many points round its centre (a stereo cloud of a 12 cm object holds
#: hundreds of points; the twin's conditioning wants at least 20)
BALL_RADIUS_M = 0.002
BALL_RING = 6


def ball_points(centres_m: np.ndarray) -> np.ndarray:
    """The camera's cloud of point scatterers: each centre (float64 (J, 3) metres) and a ring of
    :data:`BALL_RING` points :data:`BALL_RADIUS_M` round it in its x/y plane; float64 (J * 7, 3)."""
    a = 2 * np.pi * np.arange(BALL_RING) / BALL_RING
    ring = np.concatenate([[[0.0, 0.0, 0.0]], BALL_RADIUS_M * np.stack([np.cos(a), np.sin(a), 0 * a], axis=1)])
    return (np.asarray(centres_m, np.float64)[:, None, :] + ring[None]).reshape(-1, 3)


def camera_track(timestamps_ns: np.ndarray, position_m: np.ndarray, quat_xyzw: np.ndarray, lead_ns: int):
    """The camera's own recording of a track on the radar's clock: it starts ``lead_ns`` before
    the first pose (standing still there, :data:`PAD_POSES` poses) and stops ``lead_ns`` after the
    last. Returns (stamps int64 (M + 2 pad,), positions float64 (., 3), quaternions (., 4))."""
    pad = PAD_POSES
    ts = np.asarray(timestamps_ns, np.int64)
    before = ts[0] - lead_ns + np.arange(pad) * lead_ns // pad
    after = ts[-1] + (np.arange(pad) + 1) * lead_ns // pad
    pos = np.concatenate([np.repeat(position_m[:1], pad, 0), position_m, np.repeat(position_m[-1:], pad, 0)])
    quat = np.concatenate([np.repeat(quat_xyzw[:1], pad, 0), quat_xyzw, np.repeat(quat_xyzw[-1:], pad, 0)])
    return np.concatenate([before, ts, after]), pos, quat


def write_zed_bag(
    out: Path,
    timestamps_ns: np.ndarray,
    position_m: np.ndarray,
    quat_xyzw: np.ndarray,
    cloud_scene_m: np.ndarray,
    lever_arm_m=(0.06, 0.08, 0.0),
) -> Path:
    """Write the bag: the radar's poses (optical axes in the scene frame: float64 (M, 3) metres,
    (M, 4) x y z w) moved to the camera's (``lever_arm_m``: the radar's origin in the camera's
    axes, metres) and turned into the ZED wrapper's body axes in a ROS ``map`` frame, and one
    cloud (float64 (N, 3) metres, scene frame) in the left camera's body axes at the middle
    stamp, seen from the camera at the middle pose's place in a still scene (the first pose's)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts_store = get_typestore(Stores.ROS2_HUMBLE)
    T = ts_store.types
    g = "geometry_msgs/msg/"

    def header(ns: int, frame: str):
        return T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame
        )

    # the camera's origin: p_camera = R p_radar + t puts the radar's origin at t in the camera's axes
    arm = np.asarray(lever_arm_m, np.float64)
    rot = np.stack([quat_to_matrix(np.asarray(q) / np.linalg.norm(q)) for q in quat_xyzw])
    cam = np.asarray(position_m, np.float64) - np.einsum("mij,j->mi", rot, arm)
    # the scene's axes (x right, y down, z forward) are the optical axes; a ROS map's are the body's
    p_map = cam @ R_BODY_OPTICAL.T
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        pose_c = w.add_connection(POSE_TOPIC, "geometry_msgs/msg/PoseStamped", typestore=ts_store)
        cloud_c = w.add_connection(CLOUD_TOPIC, "sensor_msgs/msg/PointCloud2", typestore=ts_store)
        for ns, p, r in zip(np.asarray(timestamps_ns).tolist(), p_map, rot, strict=True):
            r_body = R_BODY_OPTICAL @ r @ R_BODY_OPTICAL.T
            qb = matrix_to_quat(r_body)
            pose = T[g + "Pose"](
                position=T[g + "Point"](x=p[0], y=p[1], z=p[2]),
                orientation=T[g + "Quaternion"](x=qb[0], y=qb[1], z=qb[2], w=qb[3]),
            )
            msg = T[g + "PoseStamped"](header=header(ns, "map"), pose=pose)
            w.write(pose_c, ns + 5_000_000, ts_store.serialize_cdr(msg, pose_c.msgtype))  # received 5 ms later
        mid = int(timestamps_ns[len(timestamps_ns) // 2])
        # focus puts a bag's cloud at the default camera place (the aperture's centre less the arm)
        opt = np.asarray(cloud_scene_m, np.float64) - np.asarray(BAG_CLOUD_CAMERA_M)
        rec = np.zeros(len(opt), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4")])
        rec["x"], rec["y"], rec["z"] = (opt @ R_BODY_OPTICAL.T).T
        pf = T["sensor_msgs/msg/PointField"]
        fields = [pf(name=c, offset=4 * i, datatype=7, count=1) for i, c in enumerate("x y z rgb".split())]
        cloud = T["sensor_msgs/msg/PointCloud2"](
            header=header(mid, "zed_left_camera_frame"),
            height=1,
            width=len(opt),
            fields=fields,
            is_bigendian=False,
            point_step=16,
            row_step=16 * len(opt),
            data=np.frombuffer(rec.tobytes(), np.uint8),
            is_dense=True,
        )
        w.write(cloud_c, mid + 5_000_000, ts_store.serialize_cdr(cloud, cloud_c.msgtype))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("capture", type=Path, help="an emulated capture folder (trajectory.txt, scatterers.npy)")
    p.add_argument("--out", type=Path, required=True, help="the bag to write (a folder; refused if it exists)")
    p.add_argument("--lead-ms", type=float, default=60.0, help="how long the camera ran before the radar (ms)")
    p.add_argument(
        "--cloud-offset-mm", type=float, nargs=3, default=(2.0, -3.0, 0.0), metavar=("DX", "DY", "DZ"),
        help="where the camera's cloud lies off the radar's scene, mm (default 2 -3 0)",
    )  # fmt: skip
    p.add_argument(
        "--lever-arm-mm", type=float, nargs=3, default=(60.0, 80.0, 0.0), metavar=("X", "Y", "Z"),
        help="the radar's origin in the left camera's axes, mm (default 60 80 0)",
    )  # fmt: skip
    args = p.parse_args(argv)
    try:
        if args.out.exists():
            raise TwinFocusError(f"{args.out}: exists; choose another --out")
        if not np.isfinite(args.lead_ms) or args.lead_ms < 0:
            raise TwinFocusError(f"--lead-ms must be a finite number >= 0, got {args.lead_ms}")
        track = read_tum(args.capture / "trajectory.txt")
        scatterers = args.capture / "scatterers.npy"
        if not scatterers.is_file():
            raise TwinFocusError(f"{scatterers}: no such file (not an emulated capture?)")
        ref = np.load(scatterers, allow_pickle=False)[:N_REFERENCE_SCATTERERS]
        ts, pos, quat = camera_track(track.timestamps_ns, track.position_m, track.quat_xyzw, round(args.lead_ms * 1e6))
        arm = np.asarray(args.lever_arm_mm) * 1e-3
        if not np.isfinite(arm).all() or np.abs(arm).max() > 1.0:
            raise TwinFocusError(f"--lever-arm-mm must be finite and within 1000 mm, got {args.lever_arm_mm}")
        write_zed_bag(args.out, ts, pos, quat, ball_points(ref) + np.asarray(args.cloud_offset_mm) * 1e-3, arm)
    except TwinFocusError as exc:
        print(f"zed_bag: {exc}", file=sys.stderr)
        return 2
    print(
        f"wrote {args.out}: {len(ts)} poses on {POSE_TOPIC} (camera clock {args.lead_ms:g} ms ahead), "
        f"{len(ref) * (BALL_RING + 1)} points on {CLOUD_TOPIC}",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
