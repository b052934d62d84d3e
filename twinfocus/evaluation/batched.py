"""The paper's optimiser on several templates of one reference basis at once.

The evaluation runs the paper's twin optimiser (:func:`twinfocus.focus.autofocus.twin_autofocus` with
its defaults: phases from zero, one stage, 300 Adam steps) more than once on the same reference
basis of a draw: the physical and the digital twin, and a template from each room. Each step's
cost is two products with the basis (forward and gradient, docs/performance.md). Torch's CPU
half-precision product reads the whole float16 basis once per estimate; here the basis is turned
into float32 one cache-sized block at a time and every estimate's rows go through that block
together, so R estimates read the basis once per step instead of R times.

The arithmetic is the single run's: phases and gradients are rounded to float16 as
:class:`twinfocus.focus.autofocus._BasisOperator`'s product rounds them, products accumulate in float32
and are rounded to float16, each estimate's gradient is scaled by its own peak. Adam acts on
every element alone and the summed loss gives each row its own gradient, so each estimate is the
single run's up to float32 summation order (tests/test_evaluation_batched.py).
"""

from __future__ import annotations

import functools
import time
from typing import TYPE_CHECKING

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.focus.autofocus import AutofocusConfig, _loss_steepness, _prepare_template, _torch_dtype
from twinfocus.imaging.metrics import ssim_torch

if TYPE_CHECKING:
    import torch

#: float32 bytes of one converted block of the basis: fits a core's share of cache
BLOCK_BYTES = 2 << 20


def batchable(cfg: AutofocusConfig) -> bool:
    """Whether ``cfg`` is the paper's single-stage optimiser from zero that
    :func:`paper_estimates` runs (no coarse stage, registration, prior or closed-form start)."""
    return (
        cfg.init == "zero"
        and int(cfg.coarse_iterations) == 0
        and cfg.template_registration == "none"
        and cfg.smoothness_weight == 0
        and int(cfg.iterations) >= 1
    )


@functools.cache
def _blocked_product():
    """The autograd function below, defined on first use so importing this module needs no torch."""
    import torch

    class _BlockedHalfProduct(torch.autograd.Function):
        """y = cs @ A^T for cs (R, M) float32 and A (N, M) float16, A read once per call."""

        @staticmethod
        def forward(ctx, cs, a_cols, block_rows: int):
            ctx.save_for_backward(a_cols)
            ctx.block_rows = block_rows
            cs16 = cs.half().float()
            if a_cols.device.type != "cpu":
                return (cs16.half() @ a_cols.T).float()
            n = a_cols.shape[0]
            out = torch.empty(cs.shape[0], n, dtype=torch.float32)
            buf = torch.empty(min(block_rows, n), a_cols.shape[1], dtype=torch.float32)
            for i in range(0, n, block_rows):
                blk = buf[: min(block_rows, n - i)]
                blk.copy_(a_cols[i : i + block_rows])
                torch.mm(cs16, blk.T, out=out[:, i : i + block_rows])
            return out.half().float()

        @staticmethod
        def backward(ctx, grad):
            (a_cols,) = ctx.saved_tensors
            block_rows = ctx.block_rows
            # one scale per estimate, as each single run scales its own gradient
            scale = grad.abs().amax(dim=1, keepdim=True).clamp_min(1e-30)
            g16 = (grad / scale).half().float()
            if a_cols.device.type != "cpu":
                return (g16.half() @ a_cols).float() * scale, None, None
            n = a_cols.shape[0]
            out = torch.zeros(grad.shape[0], a_cols.shape[1], dtype=torch.float32)
            buf = torch.empty(min(block_rows, n), a_cols.shape[1], dtype=torch.float32)
            for i in range(0, n, block_rows):
                blk = buf[: min(block_rows, n - i)]
                blk.copy_(a_cols[i : i + block_rows])
                out.addmm_(g16[:, i : i + block_rows], blk)
            return out.half().float() * scale, None, None

    return _BlockedHalfProduct


