"""The radar-camera clock offset, found from the scan itself (``convert --align scan``,
``focus --clock-search``).

A hand moving at v puts every position ``v * dt`` off along its direction of motion when the
radar's time stamps are ``dt`` off the camera's; on a zig-zag the error flips sign with each leg,
which no per-position phase of the ladder fits well. Two estimates, both plain functions on arrays:

- **range history** (:func:`range_history_offset`): the range of the brightest static scatterer in
  each frame (peak of the range-compressed data, summed over channels) against the radar's distance
  to that scatterer along the camera's trajectory (its jitter smoothed, :func:`smooth_track`)
  re-sampled at ``t + dt``; the scatterer's place and a range bias are fitted for each ``dt``, a
  coarse grid then a parabola through a fine one around the best. The uncertainty is the spread
  of that vertex over block resamplings of the frames: the peak mixes several scatterers and its
  range errors run over a few frames, which the residual's curvature alone does not see. With
  ``fit_rate`` the two halves of the sweep are fitted apart and their difference gives a clock
  rate (drift, s per s), where the sweep is long enough to show one; else it is held at 0.
- **focus** (:func:`focus_offset`, :func:`refine_offset`): each position re-sampled at ``t + dt``
  -- along the scan's own track (:func:`along_track`: its time stamps, else the order of its
  positions; ``focus --clock-search``), or on the camera's trajectory (:func:`on_track`: its poses
  through the turns; convert's second stage, :func:`refine_by_focus`, over the range history's
  +- 3 sigma, on the brightest region found in the scan) -- ``dt`` chosen by the focus of the
  back-projected region (a template's match, or its sharpness).

Convention: ``dt`` is what is *added to the radar's time stamps* to put them on the camera's clock
(a radar clock running 15 ms behind the camera's gives ``dt = +0.015``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, replace

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.metrics import image_sharpness
from twinfocus.radar.fmcw import Chirp, range_compress

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
#: a step between consecutive positions longer than this many times the median step ends a leg
#: (a turn between columns where no frame was kept, a pause, a run of lost frames)
LEG_BREAK = 3.0
#: poses of the line each camera pose is replaced by before the range history re-samples the track
SMOOTH_POSES = 5
#: the range history's fine search: offsets FINE_STEP_S apart over +- FINE_HALF_S around the coarse best
FINE_HALF_S = 0.03
FINE_STEP_S = 0.002
#: resamplings of the range history that give its offset's sigma
BOOTSTRAP_REPLICATES = 100
#: the largest drift two free-running clocks show (crystals of +- 50 ppm each), s per s: a rate is
#: fitted only over a sweep long enough for this much drift to stand out of the offset's sigma
MAX_CLOCK_RATE = 1e-4


@dataclass
class ClockEstimate:
    """A clock offset found from the data.

    offset_s : added to the radar's stamps, seconds. sigma_s : its 1-sigma uncertainty, seconds.
    rate : clock rate (s per s, radar - camera) when fitted, else None; sigma_rate likewise; 0 with
    ``rate_note`` saying why where the sweep is too short to show one.
    method : ``"range_history"`` or ``"focus"``. residual_m : r.m.s. range residual (range history).
    """

    offset_s: float
    sigma_s: float
    method: str
    rate: float | None = None
    sigma_rate: float | None = None
    residual_m: float | None = None
    scatterer_m: list[float] | None = None
    rate_note: str | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        """One line for the user."""
        s = f"clock offset {self.offset_s * 1e3:+.2f} +- {self.sigma_s * 1e3:.2f} ms ({self.method.replace('_', ' ')})"
        if self.rate is not None and self.sigma_rate is not None:
            s += f", rate {self.rate * 1e6:+.0f} +- {self.sigma_rate * 1e6:.0f} ppm"
        elif self.rate_note:
            s += f", rate {self.rate_note} (held at 0)"
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
    s, b, ssr = _fit_scatterers(centres_m[None], ranges_m[None], start, iters)
    return s[0], float(b[0]), float(ssr[0])


def _fit_scatterers(centres_m: np.ndarray, ranges_m: np.ndarray, start: np.ndarray, iters: int = 12):
    """:func:`_fit_scatterer` for B range histories at once (Gauss-Newton).

    centres_m : (B, n, 3) metres; ranges_m : (B, n) metres; start : (3,) metres.
    Returns (s float64 (B, 3), b (B,), sums of squares (B,)).
    """
    n_b = centres_m.shape[0]
    s, b = np.tile(np.asarray(start, np.float64), (n_b, 1)), np.zeros(n_b)
    for _ in range(iters):
        d = centres_m - s[:, None, :]
        dist = np.linalg.norm(d, axis=2)
        res = dist + b[:, None] - ranges_m
        jac = np.concatenate([-d / np.maximum(dist, 1e-9)[..., None], np.ones(res.shape + (1,))], axis=2)
        # the pseudo-inverse, not a solve: a still radar's centres leave the fit without a unique step
        step = -(np.linalg.pinv(jac) @ res[..., None])[..., 0]
        s, b = s + step[:, :3], b + step[:, 3]
        if np.abs(step).max() < 1e-9:
            break
    res = np.linalg.norm(centres_m - s[:, None, :], axis=2) + b[:, None] - ranges_m
    return s, b, np.einsum("bn,bn->b", res, res)


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
    fit_rate : also a clock rate, from the two halves' offsets, where the sweep is long enough to
        show one (:func:`rate_needs_s`); else the rate is held at 0 and ``rate_note`` says why.
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
    h = _History(frame_s, ranges, track_s, smooth_track(track_s, track_m, track_segments(track_s, track_m)))
    est = _offset_of(h, s0, max_offset_s)
    if est.residual_m is not None and est.residual_m > MAX_RESIDUAL_SHARE * np.ptp(dist):
        raise TwinFocusError(
            f"clock offset: the brightest scatterer's range does not follow the trajectory (r.m.s. residual "
            f"{est.residual_m * 1e3:.1f} mm of a {np.ptp(dist) * 1e3:.1f} mm swing); use --align start or --time-offset-s"
        )
    est.scatterer_m = [float(v) for v in est.scatterer_m or []]
    if fit_rate:
        _fit_rate(h, s0, est, max_offset_s)
    return est


def rate_needs_s(sigma_s: float) -> float:
    """The sweep (s) over which a clock rate of :data:`MAX_CLOCK_RATE` stands at two sigma out of a
    rate fitted from the two halves' offsets, each half's offset good to about ``sigma_s`` x sqrt 2
    (half the frames), their centres half the sweep apart: sigma_rate ~ 4 sigma_s / T."""
    return 8.0 * float(sigma_s) / MAX_CLOCK_RATE


def _fit_rate(h: _History, start: np.ndarray, est: ClockEstimate, max_offset_s: float) -> None:
    """The clock rate from the two halves' offsets, in ``est``; held at 0, with ``rate_note``
    saying why, on a sweep too short to show one."""
    sweep, needs = float(np.ptp(h.frame_s)), rate_needs_s(est.sigma_s)
    if not sweep > needs:
        est.rate, est.sigma_rate = 0.0, None
        est.rate_note = f"not measurable: sweep {sweep:.1f} s, needs > {needs:.0f} s"
        return
    half = len(h.frame_s) // 2
    a, b = (
        _offset_of(replace(h, frame_s=h.frame_s[sl], ranges_m=h.ranges_m[sl]), start, max_offset_s, around=est.offset_s)
        for sl in (slice(None, half), slice(half, None))
    )
    lever = float(h.frame_s[half:].mean() - h.frame_s[:half].mean())
    est.rate = (b.offset_s - a.offset_s) / lever
    est.sigma_rate = float(np.hypot(a.sigma_s, b.sigma_s) / lever)


def track_segments(track_s: np.ndarray, track_m: np.ndarray) -> np.ndarray:
    """Bounds (S, 2) int64 [first, past-last) of the stretches of a track with no gap in them.

    track_s : (T,) seconds, non-decreasing; track_m : (T, 3) metres. A step in time, or in place,
    over :data:`LEG_BREAK` x its median (the median of the steps that move) ends a stretch: across
    such a step (a turn where the camera kept no pose, a raster's jump between columns) a position
    re-sampled from the track is a guess, not a measurement.
    """
    t = np.asarray(track_s, np.float64)
    if len(t) < 2:
        return np.array([[0, len(t)]], np.int64)
    cut = np.zeros(len(t) - 1, bool)
    for step in (np.diff(t), np.linalg.norm(np.diff(np.asarray(track_m, np.float64), axis=0), axis=1)):
        moving = step[step > 0]
        if moving.size:
            cut |= step > LEG_BREAK * float(np.median(moving))
    edges = np.concatenate([[0], np.flatnonzero(cut) + 1, [len(t)]]).astype(np.int64)
    return np.stack([edges[:-1], edges[1:]], axis=1)


def smooth_track(track_s: np.ndarray, track_m: np.ndarray, segments: np.ndarray, n: int = SMOOTH_POSES) -> np.ndarray:
    """Each pose (T, D) metres (a position, or several side by side) replaced by the least-squares line through the ``n`` poses around it
    in its stretch (:func:`track_segments`), evaluated at its time.

    Why: re-sampled linearly, a tracker's white jitter is averaged by an amount that depends on
    where between two poses a frame falls (halved midway, whole on a pose), so the range history's
    fit prefers offsets a fraction of a pose off the true one; smoothed first, the jitter left is
    nearly the same everywhere. A line, not a mean, keeps a stretch's ends in place.
    """
    t = np.asarray(track_s, np.float64)
    p = np.asarray(track_m, np.float64)
    out = p.copy()
    for a, b in segments:
        k = min(int(n), int(b - a))
        if k < 3:
            continue
        for i in range(int(a), int(b)):
            lo = min(max(i - k // 2, int(a)), int(b) - k)
            tt = t[lo : lo + k] - t[lo : lo + k].mean()
            den = float(tt @ tt)
            mean = p[lo : lo + k].mean(axis=0)
            vel = tt @ (p[lo : lo + k] - mean) / den if den > 0 else np.zeros(p.shape[1])
            out[i] = mean + (t[i] - t[lo : lo + k].mean()) * vel
    return out


@dataclass
class _History:
    """The range history and the track it is fitted to (smoothed, :func:`smooth_track`)."""

    frame_s: np.ndarray
    ranges_m: np.ndarray
    track_s: np.ndarray
    track_m: np.ndarray

    def fit(self, dt: float, start: np.ndarray):
        """The scatterer's fit (s, b, sum of squares) with the frames at ``frame_s + dt``."""
        return _fit_scatterer(resample_track(self.track_s, self.track_m, self.frame_s + dt), self.ranges_m, start)

    def ssr(self, offsets_s: np.ndarray, start: np.ndarray) -> np.ndarray:
        """The fit's sums of squares (B,) at each of the offsets (B,), fitted at once."""
        c = np.stack([resample_track(self.track_s, self.track_m, self.frame_s + dt) for dt in offsets_s])
        return _fit_scatterers(c, np.broadcast_to(self.ranges_m, c.shape[:2]), start)[2]


def _coarse_best(h: _History, start: np.ndarray, around: float, max_offset_s: float) -> float:
    """The best of offsets 5 ms apart over ``around`` +- ``max_offset_s``."""
    coarse = around + np.arange(-max_offset_s, max_offset_s + 1e-12, 0.005)
    return float(coarse[int(np.argmin(h.ssr(coarse, start)))])


def _vertex(offsets: np.ndarray, ssr: np.ndarray, reach: float = 1.0) -> float:
    """The least-squares parabola's vertex through (offsets, ssr), at most ``reach`` x the window's
    width past its ends; the least sample where the parabola has no minimum."""
    a, b_, _ = np.polyfit(offsets - offsets.mean(), ssr, 2)
    if not a > 0:
        return float(offsets[int(np.argmin(ssr))])
    wide = reach * float(offsets[-1] - offsets[0])
    return float(np.clip(offsets.mean() - b_ / (2 * a), offsets[0] - wide, offsets[-1] + wide))


def _correlation_frames(res: np.ndarray) -> float:
    """The residual's integrated correlation length in frames: 1 + 2 sum of its autocorrelation
    up to its first lag at or below zero (1 for white residuals)."""
    x = res - res.mean()
    v = float(x @ x)
    tau = 1.0
    for k in range(1, len(x) // 4):
        rho = float(x[k:] @ x[:-k]) / max(v, 1e-300)
        if rho <= 0:
            break
        tau += 2 * rho
    return tau


def _offset_of(h: _History, start: np.ndarray, max_offset_s: float, around: float = 0.0) -> ClockEstimate:
    """Coarse best, then the vertex of the parabola through the sums of squares of offsets
    :data:`FINE_STEP_S` apart over +- :data:`FINE_HALF_S` around it (the window moved onto the
    vertex twice at most); sigma by a moving-block bootstrap of the frames (blocks of twice the
    residual's correlation length)."""
    centre = _coarse_best(h, start, around, max_offset_s)
    fine = np.arange(-FINE_HALF_S, FINE_HALF_S + 1e-12, FINE_STEP_S)
    for _ in range(3):
        dt = _vertex(centre + fine, h.ssr(centre + fine, start), reach=0.0)
        if abs(dt - centre) <= FINE_HALF_S / 2:
            break
        centre = float(np.round(dt / FINE_STEP_S) * FINE_STEP_S)
    s, b, smin = h.fit(dt, start)
    res = np.linalg.norm(resample_track(h.track_s, h.track_m, h.frame_s + dt) - s, axis=1) + b - h.ranges_m
    block = max(2, int(np.ceil(2 * _correlation_frames(res))))
    sigma = _bootstrap_sigma(h, centre + fine, s, block)
    return ClockEstimate(dt, sigma, "range_history", residual_m=float(np.sqrt(smin / len(res))), scatterer_m=list(s))


def _bootstrap_sigma(h: _History, offsets: np.ndarray, start: np.ndarray, block: int) -> float:
    """Spread (s) of the fine parabola's vertex over :data:`BOOTSTRAP_REPLICATES` moving-block
    resamplings of the frames (blocks of ``block`` consecutive frames): the range history's
    errors (several scatterers in one peak, the track's jitter) run over a few frames, so frames
    resampled one by one would understate the spread. The spread is half the central 68 % of the
    vertices (a flat resampling's vertex lies far out). A fixed seed: the same data, the same sigma."""
    rng = np.random.default_rng(0)
    n = len(h.frame_s)
    block = min(block, n)
    first = rng.integers(0, n - block + 1, size=(BOOTSTRAP_REPLICATES, int(np.ceil(n / block))))
    pick = (first[:, :, None] + np.arange(block)).reshape(BOOTSTRAP_REPLICATES, -1)[:, :n]  # (B, n)
    ssr = np.empty((BOOTSTRAP_REPLICATES, len(offsets)))
    for i, dt in enumerate(offsets):  # every replicate's frames at this offset, fitted at once
        c = resample_track(h.track_s, h.track_m, h.frame_s + dt)
        ssr[:, i] = _fit_scatterers(c[pick], h.ranges_m[pick], start)[2]
    found = np.array([_vertex(offsets, row) for row in ssr])
    lo, hi = np.percentile(found, [15.87, 84.13])
    return float(hi - lo) / 2


def position_times_s(timestamps_ns: np.ndarray | None, n_positions: int, period_s: float | None = None) -> np.ndarray:
    """Each scan position's time, seconds from the first: its stamp, else its order (a scan stores
    its positions in the order taken) times ``period_s`` (default 1: offsets then count positions)."""
    if timestamps_ns is not None:
        t = np.asarray(timestamps_ns, np.int64)
        return (t - t[0]).astype(np.float64) * 1e-9
    return np.arange(n_positions, dtype=np.float64) * (1.0 if period_s is None else float(period_s))


#: least number of a leg's positions the velocity at its end is fitted over
END_FIT_POSITIONS = 9


def leg_starts(times_s: np.ndarray, positions_m: np.ndarray | None = None) -> np.ndarray:
    """Indices (L,) int64 where each leg of uninterrupted motion starts (the first is 0).

    times_s : (M,) seconds (:func:`position_times_s`); positions_m : (M, ...) metres. A leg ends
    where the step in time exceeds :data:`LEG_BREAK` x the median step (stamps), or, on positions
    counted by order (a uniform ``times_s``), where the step in place does: a scan keeps no frame
    from the turn between a zig-zag's columns, and its track has no pose there to re-sample.
    """
    t = np.asarray(times_s, np.float64)
    if len(t) < 3:
        return np.zeros(1, np.int64)
    step = np.diff(t)
    if positions_m is not None and np.ptp(step) <= 1e-9 * max(float(np.abs(step).max()), 1e-300):
        p = np.asarray(positions_m, np.float64).reshape(len(t), -1, 3).mean(axis=1)
        step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    med = float(np.median(step))
    breaks = np.flatnonzero(step > LEG_BREAK * med) + 1 if med > 0 else np.zeros(0, np.int64)
    return np.concatenate([[0], breaks]).astype(np.int64)


def _end_velocity(t: np.ndarray, p: np.ndarray, span_s: float, last: bool) -> np.ndarray:
    """Least-squares velocity (...) over a leg's end: its last (or first) positions within
    ``span_s``, at least :data:`END_FIT_POSITIONS` of them (all, on a shorter leg)."""
    n = len(t)
    if n < 2:
        return np.zeros(p.shape[1:])
    within = int(np.count_nonzero((t[-1] - t <= span_s) if last else (t - t[0] <= span_s)))
    k = min(n, max(END_FIT_POSITIONS, within))
    sl = slice(n - k, n) if last else slice(0, k)
    tt = t[sl] - t[sl].mean()
    den = float(tt @ tt)
    if den <= 0:
        return np.zeros(p.shape[1:])
    return np.tensordot(tt, p[sl] - p[sl].mean(axis=0), axes=(0, 0)) / den


def shift_positions(
    positions_m: np.ndarray, times_s: np.ndarray, offset_s: float, starts: np.ndarray | None = None
) -> np.ndarray:
    """Positions (M, ...) moved along each one's direction of motion to ``times_s + offset_s``.

    Inside a leg (:func:`leg_starts`; ``starts`` to pass them found once) the leg's own track is
    re-sampled (linear between positions); past either end of it the position goes on along the
    leg's velocity at that end (a line fitted over the end's last ``|offset_s|``, at least
    :data:`END_FIT_POSITIONS` positions), not across the turn to the next leg nor held still.
    Returns float64 (M, ...) metres.
    """
    t = np.asarray(times_s, np.float64)
    p = np.asarray(positions_m, np.float64)
    if starts is None:
        starts = leg_starts(t, p)
    bounds = [*(int(v) for v in starts), len(t)]
    out = p.copy()
    for a, b in zip(bounds[:-1], bounds[1:], strict=False):
        if b - a < 2:
            continue
        tl, pl = t[a:b], p[a:b]
        at = tl + offset_s
        moved = resample_track(tl, pl, at)
        span = abs(float(offset_s))
        for last, past in ((False, at < tl[0]), (True, at > tl[-1])):
            if past.any():
                v = _end_velocity(tl, pl, span, last)
                end, t_end = (pl[-1], tl[-1]) if last else (pl[0], tl[0])
                dt = (at[past] - t_end).reshape((-1,) + (1,) * (p.ndim - 1))
                moved[past] = end + dt * v
        out[a:b] = moved
    return out


#: the fine search's offsets: this many each side of its centre
FINE_HALF_STEPS = 6


def along_track(positions_m: np.ndarray, times_s: np.ndarray) -> Callable[[float], np.ndarray]:
    """``dt ->`` the positions (M, ...) moved to ``times_s + dt`` along the scan's own track
    (:func:`shift_positions`, its legs found once): what the searches below re-sample when no
    trajectory is at hand (``focus --clock-search``)."""
    starts = leg_starts(times_s, positions_m)
    return lambda dt: shift_positions(positions_m, times_s, dt, starts)


def on_track(track_s: np.ndarray, track_m: np.ndarray, frame_s: np.ndarray) -> Callable[[float], np.ndarray]:
    """``dt ->`` a trajectory's points (T, ...) metres re-sampled at ``frame_s + dt`` (Q,): the
    track first smoothed (:func:`smooth_track`, each stretch of :func:`track_segments` apart).

    Why smoothed: re-sampled raw, a tracker's white jitter is averaged by an amount that depends on
    where between two poses a frame falls (halved midway, whole on a pose), so the focus prefers
    offsets a fraction of a pose off the true one (on poses taken at the frames, a dip at the
    true offset itself); smoothed, the jitter left is nearly the same at every offset.
    track_s : (T,) seconds; track_m : (T, ...) metres (a pose's phase centres (T, K, 3) say).
    """
    t = np.asarray(track_s, np.float64)
    p = np.asarray(track_m, np.float64)
    centre = p.reshape(len(t), -1, 3).mean(axis=1)
    flat = p.reshape(len(t), -1)
    smooth = smooth_track(t, flat, track_segments(t, centre)).reshape(p.shape)
    frames = np.asarray(frame_s, np.float64)
    return lambda dt: resample_track(t, smooth, frames + dt)


def focus_offset(
    form_image: Callable[[np.ndarray], np.ndarray],
    positions_at: Callable[[float], np.ndarray],
    max_offset_s: float,
    coarse_steps: int = 13,
    score: Callable[[np.ndarray], float] = image_sharpness,
    centre_s: float = 0.0,
    refine: bool = True,
) -> tuple[ClockEstimate, list[tuple[float, float]]]:
    """The offset whose positions focus the reference best.

    form_image : positions (M, K, 3) -> the reference region's image (any shape).
    positions_at : ``dt ->`` the positions at offset ``dt`` (:func:`along_track`, or the
        trajectory re-sampled at the frames' stamps + ``dt``, as convert does).
    A grid of ``coarse_steps`` offsets over ``centre_s`` +- ``max_offset_s``; its best, refined
    (``refine``) by :func:`refine_offset` at a fifth of the grid's step. Returns (estimate, the
    (offset, score) pairs tried); without ``refine`` the estimate is the grid's best, sigma_s the
    step over sqrt(12).
    """
    tried: dict[float, float] = {}
    coarse = centre_s + np.linspace(-max_offset_s, max_offset_s, int(coarse_steps))
    step = float(coarse[1] - coarse[0]) if len(coarse) > 1 else float(max_offset_s)
    for v in coarse:
        _score_at(form_image, positions_at, score, v, tried)
    best = max(tried, key=tried.__getitem__)
    if not refine:
        return ClockEstimate(best, step / np.sqrt(12), "focus"), sorted(tried.items())
    return refine_offset(form_image, positions_at, best, step / 5, score)


def _score_at(form_image, positions_at, score, dt: float, tried: dict) -> float:
    dt = round(float(dt), 9)
    if dt not in tried:
        tried[dt] = float(score(form_image(positions_at(dt))))
    return tried[dt]


def _peak_span(ys: np.ndarray, least: int = 5) -> tuple[int, int]:
    """The run of samples around the best that stand in the upper half of the scores' range,
    widened to ``least`` samples: (lo, hi) slice bounds."""
    k = int(np.argmax(ys))
    cut = ys.min() + 0.5 * (ys.max() - ys.min())
    lo, hi = k, k + 1
    while lo > 0 and ys[lo - 1] >= cut:
        lo -= 1
    while hi < len(ys) and ys[hi] >= cut:
        hi += 1
    while hi - lo < min(least, len(ys)):
        if lo > 0 and (hi >= len(ys) or ys[lo - 1] >= ys[hi]):
            lo -= 1
        else:
            hi += 1
    return lo, hi


def refine_offset(
    form_image: Callable[[np.ndarray], np.ndarray],
    positions_at: Callable[[float], np.ndarray],
    centre_s: float,
    step_s: float,
    score: Callable[[np.ndarray], float] = image_sharpness,
) -> tuple[ClockEstimate, list[tuple[float, float]]]:
    """The vertex of the least-squares parabola through the scores of 2 x
    :data:`FINE_HALF_STEPS` + 1 offsets ``step_s`` apart around ``centre_s``, the window moved onto
    the vertex (twice at most) when it lies more than two steps off its centre.

    One parabola over the peak's upper half (at least 5 samples), not the best sample: near focus the score is bumpy on the
    scale of a frame (a tracker's jitter re-sampled at a fraction of a frame averages neighbouring
    errors, sharpening the image a little off the true offset), while the peak's breadth, the time
    a hand takes to cross a resolution cell, is what places it. sigma_s from the fit's covariance
    (at least the step over sqrt(12)). Returns (estimate, the (offset, score) pairs tried).
    """
    tried: dict[float, float] = {}
    centre, step = float(centre_s), float(step_s)
    best, sigma = centre, float("inf")
    for _ in range(3):
        xs = centre + step * np.arange(-FINE_HALF_STEPS, FINE_HALF_STEPS + 1)
        ys = np.array([_score_at(form_image, positions_at, score, v, tried) for v in xs])
        lo, hi = _peak_span(ys)
        (qa, qb, _), cov = np.polyfit((xs[lo:hi] - centre) / step, ys[lo:hi], 2, cov=True)
        if not qa < 0:  # no peak inside: the best sample
            best, sigma = float(xs[int(np.argmax(ys))]), float("inf")
            break
        u = -qb / (2 * qa)
        jac = np.array([qb / (2 * qa * qa), -1 / (2 * qa), 0.0])
        best = centre + step * float(np.clip(u, -FINE_HALF_STEPS, FINE_HALF_STEPS))
        sigma = step * float(np.sqrt(max(float(jac @ cov @ jac), 0.0)))
        if abs(u) <= 2:
            break
        centre = centre + step * float(np.round(np.clip(u, -FINE_HALF_STEPS, FINE_HALF_STEPS)))
    sigma = max(sigma, step / np.sqrt(12))
    return ClockEstimate(float(best), float(sigma), "focus"), sorted(tried.items())


#: the template match's best over the image's shifts within this many pixels each way: it
#: scores the reference's focus, not its place (a clock offset on unequal legs moves the image as a
#: whole, the ladder's phase ramp puts it back; a match held in place picks the offset of best place)
MATCH_SHIFT_PX = 2


def template_match(template: np.ndarray, max_shift_px: int = MATCH_SHIFT_PX) -> Callable[[np.ndarray], float]:
    """A score: the best correlation, over whole-pixel shifts within ``max_shift_px`` each way, of an
    image's amplitude with ``template``'s (same (H, W) shape) on their overlap, in [-1, 1]."""
    b = np.abs(np.asarray(template, np.complex128))
    h, w = b.shape
    s = int(max_shift_px)
    shifts = [(dy, dx) for dy in range(-s, s + 1) for dx in range(-s, s + 1)]

    def corr(x: np.ndarray, y: np.ndarray) -> float:
        x, y = x - x.mean(), y - y.mean()
        return float((x * y).sum() / max(float(np.sqrt((x * x).sum() * (y * y).sum())), 1e-300))

    def score(image: np.ndarray) -> float:
        a = np.abs(np.asarray(image)).astype(np.float64)
        best = -1.0
        for dy, dx in shifts:
            ia = slice(max(dy, 0), h + min(dy, 0)), slice(max(dx, 0), w + min(dx, 0))
            ib = slice(max(-dy, 0), h + min(-dy, 0)), slice(max(-dx, 0), w + min(-dx, 0))
            best = max(best, corr(a[ia], b[ib]))
        return best

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

    scan : :class:`~twinfocus.radar.scan.Scan`; reference_roi : (X0, X1, Y0, Y1, Z) metres; size : pixels
    per side of the coarse search's reference image; fine_size : of the fine search's (+- 1.2
    coarse steps around the coarse best; default ``size``). Without time stamps the offset counts
    positions (``max_offset_s`` / 0.1 s of them, the MMWCAS frame period). template : ``n ->`` the
    reference's image on the n x n grid (a twin's), matched by amplitude; None: the image's
    sharpness (weaker on a speckled object). step_s : the coarse grid's step (the match peaks
    within about the time a hand takes to cross a resolution cell, ~10 ms: keep it below that).
    Returns (the scan with the positions moved, a record for metrics.json: the offset, its sigma,
    the score, the images formed and the search's seconds).
    """
    import time

    from twinfocus.imaging.backprojection.numba_backend import backproject  # lazy: numba (+0.5 s at import)

    t_start = time.perf_counter()
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
        score = image_sharpness if tpl is None else template_match(tpl)

        def image(positions_m: np.ndarray) -> np.ndarray:
            return backproject(scan.data, positions_m, scan.chirp, grid, **bp)

        return image, score

    image, score = stage(size)
    steps = 2 * int(np.ceil(limit / step)) + 1
    moved = along_track(scan.positions, times)
    coarse, _ = focus_offset(image, moved, limit, coarse_steps=steps, score=score, refine=False)
    fine_n = int(fine_size or size)
    image, score = stage(fine_n)
    # a fifth of the coarse step, over +- 1.2 coarse steps
    fine, tried = refine_offset(image, moved, coarse.offset_s, step / 5, score)
    offset = fine.offset_s
    record = {
        **fine.to_dict(),
        "offset_s": offset,
        "unit": "s" if stamped else "positions",
        "searched": [-limit, limit],
        "score": "sharpness" if template is None else "template_match",
        "score_at_zero": score(image(scan.positions)),
        "score_at_offset": score(image(moved(offset))),
        "images_formed": steps + len(tried) + 2,
        "seconds": time.perf_counter() - t_start,
        "image_size": [int(size), fine_n],
    }
    return replace(scan, positions=moved(offset)), record


#: convert's focus stage (:func:`refine_by_focus`): the range history's offset +- this many of its
#: sigmas (within these bounds, s) in steps of FOCUS_STEP_S, then 13 offsets a fifth of that apart
FOCUS_SIGMAS = 3.0
FOCUS_HALF_BOUNDS_S = (0.01, 0.15)
FOCUS_STEP_S = 0.005
#: ... scored by the sharpness of an image FOCUS_SIZE pixels a side of a box FOCUS_BOX_M wide
#: around the brightest pixel of a plane at the imaging range over the aperture (FIND_SIZE pixels a side)
FOCUS_SIZE = 32
FOCUS_BOX_M = 0.06
FIND_SIZE = 48


#: what the focus stage scored, for its lines: (score, a region given) -> words
FOCUS_SCORE_WORDS = {
    ("template_match", True): "the reference region's template match",
    ("sharpness", True): "the reference region's sharpness",
    ("sharpness", False): "the brightest region's sharpness",
}


def brightest_box(data: np.ndarray, positions_m: np.ndarray, chirp: Chirp, z_m: float, bp_options: dict | None = None):
    """A box (X0, X1, Y0, Y1, Z) metres, :data:`FOCUS_BOX_M` wide, around the brightest pixel of
    the image at depth ``z_m`` over the aperture's x/y extent (:data:`FIND_SIZE` pixels a side).

    data : complex (M, K, N); positions_m : float (M, K, 3) metres. No region from the user: what
    convert's focus stage sharpens is whatever the scene holds brightest at the imaging range.
    """
    from twinfocus.imaging.backprojection.numba_backend import backproject  # lazy: numba (+0.5 s at import)

    c = np.asarray(positions_m, np.float64).reshape(-1, 3)
    lo, hi = c[:, :2].min(axis=0), c[:, :2].max(axis=0)
    grid = ImageGrid(float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]), float(z_m), FIND_SIZE, FIND_SIZE)
    energy = np.abs(backproject(data, positions_m, chirp, grid, **dict(bp_options or {}))) ** 2
    iy, ix = np.unravel_index(int(np.argmax(energy)), energy.shape)
    x, y, h = float(grid.x_m[ix]), float(grid.y_m[iy]), FOCUS_BOX_M / 2
    return (x - h, x + h, y - h, y + h, float(z_m))


def tracker_floor_s(track_s: np.ndarray, track_m: np.ndarray) -> float:
    """The time (s) the hand takes to move the tracker's jitter along the sweep: the least sigma
    the focus stage claims. Why: the tracker's errors move the sharpest image along the sweep as a
    whole by about their own size (bench_clock's draws: 0.1-0.7 mm at 0.4-0.6 mm of jitter; an
    emulated 0.06 m/s sweep with 0.5 mm ended 8 ms off), which no score's curve shows.

    track_s : (T,) seconds; track_m : (T, 3) metres (or (T, K, 3): their mean). The jitter per
    axis is the r.m.s. of the track less its smoothing (:func:`smooth_track`), scaled for the
    line's fit; the speed the median of the smoothed track's moving steps.
    """
    t = np.asarray(track_s, np.float64)
    p = np.asarray(track_m, np.float64).reshape(len(t), -1, 3).mean(axis=1)
    smooth = smooth_track(t, p, track_segments(t, p))
    jitter = float(np.sqrt(np.mean((p - smooth) ** 2) / (1 - 2 / SMOOTH_POSES)))
    dt = np.diff(t)
    v = np.linalg.norm(np.diff(smooth, axis=0), axis=1)[dt > 0] / dt[dt > 0]
    speed = float(np.median(v[v > 0])) if np.any(v > 0) else 0.0
    return jitter / speed if speed > 0 else float("inf")


def _indistinct_s(tried: list[tuple[float, float]], centre_s: float) -> float:
    """How far (s) from its vertex the parabola through the scores within +- :data:`FINE_HALF_STEPS`
    ms of ``centre_s`` falls by the scores' r.m.s. scatter about it: the offsets the image cannot
    tell apart. Why not the fit's covariance alone: the scatter is not white across offsets (the
    tracker's errors move the sharpest image off the truth as a whole: 0.6 ms on bench_clock's
    draw at 0.2 m/s, 8 ms on a sweep at 0.06 m/s), so it is the breadth it leaves, not its mean."""
    xs, ys = (np.array(v) for v in zip(*tried, strict=True))
    near = np.abs(xs - centre_s) <= FINE_HALF_STEPS * FOCUS_STEP_S / 5 + 1e-9
    if near.sum() < 4:
        return float("inf")
    u = (xs[near] - centre_s) * 1e3  # ms
    q = np.polyfit(u, ys[near], 2)
    scatter = float(np.sqrt(np.mean((np.polyval(q, u) - ys[near]) ** 2)))
    return float(np.sqrt(scatter / -q[0]) * 1e-3) if q[0] < 0 else float("inf")


def refine_by_focus(
    data: np.ndarray,
    chirp: Chirp,
    positions_at: Callable[[float], np.ndarray],
    estimate: ClockEstimate,
    z_m: float,
    bp_options: dict | None = None,
    progress: Callable[[int, int], None] | None = None,
    floor_s: float = 0.0,
    region_m: tuple | None = None,
    template: Callable[[int], np.ndarray] | None = None,
) -> tuple[ClockEstimate, dict]:
    """convert's second stage: the range history's ``estimate`` refined by the focus of the scan.

    positions_at : ``dt ->`` float (M, K, 3) the phase centres with the frames' stamps + ``dt`` s
    re-sampled on the camera's trajectory (its poses through the turns, which a converted scan
    no longer has). The offsets ``estimate`` +- :data:`FOCUS_SIGMAS` sigma (:data:`FOCUS_HALF_BOUNDS_S`)
    :data:`FOCUS_STEP_S` apart, then :func:`refine_offset` around the best, each scored on
    ``region_m`` (X0, X1, Y0, Y1, Z) metres, default the brightest region (:func:`brightest_box`):
    by its match to ``template`` (``n ->`` the reference's (n, n) image there, a twin's;
    :func:`template_match`) where one is given, else by its sharpness. Why the template first:
    on bench_clock's build draws its match peaked at most 1.4 ms off the truth, the sharpness up to
    5.9 ms (a tracker's errors reshape the image as much as a millisecond does; only a known
    image tells which shape is the right one); on the held-out draws convert's worst residual by
    the physical twin's template was 1.8 ms, by the sharpness 3.6 (docs/sensors_clock.md). Returns (estimate, a record: the score, the
    region, the offsets searched, the images formed, the seconds); raises TwinFocusError (one
    line) where the score has no peak inside the offsets searched. floor_s : the least sigma
    (:func:`tracker_floor_s`); sigma is also at least the 1 ms step and the breadth the scores'
    scatter leaves (:func:`_indistinct_s`).
    """
    import time

    from twinfocus.imaging.backprojection.numba_backend import backproject  # lazy: numba (+0.5 s at import)

    t_start = time.perf_counter()
    bp = dict(bp_options or {})
    centre = float(estimate.offset_s)
    half = float(np.clip(FOCUS_SIGMAS * estimate.sigma_s, *FOCUS_HALF_BOUNDS_S))
    if template is not None and region_m is None:
        raise TwinFocusError("the focus stage's template needs the reference's region")
    roi = tuple(region_m) if region_m is not None else brightest_box(data, positions_at(centre), chirp, z_m, bp)
    grid = ImageGrid.from_roi(roi, FOCUS_SIZE)
    score = image_sharpness if template is None else template_match(template(FOCUS_SIZE))
    named = "sharpness" if template is None else "template_match"
    steps = 2 * int(np.ceil(half / FOCUS_STEP_S)) + 1
    expected = steps + 2 * FINE_HALF_STEPS + 1
    formed = [0]

    def image(positions_m: np.ndarray) -> np.ndarray:
        formed[0] += 1
        if progress is not None:
            progress(min(formed[0], expected - 1), expected)
        return backproject(data, positions_m, chirp, grid, **bp)

    coarse, _ = focus_offset(image, positions_at, half, coarse_steps=steps, score=score, centre_s=centre, refine=False)
    fine, tried = refine_offset(image, positions_at, coarse.offset_s, FOCUS_STEP_S / 5, score)
    floor = max(FOCUS_STEP_S / 5, _indistinct_s(tried, fine.offset_s), float(floor_s))
    fine = replace(fine, sigma_s=max(fine.sigma_s, floor))
    if progress is not None:
        progress(expected, expected)
    if not (np.isfinite(fine.sigma_s) and abs(fine.offset_s - centre) < half):
        raise TwinFocusError(
            f"clock offset: {FOCUS_SCORE_WORDS[named, region_m is not None]} has no peak within {centre * 1e3:+.0f} +- "
            f"{half * 1e3:.0f} ms of the range history's offset"
        )
    record = {
        **fine.to_dict(),
        "score": named,
        "region_m": [round(float(v), 4) for v in roi],
        "searched_s": [centre - half, centre + half],
        "images_formed": formed[0],
        "seconds": time.perf_counter() - t_start,
        "tried": [[round(dt, 6), sc] for dt, sc in tried],
    }
    return fine, record


#: above this offset (s) the search's line advises converting again with it: past a leg's ends the
#: search can only go on straight, while the camera's trajectory has its poses through the turns
#: (docs/sensors.md: a digital twin's target lost up to 0.04 SSIM at 50 ms on the held-out draws,
#: 0.01 at 15 ms; set after them, as convert's least applied offset is)
RECONVERT_ABOVE_S = 0.025


def clock_search_line(record: dict) -> str:
    """One line for the user from :func:`search_scan_clock`'s record."""
    scale, unit = (1e3, "ms") if record["unit"] == "s" else (1.0, "positions")
    line = (
        f"[clock] offset {record['offset_s'] * scale:+.2f} +- {record['sigma_s'] * scale:.2f} {unit} by the "
        f"reference's focus ({record['images_formed']} images, {record['seconds']:.1f} s)"
    )
    if record["unit"] == "s" and abs(record["offset_s"]) > RECONVERT_ABOVE_S:
        line += (
            f"; so large an offset is better applied where the camera's poses through the turns are: convert "
            f"again with --align none --time-offset-s the shift it applied (<scan>.capture.json clock "
            f"applied_shift_s) {record['offset_s']:+.3f}"
        )
    return line
