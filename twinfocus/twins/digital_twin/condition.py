"""Conditioning of any reference point cloud for the digital twin: what a camera gives (a ZED, a
RealSense, a phone's LiDAR, photogrammetry, ``twinfocus twin``) -> a clean surface, the radar
template it implies, and the reference's outline on the reference grid.

Camera clouds have noise of 0.5-2 mm on every axis, holes, outliers and an offset. A radar
template is sensitive to depth at the scale of lambda/4 ~ 1 mm (1 mm of depth is ~3 rad of radar
phase per point), so the measured points are never used as scatterers directly: the cloud only
decides a *surface model*, and the model's points are the scatterers.

Steps (:func:`condition_cloud`):

1. Rows with NaN or inf are dropped (counted, warned); points whose x, y lie outside the
   reference region (with a margin) are dropped -- a cloud entirely outside is an error.
2. Clouds of more than ``max_points`` (200,000) points are thinned to a uniform random subset:
   bounds the work for clouds of millions of points without biasing the noise.
3. Outliers: isolated points (fewer than ``outlier_min_neighbours`` others within
   ``outlier_radius_factor`` x the median nearest-neighbour distance: a radius filter; unlike
   open3d's statistical filter it keeps a clean cloud's edge points, so the outline is not
   eroded), then, once a surface is fitted, every point farther from it than
   ``surface_outlier_sigma`` x the measured noise.
4. Surface model, in the frame of the best plane (least squares, trimmed at 3 sd): a height
   field w(u, v) above that plane, smoothed over ``smooth_window_m`` (normalised Gaussian
   convolution, which also bridges holes). The noise sd is measured from the points' residuals
   to it (MAD); the model's own depth uncertainty follows from the noise and the number of
   points in the window.
   * ``plane`` when the height field departs from the plane by no more than its own noise
     allows (at most ``curvature_min_m``): the points are re-made on the plane (no depth noise);
   * ``smooth`` when it is curved (a cylinder, a bent plate): points on the smoothed height field;
   * ``outline`` when the model's depth is too uncertain for radar phase (phase sd above
     ``max_phase_sd_rad``) or when asked (a rough reference: its radar image is speckle that no
     camera sees, so only where it is can be trusted). The template is then the expected
     amplitude of a rough surface (incoherent), and the support mask is what counts.
5. Holes: the outline is the occupied cells (2 x ``voxel_m``) closed over ``close_radius_m``,
   with enclosed holes up to ``fill_hole_max_m2`` filled (a camera hole looks like a letter's
   counter; only the size tells them apart, so a counter smaller than that is filled too); the
   surface points are re-made on a regular ``voxel_m`` lattice over it.

:func:`digital_twin_reference` adds the template on the reference grid and the *support mask*
(bool (H, W), where the reference is on the grid). An offset between camera and radar cannot be
seen in the cloud: give the calibration's offset (``offset_m``); a residual is what the per-scan
registration (:mod:`twinfocus.twins.digital_twin.align`) is for.
"""

from __future__ import annotations

import os
import time
import warnings
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import ndimage

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.grid import ImageGrid
from twinfocus.twins.digital_twin.align import RadarCameraCalibration
from twinfocus.twins.digital_twin.pointcloud import MIN_POINTS, check_not_degenerate
from twinfocus.twins.digital_twin.template import digital_twin_template, load_points

SURFACES = ("auto", "plane", "smooth", "outline")


class CloudWarning(UserWarning):
    """A cloud was usable only after dropping or guessing something (details in ``info``)."""


