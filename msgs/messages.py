"""One typed message per topic kind (docs/architecture.md section 4).

Units are SI, time stamps integer nanoseconds, arrays numpy with the dtype and shape each
field declares (symbols such as K, N bind across the fields of one message). Frames:
``"scene"`` is the scene frame of docs/architecture.md section 4 (x, y across the aperture, z into the scene);
``"radar"`` the radar body frame (x along the virtual array, y across, z boresight).
"""

from __future__ import annotations

import numpy as np

from msgs.schema import BusMessage, Header, array, flag, integer, mapping, message, real, stamped, strings, text
from twinfocus.radar.fmcw import Chirp


class ChirpSamples(BusMessage):
    """What the messages that carry IF samples (:class:`RadarFrame`, :class:`SarMeasurement`) share:
    the check of their chirp fields and the :class:`~twinfocus.radar.fmcw.Chirp` they make. It
    holds no fields (it is no dataclass): each message declares ``data`` complex64 (K, N),
    ``f0_hz``, ``slope_hz_per_s`` and ``fs_hz`` itself, in its own order."""

    data: np.ndarray
    f0_hz: float
    slope_hz_per_s: float
    fs_hz: float

    def check(self) -> str | None:
        for name in ("f0_hz", "slope_hz_per_s", "fs_hz"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                return f"field '{name}' must be a positive finite number, got {v!r}"
        if self.data.shape[1] < 2:
            return f"field 'data' needs at least 2 fast-time samples, got shape {self.data.shape}"
        return None

    def chirp(self) -> Chirp:
        """The :class:`~twinfocus.radar.fmcw.Chirp` these samples were taken with."""
        return Chirp(self.f0_hz, self.slope_hz_per_s, self.fs_hz, int(self.data.shape[1]))


@message(topic="radar/frame")
class RadarFrame(ChirpSamples):
    """One radar position: the monostatic-equivalent IF samples of every virtual channel.

    data : complex64 (K, N), the model of docs/architecture.md section 2 (one row of a scan's ``data``).
    f0_hz, slope_hz_per_s, fs_hz : the chirp (N = data.shape[1] samples).
    channel_offsets_m : float64 (K, 3), each channel's phase centre in the radar body frame,
        metres (``VirtualArray.offsets_m``); the synchronizer places them with the pose.
    scan_id : which scan the frame belongs to; index : its position in that scan (0, 1, ...);
    last : True on the scan's final frame.
    positions_true_m : optional float64 (K, 3) true scene-frame phase centres (simulation only,
        for metrics against the truth).
    frames_lost, frames_zero_filled, bytes_lost : capture gaps of the stream so far (a capture
        board's lost and zero-filled frames and missing bytes, counted since the stream began;
        0 from sources without gaps and in logs written before these fields existed).
    """

    header: Header = stamped()
    data: np.ndarray = array("complex64", ("K", "N"))
    f0_hz: float = real(doc="frequency of the first ADC sample, Hz")
    slope_hz_per_s: float = real(doc="chirp slope, Hz/s")
    fs_hz: float = real(doc="ADC sample rate, Hz")
    channel_offsets_m: np.ndarray = array("float64", ("K", 3))
    scan_id: str = text()
    index: int = integer(0)
    last: bool = flag(False)
    positions_true_m: np.ndarray | None = array("float64", ("K", 3), optional=True)
    frames_lost: int = integer(0, doc="capture frames of which no byte arrived, since the stream began")
    frames_zero_filled: int = integer(
        0, doc="capture frames with missing bytes (zeros stand in), since the stream began"
    )
    bytes_lost: int = integer(0, doc="capture bytes that never arrived, since the stream began")


@message(topic="vio/pose")
class Pose(BusMessage):
    """A tracked pose of the radar body (VIO output), ROS ``PoseStamped``-like.

    position_m : float64 (3,), body origin in ``header.frame_id`` (the scene frame), metres.
    quat_xyzw : float64 (4,), body -> scene rotation, (x, y, z, w), unit norm.
    confidence : the tracker's confidence in [0, 1].
    child_frame_id : the tracked body (``"radar"`` when the lever arm is already applied,
        ``"camera"`` when the synchronizer must apply its calibration).
    """

    header: Header = stamped()
    position_m: np.ndarray = array("float64", (3,))
    quat_xyzw: np.ndarray = array("float64", (4,))
    confidence: float = real(1.0)
    child_frame_id: str = text("radar")

    def check(self) -> str | None:
        if not np.isfinite(self.position_m).all() or not np.isfinite(self.quat_xyzw).all():
            return "position_m and quat_xyzw must be finite"
        n = float(np.linalg.norm(self.quat_xyzw))
        if abs(n - 1.0) > 1e-3:
            return f"quat_xyzw must be a unit quaternion (x, y, z, w), norm is {n:.6g}"
        if not 0.0 <= self.confidence <= 1.0:
            return f"confidence must lie in [0, 1], got {self.confidence}"
        return None


@message(topic="camera/stereo")
class StereoFrame(BusMessage):
    """A rectified stereo pair (ZED-like), with optional depth.

    left, right : uint8 (H, W) grey or (H, W, 3) RGB; depth_m : optional float32 (H, W) metres
    (NaN where unknown). camera_matrix : float64 (3, 3) intrinsics of the rectified left image;
    baseline_m : stereo baseline, metres.
    """

    header: Header = stamped()
    left: np.ndarray = array("uint8", [("H", "W"), ("H", "W", 3)])
    right: np.ndarray = array("uint8", [("H", "W"), ("H", "W", 3)])
    camera_matrix: np.ndarray = array("float64", (3, 3))
    baseline_m: float = real(0.12)
    depth_m: np.ndarray | None = array("float32", ("H", "W"), optional=True)

    def check(self) -> str | None:
        if self.left.shape != self.right.shape:
            return f"left {self.left.shape} and right {self.right.shape} images differ in shape"
        return None


@message(topic="sar/measurement")
class SarMeasurement(ChirpSamples):
    """A radar frame paired with its phase-centre positions: one row of a scan file.

    data : complex64 (K, N) as in :class:`RadarFrame`; positions_m : float64 (K, 3) tracked
    scene-frame phase centres (carry the tracking error); positions_true_m : optional truth.
    pose_gap_ns : width of the pose interval the position was interpolated over (0 when a pose
    fell exactly on the frame), a quality hint.
    frames_lost, frames_zero_filled, bytes_lost : the radar frame's capture gaps (counted since
    the stream began, as on :class:`RadarFrame`); the solver reports each scan's share.
    """

    header: Header = stamped()
    data: np.ndarray = array("complex64", ("K", "N"))
    positions_m: np.ndarray = array("float64", ("K", 3))
    f0_hz: float = real()
    slope_hz_per_s: float = real()
    fs_hz: float = real()
    scan_id: str = text()
    index: int = integer(0)
    last: bool = flag(False)
    pose_gap_ns: int = integer(0)
    positions_true_m: np.ndarray | None = array("float64", ("K", 3), optional=True)
    frames_lost: int = integer(0, doc="capture frames of which no byte arrived, since the stream began")
    frames_zero_filled: int = integer(
        0, doc="capture frames with missing bytes (zeros stand in), since the stream began"
    )
    bytes_lost: int = integer(0, doc="capture bytes that never arrived, since the stream began")


@message(topic="twin/template")
class TwinTemplate(BusMessage):
    """The reference object's focused image (a template file on the wire).

    image : float32 (H, W) amplitude; x_m (W,), y_m (H,) pixel coordinates; z_m the plane.
    phase_rad : optional float32 (H, W) phase of the image, radians: a physical twin's
        motion-stage image has one, and with it the solver can register the template and take
        the closed-form phase (docs/beyond.md); None for an amplitude (a digital twin's).
    support : optional bool (H, W), True inside the reference's outline: a digital twin from a
        point cloud knows it, and with it the solver's ``estimator: auto`` takes the outline
        estimator, as ``twinfocus focus --digital-twin`` does (docs/digital_twin.md); None for a
        physical twin, a template file and logs written before the field existed.
    kind : ``"physical"`` (motion-stage measurement) or ``"digital"`` (from the camera).
    source : where it came from (file name, scan, ...), for the record.
    surface, curved, curvature_m : a digital twin's cloud conditioning: the surface model
        (``plane`` / ``smooth`` / ``outline``), whether the reference is curved, and how far its
        smoothed surface departs from a plane (metres); the solver's confidence report warns on a
        curved one. Empty / False / 0 for a physical twin and older logs.
    """

    header: Header = stamped()
    image: np.ndarray = array("float32", ("H", "W"))
    x_m: np.ndarray = array("float64", ("W",))
    y_m: np.ndarray = array("float64", ("H",))
    z_m: float = real()
    phase_rad: np.ndarray | None = array("float32", ("H", "W"), optional=True)
    support: np.ndarray | None = array("bool", ("H", "W"), optional=True)
    kind: str = text("physical")
    source: str = text()
    surface: str = text()
    curved: bool = flag()
    curvature_m: float = real(0.0)


@message(topic="autofocus/result")
class AutofocusResult(BusMessage):
    """What the solver found for one scan.

    phase_rad : float64 (M,) per-position phase correction; loss_history : float64 (I,) loss
    per iteration; metrics : figures of merit (e.g. ``ssim_target``); timing_s : durations of
    the solver's steps (``basis_after_scan``, ``autofocus``, ...), seconds; latency_s : wall-clock
    seconds from the scan's last measurement reaching the solver to the focused image and the
    first result for the scan (0: unknown, as in logs recorded before the field);
    metrics_pending : True on a first result published as soon as the image was ready, whose
    metrics against the truth (simulation) follow in a second result for the same scan
    (False: this result is the scan's last, as in logs recorded before the field);
    estimator : the named estimator that found the phase (``twinfocus.focus.estimators.ESTIMATORS``,
    ``auto`` resolved: ``outline``, ``projection``, ``correlation``, ...) for ``method`` twin; empty
    for the baselines and in logs recorded before the field;
    dropped : non-empty when the scan was not focused, saying why (no template in time, too few
    positions, the focusing refused the data); ``phase_rad`` is then empty. Empty in logs recorded
    before the field.
    """

    header: Header = stamped()
    scan_id: str = text()
    method: str = text()
    phase_rad: np.ndarray = array("float64", ("M",))
    loss_history: np.ndarray = array("float64", ("I",))
    metrics: dict = mapping("float")
    timing_s: dict = mapping("float")
    latency_s: float = real(0.0, doc="last measurement in -> result out, wall-clock seconds (0: unknown)")
    metrics_pending: bool = flag(False, doc="truth metrics follow in a later result for this scan")
    estimator: str = text("", doc="the estimator that found the phase (method twin; empty: none or unknown)")
    dropped: str = text("", doc="why the scan was not focused (empty: it was)")


@message(topic="image/focused")
class Image(BusMessage):
    """A complex SAR image on a grid (docs/architecture.md section 4).

    name : which image (``"target"``, ``"target_uncorrected"``, ``"reference"``, ...);
    image : complex64 (H, W); x_m (W,), y_m (H,), z_m: pixel coordinates, metres.
    """

    header: Header = stamped()
    name: str = text()
    scan_id: str = text()
    image: np.ndarray = array("complex64", ("H", "W"))
    x_m: np.ndarray = array("float64", ("W",))
    y_m: np.ndarray = array("float64", ("H",))
    z_m: float = real(0.0)


@message(topic="graph/status")
class NodeStatus(BusMessage):
    """A node's heartbeat.

    state : ``starting`` | ``ready`` (subscriptions live) | ``running`` | ``stopping`` |
    ``stopped`` | ``error``. publishes / subscribes : topics (``*`` for everything).
    received / published / lost : per-topic message counts; lost counts gaps in ``seq``.
    """

    header: Header = stamped()
    node: str = text()
    state: str = text("starting")
    pid: int = integer(0)
    publishes: list = strings()
    subscribes: list = strings()
    types: dict = mapping("str", doc="topic -> message type of what the node publishes")
    received: dict = mapping("int")
    published: dict = mapping("int")
    lost: dict = mapping("int")
    message: str = text()


#: topic -> the message type that travels on it
TOPIC_TYPES: dict[str, type[BusMessage]] = {
    cls.TOPIC: cls
    for cls in (RadarFrame, Pose, StereoFrame, SarMeasurement, TwinTemplate, AutofocusResult, Image, NodeStatus)
    if cls.TOPIC is not None  # every one of these has a topic
}
