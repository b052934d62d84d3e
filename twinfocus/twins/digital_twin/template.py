"""Simulated SAR amplitude template of the reference from its point cloud (source paper, eq. 10).

Exact model (:func:`exact_template`): every point j is a scatterer of amplitude a_j (1 by
default, as in the paper); the IF samples over the scan's phase centres are simulated
(:func:`twinfocus.simulation.if_simulator.simulate_if`) and back-projected onto the reference grid
(:func:`twinfocus.imaging.backprojection.numba_backend.backproject`). Its cost is one full simulation plus one full
back-projection (seconds to tens of seconds on two cores at the paper's size).

Cheap model (:func:`psf_template`, the default): on a plane the image of a point cloud is its
reflectivity map convolved with the system's point-spread function, which barely changes across a
reference-sized region. So the PSF is computed once, by back-projecting one simulated point at
the cloud's centre onto a window of offsets at the grid's spacing, and every point is then placed
by an exact sub-pixel (Fourier) shift:

    image = IFFT2( FFT2(PSF) * sum_j a_j exp(-2 pi i (k_y row_j / H' + k_x col_j / W')) ),

the point sum being a separable (rows x points) @ (points x columns) product. Depth is handled by
slabs: points are grouped by depth (slab thickness well inside the depth of focus), each slab with
the PSF of its own depth, and a point's residual depth within its slab enters as the phase
2 k_c dz <cos theta>. Measured against the exact model in ``benchmarks/bench_digital_twin.py``
(docs/digital_twin.md).

``coherent=False`` gives the expected amplitude of a rough (speckled) surface instead,
sqrt(|PSF|^2 * sum_j |a_j|^2 delta_j), the mean image over random scatterer phases.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.grid import ImageGrid
from twinfocus.io.arrays import load_npy
from twinfocus.io.documents import read_file
from twinfocus.radar.fmcw import C_M_PER_S, Chirp

# Largest depth spread (metres) one PSF serves: a point dz off its slab's depth is defocused by
# far less than a resolution cell (depth of focus ~ lambda / (2 NA^2) ~ 14 mm here).
DEFAULT_SLAB_M = 4e-3
#: Aperture thinning (positions, channels) for the PSF of a full-size scan (see psf_template).
DEFAULT_ELEMENT_STEP = (2, 2)


def _check_points(points_m) -> np.ndarray:
    from twinfocus.twins.digital_twin.pointcloud import check_not_degenerate  # lazy: open3d (+4.3 s at import)

    p = np.asarray(points_m)
    if p.ndim != 2 or p.shape[1] != 3:
        raise TwinFocusError(f"reference point cloud must be an (N, 3) array of metres, got shape {p.shape}")
    p = p.astype(np.float64)
    check_not_degenerate(p)
    return p


def _check_positions(positions_m) -> np.ndarray:
    e = np.asarray(positions_m, dtype=np.float64)
    if e.ndim != 3 or e.shape[2] != 3 or e.shape[0] == 0 or e.shape[1] == 0:
        raise TwinFocusError(f"scan positions must be (M, K, 3) metres, got shape {e.shape}")
    if not np.isfinite(e).all():
        raise TwinFocusError("scan positions hold NaN or inf")
    return e


def _amplitudes(amplitudes, n: int) -> np.ndarray:
    if amplitudes is None:
        return np.ones(n, np.complex128)
    a = np.asarray(amplitudes).astype(np.complex128).reshape(-1)
    if a.shape != (n,) or not np.isfinite(a).all():
        raise TwinFocusError(f"amplitudes must be {n} finite numbers, got shape {a.shape}")
    return a


# --- exact model --------------------------------------------------------------------------------------


def exact_template(points_m, positions_m, chirp: Chirp, grid: ImageGrid, amplitudes=None, **bp_options) -> np.ndarray:
    """Point-scatterer simulation over every phase centre + back-projection: float32 (H, W)
    amplitude on ``grid``. ``bp_options`` go to :func:`twinfocus.imaging.backprojection.numba_backend.backproject`."""
    from twinfocus.imaging.backprojection.numba_backend import backproject  # lazy: numba (+2.1 s at import)
    from twinfocus.simulation.if_simulator import simulate_if  # lazy: numba (+2.1 s at import)

    p = _check_points(points_m)
    e = _check_positions(positions_m)
    a = _amplitudes(amplitudes, p.shape[0])
    data = simulate_if(p, a, e, chirp)
    return np.abs(backproject(data, e, chirp, grid, **bp_options)).astype(np.float32)


# --- PSF model ----------------------------------------------------------------------------------------


def point_spread_function(
    positions_m,
    chirp: Chirp,
    grid: ImageGrid,
    centre_m,
    half_size: tuple[int, int],
    element_step: tuple[int, int] = (1, 1),
    **bp_options,
) -> np.ndarray:
    """Back-projected image of a unit scatterer at ``centre_m`` on the plane z = ``grid.z``.

    Sampled at offsets (i dy, j dx), |i| <= half_size[0], |j| <= half_size[1], (dy, dx) the grid's
    spacing: complex64 (2 hy + 1, 2 hx + 1), entry [hy + i, hx + j] at centre + (j dx, i dy).
    ``element_step`` (positions, channels) thins the aperture for speed (grating lobes move to
    lambda R / (2 pitch); keep them outside the window).
    """
    from twinfocus.imaging.backprojection.numba_backend import backproject_points  # lazy: numba (+2.1 s at import)
    from twinfocus.simulation.if_simulator import simulate_if  # lazy: numba (+2.1 s at import)

    e = _check_positions(positions_m)[:: int(element_step[0]), :: int(element_step[1])]
    c = np.asarray(centre_m, dtype=np.float64).reshape(3)
    hy, hx = (int(v) for v in half_size)
    dy, dx = grid.spacing_m
    yy, xx = np.meshgrid(np.arange(-hy, hy + 1) * dy + c[1], np.arange(-hx, hx + 1) * dx + c[0], indexing="ij")
    pts = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, float(grid.z))], axis=1)
    data = simulate_if(c[None, :], np.ones(1, np.complex128), e, chirp)
    img = backproject_points(data, e, chirp, pts, **bp_options)
    return img.reshape(2 * hy + 1, 2 * hx + 1).astype(np.complex64)


def _fast_len(n: int) -> int:
    import scipy.fft

    return int(scipy.fft.next_fast_len(int(n)))


def _taper(n_half: int, frac: float = 0.25) -> np.ndarray:
    """Tukey window over 2 n + 1 samples: flat in the middle, cosine to 0 over ``frac`` of each side."""
    n = 2 * n_half + 1
    w = np.ones(n)
    m = max(1, int(round(frac * n_half)))
    ramp = 0.5 * (1 - np.cos(np.pi * (np.arange(m) + 1) / (m + 1)))
    w[:m] = ramp
    w[-m:] = ramp[::-1]
    return w


def convolve_points(points_rc: np.ndarray, weights: np.ndarray, psf: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """sum_j w_j PSF(r - row_j, c - col_j) on an (H, W) pixel grid, with exact sub-pixel shifts.

    points_rc : float (N, 2) fractional (row, col) of the points; weights : complex (N,);
    psf : complex (2 hy + 1, 2 hx + 1) sampled at integer offsets, centred. Points further than
    the PSF's half size outside the grid are dropped (they do not reach it). Returns complex128 (H, W).
    """
    h, w = shape
    hy, hx = psf.shape[0] // 2, psf.shape[1] // 2
    hp, wp = _fast_len(h + 2 * hy + 1), _fast_len(w + 2 * hx + 1)
    rc = np.asarray(points_rc, dtype=np.float64)
    keep = (rc[:, 0] > -hy) & (rc[:, 0] < h - 1 + hy) & (rc[:, 1] > -hx) & (rc[:, 1] < w - 1 + hx)
    rc, wt = rc[keep], np.asarray(weights)[keep]
    if rc.shape[0] == 0:
        return np.zeros((h, w), np.complex128)
    # The PSF wrapped so that offset (0, 0) sits at index (0, 0).
    kernel = np.zeros((hp, wp), np.complex128)
    rows = np.arange(-hy, hy + 1) % hp
    cols = np.arange(-hx, hx + 1) % wp
    kernel[np.ix_(rows, cols)] = psf
    ky = np.fft.fftfreq(hp)  # cycles per pixel
    kx = np.fft.fftfreq(wp)
    ey = np.exp(-2j * np.pi * np.outer(ky, rc[:, 0]))  # (hp, N)
    ex = np.exp(-2j * np.pi * np.outer(rc[:, 1], kx))  # (N, wp)
    spectrum = (ey * wt[None, :]) @ ex
    canvas = np.fft.ifft2(np.fft.fft2(kernel) * spectrum)
    return canvas[:h, :w]


def _mean_cos(positions_m: np.ndarray, centre: np.ndarray) -> float:
    d = positions_m.reshape(-1, 3) - centre
    return float(np.mean(np.abs(d[:, 2]) / np.linalg.norm(d, axis=1)))


@dataclass
class TemplateInfo:
    """What :func:`psf_template` did: slabs used, PSF half size, seconds per stage."""

    n_points: int
    n_slabs: int
    half_size: tuple[int, int]
    seconds: dict


def default_half_size(
    grid: ImageGrid, wavelength_m: float, positions_m: np.ndarray, centre_m: np.ndarray, cells: float = 10.0
) -> tuple[int, int]:
    """PSF half window in pixels: ``cells`` cross-range resolution cells each way (the side lobes
    beyond hold little energy), at least 8 pixels, at most the grid's size."""
    e = positions_m.reshape(-1, 3) - np.asarray(centre_m)
    r = np.linalg.norm(e, axis=1)
    dy, dx = grid.spacing_m
    out = []
    for axis, step, n in ((1, dy, grid.height), (0, dx, grid.width)):
        spread = np.ptp(e[:, axis] / r)
        res = wavelength_m / (2.0 * max(spread, 1e-6))
        out.append(int(min(max(8, np.ceil(cells * res / step)), n)))
    return (out[0], out[1])


