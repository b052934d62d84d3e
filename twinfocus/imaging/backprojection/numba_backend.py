"""Back-projection: the exact matched filter of the IF model, evaluated through range profiles.

For a pixel at r and a phase centre at p (distance R = |r - p|) the matched filter of the model in
:mod:`twinfocus.radar.fmcw` is

    MF(R) = sum_n s_n exp(-j 2 pi (f0 + S t_n) 2 R / c)
          = exp(-j 4 pi fc R / c) * P(R),   P(R) = sum_n s_n exp(-j 2 pi S (t_n - t_c) 2 R / c),

with fc the centre frequency and t_c the centre of the chirp. P is the *baseband* range profile:
band-limited and smooth (no carrier), so it is computed once per channel on a fine range grid that
covers only the ranges the image reaches ("zoomed" range compression, :func:`range_profiles_at`)
and linearly interpolated; the carrier term is evaluated exactly per pixel.

Interpolation error: with the default ``oversample=16`` (grid step c / (2 B) / 16, ~2.4 mm) the
linear interpolation of a point target's profile errs by at most ~0.2 % of its peak (second-order
term h^2 max|P''| / 8 of the sinc main lobe); tests compare against the brute-force sum.

Backends: ``"numba"`` (CPU, JIT-compiled, parallel over positions or pixel blocks) and
``"torch"`` (any torch device; the CUDA path). Both compute the same function.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.range_geometry import (
    _COS_C,
    _SIN_C,
    DEFAULT_OVERSAMPLE,
    local_frame,
    range_lattice,
    turns_per_m,
)
from twinfocus.radar.fmcw import C_M_PER_S, Chirp, range_profiles_at

try:  # numba is a hard dependency; the guard only keeps import errors readable
    import numba
    from numba import njit, prange
except ImportError as exc:  # pragma: no cover
    raise ImportError("twinfocus.imaging.backprojection.numba_backend needs numba (pip install numba)") from exc

ProgressFn = Callable[[int, int], None]


def _kernel_constants(dtype, qmax: float) -> np.ndarray:
    """The constants of :func:`_accumulate_channel` as an array of the arithmetic's dtype: a
    Python float literal in jitted code is float64 and would promote every float32 operation it
    touches to float64 (half the vector width). [0, 1/2, qmax, sin coefficients (7), cos (8)]."""
    return np.array((0.0, 0.5, qmax, *_SIN_C, *_COS_C), dtype=dtype)


@njit(inline="always", fastmath=True)
def _accumulate_channel(
    tab, ex, ey, ez, px, py, pz, r0, inv_dr, turns_per_m, kc, out_re, out_im, p_lo, p_hi, idx, frac, cos_buf, sin_buf
):
    """Add one channel's matched filter to out[0:p_hi-p_lo] for pixels p_lo..p_hi.

    Two passes over the pixel block: distance, interpolation index and carrier (branch-free
    arithmetic in the dtype of the inputs, which the compiler vectorises), then the profile
    gather and accumulation. tab: (Q, 4) the channel's profile as (re, im, d re, d im) per range
    node (:func:`_interpolation_table`): one 16-byte read per pixel instead of four scattered
    ones, which made the gather pass 1.5x faster. kc: :func:`_kernel_constants`. idx/frac/cos_buf/sin_buf
    are scratch buffers of the block's length (:func:`_channel_scratch`). The carrier is
    :func:`~twinfocus.imaging.range_geometry.cis_turns`' polynomials, evaluated here with typed constants.
    """
    zero, half, qmax = kc[0], kc[1], kc[2]
    s0, s1, s2, s3, s4, s5, s6 = kc[3], kc[4], kc[5], kc[6], kc[7], kc[8], kc[9]
    c0, c1, c2, c3, c4, c5, c6, c7 = kc[10], kc[11], kc[12], kc[13], kc[14], kc[15], kc[16], kc[17]
    n = p_hi - p_lo
    for q in range(n):
        p = p_lo + q
        dx = px[p] - ex
        dy = py[p] - ey
        dz = pz[p] - ez
        rel = math.sqrt(dx * dx + dy * dy + dz * dz) - r0
        u = min(max(rel * inv_dr, zero), qmax)
        fl = np.floor(u)  # u >= 0: floor is the truncation, in u's type
        idx[q] = np.int32(fl)
        frac[q] = u - fl
        t = rel * turns_per_m
        r = t - np.floor(t + half)
        r2 = r * r
        sin_buf[q] = r * (s0 + r2 * (s1 + r2 * (s2 + r2 * (s3 + r2 * (s4 + r2 * (s5 + r2 * s6))))))
        cos_buf[q] = c0 + r2 * (c1 + r2 * (c2 + r2 * (c3 + r2 * (c4 + r2 * (c5 + r2 * (c6 + r2 * c7))))))
    for q in range(n):
        i = idx[q]
        f = frac[q]
        vr = tab[i, 0] + f * tab[i, 2]
        vi = tab[i, 1] + f * tab[i, 3]
        c = cos_buf[q]
        s = sin_buf[q]
        # v * exp(-j phase)
        out_re[q] += vr * c + vi * s
        out_im[q] += vi * c - vr * s


@njit(inline="always")
def _channel_scratch(n, like):
    """:func:`_accumulate_channel`'s scratch for a block of ``n`` pixels: (idx int32, frac, cos_buf,
    sin_buf), each (n,), the last three in the dtype of the array ``like``."""
    return np.empty(n, np.int32), np.empty(n, like.dtype), np.empty(n, like.dtype), np.empty(n, like.dtype)


@njit(inline="always", fastmath=True)
def _accumulate_position(
    tab, pos, px, py, pz, r0, inv_dr, turns_per_m, kc, out_re, out_im, p_lo, p_hi, idx, frac, cos_buf, sin_buf
):
    """Add one radar position's channels to out[0:p_hi-p_lo] for pixels p_lo..p_hi, channel by
    channel (:func:`_accumulate_channel`): tab (K, Q, 4) its channels' tables, pos (K, 3) their
    phase centres; the rest as :func:`_accumulate_channel`'s. What both kernels do per position."""
    for k in range(pos.shape[0]):
        _accumulate_channel(
            tab[k], pos[k, 0], pos[k, 1], pos[k, 2], px, py, pz, r0, inv_dr, turns_per_m, kc, out_re, out_im, p_lo,
            p_hi, idx, frac, cos_buf, sin_buf
        )  # fmt: skip


