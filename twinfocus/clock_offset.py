"""The radar-camera clock offset, found from the scan itself (``convert --align scan``,
``focus --clock-search``).

A hand moving at v puts every position ``v * dt`` off along its direction of motion when the
radar's time stamps are ``dt`` off the camera's; on a zig-zag the error flips sign with each leg,
which no per-position phase of the ladder fits well. Two estimates, both plain functions on arrays:

- **range history** (:func:`range_history_offset`): the range of the brightest static scatterer in
  each frame (peak of the range-compressed data, summed over channels) against the radar's distance
  to that scatterer along the camera's trajectory re-sampled at ``t + dt``; the scatterer's place
  and a range bias are fitted for each ``dt``, a coarse grid then a fine one around the best, the
  uncertainty from the curvature of the residual. With ``fit_rate`` the two halves of the sweep
  are fitted apart and their difference gives a clock rate (drift, s per s).
- **focus** (:func:`focus_offset`): each position re-sampled at ``t + dt`` along the scan's own
  track (its time stamps, else the order of its positions), ``dt`` chosen by the sharpness of the
  back-projected reference region.

Convention: ``dt`` is what is *added to the radar's time stamps* to put them on the camera's clock
(a radar clock running 15 ms behind the camera's gives ``dt = +0.015``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.radar import Chirp, range_compress

#: least peak-to-median ratio of the summed range profile for a scatterer to count as one
MIN_PEAK_TO_MEDIAN = 8.0
#: least change of the radar's distance to the scatterer over the sweep, in range resolutions
MIN_RANGE_SWING_CELLS = 0.02
#: ranges below this are not searched for the scatterer (DC, leakage), m
MIN_RANGE_M = 0.15
#: the fit's r.m.s. residual may be at most this share of the distance's swing over the sweep
MAX_RESIDUAL_SHARE = 0.25
#: fewest frames the range history needs
MIN_FRAMES = 20


@dataclass
class ClockEstimate:
    """A clock offset found from the data.

    offset_s : added to the radar's stamps, seconds. sigma_s : its 1-sigma uncertainty, seconds.
    rate : clock rate (s per s, radar - camera) when fitted, else None; sigma_rate likewise.
    method : ``"range_history"`` or ``"focus"``. residual_m : r.m.s. range residual (range history).
    """

    offset_s: float
    sigma_s: float
    method: str
    rate: float | None = None
    sigma_rate: float | None = None
    residual_m: float | None = None
    scatterer_m: list[float] | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        """One line for the user."""
        s = f"clock offset {self.offset_s * 1e3:+.2f} +- {self.sigma_s * 1e3:.2f} ms ({self.method.replace('_', ' ')})"
        if self.rate is not None and self.sigma_rate is not None:
            s += f", rate {self.rate * 1e6:+.0f} +- {self.sigma_rate * 1e6:.0f} ppm"
        return s


def peak_range_m(data: np.ndarray, chirp: Chirp, oversample: int = 8) -> tuple[np.ndarray, float]:
    """Range of the brightest scatterer in each frame, from range compression.

    data : complex (M, K, N) IF samples (channels summed incoherently).
    Returns (float64 (M,) metres, the peak-to-median ratio of the mean profile). The brightest bin
    of the mean profile over all frames picks the scatterer; each frame's peak is sought within
    two range resolutions of it and interpolated (parabola on the log magnitude).
    """
    data = np.asarray(data)
    if data.ndim != 3:
        raise TwinFocusError(f"data must be (M, K, N), got shape {data.shape}")
    n_fft = int(oversample) * chirp.n_samples
    prof = np.abs(range_compress(data, chirp, n_fft=n_fft, window="hann")).sum(axis=1)  # (M, n_fft)
    # DC and the antennas' leakage sit within a few centimetres of zero range
    prof[:, : max(oversample, int(np.ceil(MIN_RANGE_M / (chirp.max_range_m / n_fft))))] = 0.0
    mean = prof.mean(axis=0)
    b0 = int(np.argmax(mean))
    ratio = float(mean[b0] / max(np.median(mean), 1e-30))
    half = 2 * oversample
    lo, hi = max(b0 - half, 1), min(b0 + half + 1, n_fft - 1)
    b = lo + np.argmax(prof[:, lo:hi], axis=1)
    b = np.clip(b, 1, n_fft - 2)
    rows = np.arange(prof.shape[0])
    ym, y0, yp = (np.log(prof[rows, b + d] + 1e-30) for d in (-1, 0, 1))
    den = ym - 2 * y0 + yp
    frac = np.where(den < 0, 0.5 * (ym - yp) / np.where(den < 0, den, -1.0), 0.0)
    return (b + np.clip(frac, -0.5, 0.5)) * chirp.max_range_m / n_fft, ratio


def resample_track(times_s: np.ndarray, points_m: np.ndarray, at_s: np.ndarray) -> np.ndarray:
    """Points along a track at other times: linear between samples, clamped at the ends.

    times_s : (T,) non-decreasing; points_m : (T, ...) ; at_s : (Q,). Returns (Q, ...).
    """
    t = np.asarray(times_s, np.float64)
    p = np.asarray(points_m, np.float64)
    at = np.clip(np.asarray(at_s, np.float64), t[0], t[-1])
    i1 = np.clip(np.searchsorted(t, at, side="right"), 1, len(t) - 1)
    i0 = i1 - 1
    span = t[i1] - t[i0]
    frac = np.where(span > 0, (at - t[i0]) / np.where(span > 0, span, 1.0), 0.0)
    frac = frac.reshape(frac.shape + (1,) * (p.ndim - 1))
    return p[i0] + frac * (p[i1] - p[i0])


def _fit_scatterer(centres_m: np.ndarray, ranges_m: np.ndarray, start: np.ndarray, iters: int = 12):
    """Least squares |c_i - s| + b = r_i over s (3,) and b: (s, b, sum of squares)."""
    s, b = start.copy(), 0.0
    for _ in range(iters):
        d = centres_m - s
        dist = np.linalg.norm(d, axis=1)
        res = dist + b - ranges_m
        jac = np.concatenate([-d / np.maximum(dist, 1e-9)[:, None], np.ones((len(res), 1))], axis=1)
        step, *_ = np.linalg.lstsq(jac, -res, rcond=None)
        s, b = s + step[:3], b + step[3]
        if np.abs(step).max() < 1e-9:
            break
    res = np.linalg.norm(centres_m - s, axis=1) + b - ranges_m
    return s, b, float(res @ res)


def _profile(
    frame_s: np.ndarray, ranges_m: np.ndarray, track_s: np.ndarray, track_m: np.ndarray, offsets_s: np.ndarray, start
) -> tuple[np.ndarray, list]:
    ssr, fits = np.empty(len(offsets_s)), []
    for i, dt in enumerate(offsets_s):
        c = resample_track(track_s, track_m, frame_s + dt)
        fit = _fit_scatterer(c, ranges_m, start)
        ssr[i] = fit[2]
        fits.append(fit)
    return ssr, fits


def _parabola_min(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Vertex and curvature (y'') of the parabola through the 5 points around the least y."""
    i = int(np.clip(np.argmin(y), 2, len(y) - 3))
    a, b_, _ = np.polyfit(x[i - 2 : i + 3] - x[i], y[i - 2 : i + 3], 2)
    if a <= 0:
        return float(x[int(np.argmin(y))]), 0.0
    return float(x[i] - b_ / (2 * a)), float(2 * a)


