"""Space-variant correction: a per-position 3-D position error instead of one scalar phase.

The scalar method applies the reference's phase phi_m to every pixel, which is right only where
the line of sight matches the reference's: a position error dp_m puts the phase
k u . dp_m (k = 4 pi / lambda, u the unit line of sight) on a pixel, so a target ``theta`` away
from the reference keeps k (u_tgt - u_ref) . dp_m (docs/architecture.md section 1, paper eq. 7).

With several references (or several parts of one extended reference) seen along different lines
of sight, their per-position phases phi_{r,m} (:func:`twinfocus.focus.template_match.correlation_phase`
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
(:func:`pixel_phases`, then :func:`twinfocus.imaging.basis.form_image_space_variant`).

Measured (docs/beyond.md): references at -20 / +20 degrees, 0.5 mm x/y/z jitter: the target's
SSIM 0.963 with the nearer reference's scalar phase, 0.991 space-variant (ceiling 0.997).

**One extended reference, a hand's drift** (:func:`fit_smooth_drift`): per-region phases of one
reference see too short a lever, and single positions' sub-images mix scatterers at one range
from far across the region, which halves the apparent lever. Fitting the reference's whole image
instead, with the per-pixel model phi_m + k (u_{m,p} - u_{m,c}) . dp_m and dp smooth over the
capture (a hand drifts; piecewise linear between knots), recovers the across-sight drift
(docs/handheld.md). A hand also tilts the array: with the sub-images of one half of the array's
channels (:func:`array_half`) the fit follows the halves' differential phase too
(:func:`tilted_basis`). Handheld scenes: 0.83 -> 0.95 (0.90-0.97 per draw, ceiling 0.97), the
paper's protocol unchanged.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl

from twinfocus.errors import TwinFocusError
from twinfocus.focus.band_delay import bright_pixels
from twinfocus.focus.reference_free import resolution_cell_m
from twinfocus.imaging.device import resolve_device
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.range_geometry import _COS_C, _SIN_C

try:  # numba is a hard dependency; the guard only keeps import errors readable
    from numba import njit, prange
except ImportError as exc:  # pragma: no cover
    raise ImportError("twinfocus.focus.space_variant needs numba (pip install numba)") from exc


def lines_of_sight(centres_m: np.ndarray, points_m: np.ndarray) -> np.ndarray:
    """Unit vectors from each radar position to each point: float64 (M, ..., 3).

    centres_m : (M, 3) phase centres (channel mean), metres; points_m : (..., 3) metres.
    """
    c = np.asarray(centres_m, float)
    p = np.asarray(points_m, float)
    d = p[None] - c.reshape((c.shape[0],) + (1,) * (p.ndim - 1) + (3,))
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def fit_position_errors(
    phases_rad: np.ndarray,
    weights: np.ndarray,
    points_m: np.ndarray,
    centres_m: np.ndarray,
    wavelength_m: float,
    prior_sigma_m: float = 0.5e-3,
    noise_rad: float = 0.3,
    step_sigma_m: float | None = None,
    absolute: bool = True,
    absolute_noise_rad: float = 1.0,
) -> np.ndarray:
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


def pixel_phases(
    phase0_rad: np.ndarray,
    dp_m: np.ndarray,
    point0_m: np.ndarray,
    centres_m: np.ndarray,
    grid: ImageGrid,
    wavelength_m: float,
) -> np.ndarray:
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
        up = lines_of_sight(c[i : i + 64], pix)
        out[i : i + 64] = np.asarray(phase0_rad, float)[i : i + 64, None, None] + k * np.einsum(
            "mhwc,mc->mhw", up - u0[i : i + 64, None, None, :], np.asarray(dp_m, float)[i : i + 64]
        )
    return out


def array_half(positions_m: np.ndarray) -> np.ndarray:
    """The channels on one side of the array's middle, along its long axis: bool (K,).

    positions_m : float (M, K, 3) phase centres. The axis is the principal direction of the
    channels' mean offsets from their position's centre (the array turns by fractions of a
    degree over a scan), so any array geometry splits the same way; the half is the one on the
    negative side of the axis, turned so that its largest component is positive (an array along
    x: the channels at negative x), whatever sign the decomposition returns.
    """
    p = np.asarray(positions_m, float)
    if p.ndim != 3 or p.shape[2] != 3:
        raise TwinFocusError(f"positions must be (M, K, 3), got {p.shape}")
    offsets = (p - p.mean(axis=1, keepdims=True)).mean(axis=0)  # (K, 3)
    _, _, vt = np.linalg.svd(offsets, full_matrices=False)
    axis = vt[0] * np.sign(vt[0][np.argmax(np.abs(vt[0]))])
    along = offsets @ axis
    half = along < 0.0
    if np.ptp(along) <= 1e-6 or half.all() or not half.any():
        raise TwinFocusError("the array's tilt needs channels spread along the array; these have no extent")
    return half


def tilted_basis(basis: np.ndarray, half_basis: np.ndarray, tilt_rad: np.ndarray) -> np.ndarray:
    """Sub-images with the array's halves phased apart: L_m exp(j psi_m) + (B_m - L_m) exp(-j psi_m).

    A tilt of the array about its cross axis moves its two ends along the line of sight in
    opposite senses; to first order the halves' sub-images turn by +-psi_m. basis : complex
    (M, H, W) all channels; half_basis : complex (M, H, W) the channels of :func:`array_half`;
    tilt_rad : float (M,) psi. Returns complex64 (M, H, W).
    """
    b = np.asarray(basis)
    half = np.asarray(half_basis)
    psi = np.asarray(tilt_rad, float)
    if half.shape != b.shape or psi.shape != b.shape[:1]:
        raise TwinFocusError(f"half basis {half.shape} and tilt {psi.shape} do not fit the basis {b.shape}")
    e, s2 = _tilt_factors(psi)
    return (b * e[:, None, None] + half * s2[:, None, None]).astype(np.complex64)


def _tilt_factors(tilt_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """exp(-j psi) and 2j sin(psi), complex64 (M,): E_m = B_m exp(-j psi_m) + 2j sin(psi_m) L_m
    (:func:`tilted_basis`)."""
    psi = np.asarray(tilt_rad, float)
    return np.exp(-1j * psi).astype(np.complex64), (2j * np.sin(psi)).astype(np.complex64)


def drift_image(
    basis: np.ndarray,
    phase0_rad: np.ndarray,
    dp_m: np.ndarray,
    point0_m: np.ndarray,
    centres_m: np.ndarray,
    grid: ImageGrid,
    wavelength_m: float,
    half_basis: np.ndarray | None = None,
    tilt_rad: np.ndarray | None = None,
) -> np.ndarray:
    """The image a drift (and tilt) correction forms: complex64 (H, W) on ``grid``,
    sum_m E_m(p) exp(j phi_m(p)) with phi_m(p) from :func:`pixel_phases` and E_m the
    :func:`tilted_basis` (``basis`` itself without ``half_basis``).

    The same sum as ``form_image_space_variant(tilted_basis(...), pixel_phases(...))``
    (:mod:`twinfocus.imaging.basis`) in one numba pass over the bases, the lines of sight computed per
    pixel as it goes: no (M, H, W) phases or tilted basis are formed (at 780 x 100 x 100 on 2
    cores 0.5 s and 0.19 GB of temporaries for the composition, ~0.05 s for this). basis,
    half_basis : complex (M, H, W); phase0_rad : (M,) radians at ``point0_m`` (3,); dp_m : (M, 3)
    metres; centres_m : (M, 3) metres; tilt_rad : (M,) radians, with ``half_basis``.
    """
    b = np.asarray(basis)
    m = b.shape[0]
    if b.ndim != 3 or b.shape[1:] != grid.shape:
        raise TwinFocusError(f"basis {b.shape} does not fit the grid {grid.shape}")
    c = np.ascontiguousarray(centres_m, np.float64)
    dp = np.ascontiguousarray(dp_m, np.float64)
    phase0 = np.ascontiguousarray(phase0_rad, np.float64)
    if c.shape != (m, 3) or dp.shape != (m, 3) or phase0.shape != (m,):
        raise TwinFocusError(f"centres {c.shape}, drift {dp.shape} and phases {phase0.shape} do not fit {m} positions")
    if (half_basis is None) != (tilt_rad is None):
        raise TwinFocusError("the tilt needs both the half-array basis and the tilt")
    k = 4.0 * np.pi / float(wavelength_m)
    u0 = lines_of_sight(c, np.asarray(point0_m, float))  # (M, 3)
    kd = k * dp
    offset = phase0 - np.einsum("mc,mc->m", kd, u0)  # phi_m(p) = offset_m + kd_m . u_{m,p}
    if half_basis is None or tilt_rad is None:
        e = np.ones(m, np.complex64)
        s2 = np.zeros(m, np.complex64)
        half = np.zeros((0, 0), np.complex64)
    else:
        half, psi = np.asarray(half_basis), np.asarray(tilt_rad, float)
        if half.shape != b.shape or psi.shape != (m,):
            raise TwinFocusError(f"half basis {half.shape} and tilt {psi.shape} do not fit {b.shape}")
        e, s2 = _tilt_factors(psi)
        half = np.ascontiguousarray(half.reshape(m, -1), np.complex64)
    image = np.empty(b.shape[1] * b.shape[2], np.complex64)
    _drift_sum(np.ascontiguousarray(b.reshape(m, -1), np.complex64), half, e, s2, c, kd, offset,
               grid.points(), _ROTATE_BLOCK, image)  # fmt: skip
    return image.reshape(grid.shape)


@njit(parallel=True, fastmath=True, cache=True)
def _drift_sum(b, half, e, s2, c, kd, offset, points, block, image):
    """:func:`drift_image`'s sum, parallel over pixel blocks (no two threads add to one pixel):
    b complex64 (M, P), half (M, P) or (0, 0) (no tilt), e / s2 complex64 (M,), c float64 (M, 3),
    kd float64 (M, 3) = k dp, offset float64 (M,), points float64 (P, 3); writes image (P,)."""
    n_pos, n_pix = b.shape
    tilted = half.shape[0] > 0
    n_blocks = (n_pix + block - 1) // block
    for blk in prange(n_blocks):
        lo = blk * block
        hi = min(lo + block, n_pix)
        acc = np.zeros(hi - lo, np.complex128)
        for m in range(n_pos):
            cx, cy, cz = c[m, 0], c[m, 1], c[m, 2]
            kx, ky, kz = kd[m, 0], kd[m, 1], kd[m, 2]
            for q in range(lo, hi):
                dx, dy, dz = points[q, 0] - cx, points[q, 1] - cy, points[q, 2] - cz
                phi = offset[m] + (kx * dx + ky * dy + kz * dz) / np.sqrt(dx * dx + dy * dy + dz * dz)
                v = b[m, q] * e[m] + half[m, q] * s2[m] if tilted else b[m, q]
                acc[q - lo] += v * complex(np.cos(phi), np.sin(phi))
        for q in range(lo, hi):
            image[q] = acc[q - lo]


def knot_basis(n_positions: int, spacing: int) -> np.ndarray:
    """Piecewise-linear interpolation from knots every ``spacing`` positions: float64 (M, n_knots),
    rows sum to 1 (a smooth curve over the capture order from its values at the knots)."""
    if n_positions < 1 or spacing < 1:
        raise TwinFocusError(f"knot basis needs >= 1 position and a spacing >= 1, got {n_positions}, {spacing}")
    knots = np.arange(0.0, n_positions - 1 + spacing, spacing)
    t = np.arange(n_positions, dtype=np.float64)
    b = np.maximum(0.0, 1.0 - np.abs(t[:, None] - knots[None, :]) / spacing)
    return b / b.sum(axis=1, keepdims=True)


#: :func:`fit_smooth_drift`'s per-position stage stops once its last ``REFINE_WINDOW`` steps gained
#: less than this share of all it gained (benchmarks/results/idle/field_speed.json)
REFINE_STOP = 0.01
REFINE_WINDOW = 10

#: the share of the template's energy whose pixels the knots' stage of :func:`fit_smooth_drift`
#: runs on (benchmarks/results/field_speed.json: the target's SSIM and the drift's error as good as
#: the fit on every pixel in both stages, draw for draw, the fit 2-6x faster with the gradients
#: written out)
KNOT_ENERGY_FRACTION = 0.9

#: :func:`fit_smooth_drift` correlates on rows up to this share of the resolution cell across y
#: apart (the share ``--model fast`` forms its reference at, twinfocus.focus.ladder.FAST_REFERENCE_CELL_SHARE):
#: every other row on the hand-drift scene (100 x 100 over 4.4 mm cells, rows 1.6 mm apart), half
#: the fit's work, its target SSIM within 0.001 of every row's
#: (benchmarks/results/drift_fit_speed.json)
ROW_CELL_SHARE = 0.8


def _row_stride(centres_m: np.ndarray, grid: ImageGrid, wavelength_m: float, share: float) -> int:
    """Rows of ``grid`` per row the drift fit correlates on: the largest stride that keeps them
    within ``share`` of the resolution cell across y (:func:`twinfocus.focus.reference_free.resolution_cell_m`
    of the phase centres (M, 3), metres) apart; 1 for ``share`` <= 0 or a grid of one row."""
    if share <= 0 or grid.height < 2:
        return 1

    cell_y, _ = resolution_cell_m(np.asarray(centres_m, float)[:, None, :], grid, wavelength_m)
    return max(1, int(share * cell_y / ((grid.y1 - grid.y0) / (grid.height - 1))))


@dataclass(frozen=True)
class DriftFitSettings:
    """How :func:`fit_smooth_drift` climbs: its knots, stages, steps and penalty.

    knot_spacing : positions between knots (a hand's drift stays correlated over ~20 positions of
    a 10 Hz sweep, and wanders within that: knots every 10 follow it better than every 20).
    iterations, step_m : Adam's iterations and step on the knots, metres. phase_step_rad : Adam's
    step on phi, radians (0: phi fixed). refine_iterations : the per-position stage's iterations
    (same steps; 0: the knots' curve as it is). refine_stop : the per-position stage ends early
    once its last ``REFINE_WINDOW`` steps gained less than this share of all it gained (0: every
    step). smoothness_per_mm2 : its penalty weight, per mm^2 of squared step between neighbours
    (against a correlation of at most 1). tilt_step_rad : Adam's step on the tilt's knots, radians.
    knot_energy_fraction : the knots' stage runs on the template's brightest pixels that hold this
    share of its energy (1: every pixel). row_cell_share : the fit's
    correlation on every k-th row of the grid, k the largest stride that keeps its rows within this
    share of the scan's resolution cell across y apart (:func:`_row_stride`; 0: every row).

    phi moves in steps ten times smaller than it may: the closed-form scalar phase is already
    near the best one phase per position, and 780 phases moving as fast as the drift fit the
    reference's noise and pull the drift off (handheld draws 3 / 4, docs/handheld.md: 0.893 /
    0.899 with phi steps of 0.02 rad and knots every 20 positions; 0.912 / 0.928 with phi fixed
    and knots every 10; 0.914 / 0.932 with steps of 0.002 rad). The per-position stage stops
    early: on the hand-drift draws 3, 5, 8, 11, 13 of benchmarks/bench_field_speed.py after 73-90
    steps, target SSIM 0.9429 against 0.9431 with all 100.
    """

    knot_spacing: int = 10
    iterations: int = 100
    step_m: float = 2e-5
    phase_step_rad: float = 0.002
    refine_iterations: int = 100
    refine_stop: float = REFINE_STOP
    smoothness_per_mm2: float = 1e-4
    tilt_step_rad: float = 0.01
    knot_energy_fraction: float = KNOT_ENERGY_FRACTION
    row_cell_share: float = ROW_CELL_SHARE

    def __post_init__(self) -> None:
        if not 0.0 < float(self.knot_energy_fraction) <= 1.0:
            raise TwinFocusError(f"knot_energy_fraction must be in (0, 1], got {self.knot_energy_fraction!r}")
        if int(self.knot_spacing) < 1 or min(self.iterations, self.refine_iterations) < 0:
            raise TwinFocusError("knot_spacing must be >= 1 and the iterations >= 0")


@dataclass(frozen=True)
class DriftStart:
    """Where a warm-started :func:`fit_smooth_drift` begins: an earlier fit's end on the first
    ``rows`` positions of the same scan (the solver node fits the drift as a sweep's positions
    arrive, then refines on the whole scan from there). Made by the fit (its info's
    ``end_state``), not by hand.

    phase_offset_rad : float64 (rows,) the fitted phase less that fit's ``phase0_rad`` (the scalar
    estimate beneath moves as the scan grows; the fit's own offset from it is what carries over);
    knots_m : float64 (n_knots, 2) the knots' values, metres; residual_m : float64 (rows, 2) the
    per-position stage's drift less the knots' curve, metres; tilt_knots_rad : float64 (n_knots,)
    the tilt's knots, radians (None: no tilt fitted); knot_spacing : positions between knots
    (a start only fits a fit with the same knots)."""

    phase_offset_rad: np.ndarray
    knots_m: np.ndarray
    residual_m: np.ndarray
    tilt_knots_rad: np.ndarray | None
    knot_spacing: int

    @property
    def rows(self) -> int:
        return int(self.phase_offset_rad.shape[0])


def fit_smooth_drift(
    basis: np.ndarray,
    template: np.ndarray,
    phase0_rad: np.ndarray,
    centres_m: np.ndarray,
    grid: ImageGrid,
    wavelength_m: float,
    settings: DriftFitSettings | None = None,
    half_basis: np.ndarray | None = None,
    pixels: np.ndarray | None = None,
    device: str | None = "cpu",
    progress: Callable[[int, int, float], None] | None = None,
    start: DriftStart | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Smooth across-sight drift (and optionally the per-position phase) from one extended
    reference's image.

    Maximises the normalised complex correlation of the reference image with its template,

        I(p) = sum_m B_m(p) exp(j (phi_m + k (u_{m,p} - u_{m,c}) . dp_m)),  dp = S c,

    over the knot values c of dp's x and y (S: :func:`knot_basis`; along z the line of sight
    barely turns over a region, so phi holds it) with Adam from dp = 0, and phi
    (one per position) from ``phase0_rad`` in small steps. u_{m,p}: unit line of sight from
    position m to pixel p; u_{m,c}: to the region's centre, where phi is the phase. Then dp is
    refined position by position, from the knots' curve, with a penalty ``smoothness_per_mm2`` *
    sum_m |dp_{m+1} - dp_m|^2 (mm^2) on the correlation: the knots' straight segments miss a
    hand's wander within 10 positions, and the penalty keeps each position's noise out (handheld
    draws 1-10, docs/handheld.md: 1e-4 gains 0.006 on average over the knots alone; 3e-4 and more
    pull the drift in, 3e-5 lets noise in). ``settings``: :class:`DriftFitSettings`.

    basis : complex (M, H, W) the reference's sub-image basis on ``grid``; template : complex
    (H, W), registered to the scan (its phase is what pins the fit); phase0_rad : float (M,) the
    scalar estimate (e.g. :func:`twinfocus.focus.template_match.correlation_phase`); centres_m : float
    (M, 3) phase centres (channel mean), metres, in capture order (smoothness runs along it).

    half_basis : complex (M, H, W) the reference's sub-images from the channels of
    :func:`array_half` alone: the fit then also follows the array's tilt, a differential phase
    psi_m between its halves (:func:`tilted_basis`) on the same knots (a hand turns the array as
    it drifts; handheld draws 3 / 5: 0.922 / 0.917 without, 0.948 / 0.947 with).

    pixels : bool (H, W), the fit on these pixels alone (a held-out fit: the same as zeroing the
    others in the bases and the template; None: every pixel).
    device : cpu (numpy and numba, :class:`_CpuDriftMatch`: no torch import) or a torch device
    (cuda, cuda:N; :class:`_TorchDriftMatch`); None: :func:`twinfocus.imaging.device.resolve_device`'s
    choice. On a CPU the BLAS products run on one thread, numba's pass on its own count or, when
    the load average is at or above the cores, on one too (:func:`_threads_for_the_load`).

    start : warm start (:class:`DriftStart`, an earlier fit's ``end_state`` on the scan's first
    rows): the knots, the phase's offset from ``phase0_rad``, the tilt and the per-position
    stage's residual from there, the positions after it from the last knot's values (None: dp =
    0, phi = ``phase0_rad``, as always without one). ``settings`` then says how many steps each
    stage takes from it.

    Returns (phase float64 (M,) radians at the region's centre (``phase0_rad`` when phi is
    fixed), dp float64 (M, 3) metres in the correction's sense (z is 0), tilt float64 (M,)
    radians (zeros without ``half_basis``), info: ``match_before`` / ``match_after`` (the
    correlation on every pixel of ``pixels``), the settings, ``knot_pixels``, ``device``,
    ``threads`` (numba's on a CPU, None elsewhere), ``row_stride``, ``cost_evaluations``, ``time_s``,
    ``warm_start_positions``, ``match_cold_start`` (where a fit without ``start`` begins), ``end_state``:
    the :class:`DriftStart` a later fit on more of the scan may start from). Memory on the CPU: the bases as given, 12 bytes per position and fitted pixel of
    working arrays (20 with ``half_basis``) and copies of the bases on the fitted pixels.
    """
    t0 = time.perf_counter()
    cfg = settings or DriftFitSettings()
    b, tpl, c, fitted = _check_drift_inputs(basis, template, centres_m, grid, half_basis, pixels)
    fitted, stride = _on_rows(fitted, tpl, _row_stride(c, grid, wavelength_m, cfg.row_cell_share))
    m = b.shape[0]
    whole = _drift_match(b, half_basis, tpl, c, grid, wavelength_m, device)
    match = coarse = whole if fitted.all() else whole.on(fitted.ravel())
    if cfg.knot_energy_fraction < 1.0:
        coarse = whole.on((bright_pixels(np.where(fitted, tpl, 0), cfg.knot_energy_fraction) & fitted).ravel())
    fit = _DriftDescent(cfg, knot_basis(m, int(cfg.knot_spacing)), np.asarray(phase0_rad, np.float64),
                        half_basis is not None, progress, start)  # fmt: skip
    knot_steps, refine_steps = int(cfg.iterations), int(cfg.refine_iterations)
    with _threads_for_the_load(whole.device) as threads:
        before = match.value_and_gradients(fit.phase, fit.s @ fit.coef, fit.tilt())[0]
        cold = before if start is None else fit.cold_start_value(match, np.asarray(phase0_rad, np.float64))
        fit.total = knot_steps + refine_steps
        fit.descend(fit.coef, True, knot_steps, 0.0, coarse)
        # Per-position refinement: the knots' straight segments cannot follow a drift that wanders
        # within 10 positions; a penalty on the step between neighbours keeps the noise out.
        drift = fit.s @ fit.coef
        if fit.residual is not None:  # a warm start: the per-position stage from where it ended
            drift += fit.residual
        refined = fit.descend(drift, False, refine_steps, float(cfg.smoothness_per_mm2), match, float(cfg.refine_stop))
        after = match.value_and_gradients(fit.phase, drift, fit.tilt())[0] if fit.total else before
    dp = np.zeros((m, 3))
    dp[:, :2] = drift
    record = {
        "knot_pixels": int(coarse.n_pixels),
        "row_stride": stride,
        "device": str(whole.device),
        "threads": threads,
    }
    info = _fit_info(cfg, fit, (before, after, cold), refined, record, start)
    info["end_state"] = fit.end_state(drift, np.asarray(phase0_rad, np.float64))
    info["time_s"] = time.perf_counter() - t0
    tilt = fit.tilt()
    return fit.phase.copy(), dp, np.zeros(m) if tilt is None else tilt.astype(np.float64), info