@njit(parallel=True, fastmath=True, cache=True)
def _basis_kernel(tab, pos, px, py, pz, r0, inv_dr, turns_per_m, kc, out_re, out_im):
    """out[m, p] = sum_k MF_mk(R_mkp); parallel over positions (rows never collide)."""
    n_pos = pos.shape[0]
    n_pix = px.shape[0]
    for m in prange(n_pos):
        idx, frac, cos_buf, sin_buf = _channel_scratch(n_pix, px)
        _accumulate_position(
            tab[m], pos[m], px, py, pz, r0, inv_dr, turns_per_m, kc, out_re[m], out_im[m], 0, n_pix, idx, frac,
            cos_buf, sin_buf
        )  # fmt: skip


@njit(parallel=True, fastmath=True, cache=True)
def _image_kernel(tab, pos, px, py, pz, r0, inv_dr, turns_per_m, kc, block, out_re, out_im):
    """out[p] = sum_{m,k} MF_mk(R_mkp); parallel over pixel blocks that stay in cache."""
    n_pos = pos.shape[0]
    n_pix = px.shape[0]
    n_blocks = (n_pix + block - 1) // block
    for b in prange(n_blocks):
        lo = b * block
        hi = min(lo + block, n_pix)
        acc_re = np.zeros(hi - lo, dtype=out_re.dtype)
        acc_im = np.zeros(hi - lo, dtype=out_im.dtype)
        idx, frac, cos_buf, sin_buf = _channel_scratch(hi - lo, px)
        for m in range(n_pos):
            _accumulate_position(
                tab[m], pos[m], px, py, pz, r0, inv_dr, turns_per_m, kc, acc_re, acc_im, lo, hi, idx, frac, cos_buf,
                sin_buf
            )  # fmt: skip
        out_re[lo:hi] = acc_re
        out_im[lo:hi] = acc_im