def range_history_offset(
    data: np.ndarray,
    chirp: Chirp,
    frame_s: np.ndarray,
    track_s: np.ndarray,
    track_m: np.ndarray,
    max_offset_s: float = 0.5,
    fit_rate: bool = False,
) -> ClockEstimate:
    """The clock offset from the brightest static scatterer's range history.

    data : complex (M, K, N) IF samples, one frame per radar position.
    frame_s : float64 (M,) the frames' stamps on the camera's clock as first aligned, seconds.
    track_s, track_m : the radar's trajectory (camera poses through the extrinsics), (T,) seconds
        and (T, 3) metres, on the camera's clock.
    max_offset_s : the offsets searched, +- this around the first alignment.
    Returns a :class:`ClockEstimate`; raises TwinFocusError (one line) when the data cannot tell.
    """
    frame_s = np.asarray(frame_s, np.float64)
    track_s, track_m = np.asarray(track_s, np.float64), np.asarray(track_m, np.float64)
    if len(frame_s) < MIN_FRAMES:
        raise TwinFocusError(
            f"clock offset: {len(frame_s)} frames are too few to find the clock from the data (need {MIN_FRAMES}); "
            "use --align start or --time-offset-s"
        )
    ranges, ratio = peak_range_m(data, chirp)
    if ratio < MIN_PEAK_TO_MEDIAN:
        raise TwinFocusError(
            f"clock offset: no static scatterer stands out of the range profiles (peak {ratio:.1f} x the median, "
            f"need {MIN_PEAK_TO_MEDIAN:g}); use --align start or --time-offset-s"
        )
    centres = resample_track(track_s, track_m, frame_s)
    start = centres.mean(axis=0) + np.array([0.0, 0.0, float(np.median(ranges))])
    s0, _, _ = _fit_scatterer(centres, ranges, start)
    dist = np.linalg.norm(centres - s0, axis=1)
    if np.ptp(dist) < MIN_RANGE_SWING_CELLS * chirp.range_resolution_m or np.ptp(frame_s) < 10 * max_offset_s / 30:
        raise TwinFocusError(
            f"clock offset: the sweep is too short (the distance to the scatterer changes by {np.ptp(dist) * 1e3:.1f} mm) "
            "to find the clock from the data; use --align start or --time-offset-s"
        )
    est = _offset_of(frame_s, ranges, track_s, track_m, max_offset_s, s0)
    if est.residual_m is not None and est.residual_m > MAX_RESIDUAL_SHARE * np.ptp(dist):
        raise TwinFocusError(
            f"clock offset: the brightest scatterer's range does not follow the trajectory (r.m.s. residual "
            f"{est.residual_m * 1e3:.1f} mm of a {np.ptp(dist) * 1e3:.1f} mm swing); use --align start or --time-offset-s"
        )
    est.scatterer_m = [float(v) for v in est.scatterer_m or []]
    if fit_rate:
        half = len(frame_s) // 2
        a = _offset_of(frame_s[:half], ranges[:half], track_s, track_m, max_offset_s, s0, around=est.offset_s)
        b = _offset_of(frame_s[half:], ranges[half:], track_s, track_m, max_offset_s, s0, around=est.offset_s)
        lever = float(frame_s[half:].mean() - frame_s[:half].mean())
        est.rate = (b.offset_s - a.offset_s) / lever
        est.sigma_rate = float(np.hypot(a.sigma_s, b.sigma_s) / lever)
    return est