def _fit_info(
    cfg: DriftFitSettings, fit, matches: tuple[float, float, float], refined: int, record: dict, start
) -> dict:
    """:func:`fit_smooth_drift`'s info (its docstring's keys but ``end_state`` and ``time_s``):
    ``matches`` the correlation before, after and where a cold fit begins, ``refined`` the
    per-position stage's steps, ``record`` the knot pixels, row stride, device and threads."""
    return {
        "match_before": matches[0],
        "match_after": matches[1],
        "match_cold_start": matches[2],
        "knot_spacing_positions": int(cfg.knot_spacing),
        "iterations": int(cfg.iterations),
        "refine_iterations": refined,
        "smoothness_per_mm2": float(cfg.smoothness_per_mm2),
        "knot_pixels": record["knot_pixels"],
        "row_stride": record["row_stride"],
        "phase_fitted": cfg.phase_step_rad > 0,
        "tilt_fitted": fit.tilt_coef is not None,
        "cost_evaluations": len(fit.matches) + 1 + (1 if fit.total else 0) + (start is not None),
        "device": record["device"],
        "threads": record["threads"],
        "warm_start_positions": 0 if start is None else start.rows,
    }


def _on_rows(fitted: np.ndarray, template: np.ndarray, stride: int) -> tuple[np.ndarray, int]:
    """The fitted pixels (bool (H, W)) on every ``stride``-th row, and the stride taken: 1 (all
    of ``fitted``) when those rows hold less than half their share of the template's energy on
    ``fitted`` (a mask in step with the rows, e.g. a held-out half of one-row blocks)."""
    if stride <= 1:
        return fitted, 1
    rows = fitted & (np.arange(fitted.shape[0]) % stride == 0)[:, None]
    energy = np.abs(template) ** 2
    if energy[rows].sum() >= 0.5 * energy[fitted].sum() / stride > 0:
        return rows, stride
    return fitted, 1


