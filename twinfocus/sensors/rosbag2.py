"""ROS 2 messages as the ZED ROS 2 wrapper records them, turned into arrays (no file access here).

The bag itself is opened by :mod:`twinfocus.sensors.rosbag2_files` (the ``rosbags`` library);
this module takes the deserialised messages (any object with the ROS field names) apart:

- poses: ``geometry_msgs/msg/PoseStamped``, ``geometry_msgs/msg/PoseWithCovarianceStamped``,
  ``nav_msgs/msg/Odometry`` and ``tf2_msgs/msg/TFMessage`` (one named child frame);
- ``sensor_msgs/msg/PointCloud2``: the float32/float64 ``x y z`` fields at any ``point_step``
  and ``row_step``, invalid points kept as the NaN rows the ZED writes;
- ``sensor_msgs/msg/Image`` (``bgra8`` as the ZED publishes, ``bgr8``, ``rgb8``, ``rgba8``,
  ``mono8``) and ``sensor_msgs/msg/CameraInfo`` (the rectified projection ``P``).

Frames. ROS frames are x forward, y left, z up (REP 103); twinfocus's camera and scene frames
follow OpenCV (x right, y down, z forward), as the ZED SDK's ``IMAGE`` system and the
``*_optical_frame`` frames do. A pose of a non-optical child frame gets the fixed rotation to
its optical axes appended, and a cloud in a non-optical frame is rotated into them
(:func:`optical_points`), so identity extrinsics mean the radar looks where the camera looks.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import Poses, matrix_to_quat, quat_multiply

POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "nav_msgs/msg/Odometry",
    "tf2_msgs/msg/TFMessage",
)
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
IMAGE_TYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"

#: Columns: the optical frame's x, y, z axes in the ROS body frame (x right = -y_body,
#: y down = -z_body, z forward = x_body); ``p_body = R_BODY_OPTICAL @ p_optical``.
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
#: The same rotation as a quaternion (x, y, z, w).
Q_BODY_OPTICAL = matrix_to_quat(R_BODY_OPTICAL)

# sensor_msgs/PointField datatypes read for x, y, z
_FIELD_DTYPES = {7: "f4", 8: "f8"}


class PoseRecord(NamedTuple):
    """One pose message: stamp_ns (header), parent frame, child frame, position (3,), quat (x, y, z, w)."""

    stamp_ns: int
    frame_id: str
    child_frame_id: str
    position_m: np.ndarray
    quat_xyzw: np.ndarray


def stamp_ns(header: Any) -> int:
    """A ``std_msgs/Header``'s stamp as integer nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def is_optical(frame_id: str) -> bool:
    """Whether a frame follows the optical convention (the ZED's ``*_optical_frame``)."""
    return frame_id.rstrip("/").endswith("optical_frame")


def _pose_arrays(pose: Any) -> tuple[np.ndarray, np.ndarray]:
    p, q = pose.position, pose.orientation
    return np.array([p.x, p.y, p.z], np.float64), np.array([q.x, q.y, q.z, q.w], np.float64)


def pose_records(msgtype: str, msg: Any, child_frame: str | None = None) -> list[PoseRecord]:
    """The poses one message holds: one for PoseStamped / PoseWithCovarianceStamped / Odometry,
    those of ``child_frame`` (all, when None) for a TFMessage."""
    if msgtype == "geometry_msgs/msg/PoseStamped":
        pos, quat = _pose_arrays(msg.pose)
        return [PoseRecord(stamp_ns(msg.header), msg.header.frame_id, "", pos, quat)]
    if msgtype == "geometry_msgs/msg/PoseWithCovarianceStamped":
        pos, quat = _pose_arrays(msg.pose.pose)
        return [PoseRecord(stamp_ns(msg.header), msg.header.frame_id, "", pos, quat)]
    if msgtype == "nav_msgs/msg/Odometry":
        pos, quat = _pose_arrays(msg.pose.pose)
        return [PoseRecord(stamp_ns(msg.header), msg.header.frame_id, msg.child_frame_id, pos, quat)]
    if msgtype == "tf2_msgs/msg/TFMessage":
        out = []
        for tf in msg.transforms:
            if child_frame is not None and tf.child_frame_id != child_frame:
                continue
            t, r = tf.transform.translation, tf.transform.rotation
            out.append(
                PoseRecord(
                    stamp_ns(tf.header),
                    tf.header.frame_id,
                    tf.child_frame_id,
                    np.array([t.x, t.y, t.z], np.float64),
                    np.array([r.x, r.y, r.z, r.w], np.float64),
                )
            )
        return out
    raise TwinFocusError(f"{msgtype} holds no pose (use one of {', '.join(POSE_TYPES)})")


