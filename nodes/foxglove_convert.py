"""Graph messages -> Foxglove's well-known schemas: the one conversion the bridge, ``twinfocus
export --to foxglove`` and ``record --foxglove`` share.

:class:`FoxgloveConverter` turns each typed message (``msgs.messages``) into zero or more
:class:`FoxgloveMessage` records: a Foxglove topic, its schema (name, encoding, bytes) and the
encoded payload. The sinks only move bytes: the bridge logs them on ``foxglove.Channel``s of its
WebSocket server, the MCAP writers (:meth:`msgs.mcap_log.LogWriter.write_encoded`) register the
schema and add the message. Conversions:

=====================  ==================================  ====================================
graph topic            Foxglove topic                      schema
=====================  ==================================  ====================================
``image/focused``      ``/image/<name>`` (``target``,      ``foxglove.CompressedImage`` PNG,
                       ``target_uncorrected``,             ``|image| / max`` through inferno
                       ``reference``, ...)                 (``nodes.visualizer.amplitude_png``)
``twin/template``      ``/twin/template``                  same, of the template amplitude
                       ``/twin/points``                    ``foxglove.PointCloud`` x y z
                                                           intensity (float32), scene frame
``vio/pose``           ``/vio/pose``                       ``foxglove.PoseInFrame``
                       ``/vio/trajectory``                 ``foxglove.SceneUpdate``: the track
                                                           so far as a line strip (every
                                                           ``trajectory_every`` poses)
                       ``/vio/confidence``                 JSON ``{confidence}``
``sar/measurement``    ``/sar/phase_centres``              ``foxglove.PointCloud`` of the K
                                                           phase centres x y z (float32)
                       ``/sar/quality``                    JSON ``{index, pose_gap_ms}``
``autofocus/result``   ``/autofocus/result``               JSON: ``phase_rad`` per position,
                                                           ``loss_history``, ``metrics``,
                                                           ``timing_s`` (plottable numbers)
``camera/stereo``      ``/camera/left``                    ``foxglove.RawImage`` mono8 / rgb8
``graph/status``       ``/log``                            ``foxglove.Log``: a node's state
                                                           change, status message or new loss
``vio/pose``           ``/tf``                             ``foxglove.FrameTransform``: scene
(and calibration)                                          -> radar (the pose), radar -> camera
                                                           (``calibration``'s extrinsics, once)
=====================  ==================================  ====================================

The digital twin's point cloud travels on no topic of the graph; ``/twin/points`` shows the
template's pixels above ``points_threshold`` of its peak on the plane ``z_m`` (for a digital
twin that is the cloud rendered as the radar should see it). ``radar/frame`` (raw IF samples)
has no Foxglove picture and is left out.

One clock (:class:`SensorClock`): every record's MCAP log time, publish time and Foxglove
``timestamp`` field (JSON channels: ``timestamp`` ``{sec, nsec}``) are the same time, the
sensors' clock. A sensor message (radar frame, pose, camera frame, measurement) is at its header
stamp; a simulation's stamps start at 0, so they are shifted to put the first sensor message at
the wall-clock time it was logged (a viewer shows 1970 otherwise). A computed message (images,
the template, the solver's result, node states) is at the sensor time of the latest sensor
message before it.
"""

from __future__ import annotations

import json
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from foxglove.messages import (
    Color,
    CompressedImage,
    FrameTransform,
    LinePrimitive,
    Log,
    LogLevel,
    PackedElementField,
    PackedElementFieldNumericType,
    Point3,
    PointCloud,
    PoseInFrame,
    Quaternion,
    RawImage,
    SceneEntity,
    SceneUpdate,
    Timestamp,
    Vector3,
)
from foxglove.messages import Pose as FPose

import msgs
from msgs.mcap_log import LogReader, LogWriter
from msgs.schema import MessageError
from nodes.visualizer import amplitude_png
from twinfocus.errors import TwinFocusError
from twinfocus.sensors.extrinsics import RadarCameraExtrinsics

PROTOBUF = "protobuf"
JSON = "json"

#: a Foxglove time in a JSON message
_TIME_SCHEMA = {
    "type": "object",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0}},
    "required": ["sec", "nsec"],
}


def _record_schema(**properties: dict) -> dict:
    """The JSON schema of a record of ``timestamp`` and ``properties`` (name -> schema), all required."""
    return {
        "type": "object",
        "properties": {"timestamp": _TIME_SCHEMA, **properties},
        "required": ["timestamp", *properties],
    }