def _check_drift_inputs(basis, template, centres_m, grid, half_basis, pixels):
    """:func:`fit_smooth_drift`'s inputs checked: (basis, template, centres float64 (M, 3), the
    fitted pixels' bool (H, W) mask)."""
    b = np.asarray(basis)
    tpl = np.asarray(template)
    m = b.shape[0]
    if b.ndim != 3 or tpl.shape != b.shape[1:] or b.shape[1:] != grid.shape:
        raise TwinFocusError(f"basis {b.shape}, template {tpl.shape} and grid {grid.shape} do not fit")
    if not np.iscomplexobj(tpl):
        raise TwinFocusError("the smooth-drift fit needs a template with phase (a physical twin's image)")
    if half_basis is not None and np.shape(half_basis) != b.shape:
        raise TwinFocusError(f"half basis {np.shape(half_basis)} does not fit the basis {b.shape}")
    c = np.asarray(centres_m, np.float64)
    if c.shape != (m, 3):
        raise TwinFocusError(f"centres must be (M, 3) = ({m}, 3), got {c.shape}")
    fitted = np.ones(grid.shape, bool) if pixels is None else np.asarray(pixels, bool)
    if fitted.shape != grid.shape or not fitted.any():
        raise TwinFocusError(f"pixels must be a {grid.shape} mask with a pixel in it, got {fitted.shape}")
    return b, tpl, c, fitted


