"""Whether a per-position phase estimate moves smoothly from one position to the next: the mark
of a drifting tracker rather than a jittering one.

Jitter (each position's error its own) gives phases with no relation between neighbours once it
passes a few tenths of a millimetre: the mean phasor of the steps exp(j (phi_{m+1} - phi_m)) is
near 0 (0.01-0.11 on the family bench's draws at 0.5-1.6 mm). A drift (a hand's, or a VIO's)
changes slowly along the scan, so consecutive positions' phases agree (0.41-0.50 under a hand's
0.8 mm drift and 0.15 degrees of rotation). A drift moves every pixel of the reference its own
way (its rotation most of all), which one phase per position cannot undo; the physical twin's
drift fit can (:func:`twinfocus.focus.space_variant.fit_smooth_drift`), a digital twin's outline cannot.
A scan tracked well also moves smoothly, so a drift counts only where the phases also spread
(:func:`phase_concentration`).
"""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError


def step_coherence(phase_rad: np.ndarray) -> float:
    """|mean_m exp(j (phi_{m+1} - phi_m))| over the positions in capture order: float in [0, 1],
    1 when every step is the same (a constant or a linear ramp along the scan), near 0 when
    neighbours' phases are unrelated.

    phase_rad : float (M,) radians, M >= 2, in the order the positions were captured.
    """
    phi = np.asarray(phase_rad, dtype=np.float64)
    if phi.ndim != 1 or phi.size < 2:
        raise TwinFocusError(f"the step coherence needs a (M,) phase with M >= 2, got {phi.shape}")
    if not np.isfinite(phi).all():
        raise TwinFocusError("phase holds NaN or inf")
    return float(np.abs(np.exp(1j * np.diff(phi)).mean()))


def phase_concentration(phase_rad: np.ndarray) -> float:
    """|mean_m exp(j phi_m)|: float in [0, 1], 1 when every position has the same phase (a scan
    tracked exactly), near 0 when the phases cover the circle (errors past a quarter wavelength).
    A scan tracked well moves smoothly too (its step coherence is near 1), but its phases stay
    together; a drift that matters spreads them (below 0.5 for 0.5 mm of drift and more).

    phase_rad : float (M,) radians, M >= 1.
    """
    phi = np.asarray(phase_rad, dtype=np.float64)
    if phi.ndim != 1 or phi.size < 1 or not np.isfinite(phi).all():
        raise TwinFocusError(f"the phase concentration needs a finite (M,) phase, got {phi.shape}")
    return float(np.abs(np.exp(1j * phi).mean()))