_TEXT = {"type": "string"}
_NUMBERS = {"type": "object", "additionalProperties": {"type": "number"}}

#: JSON schemas of the plottable-number channels (Foxglove draws them in its Plot panel)
JSON_SCHEMAS: dict[str, dict] = {
    "twinfocus.AutofocusResult": _record_schema(
        scan_id=_TEXT,
        method=_TEXT,
        phase_rad={
            "type": "array",
            "items": {"type": "number"},
            "description": "estimated phase per radar position, rad",
        },
        loss_history={"type": "array", "items": {"type": "number"}, "description": "loss per iteration"},
        metrics=_NUMBERS,
        timing_s=_NUMBERS,
    ),
    "twinfocus.PoseConfidence": _record_schema(confidence={"type": "number", "minimum": 0, "maximum": 1}),
    "twinfocus.MeasurementQuality": _record_schema(
        scan_id=_TEXT,
        index={"type": "integer"},
        pose_gap_ms={"type": "number", "description": "width of the pose interval the position was interpolated over"},
    ),
}


@dataclass(frozen=True)
class FoxgloveMessage:
    """One Foxglove record: ``topic``, schema (``schema_name``, ``schema_encoding``
    ``protobuf`` / ``jsonschema``, ``schema_data`` bytes), ``message_encoding`` (``protobuf`` /
    ``json``), ``data`` (encoded payload) and ``log_time_ns``."""

    topic: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str
    data: bytes
    log_time_ns: int

    def write_to(self, writer, publish_time_ns: int | None = None) -> None:
        """Append to a :class:`msgs.mcap_log.LogWriter` on its own schema's channel (publish
        time: the log time unless given)."""
        writer.write_encoded(
            self.topic,
            self.schema_name,
            self.schema_encoding,
            self.schema_data,
            self.message_encoding,
            self.data,
            self.log_time_ns,
            self.log_time_ns if publish_time_ns is None else publish_time_ns,
        )


def _stamp(stamp_ns: int):

    ns = max(0, int(stamp_ns))
    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _proto(topic: str, msg: Any, log_time_ns: int) -> FoxgloveMessage:
    s = msg.get_schema()
    return FoxgloveMessage(topic, s.name, s.encoding, bytes(s.data), PROTOBUF, msg.encode(), int(log_time_ns))


def _json(topic: str, schema_name: str, value: dict, time_ns: int) -> FoxgloveMessage:
    """A JSON record, its ``timestamp`` ``{sec, nsec}`` first."""
    ns = max(0, int(time_ns))
    value = {"timestamp": {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}, **value}
    schema = json.dumps(JSON_SCHEMAS[schema_name]).encode()
    return FoxgloveMessage(topic, schema_name, "jsonschema", schema, JSON, json.dumps(value).encode(), ns)


#: messages whose header stamp is a sensor's clock (the others are stamped when computed)
SENSOR_TYPES = (msgs.RadarFrame, msgs.Pose, msgs.StereoFrame, msgs.SarMeasurement)
_DAY_NS = 86_400 * 10**9


class SensorClock:
    """The one time base of a Foxglove stream (module docstring): :meth:`time_ns` of each
    message, in log order. The offset added to sensor stamps is 0 when the first sensor stamp is
    within a day of its log time (the sensors stamp with the wall clock), else the difference
    (a simulation's clock, starting at 0)."""

    def __init__(self) -> None:
        self.offset_ns: int | None = None
        self.now_ns: int | None = None  # the latest sensor time seen

    def time_ns(self, msg: Any, log_time_ns: int) -> int:
        """Nanoseconds on the sensors' clock for ``msg``, logged at ``log_time_ns`` (wall clock)."""
        if isinstance(msg, SENSOR_TYPES):
            stamp = int(msg.header.stamp_ns)
            if self.offset_ns is None:
                self.offset_ns = 0 if abs(int(log_time_ns) - stamp) < _DAY_NS else int(log_time_ns) - stamp
            t = stamp + self.offset_ns
            self.now_ns = t if self.now_ns is None else max(self.now_ns, t)
            return t
        return self.now_ns if self.now_ns is not None else int(log_time_ns)


