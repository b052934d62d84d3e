"""The named estimators of ``twinfocus focus --estimator`` (and the solver node's ``estimator``):
which :class:`~twinfocus.focus.autofocus.AutofocusConfig` fields make each, and which one ``auto``
takes. Plain Python, so a node can list the choices without importing the numerics.
"""

from __future__ import annotations

from twinfocus.errors import TwinFocusError

#: how the phases are found from the reference (``twinfocus focus --estimator``; docs/beyond.md)
ESTIMATORS = (
    "paper",
    "projection",
    "projection-refined",
    "outline",
    "registered",
    "correlation",
    "correlation-refined",
)
#: the estimators that need the template's phase (a physical twin's complex image)
PHASE_ESTIMATORS = ("registered", "correlation", "correlation-refined")


#: ``--estimator auto`` with an amplitude template and no outline runs the optimiser after the
#: projections only when their phases' coherence x sqrt(M) is below this: M random phases reach
#: 2.5 / sqrt(M) once in 500 (Rayleigh), so below it the errors wrap every phase (past about
#: lambda/5 along the line of sight); measured in docs/digital_twin.md
AUTO_REFINE_BELOW_COHERENCE = 2.5


def auto_estimator(has_phase: bool, has_support: bool = False) -> str:
    """The estimator measured best for a template (docs/beyond.md, docs/digital_twin.md), chosen
    from what the template is, never from an assumed tracking error:

    * with the template's phase, the registered closed form ("correlation"): at the transfer
      ceiling from 0.5 to 1.6 mm of tracking error, in 0.15 s;
    * a digital twin from a point cloud, which knows the reference's outline: the outline
      estimator ("outline"), whatever the tracking error: on rough references and camera clouds
      it holds where the template's texture misleads the others; its outline first grown into
      what its estimates light up, then averaged over the outlines grown from there
      (``outline_ensemble``, ``outline_growth_rounds``), which fill a camera cloud's holes;
    * an amplitude template without an outline (a template file): the alternating projections,
      then the optimiser only if the projections' phases show that the errors wrap
      ("projection-refined" with ``refine_below_coherence``, :func:`estimator_settings`): the
      projections alone are best while the phases hold together (0.937-0.961 against
      0.923-0.931 at 0.3 mm along z), the optimiser where they have wrapped and the projections
      stop short (0.915-0.924 against 0.849-0.894 at 0.8 and 1.6 mm; docs/digital_twin.md).
    """
    if has_phase:
        return "correlation"
    if has_support:
        return "outline"
    return "projection-refined"


def resolve_estimator(estimator: str, has_phase: bool, has_support: bool = False) -> str:
    """The named estimator that runs: ``estimator`` itself, or for ``"auto"`` the one
    :func:`auto_estimator` takes."""
    return auto_estimator(has_phase, has_support) if estimator == "auto" else estimator


def estimator_that_ran(resolved: str, estimator_metrics: dict) -> str:
    """The named estimator that found the phase: ``resolved`` (:func:`resolve_estimator`), except
    that "projection-refined" whose optimiser the data skipped (``estimator_metrics``, metrics.json's
    ``estimator``: ``refine_check.refined`` false) ran as "projection"."""
    check = estimator_metrics.get("refine_check")
    if resolved == "projection-refined" and check is not None and not check["refined"]:
        return "projection"
    return resolved


