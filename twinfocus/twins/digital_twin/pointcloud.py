"""The reference's point cloud: masked stereo depth -> cleaned, down-sampled points in the radar's
scene frame.

Steps (:func:`reference_point_cloud`):

1. Back-project the masked pixels that have a disparity (rectified left frame).
2. Remove outliers (open3d statistical outlier removal: points far from their neighbours).
3. Surface model, only as much as the scene needs. A radar template is an amplitude image whose
   phase depends on depth at the scale of lambda/4 ~ 1 mm, so raw stereo depth noise of that size
   would turn a flat plate into speckle. If a plane explains the cloud (RANSAC with a fixed
   seed, :func:`fit_plane`) the points are re-made as the intersections of every masked pixel's ray with
   that plane: exact outline from the mask, no depth noise. Otherwise the measured points are
   kept ("raw").
4. Voxel down-sampling to the spacing the radar resolves (:func:`radar_point_spacing`, half the
   finest cross-range resolution): finer points cost simulation time and add nothing.
5. Transform to the scene frame with the camera's pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Imported here, not inside the functions: its first import costs ~1 s, which belongs to start-up,
# not to the point-cloud stage's timing.
import open3d as o3d

from twinfocus.errors import TwinFocusError
from twinfocus.twins.digital_twin.camera import Intrinsics, transform_points

MIN_POINTS = 20


@dataclass(frozen=True)
class PointCloudConfig:
    """Settings of :func:`reference_point_cloud`.

    surface : ``"auto"`` (plane if one fits, else raw), ``"plane"`` or ``"raw"``.
    voxel_m : down-sampling voxel (metres); None = keep every point.
    plane_threshold_m : RANSAC inlier distance at 1 m depth (scaled by depth^2 like stereo noise).
    plane_min_inliers : inlier fraction above which the object counts as planar.
    min_confidence : stereo confidence below which a pixel is not used for geometry.
    """

    surface: str = "auto"
    voxel_m: float | None = 1.0e-3
    outlier_neighbours: int = 20
    outlier_std_ratio: float = 2.0
    plane_threshold_m: float = 0.006
    plane_min_inliers: float = 0.85
    min_confidence: float = 0.5
    seed: int = 0

    def validate(self) -> None:
        if self.surface not in ("auto", "plane", "raw"):
            raise TwinFocusError(f"point-cloud surface model must be 'auto', 'plane' or 'raw', got {self.surface!r}")
        if self.voxel_m is not None and not self.voxel_m > 0:
            raise TwinFocusError(f"voxel size must be positive metres, got {self.voxel_m}")


@dataclass
class PointCloudResult:
    """points_m float64 (N, 3) in the scene frame; plane (normal (3,), offset) in the scene frame
    when a plane was used (n . p = offset); counts of each step for the log."""

    points_m: np.ndarray
    surface: str
    plane: tuple[np.ndarray, float] | None
    counts: dict = field(default_factory=dict)


def points_from_depth(depth_m: np.ndarray, mask: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """Camera-frame points of the masked pixels with a finite positive depth: float64 (N, 3).

    Pixel (u, v) with depth Z gives ((u - cx) Z / fx, (v - cy) Z / fy, Z).
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    mask = np.asarray(mask, bool)
    if depth.shape != mask.shape:
        raise TwinFocusError(f"depth map {depth.shape} and mask {mask.shape} differ in size")
    sel = mask & np.isfinite(depth) & (depth > 0)
    v, u = np.nonzero(sel)
    z = depth[v, u]
    return np.stack([(u - intrinsics.cx) * z / intrinsics.fx, (v - intrinsics.cy) * z / intrinsics.fy, z], axis=1)


def rays_through(mask: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """Camera-frame ray directions (x/z, y/z, 1) of the masked pixels: float64 (N, 3)."""
    v, u = np.nonzero(np.asarray(mask, bool))
    return np.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, np.ones(u.size)], axis=1)


def _o3d_cloud(points: np.ndarray):
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
    return pcd