def amplitude_image(topic: str, image: np.ndarray, stamp_ns: int, frame_id: str, log_time_ns: int) -> FoxgloveMessage:
    """A ``foxglove.CompressedImage`` PNG of ``|image| / max`` through inferno (the visualizer's
    pictures, pixel (i, j) = image (i, j)); ``image`` real or complex (H, W)."""

    msg = CompressedImage(timestamp=_stamp(stamp_ns), frame_id=frame_id, data=amplitude_png(image), format="png")
    return _proto(topic, msg, log_time_ns)


def point_cloud(
    topic: str,
    points_m: np.ndarray,
    stamp_ns: int,
    frame_id: str,
    log_time_ns: int,
    intensity: np.ndarray | None = None,
) -> FoxgloveMessage:
    """A ``foxglove.PointCloud`` of ``points_m`` (N, 3) metres, fields x y z [intensity] float32."""

    cols = [np.asarray(points_m, np.float32).reshape(-1, 3)]
    names = ["x", "y", "z"]
    if intensity is not None:
        cols.append(np.asarray(intensity, np.float32).reshape(-1, 1))
        names.append("intensity")
    packed = np.ascontiguousarray(np.hstack(cols), dtype="<f4")
    fields = [
        PackedElementField(name=n, offset=4 * i, type=PackedElementFieldNumericType.Float32)
        for i, n in enumerate(names)
    ]
    msg = PointCloud(
        timestamp=_stamp(stamp_ns),
        frame_id=frame_id,
        pose=FPose(position=Vector3(x=0, y=0, z=0), orientation=Quaternion(x=0, y=0, z=0, w=1)),
        point_stride=4 * len(names),
        fields=fields,
        data=packed.tobytes(),
    )
    return _proto(topic, msg, log_time_ns)


def frame_transform(parent: str, child: str, translation_m, quat_xyzw, t: int) -> FoxgloveMessage:
    """A ``foxglove.FrameTransform`` on ``/tf``: the pose of ``child`` in ``parent``
    (``translation_m`` (3,) metres, ``quat_xyzw`` (4,) child -> parent rotation)."""

    p, q = [float(v) for v in translation_m], [float(v) for v in quat_xyzw]
    msg = FrameTransform(
        timestamp=_stamp(t),
        parent_frame_id=parent,
        child_frame_id=child,
        translation=Vector3(x=p[0], y=p[1], z=p[2]),
        rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
    )
    return _proto("/tf", msg, t)


