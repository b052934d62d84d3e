"""Point scatterers of a surface: how densely they sample it and their complex amplitudes.

Scatterer density: the cross-range resolution of the paper's aperture is
lambda R / (2 D) = 3.9 mm * 0.6 m / (2 * 0.49 m) ~ 2.4 mm; scatterers a quarter to a half of that
apart make a continuous surface in the image. :data:`DEFAULT_SPACING_M` is half (1.2 mm), which
gives about 1,500-2,500 points for a 127 mm letter.
"""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError

#: Cross-range resolution of the paper set-up (wavelength 3.9 mm, 0.6 m, 0.49 m aperture) / 2.
DEFAULT_SPACING_M = 1.2e-3


def scatterer_spacing_m(
    range_m: float, aperture_m: float = 0.49, wavelength_m: float = 3.9e-3, fraction: float = 0.5
) -> float:
    """``fraction`` of the cross-range resolution lambda R / (2 D), metres."""
    if not (range_m > 0 and aperture_m > 0 and wavelength_m > 0 and fraction > 0):
        raise TwinFocusError("range_m, aperture_m, wavelength_m and fraction must all be positive")
    return float(fraction * wavelength_m * range_m / (2.0 * aperture_m))


def random_phase(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` unit phasors exp(j 2 pi U), U uniform in [0, 1): speckle, complex128 (n,)."""
    return np.exp(2j * np.pi * rng.random(n))


def rough_amplitudes(
    reflectivity: float, n: int, roughness_deg: float, amplitude_spread: float, rng: np.random.Generator
) -> np.ndarray:
    """Amplitudes of ``n`` scatterers of a rough surface, complex128 (n,).

    Each scatterer has its own reflectivity phase, uniform in [-roughness_deg, +roughness_deg]
    degrees, and its own magnitude, uniform in reflectivity x [1 - amplitude_spread,
    1 + amplitude_spread]. 180 degrees is full speckle (as ``speckle=True``), 0 a smooth surface.
    """
    phase = np.deg2rad(float(roughness_deg)) * (2.0 * rng.random(n) - 1.0)
    mag = float(reflectivity) * (1.0 + float(amplitude_spread) * (2.0 * rng.random(n) - 1.0))
    return mag * np.exp(1j * phase)