class _DriftDescent:
    """The state of one :func:`fit_smooth_drift`: the knot basis ``s`` float64 (M, n_knots), the
    knots' values ``coef`` (n_knots, 2) metres, the phase (M,) radians, the tilt's knots (n_knots,)
    radians (None without the tilt) and the correlation before each step (``matches``)."""

    def __init__(self, cfg, s, phase0, tilted, progress, start: DriftStart | None = None):
        self.cfg, self.s, self.progress = cfg, s, progress
        self.phase = phase0.copy()
        self.coef = np.zeros((s.shape[1], 2))
        self.tilt_coef = np.zeros(s.shape[1]) if tilted else None
        self.residual: np.ndarray | None = None  # (M, 2) the per-position stage's start off the knots' curve
        self.matches: list[float] = []
        self.total = 0
        if start is not None:
            self._warm(start)

    def _warm(self, start: DriftStart) -> None:
        """From ``start``'s state on the scan's first rows; the knots after its last from that
        knot's values (a hand's drift is correlated over more than a knot's spacing)."""
        m, n_knots = self.s.shape
        rows = start.rows
        if start.knot_spacing != int(self.cfg.knot_spacing) or rows > m or start.knots_m.shape[1:] != (2,):
            raise TwinFocusError(
                f"a warm start of {rows} positions with knots every {start.knot_spacing} does not fit a fit of "
                f"{m} positions with knots every {self.cfg.knot_spacing}"
            )
        k = min(start.knots_m.shape[0], n_knots)
        self.coef[:k] = start.knots_m[:k]
        self.coef[k:] = start.knots_m[k - 1]
        self.phase[:rows] += start.phase_offset_rad
        if self.tilt_coef is not None and start.tilt_knots_rad is not None:
            self.tilt_coef[:k] = start.tilt_knots_rad[:k]
            self.tilt_coef[k:] = start.tilt_knots_rad[k - 1]
        self.residual = np.zeros((m, 2))
        self.residual[:rows] = start.residual_m

    def end_state(self, drift: np.ndarray, phase0: np.ndarray) -> DriftStart:
        """The fit's end as a :class:`DriftStart` (drift: float64 (M, 2), the per-position stage's)."""
        return DriftStart(
            phase_offset_rad=self.phase - phase0,
            knots_m=self.coef.copy(),
            residual_m=drift - self.s @ self.coef,
            tilt_knots_rad=None if self.tilt_coef is None else self.tilt_coef.copy(),
            knot_spacing=int(self.cfg.knot_spacing),
        )

    def tilt(self) -> np.ndarray | None:
        return None if self.tilt_coef is None else self.s @ self.tilt_coef

    def cold_start_value(self, match, phase0: np.ndarray) -> float:
        """The correlation on ``match``'s pixels where a fit without a start begins (dp = 0, phi =
        ``phase0``, no tilt): a warm fit that ends below it began from a poor start."""
        m = self.s.shape[0]
        return match.value_and_gradients(phase0, np.zeros((m, 2)), None if self.tilt_coef is None else np.zeros(m))[0]

    def descend(self, parameter, knots: bool, steps: int, smoothness: float, objective, stop: float = 0.0) -> int:
        """Adam on ``parameter`` (float64, in place; metres: the knots' values when ``knots``, else
        each position's drift) and phi and the tilt's knots, each at its own step, maximising the
        correlation less ``smoothness`` * sum |dp_{m+1} - dp_m|^2 (mm^2) on ``objective``'s pixels.
        The gradients are the correlation's own (``value_and_gradients``). ``stop`` > 0: done once
        the last ``REFINE_WINDOW`` steps gained less than ``stop`` of all this stage's gain (after
        at least two windows). Returns the steps taken."""
        cfg, s = self.cfg, self.s
        params, rates = [parameter], [cfg.step_m]
        if cfg.phase_step_rad > 0:
            params.append(self.phase)
            rates.append(cfg.phase_step_rad)
        if self.tilt_coef is not None:
            params.append(self.tilt_coef)
            rates.append(cfg.tilt_step_rad)
        opt = _Adam(params, rates)
        first = len(self.matches)
        for n in range(int(steps)):
            if stop > 0 and n >= 2 * REFINE_WINDOW:
                gained = self.matches[-1] - self.matches[first]
                recent = self.matches[-1] - self.matches[-1 - REFINE_WINDOW]
                if gained > 0 and recent < stop * gained:
                    return n
            dp = s @ parameter if knots else parameter
            corr, g_phase, g_dp, g_tilt = objective.value_and_gradients(self.phase, dp, self.tilt())
            self.matches.append(corr)
            grad = -g_dp
            if smoothness:
                step = (dp[1:] - dp[:-1]) * (2e6 * smoothness)  # d/d dp of smoothness * |1e3 step|^2
                grad[1:] += step
                grad[:-1] -= step
            grads = [s.T @ grad if knots else grad]
            if cfg.phase_step_rad > 0:
                grads.append(-g_phase)
            if self.tilt_coef is not None:
                grads.append(-(s.T @ g_tilt))
            opt.step(grads)
            if self.progress is not None:
                self.progress(len(self.matches), self.total, -self.matches[-1])
        return int(steps)