def remove_outliers(points: np.ndarray, neighbours: int = 20, std_ratio: float = 2.0) -> np.ndarray:
    """open3d statistical outlier removal; float64 (N', 3)."""
    if points.shape[0] <= neighbours:
        return points
    pcd, _ = _o3d_cloud(points).remove_statistical_outlier(nb_neighbors=int(neighbours), std_ratio=float(std_ratio))
    return np.asarray(pcd.points)


def voxel_down_sample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """open3d voxel down-sampling (one centroid per occupied voxel); float64 (N', 3)."""
    return np.asarray(_o3d_cloud(points).voxel_down_sample(float(voxel_m)).points)


def fit_plane(
    points: np.ndarray, threshold_m: float, seed: int = 0, iterations: int = 500
) -> tuple[np.ndarray, float, np.ndarray]:
    """RANSAC plane (``iterations`` planes through 3 points drawn with ``seed``, the one with
    most points within ``threshold_m`` metres kept) refined by least squares on its inliers.

    Not open3d's ``segment_plane``: its threads share out the iterations and stop early as they
    race, so its plane, and the twin built on it, changed from run to run and with the machine's
    load (tests/test_batch.py's serial and Dask runs of the same experiment disagreed). This one
    gives the same plane for the same points and seed.

    points : float (N, 3), metres. Returns (unit normal (3,), offset d with n . p = d, inlier
    bool mask (N,)).
    """
    check_not_degenerate(points)
    p = np.asarray(points, np.float64)
    tri = p[np.random.default_rng(int(seed)).integers(0, p.shape[0], size=(int(iterations), 3))]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(normals, axis=1)
    good = norm > 1e-12 * max(float(np.abs(p).max()), 1e-12) ** 2  # three distinct, non-collinear points
    normals = normals[good] / norm[good, None]
    offsets = np.einsum("ij,ij->i", normals, tri[good, 0])
    counts = np.zeros(normals.shape[0], np.int64)
    for i in range(0, normals.shape[0], 32):  # 32 planes at a time: N x 32 distances in memory
        counts[i : i + 32] = (np.abs(p @ normals[i : i + 32].T - offsets[i : i + 32]) <= threshold_m).sum(axis=0)
    if counts.size == 0:
        raise TwinFocusError("reference point cloud is degenerate: no three of its points span a plane")
    best = int(np.argmax(counts))  # the first of equals: the same plane every run
    n, d = normals[best], float(offsets[best])
    inl = np.abs(p @ n - d) <= threshold_m
    if inl.sum() >= 3:
        c = p[inl].mean(axis=0)
        _, _, vt = np.linalg.svd(p[inl] - c, full_matrices=False)
        n = vt[2]
        d = float(n @ c)
        inl = np.abs(p @ n - d) <= threshold_m
    return n, d, inl


def check_not_degenerate(points: np.ndarray, what: str = "reference point cloud") -> None:
    """Raise :class:`TwinFocusError` for an empty, too small, non-finite or collinear cloud."""
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != 3:
        raise TwinFocusError(f"{what} must be an (N, 3) array of metres, got shape {p.shape}")
    if p.shape[0] == 0:
        raise TwinFocusError(f"{what} is empty")
    if not np.isfinite(p).all():
        raise TwinFocusError(f"{what} holds NaN or inf")
    if p.shape[0] < MIN_POINTS:
        raise TwinFocusError(f"{what} has only {p.shape[0]} points (at least {MIN_POINTS} needed)")
    sv = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
    if sv[1] <= 1e-6 * max(sv[0], 1e-12) or sv[0] < 1e-6:
        raise TwinFocusError(f"{what} is degenerate: its points lie on a line or a single spot")


