"""Autofocus on the sub-image basis: twin-reference (the paper's method) and baselines.

With the basis B (M, H, W) of a region (``twinfocus.imaging.backprojection.numba_backend.subimage_basis``) the image
corrected by one phase per radar position is

    image(phi) = sum_m exp(j phi_m) B_m.

The twin method (source paper, section 4.2) finds phi that makes the max-normalised, soft-
thresholded amplitude of the *reference* region match the template under the loss 1 - SSIM, with
Adam (lr 5e-2), cosine annealing to 1e-5 and 300 iterations, phi starting at 0; the same phi then
focuses the *target* region (phase transfer: ``form_image(target_basis, phi)``).

Speed: the basis is held as one real matrix [Re B | Im B] (M, 2P) so each iteration is two
matrix products over it (forward and gradient); at the paper size (780 x 100 x 100) that is the
whole cost (see docs/performance.md).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.focus.phase_ramp import (  # fit_linear_phase: also found here by its callers
    fit_linear_phase,
    ramp_free_coherence,
)
from twinfocus.focus.settings import FOCUS_SETTINGS, config_default
from twinfocus.focus.template_match import (
    OUTLINE_CHOICE,
    OUTLINE_CHOICES,
    averaged_outline_phase,
    correlation_phase,
    outline_phase,
    projection_phase,
    register_template,
)
from twinfocus.imaging.basis import form_image
from twinfocus.imaging.device import resolve_device
from twinfocus.imaging.metrics import ssim, ssim_torch

if TYPE_CHECKING:  # torch is imported where the optimiser runs: the closed-form estimators need none
    import torch

ProgressFn = Callable[[int, int, float], None]
#: where the optimiser's phases start (:attr:`AutofocusConfig.init`)
INITS = ("zero", "correlation", "projection", "outline")


@dataclass
class AutofocusConfig:
    """Optimiser settings (defaults: the source paper). The fields that ``twinfocus focus`` and the
    solver node expose take their defaults from :data:`twinfocus.focus.settings.FOCUS_SETTINGS`."""

    iterations: int = config_default("iterations")
    lr: float = config_default("lr")
    lr_min: float = config_default("lr_min")
    threshold_centre: float = config_default("threshold_centre")
    threshold_steepness: float = config_default("threshold_steepness")
    #: steepness of the soft threshold inside the loss only (None: ``threshold_steepness``, the
    #: paper's). A steeper loss (5) lets a smooth digital-twin template match a speckled reference
    #: by its outline (docs/beyond.md); metrics keep ``threshold_steepness``.
    loss_steepness: float | None = config_default("loss_steepness")
    precision: str = config_default("precision")
    basis_dtype: str = config_default("basis_dtype")
    #: the torch device, as decided (:func:`twinfocus.imaging.device.resolve_device`, which
    #: :meth:`from_settings` applies to the ``device`` setting); a config of its own runs on the CPU
    device: str = "cpu"
    #: coarse-to-fine: first ``coarse_iterations`` on images blurred by a Gaussian of
    #: ``coarse_blur_px`` pixels (a smoother loss with fewer local minima when phases wrap),
    #: then ``iterations`` at full resolution from there. 0 = the paper's single stage.
    coarse_iterations: int = config_default("coarse_iterations")
    coarse_blur_px: float = 2.0
    #: where the phases start: "zero" (the paper); "correlation": the closed-form per-position
    #: matched filter against a complex template (:func:`twinfocus.focus.template_match.correlation_phase`);
    #: "projection": alternating projections onto an amplitude template, any template
    #: (:func:`twinfocus.focus.template_match.projection_phase`); "outline": the reference's energy
    #: inside its outline, no template texture (:func:`twinfocus.focus.template_match.outline_phase`,
    #: needs ``twin_autofocus(support=...)``). None needs unwrapping; with ``iterations=0`` the
    #: start is the whole estimate.
    init: str = "zero"
    #: ``init="outline"`` also from the outlines grown from its first estimate's image, the
    #: estimates averaged (:func:`twinfocus.focus.template_match.averaged_outline_phase`: five outline
    #: runs instead of one; needs ``twin_autofocus(aperture_m=...)``). A camera cloud's holes leave
    #: its outline short; docs/digital_twin.md has what it gains. The named estimator "outline"
    #: (:func:`twinfocus.focus.estimators.estimator_settings`) turns it on; off, one outline run.
    outline_ensemble: bool = False
    #: with ``outline_ensemble``, rounds of growing the cloud's outline into what its estimates
    #: light up before the ensemble (:func:`twinfocus.focus.template_match.grown_outline`; the default
    #: is ``template_match.OUTLINE_GROWTH_ROUNDS``). Each costs one outline run (~0.17 s at 780 x
    #: 100 x 100 on 2 cores); docs/digital_twin.md has what they gain. 0: the cloud's outline as it is.
    outline_growth_rounds: int = 2
    #: how ``init="outline"`` picks one of its starts' ends: "auto" (the most energy inside the
    #: outline unless that end piled it), "energy" or "speckle"
    #: (:data:`twinfocus.focus.template_match.OUTLINE_CHOICES`; docs/digital_twin_field.md)
    outline_choice: str = OUTLINE_CHOICE
    #: projection steps of ``init="projection"`` (~3 ms each at 780 x 100 x 100 on 2 cores)
    projection_iterations: int = config_default("projection_iterations")
    #: ``init="projection"`` also from this many random starts (fixed seed); the end with the
    #: lowest loss (:func:`template_loss`) starts the optimiser. Pays past lambda/4, where the
    #: projections' local maxima differ; each costs ``projection_iterations`` steps + one loss.
    projection_restarts: int = config_default("projection_restarts")
    #: ``init="projection"`` with ``iterations`` > 0: run the optimiser only when the projections'
    #: phases have wrapped, i.e. when their coherence |mean exp(j (phi - ramp))| (the constant +
    #: linear-in-aperture ramp taken out, :func:`fit_linear_phase`) times sqrt(M) is below this.
    #: Within about lambda/5 of tracking error the phases hold together and the projections alone
    #: are best (the optimiser pulls a speckled reference towards the template's texture); past
    #: it every phase wraps and the optimiser finds what the projections miss. 0: always run it.
    #: ``--estimator auto`` sets it for an amplitude template without an outline (docs/digital_twin.md).
    refine_below_coherence: float = 0.0
    #: prior that the hand moves smoothly: adds ``smoothness_weight`` x mean |exp(j phi_{m+1}) -
    #: exp(j phi_m)|^2 over consecutive radar positions (basis order = capture order) to the loss.
    #: A chord on the unit circle, so it never fights a wrap. 0 = the paper (no prior).
    smoothness_weight: float = 0.0
    #: "none", or "correlation": first move a complex template to where the scan puts the reference
    #: (:func:`twinfocus.focus.template_match.register_template`), so a misplaced twin pulls no shift in
    template_registration: str = "none"
    registration_max_shift_px: int = 4

    def validate(self) -> None:
        if self.init not in INITS:
            raise TwinFocusError(f"init must be one of {', '.join(map(repr, INITS))}, got {self.init!r}")
        if int(self.projection_restarts) < 0:
            raise TwinFocusError(f"projection_restarts must be >= 0, got {self.projection_restarts}")
        if int(self.outline_growth_rounds) < 0:
            raise TwinFocusError(f"outline_growth_rounds must be >= 0, got {self.outline_growth_rounds}")
        if self.outline_choice not in OUTLINE_CHOICES:
            raise TwinFocusError(
                f"outline_choice must be one of {', '.join(OUTLINE_CHOICES)}, got {self.outline_choice!r}"
            )
        if not (np.isfinite(self.refine_below_coherence) and self.refine_below_coherence >= 0):
            raise TwinFocusError(f"refine_below_coherence must be >= 0, got {self.refine_below_coherence}")
        if int(self.projection_iterations) < 1:
            raise TwinFocusError(f"projection_iterations must be >= 1, got {self.projection_iterations}")
        if self.template_registration not in ("none", "correlation"):
            raise TwinFocusError(
                f"template_registration must be 'none' or 'correlation', got {self.template_registration!r}"
            )
        if int(self.registration_max_shift_px) < 1:
            raise TwinFocusError(f"registration_max_shift_px must be >= 1, got {self.registration_max_shift_px}")
        if int(self.iterations) < (1 if self.init == "zero" else 0):
            raise TwinFocusError(
                f"iterations must be >= 1 (0 only with init 'correlation', 'projection' or 'outline'), got {self.iterations}"
            )
        if not self.lr > 0 or not self.lr_min >= 0:
            raise TwinFocusError(f"learning rates must be positive, got lr={self.lr}, lr_min={self.lr_min}")
        if self.precision not in ("float32", "float64"):
            raise TwinFocusError(f"precision must be 'float32' or 'float64', got {self.precision!r}")
        if int(self.coarse_iterations) < 0 or not self.coarse_blur_px >= 0:
            raise TwinFocusError("coarse_iterations and coarse_blur_px must be non-negative")
        if not (np.isfinite(self.smoothness_weight) and self.smoothness_weight >= 0):
            raise TwinFocusError(f"smoothness_weight must be a non-negative number, got {self.smoothness_weight}")
        if self.loss_steepness is not None and not self.loss_steepness > 0:
            raise TwinFocusError(
                f"loss_steepness must be positive, or unset for the estimator's default, got {self.loss_steepness}"
            )
        if self.basis_dtype not in ("float32", "float16"):
            raise TwinFocusError(f"basis_dtype must be 'float32' or 'float16', got {self.basis_dtype!r}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_settings(cls, values: Mapping[str, Any], **overrides) -> AutofocusConfig:
        """The config that focus settings make (``values``: name -> value for every entry of
        :data:`~twinfocus.focus.settings.FOCUS_SETTINGS` that has a ``config`` field, e.g. a parsed
        ``twinfocus focus`` or the solver's parameters), then ``overrides`` (an estimator's
        fields, :func:`~twinfocus.focus.estimators.estimator_settings`); the device is resolved
        (:func:`~twinfocus.imaging.device.resolve_device`). Validated."""
        fields = {s.config: values[s.name] for s in FOCUS_SETTINGS if s.config}
        fields["device"] = resolve_device(fields["device"])
        cfg = cls(**{**fields, **overrides})
        cfg.validate()
        return cfg


@dataclass
class AutofocusResult:
    """phase_rad float64 (M,); loss_history float64 (iterations,); image complex64 (H, W): the
    corrected region the optimiser looked at; time_s: optimiser wall time."""

    phase_rad: np.ndarray
    loss_history: np.ndarray
    image: np.ndarray
    time_s: float
    method: str
    extra: dict = field(default_factory=dict)


@functools.cache
def _half_basis_product():
    """The autograd function below, defined on first use so importing this module needs no torch."""
    import torch

    class _HalfBasisProduct(torch.autograd.Function):
        """y = cs @ A with A held in float16 twice, once per product layout.

        Torch's CPU half-precision GEMM is fast only when its second operand is a transposed view,
        so the forward keeps A^T (2P, M) and the backward A (M, 2P) contiguous; operands are scaled
        to unit peak before the cast so nothing overflows or flushes to zero.
        """

        @staticmethod
        def forward(ctx, cs, a_rows, a_cols):
            ctx.save_for_backward(a_rows)
            return (cs.half() @ a_cols.T).float()

        @staticmethod
        def backward(ctx, grad):
            (a_rows,) = ctx.saved_tensors
            scale = grad.abs().max().clamp_min(1e-30)
            return ((grad / scale).half() @ a_rows.T).float() * scale, None, None

    return _HalfBasisProduct


class _BasisOperator:
    """The map phi -> amplitude image as torch operations on the stacked real basis
    [Re B | Im B] (M, 2P). ``basis_dtype`` float16 halves the memory traffic that bounds the
    optimiser's speed (relative error of a product ~4e-4, docs/performance.md)."""

    def __init__(self, basis: np.ndarray, dtype, device: str, basis_dtype: str = "float32"):
        import torch

        basis = np.asarray(basis)
        if basis.ndim != 3 or not np.iscomplexobj(basis):
            raise TwinFocusError(f"basis must be complex (M, H, W), got {basis.dtype} {basis.shape}")
        if not np.isfinite(basis).all():
            raise TwinFocusError("basis holds NaN or inf")
        self.shape = basis.shape[1:]
        self.n_pix = int(np.prod(self.shape))
        self.dtype = dtype
        flat = basis.reshape(basis.shape[0], -1)
        peak = float(np.abs(flat).max()) or 1.0
        # The amplitude is max-normalised downstream, so the basis scale is free: unit peak.
        stacked = np.concatenate([flat.real, flat.imag], axis=1) / peak
        self.half = basis_dtype == "float16"
        if self.half:
            rows = torch.from_numpy(stacked.astype(np.float16)).to(device)
            self.a_rows, self.a_cols = rows, rows.T.contiguous()
        elif basis_dtype == "float32":
            self.matrix = torch.from_numpy(np.ascontiguousarray(stacked)).to(device=device, dtype=dtype)
        else:
            raise TwinFocusError(f"basis_dtype must be 'float32' or 'float16', got {basis_dtype!r}")

    def amplitude(self, phase):
        import torch

        cs = torch.stack([torch.cos(phase), torch.sin(phase)])  # (2, M)
        if self.half:
            y = _half_basis_product().apply(cs.float(), self.a_rows, self.a_cols).to(self.dtype)
        else:
            y = cs @ self.matrix  # (2, 2P): [c.Br | c.Bi ; s.Br | s.Bi]
        p = self.n_pix
        re = y[0, :p] - y[1, p:]
        im = y[0, p:] + y[1, :p]
        # The epsilon keeps the gradient of |.| finite at exact zeros.
        return torch.sqrt(re * re + im * im + 1e-30).reshape(self.shape)