def psf_template(
    points_m,
    positions_m,
    chirp: Chirp,
    grid: ImageGrid,
    amplitudes=None,
    *,
    coherent: bool = True,
    half_size: tuple[int, int] | None = None,
    slab_m: float = DEFAULT_SLAB_M,
    element_step: tuple[int, int] | None = None,
    return_info: bool = False,
    **bp_options,
):
    """Amplitude template by PSF convolution (module docstring): float32 (H, W) on ``grid``.

    Parameters
    ----------
    points_m : float (N, 3) scene-frame points of the reference, metres.
    positions_m : float (M, K, 3) the scan's phase centres (tracked positions are fine: the
        template is an error-free image of the same aperture).
    amplitudes : optional complex (N,) reflectivities (default 1).
    coherent : True for a smooth surface (complex sum), False for the expected amplitude of a
        rough one.
    half_size : PSF half window (rows, columns) in pixels; default :func:`default_half_size`.
    element_step : (positions, channels) thinning of the aperture for the PSF; default
        :data:`DEFAULT_ELEMENT_STEP` for scans of at least 64 positions x 16 channels, else none.
        Halving both moves the grating lobes to lambda R / (2 x 2 pitch) (~0.29 m in y for the
        paper's 2 mm rows), far outside the window: same template (measured display-domain SSIM
        vs the exact model 0.986 either way) for a quarter of the PSF's cost.
    """
    times: dict[str, float] = {}
    p = _check_points(points_m)
    e = _check_positions(positions_m)
    a = _amplitudes(amplitudes, p.shape[0])
    centre = np.array([p[:, 0].mean(), p[:, 1].mean(), np.median(p[:, 2])])
    hs = half_size or default_half_size(grid, chirp.wavelength_m, e, centre)
    if element_step is None:
        element_step = DEFAULT_ELEMENT_STEP if (e.shape[0] >= 64 and e.shape[1] >= 16) else (1, 1)
    dy, dx = grid.spacing_m
    rc = np.stack([(p[:, 1] - grid.y0) / dy, (p[:, 0] - grid.x0) / dx], axis=1)
    # Depth slabs: one PSF per slab.
    z = p[:, 2]
    n_slabs = max(1, int(np.ceil((z.max() - z.min()) / slab_m)))
    edges = np.linspace(z.min(), z.max(), n_slabs + 1)
    slab = np.clip(np.searchsorted(edges, z, side="right") - 1, 0, n_slabs - 1)
    k2 = 2.0 * 2.0 * np.pi * chirp.fc_hz / C_M_PER_S
    cos_mean = _mean_cos(e, centre)
    taper = np.outer(_taper(hs[0]), _taper(hs[1]))
    total = np.zeros(grid.shape, np.float64 if not coherent else np.complex128)
    t_psf = t_conv = 0.0
    for s in range(n_slabs):
        sel = slab == s
        if not sel.any():
            continue
        zs = float(np.median(z[sel]))
        t0 = time.perf_counter()
        psf = point_spread_function(e, chirp, grid, (centre[0], centre[1], zs), hs, element_step, **bp_options) * taper
        t_psf += time.perf_counter() - t0
        t0 = time.perf_counter()
        if coherent:
            w = a[sel] * np.exp(1j * k2 * cos_mean * (z[sel] - zs))
            total = total + convolve_points(rc[sel], w, psf, grid.shape)
        else:
            total = total + convolve_points(rc[sel], np.abs(a[sel]) ** 2, np.abs(psf) ** 2, grid.shape).real
        t_conv += time.perf_counter() - t0
    times["psf"] = t_psf
    times["convolution"] = t_conv
    amp = np.abs(total) if coherent else np.sqrt(np.maximum(total, 0.0))
    out = amp.astype(np.float32)
    if return_info:
        return out, TemplateInfo(int(p.shape[0]), n_slabs, (hs[0], hs[1]), times)
    return out


