"""A reference's point cloud as a depth camera delivers it: the impairments of a ZED, a RealSense,
a phone's LiDAR or photogrammetry, applied to exact surface points (for the simulator and tests).

What such clouds have (the field-like scenes of docs/simulation.md): noise of 0.5-2 mm on every axis (depth usually
the worst), 10-40 % of the surface missing in patches (specular spots, low texture, occlusion),
0-5 % outliers spread around the object (flying pixels, mismatches), a rigid offset of a few mm
from where the radar sees the object (camera-radar calibration), and no plane fitted.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from twinfocus.errors import TwinFocusError

#: Outliers are drawn uniformly in the surface's bounding box grown by this on every side, metres.
OUTLIER_MARGIN_M = 0.02

#: Mean number of surface points removed per hole patch (patches are discs around random points).
POINTS_PER_HOLE = 400


def _fraction(name: str, v, hi: float) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise TwinFocusError(f"{name} must be a number, got {v!r}") from None
    if not (np.isfinite(f) and 0.0 <= f < hi):
        raise TwinFocusError(f"{name} must lie in [0, {hi}), got {v!r}")
    return f


def _axes(name: str, v) -> np.ndarray:
    a = np.broadcast_to(np.asarray(v, dtype=np.float64), (3,)).copy() if np.ndim(v) == 0 else np.asarray(v, np.float64)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise TwinFocusError(f"{name} must be one number or 3 (x, y, z), metres, got {v!r}")
    return a


def _holes(points: np.ndarray, fraction: float, gen: np.random.Generator) -> np.ndarray:
    """bool (N,): True for the points kept after cutting patches covering ``fraction`` of them."""
    n = points.shape[0]
    keep = np.ones(n, dtype=bool)
    target = round(fraction * n)
    if target == 0:
        return keep
    tree = cKDTree(points)
    k = min(n, max(1, min(POINTS_PER_HOLE, target)))
    removed = 0
    # Patches of about POINTS_PER_HOLE points (a disc ~2 cm across at 1 mm spacing) around random
    # surface points until the asked fraction is gone; the last patch is trimmed to hit it exactly.
    while removed < target:
        c = points[gen.choice(np.flatnonzero(keep))]
        _, idx = tree.query(c, k=k)
        idx = np.atleast_1d(idx)
        idx = idx[keep[idx]][: target - removed]
        keep[idx] = False
        removed += idx.size
    return keep


def camera_cloud(
    points_m,
    noise_m=1e-3,
    hole_fraction: float = 0.25,
    outlier_fraction: float = 0.02,
    offset_m=0.0,
    rng: np.random.Generator | int | None = None,
    return_truth: bool = False,
):
    """Impair exact surface points as a depth camera would.

    Parameters
    ----------
    points_m : float (N, 3), the exact surface (scene frame, metres), e.g.
        ``PlanarObject.surface_points(1e-3)``; about 1 mm apart, as a camera samples at 0.6 m.
    noise_m : per-axis noise standard deviation, metres: one number for all axes or (sx, sy, sz).
    hole_fraction : fraction of the surface points removed, in patches (discs of about
        :data:`POINTS_PER_HOLE` neighbouring points), in [0, 1).
    outlier_fraction : fraction of the *returned* points that are outliers, drawn uniformly in the
        surface's bounding box grown by :data:`OUTLIER_MARGIN_M`, in [0, 0.5).
    offset_m : rigid offset of the whole cloud: a number (its length, in a random direction) or a
        vector (3,), metres.
    rng : seed or Generator.
    return_truth : also return a dict: ``kept`` int64 (K,) indices of the input points that
        survive (in output order, first K rows), ``outlier`` bool (N',), ``offset_m`` (3,).

    Returns
    -------
    float64 (N', 3), N' = K + outliers: the K surviving surface points (noisy) first, then the
    outliers, all offset; nothing fitted. With ``return_truth``: (cloud, truth).
    """
    p = np.asarray(points_m, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0:
        raise TwinFocusError(f"points must be a non-empty (N, 3) array, got shape {p.shape}")
    if not np.isfinite(p).all():
        raise TwinFocusError("points hold NaN or inf")
    sd = _axes("noise_m", noise_m)
    if np.any(sd < 0):
        raise TwinFocusError(f"noise_m must be >= 0, got {noise_m!r}")
    hole_fraction = _fraction("hole_fraction", hole_fraction, 1.0)
    outlier_fraction = _fraction("outlier_fraction", outlier_fraction, 0.5)
    gen = np.random.default_rng(rng)
    if np.ndim(offset_m) == 0:
        length = float(offset_m)
        if not (np.isfinite(length) and length >= 0):
            raise TwinFocusError(f"offset_m must be a non-negative length or a vector (3,), got {offset_m!r}")
        d = gen.normal(size=3)
        offset = length * d / np.linalg.norm(d)
    else:
        offset = _axes("offset_m", offset_m)

    keep = _holes(p, hole_fraction, gen)
    kept = np.flatnonzero(keep)
    surface = p[kept] + gen.normal(size=(kept.size, 3)) * sd
    n_out = round(outlier_fraction * kept.size / (1.0 - outlier_fraction))
    lo, hi = p.min(axis=0) - OUTLIER_MARGIN_M, p.max(axis=0) + OUTLIER_MARGIN_M
    outliers = lo + gen.random((n_out, 3)) * (hi - lo)
    cloud = np.concatenate([surface, outliers], axis=0) + offset
    if not return_truth:
        return cloud
    flag = np.zeros(cloud.shape[0], dtype=bool)
    flag[kept.size :] = True
    return cloud, {"kept": kept, "outlier": flag, "offset_m": offset}
