"""rosbag2 recordings (MCAP or SQLite storage) read with the ``rosbags`` library.

A *bag* is a rosbag2 folder holding ``metadata.yaml``, or one ``.mcap`` / ``.db3`` storage file.
Messages are deserialised with the definitions the bag carries (MCAP) or, where it carries none
(SQLite), with ``rosbags``' ROS 2 Humble types. The messages are taken apart by
:mod:`twinfocus.sensors.rosbag2`; see there for the frames.

- :func:`read_bag_poses`: a pose topic -> :class:`~twinfocus.motion.trajectory.Poses` (``convert
  --trajectory run.bag --pose-topic /zed/zed_node/pose``).
- :func:`read_bag_cloud`: a ``PointCloud2`` topic -> float64 (N, 3) in the camera's optical
  axes (``focus --digital-twin bag.mcap:/zed/zed_node/point_cloud/cloud_registered``).
- :func:`read_bag_stereo`: the left and right ``Image`` with their ``CameraInfo``.
- :func:`read_svo_poses`: a ZED SDK ``.svo`` / ``.svo2`` recording's tracked poses (needs ``pyzed``).

A *bag source* is ``BAG:TOPIC`` with the topic's leading slash, optionally ``@STAMP_NS`` for the
message whose header stamp is nearest that time (:func:`split_bag_source`).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import Poses
from twinfocus.sensors import rosbag2 as msgs

BAG_SUFFIXES = (".mcap", ".db3")
SVO_SUFFIXES = (".svo", ".svo2")


def is_bag(path: str | os.PathLike) -> bool:
    """A rosbag2 folder (``metadata.yaml`` inside) or a ``.mcap`` / ``.db3`` storage file."""
    p = Path(path)
    return (p.is_dir() and (p / "metadata.yaml").is_file()) or (p.is_file() and p.suffix.lower() in BAG_SUFFIXES)


class BagSource(NamedTuple):
    """``BAG:TOPIC[@STAMP_NS]`` taken apart: the bag's path, the topic, the stamp or None."""

    path: Path
    topic: str
    at_ns: int | None


def split_bag_source(text: str) -> BagSource | None:
    """``bag.mcap:/zed/zed_node/point_cloud/cloud_registered[@STAMP_NS]`` -> :class:`BagSource`;
    None for anything else (a plain file name)."""
    s = str(text)
    head, sep, topic = s.rpartition(":")
    if not sep or not head or not topic.startswith("/"):
        return None
    at_ns = None
    if "@" in topic:
        topic, _, stamp = topic.partition("@")
        try:
            at_ns = int(stamp)
        except ValueError:
            raise TwinFocusError(f"{s}: the time after '@' must be integer nanoseconds, got {stamp!r}") from None
    return BagSource(Path(head), topic, at_ns)


@contextmanager
def open_bag(path: str | os.PathLike) -> Iterator[Any]:
    """An open ``rosbags`` ``AnyReader`` over the bag, with clear errors for a missing or unreadable one."""
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    p = Path(path)
    if not is_bag(p):
        raise TwinFocusError(
            f"{p}: not a rosbag2 recording (a folder with metadata.yaml, or a .mcap / .db3 file)"
            if p.exists()
            else f"{p}: no such rosbag2 recording"
        )
    try:
        reader = AnyReader([p], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError) as exc:
        raise TwinFocusError(f"{p}: not a readable rosbag2 recording ({exc})") from None
    try:
        yield reader
    finally:
        reader.close()


def bag_topics(reader: Any) -> dict[str, str]:
    """topic -> message type of every connection in an open bag."""
    return {c.topic: c.msgtype for c in reader.connections}


def _listing(topics: dict[str, str], types: tuple[str, ...]) -> str:
    hits = [f"{t} ({ty.replace('/msg/', '/')})" for t, ty in sorted(topics.items()) if ty in types]
    return ", ".join(hits) if hits else "none"


def _connections(reader: Any, path: Path, topic: str, types: tuple[str, ...], what: str) -> tuple[list, str]:
    topics = bag_topics(reader)
    if topic not in topics:
        raise TwinFocusError(f"{path}: no topic {topic}; its {what} topics: {_listing(topics, types)}")
    if topics[topic] not in types:
        raise TwinFocusError(
            f"{path}: {topic} is {topics[topic]}, not a {what} message; its {what} topics: {_listing(topics, types)}"
        )
    return [c for c in reader.connections if c.topic == topic], topics[topic]


