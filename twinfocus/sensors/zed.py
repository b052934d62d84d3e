"""ZED 2i: poses through the ZED SDK, or the raw side-by-side UVC stream with its factory calibration.

Two backends:

- :class:`ZedSdkCamera`: the ZED SDK's Python module (``pyzed.sl``) when installed — positional
  tracking (VIO) with the SDK's pose confidence, and rectified images. Without the SDK it raises
  :class:`TwinFocusError` saying so (the import is optional).
- :class:`ZedUvcStereo`: the camera as a plain UVC webcam through OpenCV: each frame is the left
  and right images side by side (2W x H); with the factory calibration file ``SN<serial>.conf``
  (:func:`load_zed_calibration`) the pair is undistorted and rectified for the digital twin's
  stereo point cloud. No poses (use the SDK or a trajectory file for those).

Calibration file (Stereolabs, INI): sections ``[LEFT_CAM_<RES>]`` / ``[RIGHT_CAM_<RES>]`` with
``fx fy cx cy k1 k2 p1 p2 k3`` (pixels, OpenCV's model) per resolution ``2K FHD HD VGA``, and
``[STEREO]`` with ``Baseline`` (mm), ``TY_<RES> TZ_<RES>`` (mm) and ``RX_<RES> CV_<RES> RZ_<RES>``
(rotation vector, radians) of the right camera; OpenCV's stereo convention is R = Rodrigues(RX,
CV, RZ), T = (-Baseline, TY, TZ) (as Stereolabs' ``zed-opencv-native`` sample does).
"""

from __future__ import annotations

import configparser
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import Poses

#: Per-eye image size of each ZED resolution (width, height), pixels.
RESOLUTIONS: dict[str, tuple[int, int]] = {
    "2K": (2208, 1242),
    "FHD": (1920, 1080),
    "HD": (1280, 720),
    "VGA": (672, 376),
}

ZED_SDK_MISSING = (
    "the ZED SDK's Python module (pyzed) is not installed: install the ZED SDK from stereolabs.com and run "
    "its get_python_api.py in this environment; without it use the 'zed_uvc' backend for stereo images and a "
    "TUM/EuRoC trajectory file for poses"
)


class PoseSample(NamedTuple):
    """One tracked pose: stamp_ns, position_m (3,), quat_xyzw (4,), confidence in [0, 1]."""

    stamp_ns: int
    position_m: np.ndarray
    quat_xyzw: np.ndarray
    confidence: float


class StereoPair(NamedTuple):
    """Left and right images (uint8 (H, W, 3) BGR), rectified when a calibration was given."""

    stamp_ns: int
    left: np.ndarray
    right: np.ndarray


def poses_from_samples(samples) -> Poses:
    """Collect :class:`PoseSample` into :class:`~twinfocus.motion.trajectory.Poses` (confidence kept)."""
    samples = list(samples)
    if not samples:
        raise TwinFocusError("no poses were tracked")
    return Poses(
        np.array([s.stamp_ns for s in samples], np.int64),
        np.array([s.position_m for s in samples], np.float64),
        np.array([s.quat_xyzw for s in samples], np.float64),
        np.array([s.confidence for s in samples], np.float64),
    )


# --- factory calibration ----------------------------------------------------------------------


@dataclass(frozen=True)
class StereoCalibration:
    """A calibrated stereo pair in OpenCV's convention (X_right = R X_left + T).

    image_size : (width, height) of one eye; camera_matrix_* float64 (3, 3); dist_* float64 (5,)
    or (8,) (k1 k2 p1 p2 k3 [k4 k5 k6]); rotation float64 (3, 3); translation_m float64 (3,).
    """

    image_size: tuple[int, int]
    camera_matrix_left: np.ndarray
    dist_left: np.ndarray
    camera_matrix_right: np.ndarray
    dist_right: np.ndarray
    rotation: np.ndarray
    translation_m: np.ndarray

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.translation_m))

    def rectification(self) -> StereoRectification:
        """Undistort-and-rectify maps (``cv2.stereoRectify``, zero disparity at infinity, alpha 0)."""
        import cv2

        size = tuple(int(v) for v in self.image_size)
        r1, r2, p1, p2, q, _, _ = cv2.stereoRectify(
            self.camera_matrix_left,
            self.dist_left,
            self.camera_matrix_right,
            self.dist_right,
            size,
            self.rotation,
            self.translation_m.reshape(3, 1),
            flags=cv2.CALIB_ZERO_DISPARITY,
            alpha=0,
        )
        lx, ly = cv2.initUndistortRectifyMap(self.camera_matrix_left, self.dist_left, r1, p1, size, cv2.CV_32FC1)
        rx, ry = cv2.initUndistortRectifyMap(self.camera_matrix_right, self.dist_right, r2, p2, size, cv2.CV_32FC1)
        return StereoRectification(lx, ly, rx, ry, r1, r2, p1, p2, q)


