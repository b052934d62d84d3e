"""The torch back-end against the numba kernels, and the autofocus on CUDA against the CPU.

The CUDA tests carry the ``gpu`` mark (skipped without a CUDA device, tests/conftest.py); the
torch CPU back-end is checked everywhere on a small case (it is the CUDA code on another device).
"""

import numpy as np
import pytest

from twinfocus.imaging.backprojection.numba_backend import backproject, subimage_basis
from twinfocus.imaging.grid import ImageGrid
from twinfocus.radar.fmcw import C_M_PER_S, Chirp, mmwcas_virtual_array


def speckle_scan(n_positions=12, n_points=25, seed=0):
    """Random scatterers seen from a short row of radar positions (IF model written out here)."""
    rng = np.random.default_rng(seed)
    ch = Chirp()
    va = mmwcas_virtual_array()
    pos = np.array([va.offsets_m + np.array([0.0, y, 0.0]) for y in (np.arange(n_positions) - n_positions / 2) * 0.004])
    pts = np.column_stack(
        [rng.uniform(-0.03, 0.03, n_points), rng.uniform(-0.03, 0.03, n_points), np.full(n_points, 0.6)]
    )
    amp = rng.normal(size=n_points) + 1j * rng.normal(size=n_points)
    r = np.linalg.norm(pos[:, :, None, :] - pts[None, None], axis=-1)  # (M, K, S)
    data = np.einsum("s,mksn->mkn", amp, np.exp(1j * 2 * np.pi * ch.frequencies_hz * 2 * r[..., None] / C_M_PER_S))
    return data.astype(np.complex64), pos, ch


GRID = ImageGrid(-0.04, 0.04, -0.04, 0.04, 0.6, 24, 24)


def _rel(a, b):
    """max |a - b| relative to the peak of b, per leading row when 2-D or more."""
    a, b = np.asarray(a), np.asarray(b)
    peak = np.abs(b).reshape(b.shape[0], -1).max(axis=1) if b.ndim > 2 else np.abs(b).max()
    return (
        float((np.abs(a - b).reshape(b.shape[0], -1).max(axis=1) / peak).max())
        if b.ndim > 2
        else float(np.abs(a - b).max() / peak)
    )


def _compare_backends(device, precision, tol):
    data, pos, ch = speckle_scan()
    for fn in (backproject, subimage_basis):
        ref = fn(data, pos, ch, GRID, precision=precision)
        got = fn(data, pos, ch, GRID, precision=precision, backend="torch", device=device)
        assert got.shape == ref.shape and got.dtype == np.complex64
        assert _rel(got, ref) < tol, (fn.__name__, precision, _rel(got, ref))


def test_torch_cpu_backend_matches_numba():
    # float32 round-off of a sum of ~1000 terms with phases from ranges of 0.6 m: ~1e-5 of the peak
    _compare_backends("cpu", "float32", 1e-4)


@pytest.mark.gpu
@pytest.mark.parametrize("precision,tol", [("float32", 1e-4), ("float64", 1e-6)])
def test_cuda_backend_matches_numba(precision, tol):
    # float64 still differs by the linear interpolation's order of operations only
    _compare_backends("cuda", precision, tol)


@pytest.mark.gpu
def test_autofocus_on_cuda_matches_cpu():
    """The paper's optimiser from the same start on both devices: float32 round-off only, so the
    same phases (up to the constant no image shows) and the same loss."""
    from twinfocus.focus.autofocus import AutofocusConfig, twin_autofocus

    rng = np.random.default_rng(1)
    data, pos, ch = speckle_scan(n_positions=40, n_points=40)
    truth = subimage_basis(data, pos, ch, GRID)
    template = np.abs(truth.sum(axis=0))
    error = rng.normal(scale=0.8, size=truth.shape[0])
    basis = truth * np.exp(1j * error)[:, None, None].astype(np.complex64)
    out = {}
    for device in ("cpu", "cuda"):
        out[device] = twin_autofocus(basis, template, AutofocusConfig(iterations=80, device=device))
    d = out["cuda"].phase_rad - out["cpu"].phase_rad
    d = np.angle(np.exp(1j * (d - np.angle(np.exp(1j * d).mean()))))
    assert np.sqrt((d**2).mean()) < 0.02
    assert abs(out["cuda"].loss_history[-1] - out["cpu"].loss_history[-1]) < 1e-3
    # and it focused: the loss fell well below where it started
    assert out["cuda"].loss_history[-1] < 0.5 * out["cuda"].loss_history[0]