# --- shared preparation ----------------------------------------------------------------------


def _interpolation_table(prof_re: np.ndarray, prof_im: np.ndarray) -> np.ndarray:
    """(M, K, Q, 4) [re, im, next re - re, next im - im] per range node, the kernels' layout
    (the last node's differences are 0: the kernels never interpolate past Q - 1.0001)."""
    tab = np.zeros((*prof_re.shape, 4), prof_re.dtype)
    tab[..., 0] = prof_re
    tab[..., 1] = prof_im
    tab[..., :-1, 2] = np.diff(prof_re, axis=-1)
    tab[..., :-1, 3] = np.diff(prof_im, axis=-1)
    return tab


def _check_inputs(data: np.ndarray, positions: np.ndarray, chirp: Chirp) -> None:
    if data.ndim != 3 or not np.iscomplexobj(data):
        raise TwinFocusError(f"data must be complex (M, K, N), got {data.dtype} {data.shape}")
    if positions.shape != (*data.shape[:2], 3):
        raise TwinFocusError(f"positions must be (M, K, 3) = {(*data.shape[:2], 3)}, got {positions.shape}")
    if data.shape[2] != chirp.n_samples:
        raise TwinFocusError(f"data has {data.shape[2]} samples per chirp, the chirp has {chirp.n_samples}")
    if not np.isfinite(positions).all():
        raise TwinFocusError("positions hold NaN or inf")
    if not np.isfinite(data).all():
        raise TwinFocusError("data hold NaN or inf")


