"""Calibrated pinhole stereo camera: intrinsics, the left-right geometry, rectification and the
camera-to-radar (scene) transform.

Conventions (OpenCV's): a camera frame has x to the right of the picture, y down and z along the
optical axis; pixel (u, v) = (column, row) has its centre at integer coordinates, so a point
(X, Y, Z) in the camera frame projects to u = fx X / Z + cx, v = fy Y / Z + cy. The right camera
sees a left-frame point p at ``R_rl @ p + t_rl`` (``cv2.stereoCalibrate``'s R, T); an ideal
rectified pair has R_rl = I and t_rl = (-baseline, 0, 0).

The radar's scene frame (docs/architecture.md section 4) has x, y in the aperture plane and z into the scene;
its image rows grow with y (``ImageGrid``), so a camera looking along scene +z with identity
rotation shows the scene in the same orientation as the radar image. ``scene_from_left`` is the
4 x 4 pose of the left camera in the scene frame at the instant the stereo pair was taken (the
product of the VIO pose and the fixed camera-to-radar mounting).

Defaults (:meth:`StereoCamera.zed2i`) are those of a ZED 2i at HD720: 1280 x 720 per eye, 120 mm
baseline, fx = fy = 700 px (factory calibration files of the ZED 2/2i at HD720 give fx ~ 700),
principal point at the image centre, no distortion (the SDK delivers rectified images).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.io.documents import read_file, read_json, write_json_document

ZED2I_BASELINE_M = 0.120
ZED2I_HD720 = (1280, 720)
ZED2I_HD720_FOCAL_PX = 700.0
# Left camera of the default rig, in the scene frame: 6 cm left of and 8 cm above (scene -y) the
# aperture centre, so the baseline's midpoint sits right above the radar's array.
DEFAULT_LEFT_CAMERA_POSITION_M = (-0.06, -0.08, 0.0)


@dataclass(frozen=True)
class Intrinsics:
    """One eye's pinhole model: focal lengths and principal point in pixels, image size, and the
    OpenCV distortion vector (k1, k2, p1, p2, k3)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        for name in ("fx", "fy"):
            v = float(getattr(self, name))
            if not np.isfinite(v) or v <= 0:
                raise TwinFocusError(f"camera {name} must be a positive number of pixels, got {v!r}")
        if not (np.isfinite(self.cx) and np.isfinite(self.cy)):
            raise TwinFocusError(f"camera principal point must be finite, got ({self.cx}, {self.cy})")
        if int(self.width) < 8 or int(self.height) < 8:
            raise TwinFocusError(f"camera image size must be at least 8 x 8, got {self.width} x {self.height}")
        object.__setattr__(self, "dist", tuple(float(d) for d in self.dist))

    @property
    def K(self) -> np.ndarray:
        """3 x 3 camera matrix, float64."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels, the order OpenCV takes."""
        return (int(self.width), int(self.height))

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width): the numpy shape of one channel."""
        return (int(self.height), int(self.width))

    @property
    def has_distortion(self) -> bool:
        return any(d != 0.0 for d in self.dist)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates (u, v) of camera-frame points (N, 3) -> float64 (N, 2); no distortion."""
        p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        z = p[:, 2]
        return np.stack([self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy], axis=1)

    def rays(self) -> np.ndarray:
        """Unnormalised ray direction (x/z, y/z, 1) through every pixel centre: float64 (H, W, 3)."""
        u = np.arange(int(self.width), dtype=np.float64)
        v = np.arange(int(self.height), dtype=np.float64)
        uu, vv = np.meshgrid(u, v)
        return np.stack([(uu - self.cx) / self.fx, (vv - self.cy) / self.fy, np.ones_like(uu)], axis=-1)

    def scaled(self, factor: float) -> Intrinsics:
        """The same camera at ``factor`` times the resolution (pixel centres stay consistent)."""
        f = float(factor)
        return Intrinsics(
            self.fx * f,
            self.fy * f,
            (self.cx + 0.5) * f - 0.5,
            (self.cy + 0.5) * f - 0.5,
            int(round(self.width * f)),
            int(round(self.height * f)),
            self.dist,
        )

    def to_dict(self) -> dict:
        return {
            "fx": float(self.fx),
            "fy": float(self.fy),
            "cx": float(self.cx),
            "cy": float(self.cy),
            "width": int(self.width),
            "height": int(self.height),
            "dist": list(self.dist),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Intrinsics:
        try:
            return cls(
                float(d["fx"]),
                float(d["fy"]),
                float(d["cx"]),
                float(d["cy"]),
                int(d["width"]),
                int(d["height"]),
                tuple(d.get("dist", (0.0,) * 5)),
            )
        except KeyError as exc:
            raise TwinFocusError(f"camera intrinsics miss the key {exc.args[0]!r}") from None


def pose_matrix(rotation: np.ndarray | None = None, translation_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    """4 x 4 rigid transform from a 3 x 3 rotation (default identity) and a translation (metres)."""
    t = np.eye(4)
    if rotation is not None:
        t[:3, :3] = np.asarray(rotation, dtype=np.float64)
    t[:3, 3] = np.asarray(translation_m, dtype=np.float64)
    return t


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4 x 4 rigid transform to points (N, 3) -> float64 (N, 3)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(transform, dtype=np.float64)
    return p @ t[:3, :3].T + t[:3, 3]


def _check_rigid(name: str, t: np.ndarray) -> np.ndarray:
    t = np.asarray(t, dtype=np.float64)
    if t.shape != (4, 4) or not np.isfinite(t).all():
        raise TwinFocusError(f"{name} must be a finite 4 x 4 transform, got shape {t.shape}")
    r = t[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0 or not np.allclose(t[3], [0, 0, 0, 1]):
        raise TwinFocusError(f"{name} must be a rigid transform (orthonormal rotation, det +1, last row 0 0 0 1)")
    return t


@dataclass(frozen=True)
class Rectification:
    """What ``cv2.stereoRectify`` returns, plus the remap tables.

    ``rect_from_left`` (3 x 3) rotates left-camera vectors into the rectified left frame (R1);
    ``P1``/``P2`` are the rectified projection matrices; ``Q`` re-projects (u, v, d, 1) to 3-D in
    the rectified left frame; ``map_*`` feed ``cv2.remap``.
    """

    rect_from_left: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    Q: np.ndarray
    map_left: tuple[np.ndarray, np.ndarray]
    map_right: tuple[np.ndarray, np.ndarray]

    @property
    def focal_px(self) -> float:
        return float(self.P1[0, 0])

    @property
    def baseline_m(self) -> float:
        return float(-self.P2[0, 3] / self.P2[0, 0])

    @property
    def intrinsics(self) -> Intrinsics:
        """The rectified (distortion-free) camera both rectified images share."""
        h, w = self.map_left[0].shape[:2]
        return Intrinsics(self.P1[0, 0], self.P1[1, 1], self.P1[0, 2], self.P1[1, 2], w, h)


@dataclass(frozen=True)
class StereoCamera:
    """A calibrated stereo pair and where its left camera sat in the radar's scene frame.

    Attributes
    ----------
    left, right : :class:`Intrinsics` of each eye (same image size).
    rotation_rl : float64 (3, 3), ``R`` of ``cv2.stereoCalibrate`` (left frame -> right frame).
    translation_rl_m : float64 (3,), ``T`` of ``cv2.stereoCalibrate`` in metres
        ((-baseline, 0, 0) for an ideal pair).
    scene_from_left : float64 (4, 4), pose of the left camera in the scene frame.
    """

    left: Intrinsics
    right: Intrinsics
    rotation_rl: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation_rl_m: np.ndarray = field(default_factory=lambda: np.array([-ZED2I_BASELINE_M, 0.0, 0.0]))
    scene_from_left: np.ndarray = field(default_factory=lambda: pose_matrix(None, DEFAULT_LEFT_CAMERA_POSITION_M))

    def __post_init__(self) -> None:
        if self.left.size != self.right.size:
            raise TwinFocusError(
                f"left and right images must have the same size, got {self.left.size} and {self.right.size}"
            )
        r = np.asarray(self.rotation_rl, dtype=np.float64)
        t = np.asarray(self.translation_rl_m, dtype=np.float64).reshape(-1)
        if t.shape != (3,) or not np.isfinite(t).all():
            raise TwinFocusError(f"stereo translation must be 3 finite numbers (metres), got {t}")
        rig = _check_rigid("stereo rotation", pose_matrix(r, t))
        if not np.linalg.norm(t) > 1e-3:
            raise TwinFocusError(f"stereo baseline must be longer than 1 mm, got {np.linalg.norm(t) * 1e3:.3f} mm")
        object.__setattr__(self, "rotation_rl", rig[:3, :3].copy())
        object.__setattr__(self, "translation_rl_m", t.copy())
        object.__setattr__(self, "scene_from_left", _check_rigid("scene_from_left", self.scene_from_left).copy())

    # --- construction -------------------------------------------------------------------------

    @classmethod
    def zed2i(
        cls,
        width: int = ZED2I_HD720[0],
        height: int = ZED2I_HD720[1],
        scene_from_left: np.ndarray | None = None,
        baseline_m: float = ZED2I_BASELINE_M,
    ) -> StereoCamera:
        """An ideal rectified ZED 2i-like pair (defaults: HD720, fx = fy = 700 px, 120 mm).

        Other sizes scale the focal length with the width, like the ZED's resolution modes.
        """
        f = ZED2I_HD720_FOCAL_PX * width / ZED2I_HD720[0]
        eye = Intrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)
        pose = pose_matrix(None, DEFAULT_LEFT_CAMERA_POSITION_M) if scene_from_left is None else scene_from_left
        return cls(eye, eye, np.eye(3), np.array([-float(baseline_m), 0.0, 0.0]), pose)

    def with_pose(self, scene_from_left: np.ndarray) -> StereoCamera:
        return StereoCamera(self.left, self.right, self.rotation_rl, self.translation_rl_m, scene_from_left)

    # --- geometry -----------------------------------------------------------------------------

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.translation_rl_m))

    @property
    def size(self) -> tuple[int, int]:
        return self.left.size

    @property
    def scene_from_right(self) -> np.ndarray:
        """Pose of the right camera in the scene frame (4 x 4)."""
        right_from_left = pose_matrix(self.rotation_rl, self.translation_rl_m)
        return self.scene_from_left @ np.linalg.inv(right_from_left)

    @property
    def is_rectified(self) -> bool:
        """True when the pair already is an ideal rectified pair (no remap needed)."""
        t = self.translation_rl_m
        return (
            np.allclose(self.rotation_rl, np.eye(3), atol=1e-9)
            and abs(t[1]) < 1e-9
            and abs(t[2]) < 1e-9
            and t[0] < 0
            and not self.left.has_distortion
            and not self.right.has_distortion
            and np.allclose(self.left.K, self.right.K)
        )

    def rectification(self, alpha: float = 0.0) -> Rectification:
        """Rectifying transforms and remap tables (``cv2.stereoRectify``, zero disparity at infinity)."""
        import cv2

        size = self.left.size
        r1, r2, p1, p2, q, _, _ = cv2.stereoRectify(
            self.left.K,
            np.asarray(self.left.dist),
            self.right.K,
            np.asarray(self.right.dist),
            size,
            self.rotation_rl,
            self.translation_rl_m.reshape(3, 1),
            flags=cv2.CALIB_ZERO_DISPARITY,
            alpha=alpha,
        )
        map_l = cv2.initUndistortRectifyMap(self.left.K, np.asarray(self.left.dist), r1, p1, size, cv2.CV_32FC1)
        map_r = cv2.initUndistortRectifyMap(self.right.K, np.asarray(self.right.dist), r2, p2, size, cv2.CV_32FC1)
        return Rectification(r1, p1, p2, q, map_l, map_r)

    # --- file ---------------------------------------------------------------------------------

    def to_dict(self) -> dict:
        return {
            "model": "pinhole-stereo",
            "left": self.left.to_dict(),
            "right": self.right.to_dict(),
            "rotation_rl": self.rotation_rl.tolist(),
            "translation_rl_m": self.translation_rl_m.tolist(),
            "scene_from_left": self.scene_from_left.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> StereoCamera:
        missing = [k for k in ("left", "right", "rotation_rl", "translation_rl_m", "scene_from_left") if k not in d]
        if missing:
            raise TwinFocusError(f"camera description misses key(s) {', '.join(missing)}")
        return cls(
            Intrinsics.from_dict(d["left"]),
            Intrinsics.from_dict(d["right"]),
            np.asarray(d["rotation_rl"], dtype=np.float64),
            np.asarray(d["translation_rl_m"], dtype=np.float64),
            np.asarray(d["scene_from_left"], dtype=np.float64),
        )

    def save(self, path: str | os.PathLike) -> Path:
        """Write the calibration as JSON atomically."""
        return write_json_document(path, self.to_dict())

    @classmethod
    def load(cls, path: str | os.PathLike) -> StereoCamera:
        path = Path(path)
        d = read_file(path, read_json, "camera calibration file", "not a readable JSON camera calibration")
        try:
            return cls.from_dict(d)
        except (TwinFocusError, TypeError, ValueError) as exc:
            raise TwinFocusError(f"{path}: {exc}") from None
