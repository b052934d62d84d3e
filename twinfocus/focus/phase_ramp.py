"""The constant + linear-in-aperture part of per-position phases (what moves the image).

A phase that is linear across the aperture only moves the image, and a constant changes nothing
visible: :func:`fit_linear_phase` finds that part of an estimate, without being biased by
wrapping. The transfer (:func:`twinfocus.focus.autofocus.transfer_phase`) removes it when a misplaced
template explains it; the averaged outline estimator
(:func:`twinfocus.focus.template_match.averaged_outline_phase`) removes it from the difference between
estimates before averaging them. Its own module so both can use it without an import circle.
"""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError

#: the coherence x sqrt(M) a fitted ramp must leave to be taken (random phases reach ~2.5 at the
#: best of the fit's grid of ramps)
MIN_RAMP_COHERENCE_SQRT_M = 4.0


def fit_linear_phase(
    phase_rad: np.ndarray,
    aperture_m: np.ndarray,
    max_slope_rad_per_m: float = 80.0,
    min_coherence_sqrt_m: float = MIN_RAMP_COHERENCE_SQRT_M,
) -> tuple[np.ndarray, np.ndarray]:
    """Best constant + linear-in-aperture phase a + b . p fitted to wrapped phases.

    A linear phase across the aperture only moves the image (and a constant changes nothing
    visible), so this is the part of an estimate that a misplaced template pulls in. The fit
    maximises the coherence |sum_m exp(j (phi_m - b . p_m))| — a coarse grid over the slope b,
    then Gauss-Newton steps on the wrapped residual — so wrapping never biases it.

    A ramp is taken only when it is significant: the coherence |mean exp(j (phi - ramp))| it
    leaves must reach ``min_coherence_sqrt_m / sqrt(M)`` (random phases reach ~2.5 / sqrt(M) at
    the best of the grid's ramps); otherwise the ramp is the constant alone and the slopes are 0.

    phase_rad : (M,) radians; aperture_m : (M, 2) position of each radar position in the aperture
    plane (x, y), metres. Returns (ramp (M,) radians, coefficients [a, bx, by] (rad, rad/m)).
    """
    phi = np.asarray(phase_rad, dtype=np.float64)
    p = np.asarray(aperture_m, dtype=np.float64)
    if p.shape != (phi.size, 2):
        raise TwinFocusError(f"aperture_m must be ({phi.size}, 2), got {p.shape}")
    p = p - p.mean(axis=0)
    span = np.maximum(np.ptp(p, axis=0), 1e-9)
    # Grid step: a quarter turn of ramp over the aperture in each axis. Slopes are searched only
    # up to pi / (coarsest gap between sampled coordinates): beyond that a ramp aliases (the
    # raster's columns are 82 mm apart, so +-38 rad/m in x).
    steps = (np.pi / 2) / span
    axes = []
    for k in range(2):
        if span[k] <= 1e-6:
            axes.append(np.zeros(1))
            continue
        gaps = np.diff(np.unique(np.round(p[:, k], 6)))
        limit = min(max_slope_rad_per_m, np.pi / gaps.max()) if gaps.size else max_slope_rad_per_m
        axes.append(np.arange(-limit, limit + steps[k], steps[k]))
    z = np.exp(1j * phi)
    # exp(-j (bx px + by py)) = exp(-j bx px) exp(-j by py): the whole grid's coherences in one
    # (n_bx, M) @ (M, n_by) product, not n_bx x n_by x M exponentials
    coh = np.abs((np.exp(-1j * np.outer(axes[0], p[:, 0])) * z) @ np.exp(-1j * np.outer(axes[1], p[:, 1])).T)
    i, j = np.unravel_index(int(np.argmax(coh)), coh.shape)
    best, best_b = float(coh[i, j]), np.array([axes[0][i], axes[1][j]])
    if best < min_coherence_sqrt_m * np.sqrt(phi.size):
        # The phases hold no detectable ramp (errors past lambda/4 wrap them to noise: the best of
        # the grid's ramps then only reaches ~2.5 / sqrt(M)); a fitted one would shift the image
        # at random, so only the constant is taken.
        a = float(np.angle(z.sum()))
        return np.full(phi.size, a), np.array([a, 0.0, 0.0])
    b = best_b
    a = np.angle(np.sum(z * np.exp(-1j * (p @ b))))
    design = np.column_stack([np.ones(phi.size), p])
    for _ in range(5):
        resid = np.angle(np.exp(1j * (phi - a - p @ b)))
        da, dbx, dby = np.linalg.lstsq(design, resid, rcond=None)[0]
        a, b = a + da, b + np.array([dbx, dby])
    ramp = a + p @ b
    return ramp, np.array([a, *b])


def ramp_free_coherence(phase_rad: np.ndarray, aperture_m: np.ndarray) -> float:
    """How well per-position phases hold together once their constant + linear-in-aperture ramp
    (:func:`fit_linear_phase`) is taken out: |mean exp(j (phi - ramp))| x sqrt(M), dimensionless.

    M random phases give about 0.9 and exceed 2.5 once in 500 (Rayleigh), so below that the
    phases have wrapped (tracking error past about lambda/5 along the line of sight) and their
    ramp, the image shift they carry, cannot be told from the errors.

    phase_rad : (M,) radians; aperture_m : (M, 2) each position's (x, y), metres.
    """
    phi = np.asarray(phase_rad, dtype=np.float64)
    ramp, _ = fit_linear_phase(phi, aperture_m)
    return float(np.abs(np.exp(1j * (phi - ramp)).mean()) * np.sqrt(phi.size))


def aperture_polynomial(centres_m: np.ndarray, degree: int) -> np.ndarray:
    """Monomials x^i y^j (i + j <= ``degree``) of the positions' aperture coordinates, x and y each
    scaled to [-1, 1], in the order 1, y, x, y^2, x y, x^2, ...: float64 (M, terms).

    centres_m : (M, 2 or 3) phase centres, metres (z is not used). Degree 1 is the ramp this
    module fits; degree 2 adds the defocus and astigmatism across the aperture.
    """
    c = np.asarray(centres_m, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] < 2:
        raise TwinFocusError(f"centres_m must be (M, 2) or (M, 3), got {c.shape}")
    x, y = c[:, 0], c[:, 1]
    x = (x - x.mean()) / max(np.ptp(x) / 2, 1e-12)
    y = (y - y.mean()) / max(np.ptp(y) / 2, 1e-12)
    return np.stack([x**i * y**j for n in range(int(degree) + 1) for i in range(n + 1) for j in [n - i]], axis=1)
