"""Torch back-end of :mod:`twinfocus.imaging.backprojection.numba_backend` (the CUDA path; also runs on CPU).

Same function as the numba kernels: zoomed baseband range profiles, linear interpolation at
each pixel's range, exact carrier phase relative to the window start. Work is chunked over radar
positions so peak memory is about ``chunk_elements x P x 40`` bytes.
"""

from __future__ import annotations

import numpy as np
import torch

from twinfocus.imaging.device import resolve_device
from twinfocus.imaging.range_geometry import DEFAULT_OVERSAMPLE, local_frame, range_lattice, turns_per_m
from twinfocus.radar.fmcw import Chirp, range_kernel


def backproject_points_torch(
    data: np.ndarray,
    positions_m: np.ndarray,
    chirp: Chirp,
    points_m: np.ndarray,
    *,
    oversample: int = DEFAULT_OVERSAMPLE,
    precision: str = "float32",
    device: str | None = None,
    basis: bool = False,
    max_pairs_per_chunk: int = 2**24,
) -> np.ndarray:
    """complex64 (P,) image, or (M, P) basis when ``basis`` (see backprojection module); ``device``
    None: :func:`twinfocus.imaging.device.resolve_device`'s choice."""
    device = resolve_device(device)
    real = torch.float32 if precision == "float32" else torch.float64
    cplx = torch.complex64 if precision == "float32" else torch.complex128
    np_real = np.float32 if precision == "float32" else np.float64
    pos, pts = local_frame(positions_m, points_m, np_real)
    n_pos, n_ch = data.shape[:2]
    dr = chirp.range_resolution_m / oversample
    # The same range lattice as the numba back-end (prepare_profiles).
    r0, q = range_lattice(pos.astype(np.float64), pts.astype(np.float64), dr, margin_m=2 * dr)
    tpm = turns_per_m(chirp)
    kernel = torch.from_numpy(range_kernel(chirp, r0 + dr * np.arange(q))).to(device=device, dtype=cplx)
    turns0 = tpm * r0
    kernel = kernel * complex(np.exp(-2j * np.pi * (turns0 - np.floor(turns0))))
    pts_t = torch.from_numpy(pts).to(device=device, dtype=real)
    n_pix = pts.shape[0]
    chunk = max(1, int(max_pairs_per_chunk // max(1, n_ch * n_pix)))
    out_basis: np.ndarray | None = np.empty((n_pos, n_pix), np.complex64) if basis else None
    image = torch.zeros(n_pix, dtype=cplx, device=device)
    for lo in range(0, n_pos, chunk):
        hi = min(lo + chunk, n_pos)
        d = torch.from_numpy(np.ascontiguousarray(data[lo:hi])).to(device=device, dtype=cplx).reshape(-1, data.shape[2])
        prof = d @ kernel  # (E, Q)
        e = torch.from_numpy(pos[lo:hi].reshape(-1, 3)).to(device=device, dtype=real)
        # Explicit differences: cdist's matmul form loses float32 precision at these ranges.
        rng = torch.sqrt(((e[:, None, :] - pts_t[None]) ** 2).sum(-1))
        rel = rng - r0
        u = (rel / dr).clamp(0.0, q - 1.0001)
        i = u.floor().long()
        f = (u - i).to(real)
        lo_v = torch.gather(prof, 1, i)
        hi_v = torch.gather(prof, 1, i + 1)
        v = lo_v + f * (hi_v - lo_v)
        turns = rel * tpm
        mf = v * torch.polar(torch.ones_like(turns), -2.0 * np.pi * (turns - torch.round(turns)))
        per_pos = mf.reshape(hi - lo, n_ch, n_pix).sum(1)
        if basis:
            out_basis[lo:hi] = per_pos.to(torch.complex64).cpu().numpy()  # type: ignore[index]  # set when basis
        else:
            image += per_pos.sum(0)
    if basis:
        return out_basis  # type: ignore[return-value]  # set when basis
    return image.to(torch.complex64).cpu().numpy()