def poses_from_records(records: list[PoseRecord], optical: bool):
    """:class:`~twinfocus.motion.trajectory.Poses` from pose records in time order (stably sorted by
    header stamp, as a bag stores messages by receive time). ``optical``: append
    :data:`Q_BODY_OPTICAL` so each pose is that of the child's optical axes."""
    if not records:
        raise TwinFocusError("no poses")
    order = np.argsort(np.array([r.stamp_ns for r in records], np.int64), kind="stable")
    ts = np.array([records[i].stamp_ns for i in order], np.int64)
    pos = np.array([records[i].position_m for i in order], np.float64)
    quat = np.array([records[i].quat_xyzw for i in order], np.float64)
    if optical:
        quat = quat_multiply(quat, np.broadcast_to(Q_BODY_OPTICAL, quat.shape))
    return Poses(ts, pos, quat)


def pointcloud2_xyz(msg: Any) -> np.ndarray:
    """The ``x y z`` of a ``sensor_msgs/PointCloud2``: float64 (height * width, 3), metres, row
    by row, invalid points as NaN rows (kept: the conditioning drops and counts them)."""
    fields = {f.name: f for f in msg.fields}
    missing = [n for n in "xyz" if n not in fields]
    if missing:
        have = ", ".join(fields) or "none"
        raise TwinFocusError(f"the PointCloud2 has no {', '.join(missing)} field (fields: {have})")
    h, w = int(msg.height), int(msg.width)
    step, row_step = int(msg.point_step), int(msg.row_step)
    data = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, np.ndarray) else msg.data, np.uint8)
    if h * w == 0:
        return np.zeros((0, 3), np.float64)
    if row_step < w * step or data.size < (h - 1) * row_step + w * step:
        raise TwinFocusError(
            f"the PointCloud2's data ({data.size} bytes) is shorter than {h} rows of {w} points of {step} bytes"
        )
    out = np.empty((h, w, 3), np.float64)
    for j, name in enumerate("xyz"):
        f = fields[name]
        kind = _FIELD_DTYPES.get(int(f.datatype))
        if kind is None:
            raise TwinFocusError(
                f"the PointCloud2's {name} field has datatype {f.datatype}; float32 (7) or float64 (8)"
            )
        dt = np.dtype(kind).newbyteorder(">" if msg.is_bigendian else "<")
        if int(f.offset) + dt.itemsize > step:
            raise TwinFocusError(
                f"the PointCloud2's {name} field (offset {f.offset}) lies outside its point_step {step}"
            )
        # a strided view over rows and points: any point_step and row padding, no copy of the blob
        view = np.ndarray((h, w), dtype=dt, buffer=data, offset=int(f.offset), strides=(row_step, step))
        out[:, :, j] = view
    return out.reshape(-1, 3)


def optical_points(points: np.ndarray, frame_id: str) -> np.ndarray:
    """Points (N, 3) of a camera frame in its optical axes (unchanged when already optical)."""
    p = np.asarray(points, np.float64)
    return p if is_optical(frame_id) else p @ R_BODY_OPTICAL


_CHANNELS = {"bgra8": (4, (0, 1, 2)), "rgba8": (4, (2, 1, 0)), "bgr8": (3, (0, 1, 2)), "rgb8": (3, (2, 1, 0))}


def image_bgr(msg: Any) -> np.ndarray:
    """A ``sensor_msgs/Image`` as uint8 (H, W, 3) BGR (the twin's picture convention)."""
    h, w, step, enc = int(msg.height), int(msg.width), int(msg.step), str(msg.encoding).lower()
    data = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, np.ndarray) else msg.data, np.uint8)
    if data.size < h * step:
        raise TwinFocusError(f"the {enc} image's data ({data.size} bytes) is shorter than {h} rows of {step}")
    rows = data[: h * step].reshape(h, step)
    if enc in ("mono8", "8uc1"):
        grey = rows[:, :w]
        return np.repeat(grey[:, :, None], 3, axis=2).copy()
    if enc not in _CHANNELS:
        raise TwinFocusError(f"image encoding {msg.encoding!r} is not read (bgra8, bgr8, rgba8, rgb8, mono8)")
    n, order = _CHANNELS[enc]
    px = rows[:, : w * n].reshape(h, w, n)
    return np.ascontiguousarray(px[:, :, list(order)])


class CameraModel(NamedTuple):
    """A rectified eye from ``CameraInfo``: width, height, fx, fy, cx, cy (pixels, from ``P``)
    and ``tx_m`` = -P[0, 3] / fx (the right eye's baseline, 0 for the left)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    tx_m: float


def camera_model(msg: Any) -> CameraModel:
    """A ``sensor_msgs/CameraInfo``'s rectified projection ``P`` (the ZED's ``image_rect_*`` are
    rectified, so ``P`` is their camera; ``K`` is used when ``P`` is all zero)."""
    p = np.asarray(msg.p, np.float64).reshape(-1)
    k = np.asarray(msg.k, np.float64).reshape(-1)
    if p.size == 12 and p[0] > 0:
        fx, fy, cx, cy, tx = p[0], p[5], p[2], p[6], -p[3] / p[0]
    elif k.size == 9 and k[0] > 0:
        fx, fy, cx, cy, tx = k[0], k[4], k[2], k[5], 0.0
    else:
        raise TwinFocusError("the CameraInfo has neither a projection P nor a camera matrix K")
    return CameraModel(int(msg.width), int(msg.height), float(fx), float(fy), float(cx), float(cy), float(tx))