class _Adam:
    """Adam (betas 0.9 / 0.999, eps 1e-8: torch.optim.Adam's update) on float64 numpy arrays, each
    with its own step, updated in place: no torch, whose import and optimiser set-up (1.5 s and
    1.0-1.3 s on the 2-core machine) cost more than a whole fit."""

    def __init__(self, params: list[np.ndarray], rates: list[float]) -> None:
        self.params, self.rates = params, [float(r) for r in rates]
        self.avg = [np.zeros_like(p) for p in params]
        self.avg_sq = [np.zeros_like(p) for p in params]
        self.n = 0

    def step(self, grads: list[np.ndarray]) -> None:
        self.n += 1
        c1, c2 = 1.0 - 0.9**self.n, np.sqrt(1.0 - 0.999**self.n)
        for p, g, avg, avg_sq, lr in zip(self.params, grads, self.avg, self.avg_sq, self.rates, strict=True):
            avg *= 0.9
            avg += 0.1 * g
            avg_sq *= 0.999
            avg_sq += 0.001 * g * g
            p -= (lr / c1) * avg / (np.sqrt(avg_sq) / c2 + 1e-8)


@contextlib.contextmanager
def _threads_for_the_load(device: str) -> Iterator[int | None]:
    """The fit's threads on a CPU (restored after): BLAS's products on one, numba's pass on its own
    count, or on one too when the load average is at or above the cores; yields numba's count
    (None on another device).

    Each step is a numba parallel region then small BLAS products: with both pools at two threads,
    each pool's idle threads spin while the other's work (780 x 100 x 100 on 2 cores at load 5:
    22-35 s wall against 9-10 s on one thread), and on a busy machine each region waits for
    whichever thread was descheduled (load 10-12: 25-36 s against 7-11 s)."""
    if device != "cpu":
        yield None
        return
    import numba
    from threadpoolctl import threadpool_limits

    cores = os.cpu_count() or 1
    busy = hasattr(os, "getloadavg") and os.getloadavg()[0] >= cores
    before = numba.get_num_threads()
    if busy:
        numba.set_num_threads(1)
    try:
        with threadpool_limits(1, user_api="blas"):
            yield numba.get_num_threads()
    finally:
        numba.set_num_threads(before)