# --- entry points ---------------------------------------------------------------------------------------


def digital_twin_template(
    points_m,
    scan_positions,
    chirp: Chirp,
    grid: ImageGrid,
    *,
    method: str = "psf",
    amplitudes=None,
    coherent: bool = True,
    offset_m=None,
    **bp_options,
) -> np.ndarray:
    """The digital twin's amplitude template of the reference on ``grid``: float32 (H, W).

    Parameters
    ----------
    points_m : float (N, 3) reference point cloud in the scene frame (``twinfocus twin`` writes it).
    scan_positions : float (M, K, 3) the scan's (tracked) phase centres.
    chirp : the scan's chirp.
    grid : the reference region's :class:`~twinfocus.imaging.grid.ImageGrid`.
    method : ``"psf"`` (fast, default) or ``"exact"`` (simulate + back-project every point).
    offset_m : optional (3,) radar-camera offset added to the points first (the one-time
        calibration of :mod:`twinfocus.twins.digital_twin.align`).
    bp_options : back-projection keywords (``oversample``, ``precision``, ``backend``, ``device``).
    """
    p = _check_points(points_m)
    if offset_m is not None:
        off = np.asarray(offset_m, dtype=np.float64).reshape(-1)
        if off.shape != (3,) or not np.isfinite(off).all():
            raise TwinFocusError(f"camera-radar offset must be 3 finite numbers (metres), got {offset_m!r}")
        p = p + off
    if method == "psf":
        return psf_template(p, scan_positions, chirp, grid, amplitudes, coherent=coherent, **bp_options)
    if method == "exact":
        if not coherent:
            raise TwinFocusError("the exact template simulates one realisation: use coherent=True (or method='psf')")
        return exact_template(p, scan_positions, chirp, grid, amplitudes, **bp_options)
    raise TwinFocusError(f"unknown template method {method!r}; use 'psf' or 'exact'")


