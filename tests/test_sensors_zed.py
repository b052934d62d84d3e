"""ZED 2i: the factory calibration file, stereo rectification checked against projected 3-D
points, the UVC side-by-side stream, and the optional ZED SDK backend."""

from __future__ import annotations

import sys
import types

import cv2
import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.sensors.zed import (
    RESOLUTIONS,
    ZedSdkCamera,
    ZedUvcStereo,
    load_zed_calibration,
    poses_from_samples,
)

KL = dict(fx=700.5, fy=701.25, cx=641.0, cy=358.5, k1=-0.05, k2=0.02, p1=0.0005, p2=-0.0003, k3=-0.003)
KR = dict(fx=699.75, fy=700.0, cx=638.5, cy=361.0, k1=-0.04, k2=0.015, p1=-0.0002, p2=0.0004, k3=-0.002)
ROTVEC = (0.001, 0.004, -0.002)  # RX, CV, RZ
T_MM = (-119.9, 0.3, -0.5)  # -Baseline, TY, TZ


def _write_conf(path, res="HD"):
    lines = []
    for side, k in (("LEFT", KL), ("RIGHT", KR)):
        for r in RESOLUTIONS:
            scale = 1.0 if r == res else 0.5
            lines.append(f"[{side}_CAM_{r}]")
            lines += [f"{n}={v * scale if n in ('fx', 'fy', 'cx', 'cy') else v}" for n, v in k.items()]
            lines.append("")
    lines += [
        "[STEREO]",
        f"Baseline={-T_MM[0]}",
        f"TY_{res}={T_MM[1]}",
        f"TZ_{res}={T_MM[2]}",
        f"CV_{res}={ROTVEC[1]}",
        f"RX_{res}={ROTVEC[0]}",
        f"RZ_{res}={ROTVEC[2]}",
        "",
        "[MISC]",
        "Sensor_ID=1",
        "",
    ]
    path.write_text("\n".join(lines))
    return path


def _k(d):
    return np.array([[d["fx"], 0, d["cx"]], [0, d["fy"], d["cy"]], [0, 0, 1.0]])


def _dist(d):
    return np.array([d["k1"], d["k2"], d["p1"], d["p2"], d["k3"]])


def test_calibration_file_and_rectification_against_projected_points(tmp_path):
    calib = load_zed_calibration(_write_conf(tmp_path / "SN12345.conf"), "HD")
    assert calib.image_size == (1280, 720)
    np.testing.assert_allclose(calib.camera_matrix_left, _k(KL))
    np.testing.assert_allclose(calib.dist_right, _dist(KR))
    np.testing.assert_allclose(calib.translation_m, np.array(T_MM) * 1e-3)
    assert calib.baseline_m == pytest.approx(np.linalg.norm(T_MM) * 1e-3)
    # 3-D points in front of the left camera, seen by both (X_right = R X_left + T).
    g = np.stack(np.meshgrid(np.linspace(-0.6, 0.6, 7), np.linspace(-0.3, 0.3, 5), [1.2, 2.5]), -1).reshape(-1, 3)
    rot, _ = cv2.Rodrigues(np.array(ROTVEC))
    pl, _ = cv2.projectPoints(g, np.zeros(3), np.zeros(3), _k(KL), _dist(KL))
    pr, _ = cv2.projectPoints(g, np.array(ROTVEC), np.array(T_MM) * 1e-3, _k(KR), _dist(KR))
    rect = calib.rectification()
    ql = cv2.undistortPoints(pl, _k(KL), _dist(KL), R=rect.r_left, P=rect.p_left).reshape(-1, 2)
    qr = cv2.undistortPoints(pr, _k(KR), _dist(KR), R=rect.r_right, P=rect.p_right).reshape(-1, 2)
    assert np.abs(ql[:, 1] - qr[:, 1]).max() < 0.02  # rows line up after rectification
    disparity = ql[:, 0] - qr[:, 0]
    assert (disparity > 0).all()
    z_rect = (rect.r_left @ g.T)[2]
    z_est = rect.p_left[0, 0] * calib.baseline_m / disparity
    np.testing.assert_allclose(z_est, z_rect, rtol=2e-3)
    assert not np.allclose(rot, np.eye(3))


def test_calibration_file_errors(tmp_path):
    p = _write_conf(tmp_path / "SN1.conf")
    with pytest.raises(TwinFocusError, match="unknown ZED resolution"):
        load_zed_calibration(p, "4K")
    p.write_text(p.read_text().replace("[STEREO]", "[OTHER]"))
    with pytest.raises(TwinFocusError, match=r"missing section \[STEREO\]"):
        load_zed_calibration(p)
    p.write_text("[LEFT_CAM_HD]\nfx=abc\n")
    with pytest.raises(TwinFocusError, match="fx = 'abc' is not a number"):
        load_zed_calibration(p)
    with pytest.raises(TwinFocusError, match="calib.stereolabs.com"):
        load_zed_calibration(tmp_path / "SN404.conf")