def _offset_of(frame_s, ranges, track_s, track_m, max_offset_s, start, around: float = 0.0) -> ClockEstimate:
    coarse = around + np.arange(-max_offset_s, max_offset_s + 1e-12, 0.005)
    ssr, _ = _profile(frame_s, ranges, track_s, track_m, coarse, start)
    best = float(coarse[int(np.argmin(ssr))])
    fine = best + np.arange(-0.008, 0.008 + 1e-12, 0.0005)
    ssr, fits = _profile(frame_s, ranges, track_s, track_m, fine, start)
    dt, curv = _parabola_min(fine, ssr)
    n = len(ranges)
    s, _, smin = fits[int(np.argmin(ssr))]
    var = smin / max(n - 5, 1)
    sigma = float(np.sqrt(2 * var / curv)) if curv > 0 else float("inf")
    return ClockEstimate(dt, sigma, "range_history", residual_m=float(np.sqrt(smin / n)), scatterer_m=list(s))


def position_times_s(timestamps_ns: np.ndarray | None, n_positions: int, period_s: float | None = None) -> np.ndarray:
    """Each scan position's time, seconds from the first: its stamp, else its order (a scan stores
    its positions in the order taken) times ``period_s`` (default 1: offsets then count positions)."""
    if timestamps_ns is not None:
        t = np.asarray(timestamps_ns, np.int64)
        return (t - t[0]).astype(np.float64) * 1e-9
    return np.arange(n_positions, dtype=np.float64) * (1.0 if period_s is None else float(period_s))


def shift_positions(positions_m: np.ndarray, times_s: np.ndarray, offset_s: float) -> np.ndarray:
    """Positions (M, K, 3) re-sampled along the scan's own track at ``times_s + offset_s``."""
    return resample_track(times_s, positions_m, np.asarray(times_s, np.float64) + offset_s)


def sharpness(image: np.ndarray) -> float:
    """Normalised intensity sharpness sum(|I|^4) / sum(|I|^2)^2 (larger = more focused)."""
    p = np.abs(np.asarray(image)) ** 2
    return float((p * p).sum() / max(p.sum() ** 2, 1e-300))


