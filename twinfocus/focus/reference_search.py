"""Where the reference is, from what is already known about it, so its region need not be typed.

- a digital twin's point cloud (scene frame, after the camera-radar extrinsics): the x/y box of
  its points (robust to stray points) grown by a margin, at the depth of their median;
- a template file: the grid it was made on;
- a physical twin's scan (the reference alone, on accurate positions): the brightest object of
  the wide look at that scan (:func:`twinfocus.focus.boxes.look`), its x/y extent grown by a margin, at
  the depth where it is sharpest.

Each returns the region (X0, X1, Y0, Y1, Z) and how surely it was found, for metrics.json, with
the object's own ``extent_m`` (the region less the margin).
"""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import Chirp

#: the region is the object's x/y box grown by this on every side, metres: the estimators need the
#: reference's blurred edge inside the region (a digital twin's cloud on the small simulated scene
#: of tests/test_reference_search.py's size: target SSIM 0.88 with 1.5 cm, 0.960 with 3 cm, as with
#: the paper's typed region, whose margins are 3-5 cm)
REGION_MARGIN_M = 0.03
#: a cloud's box is taken between these percentiles of its x and y (stray points beyond are ignored)
CLOUD_PERCENTILES = (1.0, 99.0)


def region_from_cloud(points_m: np.ndarray, margin_m: float = REGION_MARGIN_M) -> tuple[tuple, dict]:
    """The reference region from its point cloud: float (N, 3) metres, scene frame (rows with NaN
    or inf are ignored). Returns ((X0, X1, Y0, Y1, Z), info)."""
    p = np.asarray(points_m, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise TwinFocusError(f"reference point cloud must be an (N, 3) array of metres, got {p.shape}")
    p = p[np.isfinite(p).all(axis=1)]
    if p.shape[0] < 3:
        raise TwinFocusError(f"the reference point cloud has {p.shape[0]} finite points; a region needs at least 3")
    lo = np.percentile(p[:, :2], CLOUD_PERCENTILES[0], axis=0) - margin_m
    hi = np.percentile(p[:, :2], CLOUD_PERCENTILES[1], axis=0) + margin_m
    z = float(np.median(p[:, 2]))
    if not z > 0:
        raise TwinFocusError(f"the reference point cloud lies at depth {z:.3f} m; it must be in front of the radar")
    inside = (p[:, :2] >= lo).all(axis=1) & (p[:, :2] <= hi).all(axis=1)
    roi = (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]), z)
    return roi, {
        "source": "digital twin cloud",
        "extent_m": [*(roi[i] + (margin_m if i % 2 == 0 else -margin_m) for i in range(4)), z],
        "points": int(p.shape[0]),
        "points_inside": round(float(inside.mean()), 4),
        # how far the surface departs from one depth (a tilted or curved reference is deep)
        "depth_spread_m": round(float(np.percentile(p[:, 2], 95) - np.percentile(p[:, 2], 5)), 4),
    }


def region_from_template_file(x_m: np.ndarray, y_m: np.ndarray, z_m: float) -> tuple[tuple, dict]:
    """The region a template file was made on: its pixel centres' box at its depth (metres)."""
    x, y = np.asarray(x_m, np.float64), np.asarray(y_m, np.float64)
    roi = (float(x.min()), float(x.max()), float(y.min()), float(y.max()), float(z_m))
    return roi, {"source": "template file", "extent_m": list(roi)}


def region_from_scan(
    data: np.ndarray,
    positions_m: np.ndarray,
    chirp: Chirp,
    *,
    margin_m: float | None = None,
    bp_options: dict | None = None,
    progress_factory=None,
) -> tuple[tuple, dict]:
    """The region of the one object a scan holds (a physical twin's scan of the reference
    alone): the brightest object of :func:`twinfocus.focus.boxes.look` at the scan, its extent grown by
    ``margin_m`` (default :data:`twinfocus.focus.boxes.REGION_MARGIN_M`), at the depth where it is sharpest.

    data : complex (M, K, N); positions_m : float64 (M, K, 3) metres. Returns ((X0, X1, Y0, Y1, Z),
    info with the object's ``extent_m`` and its share of the look's bright energy (1: nothing else
    bright))."""
    from twinfocus.focus import boxes  # lazy: twinfocus.focus.boxes (+0.14 s on twinfocus focus --help)

    seen = boxes.look(data, positions_m, chirp, bp_options=bp_options, progress_factory=progress_factory)
    obj = seen.objects[0]
    grown = boxes.grow(obj.extent_m, boxes.REGION_MARGIN_M if margin_m is None else margin_m)
    roi = (*grown, float(obj.depth_m))
    return roi, {
        "source": "physical twin scan",
        "extent_m": [*obj.extent_m, float(obj.depth_m)],
        "object_energy_share": round(obj.share, 4),
    }


def candidate_score(confidence: dict) -> float:
    """A reference candidate's score from its confidence report
    (:func:`twinfocus.focus.pipeline.confidence_report`): how well the corrected reference matches its
    template (SSIM, 0 when there is none) less one for each warning, so a candidate the report
    trusts outranks any it warns about. Larger is better.

    The drift warning (``drift_warnings`` of them) does not count: it reads the scan's tracking
    through the estimate, so the right candidate's estimate shows a drift that a wrong one's,
    which is noise, does not."""
    match = confidence.get("reference_match_ssim")
    warned = len(confidence.get("warnings", [])) - int(confidence.get("drift_warnings", 0))
    return float(match or 0.0) - warned