@dataclass(frozen=True)
class StereoRectification:
    """Remap tables and the rectified projections (P1, P2 float64 (3, 4); Q (4, 4) for depth)."""

    map_left_x: np.ndarray
    map_left_y: np.ndarray
    map_right_x: np.ndarray
    map_right_y: np.ndarray
    r_left: np.ndarray
    r_right: np.ndarray
    p_left: np.ndarray
    p_right: np.ndarray
    q: np.ndarray

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import cv2

        return (
            cv2.remap(left, self.map_left_x, self.map_left_y, cv2.INTER_LINEAR),
            cv2.remap(right, self.map_right_x, self.map_right_y, cv2.INTER_LINEAR),
        )


def load_zed_calibration(path: str | os.PathLike, resolution: str = "HD") -> StereoCalibration:
    """Read a Stereolabs factory calibration file (``SN<serial>.conf``) for one resolution."""
    path = Path(path)
    res = str(resolution).upper()
    if res not in RESOLUTIONS:
        raise TwinFocusError(f"unknown ZED resolution {resolution!r}; use one of {', '.join(RESOLUTIONS)}")
    if not path.is_file():
        raise TwinFocusError(
            f"{path}: no such ZED calibration file (download it from calib.stereolabs.com/?SN=<serial>)"
        )
    cp = configparser.ConfigParser()
    try:
        cp.read_string(path.read_text(errors="replace"))
    except configparser.Error as exc:
        raise TwinFocusError(f"{path}: not a ZED calibration file ({exc.__class__.__name__})") from None

    def get(section: str, key: str, default: float | None = None) -> float:
        if not cp.has_section(section):
            raise TwinFocusError(f"{path}: missing section [{section}]")
        if not cp.has_option(section, key):
            if default is not None:
                return default
            raise TwinFocusError(f"{path}: [{section}] has no {key}")
        raw = cp.get(section, key).split()[0]
        try:
            return float(raw)
        except ValueError:
            raise TwinFocusError(f"{path}: [{section}] {key} = {raw!r} is not a number") from None

    def camera(side: str):
        sec = f"{side}_CAM_{res}"
        k = np.array([[get(sec, "fx"), 0, get(sec, "cx")], [0, get(sec, "fy"), get(sec, "cy")], [0, 0, 1]])
        dist = [get(sec, n, 0.0) for n in ("k1", "k2", "p1", "p2", "k3")]
        extra = [n for n in ("k4", "k5", "k6") if cp.has_option(sec, n)]
        if extra:
            dist += [get(sec, n, 0.0) for n in ("k4", "k5", "k6")]
        return k, np.array(dist)

    kl, dl = camera("LEFT")
    kr, dr = camera("RIGHT")
    baseline = get("STEREO", "Baseline")
    ty = get("STEREO", f"TY_{res}", get("STEREO", "TY", 0.0))
    tz = get("STEREO", f"TZ_{res}", get("STEREO", "TZ", 0.0))
    rotvec = np.array(
        [get("STEREO", f"RX_{res}", 0.0), get("STEREO", f"CV_{res}", 0.0), get("STEREO", f"RZ_{res}", 0.0)]
    )
    import cv2

    rot, _ = cv2.Rodrigues(rotvec)
    t = np.array([-baseline, ty, tz]) * 1e-3
    return StereoCalibration(RESOLUTIONS[res], kl, dl, kr, dr, rot, t)


# --- UVC backend ------------------------------------------------------------------------------


