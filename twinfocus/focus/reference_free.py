"""Reference-free autofocus on the sub-image basis: minimum entropy and phase-gradient autofocus.

With the basis B (M, H, W) of a region (:func:`twinfocus.imaging.backprojection.numba_backend.subimage_basis`) the image
corrected by one phase per radar position is image(phi) = sum_m exp(j phi_m) B_m
(:func:`twinfocus.imaging.basis.form_image`). Both methods here choose phi from the region's own image,
with no template: what the field uses when no reference is in view.

* :func:`minimum_entropy_phase`: the phases that make the image's intensity least spread out
  (smallest Shannon entropy), one position at a time. With the others fixed the intensity is
  I(p; t) = c0(p) + Re(c1(p) exp(j t)) in that position's phase t: a second-order model of the
  entropy in t proposes a step, and when the exact entropy does not fall there, a full turn of
  candidates is searched; a step is kept only when it lowers the entropy, so it never rises and
  no step is caught by a wrap.
* :func:`phase_gradient_phase`: phase-gradient autofocus (PGA) adapted to the basis. The
  back-projection has already taken the near-field range migration out, so a bright pixel's
  column B[:, p] is the phase history of the scatterer there, and the eigenvector estimator of
  PGA (the dominant scatterers' coherent products) becomes
  phi_m <- angle(sum_p conj(B_m(p)) image(p)) over the brightest local maxima, repeated with
  the pixels chosen again on the sharper image.

Neither can see a constant phase (it changes nothing) nor a phase linear across the aperture (it
only moves the image): their estimates hold the truth up to those (:mod:`twinfocus.focus.phase_ramp`).
The basis's scale is free (each works on the basis divided by its peak), so amplitudes from
1e-20 to 1e20 give the same phases.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.focus.autofocus import AutofocusResult
from twinfocus.imaging.basis import form_image


def _unit_basis(basis: np.ndarray) -> np.ndarray:
    """The basis as complex128 (M, P) divided by its peak |B|; refuses what holds no image."""
    b = np.asarray(basis)
    if b.ndim != 3 or b.shape[0] < 1 or b.shape[1] < 1 or b.shape[2] < 1:
        raise TwinFocusError(f"basis must be (M, H, W) with M, H, W >= 1, got shape {b.shape}")
    if not np.iscomplexobj(b):
        raise TwinFocusError(f"basis must be complex (a sub-image per radar position), got {b.dtype}")
    flat = b.reshape(b.shape[0], -1)
    if not np.isfinite(flat).all():
        raise TwinFocusError("basis holds NaN or inf")
    peak = float(np.abs(flat).max())
    if peak == 0.0:
        raise TwinFocusError("basis is empty: no signal reaches the region")
    # divided in float64 first: a peak near 1e-40 would overflow 1 / peak in complex64
    return flat.astype(np.complex128) / peak


def _entropy(intensity: np.ndarray) -> np.ndarray:
    """Shannon entropy (nats) of intensity (P, K) normalised over its first axis: float64 (K,).
    ln S - sum(I ln I) / S, with 0 ln 0 = 0 (0 for an all-zero column)."""
    from scipy.special import xlogy

    i = np.maximum(intensity, 0.0)
    s = i.sum(axis=0)
    safe = np.where(s > 0, s, 1.0)
    return np.where(s > 0, np.log(safe) - xlogy(i, i).sum(axis=0) / safe, 0.0)


def _model_step(c0: np.ndarray, c1: np.ndarray, t_now: float, grid: int = 64) -> float:
    """The phase t (radians) that minimises a second-order model of the entropy of
    I(t) = c0 + Re(c1 exp(j t)) (c0 float (P,), c1 complex (P,)) around ``t_now``.

    The image's energy S(t) = sum c0 + Re(sum c1 exp(j t)) is exact; sum I ln I is expanded to
    second order in dI = I(t) - I(t_now), which makes it a trigonometric polynomial of order 2 in
    t: a handful of sums over the pixels, then ``grid`` phases tried on the polynomial alone (the
    exact entropy of a full turn costs a pass over the pixels per phase)."""
    z0 = np.exp(1j * t_now)
    q = (c1 * z0).real
    i0 = c0 + q
    i0 = np.maximum(i0, 1e-6 * max(float(i0.max()), 1e-300))  # the model's curvature 1 / I stays bounded
    inv = 1.0 / i0
    g1 = np.log(i0) + 1.0
    a1 = np.sum(g1 * c1)
    a2 = np.sum(c1 * c1 * inv)
    a3 = np.sum(q * c1 * inv)
    k0 = float(np.sum((c1.real**2 + c1.imag**2) * inv))
    q0 = float(np.sum(q * q * inv))
    f0 = float(np.sum(i0 * np.log(i0))) - float(np.sum(g1 * q))
    t = t_now + 2.0 * np.pi * np.arange(grid) / grid
    z = np.exp(1j * t)
    f = f0 + (a1 * z).real + 0.5 * (0.5 * k0 + 0.5 * (a2 * z * z).real - 2.0 * (a3 * z).real + q0)
    s = float(np.sum(c0)) + (np.sum(c1) * z).real
    with np.errstate(divide="ignore", invalid="ignore"):
        model = np.where(s > 0, np.log(np.where(s > 0, s, 1.0)) - f / np.where(s > 0, s, 1.0), np.inf)
    k = int(np.argmin(model))
    lo, mid, hi = model[k - 1], model[k], model[(k + 1) % grid]
    curvature = lo - 2.0 * mid + hi
    # between the grid's phases: a step that moves smoothly with the data, not by grid steps
    offset = 0.5 * (lo - hi) / curvature if np.isfinite(curvature) and curvature > 0 else 0.0
    return float(t[k] + 2.0 * np.pi / grid * offset)


def minimum_entropy_phase(
    basis: np.ndarray,
    iterations: int = 10,
    *,
    candidates: int = 16,
    tol_rad: float = 1e-3,
    init_phase_rad: np.ndarray | None = None,
) -> tuple[np.ndarray, dict]:
    """Per-position phases that minimise the entropy of the region's intensity (coordinate descent).

    Each sweep visits the positions in order; for position m the intensity is
    I(p; t) = |a|^2 + |B_m|^2 + 2 Re(conj(a) B_m exp(j t)) with a = the image without it. The
    phase that minimises a second-order model of the entropy in t is tried first (a few passes
    over the pixels); when it does not lower the exact entropy, the exact entropy at
    ``candidates`` phases over a full turn is searched, the best refined by a parabola through it
    and its neighbours. A phase is kept only when it lowers the exact entropy, so the entropy never rises.

    Parameters
    ----------
    basis : complex (M, H, W) sub-image basis of the region (any scale; complex64 or complex128).
    iterations : sweeps over the positions at most (>= 1); stops earlier when no phase moved by
        more than ``tol_rad`` in a sweep.
    candidates : phases of the exact search (>= 4), spaced 2 pi / ``candidates``; each costs a
        pass over the pixels.
    tol_rad : convergence threshold, radians.
    init_phase_rad : float (M,) radians to start from (zeros when None).

    Returns
    -------
    phase_rad : float64 (M,) radians in [-pi, pi), known up to a constant and a linear ramp
        across the aperture.
    info : dict with ``entropy`` (float, nats: uncorrected, then after each sweep), ``sweeps``,
        ``converged`` (bool: the last sweep moved no phase by more than ``tol_rad``), ``time_s``.
    """
    if int(iterations) < 1:
        raise TwinFocusError(f"iterations must be >= 1, got {iterations}")
    if int(candidates) < 4:
        raise TwinFocusError(f"candidates must be >= 4, got {candidates}")
    if not (np.isfinite(tol_rad) and tol_rad >= 0):
        raise TwinFocusError(f"tol_rad must be a non-negative number, got {tol_rad}")
    t0 = time.perf_counter()
    b = _unit_basis(basis)
    m_count = b.shape[0]
    phase = _initial_phase(init_phase_rad, m_count)
    e = np.exp(1j * phase)
    image = e @ b
    history = [float(_entropy(np.abs(image[:, None]) ** 2)[0])]
    steps = 2.0 * np.pi * np.arange(int(candidates)) / int(candidates)
    converged = False
    sweeps = 0
    for _ in range(int(iterations)):
        sweeps += 1
        largest = 0.0
        current = history[-1]
        for m in range(m_count):
            row = b[m]
            rest = image - e[m] * row
            c0 = (rest.real**2 + rest.imag**2) + (row.real**2 + row.imag**2)
            c1 = 2.0 * np.conj(rest) * row

            def entropies(t: np.ndarray, c0=c0, c1=c1) -> np.ndarray:
                # Re(c1 exp(j t)) = Re c1 cos t - Im c1 sin t: real outer products, no complex (P, K)
                return _entropy(c0[:, None] + np.outer(c1.real, np.cos(t)) - np.outer(c1.imag, np.sin(t)))

            best_t = _model_step(c0, c1, phase[m])
            best_v = entropies(np.array([best_t]))[0]
            if not best_v < current:
                # the model's step did not lower the entropy: the exact search over a full turn
                tried = phase[m] + steps
                values = entropies(tried)
                k = int(np.argmin(values))
                best_t, best_v = tried[k], values[k]
                lo, hi = values[k - 1], values[(k + 1) % len(steps)]
                curvature = lo - 2.0 * best_v + hi
                if curvature > 0:
                    refined = best_t + 0.5 * steps[1] * (lo - hi) / curvature
                    v = entropies(np.array([refined]))[0]
                    if v < best_v:
                        best_t, best_v = refined, v
            if best_v < current:
                moved = abs(float(np.angle(np.exp(1j * (best_t - phase[m])))))
                largest = max(largest, moved)
                phase[m] = best_t
                e[m] = np.exp(1j * best_t)
                image = rest + e[m] * row
                current = best_v
        history.append(float(_entropy(np.abs(image[:, None]) ** 2)[0]))
        if largest <= tol_rad:
            converged = True
            break
    info = {
        "entropy": history,
        "sweeps": sweeps,
        "converged": converged,
        "time_s": time.perf_counter() - t0,
    }
    return _centred(phase), info


def phase_gradient_phase(
    basis: np.ndarray,
    iterations: int = 30,
    *,
    n_pixels: int = 32,
    min_separation_px: int = 2,
    floor_db: float = -10.0,
    tol_rad: float = 1e-3,
    init_phase_rad: np.ndarray | None = None,
) -> tuple[np.ndarray, dict]:
    """Per-position phases by phase-gradient autofocus adapted to a basis of sub-images.

    Each iteration forms the image, picks its brightest local maxima (at most ``n_pixels``, at
    least ``min_separation_px`` apart: the dominant scatterers), and sets
    phi_m = angle(sum_p conj(B_m(p)) image(p)) over them: every position's contribution turned
    into phase with what the scatterers' pixels hold. That is one step of the eigenvector (maximum
    likelihood) estimator of PGA on the histories B[:, p], weighted by the scatterers' brightness,
    and it never lowers the energy at the chosen pixels. The pixels are chosen again on each
    sharper image, as PGA narrows its window.

    Parameters
    ----------
    basis, tol_rad, init_phase_rad : as :func:`minimum_entropy_phase`.
    iterations : at most this many (>= 1); stops earlier when no phase moved by more than
        ``tol_rad``.
    n_pixels : the most scatterer pixels used (>= 1).
    min_separation_px : local maxima closer than this (pixels, Chebyshev) count as one scatterer.
    floor_db : only maxima within this many dB (intensity) of the brightest count: the dominant
        scatterers, not their sidelobes (-10: on point scenes with 20 dB SNR, the estimate's error
        was 3-6 x smaller than with -20).

    Returns
    -------
    phase_rad : as :func:`minimum_entropy_phase`.
    info : dict with ``iterations`` (run), ``converged`` (bool), ``n_pixels`` (used in the last
        iteration), ``energy_fraction`` (float: the share of the image's energy at those pixels,
        uncorrected then after each iteration), ``time_s``.
    """
    if int(iterations) < 1:
        raise TwinFocusError(f"iterations must be >= 1, got {iterations}")
    if int(n_pixels) < 1:
        raise TwinFocusError(f"n_pixels must be >= 1, got {n_pixels}")
    if int(min_separation_px) < 1:
        raise TwinFocusError(f"min_separation_px must be >= 1, got {min_separation_px}")
    if not (np.isfinite(floor_db) and floor_db <= 0):
        raise TwinFocusError(f"floor_db must be a number <= 0 (dB below the brightest), got {floor_db}")
    if not (np.isfinite(tol_rad) and tol_rad >= 0):
        raise TwinFocusError(f"tol_rad must be a non-negative number, got {tol_rad}")
    t0 = time.perf_counter()
    shape = np.asarray(basis).shape[1:]
    b = _unit_basis(basis)
    phase = _initial_phase(init_phase_rad, b.shape[0])
    fractions = []
    converged = False
    runs = 0
    pixels = np.zeros(0, dtype=np.int64)
    for _ in range(int(iterations)):
        runs += 1
        image = np.exp(1j * phase) @ b
        intensity = np.abs(image) ** 2
        pixels = _scatterer_pixels(
            intensity.reshape(shape), int(n_pixels), int(min_separation_px), 10.0 ** (floor_db / 10.0)
        )
        fractions.append(float(intensity[pixels].sum() / max(intensity.sum(), 1e-300)))
        products = np.conj(b[:, pixels]) @ image[pixels]  # (M,)
        # a position with no part in the chosen pixels keeps its phase
        new = np.where(np.abs(products) > 0, np.angle(products), phase)
        # the common phase is free: measure the move without it
        moved = np.abs(np.angle(np.exp(1j * (new - phase - np.angle(np.exp(1j * (new - phase)).mean())))))
        phase = new
        if moved.max() <= tol_rad:
            converged = True
            break
    final = np.abs(np.exp(1j * phase) @ b) ** 2
    fractions.append(float(final[pixels].sum() / max(final.sum(), 1e-300)))
    info = {
        "iterations": runs,
        "converged": converged,
        "n_pixels": int(pixels.size),
        "energy_fraction": fractions,
        "time_s": time.perf_counter() - t0,
    }
    return _centred(phase), info


def _scatterer_pixels(intensity: np.ndarray, n: int, separation: int, floor: float = 0.0) -> np.ndarray:
    """Flat indices of the ``n`` brightest local maxima of intensity (H, W), none within
    ``separation`` pixels of a brighter one and none below ``floor`` x the brightest; the
    brightest pixel when there is none."""
    from scipy.ndimage import maximum_filter

    size = 2 * separation + 1
    peaks = intensity == maximum_filter(intensity, size=size, mode="constant", cval=-np.inf)
    peaks &= (intensity > 0) & (intensity >= floor * intensity.max())
    flat = np.flatnonzero(peaks.ravel())
    if flat.size == 0:
        return np.array([int(np.argmax(intensity))])
    order = np.argsort(intensity.ravel()[flat])[::-1]
    return flat[order[:n]]


def _initial_phase(init_phase_rad: np.ndarray | None, m_count: int) -> np.ndarray:
    if init_phase_rad is None:
        return np.zeros(m_count)
    phase = np.array(init_phase_rad, dtype=np.float64)
    if phase.shape != (m_count,):
        raise TwinFocusError(f"init_phase_rad must have one value per radar position ({m_count}), got {phase.shape}")
    if not np.isfinite(phase).all():
        raise TwinFocusError("init_phase_rad holds NaN or inf")
    return phase


def _centred(phase: np.ndarray) -> np.ndarray:
    """The phases with their common phase taken out, wrapped to [-pi, pi): float64 (M,)."""
    phase = phase - np.angle(np.exp(1j * phase).mean())
    return np.angle(np.exp(1j * phase))


#: below this many resolution cells of the region per radar position the image holds too little
#: to pin every phase, and a reference-free estimate can sharpen the image away from the truth: the
#: default scene (3.1) gains (target SSIM 0.78 -> 0.90 with either method), a two-point scene with
#: 2 cells per position lost with minimum entropy at every image size tried (docs/reference_free.md)
MIN_CELLS_PER_POSITION = 2.5


def resolution_cell_m(positions_m: np.ndarray, grid, wavelength_m: float) -> tuple[float, float]:
    """The scan's resolution cell at the region (an :class:`~twinfocus.imaging.grid.ImageGrid`), metres,
    (across y, across x): lambda R / (2 L) on each axis, L the aperture's extent there (all
    channels of ``positions_m``, float (M, K, 3) phase centres, metres; at least half a
    wavelength), R the range from the aperture's centre to the region's."""
    p = np.asarray(positions_m, dtype=np.float64).reshape(-1, 3)
    r = float(np.linalg.norm(np.asarray(grid.centre_m, dtype=np.float64) - p.mean(axis=0)))
    cell_y, cell_x = (
        float(wavelength_m) * r / (2.0 * max(float(np.ptp(p[:, axis])), float(wavelength_m) / 2.0)) for axis in (1, 0)
    )
    return cell_y, cell_x


def resolution_cells(positions_m: np.ndarray, grid, wavelength_m: float) -> float:
    """How many resolution cells the region (an :class:`~twinfocus.imaging.grid.ImageGrid`) holds for the
    aperture of ``positions_m`` (float (M, K, 3) phase centres, metres): its width over
    :func:`resolution_cell_m` on each axis; at most the region's pixels. Dimensionless."""
    cell_y, cell_x = resolution_cell_m(positions_m, grid, wavelength_m)
    cells = 1.0
    for cell, (lo, hi, n) in ((cell_x, (grid.x0, grid.x1, grid.width)), (cell_y, (grid.y0, grid.y1, grid.height))):
        cells *= min(float(n), max(1.0, abs(hi - lo) / cell))
    return cells


