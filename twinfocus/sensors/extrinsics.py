"""The fixed transform between the tracking camera and the radar, and how to measure it.

``T_camera_radar`` maps points from the radar body frame (x along the virtual array, y across
it, z boresight; origin at the middle of the virtual line) into the camera frame of the VIO
poses (for the ZED SDK in ``IMAGE`` coordinates: x right, y down, z forward, origin at the left
camera): ``p_camera = R p_radar + t``. Given camera poses in the world (body -> world), the radar
poses are ``R_wr = R_wc R``, ``p_wr = p_wc + R_wc t`` (:meth:`RadarCameraExtrinsics.radar_poses`).

Calibration file (YAML)::

    # T_camera_radar: radar body frame -> camera frame
    camera_frame: zed2i_left
    radar_frame: mmwcas
    translation_m: [0.000, 0.085, 0.012]     # radar origin in the camera frame, metres
    rotation_xyzw: [0.0, 0.0, 0.0, 1.0]       # or rotation_matrix: 3 rows, or rotation_rpy_deg

Measuring it (full procedure in ``docs/sensors.md``): start from the rig's drawing (ruler / CAD,
~1 mm), then refine the translation with radar images — either :func:`fit_rigid_transform` on
corner reflectors located by both sensors, or, as the source paper does, by the offset between a
simulated (digital-twin) and a measured SAR image of the same object
(:func:`image_offset_m`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.subpixel import parabola_vertex
from twinfocus.io.atomic import write_text_atomic
from twinfocus.io.documents import read_file, read_yaml
from twinfocus.motion.trajectory import Poses, matrix_to_quat, quat_to_matrix

#: A lever arm longer than this is taken for a unit mistake (millimetres instead of metres).
MAX_TRANSLATION_M = 1.0


def _rpy_matrix(rpy_deg) -> np.ndarray:
    r, p, y = np.deg2rad(np.asarray(rpy_deg, dtype=np.float64))
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    return rz @ ry @ rx


@dataclass(frozen=True)
class RadarCameraExtrinsics:
    """``T_camera_radar``: rotation float64 (3, 3) and translation_m float64 (3,)."""

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    camera_frame: str = "camera"
    radar_frame: str = "radar"

    def __post_init__(self) -> None:
        r = np.asarray(self.rotation, dtype=np.float64)
        t = np.asarray(self.translation_m, dtype=np.float64)
        if r.shape != (3, 3) or not np.isfinite(r).all():
            raise TwinFocusError(f"extrinsic rotation must be a finite 3 x 3 matrix, got shape {r.shape}")
        err = np.abs(r @ r.T - np.eye(3)).max()
        if err > 1e-6 or np.linalg.det(r) < 0:
            raise TwinFocusError(
                f"extrinsic rotation is not a proper rotation (|R R^T - I| = {err:.2g}, det = {np.linalg.det(r):.3g})"
            )
        if t.shape != (3,) or not np.isfinite(t).all():
            raise TwinFocusError(f"extrinsic translation_m must be 3 finite numbers, got {t.tolist()}")
        if np.linalg.norm(t) > MAX_TRANSLATION_M:
            raise TwinFocusError(
                f"extrinsic translation is {np.linalg.norm(t):.3g} m: implausible for a handheld rig; "
                "translation_m must be in metres (not millimetres)"
            )
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation_m", t)

    @property
    def quat_xyzw(self) -> np.ndarray:
        return matrix_to_quat(self.rotation)

    def radar_poses(self, camera_poses: Poses) -> Poses:
        """Radar body poses (body -> world) from camera poses (camera -> world); confidence kept."""
        r_wc = camera_poses.rotation_matrices()
        pos = camera_poses.position_m + np.einsum("mij,j->mi", r_wc, self.translation_m)
        rot = np.einsum("mij,jk->mik", r_wc, self.rotation)
        return Poses(camera_poses.timestamps_ns, pos, matrix_to_quat(rot), camera_poses.confidence)

    def inverse(self) -> RadarCameraExtrinsics:
        """``T_radar_camera``."""
        return RadarCameraExtrinsics(
            self.rotation.T, -self.rotation.T @ self.translation_m, self.radar_frame, self.camera_frame
        )

    def corrected_by_image_offset(self, dx_m: float, dy_m: float, dz_m: float = 0.0) -> RadarCameraExtrinsics:
        """The extrinsics with the translation fixed from an observed image shift.

        (dx, dy, dz) : how far the measured SAR image of an object lies from where the camera
        puts it (e.g. :func:`image_offset_m` of the digital-twin image and the real one), in the
        aperture frame (the radar's axes). An error e in the translation makes the scan's radar
        positions wrong by R_wc e, and the image moves by the negative of that; so the true
        translation is t - R d. Valid for the usual sweep with the rig's orientation fixed.
        """
        d = np.array([dx_m, dy_m, dz_m], dtype=np.float64)
        return RadarCameraExtrinsics(
            self.rotation, self.translation_m - self.rotation @ d, self.camera_frame, self.radar_frame
        )

    def to_dict(self) -> dict:
        return {
            "camera_frame": self.camera_frame,
            "radar_frame": self.radar_frame,
            "translation_m": [float(v) for v in self.translation_m],
            "rotation_xyzw": [float(v) for v in self.quat_xyzw],
        }

    @classmethod
    def from_dict(cls, d: dict, where: str = "extrinsics") -> RadarCameraExtrinsics:
        if not isinstance(d, dict):
            raise TwinFocusError(f"{where}: expected a mapping with translation_m and a rotation")
        known = {"camera_frame", "radar_frame", "translation_m", "rotation_xyzw", "rotation_matrix", "rotation_rpy_deg"}
        unknown = sorted(set(d) - known)
        if unknown:
            raise TwinFocusError(f"{where}: unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})")
        if "translation_m" not in d:
            raise TwinFocusError(f"{where}: missing translation_m (radar origin in the camera frame, metres)")
        rots = [k for k in ("rotation_xyzw", "rotation_matrix", "rotation_rpy_deg") if k in d]
        if len(rots) > 1:
            raise TwinFocusError(f"{where}: give one rotation, not {', '.join(rots)}")
        try:
            t = np.asarray(d["translation_m"], dtype=np.float64)
            if not rots:
                r = np.eye(3)
            elif rots[0] == "rotation_xyzw":
                q = np.asarray(d["rotation_xyzw"], dtype=np.float64)
                if q.shape != (4,) or abs(np.linalg.norm(q) - 1) > 1e-3:
                    raise TwinFocusError(
                        f"{where}: rotation_xyzw must be a unit quaternion (x, y, z, w), got {q.tolist()}"
                    )
                r = quat_to_matrix(q)
            elif rots[0] == "rotation_matrix":
                r = np.asarray(d["rotation_matrix"], dtype=np.float64)
            else:
                rpy = np.asarray(d["rotation_rpy_deg"], dtype=np.float64)
                if rpy.shape != (3,):
                    raise TwinFocusError(f"{where}: rotation_rpy_deg must be 3 angles (roll, pitch, yaw), degrees")
                r = _rpy_matrix(rpy)
            return cls(r, t, str(d.get("camera_frame", "camera")), str(d.get("radar_frame", "radar")))
        except (TypeError, ValueError) as exc:
            if isinstance(exc, TwinFocusError):
                raise TwinFocusError(f"{where}: {exc}") from None
            raise TwinFocusError(f"{where}: values must be numbers ({exc})") from None

    @classmethod
    def load(cls, path: str | os.PathLike) -> RadarCameraExtrinsics:
        """Read a calibration file (YAML, see the module docstring)."""
        import yaml

        d = read_file(path, read_yaml, "extrinsics file", "not valid YAML", (yaml.YAMLError,))
        return cls.from_dict(d, where=str(path))

    def save(self, path: str | os.PathLike) -> Path:
        """Write the calibration file atomically."""
        import yaml

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        text = "# T_camera_radar: radar body frame -> camera frame (p_camera = R p_radar + t)\n" + yaml.safe_dump(
            self.to_dict(), sort_keys=False, default_flow_style=None
        )
        return write_text_atomic(path, text)


def fit_rigid_transform(points_from: np.ndarray, points_to: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares rotation and translation with ``points_to ~ R points_from + t`` (Kabsch).

    points_from, points_to : float (P, 3), P >= 3 non-collinear corresponding points (e.g. corner
    reflectors located in radar images and, via the stereo camera, in the camera frame).
    Returns (R float64 (3, 3), t float64 (3,), rms residual in metres).
    """
    a = np.asarray(points_from, dtype=np.float64)
    b = np.asarray(points_to, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 3:
        raise TwinFocusError(f"need two (P, 3) point sets with P >= 3, got {a.shape} and {b.shape}")
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    h = (a - ca).T @ (b - cb)
    u, s, vt = np.linalg.svd(h)
    if s[1] < 1e-9 * max(s[0], 1e-300):
        raise TwinFocusError(
            "the points are collinear: a rotation cannot be fitted (use 3 or more spread-out reflectors)"
        )
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    t = cb - r @ ca
    rms = float(np.sqrt(np.mean(np.sum((a @ r.T + t - b) ** 2, axis=1))))
    return r, t, rms


def image_offset_m(
    reference: np.ndarray, measured: np.ndarray, x_m: np.ndarray, y_m: np.ndarray
) -> tuple[float, float]:
    """How far ``measured`` is shifted from ``reference`` on the image plane, metres (dx, dy).

    Both are amplitude images (H, W) on the same grid (pixel [i, j] at x_m[j], y_m[i], uniformly
    spaced). The shift maximises their cross-correlation (FFT, zero-padded so nothing wraps),
    refined to sub-pixel by a parabola through the peak and its neighbours. ``measured`` equals
    ``reference`` moved by (+dx, +dy). Used to calibrate the camera-radar translation from a
    digital-twin image (simulated from the camera's point cloud) and the real SAR image.
    """
    a = np.asarray(reference, dtype=np.float64)
    b = np.asarray(measured, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2:
        raise TwinFocusError(f"images must be 2-D and the same shape, got {a.shape} and {b.shape}")
    x_m = np.asarray(x_m, np.float64)
    y_m = np.asarray(y_m, np.float64)
    if x_m.shape != (a.shape[1],) or y_m.shape != (a.shape[0],):
        raise TwinFocusError(f"x_m must be ({a.shape[1]},) and y_m ({a.shape[0]},), got {x_m.shape} and {y_m.shape}")
    a = a - a.mean()
    b = b - b.mean()
    h, w = a.shape
    fa = np.fft.rfft2(a, s=(2 * h, 2 * w))
    fb = np.fft.rfft2(b, s=(2 * h, 2 * w))
    xc = np.fft.irfft2(fb * np.conj(fa), s=(2 * h, 2 * w))
    i, j = np.unravel_index(np.argmax(xc), xc.shape)

    di = i + parabola_vertex(xc[i - 1, j], xc[i, j], xc[(i + 1) % (2 * h), j])
    dj = j + parabola_vertex(xc[i, j - 1], xc[i, j], xc[i, (j + 1) % (2 * w)])
    di = di - 2 * h if di > h else di
    dj = dj - 2 * w if dj > w else dj
    dx = float(dj * (x_m[-1] - x_m[0]) / (w - 1))
    dy = float(di * (y_m[-1] - y_m[0]) / (h - 1))
    return dx, dy
