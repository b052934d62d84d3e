"""Range geometry shared by the back-projection and the simulator: the carrier phase in turns,
the range window an image or a scene spans, and the local frame that keeps float32 distances exact.

Both sides evaluate the carrier exp(+-j 4 pi fc R / c) = cis(2 pi R turns_per_m) per (phase
centre, pixel or scatterer) pair inside numba loops; :func:`cis_turns` does it with polynomials
that LLVM vectorises. Both sample range-dependent terms on a uniform range lattice
(:func:`range_lattice`) whose nodes are integer multiples of the step, so a result built chunk by
chunk (positions in batches) equals the one built at once.

Note: numba's on-disk cache (``cache=True``) of a kernel that inlines :func:`cis_turns` is keyed
on the kernel's own file, not this one: after editing this module, clear the ``__pycache__``
``*.nbi``/``*.nbc`` files of :mod:`twinfocus.imaging.backprojection.numba_backend` and :mod:`twinfocus.simulation.if_simulator`.
"""

from __future__ import annotations

import numpy as np

from twinfocus.radar.fmcw import C_M_PER_S, Chirp

try:  # numba is a hard dependency; the guard only keeps import errors readable
    from numba import njit
except ImportError as exc:  # pragma: no cover
    raise ImportError("twinfocus.imaging.range_geometry needs numba (pip install numba)") from exc

#: Range-profile oversampling the back-projection interpolates on (both back-ends).
DEFAULT_OVERSAMPLE = 16

# Minimax-fitted polynomials for sin(2 pi r), cos(2 pi r) on r in [-1/2, 1/2]: max error 1.2e-9 and
# 1.2e-10 in float64. Evaluating them inline lets LLVM vectorise the pixel loop (libm sin/cos do not).
_SIN_C = (6.28318527, -41.34169704, 81.6050236, -76.70153711, 42.01607168, -14.86830851, 3.19931986)
_COS_C = (1.0, -19.73920874, 64.93938907, -85.45665829, 60.24213103, -26.40466624, 7.80012531, -1.45310477)


@njit(inline="always", fastmath=True)
def cis_turns(t):
    """(cos 2 pi t, sin 2 pi t) for t >= -1/2 (turns), without libm calls.

    A numba function (call it from jitted code, or from Python for checks): float32 or float64
    scalar in, a pair of the same type out; error <= 1.2e-9 in float64.
    """
    r = t - int(t + 0.5)
    r2 = r * r
    s = r * (
        _SIN_C[0]
        + r2 * (_SIN_C[1] + r2 * (_SIN_C[2] + r2 * (_SIN_C[3] + r2 * (_SIN_C[4] + r2 * (_SIN_C[5] + r2 * _SIN_C[6])))))
    )
    c = _COS_C[0] + r2 * (
        _COS_C[1]
        + r2 * (_COS_C[2] + r2 * (_COS_C[3] + r2 * (_COS_C[4] + r2 * (_COS_C[5] + r2 * (_COS_C[6] + r2 * _COS_C[7])))))
    )
    return c, s


def turns_per_m(chirp: Chirp) -> float:
    """Carrier turns per metre of one-way range, 2 fc / c (the two-way path at the centre frequency)."""
    return 2.0 * chirp.fc_hz / C_M_PER_S


def range_window(positions_m: np.ndarray, points_m: np.ndarray, margin_m: float) -> tuple[float, float]:
    """Smallest and largest distance between any phase centre and the bounding box of ``points_m``.

    positions_m : (..., 3); points_m : (P, 3). Returns (r_min, r_max) in metres, widened by margin
    (r_min not below 0).
    """
    e = positions_m.reshape(-1, 3)
    lo, hi = points_m.min(axis=0), points_m.max(axis=0)
    nearest = np.clip(e, lo, hi)
    r_min = np.sqrt(((nearest - e) ** 2).sum(axis=1)).min()
    far = np.where(np.abs(e - lo) > np.abs(e - hi), lo, hi)
    r_max = np.sqrt(((far - e) ** 2).sum(axis=1)).max()
    return max(r_min - margin_m, 0.0), r_max + margin_m


def range_lattice(positions_m: np.ndarray, points_m: np.ndarray, step_m: float, margin_m: float) -> tuple[float, int]:
    """A uniform range grid r0 + step_m * arange(n) covering :func:`range_window` (with margin),
    whose nodes sit on the global lattice step_m * integer whatever the positions given.

    Returns (r0 in metres, n). The lattice makes a chunk's grid a sub-grid of the whole scan's,
    so results built batch by batch equal the whole-scan one; n includes one node of slack at
    the far end for linear interpolation.
    """
    r_min, r_max = range_window(positions_m, points_m, margin_m)
    r0 = np.floor(r_min / step_m) * step_m
    return float(r0), int(np.ceil((r_max - r0) / step_m)) + 2


def local_frame(positions_m: np.ndarray, points_m: np.ndarray, dtype) -> tuple[np.ndarray, np.ndarray]:
    """Both point sets shifted to the mean of ``points_m`` (in float64), then cast to ``dtype``:
    distances then keep float32 precision even far from the origin.

    positions_m : float64 (..., 3); points_m : float64 (P, 3). Returns the two arrays as ``dtype``.
    """
    origin = points_m.mean(axis=0)
    return (positions_m - origin).astype(dtype), (points_m - origin).astype(dtype)
