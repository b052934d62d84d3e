"""Sub-pixel helpers shared by template registration, the digital twin's alignment and the
radar-camera calibration: moving an image by a fraction of a pixel, and the vertex of the
parabola through a sampled extremum and its two neighbours.
"""

from __future__ import annotations

import numpy as np


def shift_image(image: np.ndarray, dy: float, dx: float) -> np.ndarray:
    """``image`` moved by (dy, dx) pixels (cubic spline, zeros shifted in); same dtype.

    image : (H, W) real or complex. Complex images are shifted in real and imaginary parts (a
    back-projected image is shift-equivariant, phases included, for shifts small against the
    range); a non-negative real image stays non-negative (the spline's overshoot is cut).
    """
    from scipy.ndimage import shift

    img = np.asarray(image)
    if np.iscomplexobj(img):
        re = shift(img.real, (dy, dx), order=3, mode="constant")
        return (re + 1j * shift(img.imag, (dy, dx), order=3, mode="constant")).astype(img.dtype)
    out = shift(img.astype(np.float64), (dy, dx), order=3, mode="constant")
    return np.maximum(out, 0.0).astype(img.dtype) if np.all(img >= 0) else out.astype(img.dtype)


def parabola_vertex(m1: float, c: float, p1: float, limit: float = 0.5) -> float:
    """Abscissa of the vertex of the parabola through (-1, m1), (0, c), (+1, p1), in samples,
    clipped to +-``limit``; 0 when the three lie on a line.

    At a sampled maximum (c >= m1, p1) or minimum (c <= m1, p1) the vertex lies within +-0.5.
    """
    den = m1 - 2.0 * c + p1
    if den == 0:
        return 0.0
    return float(np.clip(0.5 * (m1 - p1) / den, -limit, limit))