@dataclass(frozen=True)
class ConditionConfig:
    """Settings of :func:`condition_cloud` (lengths in metres).

    surface : ``"auto"`` (chosen from the cloud), or force ``"plane"``, ``"smooth"``, ``"outline"``
        (``outline`` for a reference known to be rough).
    voxel_m : spacing of the model's points (the outline's cells are twice it).
    max_points : larger clouds are thinned to a uniform random subset of this many first.
    region_margin_m : points this far outside the reference region's x, y are still kept.
    plane_threshold_m : least inlier distance of the plane that sets the frame.
    smooth_window_m : Gaussian sigma x 2 of the height-field smoothing.
    curvature_min_m : departures from the plane below this count as planar.
    surface_outlier_sigma : points farther than this x the noise sd from the model are outliers.
    close_radius_m : gaps narrower than 2 x this are closed in the outline.
    fill_hole_max_m2 : enclosed holes up to this area are filled (camera holes); larger ones (a
        letter's counter: ~9 cm2 for the paper's 127 mm A) are kept.
    max_phase_sd_rad : model depth uncertainty, as radar phase, above which only the outline is used.
    """

    surface: str = "auto"
    voxel_m: float = 1e-3
    max_points: int = 200_000
    region_margin_m: float = 0.01
    outlier_radius_factor: float = 4.0
    outlier_min_neighbours: int = 6
    plane_threshold_m: float = 3e-3
    smooth_window_m: float = 8e-3
    curvature_min_m: float = 1.5e-3
    surface_outlier_sigma: float = 4.0
    close_radius_m: float = 6e-3
    fill_hole_max_m2: float = 5e-4
    max_phase_sd_rad: float = 1.0
    seed: int = 0

    def validate(self) -> None:
        if self.surface not in SURFACES:
            raise TwinFocusError(f"surface model must be one of {', '.join(SURFACES)}, got {self.surface!r}")
        for name in (
            "voxel_m",
            "plane_threshold_m",
            "smooth_window_m",
            "curvature_min_m",
            "surface_outlier_sigma",
            "max_phase_sd_rad",
        ):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise TwinFocusError(f"{name} must be a positive number, got {v!r}")
        for name in ("region_margin_m", "close_radius_m", "fill_hole_max_m2"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise TwinFocusError(f"{name} must be >= 0, got {v!r}")


@dataclass
class ConditionedCloud:
    """What :func:`condition_cloud` made of a cloud.

    points_m : float64 (N, 3) the model surface's points (scene frame), ``voxel_m`` apart.
    surface : ``"plane"``, ``"smooth"`` or ``"outline"``.
    plane : (unit normal (3,), offset d) of the frame plane, n . p = d, normal away from the radar.
    info : JSON-able dict: counts removed at each step, noise, curvature, model and why.
    warnings : one line per thing the user should know (also issued as :class:`CloudWarning`).
    """

    points_m: np.ndarray
    surface: str
    plane: tuple[np.ndarray, float]
    info: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)


@dataclass
class DigitalTwinReference:
    """The digital twin of the reference on its grid (:func:`digital_twin_reference`).

    template : float32 (H, W) amplitude template on the reference grid.
    support : bool (H, W), True where the reference is (its outline on the grid).
    cloud : the :class:`ConditionedCloud` (its ``points_m`` made ``template``).
    info : ``cloud.info`` plus the template's settings; write it into metrics.json.
    """

    template: np.ndarray
    support: np.ndarray
    cloud: ConditionedCloud
    info: dict = field(default_factory=dict)

    @property
    def surface(self) -> str:
        return self.cloud.surface

    @property
    def warnings(self) -> list:
        return self.cloud.warnings


def _remove_isolated(points: np.ndarray, radius_factor: float, min_neighbours: int) -> np.ndarray:
    # One k-nearest-neighbour query (scipy's KD-tree): a point is isolated when its
    # min_neighbours-th neighbour lies beyond radius_factor x the median nearest-neighbour
    # distance. open3d's remove_radius_outlier does the same but visits every neighbour within the
    # radius: 2.9 s for 300,000 dense points against ~0.5 s here (loaded 2-core machine).
    from scipy.spatial import cKDTree

    k = int(min_neighbours) + 1
    if points.shape[0] <= k:
        return points
    d, _ = cKDTree(points).query(points, k=k, workers=2)
    radius = float(radius_factor) * float(np.median(d[:, 1]))
    if not radius > 0:
        return points
    return points[d[:, -1] <= radius]