def _messages(reader: Any, conns: list) -> Iterator[Any]:
    from rosbags.serde import SerdeError

    for conn, _, raw in reader.messages(connections=conns):
        try:
            yield reader.deserialize(raw, conn.msgtype)
        except (SerdeError, ValueError, KeyError) as exc:
            raise TwinFocusError(f"{conn.topic}: a {conn.msgtype} message does not deserialise ({exc})") from None


def read_bag_poses(path: str | os.PathLike, topic: str, child_frame: str | None = None) -> tuple[Poses, str]:
    """The poses on ``topic`` in time order, and a description of their frame ("map -> zed_camera_link").

    child_frame : for a ``tf2_msgs/TFMessage`` topic, the child frame to follow (its parent must
    not change); needed when the topic carries several. Poses of a non-optical child frame get
    the rotation to its optical axes (:mod:`twinfocus.sensors.rosbag2`).
    """
    p = Path(path)
    with open_bag(p) as reader:
        conns, msgtype = _connections(reader, p, topic, msgs.POSE_TYPES, "pose")
        records = [r for m in _messages(reader, conns) for r in msgs.pose_records(msgtype, m, child_frame)]
    if msgtype == "tf2_msgs/msg/TFMessage":
        children = sorted({r.child_frame_id for r in records})
        if child_frame is None and len(children) > 1:
            raise TwinFocusError(
                f"{p}: {topic} carries several frames ({', '.join(children)}); choose one with --pose-frame"
            )
        if not records:
            raise TwinFocusError(f"{p}: {topic} has no transform of frame {child_frame}")
    elif not records:
        raise TwinFocusError(f"{p}: {topic} has no messages")
    parents = sorted({r.frame_id for r in records})
    if len(parents) > 1:
        raise TwinFocusError(f"{p}: {topic}'s poses change frame ({', '.join(parents)}); one frame is needed")
    child = records[0].child_frame_id or "(the camera)"
    optical = not msgs.is_optical(child)
    try:
        poses = msgs.poses_from_records(records, optical=optical)
    except TwinFocusError as exc:
        raise TwinFocusError(f"{p}: {topic}: {exc}") from None
    return poses, f"{parents[0] or '(unnamed)'} -> {child}{' (optical axes)' if optical else ''}"


class BagCloud(NamedTuple):
    """A point cloud taken from a bag: points float64 (N, 3), metres, optical axes of the
    message's frame (NaN rows kept); the message's frame, header stamp, the bag's receive time
    of it (``log_ns``, what ``@STAMP_NS`` selects by), its position on the topic (0 = first), and how it was chosen."""

    points: np.ndarray
    frame_id: str
    stamp_ns: int
    log_ns: int
    position: int
    chosen: str


def read_bag_cloud(path: str | os.PathLike, topic: str, at_ns: int | None = None) -> BagCloud:
    """One ``PointCloud2`` of ``topic``: the one recorded nearest ``at_ns`` (the bag's receive
    time, ns; only that one is deserialised, a ZED cloud being ~15 MB), or the first."""
    from rosbags.serde import SerdeError

    p = Path(path)
    with open_bag(p) as reader:
        conns, msgtype = _connections(reader, p, topic, (msgs.CLOUD_TYPE,), "PointCloud2")
        best = None
        for i, (_, t, raw) in enumerate(reader.messages(connections=conns)):
            if best is None or (at_ns is not None and abs(t - at_ns) < abs(best[1] - at_ns)):
                best = (i, t, raw)
            if at_ns is None:
                break  # the first is the one
        if best is None:
            raise TwinFocusError(f"{p}: {topic} has no messages")
        i, t, raw = best
        try:
            m = reader.deserialize(raw, msgtype)
        except (SerdeError, ValueError, KeyError) as exc:
            raise TwinFocusError(f"{topic}: a {msgtype} message does not deserialise ({exc})") from None
    try:
        xyz = msgs.pointcloud2_xyz(m)
    except TwinFocusError as exc:
        raise TwinFocusError(f"{p}: {topic}: {exc}") from None
    chosen = "the first message" if at_ns is None else f"the message recorded nearest {at_ns} ns"
    return BagCloud(
        msgs.optical_points(xyz, m.header.frame_id), m.header.frame_id, msgs.stamp_ns(m.header), t, i, chosen
    )


def bag_source_sha256(source: BagSource) -> str:
    """Digest naming a bag source's cloud for the template cache: the cloud's points, frame and stamp."""
    cloud = read_bag_cloud(source.path, source.topic, source.at_ns)
    h = hashlib.sha256(np.ascontiguousarray(cloud.points).tobytes())
    h.update(f"{cloud.frame_id}|{cloud.stamp_ns}".encode())
    return h.hexdigest()


