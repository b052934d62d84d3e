"""Reference templates: the focused amplitude of the reference on the reference grid.

Template file (``.npz``, docs/architecture.md section 4): ``image`` float32 (H, W) amplitude, ``x_m`` (W,),
``y_m`` (H,), ``z_m`` scalar, and optionally ``phase_rad`` float32 (H, W): the phase of a physical
twin's image, which lets autofocus register the template and estimate the phases in closed form
(:mod:`twinfocus.focus.template_match`); a digital twin's also ``support`` uint8 (H, W), the reference's
outline the outline estimator needs, and ``conditioning_json``, what its cloud's conditioning
chose (:attr:`twinfocus.twins.digital_twin.condition.DigitalTwinReference.info`). A template made on
another grid is resampled (bilinear, on the complex image when it has a phase) onto the reference
grid; one that does not cover it is refused.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.backprojection.numba_backend import backproject
from twinfocus.imaging.grid import ImageGrid
from twinfocus.io.arrays import load_npz, save_npz_atomic
from twinfocus.radar.scan import Scan


def save_template(
    path: str | os.PathLike,
    image: np.ndarray,
    grid: ImageGrid,
    *,
    support: np.ndarray | None = None,
    info: dict | None = None,
) -> None:
    """Write a template file for ``grid``: a float image is stored as the amplitude, a complex one
    as amplitude and ``phase_rad``; a digital twin's outline ``support`` bool (H, W) and its
    conditioning ``info`` travel with it, so ``focus --template`` runs what ``--digital-twin`` runs."""
    image = np.asarray(image)
    if image.shape != grid.shape:
        raise TwinFocusError(f"template image is {image.shape}, grid is {grid.shape}")
    arrays = {"image": np.abs(image).astype(np.float32), "x_m": grid.x_m, "y_m": grid.y_m, "z_m": np.float64(grid.z)}
    if np.iscomplexobj(image):
        arrays["phase_rad"] = np.angle(image).astype(np.float32)
    if support is not None:
        if np.shape(support) != grid.shape:
            raise TwinFocusError(f"template support is {np.shape(support)}, grid is {grid.shape}")
        arrays["support"] = np.asarray(support, dtype=bool).astype(np.uint8)
    if info is not None:
        arrays["conditioning_json"] = np.asarray(json.dumps(info, default=float))
    save_npz_atomic(path, arrays)


def load_template(
    path: str | os.PathLike, grid: ImageGrid, z_tolerance_m: float = 0.01, *, with_outline: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray | None, dict | None]:
    """Read a template file and resample it onto ``grid`` (:func:`resample_template`): float32
    (H, W), or complex64 (H, W) when the file holds ``phase_rad``.

    with_outline : return (image, the outline bool (H, W) resampled onto ``grid``
    (:func:`resample_support`) or None, the conditioning dict or None) instead: what a digital
    twin's file carries besides its image."""
    z = load_npz(path)
    missing = [k for k in ("image", "x_m", "y_m", "z_m") if k not in z]
    if missing:
        raise TwinFocusError(f"{path}: not a template file, missing key(s) {', '.join(missing)}")
    try:
        image = resample_template(
            z["image"],
            z["x_m"],
            z["y_m"],
            float(z["z_m"]),
            grid,
            phase_rad=z["phase_rad"] if "phase_rad" in z else None,
            z_tolerance_m=z_tolerance_m,
        )
        if not with_outline:
            return image
        support = resample_support(z["support"] > 0, z["x_m"], z["y_m"], grid) if "support" in z else None
    except TwinFocusError as exc:
        raise TwinFocusError(f"{path}: {exc}") from None
    try:
        info = json.loads(str(z["conditioning_json"])) if "conditioning_json" in z else None
    except json.JSONDecodeError as exc:
        raise TwinFocusError(f"{path}: conditioning_json is not JSON ({exc})") from None
    if info is not None and not isinstance(info, dict):
        raise TwinFocusError(f"{path}: conditioning_json must be a JSON object, got {type(info).__name__}")
    return image, support, info


def resample_template(
    image: np.ndarray,
    x_m: np.ndarray,
    y_m: np.ndarray,
    z_m: float,
    grid: ImageGrid,
    phase_rad: np.ndarray | None = None,
    z_tolerance_m: float = 0.01,
) -> np.ndarray:
    """A template on its own grid, checked and resampled (bilinear) onto ``grid``.

    image : (Ny, Nx) amplitude (its magnitude is taken); x_m (Nx,), y_m (Ny,) increasing pixel
    centres and z_m its plane, metres; phase_rad : optional (Ny, Nx) radians. Returns float32
    (H, W), or complex64 (H, W) with a phase; raises :class:`TwinFocusError` naming what does not
    fit (shape, NaN, plane, coverage of the reference region).
    """
    image, x, y = np.asarray(image), np.asarray(x_m, float), np.asarray(y_m, float)
    _check_template_grid(image.shape, x, y, "image")
    if not np.isfinite(image).all():
        raise TwinFocusError("template image holds NaN or inf")
    if abs(float(z_m) - grid.z) > z_tolerance_m:
        raise TwinFocusError(
            f"template is on the plane z = {float(z_m):.3f} m, the reference region is at z = {grid.z:.3f} m"
        )
    img = np.abs(image).astype(np.float64)
    if phase_rad is not None:
        phase = np.asarray(phase_rad, dtype=np.float64)
        if phase.shape != img.shape or not np.isfinite(phase).all():
            raise TwinFocusError(f"phase_rad must be finite and of the image's shape {img.shape}, got {phase.shape}")
        img = img * np.exp(1j * phase)
    out_dtype = np.complex64 if np.iscomplexobj(img) else np.float32
    if np.iscomplexobj(img):
        return (_bilinear(img.real, x, y, grid) + 1j * _bilinear(img.imag, x, y, grid)).astype(out_dtype)
    return _bilinear(img, x, y, grid).astype(out_dtype)


