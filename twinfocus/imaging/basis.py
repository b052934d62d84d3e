"""Images from the sub-image basis: one phase per radar position, or one per position and pixel.

The basis B (M, H, W) of a region (:func:`twinfocus.imaging.backprojection.numba_backend.subimage_basis`) holds each
radar position's contribution to the region's image, so a correction of the positions' phases
is a weighted sum (docs/architecture.md section 1):

    image(phi) = sum_m exp(j phi_m) B_m                  (:func:`form_image`)
    image(phi)(p) = sum_m exp(j phi_m(p)) B_m(p)         (:func:`form_image_space_variant`)

Every estimator and the phase transfer use these two; they sit below them (no imports but numpy).
"""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError


def form_image(basis: np.ndarray, phase_rad: np.ndarray) -> np.ndarray:
    """sum_m exp(j phi_m) B_m: complex64 (H, W) from basis (M, H, W) and phase (M,) in radians."""
    basis = np.asarray(basis)
    phase_rad = np.asarray(phase_rad, dtype=np.float64)
    if phase_rad.shape != (basis.shape[0],):
        raise TwinFocusError(f"phase must have one value per radar position ({basis.shape[0]}), got {phase_rad.shape}")
    w = np.exp(1j * phase_rad).astype(np.complex64)
    return np.tensordot(w, basis, axes=(0, 0)).astype(np.complex64)


def form_image_space_variant(basis: np.ndarray, phases_rad: np.ndarray) -> np.ndarray:
    """sum_m exp(j phi_m(p)) B_m(p): complex64 (H, W) from basis and phases (radians), both (M, H, W)."""
    b = np.asarray(basis)
    ph = np.asarray(phases_rad)
    if ph.shape != b.shape:
        raise TwinFocusError(f"per-pixel phases {ph.shape} must match the basis {b.shape}")
    out = np.zeros(b.shape[1:], np.complex64)
    for i in range(0, b.shape[0], 64):  # bounded temporaries: 64 positions' phasors at a time
        out += (b[i : i + 64] * np.exp(1j * ph[i : i + 64]).astype(np.complex64)).sum(axis=0)
    return out


class BasisRows:
    """A sub-image basis streamed in batch by batch (the solver node's, as radar frames arrive):
    rows appended into one array that doubles when full, so the whole basis is there at the
    scan's end without a final copy (np.concatenate of the paper's two bases, 2 x 62 MB, took
    0.2 s on the loaded 2-core VM, all of it after the last measurement)."""

    def __init__(self) -> None:
        self.buf: np.ndarray | None = None
        self.n = 0

    def append(self, rows: np.ndarray) -> None:
        """Add (k, H, W) rows (the basis of k more positions, in capture order)."""
        k = rows.shape[0]
        if self.buf is not None and rows.shape[1:] != self.buf.shape[1:]:
            raise TwinFocusError(f"basis rows {rows.shape[1:]} do not match the rows so far {self.buf.shape[1:]}")
        if self.buf is None or self.n + k > self.buf.shape[0]:
            cap = max(64, self.n + k, 0 if self.buf is None else 2 * self.buf.shape[0])
            grown = np.empty((cap,) + rows.shape[1:], rows.dtype)
            if self.buf is not None:
                grown[: self.n] = self.buf[: self.n]
            self.buf = grown
        self.buf[self.n : self.n + k] = rows
        self.n += k

    def array(self) -> np.ndarray:
        """(M, H, W) the rows so far (a view, not a copy)."""
        if self.buf is None:
            raise TwinFocusError("no basis rows yet")
        return self.buf[: self.n]