def _warn(out: list, msg: str) -> None:
    out.append(msg)
    warnings.warn(msg, CloudWarning, stacklevel=3)


def _frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal (eu, ev, n) with n pointing away from the radar (+z) and eu as close to +x as possible."""
    n = n / np.linalg.norm(n)
    if n[2] < 0:
        n = -n
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    eu = ref - (ref @ n) * n
    eu /= np.linalg.norm(eu)
    return eu, np.cross(n, eu), n


def _height_field(uv: np.ndarray, w: np.ndarray, cell: float, sigma_cells: float):
    """Normalised-convolution height field on cells ``cell`` wide: (origin (2,), shape, field (H, W),
    weight (H, W), occupancy count (H, W))."""
    lo = uv.min(axis=0) - 3 * sigma_cells * cell
    idx = np.floor((uv - lo) / cell).astype(np.int64)
    shape = tuple(int(v) for v in idx.max(axis=0) + 1 + int(np.ceil(3 * sigma_cells)))
    cnt = np.zeros(shape)
    tot = np.zeros(shape)
    np.add.at(cnt, (idx[:, 0], idx[:, 1]), 1.0)
    np.add.at(tot, (idx[:, 0], idx[:, 1]), w)
    wt = ndimage.gaussian_filter(cnt, sigma_cells, mode="constant")
    num = ndimage.gaussian_filter(tot, sigma_cells, mode="constant")
    with np.errstate(invalid="ignore", divide="ignore"):
        h = np.where(wt > 1e-6, num / wt, 0.0)
    return lo, shape, h, wt, cnt


def _frame_plane(points: np.ndarray, threshold_m: float, rounds: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plane that sets the frame: least squares (SVD), refitted on the points within
    max(threshold, 3 x the residuals' robust sd) of it. Returns (unit normal, centroid, inliers).

    Not a RANSAC plane (pointcloud.fit_plane; with open3d's ``segment_plane`` the inlier set, and
    with it the frame, changed from run to run: curvature 7.2 then 5.2 mm on one cloud): the
    isolated outliers are already gone here, and a curved surface needs only a frame.
    """
    inl = np.ones(points.shape[0], dtype=bool)
    for _ in range(rounds):
        c = points[inl].mean(axis=0)
        _, _, vt = np.linalg.svd(points[inl] - c, full_matrices=False)
        n = vt[2]
        r = (points - c) @ n
        sd = 1.4826 * float(np.median(np.abs(r[inl] - np.median(r[inl]))))
        new = np.abs(r) <= max(threshold_m, 3.0 * sd)
        if new.sum() < 3 or np.array_equal(new, inl):
            break
        inl = new
    return n, c, inl


def _disc(radius_cells: float) -> np.ndarray:
    r = int(np.ceil(radius_cells))
    y, x = np.mgrid[-r : r + 1, -r : r + 1]
    return (x * x + y * y) <= radius_cells * radius_cells + 1e-9