def prepare_profiles(
    data: np.ndarray,
    positions_m: np.ndarray,
    chirp: Chirp,
    points_m: np.ndarray,
    oversample: int = DEFAULT_OVERSAMPLE,
    dtype=np.float32,
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Baseband range profiles on the range window the image reaches.

    Returns (prof_re, prof_im) of dtype (M, K, Q), the window start r0 (m) and step dr (m). The
    profiles are pre-multiplied by exp(-j 4 pi fc r0 / c) so the per-pixel carrier phase is the
    small local quantity 4 pi fc (R - r0) / c: this keeps float32 phases exact at long range.
    """
    if oversample < 1:
        raise TwinFocusError(f"oversample must be >= 1, got {oversample}")
    dr = chirp.range_resolution_m / oversample
    # On the global lattice dr * integer: a basis built batch by batch equals a whole-scan one.
    r_min, q = range_lattice(positions_m, points_m, dr, margin_m=2 * dr)
    ranges = r_min + dr * np.arange(q)
    prof = range_profiles_at(data.reshape(-1, data.shape[-1]), chirp, ranges)
    turns0 = 2.0 * chirp.fc_hz * r_min / C_M_PER_S
    prof = prof * np.complex64(np.exp(-2j * np.pi * (turns0 - np.floor(turns0))))
    prof = prof.reshape(*data.shape[:2], q)
    return prof.real.astype(dtype), prof.imag.astype(dtype), float(r_min), float(dr)


def _normalise_precision(precision: str):
    if precision not in ("float32", "float64"):
        raise TwinFocusError(f"precision must be 'float32' or 'float64', got {precision!r}")
    return np.float32 if precision == "float32" else np.float64


def _dispatch(
    numba_impl, data, positions_m, chirp: Chirp, points_m, oversample, precision, backend, device, progress, basis: bool
):
    """What :func:`backproject_points` and :func:`subimage_basis_points` share: convert and check
    the inputs, then run the torch back-end (``basis`` picks image or basis) or
    ``numba_impl(data, pos, pts, dtype, chirp, oversample, progress)`` with positions and points
    in the local frame (:func:`~twinfocus.imaging.range_geometry.local_frame`) as ``dtype``."""
    data = np.asarray(data)
    positions_m = np.asarray(positions_m, dtype=np.float64)
    points_m = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    _check_inputs(data, positions_m, chirp)
    dtype = _normalise_precision(precision)
    if backend == "torch":
        from twinfocus.imaging.backprojection.torch_backend import (
            backproject_points_torch,  # lazy: torch (+10.5 s at import)
        )

        return backproject_points_torch(
            data, positions_m, chirp, points_m, oversample=oversample, precision=precision, device=device, basis=basis
        )
    if backend != "numba":
        raise TwinFocusError(f"unknown back-projection backend {backend!r}; use 'numba' or 'torch'")
    pos, pts = local_frame(positions_m, points_m, dtype)
    return numba_impl(data, pos, pts, dtype, chirp, oversample, progress)


# --- public API --------------------------------------------------------------------------------


def backproject_points(
    data: np.ndarray,
    positions_m: np.ndarray,
    chirp: Chirp,
    points_m: np.ndarray,
    *,
    oversample: int = DEFAULT_OVERSAMPLE,
    precision: str = "float32",
    backend: str = "numba",
    device: str | None = None,
    progress: ProgressFn | None = None,
) -> np.ndarray:
    """Back-projected complex image at arbitrary points.

    Parameters
    ----------
    data : complex64 (M, K, N) IF samples.
    positions_m : float64 (M, K, 3) phase centres, metres.
    points_m : float64 (P, 3) pixel/voxel positions, metres.
    precision : ``"float32"`` (default) or ``"float64"`` arithmetic.
    backend : ``"numba"`` (CPU) or ``"torch"`` (``device`` e.g. ``"cuda"``).

    Returns
    -------
    complex64 (P,) sum over positions and channels of the matched filter (unnormalised).
    """
    return _dispatch(
        _image_numba, data, positions_m, chirp, points_m, oversample, precision, backend, device, progress, basis=False
    )


def pixel_block(n_pixels: int) -> int:
    """Pixels per block of a kernel parallel over pixel blocks: at most 4096 (cache-resident), in
    blocks whose count is a multiple of numba's thread count, so that no thread idles at the end."""
    threads = numba.get_num_threads()
    n_blocks = max(1, -(-n_pixels // 4096))
    n_blocks = -(-n_blocks // threads) * threads
    return max(1, -(-n_pixels // n_blocks))


def _image_numba(data, pos, pts, dtype, chirp: Chirp, oversample: int, progress: ProgressFn | None) -> np.ndarray:
    """The numba path of :func:`backproject_points` (inputs checked, in the local frame)."""
    out_re = np.zeros(pts.shape[0], dtype)
    out_im = np.zeros(pts.shape[0], dtype)
    block = pixel_block(pts.shape[0])
    for _, _, inputs in _position_chunks(data, pos, pts, dtype, chirp, oversample, progress):
        part_re = np.empty_like(out_re)
        part_im = np.empty_like(out_im)
        _image_kernel(*inputs, block, part_re, part_im)
        out_re += part_re
        out_im += part_im
    return (out_re + 1j * out_im).astype(np.complex64)


def _position_chunks(data, pos, pts, dtype, chirp: Chirp, oversample: int, progress: ProgressFn | None):
    """The positions in chunks, which bound the profile memory: yields (lo, hi, inputs) per chunk
    of positions lo..hi, inputs the kernels' first nine arguments (interpolation table, positions,
    pixel x, y, z, r0, 1 / dr, turns per metre, :func:`_kernel_constants`) in ``dtype``; calls
    ``progress(hi, M)`` once the chunk is done (when the next is asked for)."""
    px, py, pz = pts[:, 0].copy(), pts[:, 1].copy(), pts[:, 2].copy()
    n_pos = data.shape[0]
    chunk = max(1, int(4e6 // max(1, data.shape[1] * chirp.n_samples)))
    for lo in range(0, n_pos, chunk):
        hi = min(lo + chunk, n_pos)
        pre, pim, r0, dr = prepare_profiles(
            data[lo:hi], pos[lo:hi].astype(np.float64), chirp, pts.astype(np.float64), oversample, dtype
        )
        table = _interpolation_table(pre, pim)
        kc = _kernel_constants(dtype, pre.shape[2] - 1.0001)
        yield lo, hi, (table, pos[lo:hi], px, py, pz, dtype(r0), dtype(1.0 / dr), dtype(turns_per_m(chirp)), kc)
        if progress is not None:
            progress(hi, n_pos)


def subimage_basis_points(
    data: np.ndarray,
    positions_m: np.ndarray,
    chirp: Chirp,
    points_m: np.ndarray,
    *,
    oversample: int = DEFAULT_OVERSAMPLE,
    precision: str = "float32",
    backend: str = "numba",
    device: str | None = None,
    progress: ProgressFn | None = None,
) -> np.ndarray:
    """Per-position sub-images B_m (channels summed) at arbitrary points: complex64 (M, P).

    ``basis.sum(axis=0)`` equals :func:`backproject_points`; the autofocus forms
    |sum_m exp(j phi_m) B_m| from it.
    """
    return _dispatch(
        _basis_numba, data, positions_m, chirp, points_m, oversample, precision, backend, device, progress, basis=True
    )


def _basis_numba(data, pos, pts, dtype, chirp: Chirp, oversample: int, progress: ProgressFn | None) -> np.ndarray:
    """The numba path of :func:`subimage_basis_points` (inputs checked, in the local frame)."""
    out = np.empty((data.shape[0], pts.shape[0]), np.complex64)
    for lo, hi, inputs in _position_chunks(data, pos, pts, dtype, chirp, oversample, progress):
        o_re = np.zeros((hi - lo, pts.shape[0]), dtype)
        o_im = np.zeros((hi - lo, pts.shape[0]), dtype)
        _basis_kernel(*inputs, o_re, o_im)
        out[lo:hi].real = o_re
        out[lo:hi].imag = o_im
    return out


def backproject(data, positions_m, chirp: Chirp, grid, **kwargs) -> np.ndarray:
    """Back-projected complex image on a grid (:class:`~twinfocus.imaging.grid.ImageGrid` or
    :class:`~twinfocus.imaging.grid.VolumeGrid`): complex64 ``grid.shape``. Keywords as
    :func:`backproject_points`."""
    return backproject_points(data, positions_m, chirp, grid.points(), **kwargs).reshape(grid.shape)


def subimage_basis(data, positions_m, chirp: Chirp, grid, **kwargs) -> np.ndarray:
    """Sub-image basis on a grid: complex64 (M, *grid.shape). Keywords as
    :func:`subimage_basis_points`."""
    basis = subimage_basis_points(data, positions_m, chirp, grid.points(), **kwargs)
    return basis.reshape(basis.shape[0], *grid.shape)


def matched_filter_bruteforce(
    data: np.ndarray, positions_m: np.ndarray, chirp: Chirp, points_m: np.ndarray
) -> np.ndarray:
    """Reference: the full matched-filter sum over positions, channels and samples in float64.

    complex128 (P,). Cost M*K*N*P: for tests on small cases only.
    """
    data = np.asarray(data, dtype=np.complex128).reshape(-1, chirp.n_samples)
    e = np.asarray(positions_m, dtype=np.float64).reshape(-1, 3)
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    k2 = 2.0 * chirp.wavenumbers_rad_per_m  # (N,)
    out = np.zeros(pts.shape[0], np.complex128)
    for i, p in enumerate(pts):
        rng = np.sqrt(((e - p) ** 2).sum(axis=1))  # (MK,)
        out[i] = np.sum(data * np.exp(-1j * np.outer(rng, k2)))
    return out


def set_threads(n: int) -> None:
    """Number of CPU threads the numba kernels use (<= NUMBA_NUM_THREADS)."""
    numba.set_num_threads(int(n))