def paper_estimates(
    basis: np.ndarray, templates: list[np.ndarray], config: AutofocusConfig
) -> tuple[list[np.ndarray | TwinFocusError], float]:
    """Per-position phases from one reference basis and each of ``templates``, as
    ``twin_autofocus(basis, template, config).phase_rad`` gives them one at a time.

    Parameters
    ----------
    basis : complex64 (M, H, W) sub-image basis of the reference region.
    templates : R float or complex (H, W) templates on the same grid (any scale; amplitude used).
    config : the optimiser's settings; :func:`batchable` must hold and ``basis_dtype`` be float16.

    Returns
    -------
    (R entries: float64 (M,) phases in radians, or the TwinFocusError the single run would have
    raised (a bad template, a divergence); wall seconds of the whole batch).
    """
    import torch

    cfg = config
    cfg.validate()
    if not batchable(cfg) or cfg.basis_dtype != "float16":
        raise TwinFocusError("batched estimates run the paper's single-stage optimiser from zero on a float16 basis")
    basis = np.asarray(basis)
    if basis.ndim != 3 or not np.iscomplexobj(basis):
        raise TwinFocusError(f"basis must be complex (M, H, W), got {basis.dtype} {basis.shape}")
    if not np.isfinite(basis).all():
        raise TwinFocusError("basis holds NaN or inf")
    t0 = time.perf_counter()
    m, h, w = basis.shape
    p = h * w
    results: list[np.ndarray | TwinFocusError] = []
    goals = []
    for tpl in templates:
        try:
            goals.append(_prepare_template(np.abs(np.asarray(tpl)).astype(np.float64), (h, w), cfg))
            results.append(np.zeros(0))
        except TwinFocusError as exc:
            results.append(exc)
    rows = [i for i, r in enumerate(results) if not isinstance(r, TwinFocusError)]
    if not rows:
        return results, time.perf_counter() - t0
    dtype = _torch_dtype(cfg)
    flat = basis.reshape(m, -1)
    peak = float(np.abs(flat).max()) or 1.0
    stacked = np.concatenate([flat.real, flat.imag], axis=1) / peak  # (M, 2P), unit peak as _BasisOperator
    a_cols = torch.from_numpy(np.ascontiguousarray(stacked.astype(np.float16).T)).to(cfg.device)  # (2P, M)
    block_rows = max(1, BLOCK_BYTES // (4 * m))
    goal = torch.from_numpy(np.stack(goals)).to(device=cfg.device, dtype=dtype)  # (R, H, W)
    product = _blocked_product()
    k = _loss_steepness(cfg)

    def losses_of(phase: torch.Tensor) -> torch.Tensor:
        cs = torch.cat([torch.cos(phase), torch.sin(phase)])  # (2R, M): cos rows, then sin rows
        y = product.apply(cs.float(), a_cols, block_rows).to(dtype)
        n = phase.shape[0]
        re = y[:n, :p] - y[n:, p:]
        im = y[:n, p:] + y[n:, :p]
        amp = torch.sqrt(re * re + im * im + 1e-30).reshape(n, h, w)
        peak_r = amp.amax(dim=(1, 2), keepdim=True)
        soft = torch.sigmoid(k * (amp / peak_r - cfg.threshold_centre))
        return 1.0 - ssim_torch(soft, goal)

    iterations = int(cfg.iterations)
    phase = torch.zeros(len(rows), m, dtype=dtype, device=cfg.device, requires_grad=True)
    opt = torch.optim.Adam([phase], lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=iterations, eta_min=cfg.lr_min)
    diverged: dict[int, tuple[int, float]] = {}
    for it in range(iterations):
        opt.zero_grad(set_to_none=True)
        losses = losses_of(phase)
        losses.sum().backward()
        opt.step()
        sched.step()
        values = losses.detach().cpu().double().numpy()
        for bad in np.flatnonzero(~np.isfinite(values)).tolist():
            diverged.setdefault(bad, (it, float(values[bad])))
    phases = phase.detach().cpu().double().numpy()
    for j, i in enumerate(rows):
        if j in diverged:
            it, value = diverged[j]
            results[i] = TwinFocusError(f"autofocus diverged at iteration {it} (loss {value}); lower the learning rate")
        else:
            results[i] = phases[j]
    return results, time.perf_counter() - t0