#: degree of the polynomial in the pixel's place that stands for each position's line-of-sight
#: term a_m(p) (:class:`_DriftMatch`): 4 keeps it within 3e-5 rad of the exact phase at 2 mm of
#: drift over a 100 x 100 region at 0.6 m (degree 3: 3e-4)
LINE_OF_SIGHT_DEGREE = 2
#: pixels per side of the lattice that polynomial is fitted on
LINE_OF_SIGHT_SAMPLES = 16


def _line_of_sight_polynomial(centres_m, grid: ImageGrid, wavelength_m: float):
    """a_m(p) = k (u_{m,p} - u_{m,c}) as U_m . q(p): (q float64 (P, n) orthonormal over the pixels,
    U float64 (2 M, n): x rows, then y rows), fitted on a lattice of ``LINE_OF_SIGHT_SAMPLES``^2
    pixels (it is smooth, and the exact lines of sight of every position to every pixel were most
    of the set-up's time; monomials = q r, so q's coefficients are r times the monomials')."""
    pts = grid.points()
    x = (pts[:, 0] - grid.centre_m[0]) / max(grid.x1 - grid.x0, 1e-12) * 2.0
    y = (pts[:, 1] - grid.centre_m[1]) / max(grid.y1 - grid.y0, 1e-12) * 2.0
    deg = LINE_OF_SIGHT_DEGREE
    monomials = np.stack([x**i * y**j for i in range(deg + 1) for j in range(deg + 1 - i)], axis=1)
    q, r = np.linalg.qr(monomials)
    h, w = grid.shape
    rows = np.unique(np.linspace(0, h - 1, min(h, LINE_OF_SIGHT_SAMPLES)).round().astype(int))
    cols = np.unique(np.linspace(0, w - 1, min(w, LINE_OF_SIGHT_SAMPLES)).round().astype(int))
    sample = (rows[:, None] * w + cols[None, :]).ravel()
    k = 4.0 * np.pi / float(wavelength_m)
    d = k * (lines_of_sight(centres_m, pts[sample]) - lines_of_sight(centres_m, grid.centre_m)[:, None, :])
    fit = np.linalg.lstsq(monomials[sample], np.concatenate([d[..., 0], d[..., 1]]).T, rcond=None)[0]
    return q, (r @ fit).T


def _drift_match(basis, half_basis, template, centres_m, grid, wavelength_m, device):
    """The correlation of :func:`fit_smooth_drift` on ``device``: :class:`_CpuDriftMatch` on the
    CPU, :class:`_TorchDriftMatch` elsewhere (one implementation per device)."""
    dev = resolve_device(device)
    q, u = _line_of_sight_polynomial(centres_m, grid, wavelength_m)
    cls = _CpuDriftMatch if dev == "cpu" else _TorchDriftMatch
    return cls(basis, half_basis, template, q, u, dev)


class _DriftMatch:
    """The correlation of :func:`fit_smooth_drift`, with its gradients.

    corr = Re<I, T> / (|I| |T|), I(p) = sum_m C_m(p), C_m(p) = E_m(p) exp(j theta_m(p)),
    theta_m(p) = phi_m + a_m(p) . dp_m, E_m = B_m exp(-j psi_m) + 2j sin(psi_m) L_m (the tilted
    basis) or B_m. A change dC of the contributions changes corr by Re sum_p dC(p) conj(W(p)),
    W = T / (|I| |T|) - corr I / |I|^2, so d corr / d theta_m(p) = -Im(C_m(p) conj W(p)).

    a_m(p) = k (u_{m,p} - u_{m,c}) turns slowly over the region: each position's is a polynomial
    of degree ``LINE_OF_SIGHT_DEGREE`` in the pixel's place, a_m(p) = U_m . q(p)
    (:func:`_line_of_sight_polynomial`). Then theta is one matrix product, and the gradients' sums
    over the pixels are products of the contributions with the few columns conj(W) [1, q]: no
    (M, P) array beyond theta, C and L exp(j theta) is formed, and no autograd graph is kept.
    Subclasses hold the arrays on their device and form C: :class:`_CpuDriftMatch` (numpy, numba),
    :class:`_TorchDriftMatch`. The bases are used as they are (on the CPU no copy of a complex64
    basis): the correlation is scale-free, and its image is taken to the basis' unit peak before
    any sum of squares, so a scan at 1e20 does not overflow float32 (nor flush at 1e-20).
    """

    device: str
    n_pixels: int

    def on(self, pixels: np.ndarray) -> _DriftMatch:
        """The same correlation on the pixels of a bool (P,) mask (the polynomial basis is the one
        fitted over every pixel)."""
        raise NotImplementedError

    def value_and_gradients(self, phase, dp, tilt):
        """(corr float, d corr / d phi (M,), d corr / d dp (M, 2), d corr / d psi (M,) or None)
        at phase (M,) radians, dp (M, 2) metres, tilt (M,) radians or None: float64 numpy arrays."""
        raise NotImplementedError