class FoxgloveConverter:
    """Stateful converter (the trajectory so far, each node's last state) of graph messages.

    ``trajectory_every``: a ``/vio/trajectory`` update after this many poses (it carries the
    whole track, so every pose would grow quadratically); ``max_track`` poses at most.
    ``points_threshold``: fraction of the
    template's peak amplitude above which a pixel becomes a ``/twin/points`` point.
    ``extrinsics``: ``T_camera_radar`` as a calibration file gives it (mapping,
    :meth:`twinfocus.sensors.extrinsics.RadarCameraExtrinsics.from_dict`; a log's
    ``calibration`` metadata holds it as ``extrinsics``), for the radar -> camera transform.
    """

    def __init__(
        self,
        trajectory_every: int = 10,
        points_threshold: float = 0.2,
        scene_frame: str = "scene",
        max_track: int = 20000,
        extrinsics: dict | None = None,
    ):

        self.clock = SensorClock()
        self.extrinsics = RadarCameraExtrinsics.from_dict(extrinsics) if extrinsics else None
        self._static_sent = False
        self.trajectory_every = max(1, int(trajectory_every))
        self.points_threshold = float(points_threshold)
        self.scene_frame = scene_frame
        self._track: deque[np.ndarray] = deque(maxlen=max_track)  # a graph that runs for hours stays bounded
        self._n_poses = 0
        self._node_state: dict[str, tuple[str, str, int]] = {}

    def convert(self, topic: str, msg: Any, log_time_ns: int) -> list[FoxgloveMessage]:
        """The Foxglove records of one graph message (empty for types with no picture), all at
        its time on the one clock (:class:`SensorClock`); call in log order."""
        t = self.clock.time_ns(msg, log_time_ns)
        if isinstance(msg, msgs.Image):
            return [
                amplitude_image(
                    f"/image/{msg.name or 'image'}",
                    msg.image,
                    t,
                    msg.header.frame_id or self.scene_frame,
                    t,
                )
            ]
        if isinstance(msg, msgs.TwinTemplate):
            return self._template(msg, t)
        if isinstance(msg, msgs.Pose):
            return self._pose(msg, t)
        if isinstance(msg, msgs.SarMeasurement):
            frame = msg.header.frame_id or self.scene_frame
            return [
                point_cloud("/sar/phase_centres", msg.positions_m, t, frame, t),
                _json(
                    "/sar/quality",
                    "twinfocus.MeasurementQuality",
                    {"scan_id": msg.scan_id, "index": int(msg.index), "pose_gap_ms": msg.pose_gap_ns / 1e6},
                    t,
                ),
            ]
        if isinstance(msg, msgs.AutofocusResult):
            value = {
                "scan_id": msg.scan_id,
                "method": msg.method,
                "phase_rad": [float(v) for v in msg.phase_rad],
                "loss_history": [float(v) for v in msg.loss_history],
                "metrics": {k: float(v) for k, v in msg.metrics.items() if np.isfinite(v)},
                "timing_s": {k: float(v) for k, v in msg.timing_s.items()},
            }
            return [_json("/autofocus/result", "twinfocus.AutofocusResult", value, t)]
        if isinstance(msg, msgs.StereoFrame):
            return [self._camera(msg, t)]
        if isinstance(msg, msgs.NodeStatus):
            return self._status(msg, t)
        return []

    def _template(self, msg: msgs.TwinTemplate, t: int) -> list[FoxgloveMessage]:
        frame = msg.header.frame_id or self.scene_frame
        amp = np.abs(msg.image).astype(np.float64)
        peak = amp.max()
        out = [amplitude_image("/twin/template", amp, t, frame, t)]
        if peak > 0:
            i, j = np.nonzero(amp >= self.points_threshold * peak)
            pts = np.column_stack([msg.x_m[j], msg.y_m[i], np.full(i.size, msg.z_m)])
            out.append(point_cloud("/twin/points", pts, t, frame, t, intensity=amp[i, j] / peak))
        return out

    def _pose(self, msg: msgs.Pose, t: int) -> list[FoxgloveMessage]:

        frame = msg.header.frame_id or self.scene_frame
        p, q = msg.position_m, msg.quat_xyzw
        fpose = FPose(
            position=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
            orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        )
        out = [
            _proto("/vio/pose", PoseInFrame(timestamp=_stamp(t), frame_id=frame, pose=fpose), t),
            _json("/vio/confidence", "twinfocus.PoseConfidence", {"confidence": float(msg.confidence)}, t),
            frame_transform(frame, msg.child_frame_id or "radar", p, q, t),
        ]
        if self.extrinsics is not None and not self._static_sent:
            self._static_sent = True
            # The pose's body is the radar (or the camera); the calibration hangs the other below it.
            e = self.extrinsics.inverse() if (msg.child_frame_id or "radar") == "radar" else self.extrinsics
            body, other = ("radar", "camera") if (msg.child_frame_id or "radar") == "radar" else ("camera", "radar")
            out.append(frame_transform(body, other, e.translation_m, e.quat_xyzw, t))
        self._track.append(np.array(p, np.float64))
        self._n_poses += 1
        if self._n_poses % self.trajectory_every == 0:
            line = LinePrimitive(
                thickness=2.0,
                scale_invariant=True,
                color=Color(r=0.2, g=0.8, b=1.0, a=1.0),
                points=[Point3(x=float(a), y=float(b), z=float(c)) for a, b, c in self._track],
            )
            entity = SceneEntity(timestamp=_stamp(t), frame_id=frame, id="trajectory", lines=[line])
            out.append(_proto("/vio/trajectory", SceneUpdate(entities=[entity]), t))
        return out

    def _camera(self, msg: msgs.StereoFrame, t: int) -> FoxgloveMessage:

        img = np.ascontiguousarray(msg.left)
        h, w = img.shape[:2]
        enc, step = ("rgb8", 3 * w) if img.ndim == 3 else ("mono8", w)
        raw = RawImage(
            timestamp=_stamp(t),
            frame_id=msg.header.frame_id or "camera",
            width=w,
            height=h,
            encoding=enc,
            step=step,
            data=img.tobytes(),
        )
        return _proto("/camera/left", raw, t)

    def _status(self, msg: msgs.NodeStatus, t: int) -> list[FoxgloveMessage]:

        lost = int(sum(msg.lost.values()))
        prev = self._node_state.get(msg.node)
        self._node_state[msg.node] = (msg.state, msg.message, lost)
        if prev is not None and prev == (msg.state, msg.message, lost):
            return []
        if msg.state == "error":
            level, text = LogLevel.Error, f"{msg.state}: {msg.message}"
        elif prev is not None and lost > prev[2]:
            level, text = (
                LogLevel.Warning,
                f"lost {lost - prev[2]} message(s) ({', '.join(f'{k}: {v}' for k, v in msg.lost.items() if v)})",
            )
        else:
            level, text = LogLevel.Info, msg.state + (f": {msg.message}" if msg.message else "")
        log = Log(timestamp=_stamp(t), level=level, message=text, name=msg.node)
        return [_proto("/log", log, t)]


