"""Space-variant correction: a per-position 3-D position error instead of one scalar phase.

The scalar method applies the reference's phase phi_m to every pixel, which is right only where
the line of sight matches the reference's: a position error dp_m puts the phase
k u . dp_m (k = 4 pi / lambda, u the unit line of sight) on a pixel, so a target ``theta`` away
from the reference keeps k (u_tgt - u_ref) . dp_m (DESIGN.md section 1, paper eq. 7).

With several references (or several parts of one extended reference) seen along different lines
of sight, their per-position phases phi_{r,m} (:func:`twinfocus.template_match.correlation_phase`
per reference) measure dp_m across the line of sight:

    wrap(phi_{r,m} - phi_{0,m}) = k (u_{r,m} - u_{0,m}) . dp_m      (r = 1 .. R-1)

together with each reference's own phase, k u_{r,m} . dp_m up to one constant per reference,
which pins the along-sight part (with a looser noise: it wraps past pi far more often than the
differences do). Solved for all positions at once by sparse least squares with a Gaussian prior
of ``prior_sigma_m`` on dp_m, and optionally a smoothness prior ``step_sigma_m`` on
dp_m - dp_{m-1} (a hand moves smoothly; jitter does not, so leave it off there). A difference
that wraps past pi (a 3-sigma error along the references' baseline at 0.5 mm and 40 degrees, 1 %
of positions at 1 mm) aliases: that position gets a phase ~pi off at the target.

Each target pixel p then gets phi_m(p) = phi_{0,m} + k (u_{m,p} - u_{0,m}) . dp_m
(:func:`pixel_phases`, :func:`form_image_space_variant`).

Measured (docs/beyond.md): references at -20 / +20 degrees, 0.5 mm x/y/z jitter: the target's
SSIM 0.963 with the nearer reference's scalar phase, 0.991 space-variant (ceiling 0.997). With one
extended reference the lever (its own few degrees) is too short to see dp_m across the line of
sight (docs/evaluation.md).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl

from twinfocus.errors import TwinFocusError
from twinfocus.grid import ImageGrid


def lines_of_sight(centres_m: np.ndarray, points_m: np.ndarray) -> np.ndarray:
    """Unit vectors from each radar position to each point: float64 (M, ..., 3).

    centres_m : (M, 3) phase centres (channel mean), metres; points_m : (..., 3) metres.
    """
    c = np.asarray(centres_m, float)
    p = np.asarray(points_m, float)
    d = p[None] - c.reshape((c.shape[0],) + (1,) * (p.ndim - 1) + (3,))
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def fit_position_errors(phases_rad: np.ndarray, weights: np.ndarray, points_m: np.ndarray, centres_m: np.ndarray,
                        wavelength_m: float, prior_sigma_m: float = 0.5e-3, noise_rad: float = 0.3,
                        step_sigma_m: float | None = None, absolute: bool = True, absolute_noise_rad: float = 1.0) -> np.ndarray:
    """Per-position position-error estimate dp_m (the part the references' lines of sight see).

    phases_rad : float (R, M) per-position phase at each reference (R >= 2), radians; reference 0
        is the one the scalar phase is taken from. weights : float (R, M) >= 0, e.g. |<B_m, T_r>|^2
        (how well each position sees each reference); normalised inside.
    points_m : (R, 3) reference centres; centres_m : (M, 3) radar phase centres (channel mean).
    prior_sigma_m : expected size of dp per axis; noise_rad : expected phase noise of one
        reference's per-position phase; step_sigma_m : expected change of dp between consecutive
        positions (None: positions independent).

    absolute : also fit each reference's own phase (``absolute_noise_rad``): pins dp along the
        lines of sight, which the differences cannot see.

    Returns float64 (M, 3) metres, in the phases' sense: phi_r,m - phi_0,m ~ k (u_r - u_0) . dp_m
    (a correction, so minus the position error when the phases are corrections).
    """
    ph = np.asarray(phases_rad, float)
    w = np.asarray(weights, float)
    pts = np.asarray(points_m, float)
    c = np.asarray(centres_m, float)
    if ph.ndim != 2 or ph.shape[0] < 2:
        raise TwinFocusError(f"space-variant correction needs phases at >= 2 references, (R, M); got {ph.shape}")
    r, m = ph.shape
    if w.shape != ph.shape or pts.shape != (r, 3) or c.shape != (m, 3):
        raise TwinFocusError(f"weights {w.shape}, points {pts.shape}, centres {c.shape} do not fit phases {ph.shape}")
    if not (np.isfinite(ph).all() and np.isfinite(w).all() and (w >= 0).all()):
        raise TwinFocusError("phases and weights must be finite, weights >= 0")
    if not (prior_sigma_m > 0 and noise_rad > 0) or (step_sigma_m is not None and not step_sigma_m > 0):
        raise TwinFocusError("prior_sigma_m, noise_rad and step_sigma_m must be positive")
    k = 4.0 * np.pi / float(wavelength_m)
    u = lines_of_sight(c, pts)  # (M, R, 3)
    du = k * (u[:, 1:] - u[:, :1])  # (M, R-1, 3)
    delta = np.angle(np.exp(1j * (ph[1:] - ph[:1]))).T  # (M, R-1)
    ww = (w[1:] * w[:1] / np.maximum(w[1:] + w[:1], 1e-300)).T  # a difference is as good as its worse side
    ww = ww / max(ww.mean(), 1e-300)
    # rows: sqrt(w) (du . d - delta) / noise; prior d / prior_sigma; smoothness (d_m - d_{m-1}) / step
    rows = np.repeat(np.arange(m * (r - 1)), 3)
    cols = (np.arange(m)[:, None, None] * 3 + np.arange(3)[None, None, :]).repeat(r - 1, axis=1).reshape(-1)
    sw = np.sqrt(ww)[..., None] / noise_rad
    a = sp.csr_matrix(((du * sw).reshape(-1), (rows, cols)), shape=(m * (r - 1), 3 * m))
    rhs = (delta * sw[..., 0]).reshape(-1)
    blocks = [a, sp.eye(3 * m, format="csr") / prior_sigma_m]
    rhs_all = [rhs, np.zeros(3 * m)]
    if absolute:
        # Each reference's own phase is k u_r . dp_m plus one constant per reference (its
        # template's phase origin; the error is zero-mean, so the constant is the circular
        # mean). It pins the along-sight part the differences cannot see, where it has not
        # wrapped: past pi it is 2 pi off, so it gets its own, looser noise.
        z = np.exp(1j * ph)
        own = np.angle(z * np.exp(-1j * np.angle(z.sum(axis=1)))[:, None]).T  # (M, R)
        uk = k * u  # (M, R, 3)
        sa = np.sqrt(w.T / max(w.mean(), 1e-300))[..., None] / absolute_noise_rad
        rows_a = np.repeat(np.arange(m * r), 3)
        cols_a = (np.arange(m)[:, None, None] * 3 + np.arange(3)[None, None, :]).repeat(r, axis=1).reshape(-1)
        blocks.append(sp.csr_matrix(((uk * sa).reshape(-1), (rows_a, cols_a)), shape=(m * r, 3 * m)))
        rhs_all.append((own * sa[..., 0]).reshape(-1))
    if step_sigma_m is not None and m > 1:
        diff = sp.kron(sp.diags([np.ones(m - 1), -np.ones(m - 1)], [0, 1], shape=(m - 1, m)), sp.eye(3)) / step_sigma_m
        blocks.append(diff.tocsr())
        rhs_all.append(np.zeros(3 * (m - 1)))
    big = sp.vstack(blocks).tocsr()
    normal = (big.T @ big).tocsc()
    return spl.spsolve(normal, big.T @ np.concatenate(rhs_all)).reshape(m, 3)


def pixel_phases(phase0_rad: np.ndarray, dp_m: np.ndarray, point0_m: np.ndarray, centres_m: np.ndarray, grid: ImageGrid,
                 wavelength_m: float) -> np.ndarray:
    """phi_m(p) = phi_0,m + k (u_{m,p} - u_{0,m}) . dp_m for every pixel of ``grid``: float32 (M, H, W).

    phase0_rad : (M,) the scalar phase at reference 0 (at ``point0_m``); dp_m : (M, 3) from
    :func:`fit_position_errors`; centres_m : (M, 3)."""
    k = 4.0 * np.pi / float(wavelength_m)
    c = np.asarray(centres_m, float)
    yy, xx = np.meshgrid(grid.y_m, grid.x_m, indexing="ij")
    pix = np.stack([xx, yy, np.full_like(xx, grid.z)], axis=-1)
    u0 = lines_of_sight(c, np.asarray(point0_m, float))  # (M, 3)
    out = np.empty((c.shape[0],) + grid.shape, np.float32)
    for i in range(0, c.shape[0], 64):  # (64, H, W, 3) at a time
        up = lines_of_sight(c[i:i + 64], pix)
        out[i:i + 64] = np.asarray(phase0_rad, float)[i:i + 64, None, None] + k * np.einsum(
            "mhwc,mc->mhw", up - u0[i:i + 64, None, None, :], np.asarray(dp_m, float)[i:i + 64])
    return out


def form_image_space_variant(basis: np.ndarray, phases_rad: np.ndarray) -> np.ndarray:
    """sum_m exp(j phi_m(p)) B_m(p): complex64 (H, W) from basis and phases, both (M, H, W)."""
    b = np.asarray(basis)
    ph = np.asarray(phases_rad)
    if ph.shape != b.shape:
        raise TwinFocusError(f"per-pixel phases {ph.shape} must match the basis {b.shape}")
    out = np.zeros(b.shape[1:], np.complex64)
    for i in range(0, b.shape[0], 64):
        out += (b[i:i + 64] * np.exp(1j * ph[i:i + 64]).astype(np.complex64)).sum(axis=0)
    return out