class _CpuDriftMatch(_DriftMatch):
    """:class:`_DriftMatch` in numpy (BLAS products) and one fused numba pass (:func:`_rotate`:
    exp(j theta), the tilted basis and the image's sum in one read of the bases)."""

    def __init__(self, basis, half_basis, template, q, u, device="cpu"):
        m = basis.shape[0]
        self.device = device
        self.ux, self.uy = np.ascontiguousarray(u[:m], np.float32), np.ascontiguousarray(u[m:], np.float32)
        self.q_t = np.ascontiguousarray(q.T, np.float32)  # (n, P)
        self.columns = np.ascontiguousarray(np.c_[np.ones(q.shape[0]), q], np.complex64)  # (P, 1 + n)
        self.unit = 1.0 / max(float(np.abs(basis).max()), 1e-30)
        self.b = np.ascontiguousarray(np.asarray(basis).reshape(m, -1), np.complex64)
        self.half = (
            None if half_basis is None else np.ascontiguousarray(np.asarray(half_basis).reshape(m, -1), np.complex64)
        )
        tpl = np.asarray(template).reshape(-1)
        self.t = (tpl / max(float(np.abs(tpl).max()), 1e-30)).astype(np.complex64)
        self._set_pixels()

    def _set_pixels(self) -> None:
        self.n_pixels = int(self.t.shape[0])
        self.t_norm = float(np.linalg.norm(self.t))
        shape = self.b.shape
        # kept across steps: a fresh 60 MB array each step costs its page faults
        self._theta = np.empty(shape, np.float32)
        self._c = np.empty(shape, np.complex64)
        self._h = np.empty(shape if self.half is not None else (0, 0), np.complex64)
        self._kc = _rotation_constants()

    def on(self, pixels: np.ndarray) -> _CpuDriftMatch:
        sub = object.__new__(_CpuDriftMatch)
        sub.__dict__.update(self.__dict__)
        idx = np.flatnonzero(pixels)
        sub.q_t = np.ascontiguousarray(self.q_t[:, idx])
        sub.columns = np.ascontiguousarray(self.columns[idx])
        sub.b = np.ascontiguousarray(self.b[:, idx])
        sub.half = None if self.half is None else np.ascontiguousarray(self.half[:, idx])
        sub.t = self.t[idx]
        sub._set_pixels()
        return sub

    def value_and_gradients(self, phase, dp, tilt):
        slopes = (self.ux * dp[:, :1].astype(np.float32) + self.uy * dp[:, 1:].astype(np.float32)).astype(np.float32)
        theta = self._theta
        np.matmul(slopes, self.q_t, out=theta)
        theta += phase.astype(np.float32)[:, None]
        e = s2 = None
        if tilt is not None:
            e, s2 = _tilt_factors(tilt)
        image32 = np.empty(self.n_pixels, np.complex64)
        _rotate(theta, self.b, self.half if e is not None else None, e, s2, self._kc,
                _rotate_block(self.n_pixels), self._c, self._h, image32)  # fmt: skip
        image = image32.astype(np.complex128) * self.unit
        i_norm = float(np.linalg.norm(image))
        corr = float(np.vdot(self.t, image).real) / max(i_norm * self.t_norm, 1e-300)
        w = self.t / max(i_norm * self.t_norm, 1e-300) - image * (corr / max(i_norm * i_norm, 1e-300))
        # conj W [1, q], W of the unscaled image
        x = self.columns * (w.conj() * self.unit).astype(np.complex64)[:, None]
        sums = self._c @ x  # (M, 1 + n)
        g = -sums.imag.astype(np.float64)  # sum_p d corr / d theta_m(p) [1, q(p)]
        g_dp = np.stack(((self.ux * g[:, 1:]).sum(1), (self.uy * g[:, 1:]).sum(1)), axis=1)
        g_tilt = None
        if e is not None:
            # d C_m / d psi_m = -j C_m + 2j exp(j psi) L exp(j theta)
            yh = self._h @ np.ascontiguousarray(x[:, 0])
            g_tilt = sums[:, 0].imag.astype(np.float64) - 2.0 * (np.conj(e) * yh).imag
        return corr, g[:, 0], g_dp, g_tilt