def condition_cloud(
    points_m, grid: ImageGrid | None = None, wavelength_m: float = 3.9e-3, config: ConditionConfig | None = None
) -> ConditionedCloud:
    """Condition a reference point cloud (module docstring): float (N, 3) scene metres ->
    :class:`ConditionedCloud`.

    grid : the reference region; points outside its x, y (plus ``region_margin_m``) are dropped
        and a cloud entirely outside is an error. None: keep every point.
    wavelength_m : radar wavelength (for the phase criterion of the surface model).

    Raises :class:`TwinFocusError` for a cloud that is not (N, 3), has fewer than
    :data:`~twinfocus.twins.digital_twin.pointcloud.MIN_POINTS` finite points (in the region), or lies on
    a line; issues :class:`CloudWarning` (and lists it in ``warnings``) for dropped rows.
    """
    t0 = time.perf_counter()
    cfg = config or ConditionConfig()
    cfg.validate()
    p = np.asarray(points_m)
    if p.ndim != 2 or p.shape[1] != 3 or not np.issubdtype(p.dtype, np.number):
        raise TwinFocusError(f"reference point cloud must be an (N, 3) array of metres, got {p.dtype} {p.shape}")
    p = p.astype(np.float64, copy=False)
    info: dict = {"input_points": int(p.shape[0])}
    warn: list = []
    p = _finite_rows(p, info, warn)
    if grid is not None:
        p = _in_region(p, grid, cfg.region_margin_m, info, warn)
    check_not_degenerate(p)
    if p.shape[0] > cfg.max_points:
        # A uniform random subset, not voxel averaging: averaging over 3-D voxels keeps one point
        # per occupied voxel, which over-weights the noise tails (measured: 1 mm noise -> 1.75 mm).
        keep = np.random.default_rng(cfg.seed).choice(p.shape[0], cfg.max_points, replace=False)
        p = p[np.sort(keep)]
    info["subsampled_to"] = int(p.shape[0])
    before = p.shape[0]
    p = _remove_isolated(p, cfg.outlier_radius_factor, cfg.outlier_min_neighbours)
    info["isolated_outliers"] = int(before - p.shape[0])
    check_not_degenerate(p)

    n, c0, inl = _frame_plane(p, cfg.plane_threshold_m)
    eu, ev, n = _frame(n)
    q = p - c0
    uv = np.stack([q @ eu, q @ ev], axis=1)
    w = q @ n
    info["plane_inlier_fraction"] = round(float(inl.mean()), 4)

    # Cells twice the sampling: a camera cloud ~1 mm apart leaves no empty cells at 2 mm.
    cell = 2.0 * cfg.voxel_m
    sigma_cells = max(1.0, cfg.smooth_window_m / (2.0 * cell))
    field = _height_field_without_outliers(uv, w, cell, sigma_cells, cfg.surface_outlier_sigma, info)
    lo, h, wt, cnt, n_points, noise = field
    support, occ = _outline(cnt, cell, cfg)
    info["holes_filled_fraction"] = round(float(1.0 - (occ & support).sum() / max(support.sum(), 1)), 4)
    surface, curved = _surface_model(h, wt, occ, support, n_points, noise, sigma_cells, float(wavelength_m), cfg, info)

    # Model points on a voxel_m lattice over the outline, heights interpolated from the field.
    f = round(cell / cfg.voxel_m)
    fine = np.kron(support, np.ones((f, f), bool))
    ii, jj = np.nonzero(fine)
    uvs = lo + (np.stack([ii, jj], axis=1) + 0.5) * cfg.voxel_m
    if surface == "plane" or (surface == "outline" and not curved):
        ws = np.zeros(ii.size)
    else:
        ws = ndimage.map_coordinates(h, [(ii + 0.5) / f - 0.5, (jj + 0.5) / f - 0.5], order=1, mode="nearest")
    pts = c0 + uvs[:, :1] * eu + uvs[:, 1:] * ev + ws[:, None] * n
    info["points"] = int(pts.shape[0])
    info["seconds"] = round(time.perf_counter() - t0, 4)
    return ConditionedCloud(pts, surface, (n, float(n @ c0)), info, warn)


def _finite_rows(p: np.ndarray, info: dict, warn: list) -> np.ndarray:
    """The cloud's finite rows (float (N, 3) metres), the others counted in ``info`` and warned of."""
    finite = np.isfinite(p).all(axis=1)
    info["non_finite_rows"] = int((~finite).sum())
    if info["non_finite_rows"]:
        p = p[finite]
        _warn(
            warn,
            f"reference point cloud: dropped {info['non_finite_rows']} of {info['input_points']} rows holding NaN or inf",
        )
    if p.shape[0] < MIN_POINTS:
        raise TwinFocusError(
            f"reference point cloud has only {p.shape[0]} finite points (at least {MIN_POINTS} needed)"
        )
    return p