def _prepare_template(template: np.ndarray, shape: tuple[int, int], cfg: AutofocusConfig) -> np.ndarray:
    t = np.asarray(template, dtype=np.float64)
    if t.shape != tuple(shape):
        raise TwinFocusError(f"template is {t.shape} but the reference region is {tuple(shape)}")
    if not np.isfinite(t).all():
        raise TwinFocusError("template holds NaN or inf")
    t = np.abs(t)
    if t.max() <= 0:
        raise TwinFocusError("template is empty (all zeros)")
    if t.max() - t.min() <= 1e-6 * t.max():
        raise TwinFocusError("template is constant: it holds no structure to focus on")
    t = t / t.max()
    return 1.0 / (1.0 + np.exp(-_loss_steepness(cfg) * (t - cfg.threshold_centre)))


def _loss_steepness(cfg: AutofocusConfig) -> float:
    return float(cfg.threshold_steepness if cfg.loss_steepness is None else cfg.loss_steepness)


def _run_adam(
    loss_fn: Callable[[torch.Tensor], torch.Tensor],
    n_positions: int,
    cfg: AutofocusConfig,
    dtype: torch.dtype,
    progress: ProgressFn | None,
    init: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    import torch

    phase0 = np.zeros(n_positions) if init is None else np.asarray(init, dtype=np.float64)
    phase = torch.tensor(phase0, dtype=dtype, device=cfg.device, requires_grad=True)
    opt = torch.optim.Adam([phase], lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=int(cfg.iterations), eta_min=cfg.lr_min)
    losses = np.empty(int(cfg.iterations))
    for it in range(int(cfg.iterations)):
        opt.zero_grad(set_to_none=True)
        loss = loss_fn(phase)
        loss.backward()
        opt.step()
        sched.step()
        losses[it] = float(loss.detach())
        if not np.isfinite(losses[it]):
            raise TwinFocusError(f"autofocus diverged at iteration {it} (loss {losses[it]}); lower the learning rate")
        if progress is not None:
            progress(it + 1, int(cfg.iterations), losses[it])
    return phase.detach().cpu().double().numpy(), losses


def _torch_dtype(cfg: AutofocusConfig):
    import torch

    return torch.float32 if cfg.precision == "float32" else torch.float64


def twin_autofocus(
    basis: np.ndarray,
    template: np.ndarray,
    config: AutofocusConfig | None = None,
    progress: ProgressFn | None = None,
    init_phase_rad: np.ndarray | None = None,
    support: np.ndarray | None = None,
    registration_scores: np.ndarray | None = None,
    aperture_m: np.ndarray | None = None,
) -> AutofocusResult:
    """Estimate per-position phases from a reference region and its template (the paper's method).

    Parameters
    ----------
    basis : complex64 (M, H, W) sub-image basis of the reference region.
    template : float (H, W) focused amplitude of the reference on the same grid (any scale), or
        complex (H, W) (a physical twin's image), which ``config.template_registration`` and
        ``config.init="correlation"`` need (``init="projection"`` takes either).
    config : optimiser settings; ``progress(iteration, total, loss)`` is called every iteration.
    init_phase_rad : float (M,) radians where the optimiser starts (zeros), and where
        ``config.init="projection"`` starts its projections; ignored with ``init="correlation"``.
    support : bool (H, W), the reference's outline on the grid (a digital twin's
        :attr:`~twinfocus.twins.digital_twin.condition.DigitalTwinReference.support`): what
        ``config.init="outline"`` needs.
    registration_scores : float64 (2 S + 1, 2 S + 1), S = ``config.registration_max_shift_px``:
        the registration's scores of ``template`` against all of ``basis``, when already at hand
        (a :class:`~twinfocus.focus.template_match.MatchScores` filled as a live scan arrived, so the
        registration costs nothing after it); computed here when None.
    aperture_m : float (M, 2) each radar position's (x, y) in the aperture plane, metres (the
        mean of its channels' phase centres): ``config.outline_ensemble`` lines its estimates up
        by their linear-in-aperture ramps, ``config.refine_below_coherence`` takes the ramp out of
        the projections' phases.

    Returns
    -------
    AutofocusResult with phase_rad (M,) to apply to any region's basis; ``extra`` holds the
    registration's shift (pixels) and score gain when it ran, ``outline`` (the outline estimator's
    info; with ``config.outline_ensemble`` that of the cloud's outline's run, and
    ``outline_ensemble`` the averaged runs'), ``refine_check`` (``config.refine_below_coherence``:
    the projections' coherence and whether the optimiser ran), and ``template``: the template the phases were
    fitted to (moved by the registration).
    """
    cfg = config or AutofocusConfig()
    cfg.validate()
    extra: dict = {}
    t0 = time.perf_counter()
    if cfg.template_registration == "correlation":
        template, _, extra["registration"] = register_template(
            basis, template, int(cfg.registration_max_shift_px), scores=registration_scores
        )
    if cfg.init == "correlation":
        init_phase_rad = correlation_phase(basis, template)
    elif cfg.init == "projection":
        init_phase_rad, cfg = _projection_start(basis, template, cfg, init_phase_rad, aperture_m, extra)
    elif cfg.init == "outline":
        init_phase_rad = _outline_start(basis, cfg, support, aperture_m, extra)
    extra["template"] = template
    if cfg.init != "zero" and int(cfg.iterations) == 0:
        assert init_phase_rad is not None  # every init but "zero" has set it above
        loss = np.array([template_loss(basis, init_phase_rad, template, cfg)])
        return AutofocusResult(
            init_phase_rad, loss, form_image(basis, init_phase_rad), time.perf_counter() - t0, "twin", extra
        )
    phase, losses = _optimise(basis, template, cfg, progress, init_phase_rad)
    elapsed = time.perf_counter() - t0
    return AutofocusResult(phase, losses, form_image(basis, phase), elapsed, "twin", extra)


def _projection_start(
    basis: np.ndarray,
    template: np.ndarray,
    cfg: AutofocusConfig,
    init_phase_rad: np.ndarray | None,
    aperture_m: np.ndarray | None,
    extra: dict,
) -> tuple[np.ndarray, AutofocusConfig]:
    """``init="projection"``: the projections from ``init_phase_rad`` and ``projection_restarts``
    random starts, the lowest template loss kept; with ``refine_below_coherence``, ``cfg`` comes
    back with no iterations when the projections' coherence says the optimiser would not help.
    Returns (phase float (M,) rad, config); what it chose goes into ``extra``."""

    starts = [init_phase_rad]
    # fixed seed: the same scan gives the same estimate
    rng = np.random.default_rng(0)
    starts += [rng.uniform(-np.pi, np.pi, int(basis.shape[0])) for _ in range(int(cfg.projection_restarts))]
    ends = [projection_phase(basis, template, int(cfg.projection_iterations), s) for s in starts]
    init_phase_rad = ends[0]
    if len(ends) > 1:
        end_losses = [template_loss(basis, e, template, cfg) for e in ends]
        best = int(np.argmin(end_losses))
        init_phase_rad = ends[best]
        extra["projection_restarts"] = {"losses": end_losses, "chosen": best}
    if cfg.refine_below_coherence > 0 and int(cfg.iterations) > 0:
        if aperture_m is None:
            raise TwinFocusError(
                "refine_below_coherence needs each radar position's place in the aperture (aperture_m, (M, 2) "
                "metres) to take the ramp out of the projections' phases"
            )
        extra["refine_check"] = refine_check(init_phase_rad, aperture_m, cfg.refine_below_coherence)
        if not extra["refine_check"]["refined"]:
            cfg = replace(cfg, iterations=0)
    return init_phase_rad, cfg


def _outline_start(
    basis: np.ndarray, cfg: AutofocusConfig, support: np.ndarray | None, aperture_m: np.ndarray | None, extra: dict
) -> np.ndarray:
    """``init="outline"``: the phase that fills the reference's outline ``support`` (bool (H, W)),
    averaged over the ensemble with ``outline_ensemble``. Returns float (M,) rad; the outline's
    info goes into ``extra``."""

    if support is None:
        raise TwinFocusError(
            "the outline estimator needs the reference's outline (a digital twin from a point "
            "cloud gives one: --digital-twin); choose another --estimator for this template"
        )
    if not cfg.outline_ensemble:
        phase, extra["outline"] = outline_phase(basis, support, choose=cfg.outline_choice)
        return phase
    if aperture_m is None:
        raise TwinFocusError(
            "outline_ensemble needs each radar position's place in the aperture (aperture_m, (M, 2) metres) "
            "to line the estimates up"
        )
    phase, ensemble = averaged_outline_phase(
        basis, support, aperture_m, growth_rounds=cfg.outline_growth_rounds, choose=cfg.outline_choice
    )
    extra["outline"] = ensemble.pop("first")
    extra["outline_ensemble"] = ensemble
    return phase


def _optimise(
    basis: np.ndarray,
    template: np.ndarray,
    cfg: AutofocusConfig,
    progress: ProgressFn | None,
    init_phase_rad: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """The paper's optimiser: Adam on 1 - SSIM(soft-thresholded image, template), after
    ``coarse_iterations`` on blurred images when asked. Returns (phase float (M,) rad, the loss
    of every iteration, coarse ones first)."""
    import torch

    dtype = _torch_dtype(cfg)
    op = _BasisOperator(basis, dtype, cfg.device, cfg.basis_dtype)
    tpl = np.abs(np.asarray(template)).astype(np.float64)
    target = torch.from_numpy(_prepare_template(tpl, op.shape, cfg)).to(device=cfg.device, dtype=dtype)

    def make_loss(blur_px: float):
        if blur_px > 0:
            by = torch.from_numpy(_blur_matrix(op.shape[0], blur_px)).to(device=cfg.device, dtype=dtype)
            bx = torch.from_numpy(_blur_matrix(op.shape[1], blur_px)).to(device=cfg.device, dtype=dtype)
            blurred_tpl = (by @ torch.from_numpy(tpl).to(device=cfg.device, dtype=dtype) @ bx.T).cpu().numpy()
            goal = torch.from_numpy(_prepare_template(blurred_tpl, op.shape, cfg)).to(device=cfg.device, dtype=dtype)
        else:
            goal = target

        def loss_fn(phase: torch.Tensor) -> torch.Tensor:
            amp = op.amplitude(phase)
            if blur_px > 0:
                amp = by @ amp @ bx.T
            soft = torch.sigmoid(_loss_steepness(cfg) * (amp / amp.max() - cfg.threshold_centre))
            loss = 1.0 - ssim_torch(soft, goal)
            if cfg.smoothness_weight > 0:
                loss = loss + cfg.smoothness_weight * smoothness_penalty(phase)
            return loss

        return loss_fn

    init = init_phase_rad
    history: list[np.ndarray] = []
    if cfg.coarse_iterations > 0:
        coarse = replace(cfg, iterations=cfg.coarse_iterations)
        init, coarse_losses = _run_adam(make_loss(cfg.coarse_blur_px), basis.shape[0], coarse, dtype, progress, init)
        history.append(coarse_losses)
    phase, losses = _run_adam(make_loss(0.0), basis.shape[0], cfg, dtype, progress, init)
    history.append(losses)
    return phase, np.concatenate(history)


def refine_check(phase_rad: np.ndarray, aperture_m: np.ndarray, refine_below: float) -> dict:
    """Whether the optimiser should refine a closed-form estimate (``refine_below_coherence``):
    yes when its phases, their constant + linear ramp taken out, hold together less than
    ``refine_below`` (coherence x sqrt(M), :func:`ramp_free_coherence`): they have wrapped.

    phase_rad : float (M,) radians; aperture_m : float (M, 2) metres. Returns the record
    metrics.json keeps: ``coherence_sqrt_m``, ``refine_below``, ``refined``, ``why``."""
    coherence = ramp_free_coherence(phase_rad, aperture_m)
    refine = coherence < refine_below
    return {
        "coherence_sqrt_m": round(coherence, 3),
        "refine_below": float(refine_below),
        "refined": bool(refine),
        "why": (
            "the projections' phases have wrapped (tracking error past about lambda/5): the optimiser ran"
            if refine
            else "the projections' phases hold together (tracking error within about lambda/5): projections alone"
        ),
    }


def template_loss(
    basis: np.ndarray, phase_rad: np.ndarray, template: np.ndarray, config: AutofocusConfig | None = None
) -> float:
    """The optimiser's loss 1 - SSIM(soft(|image(phi)|), soft(|template|)) at one phase (M,)
    radians, in float64 on the CPU: for estimates that do not come from the optimiser."""
    cfg = config or AutofocusConfig()
    shape = np.asarray(basis).shape[1:]
    amp = _prepare_template(np.abs(form_image(basis, phase_rad)), shape, cfg)
    return 1.0 - ssim(amp, _prepare_template(np.abs(template), shape, cfg))


def smoothness_penalty(phase: torch.Tensor) -> torch.Tensor:
    """mean_m |exp(j phi_{m+1}) - exp(j phi_m)|^2 = mean 2 (1 - cos(phi_{m+1} - phi_m)): 0 for a
    constant phase, 2 on average for independent ones; phase (M,) radians in capture order."""
    import torch

    return 2.0 * (1.0 - torch.cos(phase[1:] - phase[:-1])).mean()


def _blur_matrix(n: int, sigma_px: float) -> np.ndarray:
    """(n, n) Gaussian smoothing matrix with rows renormalised at the edges ('same' size)."""
    i = np.arange(n)
    g = np.exp(-((i[:, None] - i[None, :]) ** 2) / (2.0 * sigma_px**2))
    return g / g.sum(axis=1, keepdims=True)


def sharpness_autofocus(
    basis: np.ndarray,
    config: AutofocusConfig | None = None,
    progress: ProgressFn | None = None,
) -> AutofocusResult:
    """Baseline: maximise the image sharpness sum(I^2)/sum(I)^2 (I = |image|^2) of the region
    itself, with the same optimiser. Needs no reference."""
    cfg = config or AutofocusConfig()
    cfg.validate()
    dtype = _torch_dtype(cfg)
    op = _BasisOperator(basis, dtype, cfg.device, cfg.basis_dtype)
    import torch

    def loss_fn(phase):
        inten = op.amplitude(phase) ** 2
        # log keeps the gradient scale independent of the image energy
        return -torch.log((inten**2).sum() / inten.sum() ** 2)

    t0 = time.perf_counter()
    phase, losses = _run_adam(loss_fn, basis.shape[0], cfg, dtype, progress)
    elapsed = time.perf_counter() - t0
    return AutofocusResult(phase, losses, form_image(basis, phase), elapsed, "sharpness")


def no_correction(basis: np.ndarray) -> AutofocusResult:
    """Baseline: phi = 0."""
    phase = np.zeros(np.asarray(basis).shape[0])
    return AutofocusResult(phase, np.zeros(0), form_image(basis, phase), 0.0, "none")


#: how the estimated phase's constant + linear ramp is handled before the transfer (``--phase-ramp``)
RAMP_MODES = ("auto", "remove", "keep")
#: the largest template misplacement ``auto`` takes a ramp for, metres: a physical twin placed by
#: hand to ~1 mm, a digital twin's camera-to-radar offset of 2-3 mm
MAX_TEMPLATE_OFFSET_M = 3e-3
#: the same with the positions' range errors measured (``range_errors_m``), metres: the ramp then
#: left is the misplacement alone, which for a camera cloud's outline is the camera's offset (2-3
#: mm) plus the outline's shift search (3 px, ~7 mm across y on the field scenes)
MAX_TEMPLATE_OFFSET_RANGED_M = 10e-3
#: the coherence x sqrt(M) the ramp fitted with the range errors taken out must leave to be
#: removed: above the fit's detection threshold (4), since moving the image by a wrong ramp costs
#: more than leaving it; on the field scenes every draw between 4 and 5 that moved the image by
#: more than 2 mm moved it the wrong way (docs/digital_twin.md)
MIN_RANGED_RAMP_COHERENCE_SQRT_M = 5.0


def transfer_phase(
    phase_rad: np.ndarray,
    aperture_m: np.ndarray,
    range_m: float,
    wavelength_m: float,
    mode: str = "auto",
    registered: bool = False,
    max_template_offset_m: float = MAX_TEMPLATE_OFFSET_M,
    range_errors_m: np.ndarray | None = None,
) -> tuple[np.ndarray, dict]:
    """The phase to apply to the target, and why: the estimate with or without its constant +
    linear-in-aperture ramp (:func:`fit_linear_phase`).

    A ramp b across the aperture moves the image by b R / k (k = 4 pi / lambda, R the range), so
    a misplaced template pulls one in, and transferring it would move the target. But a hand's
    drift also has a ramp-like part (each column of a sweep drifts its own way), which is real
    error and must be transferred. ``auto`` removes only what a template's misplacement explains:

    * nothing when the template was registered to the scan (``registered``: its misplacement was
      measured and taken out before the estimate);
    * otherwise the fitted ramp when the image shift it stands for is at most
      ``max_template_offset_m`` on both axes, and nothing when it is larger (no template is that
      far off: the ramp is tracking error).

    ``remove`` always removes the fitted ramp, ``keep`` never does (the source paper).

    Past about lambda/5 of tracking error the estimate's phases wrap and its ramp cannot be told
    from the errors. ``range_errors_m`` (M,), each position's range error measured from the band's
    halves (:func:`twinfocus.focus.band_delay.position_range_errors_m`), then lets the fit see it: the
    ramp is fitted to the estimate with those errors' phase 4 pi dR / lambda taken out, which
    leaves the misplacement's ramp and noise; it counts only when it leaves a coherence of at
    least ``MIN_RANGED_RAMP_COHERENCE_SQRT_M``, and ``auto`` takes it up to
    ``MAX_TEMPLATE_OFFSET_RANGED_M`` (the tracking error is then out of it).

    phase_rad : float (M,) radians; aperture_m : float (M, 2) each position's (x, y), metres;
    range_m : distance from the aperture to the reference, metres. Returns (float64 (M,) radians,
    info dict: ``mode``, ``removed``, ``reason``, ``implied_shift_m`` (x, y) of the fitted ramp,
    ``from_range_errors`` and, with them, ``ramp_coherence_sqrt_m``).
    """
    if mode not in RAMP_MODES:
        raise TwinFocusError(f"phase ramp mode must be one of {', '.join(RAMP_MODES)}, got {mode!r}")
    phi = np.asarray(phase_rad, dtype=np.float64)
    info: dict = {"mode": mode, "from_range_errors": range_errors_m is not None}
    if range_errors_m is None:
        ramp, coeffs = fit_linear_phase(phi, aperture_m)
    else:
        dr = np.asarray(range_errors_m, dtype=np.float64)
        if dr.shape != phi.shape:
            raise TwinFocusError(f"range_errors_m must have one value per radar position ({phi.size}), got {dr.shape}")
        ranged = phi + 4.0 * np.pi / float(wavelength_m) * dr
        ramp, coeffs = fit_linear_phase(ranged, aperture_m, min_coherence_sqrt_m=0.0)
        coherence = float(np.abs(np.exp(1j * (ranged - ramp)).mean()) * np.sqrt(phi.size))
        info["ramp_coherence_sqrt_m"] = round(coherence, 3)
        # the linear part alone (the ranged fit's constant is not the estimate's), and none when
        # it is not clear enough to move the image by
        linear = ramp - coeffs[0]
        if coherence < MIN_RANGED_RAMP_COHERENCE_SQRT_M:
            linear, coeffs = np.zeros_like(phi), np.zeros(3)
        ramp = linear + np.angle(np.exp(1j * (phi - linear)).mean())
        max_template_offset_m = max(max_template_offset_m, MAX_TEMPLATE_OFFSET_RANGED_M)
    shift = coeffs[1:] * float(range_m) * float(wavelength_m) / (4.0 * np.pi)
    info.update(implied_shift_m=shift.tolist(), slope_rad_per_m=coeffs[1:].tolist())
    if mode == "remove":
        remove, why = True, "removed on request"
    elif mode == "keep":
        remove, why = False, "kept on request (the source paper)"
    elif registered:
        remove, why = (
            False,
            "kept: the template was registered to the scan, so no misplacement ramp is left in the estimate",
        )
    elif range_errors_m is not None and not np.any(coeffs[1:]):
        remove, why = (
            False,
            f"nothing to remove: with the range errors taken out no ramp stands out (coherence x sqrt(M) "
            f"{info['ramp_coherence_sqrt_m']:.2f} < {MIN_RANGED_RAMP_COHERENCE_SQRT_M})",
        )
    elif np.all(np.abs(shift) <= max_template_offset_m):
        remove, why = (
            True,
            (
                f"removed: it moves the image by ({shift[0] * 1e3:+.1f}, {shift[1] * 1e3:+.1f}) mm, "
                f"what a template misplaced by up to {max_template_offset_m * 1e3:.0f} mm explains"
            ),
        )
    else:
        remove, why = (
            False,
            (
                f"kept: it moves the image by ({shift[0] * 1e3:+.1f}, {shift[1] * 1e3:+.1f}) mm, more than "
                f"a template misplaced by up to {max_template_offset_m * 1e3:.0f} mm explains: tracking error"
            ),
        )
    if range_errors_m is not None and mode != "keep" and not registered and np.any(coeffs[1:]):
        why += " (fitted with the positions' range errors, measured from the band's halves, taken out)"
    info.update(removed=bool(remove), reason=why)
    return (np.angle(np.exp(1j * (phi - ramp))) if remove else phi), info
