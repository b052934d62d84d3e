"""How a focused reference fills its outline: the digital twin's check of like against like.

A digital twin's template is an outline drawn from a camera cloud; the radar sees a rough
reference as speckle whatever the outline says, so the corrected reference's SSIM against the
template's picture (0.66-0.78 on field draws, whether the target reached 0.49 or 0.99) says
nothing about the estimate. What the outline does say is where the reference's energy belongs,
and the focused image's energy e = |I|^2 over it spreads in a known way: a surface with a
coherent part (smooth metal, or rough within +-90 degrees of phase) fills its outline, contrast
mean(e^2) / mean(e)^2 of 1.5-2.6 on the field scenes. An estimate that lost the reference's phase
piles its energy into a few bright pixels (the outline criterion can be raised that way), 2.9-3.9;
one that left it blurred puts energy outside the outline.

A speckled surface (every scatterer's phase anywhere on the circle) in focus is fully developed
speckle, 2.8-3.3 over the grown outline, as high as a piled estimate, so the contrast cannot
judge it. The scan says which surface it is, whatever the phase errors
(:func:`surface_from_positions`).
"""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError

#: the outline grown by this many pixels before the statistics: a camera cloud sits a few
#: millimetres off where the radar sees the reference
OUTLINE_GROW_PX = 3
#: a reference whose energy over its outline varies from position to position less than this
#: (contrast over the positions, :func:`surface_from_positions`) is speckled. On the family bench's
#: draws (benchmarks/bench_dtwin_family.py: the MMWCAS array, 390 positions at 0.6 m, 64 x 64
#: pixels, 10-15 dB, jitter and a hand's drift alike; bench and held-out draws) speckled
#: references gave 1.18-1.46, rough ones (+-90 degrees) 2.67-4.99 and smooth ones 2.99-4.51:
#: between the two groups, with room for noise, which pulls every value toward 1
SPECKLED_BELOW = 1.8


def _grown(support: np.ndarray, grow_px: int) -> np.ndarray:
    """The outline, bool (H, W), grown by ``grow_px`` >= 0 pixels; refused when it is empty."""
    from scipy import ndimage  # scipy.ndimage is slow to import: only where a reference is read

    mask = np.asarray(support, dtype=bool)
    if int(grow_px) < 0:
        raise TwinFocusError(f"grow_px must be >= 0, got {grow_px}")
    if not mask.any():
        raise TwinFocusError("the outline covers none of the region")
    return ndimage.binary_dilation(mask, iterations=int(grow_px)) if int(grow_px) else mask


def outline_fill(image: np.ndarray, support: np.ndarray, grow_px: int = OUTLINE_GROW_PX) -> dict:
    """The focused reference against its outline.

    image : complex or real (H, W) the corrected reference; support : bool (H, W) its outline on
    the same grid (grown by ``grow_px`` >= 0 pixels here).

    Returns {"energy_inside": share of sum |image|^2 inside the grown outline, in [0, 1];
    "contrast": mean(e^2) / mean(e)^2 of e = |image|^2 over the grown outline (>= 1; 2 for fully
    developed speckle)}.
    """
    img = np.asarray(image)
    if img.ndim != 2 or np.shape(support) != img.shape:
        raise TwinFocusError(f"image {img.shape} and outline {np.shape(support)} must be the same (H, W)")
    mask = _grown(support, grow_px)
    e = np.abs(img.astype(np.complex128)) ** 2
    total = float(e.sum())
    inside = e[mask]
    if not np.isfinite(total) or total <= 0 or inside.sum() <= 0:
        raise TwinFocusError("the image has no finite energy inside its outline")
    return {
        "energy_inside": round(float(inside.sum()) / total, 4),
        "contrast": round(float((inside**2).mean() / inside.mean() ** 2), 3),
    }


def surface_from_positions(basis: np.ndarray, support: np.ndarray, grow_px: int = OUTLINE_GROW_PX) -> dict:
    """Whether the reference is speckled or has a coherent part, from how its return changes
    across the scan.

    Each radar position's energy over the reference's outline, E_m = sum_p |B_m(p)|^2, does not
    depend on the phase errors (they turn B_m, they do not scale it). A surface with a coherent
    part (smooth, or rough within +-90 degrees) sends back a lobe that changes with the look angle:
    E_m varies across the scan (contrast mean(E^2) / mean(E)^2 of 2.7-5.0 on the field scenes). A
    speckled surface's return at each position sums many independent speckle cells (the array's
    channels, the band, the outline's pixels): E_m barely varies (1.2-1.5). Below
    ``SPECKLED_BELOW``: speckled. Measured on the field scenes' geometry (``SPECKLED_BELOW``); a
    small reference seen by a small array over a short aperture averages fewer cells.

    basis : complex (M, H, W) the reference's sub-image basis (one image per radar position);
    support : bool (H, W) its outline on the same grid (grown by ``grow_px`` >= 0 pixels here).

    Returns {"position_energy_contrast": mean(E^2) / mean(E)^2 over the M positions (>= 1),
    "surface": "speckled" or "coherent"}.
    """
    b = np.asarray(basis)
    if b.ndim != 3 or b.shape[1:] != np.shape(support):
        raise TwinFocusError(f"basis {b.shape} must be (M, H, W) with the outline's (H, W) {np.shape(support)}")
    mask = _grown(support, grow_px)
    inside = np.abs(b[:, mask])
    # in float64 after the unit peak: a scan at 1e20 would overflow float32's squares
    peak = float(inside.max())
    if not np.isfinite(peak) or peak <= 0:
        raise TwinFocusError("the reference's sub-images have no finite energy inside its outline")
    energy = ((inside / peak).astype(np.float64) ** 2).sum(axis=1)
    contrast = float((energy**2).mean() / energy.mean() ** 2)
    return {
        "position_energy_contrast": round(contrast, 3),
        "surface": "speckled" if contrast < SPECKLED_BELOW else "coherent",
    }