def _in_region(p: np.ndarray, grid: ImageGrid, margin_m: float, info: dict, warn: list) -> np.ndarray:
    """The points (float (N, 3) metres) within ``margin_m`` of the region's x, y; refuses a cloud
    wholly outside it (a wrong frame or unit) and warns when most of it lies outside."""
    m = margin_m
    inside = (p[:, 0] >= grid.x0 - m) & (p[:, 0] <= grid.x1 + m) & (p[:, 1] >= grid.y0 - m) & (p[:, 1] <= grid.y1 + m)
    info["outside_region"] = int((~inside).sum())
    if not inside.any():
        lo, hi = p.min(axis=0), p.max(axis=0)
        raise TwinFocusError(
            f"reference point cloud lies entirely outside the reference region: cloud x [{lo[0]:.3f}, {hi[0]:.3f}] "
            f"y [{lo[1]:.3f}, {hi[1]:.3f}] m, region x [{grid.x0:.3f}, {grid.x1:.3f}] y [{grid.y0:.3f}, {grid.y1:.3f}] m "
            "(wrong frame or units? clouds are metres in the radar's scene frame)"
        )
    if info["outside_region"]:
        p = p[inside]
        if info["outside_region"] > 0.5 * (info["outside_region"] + p.shape[0]):
            _warn(
                warn,
                f"reference point cloud: {info['outside_region']} of {info['outside_region'] + p.shape[0]} "
                "points lie outside the reference region and were dropped (is the region right?)",
            )
    if p.shape[0] < MIN_POINTS:
        raise TwinFocusError(
            f"reference point cloud has only {p.shape[0]} points inside the reference region "
            f"(at least {MIN_POINTS} needed)"
        )
    return p


def _height_field_without_outliers(uv, w, cell: float, sigma_cells: float, outlier_sigma: float, info: dict):
    """The smoothed height field over the plane's (u, v) cells (``_height_field``), fitted, the points
    far from the fit dropped, fitted again: (lo, h, wt, cnt, points kept, noise sd in metres)."""
    for _ in range(2):  # fit, drop what lies far from the fit, fit again
        lo, _, h, wt, cnt = _height_field(uv, w, cell, sigma_cells)
        ij = np.floor((uv - lo) / cell).astype(np.int64)
        r = w - h[ij[:, 0], ij[:, 1]]
        noise = float(1.4826 * np.median(np.abs(r - np.median(r))))
        far = np.abs(r) > max(outlier_sigma * noise, 2.0 * cell)
        if not far.any():
            break
        uv, w = uv[~far], w[~far]
        info["surface_outliers"] = info.get("surface_outliers", 0) + int(far.sum())
        if uv.shape[0] < MIN_POINTS:
            raise TwinFocusError("reference point cloud: too few points agree on a surface (all look like outliers)")
    info.setdefault("surface_outliers", 0)
    info["noise_sd_m"] = noise
    return lo, h, wt, cnt, int(uv.shape[0]), noise


def _outline(cnt: np.ndarray, cell: float, cfg: ConditionConfig) -> tuple[np.ndarray, np.ndarray]:
    """(outline, occupied cells), bool (U, V): occupied cells, closed over close_radius_m, enclosed
    holes filled, specks dropped."""
    occ = cnt > 0
    support = ndimage.binary_closing(occ, _disc(cfg.close_radius_m / cell), border_value=0) | occ
    holes, nh = ndimage.label(ndimage.binary_fill_holes(support) & ~support)
    if nh:
        area = ndimage.sum(np.ones_like(support), holes, index=np.arange(1, nh + 1)) * cell * cell
        support |= np.isin(holes, 1 + np.flatnonzero(area <= cfg.fill_hole_max_m2))
    lab, nlab = ndimage.label(support)
    if nlab > 1:
        sizes = ndimage.sum(support, lab, index=np.arange(1, nlab + 1))
        support = np.isin(lab, 1 + np.flatnonzero(sizes >= 0.01 * sizes.max()))
    return support, occ