def radar_point_spacing(wavelength_m: float, positions_m: np.ndarray, centre_m: np.ndarray) -> float:
    """Half the finest cross-range resolution the aperture gives at ``centre_m`` (metres).

    Resolution along an axis: lambda / (2 (sin theta_max - sin theta_min)), the spread of the
    direction sines of the phase centres seen from the point. Points closer than half of it are
    not resolved by the radar, so a cloud sampled at this spacing is as good as a denser one.
    """
    e = np.asarray(positions_m, dtype=np.float64).reshape(-1, 3)
    c = np.asarray(centre_m, dtype=np.float64).reshape(3)
    d = e - c
    r = np.linalg.norm(d, axis=1)
    spread = [np.ptp(d[:, a] / r) for a in (0, 1)]
    res = [wavelength_m / (2.0 * s) for s in spread if s > 0]
    if not res:
        raise TwinFocusError("the scan positions span no aperture: cannot tell the radar resolution")
    return 0.5 * min(res)


def reference_point_cloud(
    depth_m: np.ndarray,
    mask: np.ndarray,
    intrinsics: Intrinsics,
    scene_from_camera: np.ndarray,
    config: PointCloudConfig | None = None,
    confidence: np.ndarray | None = None,
) -> PointCloudResult:
    """The masked object's point cloud in the scene frame (see the module docstring).

    Parameters
    ----------
    depth_m : float32 (H, W) depth along the optical axis of the (rectified) camera, NaN invalid.
    mask : bool (H, W) the reference's pixels.
    intrinsics : the (rectified) camera the depth belongs to.
    scene_from_camera : 4 x 4 pose of that camera in the scene frame.
    confidence : optional float (H, W) stereo confidence; pixels below ``min_confidence`` are
        not used to fit geometry.

    Raises :class:`TwinFocusError` for an empty mask, too few points or a degenerate cloud.
    """
    cfg = config or PointCloudConfig()
    cfg.validate()
    mask = np.asarray(mask, bool)
    if mask.shape != np.shape(depth_m):
        raise TwinFocusError(f"mask {mask.shape} and depth map {np.shape(depth_m)} differ in size")
    if not mask.any():
        raise TwinFocusError("the reference mask is empty: nothing to build a point cloud from")
    geo_mask = mask if confidence is None else mask & (np.asarray(confidence) >= cfg.min_confidence)
    counts: dict[str, float] = {"mask_px": int(mask.sum())}
    pts = points_from_depth(depth_m, geo_mask, intrinsics)
    counts["with_depth"] = int(pts.shape[0])
    if pts.shape[0] < MIN_POINTS:
        raise TwinFocusError(
            f"the reference point cloud is empty or too small: {pts.shape[0]} of {counts['mask_px']} masked pixels have stereo depth"
        )
    pts = remove_outliers(pts, cfg.outlier_neighbours, cfg.outlier_std_ratio)
    counts["after_outliers"] = int(pts.shape[0])
    check_not_degenerate(pts)
    surface = "raw"
    plane = None
    if cfg.surface in ("auto", "plane"):
        z_med = float(np.median(pts[:, 2]))
        n, d, inl = fit_plane(pts, cfg.plane_threshold_m * max(z_med, 0.1) ** 2, seed=cfg.seed)
        frac = float(inl.mean())
        counts["plane_inlier_fraction"] = frac
        if cfg.surface == "plane" or frac >= cfg.plane_min_inliers:
            rays = rays_through(mask, intrinsics)
            denom = rays @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                t = d / denom
            ok = np.isfinite(t) & (t > 0)
            if ok.sum() < MIN_POINTS:
                raise TwinFocusError(
                    "the fitted reference plane is seen edge-on: cannot intersect the pixels' rays with it"
                )
            pts = rays[ok] * t[ok, None]
            surface = "plane"
            plane = (n, d)
    counts["surface_points"] = int(pts.shape[0])
    if cfg.voxel_m is not None:
        pts = voxel_down_sample(pts, cfg.voxel_m)
    counts["points"] = int(pts.shape[0])
    check_not_degenerate(pts)
    scene_pts = transform_points(scene_from_camera, pts)
    if plane is not None:
        t = np.asarray(scene_from_camera, dtype=np.float64)
        n_s = t[:3, :3] @ plane[0]
        plane = (n_s, float(plane[1] + n_s @ t[:3, 3]))
    return PointCloudResult(scene_pts, surface, plane, counts)