class ZedUvcStereo:
    """The ZED's raw UVC stream through OpenCV: side-by-side frames split (and rectified).

    source : camera index (``0``), device path (``/dev/video0``) or a recorded side-by-side
    video / image-sequence pattern (``frames/%04d.png``) for replay.
    resolution : per-eye size requested from the camera (``2K``, ``FHD``, ``HD``, ``VGA``).
    calibration : :class:`StereoCalibration` to rectify with (None: raw halves).
    """

    def __init__(self, source, resolution: str = "HD", calibration: StereoCalibration | None = None, fps: float = 30):
        import cv2

        res = str(resolution).upper()
        if res not in RESOLUTIONS:
            raise TwinFocusError(f"unknown ZED resolution {resolution!r}; use one of {', '.join(RESOLUTIONS)}")
        self.size = RESOLUTIONS[res]
        self._live = isinstance(source, int) or str(source).startswith("/dev/")
        self._cap = cv2.VideoCapture(source)
        if not self._cap.isOpened():
            raise TwinFocusError(f"cannot open the ZED video source {source!r} (plugged in? another program using it?)")
        if self._live:
            self._cap.set(cv2.CAP_PROP_FRAME_WIDTH, 2 * self.size[0])
            self._cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.size[1])
            self._cap.set(cv2.CAP_PROP_FPS, fps)
        if calibration is not None and tuple(calibration.image_size) != tuple(self.size):
            raise TwinFocusError(
                f"calibration is for {calibration.image_size} images but the stream is {self.size} per eye"
            )
        self.calibration = calibration
        self._rect = calibration.rectification() if calibration is not None else None

    def __enter__(self) -> ZedUvcStereo:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._cap.release()

    def pairs(self, max_pairs: int | None = None) -> Iterator[StereoPair]:
        """Yield :class:`StereoPair` until the source ends (host receive time stamps)."""
        n = 0
        while max_pairs is None or n < max_pairs:
            ok, frame = self._cap.read()
            if not ok:
                return
            stamp = time.time_ns()
            h, w2 = frame.shape[:2]
            if w2 != 2 * self.size[0] or h != self.size[1]:
                raise TwinFocusError(
                    f"ZED frame is {w2} x {h}; a side-by-side {self.size[0]} x {self.size[1]} stream is {2 * self.size[0]} x {self.size[1]}"
                )
            left, right = frame[:, : w2 // 2], frame[:, w2 // 2 :]
            if self._rect is not None:
                left, right = self._rect.rectify(left, right)
            yield StereoPair(stamp, np.ascontiguousarray(left), np.ascontiguousarray(right))
            n += 1


# --- ZED SDK backend --------------------------------------------------------------------------


def import_pyzed():
    """``pyzed.sl``, or :class:`TwinFocusError` saying how to get it."""
    try:
        import pyzed.sl as sl  # type: ignore[import-not-found]
    except ImportError:
        raise TwinFocusError(ZED_SDK_MISSING) from None
    return sl


class ZedSdkCamera:
    """A ZED through the ZED SDK: positional tracking (VIO) and rectified images.

    Poses are the left camera's, in the SDK's ``IMAGE`` coordinate system (x right, y down,
    z forward) and metres, relative to where tracking started; ``confidence`` is the SDK's
    ``pose_confidence`` / 100 (0 while tracking is not ``OK``).

    resolution : SDK resolution name (``HD720``, ``HD1080``, ``HD2K``, ``VGA``); fps; serial :
    open that camera; svo_path : replay a recording instead.
    """

    def __init__(
        self, resolution: str = "HD720", fps: int = 60, serial: int | None = None, svo_path: str | None = None
    ):
        sl = import_pyzed()
        self.sl = sl
        init = sl.InitParameters()
        try:
            init.camera_resolution = getattr(sl.RESOLUTION, resolution)
        except AttributeError:
            raise TwinFocusError(f"unknown ZED SDK resolution {resolution!r} (HD720, HD1080, HD2K, VGA)") from None
        init.camera_fps = int(fps)
        init.coordinate_units = sl.UNIT.METER
        init.coordinate_system = sl.COORDINATE_SYSTEM.IMAGE
        if svo_path is not None:
            init.set_from_svo_file(str(svo_path))
        elif serial is not None:
            init.set_from_serial_number(int(serial))
        self.cam = sl.Camera()
        err = self.cam.open(init)
        if err != sl.ERROR_CODE.SUCCESS:
            raise TwinFocusError(f"the ZED SDK could not open the camera: {err}")
        err = self.cam.enable_positional_tracking(sl.PositionalTrackingParameters())
        if err != sl.ERROR_CODE.SUCCESS:
            self.cam.close()
            raise TwinFocusError(f"the ZED SDK could not start positional tracking: {err}")

    def __enter__(self) -> ZedSdkCamera:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        try:
            self.cam.disable_positional_tracking()
        finally:
            self.cam.close()

    def poses(self, max_poses: int | None = None, with_images: bool = False) -> Iterator:
        """Yield :class:`PoseSample` per grabbed frame (with ``with_images``: (pose, StereoPair)).

        Ends at the end of an SVO recording; grab errors on a live camera are skipped.
        """
        sl = self.sl
        runtime = sl.RuntimeParameters()
        pose = sl.Pose()
        left, right = sl.Mat(), sl.Mat()
        n = 0
        while max_poses is None or n < max_poses:
            err = self.cam.grab(runtime)
            if err != sl.ERROR_CODE.SUCCESS:
                if err == getattr(sl.ERROR_CODE, "END_OF_SVOFILE_REACHED", None):
                    return
                continue
            state = self.cam.get_position(pose, sl.REFERENCE_FRAME.WORLD)
            ok = state == sl.POSITIONAL_TRACKING_STATE.OK
            t = np.asarray(pose.get_translation(sl.Translation()).get(), np.float64)
            q = np.asarray(pose.get_orientation(sl.Orientation()).get(), np.float64)  # (x, y, z, w)
            conf = float(pose.pose_confidence) / 100.0 if ok else 0.0
            sample = PoseSample(int(pose.timestamp.get_nanoseconds()), t, q, min(max(conf, 0.0), 1.0))
            if with_images:
                self.cam.retrieve_image(left, sl.VIEW.LEFT)
                self.cam.retrieve_image(right, sl.VIEW.RIGHT)
                pair = StereoPair(
                    sample.stamp_ns,
                    np.ascontiguousarray(left.get_data()[..., :3]),
                    np.ascontiguousarray(right.get_data()[..., :3]),
                )
                yield sample, pair
            else:
                yield sample
            n += 1
