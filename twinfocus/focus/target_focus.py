"""What the corrected target says of the phase it was given: whether a defocus is left on it.

A digital twin's outline estimate can leave a smooth error across the aperture that keeps the
reference inside its outline (docs/digital_twin_field.md, "Where the estimate goes wrong"), so
the reference looks focused while the target is not. The target itself can tell part of it: a
phase of degree 2 across the aperture (defocus and astigmatism; a ramp only moves the image) that
lowers the target's entropy by much says that its focus is elsewhere. A target focused right
sits near a minimum of entropy along those directions: 0.002-0.040 nats on the family bench's
trusted digital-twin results that reached 0.95 of target SSIM; two results of 0.69 and 0.85 gave
0.10 and 0.12 (``benchmarks/bench_dtwin_family.py``, docs/digital_twin_field.md). This is a check,
not a correction: the minimum of the target's entropy is not its true phase (docs/notes.md).
"""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.focus.phase_ramp import aperture_polynomial
from twinfocus.imaging.basis import form_image
from twinfocus.imaging.metrics import entropy

#: a quadratic's coefficients are searched within +-this, radians at the aperture's edge
DEFOCUS_SEARCH_RAD = 3.0


def defocus_gain_nats(basis: np.ndarray, phase_rad: np.ndarray, centres_m: np.ndarray) -> tuple[float, np.ndarray]:
    """How far a quadratic phase across the aperture lowers the entropy of sum_m exp(j phi_m) B_m.

    basis : complex (M, H, W), the target's sub-images; phase_rad : (M,) radians, the phase that
    formed the target; centres_m : (M, 3) phase centres, metres. Powell's search over the three
    terms of degree 2 (:func:`twinfocus.focus.phase_ramp.aperture_polynomial`), each within
    +-``DEFOCUS_SEARCH_RAD``. Returns (entropy at phase_rad minus the least found, nats, >= 0;
    the quadratic's coefficients, float64 (3,), radians at the aperture's edge).
    """
    from scipy.optimize import minimize  # only this check needs it

    b = np.asarray(basis)
    phi = np.asarray(phase_rad, dtype=np.float64)
    if b.ndim != 3 or phi.shape != (b.shape[0],):
        raise TwinFocusError(f"need a basis (M, H, W) and one phase per position, got {b.shape} and {phi.shape}")
    quadratic = aperture_polynomial(centres_m, 2)[:, 3:]

    def image_entropy(coef: np.ndarray) -> float:
        return entropy(np.abs(form_image(b, phi + quadratic @ coef)) ** 2)

    start = image_entropy(np.zeros(3))
    found = minimize(image_entropy, np.zeros(3), method="Powell", bounds=[(-DEFOCUS_SEARCH_RAD, DEFOCUS_SEARCH_RAD)] * 3,
                     options={"xtol": 1e-2, "ftol": 1e-4, "maxfev": 400})  # fmt: skip
    return max(start - float(found.fun), 0.0), np.asarray(found.x, dtype=np.float64)
