"""Whether an image region holds an object at all, before anything is focused on it."""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError

#: an incoherent image sum_m |B_m|^2 of noise alone on M positions stands at most this many
#: times 1 / sqrt(M) above its median (field geometry, 64 x 64 pixels, 5 draws each: peak / median
#: 1.19 at 390 positions, 1.28 at 96, 1.73 at 24, 2.81 at 6; 4-8 on 1-2 positions, where no
#: test of one region tells an object from noise, so fewer than ``INCOHERENT_MIN_POSITIONS`` are
#: not read this way)
NOISE_INCOHERENT_PEAK_SQRT_M = 6.0


INCOHERENT_MIN_POSITIONS = 6


#: a picture of noise alone (Rayleigh amplitudes) peaks at most ~12.5 x its 10th percentile (200
#: draws each of 16 x 16 to 200 x 200 pixels: 7-10 median, 12.5 the largest); a template of a plate
#: that fills 58 % of its region (peak / median 1.3 from the cloud, 1.8 from a stage scan) keeps
#: a dark margin around it, its peak 85 x that percentile and more
NOISE_PEAK_TO_DARK = 25.0


DARK_QUANTILE = 10.0


def check_has_signal(
    amplitude: np.ndarray, what: str, min_peak_to_median: float = 4.0, basis: np.ndarray | None = None
) -> None:
    """Refuse an image region with nothing in it: its peak must stand well above its median
    (a region of pure noise has peak/median ~ 3.6 for 10^4 Rayleigh pixels).

    basis : complex (M, H, W), the region's sub-images when ``amplitude`` is their sum (a scanned
    region). Where the phase errors have smeared an object that fills most of the region (a washer
    under 0.5-1.6 mm of error: peak 3.8-4.0 x the median; a physical twin focuses it at
    0.93-0.96), the region is kept when its incoherent image sum_m |B_m|^2, which the phase errors
    do not touch, stands above what noise reaches on M positions: peak / median above
    1 + ``NOISE_INCOHERENT_PEAK_SQRT_M`` / sqrt(M) (the washers: 1.8 on 390 positions), on at
    least ``INCOHERENT_MIN_POSITIONS`` positions.

    Without ``basis`` (a picture: a template from a stage scan or a camera cloud), an object that
    fills most of the region is kept when the region has a dark part: its peak stands above its
    ``DARK_QUANTILE`` th percentile by more than ``NOISE_PEAK_TO_DARK``, which noise never
    reaches. Not for a scanned region's image: its smeared phases cancel in places, and those
    zeros are not a background.
    """
    a = np.abs(np.asarray(amplitude)).astype(np.float64)
    if not np.isfinite(a).all():
        raise TwinFocusError(f"{what} holds NaN or inf")
    peak, med = a.max(), np.median(a)
    if peak <= 0:
        raise TwinFocusError(f"{what} is empty: no signal reaches it")
    if peak - a.min() <= 1e-6 * peak:
        raise TwinFocusError(f"{what} is constant: it holds no structure to focus on")
    if med > 0 and peak / med < min_peak_to_median:
        why = ""
        if basis is None:
            dark = float(np.percentile(a, DARK_QUANTILE))
            if peak > NOISE_PEAK_TO_DARK * dark:
                return
            why = f"; nor is any of it dark: its peak is {peak / max(dark, 1e-300):.1f} x its {DARK_QUANTILE:.0f}th percentile"
        if basis is not None and np.shape(basis)[0] >= INCOHERENT_MIN_POSITIONS:
            b = np.abs(np.asarray(basis))
            # at the unit peak: float32's squares overflow past 1e19
            energy = ((b / max(float(b.max()), 1e-300)).astype(np.float64) ** 2).sum(axis=0)
            ratio = float(energy.max()) / max(float(np.median(energy)), 1e-300)
            bound = 1.0 + NOISE_INCOHERENT_PEAK_SQRT_M / np.sqrt(b.shape[0])
            if ratio > bound:
                return
            why = (
                f"; its incoherent image peaks {ratio:.2f} x its median, where noise on {b.shape[0]} "
                f"positions reaches {bound:.2f}"
            )
        raise TwinFocusError(
            f"{what} shows no object (peak only {peak / med:.1f} x the median{why}); check the region of interest"
        )
