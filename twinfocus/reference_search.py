"""Where the reference is, from what is already known about it, so its region need not be typed.

- a digital twin's point cloud (scene frame, after the camera-radar extrinsics): the x/y box of
  its points (robust to stray points) grown by a margin, at the depth of their median;
- a template file: the grid it was made on;
- a physical twin's scan (the reference alone, on accurate positions): the brightest object of
  a coarse volume of that scan, its x/y box grown by a margin, at the depth where it is sharpest
  (:func:`twinfocus.depth_search.search_depth`).

Each returns the region (X0, X1, Y0, Y1, Z) and how surely it was found, for metrics.json.
"""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.grid import ImageGrid, VolumeGrid
from twinfocus.radar import Chirp

#: the region is the object's x/y box grown by this on every side, metres: the estimators need the
#: reference's blurred edge inside the region (a digital twin's cloud on the small simulated scene
#: of tests/test_reference_search.py's size: target SSIM 0.88 with 1.5 cm, 0.960 with 3 cm, as with
#: the paper's typed region, whose margins are 3-5 cm)
REGION_MARGIN_M = 0.03
#: a cloud's box is taken between these percentiles of its x and y (stray points beyond are ignored)
CLOUD_PERCENTILES = (1.0, 99.0)
#: a physical twin's scan is searched over the aperture's x/y box grown by this, metres ...
IMAGE_SEARCH_MARGIN_M = 0.3
#: ... and these depths, metres, on this many pixels per side, with at most this many radar positions
IMAGE_SEARCH_DEPTHS_M = (0.2, 1.2)
IMAGE_SEARCH_SIZE = 40
IMAGE_SEARCH_MAX_POSITIONS = 120
#: the object is the connected pixels of the projection's energy, smoothed over this many pixels
#: (a Gaussian's sigma), within this many dB of its brightest
OBJECT_SMOOTHING_PX = 1.0
OBJECT_DB = -10.0
#: the box is drawn again on a finer plane at the object's depth, over the coarse box grown by this, metres
REFINE_MARGIN_M = 0.03


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
        "points": int(p.shape[0]),
        "points_inside": round(float(inside.mean()), 4),
        # how far the surface departs from one depth (a tilted or curved reference is deep)
        "depth_spread_m": round(float(np.percentile(p[:, 2], 95) - np.percentile(p[:, 2], 5)), 4),
    }


def region_from_template_file(x_m: np.ndarray, y_m: np.ndarray, z_m: float) -> tuple[tuple, dict]:
    """The region a template file was made on: its pixel centres' box at its depth (metres)."""
    x, y = np.asarray(x_m, np.float64), np.asarray(y_m, np.float64)
    roi = (float(x.min()), float(x.max()), float(y.min()), float(y.max()), float(z_m))
    return roi, {"source": "template file"}


def _object_box(mip: np.ndarray, plane: ImageGrid, margin_m: float) -> tuple[tuple[float, float, float, float], float]:
    """The x/y box of the connected bright pixels around the projection's brightest, grown by
    ``margin_m``, and the share of the bright pixels' energy that object holds."""
    from scipy import ndimage  # only on this path

    # speckle breaks a letter into bright islands: the energy smoothed over a few pixels joins them
    e = ndimage.gaussian_filter(mip.astype(np.float64) ** 2, OBJECT_SMOOTHING_PX)
    bright = e >= e.max() * 10 ** (OBJECT_DB / 10)
    labels, _ = ndimage.label(bright)
    obj = labels == labels[np.unravel_index(int(np.argmax(e)), e.shape)]
    ii, jj = np.nonzero(obj)
    dy, dx = plane.spacing_m
    box = (
        float(plane.x_m[jj.min()] - dx / 2 - margin_m),
        float(plane.x_m[jj.max()] + dx / 2 + margin_m),
        float(plane.y_m[ii.min()] - dy / 2 - margin_m),
        float(plane.y_m[ii.max()] + dy / 2 + margin_m),
    )
    return box, float(e[obj].sum() / e[bright].sum())


def region_from_scan(
    data: np.ndarray,
    positions_m: np.ndarray,
    chirp: Chirp,
    *,
    margin_m: float = REGION_MARGIN_M,
    bp_options: dict | None = None,
    progress_factory=None,
) -> tuple[tuple, dict]:
    """The region of the one object a scan holds (a physical twin's scan of the reference
    alone): the brightest object of a coarse volume, then its depth by
    :func:`~twinfocus.depth_search.search_depth` on its box (module docstring).

    data : complex (M, K, N); positions_m : float64 (M, K, 3) metres. Returns ((X0, X1, Y0, Y1, Z),
    info with the object's share of the bright energy (1: nothing else bright) and the depth
    search's contrast)."""
    from twinfocus.depth_search import search_depth
    from twinfocus.volume import corrected_image, projections

    prog = progress_factory or (lambda label: None)
    bp = dict(bp_options or {})
    step = max(1, -(-data.shape[0] // IMAGE_SEARCH_MAX_POSITIONS))
    d, p = data[::step], positions_m[::step]
    centres = p.reshape(-1, 3)
    lo = centres[:, :2].min(axis=0) - IMAGE_SEARCH_MARGIN_M
    hi = centres[:, :2].max(axis=0) + IMAGE_SEARCH_MARGIN_M
    z0, z1 = IMAGE_SEARCH_DEPTHS_M
    plane = ImageGrid(float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]), z0, IMAGE_SEARCH_SIZE, IMAGE_SEARCH_SIZE)
    n_planes = int(np.ceil((z1 - z0) / (0.5 * chirp.range_resolution_m))) + 1
    grid = VolumeGrid(plane, z0, z1, n_planes)
    vol = corrected_image(d, p, chirp, grid, np.zeros(d.shape[0]), progress=prog("reference search"), **bp)
    mip, _ = projections(vol, grid)
    box, _ = _object_box(mip, plane, margin_m)
    found = search_depth(d, p, chirp, box, (z0, z1), np.zeros(d.shape[0]), bp_options=bp)
    g = REFINE_MARGIN_M
    fine = ImageGrid(
        box[0] - g, box[1] + g, box[2] - g, box[3] + g, found.depth_m, IMAGE_SEARCH_SIZE, IMAGE_SEARCH_SIZE
    )
    box, share = _object_box(np.abs(corrected_image(d, p, chirp, fine, np.zeros(d.shape[0]), **bp)), fine, margin_m)
    roi = (*box, float(found.depth_m))
    return roi, {
        "source": "physical twin scan",
        "object_energy_share": round(share, 4),
        "depth_contrast": round(float(found.contrast), 2),
    }


def candidate_score(confidence: dict) -> float:
    """A reference candidate's score from its confidence report
    (:func:`twinfocus.pipeline.confidence_report`): how well the corrected reference matches its
    template (SSIM, 0 when there is none) less one for each warning, so a candidate the report
    trusts outranks any it warns about. Larger is better.

    The drift warning (``drift_warnings`` of them) does not count: it reads the scan's tracking
    through the estimate, so the right candidate's estimate shows a drift that a wrong one's,
    which is noise, does not."""
    match = confidence.get("reference_match_ssim")
    warned = len(confidence.get("warnings", [])) - int(confidence.get("drift_warnings", 0))
    return float(match or 0.0) - warned