def test_uvc_side_by_side_stream_is_split_and_rectified(tmp_path):
    w, h = RESOLUTIONS["VGA"]
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 255, (h, 2 * w, 3), dtype=np.uint8) for _ in range(3)]
    for i, f in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"f{i:03d}.png"), f)
    with ZedUvcStereo(str(tmp_path / "f%03d.png"), "VGA") as cam:
        pairs = list(cam.pairs())
    assert len(pairs) == 3
    for f, p in zip(frames, pairs):
        np.testing.assert_array_equal(p.left, f[:, :w])
        np.testing.assert_array_equal(p.right, f[:, w:])
    calib = load_zed_calibration(_write_conf(tmp_path / "SN2.conf", res="VGA"), "VGA")
    with ZedUvcStereo(str(tmp_path / "f%03d.png"), "VGA", calibration=calib) as cam:
        rect = list(cam.pairs(max_pairs=1))[0]
    ref_l, ref_r = calib.rectification().rectify(frames[0][:, :w], frames[0][:, w:])
    np.testing.assert_array_equal(rect.left, ref_l)
    np.testing.assert_array_equal(rect.right, ref_r)
    with pytest.raises(TwinFocusError, match="side-by-side"):
        with ZedUvcStereo(str(tmp_path / "f%03d.png"), "HD") as cam:
            next(cam.pairs())
    with pytest.raises(TwinFocusError, match="cannot open the ZED video source"):
        ZedUvcStereo(str(tmp_path / "none_%03d.png"))


def test_sdk_backend_absent_says_how_to_get_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyzed", None)
    with pytest.raises(TwinFocusError, match="pyzed.*get_python_api.py.*zed_uvc"):
        ZedSdkCamera()


def _fake_pyzed(states):
    """The pyzed.sl subset the backend uses, following the ZED SDK Python API."""
    sl = types.ModuleType("pyzed.sl")

    class Enum:
        def __init__(self, **kw):
            self.__dict__.update(kw)

    sl.ERROR_CODE = Enum(SUCCESS="SUCCESS", END_OF_SVOFILE_REACHED="END", FAILURE="FAILURE")
    sl.RESOLUTION = Enum(HD720="HD720", HD1080="HD1080")
    sl.UNIT = Enum(METER="METER", MILLIMETER="MILLIMETER")
    sl.COORDINATE_SYSTEM = Enum(IMAGE="IMAGE", RIGHT_HANDED_Y_UP="RHYU")
    sl.REFERENCE_FRAME = Enum(WORLD="WORLD", CAMERA="CAMERA")
    sl.POSITIONAL_TRACKING_STATE = Enum(OK="OK", SEARCHING="SEARCHING")
    sl.VIEW = Enum(LEFT="L", RIGHT="R")

    class InitParameters:
        camera_resolution = None
        coordinate_units = "MILLIMETER"  # the SDK's default
        coordinate_system = None

        def set_from_svo_file(self, p):
            self.svo = p

    class Vec:
        def __init__(self):
            self.v = None

        def get(self):
            return self.v

    class Timestamp:
        def __init__(self, ns):
            self.ns = ns

        def get_nanoseconds(self):
            return self.ns

    class Pose:
        def __init__(self):
            self.pose_confidence = 0
            self.timestamp = Timestamp(0)
            self.t = self.q = None

        def get_translation(self, out):
            out.v = self.t
            return out

        def get_orientation(self, out):
            out.v = self.q
            return out

    class Camera:
        last = None

        def __init__(self):
            self.i = -1
            Camera.last = self

        def open(self, init):
            self.init = init
            return sl.ERROR_CODE.SUCCESS

        def enable_positional_tracking(self, params):
            return sl.ERROR_CODE.SUCCESS

        def grab(self, runtime):
            self.i += 1
            return sl.ERROR_CODE.SUCCESS if self.i < len(states) else sl.ERROR_CODE.END_OF_SVOFILE_REACHED

        def get_position(self, pose, frame):
            pose.t = np.array([0.1 * self.i, 0.0, -0.02])
            pose.q = np.array([0.0, 0.0, np.sin(0.05 * self.i), np.cos(0.05 * self.i)])
            pose.pose_confidence = 80
            pose.timestamp = Timestamp(1_000_000 * (self.i + 1))
            return states[self.i]

        def disable_positional_tracking(self):
            pass

        def close(self):
            self.closed = True

    sl.InitParameters = InitParameters
    sl.Camera = Camera
    sl.Pose = Pose
    sl.Translation = Vec
    sl.Orientation = Vec
    sl.RuntimeParameters = lambda: object()
    sl.PositionalTrackingParameters = lambda: object()
    sl.Mat = lambda: object()
    pkg = types.ModuleType("pyzed")
    pkg.sl = sl
    return pkg, sl


def test_sdk_backend_carries_pose_confidence(monkeypatch):
    pkg, sl = _fake_pyzed(["OK", "SEARCHING", "OK"])
    monkeypatch.setitem(sys.modules, "pyzed", pkg)
    monkeypatch.setitem(sys.modules, "pyzed.sl", sl)
    with ZedSdkCamera(svo_path="rec.svo") as cam:
        samples = list(cam.poses())
    init = sl.Camera.last.init
    assert (init.coordinate_units, init.coordinate_system, init.svo) == ("METER", "IMAGE", "rec.svo")
    assert [s.confidence for s in samples] == [0.8, 0.0, 0.8]
    assert [s.stamp_ns for s in samples] == [1_000_000, 2_000_000, 3_000_000]
    poses = poses_from_samples(samples)
    np.testing.assert_allclose(poses.position_m[:, 0], [0.0, 0.1, 0.2])
    np.testing.assert_allclose(poses.confidence, [0.8, 0.0, 0.8])
    np.testing.assert_allclose(poses.quat_xyzw[2], [0, 0, np.sin(0.1), np.cos(0.1)])