def load_points(path: str | os.PathLike, allow_non_finite: bool = False) -> np.ndarray:
    """Read a point-cloud file (.npy, float (N, 3) metres, scene frame) with clear errors.

    allow_non_finite : keep rows with NaN or inf (for the conditioning, which drops and counts
    them) instead of refusing the file.
    """
    from pathlib import Path

    from twinfocus.sensors.rosbag2_files import (
        split_bag_source,  # lazy: twinfocus.motion (+0.16 s on twinfocus rig --help)
    )

    if (source := split_bag_source(str(path))) is not None:
        return _bag_points(source, allow_non_finite)
    path = Path(path)
    p = read_file(path, load_npy, "point-cloud file", "not a readable .npy point cloud")
    if p.ndim != 2 or p.shape[1] != 3 or not np.issubdtype(p.dtype, np.number):
        raise TwinFocusError(f"{path}: a point cloud must be an (N, 3) array of metres, got {p.dtype} {p.shape}")
    if allow_non_finite:
        return p.astype(np.float64)
    try:
        return _check_points(p)
    except TwinFocusError as exc:
        raise TwinFocusError(f"{path}: {exc}") from None


def _bag_points(source, allow_non_finite: bool) -> np.ndarray:
    """A rosbag2's PointCloud2 (:func:`twinfocus.sensors.rosbag2_files.read_bag_cloud`) placed as
    ``twin`` places a stereo cloud: the camera's optical axes, the left camera at the default
    ZED pose in the scene frame (:data:`~twinfocus.twins.digital_twin.camera.DEFAULT_LEFT_CAMERA_POSITION_M`)."""
    from twinfocus.sensors.rosbag2_files import (
        read_bag_cloud,  # lazy: twinfocus.motion (+0.16 s on twinfocus rig --help)
    )
    from twinfocus.twins.digital_twin.camera import (
        DEFAULT_LEFT_CAMERA_POSITION_M,  # lazy: twinfocus.twins.digital_twin.camera (+0.07 s on twinfocus rig --help)
    )

    cloud = read_bag_cloud(source.path, source.topic, source.at_ns)
    p = cloud.points + np.asarray(DEFAULT_LEFT_CAMERA_POSITION_M, np.float64)
    if allow_non_finite:
        return p
    keep = np.isfinite(p).all(axis=1)
    return _check_points(p[keep])