def estimator_settings(estimator: str, has_phase: bool, has_support: bool = False, model: str = "auto") -> dict:
    """The :class:`~twinfocus.focus.autofocus.AutofocusConfig` fields that make a named estimator
    (``iterations`` only where it is 0: no optimiser); ``loss_steepness`` is the default for
    it, which an explicit choice overrides. ``"auto"`` is resolved by :func:`resolve_estimator`
    (for an amplitude template without an outline, the optimiser then runs only where the
    projections' phases have wrapped: ``refine_below_coherence``); ``has_support``: the
    reference's outline is known (a digital twin from a cloud), which "outline" needs. ``model``
    (``--model``) "full" or "refine" runs the optimiser after any estimator: a closed form's
    ``iterations`` are then left to the settings."""
    by_data = estimator == "auto" and not has_phase and not has_support
    estimator = resolve_estimator(estimator, has_phase, has_support)
    if estimator not in ESTIMATORS:
        raise TwinFocusError(f"estimator must be one of {', '.join(ESTIMATORS)}, got {estimator!r}")
    if estimator in PHASE_ESTIMATORS and not has_phase:
        raise TwinFocusError(
            f"--estimator {estimator} needs the template's phase: use --template-scan or a template "
            "file with phase_rad (a digital twin's template has none; use --estimator projection, "
            "projection-refined or paper)"
        )
    if estimator == "outline" and not has_support:
        raise TwinFocusError(
            "--estimator outline needs the reference's outline: a digital twin from a point cloud "
            "(--digital-twin) gives one"
        )
    out = {
        "template_registration": "correlation" if has_phase and estimator not in ("paper", "outline") else "none",
        "init": (
            estimator.removesuffix("-refined")
            if estimator.startswith(("correlation", "projection", "outline"))
            else "zero"
        ),
        # a steeper threshold inside the loss lets a smooth amplitude template match a speckled
        # reference by its outline (docs/evaluation.md)
        "loss_steepness": 5.0 if estimator in ("paper", "projection", "projection-refined") else None,
    }
    if estimator in ("correlation", "projection", "outline") and model not in ("full", "refine"):
        out["iterations"] = 0
    if estimator == "outline":
        # averaged over the outlines grown from the first estimate: +0.010-0.019 target SSIM with
        # camera clouds, never worse on average with one impairment alone (docs/digital_twin.md)
        out["outline_ensemble"] = True
    if by_data:
        out["refine_below_coherence"] = AUTO_REFINE_BELOW_COHERENCE
    return out


#: every rung by name (the one registry; :data:`twinfocus.focus.rungs.RUNGS` resolves it into the
#: classes when a ladder is built): where its class is, "module:Class", and its ladder: "twin",
#: the twin's ladder of correction models, simplest first (:mod:`twinfocus.focus.ladder`,
#: docs/model_ladder.md): no correction; one phase per position (the estimator's closed form,
#: projections or outline); the paper's optimiser refining it; the template's placement (the
#: estimate's ramp); the range errors read from the band's halves; a smooth drift per pixel; the
#: array's tilt with it; or "reference-free", autofocus without a reference in view, each a
#: ladder of its own above "none" (``--method``). Names and places only, so that the command's and
#: the node's choices are listed without importing the numerics
RUNG_REGISTRY: dict[str, tuple[str, str]] = {
    "none": ("twinfocus.focus.rungs:NoCorrection", "twin"),
    "phase": ("twinfocus.focus.rungs:PhasePerPosition", "twin"),
    "refine": ("twinfocus.focus.rungs:Refine", "twin"),
    "placement": ("twinfocus.focus.rungs:Placement", "twin"),
    "range_errors": ("twinfocus.focus.rungs:RangeErrors", "twin"),
    "drift": ("twinfocus.focus.rungs:SmoothDrift", "twin"),
    "tilt": ("twinfocus.focus.rungs:Tilt", "twin"),
    "sharpness": ("twinfocus.focus.rungs:Sharpness", "reference-free"),
    "entropy": ("twinfocus.focus.rungs:Entropy", "reference-free"),
    "pga": ("twinfocus.focus.rungs:Pga", "reference-free"),
}
#: the twin's ladder, simplest first, and the reference-free rungs: the registry's names
TWIN_RUNGS = tuple(name for name, (_, ladder) in RUNG_REGISTRY.items() if ladder == "twin")
REFERENCE_FREE_RUNGS = tuple(name for name, (_, ladder) in RUNG_REGISTRY.items() if ladder == "reference-free")
#: ``twinfocus focus --model``: climb as the evidence says, stop at the cheapest trusted rung,
#: try every rung, or exactly one rung (those beneath it by their rules, none above it)
MODEL_CHOICES = ("auto", "fast", "full") + TWIN_RUNGS + REFERENCE_FREE_RUNGS
