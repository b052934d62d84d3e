"""The rungs of the ladder of correction models, and their registry (:data:`RUNGS`, name -> class).

Each rung is a plain estimator in scikit-learn's sense: its settings are its constructor's
arguments and never change; :meth:`Rung.fit` returns a :class:`Fitted` result (the richer
:class:`~twinfocus.focus.ladder.Model` and what the fit recorded) and :meth:`Rung.keep` a
:class:`Verdict` (kept or not, why, the model the rungs above start from, what the rule measured).
Nothing is written on the rung, so one rung object serves any number of scans in any order
(:class:`twinfocus.focus.plan.FocusPlan` builds the rungs once and climbs them for every focus).

A new rung is one class here and one line in the registry,
:data:`twinfocus.focus.estimators.RUNG_REGISTRY`, which :data:`RUNGS` resolves (docs/architecture.md, "Adding a
rung"); :func:`twinfocus.focus.plan.ladder_modes` says where it stands in a ladder.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.focus.autofocus import (
    AutofocusConfig,
    AutofocusResult,
    refine_check,
    sharpness_autofocus,
    transfer_phase,
    twin_autofocus,
)
from twinfocus.focus.band_delay import bright_pixels, position_range_errors_m
from twinfocus.focus.estimators import RUNG_REGISTRY
from twinfocus.focus.ladder import (
    FAST_FIT,
    HELDOUT_FIT,
    MODES,
    SPACE_VARIANT_MIN_RESIDUAL,
    Model,
    Problem,
    complex_match,
    heldout_gain,
    heldout_split,
    heldout_verdict,
    reference_evidence,
)
from twinfocus.focus.phase_ramp import MIN_RAMP_COHERENCE_SQRT_M, ramp_free_coherence
from twinfocus.focus.reference_free import cells_summary, reference_free_autofocus, resolution_cells
from twinfocus.focus.settings import config_default
from twinfocus.focus.template_match import correlation_phase, register_template
from twinfocus.imaging.basis import form_image


@dataclass(frozen=True)
class LadderSettings:
    """What a rung of one ladder may read of the plan when it is made (:meth:`Rung.made_for`):
    ``model`` (``--model``), the placement's and the drift's own settings, and every rung's mode
    by name (:func:`twinfocus.focus.plan.ladder_modes`)."""

    model: str = "auto"
    phase_ramp: str = "auto"
    space_variant: str = "auto"
    modes: dict[str, str] = field(default_factory=dict)


@dataclass
class Fitted:
    """A rung's fit: the richer model, and what the fit recorded (metrics.json
    ``model.rungs[].info``)."""

    model: Model
    info: dict = field(default_factory=dict)


@dataclass
class Verdict:
    """A rung's keep rule on its fit: ``kept``, ``why`` (metrics.json ``model.rungs[].why``),
    ``model`` (what the rungs above start from: the fit when kept), ``info`` (what the rule
    measured, added to the rung's ``info``) and ``heldout`` (the held-out evidence it read, or None)."""

    kept: bool
    why: str
    model: Model
    info: dict = field(default_factory=dict)
    heldout: dict | None = None


def measured_keep(why: str, judged: str, kept: int, draws: int, gain_mean: float, gain_min: float) -> str:
    """A ``keeps_because``: ``why`` the rung keeps its fit whatever it gives, and what a held-out
    rule (:func:`~twinfocus.focus.ladder.heldout_verdict`) said of that fit on the simulated draws
    of benchmarks/bench_rung_keeps.py: on how many of ``draws`` it would have kept it, and the
    gain's mean and least; ``judged``: on what, against what (benchmarks/results/rung_keeps.json,
    which tests/test_rung_keeps.py checks these figures against)."""
    return (
        f"{why}; fitted on one half of {judged}, a held-out rule would have kept it on {kept} of "
        f"{draws} simulated draws (gain {gain_mean:.3f} on average, {gain_min:.3f} at least; "
        "benchmarks/results/rung_keeps.json)"
    )


#: how the reference-free rungs are judged (the target's sharpness: nothing else is there to judge)
_FREE_JUDGED = "the target's blocks and judged on the other by its sharpness against no correction"


class Rung:
    """One correction model. Subclasses set ``name``, ``adds`` (one line), ``cheap`` (closed form:
    ``--model fast`` climbs it whatever the trust line says) and ``keeps_because`` (why a rung without a
    held-out rule always keeps its fit, with what a held-out rule measured of it: :func:`measured_keep`),
    and define :meth:`fit`;
    :meth:`cannot`, :meth:`skip` and :meth:`keep` default to "can", "fit" and "keep".

    mode : "off", "auto", "try" or "on" (``twinfocus.focus.ladder.MODES``); until_trusted : climbed only
    while the model beneath is below the trust line (``--model fast``'s costly rungs)."""

    name: ClassVar[str] = ""
    adds: ClassVar[str] = ""
    cheap: ClassVar[bool] = True
    keeps_because: ClassVar[str] = "fitted"
    #: climbed even when off (its measurement is reported whatever is done with it)
    measured_when_off: ClassVar[bool] = False

    @property
    def refused_as(self) -> str:
        """How a refusal in mode "on" begins (the option that asked for the rung)."""
        return f"--model {self.name}:"

    def __init__(self, mode: str = "auto", *, until_trusted: bool = False):
        if mode not in MODES:
            raise TwinFocusError(f"rung mode must be one of {', '.join(MODES)}, got {mode!r}")
        self.mode = mode
        self.until_trusted = until_trusted

    @classmethod
    def made_for(cls, mode: str, ladder: LadderSettings) -> Rung:
        """The rung in ``mode`` for ``ladder``: its settings from the plan's."""
        return cls(mode, until_trusted=ladder.model == "fast" and not cls.cheap)

    def record(self) -> dict:
        """What the rung's entry records before anything is tried (``info``)."""
        return {}

    def off(self) -> tuple[str, dict]:
        """Why the rung was not tried when off, and what that records."""
        return "off", {}

    def refused(self, why: str) -> dict:
        """What the rung records when it cannot run (:meth:`cannot` said ``why``)."""
        return {}

    def cannot(self, problem: Problem, model: Model) -> str | None:
        """Why this rung cannot run on ``problem`` (refused in mode "on"), or None."""
        return None

    def skip(self, problem: Problem, model: Model) -> tuple[str | None, dict]:
        """Why the fit is not run although it could (auto's checks before fitting) or None, and
        what the checks measured (added to the rung's ``info``; :meth:`keep` reads it too)."""
        return None, {}

    def fit(self, problem: Problem, model: Model) -> Fitted:
        """The richer model fitted on the reference from ``model``."""
        raise NotImplementedError

    def keep(self, problem: Problem, before: Model, fitted: Fitted, measured: dict) -> Verdict:
        """Whether the fit is kept, and why; ``measured``: what :meth:`skip` measured."""
        return Verdict(True, "kept on request" if self.mode == "on" else self.keeps_because, fitted.model)

    def parameters(self, problem: Problem) -> int:
        """How many numbers the rung adds to the model."""
        return 0

    def not_kept(self, before: Model, fitted: Fitted) -> Model:
        """The model the rungs above start from when this one's fit is not kept: ``before``."""
        return before


class NoCorrection(Rung):
    name, adds = "none", "nothing: every position's phase 0"

    @classmethod
    def made_for(cls, mode: str, ladder: LadderSettings) -> Rung:
        return cls("on")  # the baseline is always there

    def fit(self, problem: Problem, model: Model) -> Fitted:
        return Fitted(model)

    def keep(self, problem: Problem, before: Model, fitted: Fitted, measured: dict) -> Verdict:
        return Verdict(True, "the baseline the rungs above are measured against", fitted.model)


def _twin_autofocus(problem: Problem, template: np.ndarray, config: AutofocusConfig, **options) -> AutofocusResult:
    """:func:`~twinfocus.focus.autofocus.twin_autofocus` on the problem's reference basis with
    ``template`` (float (H, W)) and ``config``, its progress reported as the problem's
    "autofocus"; ``options`` are twin_autofocus' other keywords."""
    return twin_autofocus(problem.ref_basis, template, config, progress=problem.progress("autofocus"), **options)


class PhasePerPosition(Rung):
    """One phase per position from the reference, the estimator's closed form (the config's
    ``init``: correlation after the registration, projections or outline); the paper's estimator
    ("zero") has none: its phases are the optimiser's (``refine``). Always kept: it is the estimate
    every rung above refines, and its match is the ``evidence`` the rungs above are judged against."""

    name, adds = "phase", "one phase per position, the estimator's closed form"
    keeps_because = measured_keep(
        "always kept: the estimate every rung above starts from",
        "the reference's blocks and judged on the other against no correction",
        14, 15, 0.4230, 0.0366,
    )  # fmt: skip

    @classmethod
    def made_for(cls, mode: str, ladder: LadderSettings) -> Rung:
        return cls("on" if mode != "off" else "off")

    def cannot(self, problem: Problem, model: Model) -> str | None:
        return None if problem.template is not None else "needs a template"

    def parameters(self, problem: Problem) -> int:
        return int(problem.positions.shape[0])

    def fit(self, problem: Problem, model: Model) -> Fitted:
        cfg = problem.config
        assert problem.template is not None  # cannot() refuses without one
        if cfg.init == "zero":
            template, extra = problem.template, dict[str, Any]()
            if cfg.template_registration == "correlation":
                template, _, extra["registration"] = register_template(
                    problem.ref_basis,
                    template,
                    int(cfg.registration_max_shift_px),
                    scores=problem.registration_scores,
                )
            zero = np.zeros(problem.ref_basis.shape[0])
            info = {"closed_form": "none (the paper's estimator starts the optimiser from 0)", **extra}
            extra["template"] = template
            registered = "registration" in extra
            return Fitted(
                model.evolve(
                    phase_rad=zero,
                    estimate_rad=zero,
                    template=template,
                    extra=extra,
                    registered=registered,
                    estimated=True,
                ),
                info,
            )
        closed = replace(cfg, iterations=0, refine_below_coherence=0.0)
        result = _twin_autofocus(
            problem,
            problem.template,
            closed,
            support=problem.support,
            registration_scores=problem.registration_scores,
            aperture_m=problem.centres[:, :2],
        )
        extra = result.extra
        info = {"closed_form": cfg.init}
        info.update(
            {k: extra[k] for k in ("registration", "projection_restarts", "outline", "outline_ensemble") if k in extra}
        )
        if "outline" in extra:
            # the scan can check where the outline put the reference only while the phases hold
            # together (their ramp is then seen, and the transfer takes a misplacement's out)
            info["phase_coherence_sqrt_m"] = round(ramp_free_coherence(result.phase_rad, problem.centres[:, :2]), 3)
        fitted = model.evolve(
            phase_rad=result.phase_rad,
            estimate_rad=result.phase_rad,
            template=result.extra.get("template", problem.template),
            registered="registration" in result.extra,
            loss_history=result.loss_history,
            extra=result.extra,
            estimated=True,
        )
        return Fitted(fitted, info)

    def heldout(self, problem: Problem, fitted: Model) -> dict | None:
        """The held-out evidence of the correlation's closed form, a sum over the template's
        pixels and so cheap (:func:`~twinfocus.focus.ladder.heldout_verdict`): on each half of
        :func:`~twinfocus.focus.ladder.heldout_split`, the phases of the registered template zeroed
        outside it, judged on the other half against no correction; None for the other estimators
        (a fit on each half as costly as the fit itself: benchmarks/bench_rung_keeps.py measures
        them)."""
        template = fitted.template
        if problem.config.init != "correlation" or template is None or not np.iscomplexobj(template):
            return None
        first = heldout_split(problem)
        if not (np.any(template[first]) and np.any(template[~first])):
            # a template with nothing on one half (a single bright pixel) gives no held-out evidence;
            # recording evidence must never refuse a run the fit itself accepted
            return None
        basis = problem.ref_basis
        uncorrected = form_image(basis, np.zeros(basis.shape[0]))
        folds = [
            heldout_gain(uncorrected, form_image(basis, correlation_phase(basis, template * half)), template, ~half)
            for half in (first, ~first)
        ]
        return heldout_verdict(folds)

    def keep(self, problem: Problem, before: Model, fitted: Fitted, measured: dict) -> Verdict:
        # always kept (its mode is "on" whenever it is climbed; ``keeps_because`` says why, measured);
        # the held-out evidence, where it is cheap, is recorded beside it and decides nothing
        verdict = Verdict(True, self.keeps_because, fitted.model)
        evidence = self.heldout(problem, fitted.model)
        if evidence is not None:
            verdict.why += (
                f"; on this reference, fitted on one half of its blocks and judged on the other, it leaves "
                f"{evidence['unmatched_after']:.4f} unmatched against {evidence['unmatched_before']:.4f} "
                f"uncorrected (gain {evidence['gain']:.4f}, noise {evidence['noise']:.4f})"
            )
            verdict.heldout = evidence
        return verdict


class Refine(Rung):
    """The paper's optimiser (Adam on 1 - SSIM against the template) from the closed form's
    phases. Auto: the estimator decides (``config.iterations``; with ``refine_below_coherence`` and
    the projections, only when their phases have wrapped: :func:`twinfocus.focus.autofocus.refine_check`,
    whose measured ``why`` is then the keep's)."""

    name, adds, cheap = "refine", "the same phases refined by the paper's optimiser", False
    keeps_because = measured_keep(
        "kept as the estimator asks (the optimiser's target SSIM measured in docs/digital_twin.md)",
        "the reference's blocks and judged on the other against the closed form fitted on the same half",
        1, 3, 0.0195, -0.0273,
    )  # fmt: skip

    def cannot(self, problem: Problem, model: Model) -> str | None:
        return None if problem.template is not None else "needs a template"

    def skip(self, problem: Problem, model: Model) -> tuple[str | None, dict]:
        cfg = problem.config
        if self.mode != "auto":
            return None, {}
        if int(cfg.iterations) == 0:
            return f"the estimator is closed form ({cfg.init}): no optimiser", {}
        if cfg.init == "projection" and cfg.refine_below_coherence > 0:
            check = refine_check(model.estimate_rad, problem.centres[:, :2], cfg.refine_below_coherence)
            return (None if check["refined"] else check["why"]), {"refine_check": check}
        return None, {}

    def fit(self, problem: Problem, model: Model) -> Fitted:
        cfg = replace(
            problem.config,
            init="zero",
            template_registration="none",
            refine_below_coherence=0.0,
            # a closed-form estimator's config has none: the settings table's then
            iterations=int(problem.config.iterations or config_default("iterations")),
        )
        assert model.template is not None
        result = _twin_autofocus(problem, model.template, cfg, init_phase_rad=model.estimate_rad)
        fitted = model.evolve(
            phase_rad=result.phase_rad, estimate_rad=result.phase_rad, loss_history=result.loss_history
        )
        return Fitted(fitted, {"iterations": int(cfg.iterations)})

    def keep(self, problem: Problem, before: Model, fitted: Fitted, measured: dict) -> Verdict:
        check = measured.get("refine_check")
        if self.mode == "auto" and check is not None:
            return Verdict(True, f"{check['why']}; {self.keeps_because}", fitted.model)
        why = self.keeps_because if self.mode != "on" else "on request"
        return Verdict(True, why, fitted.model)


class ReferenceFree(Rung):
    """Autofocus of the target itself, no reference: subclasses define :meth:`estimate`."""

    cheap = False

    @classmethod
    def made_for(cls, mode: str, ladder: LadderSettings) -> Rung:
        return cls("on" if mode != "off" else "off", until_trusted=ladder.model == "fast")

    def parameters(self, problem: Problem) -> int:
        return int(problem.positions.shape[0])

    def estimate(self, problem: Problem) -> tuple[np.ndarray, dict, np.ndarray]:
        """(phase float (M,) radians, what it recorded, loss history float (n,)) from the target."""
        raise NotImplementedError

    def keep(self, problem: Problem, before: Model, fitted: Fitted, measured: dict) -> Verdict:
        # always kept (its mode is "on" whenever it is climbed): ``keeps_because`` says why, measured
        return Verdict(True, self.keeps_because, fitted.model)

    def fit(self, problem: Problem, model: Model) -> Fitted:
        phase, info, losses = self.estimate(problem)
        return Fitted(model.evolve(phase_rad=phase, estimate_rad=phase, loss_history=losses, estimated=True), info)


def _target_cells(problem: Problem) -> float:
    """The target region's resolution cells for the scan's aperture
    (:func:`twinfocus.focus.reference_free.resolution_cells`)."""
    return resolution_cells(problem.positions, problem.target_grid, problem.chirp.wavelength_m)


class Sharpness(ReferenceFree):
    """The paper's sharpness optimiser; its info carries the region's resolution cells per
    position and a warning when they are too few, as the other reference-free rungs' do."""

    name, adds = "sharpness", "one phase per position maximising the target's sharpness (no reference)"
    keeps_because = measured_keep(
        "always kept: nothing but the target to judge it by", _FREE_JUDGED, 6, 12, 0.736, 0.111
    )

    def estimate(self, problem: Problem) -> tuple[np.ndarray, dict, np.ndarray]:
        basis = problem.tgt_basis
        result = sharpness_autofocus(basis, problem.config, progress=problem.progress(f"{self.name} autofocus"))
        return result.phase_rad, cells_summary("sharpness", _target_cells(problem), basis.shape[0]), result.loss_history


class _FreeMethod(ReferenceFree):
    """A :mod:`twinfocus.focus.reference_free` method (its ``name``)."""

    def estimate(self, problem: Problem) -> tuple[np.ndarray, dict, np.ndarray]:
        result = reference_free_autofocus(problem.tgt_basis, self.name, cells=_target_cells(problem))
        return result.phase_rad, result.extra["reference_free"], result.loss_history


class Entropy(_FreeMethod):
    name, adds = "entropy", "one phase per position minimising the target's entropy (no reference)"
    keeps_because = measured_keep(
        "always kept: nothing but the target to judge it by", _FREE_JUDGED, 9, 12, 1.207, 0.716
    )


class Pga(_FreeMethod):
    name, adds = "pga", "one phase per position from the target's brightest scatterers (no reference)"
    keeps_because = measured_keep(
        "always kept: nothing but the target to judge it by", _FREE_JUDGED, 7, 12, 1.034, -0.006
    )


def _transfer(problem: Problem, model: Model, mode: str, range_errors_m: np.ndarray | None = None):
    centres = problem.centres
    return transfer_phase(
        model.estimate_rad,
        centres[:, :2],
        float(problem.reference_grid.z - centres[:, 2].mean()),
        problem.chirp.wavelength_m,
        mode,
        registered=model.registered,
        range_errors_m=range_errors_m,
    )


class Placement(Rung):
    """The estimate's constant + linear ramp, which moves the image, taken out where a template's
    misplacement explains it (:func:`twinfocus.focus.autofocus.transfer_phase`; ``ramp_mode``
    ``--phase-ramp``). Always measured: off, the ramp is reported and transferred as is. Kept by
    the transfer's own measured rule (``ramp.removed``, ``ramp.reason``)."""

    name, adds = "placement", "the template's place: the estimate's ramp taken out"
    measured_when_off = True

    def __init__(self, mode: str = "auto", *, until_trusted: bool = False):
        super().__init__(mode, until_trusted=until_trusted)
        self.ramp_mode = {"on": "remove", "off": "keep"}.get(mode, "auto")

    def parameters(self, problem: Problem) -> int:
        return 3

    def cannot(self, problem: Problem, model: Model) -> str | None:
        return None if model.estimated else "no estimate to place"

    def fit(self, problem: Problem, model: Model) -> Fitted:
        phase, ramp = _transfer(problem, model, self.ramp_mode)
        return Fitted(model.evolve(phase_rad=phase, ramp=ramp), ramp)

    def keep(self, problem: Problem, before: Model, fitted: Fitted, measured: dict) -> Verdict:
        ramp = fitted.model.ramp
        assert ramp is not None
        return Verdict(bool(ramp["removed"]), ramp["reason"], fitted.model)

    def not_kept(self, before: Model, fitted: Fitted) -> Model:
        # the ramp stays in the phase, and its measurement goes on to the rungs above
        return replace(before, ramp=fitted.model.ramp)


def range_errors_needed(problem: Problem, model: Model) -> str | None:
    """Why the estimate needs the range errors (its phases have wrapped, or its ramp is larger than
    a misplacement explains), or None."""
    coherence = ramp_free_coherence(model.estimate_rad, problem.centres[:, :2])
    if coherence < MIN_RAMP_COHERENCE_SQRT_M:
        return "the estimate's phases have wrapped"
    if model.ramp is not None and np.any(model.ramp["slope_rad_per_m"]) and not model.ramp["removed"]:
        return "its ramp is larger than a misplacement explains"
    return None


class RangeErrors(Rung):
    """Each position's range error read from the band's halves (on the pixels holding 99 % of the
    estimate's image energy), taken out of the estimate before its ramp is fitted
    (docs/digital_twin_autofocus.md, "Placing the reference by the band's halves"). Auto: only when the
    estimate's phases have wrapped (its ramp is out of sight) or its ramp is larger than a
    misplacement explains. Kept by the transfer's rule: a ramp is taken out only when it stands
    out of the range errors (``ramp.reason``)."""

    name, adds = "range_errors", "each position's range error from the band's halves, before the ramp fit"

    def __init__(self, mode: str = "auto", *, until_trusted: bool = False, ramp_mode: str = "auto"):
        super().__init__(mode, until_trusted=until_trusted)
        self.ramp_mode = ramp_mode

    @classmethod
    def made_for(cls, mode: str, ladder: LadderSettings) -> Rung:
        return cls(mode, ramp_mode=ladder.phase_ramp)

    def parameters(self, problem: Problem) -> int:
        return int(problem.positions.shape[0])

    def cannot(self, problem: Problem, model: Model) -> str | None:
        if not model.estimated:
            return "no estimate to place"
        if model.registered:
            return "the template was registered to the scan: no misplacement is left to place"
        if problem.upper_band is None:
            return "no upper-band basis (a chirp too short to halve, or none given)"
        return None

    def skip(self, problem: Problem, model: Model) -> tuple[str | None, dict]:
        if self.mode == "auto" and range_errors_needed(problem, model) is None:
            return "not needed: the estimate's ramp is in sight and within what a misplacement explains", {}
        return None, {}

    def fit(self, problem: Problem, model: Model) -> Fitted:
        assert problem.upper_band is not None
        pixels = bright_pixels(form_image(problem.ref_basis, model.estimate_rad))
        high = problem.upper_band(pixels)
        range_errors = position_range_errors_m(
            problem.ref_basis[:, pixels] - high, high, model.estimate_rad, problem.chirp
        )
        phase, ramp = _transfer(problem, model, self.ramp_mode, range_errors)
        ramp["asked_range_errors_because"] = range_errors_needed(problem, model) or "asked for"
        return Fitted(model.evolve(phase_rad=phase, ramp=ramp), ramp)

    def keep(self, problem: Problem, before: Model, fitted: Fitted, measured: dict) -> Verdict:
        assert fitted.model.ramp is not None
        return Verdict(True, fitted.model.ramp["reason"], fitted.model)


class SmoothDrift(Rung):
    """A smooth across-sight drift fitted to the whole reference and transferred per pixel
    (:func:`twinfocus.focus.space_variant.fit_smooth_drift`); :class:`Tilt` also the array's tilt,
    from the half-array bases, in the same fit. Needs a registered template with phase (a physical
    twin) and the whole estimate (its ramp kept). Auto: fitted only when the scalar phase leaves
    more than ``SPACE_VARIANT_MIN_RESIDUAL`` of the reference unmatched (the fit's cost); kept
    only on held-out evidence: fitted again on half of the reference's blocks
    (:func:`~twinfocus.focus.ladder.heldout_split`), it must match the other half better than the model
    beneath fitted on the same half, by more than the gain's noise
    (:func:`~twinfocus.focus.ladder.heldout_gain`).

    with_tilt_above : the tilt rung above fits the drift too, so this one leaves it to that rung
    when the half-array bases are there; setting : what metrics.json's ``space_variant.mode``
    says was asked; quick : ``--model fast``'s quick fit (``FAST_FIT``) judged on one held-out
    half, where auto judges both."""

    name = "drift"
    adds = "a smooth across-sight drift per position, transferred per pixel"
    cheap = False
    tilt: ClassVar[bool] = False

    def __init__(
        self,
        mode: str = "auto",
        *,
        until_trusted: bool = False,
        with_tilt_above: bool = False,
        setting: str = "auto",
        quick: bool = False,
    ):
        super().__init__(mode, until_trusted=until_trusted)
        self.with_tilt_above, self.setting, self.quick = with_tilt_above, setting, quick

    @classmethod
    def made_for(cls, mode: str, ladder: LadderSettings) -> Rung:
        sv, model = ladder.space_variant, ladder.model
        return cls(
            mode,
            until_trusted=model == "fast",
            with_tilt_above=ladder.modes.get("tilt", "off") != "off",
            setting=sv if sv != "auto" or model == "auto" else model,
            quick=model == "fast",
        )

    @property
    def refused_as(self) -> str:
        return "space-variant correction"

    def record(self) -> dict:
        return {"mode": self.setting, "used": False}

    def parameters(self, problem: Problem) -> int:
        m = int(problem.positions.shape[0])
        return 2 * m + (m // 10 + 1 if self.tilt else 0)

    def off(self) -> tuple[str, dict]:
        return "off on request", {"reason": "off on request"}

    def refused(self, why: str) -> dict:
        return {"reason": why}

    def cannot(self, problem: Problem, model: Model) -> str | None:
        if model.template is None or not np.iscomplexobj(model.template) or not model.registered:
            return "needs a template with phase registered to the scan (a physical twin)"
        if model.ramp is not None and model.ramp["removed"]:
            return "the phase ramp was removed before the transfer; the drift fit needs the whole estimate"
        return None

    def skip(self, problem: Problem, model: Model) -> tuple[str | None, dict]:
        if self.tilt and problem.half_bases is None:
            return "no half-array bases (an array of one channel, or none given)", {}
        if not self.tilt and self.with_tilt_above and problem.half_bases is not None:
            return "fitted with the array's tilt, one rung up", {}
        assert model.template is not None
        residual = 1.0 - complex_match(model.apply(problem, "reference"), model.template)
        if self.mode == "auto" and residual <= SPACE_VARIANT_MIN_RESIDUAL:
            why = (
                f"not needed: the scalar phase leaves {residual:.4f} of the reference "
                f"unmatched (<= {SPACE_VARIANT_MIN_RESIDUAL})"
            )
            return why, {"residual_scalar": residual, "reason": why}
        return None, {"residual_scalar": residual}

    def _fit(self, problem: Problem, model: Model, halves, fitted: np.ndarray | None = None, **settings):
        """fit_smooth_drift on the reference, or on its ``fitted`` pixels alone (bool (H, W)); the
        fit on the whole reference warm-started from ``problem.drift_starts``' state for this rung
        when it holds one (with its warm steps), whose state it then becomes; fitted again cold
        when the warm fit ends below where a cold one begins (``warm_start_refused`` in the fit's
        info)."""
        # the held-out fits stay cold: warm-started from a sweep's partial fits (which fit a part of
        # the aperture against the whole one's template, and do not generalise) they turned the
        # verdict on the hand-drift scene of bench_bus's live hand sweep; cold, it is the offline one
        starts = problem.drift_starts if fitted is None else None
        start, cold_settings = None, settings
        if starts is not None:
            settings = starts.settings(self.name, settings)
            start = starts.states.get(self.name)
            if start is not None and start.rows > problem.ref_basis.shape[0]:
                start = None  # a start from a longer scan than this one (a scan that began again)
        result = self._fit_from(problem, model, halves, fitted, settings, start)
        if start is not None and result[3]["match_after"] < result[3]["match_cold_start"]:
            # the warm fit ended below where a cold one begins: the start (a fit of the sweep's
            # first part, its later positions from the last knot) led it astray; on the 60-position
            # hand sweep of tests/test_graph_hand.py with OpenCV 5.1's letters it left 0.649 of the
            # reference unmatched against the cold fit's 0.491, the target 0.60 against 0.69
            refused = result[3]
            result = self._fit_from(problem, model, halves, fitted, cold_settings, None)
            result[3]["warm_start_refused"] = {
                "positions": start.rows,
                "match_after": refused["match_after"],
                "match_cold_start": refused["match_cold_start"],
            }
        if starts is not None:
            starts.states[self.name] = result[3]["end_state"]
        return result

    def _fit_from(self, problem: Problem, model: Model, halves, fitted, settings: dict, start):
        """One :func:`~twinfocus.focus.space_variant.fit_smooth_drift` of :meth:`_fit`, from
        ``start`` (None: cold) with ``settings`` (DriftFitSettings fields)."""
        from twinfocus.focus.space_variant import (  # lazy: numba, scipy (+1.4 s at import; only this rung fits the drift)
            DriftFitSettings,
            fit_smooth_drift,
        )

        assert model.template is not None
        return fit_smooth_drift(
            problem.ref_basis,
            model.template,
            model.phase_rad,
            problem.centres,
            problem.reference_grid,
            problem.chirp.wavelength_m,
            half_basis=None if halves is None else halves[0],
            pixels=fitted,
            device=problem.config.device,
            progress=problem.progress("space-variant fit" if fitted is None else "space-variant held-out fit"),
            settings=DriftFitSettings(**settings),
            start=start,
        )

    def fit(self, problem: Problem, model: Model) -> Fitted:
        info: dict = {}
        t = time.perf_counter()
        halves = problem.half_bases() if self.tilt and problem.half_bases is not None else None
        if halves is not None:
            # a back-projection like the whole bases', reported as a stage of its own
            info["half_array_bases_s"] = time.perf_counter() - t
        phase, drift, tilt, fit = self._fit(problem, model, halves, None, **(FAST_FIT if self.quick else {}))
        if self.quick:
            info["fit"] = (
                f"quick (--model fast): {FAST_FIT['iterations']} steps on the knots, "
                f"at most {FAST_FIT['refine_iterations']} per position"
            )
        info.update(
            residual_space_variant=1.0 - fit["match_after"],
            knot_spacing_positions=fit["knot_spacing_positions"],
            iterations=fit["iterations"],
            refine_iterations=fit["refine_iterations"],
            smoothness_per_mm2=fit["smoothness_per_mm2"],
            time_s=fit["time_s"],
            drift_rms_mm=[float(v) for v in np.sqrt((drift[:, :2] ** 2).mean(axis=0)) * 1e3],
            tilt_fitted=bool(fit["tilt_fitted"]),
            tilt_rms_rad=float(np.sqrt((tilt**2).mean())),
        )
        if fit["warm_start_positions"] and problem.drift_starts is not None:
            # the solver node's fit after a sweep, from those streamed during it
            info.update(warm_start_positions=fit["warm_start_positions"], warm_steps=dict(problem.drift_starts.warm))
        if "warm_start_refused" in fit:
            info["warm_start_refused"] = fit["warm_start_refused"]
        return Fitted(model.evolve(phase_rad=phase, drift_m=drift, tilt_rad=tilt, halves=halves), info)

    def heldout(
        self, problem: Problem, before: Model, after: Model, halves_only: int = 2
    ) -> tuple[dict, tuple[Model, ...]]:
        """The held-out evidence (:func:`~twinfocus.focus.ladder.heldout_verdict`): on each half of
        :func:`~twinfocus.focus.ladder.heldout_split` (the first ``halves_only``) this rung and the
        model beneath, each fitted on that half, judged on the other half; and this rung's half
        fits (the rungs above judge themselves against them)."""
        assert before.template is not None
        first = heldout_split(problem)
        folds, fits = [], []
        for i, fitted in enumerate((first, ~first)[:halves_only]):
            if before.heldout is not None:
                base = before.heldout[i]
            else:
                # the model beneath is one phase per position: its closed form on the same half (a sum
                # over the template's pixels, so zeroing the template's other half is enough)
                phase = correlation_phase(problem.ref_basis, before.template * fitted)
                base = before.evolve(phase_rad=phase)
            phase, drift, tilt, _ = self._fit(problem, base, after.halves, fitted, **HELDOUT_FIT)
            fits.append(after.evolve(phase_rad=phase, drift_m=drift, tilt_rad=tilt))
            folds.append(
                heldout_gain(
                    base.apply(problem, "reference"), fits[-1].apply(problem, "reference"), before.template, ~fitted
                )
            )
        return heldout_verdict(folds), tuple(fits)

    def keep(self, problem: Problem, before: Model, fitted: Fitted, measured: dict) -> Verdict:
        if self.mode == "on":
            return Verdict(True, "on request", fitted.model, {"used": True, "reason": "on request"})
        evidence, half_fits = self.heldout(problem, before, fitted.model, halves_only=1 if self.quick else 2)
        info: dict = {
            "heldout_fit": f"{'one half (--model fast)' if self.quick else 'two halves'}, "
            f"the knots' stage alone at {HELDOUT_FIT['iterations']} steps",
            "heldout": evidence,
        }
        held = (
            f"fitted on one half of the reference's blocks and judged on the other, it leaves "
            f"{evidence['unmatched_after']:.4f} unmatched against {evidence['unmatched_before']:.4f} beneath it "
            f"(gain {evidence['gain']:.4f}, noise {evidence['noise']:.4f} over {len(evidence['folds'])} halves)"
        )
        kept = bool(evidence["kept"])
        if kept:
            info["used"] = True
            why = f"kept: {held}"
            # the rungs above judge themselves against this rung's half fits
            model = replace(fitted.model, heldout=None if self.quick else half_fits)
        else:
            why = f"fitted but not kept: {held}; the error is not a smooth drift this reference shows"
            model = fitted.model
        info["reason"] = why
        return Verdict(kept, why, model, info, heldout=evidence)


class Tilt(SmoothDrift):
    """The drift with the array's tilt, from the half-array bases (one fit with the drift)."""

    name = "tilt"
    adds = "the array's tilt per position, fitted with the drift (half-array bases)"
    tilt = True


def _rung_class(where: str) -> type[Rung]:
    """The class a registry entry names ("module:Class")."""
    module, name = where.split(":")
    return getattr(importlib.import_module(module), name)


#: every rung by name, its class (the registry :data:`twinfocus.focus.estimators.RUNG_REGISTRY`
#: resolved): a ladder is a sequence of these names (:func:`twinfocus.focus.plan.ladder_modes`)
RUNGS: dict[str, type[Rung]] = {name: _rung_class(where) for name, (where, _) in RUNG_REGISTRY.items()}


def reference_free_rungs() -> tuple[str, ...]:
    """The registry's reference-free rungs (each a ladder of its own above "none": ``--method``)."""
    return tuple(name for name, cls in RUNGS.items() if issubclass(cls, ReferenceFree))


def climb(problem: Problem, rungs: Sequence[Rung], start: Model | None = None) -> tuple[Model, dict]:
    """Climb ``rungs`` (:attr:`twinfocus.focus.plan.FocusPlan.rungs`) on ``problem`` from
    ``start`` (None: no correction): returns the kept model and
    metrics.json's ``model`` section: ``rungs``, one entry per rung (``rung``, ``adds``,
    ``mode``, ``tried``, ``kept``, ``why``, ``time_s``, and when tried ``evidence``: the
    reference's match before and after and the ``parameters`` it adds, and ``info``: what its
    fit recorded), ``kept`` (the kept rungs' names), ``result`` (the top kept rung) and
    ``time_s``; and ``targets``, each tried rung's target image (complex (H, W)), for the caller
    to take out."""
    m = problem.ref_basis.shape[0]
    model = start or Model(phase_rad=np.zeros(m), estimate_rad=np.zeros(m), template=problem.template)
    entries: list[dict] = []
    kept: list[str] = []
    targets: dict[str, np.ndarray] = {}
    t_all = time.perf_counter()
    for rung in rungs:
        t = time.perf_counter()
        entry, model, target = _climb_rung(problem, rung, model, kept)
        if target is not None:
            targets[rung.name] = target
        info = entry.pop("info")
        entry["time_s"] = time.perf_counter() - t
        if info:
            entry["info"] = info
        entries.append(entry)
    section = {
        "rungs": entries,
        "kept": kept,
        "result": kept[-1] if kept else None,
        "time_s": time.perf_counter() - t_all,
    }
    section["targets"] = targets  # the images, for the pictures: not written to metrics.json
    return model, section


def _climb_rung(problem: Problem, rung: Rung, model: Model, kept: list[str]) -> tuple[dict, Model, np.ndarray | None]:
    """One rung of :func:`climb` from ``model`` (``kept``: the names kept so far, appended to):
    its entry (without ``time_s``), the model the rungs above start from, and its target image
    when it was tried."""
    entry: dict = {"rung": rung.name, "adds": rung.adds, "mode": rung.mode, "tried": False, "kept": False}
    info = rung.record()
    why: str | None
    if rung.mode == "off" and not rung.measured_when_off:
        why, recorded = rung.off()
        info.update(recorded)
    else:
        why = rung.cannot(problem, model)
        if why is not None:
            info.update(rung.refused(why))
    if why is None and rung.until_trusted and problem.trust is not None:
        below = problem.trust(problem, model)
        if below is None:
            why = f"fast: the reference passes the trust line at {kept[-1]}"
        else:
            entry["below_trust_line"] = below
    measured: dict = {}
    if why is None:
        why, measured = rung.skip(problem, model)
        info.update(measured)
    elif rung.mode == "on":
        raise TwinFocusError(f"{rung.refused_as} {why}")
    target = None
    if why is None:
        before = reference_evidence(problem, model) if rung.name != "none" else {}
        fitted = rung.fit(problem, model)
        info.update(fitted.info)
        verdict = rung.keep(problem, model, fitted, measured)
        info.update(verdict.info)
        why = verdict.why
        after = reference_evidence(problem, fitted.model)
        entry.update(tried=True, kept=verdict.kept)
        target = fitted.model.apply(problem, "target")
        entry["evidence"] = {"before": before, "after": after, "parameters": rung.parameters(problem)}
        if verdict.heldout is not None:
            entry["evidence"]["heldout"] = verdict.heldout
        if verdict.kept:
            model = verdict.model
            kept.append(rung.name)
        else:
            model = rung.not_kept(model, fitted)
    entry.update(why=why, info=info)
    return entry, model, target
