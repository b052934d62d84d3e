"""IF samples of point scatterers seen from many phase centres: the radar simulator.

Model (:mod:`twinfocus.radar.fmcw`, docs/architecture.md section 2), phase centre (m, k), scatterer j at
distance R = R_mkj:

    s_mk(t_n) = sum_j a_j exp(+j 2 pi (f0 + S t_n) 2 R / c)
              = sum_j a_j exp(+j 4 pi fc R / c) exp(+j beta_n R),   beta_n = 4 pi S (t_n - t_c) / c,

with fc = f0 + S t_c the centre frequency and t_c the middle of the sampled chirp.

:func:`simulate_if_exact` evaluates the sum as written (float64 phases, chunked): the truth for
tests and small cases. :func:`simulate_if` is the fast one. Only the second factor depends on n,
and it varies slowly with R (|beta_n| <= 80.5 rad/m for the default chirp, against 3,200 rad/m
for the carrier). So, per phase centre, each scatterer's exact carrier term a_j exp(j 4 pi fc R/c)
is deposited on the nearest node r_b of a uniform range grid (step ``range_step_m``, covering
only the ranges the scene spans) together with the Taylor terms of the residual
delta = R - r_b:

    exp(j beta_n R) = exp(j beta_n r_b) sum_{q=0}^{Q-1} (j beta_n delta)^q / q!  + remainder,

and the samples follow from one matrix product s = H @ G with, for x = delta / (h / 2),
H[mk, (b, q)] = sum of carrier terms x^q / q! of the scatterers nearest node b and
G[(b, q), n] = exp(j beta_n r_b) (j beta_n h / 2)^q. The remainder per scatterer is at most
(beta_max h / 2)^Q / Q! of its amplitude (h the step, Q = ``order`` + 1 terms): 7e-4 for the
defaults (h = 4 mm, Q = 3), and the remainders of many scatterers partly cancel. The
carrier is exact (float64, evaluated by a polynomial good to 1e-9), so the error does not grow
with range. Measured on the tests' small case (3 positions x 86 channels x 300 points at
0.6 m): relative error ||s - s_exact|| / ||s_exact|| = 9.7e-5 at the defaults, 1.7e-4 for plain
first order at 1 mm, 3e-6 with 4 terms at 4 mm (benchmarks/bench_simulate.py sweeps the step and
order); the tests hold it below 1e-3, also for scatterers 6.5 m away.

Cost: one distance, one carrier and Q multiply-adds per (phase centre, scatterer) pair in a
JIT-compiled loop (~8 ns of CPU per pair, the scatter of the Q terms dominating), plus a
(K M) x (Q B) x N complex64 product. The paper scene (two 127 mm letters, 4,401 scatterers,
67,080 elements, 256 samples) takes ~2.4 s of CPU, 1.2 - 2.3 s wall on two shared cores,
against ~45 minutes for the brute-force sum.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.range_geometry import cis_turns, range_lattice, range_window, turns_per_m
from twinfocus.radar.fmcw import C_M_PER_S, Chirp

try:
    from numba import njit, prange
except ImportError as exc:  # pragma: no cover - numba is a hard dependency
    raise ImportError("twinfocus.simulation.if_simulator needs numba (pip install numba)") from exc

ProgressFn = Callable[[int, int], None]

#: Range grid step of :func:`simulate_if`, metres (a fidelity knob, see the module docstring).
DEFAULT_RANGE_STEP_M = 4e-3
#: Taylor order of the residual range term (order + 1 terms).
DEFAULT_ORDER = 2

# Cap on the working matrix H of one chunk of phase centres (bytes), so memory stays bounded.
_CHUNK_BYTES = 64 * 2**20


def _check_points(points_m, amplitudes) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(points_m)
    if p.ndim != 2 or p.shape[1] != 3:
        raise TwinFocusError(f"points_m must be (P, 3) scatterer positions in metres, got shape {p.shape}")
    if p.shape[0] == 0:
        raise TwinFocusError("points_m is empty: the scene has no scatterers")
    if not (np.issubdtype(p.dtype, np.floating) or np.issubdtype(p.dtype, np.integer)):
        raise TwinFocusError(f"points_m must be real numbers, got dtype {p.dtype}")
    p = p.astype(np.float64)
    if not np.isfinite(p).all():
        i = int(np.argwhere(~np.isfinite(p))[0][0])
        raise TwinFocusError(f"points_m holds NaN or inf (first at point {i})")
    a = np.ones(p.shape[0], np.complex128) if amplitudes is None else np.asarray(amplitudes)
    if a.shape != (p.shape[0],):
        raise TwinFocusError(f"amplitudes must have shape ({p.shape[0]},) to match points_m, got {a.shape}")
    if not np.issubdtype(a.dtype, np.number):
        raise TwinFocusError(f"amplitudes must be numbers, got dtype {a.dtype}")
    a = a.astype(np.complex128)
    if not np.isfinite(a).all():
        i = int(np.flatnonzero(~np.isfinite(a))[0])
        raise TwinFocusError(f"amplitudes hold NaN or inf (first at point {i})")
    return p, a


def _check_positions(positions_m) -> np.ndarray:
    e = np.asarray(positions_m)
    if e.ndim != 3 or e.shape[2] != 3 or e.shape[0] == 0 or e.shape[1] == 0:
        raise TwinFocusError(
            f"positions_m must be (M, K, 3) phase centres in metres with M, K >= 1, got shape {e.shape}"
        )
    e = e.astype(np.float64)
    if not np.isfinite(e).all():
        bad = np.argwhere(~np.isfinite(e))[0]
        raise TwinFocusError(f"positions_m holds NaN or inf (first at position {bad[0]}, channel {bad[1]})")
    return e


def _check_chirp(chirp) -> Chirp:
    if not isinstance(chirp, Chirp):
        raise TwinFocusError(f"chirp must be a twinfocus.radar.fmcw.Chirp, got {type(chirp).__name__}")
    return chirp


def simulate_if_exact(
    points_m, amplitudes, positions_m, chirp: Chirp, max_block: int = 2_000_000, pattern_exponent: float = 0.0
) -> np.ndarray:
    """The IF model summed as written (float64 phases), for tests and small cases.

    points_m : float (P, 3) scatterers, metres; amplitudes : complex (P,) or None (all 1);
    positions_m : float (M, K, 3) phase centres, metres; max_block : elements x points x samples
    evaluated at once (memory bound); pattern_exponent : as :func:`simulate_if`. Returns
    complex64 (M, K, N).
    """
    p, a = _check_points(points_m, amplitudes)
    e = _check_positions(positions_m)
    chirp = _check_chirp(chirp)
    m, k = e.shape[:2]
    flat = e.reshape(-1, 3)
    two_k = 2.0 * chirp.wavenumbers_rad_per_m  # (N,) phase per metre of R
    n = two_k.shape[0]
    out = np.zeros((flat.shape[0], n), np.complex128)
    pts_step = max(1, min(p.shape[0], max_block // n))
    el_step = max(1, max_block // (pts_step * n))
    for e0 in range(0, flat.shape[0], el_step):
        el = flat[e0 : e0 + el_step]
        for p0 in range(0, p.shape[0], pts_step):
            pts = p[p0 : p0 + pts_step]
            r = np.sqrt(((el[:, None, :] - pts[None, :, :]) ** 2).sum(axis=-1))  # (e, p)
            term = np.exp(1j * r[:, :, None] * two_k)
            if pattern_exponent:
                term *= (np.abs(pts[None, :, 2] - el[:, None, 2]) / r)[:, :, None] ** pattern_exponent
            out[e0 : e0 + el_step] += np.einsum("p,epn->en", a[p0 : p0 + pts_step], term)
    return out.reshape(m, k, n).astype(np.complex64)


@njit(parallel=True, fastmath=True, cache=True)
def _spread_kernel(pos, px, py, pz, a_re, a_im, turns_per_m, r0, inv_step, n_terms, out, pattern_q=0.0):
    """out[e, 2 (b Q + q) + (0, 1)] += (re, im) of a_j cis(4 pi fc R / c) x^q / q!, with
    x = (R - r_b) / (step / 2) for the nearest node r_b, Q = n_terms; with ``pattern_q`` > 0
    each term is also scaled by (|dz| / R)^pattern_q (the antennas' beam pattern).

    Two passes per phase centre: a branch-free one (distance, carrier, node) that vectorises,
    then a scatter into the centre's own row (rows never collide across threads); Q <= 4 is
    written out so the scatter is straight-line code.
    """
    n_el = pos.shape[0]
    n_pts = px.shape[0]
    for e in prange(n_el):
        ex = pos[e, 0]
        ey = pos[e, 1]
        ez = pos[e, 2]
        b_buf = np.empty(n_pts, np.int32)
        x_buf = np.empty(n_pts, np.float64)
        c_re = np.empty(n_pts, np.float64)
        c_im = np.empty(n_pts, np.float64)
        for j in range(n_pts):
            dx = px[j] - ex
            dy = py[j] - ey
            dz = pz[j] - ez
            r = math.sqrt(dx * dx + dy * dy + dz * dz)
            u = (r - r0) * inv_step
            b = np.int32(u + 0.5)
            b_buf[j] = b
            x_buf[j] = 2.0 * (u - b)
            c, s = cis_turns(r * turns_per_m)
            c_re[j] = a_re[j] * c - a_im[j] * s
            c_im[j] = a_re[j] * s + a_im[j] * c
        if pattern_q > 0.0:
            # A pass of its own, so the loop above stays branch-free for the perfect array.
            for j in range(n_pts):
                dx = px[j] - ex
                dy = py[j] - ey
                dz = pz[j] - ez
                g = (abs(dz) / math.sqrt(dx * dx + dy * dy + dz * dz)) ** pattern_q
                c_re[j] *= g
                c_im[j] *= g
        row = out[e]
        if n_terms == 1:
            for j in range(n_pts):
                i = 2 * b_buf[j]
                row[i] += c_re[j]
                row[i + 1] += c_im[j]
        elif n_terms == 2:
            for j in range(n_pts):
                i = 4 * b_buf[j]
                x = x_buf[j]
                vr = c_re[j]
                vi = c_im[j]
                row[i] += vr
                row[i + 1] += vi
                row[i + 2] += vr * x
                row[i + 3] += vi * x
        elif n_terms == 3:
            for j in range(n_pts):
                i = 6 * b_buf[j]
                x = x_buf[j]
                x2 = 0.5 * x * x
                vr = c_re[j]
                vi = c_im[j]
                row[i] += vr
                row[i + 1] += vi
                row[i + 2] += vr * x
                row[i + 3] += vi * x
                row[i + 4] += vr * x2
                row[i + 5] += vi * x2
        elif n_terms == 4:
            for j in range(n_pts):
                i = 8 * b_buf[j]
                x = x_buf[j]
                x2 = 0.5 * x * x
                x3 = x2 * x * (1.0 / 3.0)
                vr = c_re[j]
                vi = c_im[j]
                row[i] += vr
                row[i + 1] += vi
                row[i + 2] += vr * x
                row[i + 3] += vi * x
                row[i + 4] += vr * x2
                row[i + 5] += vi * x2
                row[i + 6] += vr * x3
                row[i + 7] += vi * x3
        else:
            for j in range(n_pts):
                i = 2 * n_terms * b_buf[j]
                x = x_buf[j]
                w = 1.0
                vr = c_re[j]
                vi = c_im[j]
                for q in range(n_terms):
                    row[i + 2 * q] += vr * w
                    row[i + 2 * q + 1] += vi * w
                    w = w * x * (1.0 / (q + 1))


def _basis(chirp: Chirp, r0: float, step: float, n_bins: int, n_terms: int) -> np.ndarray:
    """G[(b, q), n] = exp(j beta_n r_b) (j beta_n step / 2)^q, complex64 (n_bins * n_terms, N)."""
    beta = 4.0 * np.pi * chirp.slope_hz_per_s * (chirp.t_s - chirp.t_centre_s) / C_M_PER_S  # (N,)
    r_b = r0 + step * np.arange(n_bins)
    g = np.exp(1j * np.outer(r_b, beta))  # (B, N)
    powers = (1j * beta * step / 2.0)[None, :] ** np.arange(n_terms)[:, None]  # (Q, N)
    return (g[:, None, :] * powers[None, :, :]).reshape(n_bins * n_terms, -1).astype(np.complex64)


def simulate_if(
    points_m,
    amplitudes,
    positions_m,
    chirp: Chirp,
    range_step_m: float = DEFAULT_RANGE_STEP_M,
    order: int = DEFAULT_ORDER,
    chunk_positions: int | None = None,
    progress: ProgressFn | None = None,
    pattern_exponent: float = 0.0,
) -> np.ndarray:
    """Fast IF samples of point scatterers (method and error bound in the module docstring).

    Parameters
    ----------
    points_m : float (P, 3) scatterer positions, metres (scene frame).
    amplitudes : complex (P,) or None (all 1).
    positions_m : float (M, K, 3) phase centres, metres.
    chirp : the :class:`~twinfocus.radar.fmcw.Chirp`.
    range_step_m : range grid step h (metres); error per scatterer <= (beta_max h / 2)^Q / Q!.
    order : Taylor order of the residual range term (Q = order + 1 terms, 0..6).
    chunk_positions : radar positions per work chunk (default: sized to keep the working
        matrix under 64 MiB).
    progress : optional ``progress(done_positions, total_positions)`` after each chunk.
    pattern_exponent : q of each antenna's power pattern cos(theta)^q (0: isotropic, the
        default): a scatterer's return is scaled by cos(theta)^q, theta between the scene's z
        axis (the radar's boresight) and the ray (:mod:`twinfocus.radar.array_errors`).

    Returns
    -------
    complex64 (M, K, N).
    """
    p, a = _check_points(points_m, amplitudes)
    e = _check_positions(positions_m)
    chirp = _check_chirp(chirp)
    step = float(range_step_m)
    if not (np.isfinite(step) and step > 0):
        raise TwinFocusError(f"range_step_m must be a positive number, got {range_step_m!r}")
    if not (isinstance(order, (int, np.integer)) and 0 <= int(order) <= 6):
        raise TwinFocusError(f"order must be an integer in 0..6, got {order!r}")
    n_terms = int(order) + 1
    m_total, k = e.shape[:2]
    n = chirp.n_samples
    # Work in a frame centred on the scene: distances are the same, and numbers stay small.
    origin = p.mean(axis=0)
    p = p - origin
    e = e - origin
    # A fixed shuffle of the points: neighbours on a surface fall in the same range node, and
    # consecutive updates of one node serialise; shuffled, they overlap (~30 % faster).
    perm = np.random.default_rng(0).permutation(p.shape[0])
    p = p[perm]
    a = a[perm]
    px, py, pz = (np.ascontiguousarray(p[:, i]) for i in range(3))
    a_re = np.ascontiguousarray(a.real)
    a_im = np.ascontiguousarray(a.imag)
    carrier_turns_per_m = turns_per_m(chirp)

    if chunk_positions is None:
        lo, hi = range_window(e, p, margin_m=step)
        cols = (int(np.ceil((hi - lo) / step)) + 2) * n_terms
        chunk_positions = max(1, _CHUNK_BYTES // (16 * cols * k))
    chunk_positions = max(1, int(chunk_positions))

    out = np.empty((m_total, k, n), np.complex64)
    for m0 in range(0, m_total, chunk_positions):
        m1 = min(m_total, m0 + chunk_positions)
        el = np.ascontiguousarray(e[m0:m1].reshape(-1, 3))
        # Nodes on the lattice step * integer, whatever the chunk: the result does not depend on
        # how the positions are chunked.
        r_lo, n_bins = range_lattice(el, p, step, margin_m=step)
        h = np.zeros((el.shape[0], 2 * n_bins * n_terms))  # interleaved (re, im)
        _spread_kernel(
            el, px, py, pz, a_re, a_im, carrier_turns_per_m, r_lo, 1.0 / step, n_terms, h, float(pattern_exponent)
        )
        h = h.view(np.complex128).astype(np.complex64)
        out[m0:m1] = (h @ _basis(chirp, r_lo, step, n_bins, n_terms)).reshape(m1 - m0, k, n)
        if progress is not None:
            progress(m1, m_total)
    return out


#: CPU time per (phase centre, scatterer) pair of :func:`simulate_if`, seconds (module docstring:
#: ~8 ns measured on the paper scene); used only for up-front estimates.
SECONDS_PER_PAIR = 8e-9
#: Bytes per IF sample (complex64) held at the peak of one simulated scan with thermal noise:
#: the result (8) plus :func:`add_thermal_noise`'s transients (a complex128 power pass, the float32
#: noise pair, its complex128 sum and the complex64 result: ~48).
BYTES_PER_SAMPLE_PEAK = 56


def simulation_cost(
    n_positions: int, n_channels: int, n_samples: int, n_scatterers: int, n_scans: int = 1
) -> tuple[int, float]:
    """Up-front estimate of simulating ``n_scans`` scans of this size: (peak bytes, CPU seconds).

    Bytes: the finished scans (complex64) plus the noise pass of the last one; seconds:
    :data:`SECONDS_PER_PAIR` per (phase centre, scatterer) pair, each scan with all scatterers.
    """
    elements = int(n_positions) * int(n_channels)
    samples = elements * int(n_samples)
    peak = samples * (8 * (int(n_scans) - 1) + BYTES_PER_SAMPLE_PEAK)
    return int(peak), float(int(n_scans) * elements * int(n_scatterers) * SECONDS_PER_PAIR)


#: bytes per grid cell while a planar object's scatterers are placed (meshgrid, jitter, indices,
#: points and amplitudes: about a dozen 8-byte values per cell at the peak)
BYTES_PER_SCATTERER_CELL = 120


def scatterer_cells(scene, spacing_m: float) -> int:
    """Grid cells the scene's scatterers are drawn from at ``spacing_m`` (metres), counted without
    making them: a planar object's ceil(w / s) x ceil(h / s) cells (before its mask keeps some),
    a point cloud's points, the clutter's points. Each costs about
    :data:`BYTES_PER_SCATTERER_CELL` bytes while the scatterers are placed, so a memory check can
    refuse a scene that would not fit before it is drawn."""
    n = 0
    for obj in scene.objects:
        size = getattr(obj, "size_m", None)
        if size is not None:
            w_m, h_m = size
            n += max(1, math.ceil(w_m / spacing_m)) * max(1, math.ceil(h_m / spacing_m))
        else:
            n += int(np.asarray(obj.points_m).shape[0])
    if scene.clutter is not None:
        n += int(scene.clutter.n_points) + int(scene.clutter.n_strong)
    return n


def add_thermal_noise(
    data, snr_db: float, rng: np.random.Generator | int | None = None, signal_power: float | None = None
) -> np.ndarray:
    """Add circular complex white Gaussian noise at a per-sample SNR.

    SNR definition: mean signal power over all samples, mean(|data|^2), divided by the noise
    variance E|w|^2 (split equally between I and Q). So 10 dB means each sample's noise power is
    a tenth of the average sample power; after range and aperture compression the image SNR is
    far higher (coherent gain of M K N).

    data : complex (M, K, N) (any shape); snr_db : finite number; rng : Generator, seed or None.
    signal_power : the mean signal power the SNR refers to, when ``data`` is one block of a
    larger scan (the noise of consecutive blocks drawn from one generator equals one draw over
    the whole scan); default mean(|data|^2).
    Returns complex64 of data's shape.
    """
    x = np.asarray(data)
    if not np.iscomplexobj(x):
        raise TwinFocusError(f"data must be complex IF samples, got dtype {x.dtype}")
    snr = float(snr_db)
    if not np.isfinite(snr):
        raise TwinFocusError(f"snr_db must be a finite number of decibels, got {snr_db!r}")
    if signal_power is not None:
        power = float(signal_power)
    else:
        power = float(np.mean(np.abs(x.astype(np.complex128)) ** 2)) if x.size else 0.0
    if not power > 0:
        raise TwinFocusError("data is all zeros (or empty): an SNR relative to it is undefined")
    sigma = np.sqrt(power * 10.0 ** (-snr / 10.0) / 2.0)
    gen = np.random.default_rng(rng)
    noise = gen.standard_normal(x.shape + (2,), dtype=np.float32) * np.float32(sigma)
    return (x + (noise[..., 0] + 1j * noise[..., 1])).astype(np.complex64)