class _TorchDriftMatch(_DriftMatch):
    """:class:`_DriftMatch` with torch's element-wise products on a torch device (a GPU); numpy
    in, numpy out (the optimiser's few thousand numbers cross each step)."""

    def __init__(self, basis, half_basis, template, q, u, device):
        import torch

        self.torch = torch
        self.device = device
        m = basis.shape[0]

        def put(v, dtype):
            return torch.from_numpy(np.ascontiguousarray(v, dtype)).to(device)

        self.ux, self.uy = put(u[:m], np.float32), put(u[m:], np.float32)
        self.q_t = put(q.T, np.float32)  # (n, P)
        self.columns = put(np.c_[np.ones(q.shape[0]), q], np.float32)  # (P, 1 + n)
        self.unit = 1.0 / max(float(np.abs(basis).max()), 1e-30)
        self.b = put(np.asarray(basis).reshape(m, -1), np.complex64)
        self.half = None if half_basis is None else put(np.asarray(half_basis).reshape(m, -1), np.complex64)
        tpl = np.asarray(template).reshape(-1)
        self.t = put(tpl / max(float(np.abs(tpl).max()), 1e-30), np.complex64)
        self.t_norm = float(torch.linalg.vector_norm(self.t))
        self.n_pixels = int(self.t.shape[0])
        self.one = torch.ones((1, 1), dtype=torch.float32, device=device)  # |exp(j theta)|, broadcast

    def on(self, pixels: np.ndarray) -> _TorchDriftMatch:
        sub = object.__new__(_TorchDriftMatch)
        sub.__dict__.update(self.__dict__)
        idx = self.torch.from_numpy(np.flatnonzero(pixels)).to(self.device)
        sub.q_t = self.q_t[:, idx].contiguous()
        sub.columns = self.columns[idx].contiguous()
        sub.b = self.b[:, idx].contiguous()
        sub.half = None if self.half is None else self.half[:, idx].contiguous()
        sub.t = self.t[idx]
        sub.t_norm = float(self.torch.linalg.vector_norm(sub.t))
        sub.n_pixels = int(sub.t.shape[0])
        return sub

    def value_and_gradients(self, phase, dp, tilt):
        torch = self.torch

        def put(v):
            return torch.from_numpy(np.ascontiguousarray(v, np.float32)).to(self.device)

        ph, d = put(phase), put(dp)
        slopes = self.ux * d[:, :1] + self.uy * d[:, 1:]  # (M, n): theta_m(p) = phi_m + slopes_m . q(p)
        rot = torch.polar(self.one, torch.addmm(ph[:, None], slopes, self.q_t))
        if tilt is None:
            contributions = rot.mul_(self.b)
        else:
            psi = put(tilt)
            e = torch.polar(torch.ones_like(psi), -psi)
            s2 = torch.complex(torch.zeros_like(psi), 2.0 * torch.sin(psi))
            half_rotated = self.half * rot
            contributions = rot.mul_(self.b).mul_(e[:, None]).add_(half_rotated * s2[:, None])
        image = contributions.sum(0) * self.unit
        i_norm = float(torch.linalg.vector_norm(image))
        corr = float(torch.vdot(self.t, image).real) / max(i_norm * self.t_norm, 1e-300)
        w = self.t / max(i_norm * self.t_norm, 1e-300) - image * (corr / max(i_norm * i_norm, 1e-300))
        x = self.columns * (w.conj() * self.unit)[:, None]
        sums = contributions @ x
        g = -sums.imag
        g_dp = torch.stack(((self.ux * g[:, 1:]).sum(1), (self.uy * g[:, 1:]).sum(1)), dim=1)
        g_tilt = None
        if tilt is not None:
            yh = half_rotated @ x[:, 0].contiguous()
            g_tilt = (sums[:, 0].imag - 2.0 * (torch.conj(e) * yh).imag).cpu().numpy().astype(np.float64)
        g_np = g.cpu().numpy().astype(np.float64)
        return corr, g_np[:, 0], g_dp.cpu().numpy().astype(np.float64), g_tilt


def _rotation_constants() -> np.ndarray:
    """[1/(2 pi), 1/2, the sine's (7) and the cosine's (8) polynomial coefficients] as float32 for
    :func:`_rotate` (a Python float literal in jitted code is float64 and would promote the
    float32 arithmetic it touches)."""
    return np.array((1.0 / (2.0 * np.pi), 0.5, *_SIN_C, *_COS_C), dtype=np.float32)


#: most pixels per block of :func:`_rotate`: the block's image sums stay in cache over the positions
_ROTATE_BLOCK = 512


def _rotate_block(n_pixels: int) -> int:
    """Pixels per block of :func:`_rotate`: at most ``_ROTATE_BLOCK``, and at least 4 blocks per
    thread, so the threads' shares differ by a quarter of one at most (the knots' stage's 2000
    bright pixels in blocks of 512: 3 blocks on one core, 1 on the other)."""
    import numba

    return int(max(32, min(_ROTATE_BLOCK, -(-n_pixels // (4 * numba.get_num_threads())))))


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def _rotate(theta, b, half, e, s2, kc, block, c_out, h_out, image):
    """The drift fit's contributions on the CPU, in one pass over the basis.

    theta float32 (M, P) radians; b, half complex64 (M, P) (half None: no tilt); e, s2 complex64
    (M,) exp(-j psi), 2j sin psi; block: pixels per block (:func:`_rotate_block`). Writes c_out
    (M, P) = (e B + s2 L) exp(j theta) (B exp(j theta) without the tilt), h_out (M, P) =
    L exp(j theta) and image (P,) = sum_m c_out. Parallel over pixel blocks, so no two threads add
    to one pixel. exp(j theta) from :func:`twinfocus.imaging.range_geometry.cis_turns`' polynomials (error
    ~1e-7 in float32), in a loop of its own per position and block: pure float32 arithmetic,
    which LLVM vectorises (with the complex products in the same loop it did not: 3x slower).
    """
    inv_turn, halfc = kc[0], kc[1]
    s0, s1, s2c, s3, s4, s5, s6 = kc[2], kc[3], kc[4], kc[5], kc[6], kc[7], kc[8]
    c0, c1, c2, c3, c4, c5, c6, c7 = kc[9], kc[10], kc[11], kc[12], kc[13], kc[14], kc[15], kc[16]
    n_pos, n_pix = theta.shape
    n_blocks = (n_pix + block - 1) // block
    for blk in prange(n_blocks):
        lo = blk * block
        hi = min(lo + block, n_pix)
        n = hi - lo
        acc_re = np.zeros(n, np.float32)
        acc_im = np.zeros(n, np.float32)
        cos_buf = np.empty(n, np.float32)
        sin_buf = np.empty(n, np.float32)
        for m in range(n_pos):
            th = theta[m, lo:hi]
            for q in range(n):
                t = th[q] * inv_turn
                r = t - np.floor(t + halfc)
                r2 = r * r
                sin_buf[q] = r * (s0 + r2 * (s1 + r2 * (s2c + r2 * (s3 + r2 * (s4 + r2 * (s5 + r2 * s6))))))
                cos_buf[q] = c0 + r2 * (c1 + r2 * (c2 + r2 * (c3 + r2 * (c4 + r2 * (c5 + r2 * (c6 + r2 * c7))))))
            bb = b[m, lo:hi]
            cc = c_out[m, lo:hi]
            if half is None:
                for q in range(n):
                    v = bb[q] * complex(cos_buf[q], sin_buf[q])
                    cc[q] = v
                    acc_re[q] += v.real
                    acc_im[q] += v.imag
            else:
                em = e[m]
                sm = s2[m]
                hh = half[m, lo:hi]
                ho = h_out[m, lo:hi]
                for q in range(n):
                    rot = complex(cos_buf[q], sin_buf[q])
                    hr = hh[q] * rot
                    ho[q] = hr
                    v = em * bb[q] * rot + sm * hr
                    cc[q] = v
                    acc_re[q] += v.real
                    acc_im[q] += v.imag
        for q in range(n):
            image[lo + q] = complex(acc_re[q], acc_im[q])
