"""The digital twin's stages chained: stereo pair + seed -> reference point cloud (scene frame).

    rectify -> disparity (SGBM + WLS, only around the seed) -> depth -> segmentation
    -> point cloud (outliers, surface model, voxel grid) -> scene frame

Each stage's wall time is kept in :attr:`TwinResult.timings_s` (the benchmark and ``twinfocus
twin`` report them). The template itself is :func:`twinfocus.twins.digital_twin.template.digital_twin_template`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.twins.digital_twin.camera import StereoCamera, pose_matrix
from twinfocus.twins.digital_twin.pointcloud import PointCloudConfig, PointCloudResult, reference_point_cloud
from twinfocus.twins.digital_twin.segment import ClassicalSegmenter, Seed, Segmenter
from twinfocus.twins.digital_twin.stereo import StereoConfig, compute_disparity, rectify_pair

# Pixels matched around a box seed beyond the box (stereo context, GrabCut's band).
_ROI_MARGIN_PX = 48


@dataclass
class TwinResult:
    """What :func:`reference_from_stereo` found.

    points_m : float64 (N, 3) the reference's cloud in the scene frame.
    mask : bool (H, W) the reference in the (rectified) left picture.
    depth_m : float32 (H, W) depth of the rectified left camera (NaN where not matched).
    """

    points_m: np.ndarray
    mask: np.ndarray
    depth_m: np.ndarray
    seed: Seed
    cloud: PointCloudResult
    timings_s: dict = field(default_factory=dict)

    def summary(self) -> dict:
        return {
            "points": int(self.points_m.shape[0]),
            "mask_px": int(self.mask.sum()),
            "surface": self.cloud.surface,
            "counts": self.cloud.counts,
            "timings_s": {k: round(v, 4) for k, v in self.timings_s.items()},
            "centroid_m": [float(v) for v in self.points_m.mean(axis=0)],
        }


def reference_from_stereo(
    left: np.ndarray,
    right: np.ndarray,
    camera: StereoCamera,
    seed: Seed,
    *,
    segmenter: Segmenter | None = None,
    stereo_config: StereoConfig | None = None,
    cloud_config: PointCloudConfig | None = None,
) -> TwinResult:
    """From a stereo pair and a seed to the reference's point cloud in the scene frame.

    Parameters
    ----------
    left, right : uint8 (H, W, 3) BGR pictures of the calibrated ``camera`` (rectified here if
        the calibration says they are not).
    seed : where the reference is (:class:`~twinfocus.twins.digital_twin.segment.Seed`; a box is
        projected from a radar ROI by :func:`~twinfocus.twins.digital_twin.segment.box_from_scene_roi`).
    segmenter : default :class:`~twinfocus.twins.digital_twin.segment.ClassicalSegmenter`.

    Raises :class:`TwinFocusError` with the failing stage's reason (different picture sizes, no
    valid disparity, no object at the seed, an empty or degenerate cloud).
    """
    timings: dict[str, float] = {}
    t = time.perf_counter()
    left_r, right_r, rect = rectify_pair(np.asarray(left), np.asarray(right), camera)
    if rect is None:
        intr = camera.left
        focal, baseline = camera.left.fx, camera.baseline_m
        scene_from_cam = camera.scene_from_left
    else:
        intr = rect.intrinsics
        focal, baseline = rect.focal_px, rect.baseline_m
        # Rectified-left frame -> left frame is R1^T.
        scene_from_cam = camera.scene_from_left @ pose_matrix(rect.rect_from_left.T)
    timings["rectify"] = time.perf_counter() - t
    seed.validate(left_r.shape[:2])

    t = time.perf_counter()
    roi = None
    if seed.kind == "box":
        x0, y0, x1, y1 = seed.clipped_box(left_r.shape[:2])
        roi = (x0 - _ROI_MARGIN_PX, y0 - _ROI_MARGIN_PX, x1 + _ROI_MARGIN_PX, y1 + _ROI_MARGIN_PX)
    disp = compute_disparity(left_r, right_r, focal, baseline, stereo_config, roi=roi)
    depth = disp.depth()
    timings["disparity"] = time.perf_counter() - t

    t = time.perf_counter()
    seg = segmenter or ClassicalSegmenter()
    if isinstance(seg, ClassicalSegmenter):
        mask = seg(left_r, seed, depth, right_bgr=right_r, disparity_px=disp.disparity)
    else:
        mask = np.asarray(seg(left_r, seed, depth), bool)
    if mask.shape != depth.shape:
        raise TwinFocusError(f"segmenter returned a {mask.shape} mask for a {depth.shape} picture")
    timings["segmentation"] = time.perf_counter() - t

    t = time.perf_counter()
    cloud = reference_point_cloud(depth, mask, intr, scene_from_cam, cloud_config, confidence=disp.confidence)
    timings["point_cloud"] = time.perf_counter() - t
    return TwinResult(cloud.points_m, mask, depth, seed, cloud, timings)