def write_point_cloud_log(
    path, points_m: np.ndarray, intensity: np.ndarray, *, topic: str = "/volume/points", frame_id: str = "scene"
) -> None:
    """One :func:`point_cloud` (x y z intensity, float32; points_m (N, 3) metres, intensity (N,))
    in a new MCAP at ``path`` (an earlier file there replaced only once this one is finished),
    schema included, stamped now: what ``twinfocus focus --volume`` writes beside its PLY."""

    t = time.time_ns()
    with LogWriter(path, overwrite=True, library="twinfocus focus", chunk_bytes=1 << 20, compression="zstd") as w:
        point_cloud(topic, points_m, t, frame_id, t, intensity=intensity).write_to(w)


def export_log(src, dst, *, overwrite: bool = False, progress=None, say=None) -> dict[str, int]:
    """Write the Foxglove records of every message of the log ``src`` into a new MCAP ``dst``
    (schemas included: Foxglove opens it with nothing else installed), chunked (1 MiB, zstd) and
    indexed, on one clock (:class:`SensorClock`), with ``/tf`` from the poses and the log's
    ``calibration``; returns messages per Foxglove topic. ``progress(done, total)`` per message;
    ``say(line)`` for what was skipped (damage in ``src``).

    Written under a partial name beside ``dst`` and moved onto it only when finished: a failed
    export (an error, Ctrl-C, a full disk) leaves no file behind and an earlier ``dst`` as it
    was. A log with nothing to show (no message, or none with a Foxglove picture) is refused.
    """

    src, dst = Path(src), Path(dst)
    if dst.exists() and not overwrite:
        raise TwinFocusError(f"{dst}: already exists; choose another name or pass --overwrite")
    reader = LogReader(src)
    total = sum(reader.counts.values())
    kept = f" ({dst} left as it was)" if dst.exists() else ""
    if total == 0:
        raise TwinFocusError(f"{src}: the log holds no messages; nothing to export{kept}")
    shown = sorted(t for t in reader.channels if t in CONVERTED_TOPICS)
    if not shown:
        raise TwinFocusError(
            f"{src}: none of its topics ({', '.join(sorted(reader.channels))}) has a Foxglove picture; "
            f"nothing to export{kept}"
        )
    if say is not None and not reader.complete:
        say(f"{src}: {reader.condition}")
    extrinsics = (reader.metadata.get("calibration") or {}).get("extrinsics")
    try:
        conv = FoxgloveConverter(extrinsics=extrinsics if isinstance(extrinsics, dict) else None)
    except TwinFocusError as exc:
        if say is not None:
            say(f"{src}: calibration not usable, no radar -> camera transform ({exc})")
        conv = FoxgloveConverter()
    skipped = 0
    with LogWriter(dst, overwrite=True, library="twinfocus export", chunk_bytes=1 << 20, compression="zstd") as writer:
        for done, m in enumerate(reader.messages(), 1):
            try:
                msg = m.decode()
            except MessageError as exc:
                skipped += 1
                if say is not None:
                    say(f"{src}: skipped a damaged message: {exc}")
                continue
            for rec in conv.convert(m.topic, msg, m.log_time_ns):
                rec.write_to(writer)
            if progress is not None:
                progress(done, total)
    return dict(writer.counts)


#: graph topics :class:`FoxgloveConverter` draws
CONVERTED_TOPICS = (
    "image/focused",
    "twin/template",
    "vio/pose",
    "sar/measurement",
    "autofocus/result",
    "camera/stereo",
    "graph/status",
)
