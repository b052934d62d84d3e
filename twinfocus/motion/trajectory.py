"""Radar trajectories: poses over time, the paper's motion-stage raster, a hand sweep, and the
phase centres a trajectory gives a MIMO array.

Frames (docs/architecture.md section 4): the scene frame has x and y spanning the aperture plane and z
pointing from the aperture into the scene. The radar *body* frame has x along the virtual array,
y across it and z along boresight (into the scene); a pose's quaternion rotates body vectors into
the scene frame, so the identity pose looks along scene +z with the array along scene x.

Quaternions are stored in ROS / TUM order ``(x, y, z, w)`` (scalar last, as
``geometry_msgs/Quaternion`` and ``scipy.spatial.transform.Rotation`` use).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.motion.tracking_errors import drift_errors
from twinfocus.radar.fmcw import VirtualArray

# A quaternion whose norm is further than this from 1 is refused rather than renormalised: it is
# not a rotation that lost a few bits, it is a wrong field (or w first instead of last).
_UNIT_TOLERANCE = 1e-3


# --- quaternion helpers (all vectorised over leading axes, order x, y, z, w) -------------------


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit quaternions.

    q : float (..., 4) in (x, y, z, w) order, unit norm (normalised here).
    Returns float64 (..., 3, 3); ``R @ v`` rotates body vector v into the scene frame.
    """
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1] != 4:
        raise TwinFocusError(f"quaternions must have 4 components (x, y, z, w) on the last axis, got shape {q.shape}")
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - z * w)
    out[..., 0, 2] = 2 * (x * z + y * w)
    out[..., 1, 0] = 2 * (x * y + z * w)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - x * w)
    out[..., 2, 0] = 2 * (x * z - y * w)
    out[..., 2, 1] = 2 * (y * z + x * w)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternions (x, y, z, w) of rotation matrices float (..., 3, 3), with w >= 0.

    Shepperd's method: the largest of the four diagonal combinations is used as the pivot, so
    the result stays accurate for every rotation angle.
    """
    r = np.asarray(r, dtype=np.float64)
    if r.shape[-2:] != (3, 3):
        raise TwinFocusError(f"rotation matrices must be (..., 3, 3), got shape {r.shape}")
    m = r.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    # 4 q_i^2 for i = x, y, z, w
    cand = np.stack([1 + 2 * m[:, 0, 0] - tr, 1 + 2 * m[:, 1, 1] - tr, 1 + 2 * m[:, 2, 2] - tr, 1 + tr], axis=1)
    pivot = np.argmax(cand, axis=1)
    q = np.empty((m.shape[0], 4))
    for i in range(4):
        sel = pivot == i
        if not np.any(sel):
            continue
        s = m[sel]
        d = np.sqrt(np.maximum(cand[sel, i], 0.0))  # = 2 |q_i|
        # Off-diagonal sums / differences, each = 4 q_a q_b.
        xy = s[:, 0, 1] + s[:, 1, 0]
        xz = s[:, 0, 2] + s[:, 2, 0]
        yz = s[:, 1, 2] + s[:, 2, 1]
        wx = s[:, 2, 1] - s[:, 1, 2]
        wy = s[:, 0, 2] - s[:, 2, 0]
        wz = s[:, 1, 0] - s[:, 0, 1]
        if i == 0:
            q[sel] = np.stack([d / 2, xy / (2 * d), xz / (2 * d), wx / (2 * d)], axis=1)
        elif i == 1:
            q[sel] = np.stack([xy / (2 * d), d / 2, yz / (2 * d), wy / (2 * d)], axis=1)
        elif i == 2:
            q[sel] = np.stack([xz / (2 * d), yz / (2 * d), d / 2, wz / (2 * d)], axis=1)
        else:
            q[sel] = np.stack([wx / (2 * d), wy / (2 * d), wz / (2 * d), d / 2], axis=1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1.0
    return q.reshape(r.shape[:-2] + (4,))


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of (x, y, z, w) quaternions (rotation b first, then a), (..., 4)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def quat_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Quaternions (x, y, z, w) of rotation vectors float (..., 3) (axis times angle, radians)."""
    v = np.asarray(rotvec, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = angle / 2.0
    # sin(a/2)/a -> 1/2 as a -> 0; the series keeps tiny rotations exact.
    scale = np.where(angle > 1e-8, np.sin(half) / np.where(angle > 1e-8, angle, 1.0), 0.5 - angle**2 / 48.0)
    return np.concatenate([v * scale, np.cos(half)], axis=-1)


def slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray | float) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions (x, y, z, w).

    q0, q1 : (..., 4), broadcastable; t : fraction(s) in [0, 1] broadcastable to the leading axes
    (t = 0 gives q0, t = 1 gives q1). Takes the short way round (q1 is negated when q0 . q1 < 0)
    and falls back to normalised linear interpolation when the two are nearly equal.
    Returns float64 (..., 4), unit norm.
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    q0 = q0 / np.linalg.norm(q0, axis=-1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
    t = np.asarray(t, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-9
    safe = np.where(near, 1.0, sin_theta)
    w0 = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    w1 = np.where(near, t, np.sin(t * theta) / safe)
    out = w0 * q0 + w1 * q1
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


# --- poses ----------------------------------------------------------------------------------


@dataclass
class Poses:
    """A sequence of radar poses (one per radar frame / position).

    Attributes
    ----------
    timestamps_ns : int64 (M,), non-decreasing capture times, nanoseconds.
    position_m : float64 (M, 3), radar body origin (the array's centre) in the scene frame, metres.
    quat_xyzw : float64 (M, 4), body -> scene rotation, (x, y, z, w), unit norm (re-normalised
        here when within 1e-3 of unit; anything further off is refused).
    confidence : optional float64 (M,) in [0, 1], the tracker's confidence in each pose.
    """

    timestamps_ns: np.ndarray
    position_m: np.ndarray
    quat_xyzw: np.ndarray
    confidence: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        ts = np.asarray(self.timestamps_ns)
        if ts.ndim != 1:
            raise TwinFocusError(f"timestamps_ns must be 1-D (M,), got shape {ts.shape}")
        if not np.issubdtype(ts.dtype, np.integer):
            raise TwinFocusError(f"timestamps_ns must be integer nanoseconds, got dtype {ts.dtype}")
        m = ts.shape[0]
        if m == 0:
            raise TwinFocusError("poses are empty: need at least one pose")
        if np.any(np.diff(ts) < 0):
            i = int(np.flatnonzero(np.diff(ts) < 0)[0])
            raise TwinFocusError(f"timestamps_ns must be non-decreasing; pose {i + 1} is earlier than pose {i}")
        self.timestamps_ns = ts.astype(np.int64, copy=False)
        self.position_m = _finite_array("position_m", self.position_m, (m, 3))
        q = _finite_array("quat_xyzw", self.quat_xyzw, (m, 4))
        norm = np.linalg.norm(q, axis=1)
        bad = np.abs(norm - 1.0) > _UNIT_TOLERANCE
        if np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            raise TwinFocusError(f"quat_xyzw must be unit quaternions (x, y, z, w); pose {i} has norm {norm[i]:.6g}")
        self.quat_xyzw = q / norm[:, None]
        if self.confidence is not None:
            c = _finite_array("confidence", self.confidence, (m,))
            if np.any((c < 0) | (c > 1)):
                raise TwinFocusError("confidence must lie in [0, 1]")
            self.confidence = c

    def __len__(self) -> int:
        return int(self.timestamps_ns.shape[0])

    @property
    def n_poses(self) -> int:
        return len(self)

    def rotation_matrices(self) -> np.ndarray:
        """Body -> scene rotations, float64 (M, 3, 3)."""
        return quat_to_matrix(self.quat_xyzw)

    def select(self, index) -> Poses:
        """The poses at ``index`` (slice, integer array or boolean mask), as new Poses."""
        idx = np.arange(len(self))[index]
        idx = np.atleast_1d(idx)
        return Poses(
            self.timestamps_ns[idx],
            self.position_m[idx],
            self.quat_xyzw[idx],
            None if self.confidence is None else self.confidence[idx],
        )

    def with_positions(self, position_m: np.ndarray) -> Poses:
        """The same poses moved to ``position_m`` (M, 3) (e.g. with tracking errors added)."""
        return Poses(self.timestamps_ns, position_m, self.quat_xyzw, self.confidence)

    def interpolate(self, timestamps_ns: np.ndarray) -> Poses:
        """Poses at other times: positions linearly, orientations by :func:`slerp`.

        ``timestamps_ns`` : int (T,), non-decreasing. Times outside [first, last] are clamped to
        the end poses (no extrapolation). The confidence, if any, is interpolated linearly.
        """
        t = np.asarray(timestamps_ns)
        if t.ndim != 1 or not np.issubdtype(t.dtype, np.integer):
            raise TwinFocusError(f"timestamps_ns to interpolate at must be 1-D integer, got {t.dtype} {t.shape}")
        ts = self.timestamps_ns
        if len(self) == 1:
            i0 = np.zeros(t.shape, dtype=int)
            i1 = i0
            frac = np.zeros(t.shape)
        else:
            i1 = np.clip(np.searchsorted(ts, t, side="right"), 1, len(self) - 1)
            i0 = i1 - 1
            span = (ts[i1] - ts[i0]).astype(np.float64)
            frac = np.where(span > 0, (t - ts[i0]).astype(np.float64) / np.where(span > 0, span, 1.0), 0.0)
            frac = np.clip(frac, 0.0, 1.0)
        pos = self.position_m[i0] + frac[:, None] * (self.position_m[i1] - self.position_m[i0])
        quat = slerp(self.quat_xyzw[i0], self.quat_xyzw[i1], frac)
        conf = None
        if self.confidence is not None:
            conf = self.confidence[i0] + frac * (self.confidence[i1] - self.confidence[i0])
        return Poses(t.astype(np.int64), pos, quat, conf)


def _finite_array(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    a = np.asarray(value)
    if a.shape != shape:
        raise TwinFocusError(f"{name} must have shape {shape}, got {a.shape}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise TwinFocusError(f"{name} must be numeric, got dtype {a.dtype}")
    a = a.astype(np.float64, copy=False)
    if not np.isfinite(a).all():
        i = int(np.argwhere(~np.isfinite(a))[0][0])
        raise TwinFocusError(f"{name} holds NaN or inf (first at index {i})")
    return a


# --- trajectories ---------------------------------------------------------------------------


def paper_raster(
    n_columns: int = 6,
    n_rows: int = 130,
    column_pitch_m: float = 0.082,
    row_pitch_m: float = 0.002,
    z_m: float = 0.0,
    frame_period_s: float = 0.1,
    t0_ns: int = 0,
) -> Poses:
    """The paper's motion-stage raster: one pose per radar frame, serpentine order.

    Columns are ``column_pitch_m`` apart in x, centred on x = 0; rows are ``row_pitch_m`` apart in
    y, centred on y = 0 (y from -129 mm to +129 mm for the defaults). The stage runs up the first
    column (y increasing), down the second, and so on, one frame every ``frame_period_s``; the
    array's axis stays along scene x (identity orientation). Defaults: M = 6 x 130 = 780.

    Returns :class:`Poses` with M = n_columns * n_rows.
    """
    n_columns, n_rows = int(n_columns), int(n_rows)
    if n_columns < 1 or n_rows < 1:
        raise TwinFocusError(f"raster needs at least one column and one row, got {n_columns} x {n_rows}")
    for name, v in (
        ("column_pitch_m", column_pitch_m),
        ("row_pitch_m", row_pitch_m),
        ("frame_period_s", frame_period_s),
    ):
        if not (np.isfinite(v) and v > 0):
            raise TwinFocusError(f"{name} must be a positive number, got {v!r}")
    if not np.isfinite(z_m):
        raise TwinFocusError(f"z_m must be finite, got {z_m!r}")
    xs = (np.arange(n_columns) - (n_columns - 1) / 2.0) * column_pitch_m
    ys = (np.arange(n_rows) - (n_rows - 1) / 2.0) * row_pitch_m
    pos = np.empty((n_columns, n_rows, 3))
    for c in range(n_columns):
        pos[c, :, 0] = xs[c]
        pos[c, :, 1] = ys if c % 2 == 0 else ys[::-1]
        pos[c, :, 2] = z_m
    m = n_columns * n_rows
    ts = int(t0_ns) + np.round(np.arange(m) * frame_period_s * 1e9).astype(np.int64)
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (m, 1))
    return Poses(ts, pos.reshape(m, 3), quat)


@dataclass(frozen=True)
class HandMotion:
    """How a simulated hand moves about its sweep (:func:`handheld_zigzag`): each a smooth
    first-order Gauss-Markov process with correlation time ``wander_time_s`` (seconds).

    speed_variation : relative standard deviation of the speed along a column; lateral_wander_m,
    depth_wander_m : r.m.s. wander across (x) and in depth (z), metres; tilt_deg : r.m.s. tilt per
    axis, degrees."""

    speed_variation: float = 0.3
    lateral_wander_m: float = 2e-3
    depth_wander_m: float = 3e-3
    tilt_deg: float = 1.0
    wander_time_s: float = 1.5


def handheld_zigzag(
    n_columns: int = 6,
    n_rows: int = 130,
    column_pitch_m: float = 0.082,
    height_m: float = 0.258,
    z_m: float = 0.0,
    frame_period_s: float = 0.1,
    column_change_s: float = 1.0,
    rng: np.random.Generator | int | None = None,
    t0_ns: int = 0,
    motion: HandMotion = HandMotion(),
) -> Poses:
    """A simulated hand sweep with the paper raster's coverage: zig-zag columns, uneven speed.

    The hand moves up the first column, across, down the next, ... with ``n_rows`` frames per
    column (so M = n_columns * n_rows, like :func:`paper_raster`) spread over ``height_m``. Along a
    column the speed varies smoothly, the hand wanders across and in depth and tilts, as
    ``motion`` says (:class:`HandMotion`). ``column_change_s`` of frames are skipped between columns.

    This is the *true* trajectory; tracking errors are added separately (:mod:`twinfocus.motion.tracking_errors`).
    Returns :class:`Poses` with M = n_columns * n_rows.
    """
    gen = np.random.default_rng(rng)
    n_columns, n_rows = int(n_columns), int(n_rows)
    if n_columns < 1 or n_rows < 2:
        raise TwinFocusError(f"hand sweep needs at least one column and two rows, got {n_columns} x {n_rows}")
    for name, v in (("column_pitch_m", column_pitch_m), ("height_m", height_m), ("frame_period_s", frame_period_s)):
        if not (np.isfinite(v) and v > 0):
            raise TwinFocusError(f"{name} must be a positive number, got {v!r}")
    for name, v in (
        ("column_change_s", column_change_s),
        ("speed_variation", motion.speed_variation),
        ("lateral_wander_m", motion.lateral_wander_m),
        ("depth_wander_m", motion.depth_wander_m),
        ("tilt_deg", motion.tilt_deg),
    ):
        if not (np.isfinite(v) and v >= 0):
            raise TwinFocusError(f"{name} must be a non-negative number, got {v!r}")
    wander_time_s = motion.wander_time_s
    if not (np.isfinite(wander_time_s) and wander_time_s > 0):
        raise TwinFocusError(f"wander_time_s must be positive, got {wander_time_s!r}")
    m = n_columns * n_rows
    frame_ns = frame_period_s * 1e9
    idx = np.arange(m)
    column = idx // n_rows
    ts = int(t0_ns) + np.round(idx * frame_ns + column * column_change_s * 1e9).astype(np.int64)

    # Speed along the column: positive, smooth, mean 1; y is its normalised running integral so
    # every column spans exactly [-height/2, +height/2].
    speed = 1.0 + drift_errors(ts, motion.speed_variation, wander_time_s, gen)[:, 0]
    speed = np.clip(speed, 0.2, None)
    pos = np.empty((m, 3))
    xs = (np.arange(n_columns) - (n_columns - 1) / 2.0) * column_pitch_m
    for c in range(n_columns):
        sl = slice(c * n_rows, (c + 1) * n_rows)
        s = speed[sl]
        travel = np.concatenate([[0.0], np.cumsum((s[1:] + s[:-1]) / 2.0)])
        y = (travel / travel[-1] - 0.5) * height_m
        pos[sl, 1] = y if c % 2 == 0 else y[::-1]
        pos[sl, 0] = xs[c]
    wander = drift_errors(ts, (motion.lateral_wander_m, 0.0, motion.depth_wander_m), wander_time_s, gen)
    pos[:, 0] += wander[:, 0]
    pos[:, 2] = z_m + wander[:, 2]
    tilt = drift_errors(ts, np.deg2rad(motion.tilt_deg), wander_time_s, gen)
    quat = quat_from_rotvec(tilt)
    return Poses(ts, pos, quat)


def phase_centres(poses: Poses, array: VirtualArray) -> np.ndarray:
    """Scene-frame phase centres of every virtual channel at every pose.

    centre[m, k] = R_m @ array.offsets_m[k] + poses.position_m[m]

    Returns float64 (M, K, 3), metres (the ``positions`` of a scan file).
    """
    if not isinstance(poses, Poses):
        raise TwinFocusError(f"poses must be a twinfocus.motion.trajectory.Poses, got {type(poses).__name__}")
    offsets = np.asarray(array.offsets_m, dtype=np.float64)
    if offsets.ndim != 2 or offsets.shape[1] != 3:
        raise TwinFocusError(f"array offsets_m must be (K, 3), got {offsets.shape}")
    rot = poses.rotation_matrices()
    return np.einsum("mij,kj->mki", rot, offsets) + poses.position_m[:, None, :]