def pin_bag_clouds(clouds: list[str], timestamps_ns: np.ndarray | None, quiet: bool = False) -> list[str]:
    """``focus --digital-twin BAG:TOPIC``: each rosbag2 source pinned to one message,
    ``BAG:TOPIC@LOG_NS``: the one recorded nearest the scan's middle time stamp, or the first when
    the scan has none (or a time was typed with ``@``). Other entries pass unchanged."""
    import sys

    from twinfocus.sensors.rosbag2_files import (  # lazy: twinfocus.motion (+0.16 s on twinfocus rig --help)
        read_bag_cloud,
        split_bag_source,
    )

    out = []
    for entry in clouds:
        source = split_bag_source(entry)
        if source is None:
            out.append(entry)
            continue
        at = source.at_ns
        if at is None and timestamps_ns is not None and len(timestamps_ns):
            ts = np.asarray(timestamps_ns, np.int64)
            at = int(ts[0] + (ts[-1] - ts[0]) // 2)
        cloud = read_bag_cloud(source.path, source.topic, at)
        if not quiet:
            what = "the scan's middle time" if source.at_ns is None and at is not None else "the time given"
            chosen = "the first message (the scan has no time stamps)" if at is None else f"the one nearest {what}"
            print(
                f"[digital twin] {source.path}:{source.topic}: message {cloud.position} ({chosen}), frame "
                f"{cloud.frame_id or '(unnamed)'}, {cloud.points.shape[0]} points",
                file=sys.stderr,
            )
        out.append(f"{source.path}:{source.topic}@{cloud.log_ns}")
    return out