class BagStereo(NamedTuple):
    """A stereo pair from a bag: stamp_ns, left and right uint8 (H, W, 3) BGR, and each eye's
    :class:`~twinfocus.sensors.rosbag2.CameraModel`."""

    stamp_ns: int
    left: np.ndarray
    right: np.ndarray
    left_model: msgs.CameraModel
    right_model: msgs.CameraModel


def camera_info_topic(image_topic: str) -> str:
    """The ``CameraInfo`` beside an image topic (``.../left/image_rect_color`` -> ``.../left/camera_info``)."""
    return image_topic.rsplit("/", 1)[0] + "/camera_info"


def read_bag_stereo(path: str | os.PathLike, left_topic: str, right_topic: str, at_ns: int | None = None) -> BagStereo:
    """The first left image (or the one nearest ``at_ns``) with the right image of the same header
    stamp (else the nearest), and the CameraInfo beside each topic."""
    p = Path(path)
    with open_bag(p) as reader:
        images = {}
        for side, topic in (("left", left_topic), ("right", right_topic)):
            conns, _ = _connections(reader, p, topic, (msgs.IMAGE_TYPE,), "Image")
            images[side] = [(msgs.stamp_ns(m.header), m) for m in _messages(reader, conns)]
            if not images[side]:
                raise TwinFocusError(f"{p}: {topic} has no messages")
        infos = {}
        for side, topic in (("left", left_topic), ("right", right_topic)):
            info_topic = camera_info_topic(topic)
            conns, _ = _connections(reader, p, info_topic, (msgs.CAMERA_INFO_TYPE,), "CameraInfo")
            first = next(_messages(reader, conns), None)
            if first is None:
                raise TwinFocusError(f"{p}: {info_topic} has no messages")
            infos[side] = msgs.camera_model(first)
    lt = np.array([t for t, _ in images["left"]])
    li = 0 if at_ns is None else int(np.argmin(np.abs(lt - at_ns)))
    t_left, left_msg = images["left"][li]
    rt = np.array([t for t, _ in images["right"]])
    t_right, right_msg = images["right"][int(np.argmin(np.abs(rt - t_left)))]
    if t_right != t_left:
        raise TwinFocusError(
            f"{p}: no {right_topic} image has the stamp of the left one ({t_left} ns; nearest {t_right} ns)"
        )
    return BagStereo(t_left, msgs.image_bgr(left_msg), msgs.image_bgr(right_msg), infos["left"], infos["right"])


def read_svo_poses(path: str | os.PathLike) -> Poses:
    """A ZED SDK recording's tracked poses (the left camera, ``IMAGE`` axes, confidence kept),
    through ``pyzed`` (:class:`~twinfocus.sensors.zed.ZedSdkCamera`)."""
    from twinfocus.sensors.zed import (  # lazy: twinfocus.sensors.zed (+0.05 s on twinfocus twin --help)
        ZedSdkCamera,
        poses_from_samples,
    )

    p = Path(path)
    if not p.is_file():
        raise TwinFocusError(f"{p}: no such SVO recording")
    with ZedSdkCamera(svo_path=str(p)) as cam:
        try:
            return poses_from_samples(cam.poses())
        except TwinFocusError as exc:
            raise TwinFocusError(f"{p}: {exc}") from None


def read_any_trajectory(
    path: str | os.PathLike, fmt: str = "auto", pose_topic: str | None = None, pose_frame: str | None = None
) -> tuple[Poses, str]:
    """``convert --trajectory``: a TUM / EuRoC file, a rosbag2 (with ``pose_topic``) or a ZED SVO
    recording -> (poses, a line saying what was read)."""
    p = Path(path)
    if is_bag(p):
        if not pose_topic:
            with open_bag(p) as reader:
                listing = _listing(bag_topics(reader), msgs.POSE_TYPES)
            raise TwinFocusError(f"{p}: a rosbag2 needs --pose-topic; its pose topics: {listing}")
        poses, frame = read_bag_poses(p, pose_topic, pose_frame)
        return poses, f"{len(poses)} poses from {p}:{pose_topic}, frame {frame}"
    if pose_topic or pose_frame:
        raise TwinFocusError(f"--pose-topic / --pose-frame are for a rosbag2 recording, and {p} is not one")
    if p.suffix.lower() in SVO_SUFFIXES:
        poses = read_svo_poses(p)
        return poses, f"{len(poses)} poses from the ZED recording {p}"
    from twinfocus.sensors.trajectory_files import (
        read_trajectory,  # lazy: twinfocus.sensors.trajectory_files (+0.02 s on twinfocus twin --help)
    )

    poses = read_trajectory(p, fmt)
    return poses, f"{len(poses)} poses from {p}"