def _surface_model(h, wt, occ, support, n_points: int, noise: float, sigma_cells: float, wavelength_m: float,
                   cfg: ConditionConfig, info: dict) -> tuple[str, bool]:  # fmt: skip
    """The surface model ("plane", "smooth" or "outline") the cloud supports, with its reason in
    ``info``, and whether the surface is curved."""
    # Model uncertainty: noise / sqrt(points in the smoothing window). Density over the outline's
    # area, not per occupied cell (which is >= 1 however sparse the cloud).
    density = n_points / max(int(support.sum()), 1)
    model_sd = noise / (2.0 * np.sqrt(np.pi) * sigma_cells * np.sqrt(density))
    k2 = 4.0 * np.pi / wavelength_m
    # Curvature over well-supported cells only: at edges and holes the field rests on few points.
    solid = support & (wt >= 0.5 * np.median(wt[occ]))
    h_sup = h[solid] if solid.any() else h[support]
    curvature = float(np.percentile(h_sup, 99) - np.percentile(h_sup, 1)) if h_sup.size else 0.0
    info["curvature_m"] = curvature
    info["model_depth_sd_m"] = float(model_sd)
    info["model_phase_sd_rad"] = float(k2 * model_sd)
    # 12 sd: the field's cells are correlated, so its spread on a noisy plane exceeds +-3 model sd
    curved = curvature > max(cfg.curvature_min_m, 12.0 * model_sd)
    # Between half that and that, the cloud cannot tell a curved surface from a flat one.
    maybe_curved = curvature > 0.5 * max(cfg.curvature_min_m, 12.0 * model_sd)

    if cfg.surface != "auto":
        surface, reason = cfg.surface, "asked for"
    elif maybe_curved and k2 * model_sd > cfg.max_phase_sd_rad:
        surface = "outline"
        shape = "curved" if curved else "possibly curved"
        reason = (
            f"{shape} ({curvature * 1e3:.1f} mm off a plane) but the cloud's noise ({noise * 1e3:.2f} mm) leaves "
            f"the surface uncertain to {model_sd * 1e3:.2f} mm = {k2 * model_sd:.1f} rad of radar phase "
            f"(> {cfg.max_phase_sd_rad} rad)"
        )
    elif curved:
        surface = "smooth"
        reason = f"curved: the smoothed surface departs {curvature * 1e3:.1f} mm from the best plane"
    else:
        surface = "plane"
        reason = (
            f"planar: the smoothed surface stays within {curvature * 1e3:.1f} mm of the plane "
            f"(noise {noise * 1e3:.2f} mm)"
        )
    info["surface"] = surface
    info["surface_reason"] = reason
    # the shape, whatever the model: an outline-only model of a bent plate is still bent
    info["curved"] = bool(curved)
    return surface, bool(curved)


def support_on_grid(points_m: np.ndarray, grid: ImageGrid) -> np.ndarray:
    """bool (H, W): grid pixels within half a pixel of a point's x, y (then a one-pixel closing, so
    points sparser than the pixels leave no gaps)."""
    p = np.asarray(points_m, dtype=np.float64)
    r, c = grid.index_of(p[:, 0], p[:, 1])
    r, c = np.rint(r).astype(np.int64), np.rint(c).astype(np.int64)
    ok = (r >= 0) & (r < grid.height) & (c >= 0) & (c < grid.width)
    mask = np.zeros(grid.shape, dtype=bool)
    mask[r[ok], c[ok]] = True
    return ndimage.binary_closing(mask, np.ones((3, 3), bool), border_value=0) | mask


