"""Each radar position's range error, read from the two halves of the chirp's band.

A range error dR of a position puts a phase 2 k dR on its samples, with k the wavenumber of each
sample: across the sampled band (3.84 GHz) that phase changes by 2 dk dR, a small and unwrapped
quantity (0.08 rad per mm between the centres of the band's halves) even when 2 k dR itself has
wrapped many times. So the difference between what a position contributes to the image in the
band's upper half and in its lower half measures dR without the ambiguity of the one phase per
position that the autofocus estimates, and without the image's place: a linear phase across the
aperture (a misplaced template's) is the same in both halves and cancels.

With those range errors, the estimate's own range-error part can be taken out
(:func:`twinfocus.focus.autofocus.transfer_phase`): what is left is the misplacement's ramp, which the
scan could not otherwise tell from the errors once they pass lambda/5 (docs/digital_twin.md,
"Placing the reference by the band's halves").
"""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import C_M_PER_S, Chirp


def half_band_chirps(chirp: Chirp) -> tuple[Chirp, Chirp]:
    """The chirp's sampled band split in two: (lower half: samples [0, N // 2), upper half:
    samples [N // 2, N)). An FMCW chirp's samples sweep the band in order, so each half is a
    chirp of its own, the upper one starting where the lower one ends."""
    n = int(chirp.n_samples)
    if n < 4:
        raise TwinFocusError(f"the band's halves need at least 4 samples per chirp, the chirp has {n}")
    h = n // 2
    low = Chirp(chirp.f0_hz, chirp.slope_hz_per_s, chirp.fs_hz, h)
    high = Chirp(chirp.f0_hz + chirp.slope_hz_per_s * h / chirp.fs_hz, chirp.slope_hz_per_s, chirp.fs_hz, n - h)
    return low, high


def half_band_data(data: np.ndarray, chirp: Chirp) -> tuple[np.ndarray, np.ndarray]:
    """The samples (M, K, N) of :func:`half_band_chirps`'s lower and upper halves, (M, K, N // 2)
    and (M, K, N - N // 2): views, so taking one half copies nothing of the other."""
    h = int(chirp.n_samples) // 2
    return data[..., :h], data[..., h:]


#: the share of the reference image's energy whose pixels the range errors are read on: the
#: rest is noise (B scenes of the field bench: target SSIM 0.915 on 25-29 % of the pixels against
#: 0.896 on all of them), and the upper band's basis costs a quarter of the whole region's
ENERGY_FRACTION = 0.99


def bright_pixels(image: np.ndarray, fraction: float = ENERGY_FRACTION) -> np.ndarray:
    """The brightest pixels of ``image`` (complex or real (H, W)) that together hold ``fraction``
    of its energy sum |image|^2: bool (H, W)."""
    if not 0.0 < float(fraction) <= 1.0:
        raise TwinFocusError(f"fraction must be in (0, 1], got {fraction!r}")
    energy = np.abs(np.asarray(image, dtype=np.complex128)) ** 2
    if not np.isfinite(energy).all() or energy.sum() <= 0:
        raise TwinFocusError("the image has no finite energy to pick pixels by")
    ordered = np.sort(energy.ravel())[::-1]
    last = int(np.searchsorted(np.cumsum(ordered) / ordered.sum(), float(fraction) - 1e-12))
    return energy >= ordered[min(last, ordered.size - 1)]


def position_range_errors_m(
    low_basis: np.ndarray, high_basis: np.ndarray, phase_rad: np.ndarray, chirp: Chirp
) -> np.ndarray:
    """Each position's range error along its line of sight to the region, from the band's halves:
    float64 (M,) metres, up to one constant for all positions.

    low_basis, high_basis : complex (M, P) sub-image bases of one region's pixels (or (M, H, W))
    from the lower and upper half of ``chirp``'s band (:func:`half_band_chirps`); phase_rad : (M,)
    the autofocus estimate, radians (the correction :func:`twinfocus.imaging.basis.form_image` applies).

    Each half's image is formed with the estimate; a position's contribution to it, compared with
    the image, leaves the phase the estimate did not undo, 2 (k_half - k) dR; the difference between
    the halves is 2 dk dR. The comparison includes the position's own share of the image, which
    pulls every value toward 0 (measured against the true range error on the field scenes: slope
    0.66 on every pixel of the region, 0.85 on its bright pixels): kept, because it lowers the error
    of each value (0.56 against 0.7 mm without it at 1 mm of error) and the ramp fit after it wants
    the least noise, not an unbiased scale (a gain other than 1 on these values did not make the
    fit's coherence larger).
    Useful while the errors stay within +-c / (4 dk) (+-37 mm for the default chirp). Even with
    the true phase and no tracking error the values scatter by 0.4-0.7 mm (a position's sub-image
    holds every scatterer on its range ring, and where their delays centre depends on the
    surface), and a constant + linear trend of the errors across the aperture is out of their
    sight (each position is read against the image of all): docs/digital_twin_autofocus.md, "What the scan
    alone can place".
    """
    low_basis = np.asarray(low_basis)
    high_basis = np.asarray(high_basis)
    phi = np.asarray(phase_rad, dtype=np.float64)
    if low_basis.shape != high_basis.shape or low_basis.ndim < 2:
        raise TwinFocusError(
            f"the band halves' bases must be two (M, ...) arrays of one shape, got {low_basis.shape} and {high_basis.shape}"
        )
    if phi.shape != (low_basis.shape[0],):
        raise TwinFocusError(f"phase must have one value per radar position ({low_basis.shape[0]}), got {phi.shape}")
    low, high = half_band_chirps(chirp)
    dk = 2.0 * np.pi * (high.fc_hz - low.fc_hz) / C_M_PER_S
    w = np.exp(1j * phi).astype(np.complex64)
    shares = []
    for basis in (low_basis, high_basis):
        flat = basis.reshape(basis.shape[0], -1)
        image = w @ flat  # the half's image formed with the estimate (form_image's sum)
        # <image, position m's contribution>: (M,) complex, one matrix-vector product
        shares.append((flat @ image.conj()) * w)
    return np.angle(shares[1] * np.conj(shares[0])).astype(np.float64) / (2.0 * dk)
