"""The named estimators of ``twinfocus focus --estimator`` (and the solver node's ``estimator``):
which :class:`~twinfocus.autofocus.AutofocusConfig` fields make each, and which one ``auto``
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


def auto_estimator(has_phase: bool, tracking_error_m: float, wavelength_m: float, has_support: bool = False) -> str:
    """The estimator measured best for a template (docs/beyond.md, six pairs x two draws;
    docs/digital_twin.md for the outline):

    * with the template's phase, the registered closed form ("correlation"): at the transfer
      ceiling from 0.5 to 1.6 mm of tracking error, in 0.15 s;
    * a digital twin from a point cloud, which knows the reference's outline: the outline
      estimator ("outline"), whatever the tracking error: on rough references and camera clouds
      it holds where the template's texture misleads the others; averaged over the outlines
      grown from its first estimate (``outline_ensemble``), which fill a camera cloud's holes
      (docs/digital_twin.md);
    * an amplitude template (a digital twin's): alternating projections alone ("projection",
      0.950 at 0.5 mm against the steepness-5 optimiser's 0.941, and 0.940 against 0.905 at 20
      degrees of separation, in 0.12 s) while the tracker's error stays within lambda/4; past
      it, where every phase wraps, the optimiser from there ("projection-refined": 0.921
      against 0.861 at 1.6 mm along z).
    """
    if has_phase:
        return "correlation"
    if has_support:
        return "outline"
    return "projection" if tracking_error_m <= wavelength_m / 4.0 else "projection-refined"


def resolve_estimator(
    estimator: str,
    has_phase: bool,
    tracking_error_m: float | None = None,
    wavelength_m: float | None = None,
    has_support: bool = False,
) -> str:
    """The named estimator that runs: ``estimator`` itself, or for ``"auto"`` the one
    :func:`auto_estimator` takes (which needs ``tracking_error_m`` and ``wavelength_m``)."""
    if estimator != "auto":
        return estimator
    if tracking_error_m is None or wavelength_m is None:
        raise TwinFocusError("estimator 'auto' needs the tracking error and the wavelength to choose")
    return auto_estimator(has_phase, tracking_error_m, wavelength_m, has_support)


def estimator_settings(
    estimator: str,
    has_phase: bool,
    tracking_error_m: float | None = None,
    wavelength_m: float | None = None,
    has_support: bool = False,
) -> dict:
    """The :class:`~twinfocus.autofocus.AutofocusConfig` fields that make a named estimator
    (``iterations`` only where it is 0: no optimiser); ``loss_steepness`` is the default for
    it, which an explicit choice overrides. ``"auto"`` is resolved by :func:`resolve_estimator`
    and needs ``tracking_error_m`` and ``wavelength_m``; ``has_support``: the reference's outline is
    known (a digital twin from a cloud), which "outline" needs."""
    estimator = resolve_estimator(estimator, has_phase, tracking_error_m, wavelength_m, has_support)
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
    if estimator in ("correlation", "projection", "outline"):
        out["iterations"] = 0
    if estimator == "outline":
        # averaged over the outlines grown from the first estimate: +0.010-0.019 target SSIM with
        # camera clouds, never worse on average with one impairment alone (docs/digital_twin.md)
        out["outline_ensemble"] = True
    return out