def cells_summary(method: str, cells: float, n_positions: int) -> dict:
    """What a reference-free estimate of ``n_positions`` phases on a region of ``cells``
    resolution cells (:func:`resolution_cells`) reports: ``cells_per_position`` and, below
    :data:`MIN_CELLS_PER_POSITION`, a ``warning`` that names ``method`` (the confidence report
    repeats it). The same for every reference-free method: each fits one phase per position to one
    image."""
    per_position = float(cells) / max(int(n_positions), 1)
    out: dict = {"cells_per_position": round(per_position, 3)}
    if per_position < MIN_CELLS_PER_POSITION:
        out["warning"] = (
            f"the region holds {per_position:.1f} resolution cells per radar position (< {MIN_CELLS_PER_POSITION}): "
            f"too few to pin every phase, so {method} may have sharpened the image away from the truth; "
            "widen the region or use a twin"
        )
    return out


#: the reference-free methods by their ``--method`` name
METHODS: dict[str, Callable[..., tuple[np.ndarray, dict]]] = {
    "entropy": minimum_entropy_phase,
    "pga": phase_gradient_phase,
}


def reference_free_autofocus(basis: np.ndarray, method: str, cells: float | None = None) -> AutofocusResult:
    """One of :data:`METHODS` on a region's basis (M, H, W), with its defaults, as the pipeline's
    :class:`~twinfocus.focus.autofocus.AutofocusResult`: ``loss_history`` is the entropy after each
    sweep (``entropy``) or the share of the image's energy outside the scatterers' pixels after
    each iteration (``pga``); ``extra["reference_free"]`` the method's info, with
    ``cells_per_position`` and a ``warning`` below :data:`MIN_CELLS_PER_POSITION` when ``cells``
    (the region's :func:`resolution_cells`) is given."""
    if method not in METHODS:
        raise TwinFocusError(f"unknown reference-free method {method!r}; choose one of {', '.join(METHODS)}")
    t0 = time.perf_counter()
    phase, info = METHODS[method](basis)
    loss = np.asarray(info["entropy"] if method == "entropy" else 1.0 - np.asarray(info["energy_fraction"]))
    summary = {k: v for k, v in info.items() if k not in ("entropy", "energy_fraction")}
    summary["loss_first_last"] = [float(loss[0]), float(loss[-1])]
    if cells is not None:
        summary.update(cells_summary(method, cells, np.asarray(basis).shape[0]))
    return AutofocusResult(
        phase, loss, form_image(basis, phase), time.perf_counter() - t0, method, {"reference_free": summary}
    )