def focus_offset(
    form_image: Callable[[np.ndarray], np.ndarray],
    positions_m: np.ndarray,
    times_s: np.ndarray,
    max_offset_s: float,
    coarse_steps: int = 13,
    score: Callable[[np.ndarray], float] = sharpness,
) -> tuple[ClockEstimate, list[tuple[float, float]]]:
    """The offset whose re-sampled positions focus the reference best.

    form_image : positions (M, K, 3) -> the reference region's image (any shape).
    times_s : (M,) each position's time (:func:`position_times_s`).
    Coarse grid of ``coarse_steps`` offsets over +- ``max_offset_s``, then 7 around the best at a
    sixth of the step, the vertex of a parabola through the best. Returns (estimate, the
    (offset, score) pairs tried). sigma_s is the fine step over sqrt(12) (the grid's resolution).
    """
    tried: dict[float, float] = {}

    def cost(dt: float) -> float:
        dt = round(float(dt), 9)
        if dt not in tried:
            tried[dt] = -score(form_image(shift_positions(positions_m, times_s, dt)))
        return tried[dt]

    coarse = np.linspace(-max_offset_s, max_offset_s, int(coarse_steps))
    step = float(coarse[1] - coarse[0])
    best = float(coarse[int(np.argmin([cost(v) for v in coarse]))])
    for _ in range(2):
        step /= 6
        fine = best + step * np.arange(-3, 4)
        vals = np.array([cost(v) for v in fine])
        best, _ = _parabola_min(fine, vals)
        best = float(np.clip(best, fine[0], fine[-1]))
    cost(best)
    if tried[round(best, 9)] > min(tried.values()):  # the vertex fell off the sampled best
        best = min(tried, key=tried.__getitem__)
    pairs = sorted((k, -v) for k, v in tried.items())
    return ClockEstimate(best, step / np.sqrt(12), "focus"), pairs


def template_match(template: np.ndarray) -> Callable[[np.ndarray], float]:
    """A score: correlation of an image's amplitude with ``template``'s (same shape), in [-1, 1]."""
    b = np.abs(np.asarray(template, np.complex128)).ravel()
    b = b - b.mean()
    b /= max(float(np.linalg.norm(b)), 1e-300)

    def score(image: np.ndarray) -> float:
        a = np.abs(np.asarray(image)).ravel().astype(np.float64)
        a = a - a.mean()
        return float(a @ b / max(float(np.linalg.norm(a)), 1e-300))

    return score


def search_scan_clock(
    scan,
    reference_roi,
    size: int,
    bp_options: dict | None = None,
    max_offset_s: float = 0.15,
    template=None,
    step_s: float = 0.005,
    fine_size: int | None = None,
):
    """``focus --clock-search``: a converted scan's positions re-sampled along its own track at the
    offset that focuses the reference region best.

    scan : :class:`~twinfocus.scan.Scan`; reference_roi : (X0, X1, Y0, Y1, Z) metres; size : pixels
    per side of the coarse search's reference image; fine_size : of the fine search's (+- 1.2
    coarse steps around the coarse best; default ``size``). Without time stamps the offset counts
    positions (``max_offset_s`` / 0.1 s of them, the MMWCAS frame period). template : ``n ->`` the
    reference's image on the n x n grid (a twin's), matched by amplitude; None: the image's
    sharpness (weaker on a speckled object). step_s : the coarse grid's step (the match peaks
    within about the time a hand takes to cross a resolution cell, ~10 ms: keep it below that).
    Returns (the scan with the positions moved, a record for metrics.json).
    """
    from dataclasses import replace

    from twinfocus.backprojection import backproject
    from twinfocus.grid import ImageGrid

    if reference_roi is None:
        raise TwinFocusError("--clock-search needs --reference-roi (the offset is chosen by the reference's focus)")
    stamped = scan.timestamps_ns is not None
    times = position_times_s(scan.timestamps_ns, scan.n_positions)
    limit = max_offset_s if stamped else max_offset_s / 0.1
    step = step_s if stamped else step_s / 0.1
    bp = dict(bp_options or {})

    def stage(n: int):
        grid = ImageGrid.from_roi(reference_roi, n)
        tpl = None if template is None else template(n)
        score = sharpness if tpl is None else template_match(tpl)

        def image(positions_m: np.ndarray) -> np.ndarray:
            return backproject(scan.data, positions_m, scan.chirp, grid, **bp)

        return image, score

    image, score = stage(size)
    steps = 2 * int(np.ceil(limit / step)) + 1
    coarse, _ = focus_offset(image, scan.positions, times, limit, coarse_steps=steps, score=score)
    fine_n = int(fine_size or size)
    image, score = stage(fine_n)
    shifted = shift_positions(scan.positions, times, coarse.offset_s)
    span = 1.2 * step
    fine, tried = focus_offset(image, shifted, times, span, coarse_steps=7, score=score)
    # shifting twice along the same track is one shift of the sum (linear re-sampling, inside the track)
    offset = coarse.offset_s + fine.offset_s
    record = {
        **fine.to_dict(),
        "offset_s": offset,
        "unit": "s" if stamped else "positions",
        "searched": [-limit, limit],
        "score": "sharpness" if template is None else "template_match",
        "score_at_zero": score(image(scan.positions)),
        "score_at_offset": max(v for _, v in tried),
        "image_size": [int(size), fine_n],
    }
    return replace(scan, positions=shift_positions(scan.positions, times, offset)), record