def digital_twin_reference(
    points_m,
    scan_positions,
    chirp,
    grid: ImageGrid,
    *,
    config: ConditionConfig | None = None,
    offset_m=None,
    method: str = "psf",
    **bp_options,
) -> DigitalTwinReference:
    """Condition ``points_m`` and build the reference's template and support on ``grid``.

    Parameters
    ----------
    points_m : float (N, 3) reference cloud, scene frame, metres (any camera, as it comes).
    scan_positions : float (M, K, 3) the scan's phase centres; chirp : the scan's chirp.
    grid : the reference region's :class:`ImageGrid`.
    offset_m : optional (3,) camera-radar offset (calibration) added to the cloud first.
    method, bp_options : as :func:`twinfocus.twins.digital_twin.template.digital_twin_template`.

    Returns :class:`DigitalTwinReference` (template float32 (H, W), support bool (H, W), the
    conditioned cloud, info for metrics.json). An outline-only model gives the incoherent
    (expected rough-surface) template.
    """
    p = np.asarray(points_m)
    if offset_m is not None:
        off = np.asarray(offset_m, dtype=np.float64).reshape(-1)
        if off.shape != (3,) or not np.isfinite(off).all():
            raise TwinFocusError(f"camera-radar offset must be 3 finite numbers (metres), got {offset_m!r}")
        p = np.asarray(p, dtype=np.float64) + off
    cfg = config or ConditionConfig()
    cloud = condition_cloud(p, grid, chirp.wavelength_m, cfg)
    t0 = time.perf_counter()
    coherent = cloud.surface != "outline"
    template = digital_twin_template(
        cloud.points_m, scan_positions, chirp, grid, method=method, coherent=coherent, **bp_options
    )
    support = support_on_grid(cloud.points_m, grid)
    if not support.any():
        raise TwinFocusError("the conditioned reference covers no pixel of the reference region")
    info = dict(cloud.info)
    info.update(
        {
            "template_method": method,
            "template_coherent": coherent,
            "template_seconds": round(time.perf_counter() - t0, 4),
            "support_pixels": int(support.sum()),
            "offset_m": None if offset_m is None else [float(v) for v in off],
            "warnings": list(cloud.warnings),
            "config": asdict(cfg),
        }
    )
    return DigitalTwinReference(template, support, cloud, info)


def digital_twin_reference_from_file(
    path: str | os.PathLike, scan, grid: ImageGrid, *, calibration=None, method: str = "psf", config=None, **bp_options
):
    """``twinfocus focus --digital-twin POINTS.npy``: the cloud in ``path`` conditioned
    (:func:`twinfocus.twins.digital_twin.condition.digital_twin_reference`) for ``scan``'s aperture on
    ``grid``: a :class:`~twinfocus.twins.digital_twin.condition.DigitalTwinReference` (template float32
    (H, W), support bool (H, W), info for metrics.json).

    calibration : optional path of a camera-radar calibration (JSON from ``twinfocus twin
    --calibrate``) whose offset is added to the points. config : optional
    :class:`~twinfocus.twins.digital_twin.condition.ConditionConfig`.
    """
    points = load_points(path, allow_non_finite=True)
    offset = None
    if calibration is not None:
        offset = RadarCameraCalibration.load(calibration).offset_m
    try:
        return digital_twin_reference(
            points, scan.positions, scan.chirp, grid, config=config, offset_m=offset, method=method, **bp_options
        )
    except TwinFocusError as exc:
        raise TwinFocusError(f"{path}: {exc}") from None


def digital_twin_template_from_file(
    path: str | os.PathLike, scan, grid: ImageGrid, *, calibration=None, method: str = "psf", **bp_options
) -> np.ndarray:
    """The template of :func:`digital_twin_reference_from_file` alone: float32 (H, W)."""
    return digital_twin_reference_from_file(
        path, scan, grid, calibration=calibration, method=method, **bp_options
    ).template
