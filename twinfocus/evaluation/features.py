"""A second image-quality metric beside SSIM that needs no downloaded weights: HOG similarity.

The source paper also reports a "semantic similarity": the cosine similarity of ResNet features
of the reconstructed and the ground-truth images. Pretrained network weights are a download this
project does not make, so the evaluation uses the classical hand-made counterpart: the cosine
similarity of Histogram-of-Oriented-Gradients descriptors (Dalal & Triggs 2005) of the two
display images. Like early CNN features, HOG encodes local edge orientation pooled over cells
and contrast-normalised over blocks, so it rewards a reconstruction whose strokes run where the
truth's do and is insensitive to the overall gain and to sub-cell shifts, unlike a pixel metric.

The descriptor follows ``skimage.feature.hog(orientations=9, pixels_per_cell=(8, 8),
cells_per_block=(2, 2), block_norm="L2-Hys")`` exactly (the tests compare against it):
central-difference gradients (zero on the border rows/columns), unsigned orientation in
[0, 180) degrees binned without interpolation, magnitudes averaged per cell, each 2 x 2-cell
block L2-normalised, clipped at 0.2 and normalised again.
"""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.metrics import display_image

HOG_ORIENTATIONS = 9
HOG_CELL_PX = 8
HOG_BLOCK_CELLS = 2
_EPS = 1e-5


def hog_descriptor(
    image: np.ndarray,
    orientations: int = HOG_ORIENTATIONS,
    cell_px: int = HOG_CELL_PX,
    block_cells: int = HOG_BLOCK_CELLS,
) -> np.ndarray:
    """HOG feature vector of a real image (H, W): float64 (n_blocks_y * n_blocks_x * block_cells^2 * orientations,).

    Pixels beyond the last whole cell are ignored (as in scikit-image).
    """
    a = np.asarray(image, dtype=np.float64)
    if a.ndim != 2 or not np.isfinite(a).all():
        raise TwinFocusError(f"HOG needs a finite 2-D image, got shape {a.shape}")
    ncy, ncx = a.shape[0] // cell_px, a.shape[1] // cell_px
    if ncy < block_cells or ncx < block_cells:
        raise TwinFocusError(
            f"image of {a.shape[0]} x {a.shape[1]} pixels is too small for {block_cells} x {block_cells} cells of {cell_px} px"
        )
    g_row = np.zeros_like(a)
    g_col = np.zeros_like(a)
    g_row[1:-1, :] = a[2:, :] - a[:-2, :]
    g_col[:, 1:-1] = a[:, 2:] - a[:, :-2]
    mag = np.hypot(g_row, g_col)
    ang = np.rad2deg(np.arctan2(g_row, g_col)) % 180.0
    step = 180.0 / orientations
    # Bin i holds [i * step, (i + 1) * step); the clip keeps float round-off at 180 in the last bin.
    bins = np.minimum((ang // step).astype(np.int64), orientations - 1)
    h, w = ncy * cell_px, ncx * cell_px
    mag, bins = mag[:h, :w], bins[:h, :w]
    onehot = np.zeros((h, w, orientations))
    np.put_along_axis(onehot, bins[..., None], mag[..., None], axis=2)
    cells = onehot.reshape(ncy, cell_px, ncx, cell_px, orientations).mean(axis=(1, 3))
    nby, nbx = ncy - block_cells + 1, ncx - block_cells + 1
    blocks = np.empty((nby, nbx, block_cells, block_cells, orientations))
    for i in range(nby):
        for j in range(nbx):
            b = cells[i : i + block_cells, j : j + block_cells]
            b = b / np.sqrt(np.sum(b * b) + _EPS**2)
            b = np.minimum(b, 0.2)
            blocks[i, j] = b / np.sqrt(np.sum(b * b) + _EPS**2)
    return blocks.ravel()


def hog_similarity(image: np.ndarray, truth: np.ndarray, centre: float = 0.4, steepness: float = 1.0) -> float:
    """Cosine similarity in [0, 1] of the HOG descriptors of two images' display versions
    (max-normalised, soft-thresholded amplitude: :func:`twinfocus.imaging.metrics.display_image`), the
    same images SSIM is taken on. 1 means the same local edge structure everywhere."""
    a = hog_descriptor(display_image(image, centre, steepness))
    b = hog_descriptor(display_image(truth, centre, steepness))
    if a.shape != b.shape:
        raise TwinFocusError(f"images differ in size: {np.shape(image)} and {np.shape(truth)}")
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        # A flat image has no edges at all: similar only to another flat image.
        return 1.0 if na == nb else 0.0
    return float(a @ b / (na * nb))