def resample_support(support: np.ndarray, x_m: np.ndarray, y_m: np.ndarray, grid: ImageGrid) -> np.ndarray:
    """A reference's outline on its template's grid, resampled onto ``grid``: bool (H, W).

    support : bool (Ny, Nx), True inside the outline (a digital twin's,
    :attr:`twinfocus.twins.digital_twin.condition.DigitalTwinReference.support`); x_m (Nx,), y_m (Ny,)
    as :func:`resample_template`. A pixel is inside when the bilinear resample of the mask is at
    least 0.5 (more than half of it covered), so the mask stays a mask and keeps its area; the
    same grid gives the mask back unchanged. Raises :class:`TwinFocusError` naming what does not
    fit (shape, axes, coverage of the reference region, an outline that on ``grid`` holds none or
    all of the region: no outline to place the reference by).
    """
    mask, x, y = np.asarray(support), np.asarray(x_m, float), np.asarray(y_m, float)
    if mask.dtype != bool:
        raise TwinFocusError(f"support must be a bool mask, got {mask.dtype}")
    _check_template_grid(mask.shape, x, y, "support")
    out = _bilinear(mask.astype(np.float64), x, y, grid) >= 0.5
    if not out.any() or out.all():
        raise TwinFocusError(
            f"the outline covers {out.mean():.0%} of the reference region on its grid (needs some but not all)"
        )
    return out


def _check_template_grid(shape: tuple, x: np.ndarray, y: np.ndarray, name: str) -> None:
    if len(shape) != 2 or shape != (y.size, x.size):
        raise TwinFocusError(f"{name} {shape} does not match y_m ({y.size}) x x_m ({x.size})")
    if x.size < 2 or y.size < 2 or np.any(np.diff(x) <= 0) or np.any(np.diff(y) <= 0):
        raise TwinFocusError("x_m and y_m must be increasing with at least 2 values")


def _bilinear(values: np.ndarray, x: np.ndarray, y: np.ndarray, grid: ImageGrid) -> np.ndarray:
    """Real (Ny, Nx) ``values`` at pixel centres (x, y) sampled (bilinear) at ``grid``'s pixels;
    the array itself when the grids agree. Refuses a grid that ``x``, ``y`` do not cover."""
    tol = 1e-9
    if grid.x0 < x[0] - tol or grid.x1 > x[-1] + tol or grid.y0 < y[0] - tol or grid.y1 > y[-1] + tol:
        raise TwinFocusError(
            f"template covers x [{x[0]:.3f}, {x[-1]:.3f}] y [{y[0]:.3f}, {y[-1]:.3f}] m, "
            f"which does not contain the reference region x [{grid.x0}, {grid.x1}] y [{grid.y0}, {grid.y1}]"
        )
    if (
        x.shape == grid.x_m.shape
        and y.shape == grid.y_m.shape
        and np.allclose(x, grid.x_m)
        and np.allclose(y, grid.y_m)
    ):
        return values
    from scipy.ndimage import map_coordinates  # only a resample needs it (0.1 s import)

    cols = np.interp(grid.x_m, x, np.arange(x.size))
    rows = np.interp(grid.y_m, y, np.arange(y.size))
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    return map_coordinates(values, [rr, cc], order=1, mode="nearest")


def scan_template_on(scan: Scan, roi) -> Callable[[int], np.ndarray]:
    """``n ->`` :func:`template_from_scan`'s amplitude on the n x n grid of ``roi`` (X0, X1, Y0, Y1, Z)
    metres: the template a clock search matches at each of its image sizes."""
    return lambda n: template_from_scan(scan, ImageGrid.from_roi(roi, n))


def template_from_scan(scan: Scan, grid: ImageGrid, keep_phase: bool = False, **bp_options) -> np.ndarray:
    """Physical twin: a scan taken on accurate positions (a motion-stage capture of the reference
    alone), back-projected on the reference grid: its amplitude, float32 (H, W), or with
    ``keep_phase`` the complex image, complex64 (H, W)."""
    positions = scan.positions_true if scan.positions_true is not None else scan.positions
    image = backproject(scan.data, positions, scan.chirp, grid, **bp_options)
    return image.astype(np.complex64) if keep_phase else np.abs(image).astype(np.float32)
