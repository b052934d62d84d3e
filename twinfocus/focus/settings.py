"""Every focus setting, described once (the device: :mod:`twinfocus.imaging.device`).

:data:`FOCUS_SETTINGS` is the table: each :class:`Setting` is at once

* a ``twinfocus focus`` option, ``--name-with-dashes`` (``twinfocus/cli/focus.py`` adds them
  from here with :func:`add_focus_options`),
* a solver node parameter of the same ``name`` (``nodes/solver.py``, through
  :func:`nodes.runtime.params.param_of`), settable from a launch file or ``name:=value``,
* and, where ``config`` names one, an :class:`~twinfocus.focus.autofocus.AutofocusConfig` field, whose
  default is the table's (:meth:`AutofocusConfig.from_settings
  <twinfocus.focus.autofocus.AutofocusConfig.from_settings>` builds a config from the values).

Not here: each entry point's inputs and outputs (the scan, the regions, the template's source,
output folders, pictures, the solver's streaming and timeouts), and the AutofocusConfig fields
that no entry point exposes: ``init``, ``template_registration`` and ``outline_ensemble`` (made by
:func:`twinfocus.focus.estimators.estimator_settings` from ``estimator``), ``outline_growth_rounds``,
``outline_choice``, ``smoothness_weight``,
``coarse_blur_px`` and ``registration_max_shift_px`` (library and benchmark use).

Plain Python: the command's ``--help`` and a node's parameter list need no numerics.
"""

from __future__ import annotations

import argparse
import threading
from dataclasses import dataclass
from typing import Any

from twinfocus.focus.estimators import ESTIMATORS, MODEL_CHOICES


@dataclass(frozen=True)
class Setting:
    """One focus setting.

    name : the solver parameter and the parsed option's attribute; the option is :attr:`option`.
    type : ``int``, ``float`` or ``str``; default : its value when none is given (None: decided
        at run time, as ``default_text`` says).
    help : one description for both; ``{other_name}`` names another setting, written as that
        entry point spells it (``--other-name`` / ``other_name``).
    unit : of the value ("px", "mm"); also in ``name`` where a value could be read in another.
    choices : the allowed values, if limited.
    config : the AutofocusConfig field it sets, if any.
    default_text : what a None default means.
    check : how a typed value is checked (:data:`twinfocus.option_types.CHECKS`: "positive",
        "non_negative_int", ...); None: any value of ``type`` (a float still finite).
    """

    name: str
    type: type
    default: Any
    help: str
    unit: str = ""
    choices: tuple[str, ...] | None = None
    config: str | None = None
    default_text: str = ""
    check: str | None = None

    @property
    def option(self) -> str:
        """The ``twinfocus focus`` option."""
        return "--" + self.name.replace("_", "-")

    def describe(self, spell) -> str:
        """The help text, with other settings written as ``spell(setting)`` (their option or name)."""
        return self.help.format(**_spelled(spell))

    def default_words(self, spell) -> str:
        """The default as the help states it: the value with its unit, or what None means."""
        if self.default is None:
            return self.default_text.format(**_spelled(spell))
        value = f"{self.default:g}" if isinstance(self.default, float) else str(self.default)
        return f"{value} {self.unit}" if self.unit else value


def _spelled(spell) -> dict[str, str]:
    return {s.name: spell(s) for s in FOCUS_SETTINGS}


FOCUS_SETTINGS: tuple[Setting, ...] = (
    Setting("size", int, 100, "image size in pixels per side", unit="px", check="positive_int"),
    Setting("iterations", int, 300, "optimiser iterations", config="iterations", check="non_negative_int"),
    Setting("lr", float, 5e-2, "Adam learning rate", config="lr", check="positive"),
    Setting(
        "lr_min", float, 1e-5, "end of the cosine schedule of the learning rate", config="lr_min", check="non_negative"
    ),
    Setting(
        "threshold_centre",
        float,
        0.4,
        "soft threshold centre (of the max-normalised amplitude)",
        config="threshold_centre",
        check="non_negative",
    ),
    Setting(
        "threshold_steepness", float, 1.0, "soft threshold steepness", config="threshold_steepness", check="positive"
    ),
    Setting(
        "loss_steepness",
        float,
        None,
        "soft threshold steepness inside the optimiser's loss only; a steeper loss lifts a digital twin from "
        "0.89 to 0.94 SSIM (docs/beyond.md)",
        config="loss_steepness",
        default_text="5 with {estimator} paper, projection or projection-refined, otherwise "
        "{threshold_steepness}, the source paper's",
        check="positive",
    ),
    Setting(
        "precision",
        str,
        "float32",
        "arithmetic of the back-projection and the optimiser",
        choices=("float32", "float64"),
        config="precision",
    ),
    Setting(
        "basis_dtype",
        str,
        "float32",
        "storage of the sub-image basis in the optimiser (float16: ~2x faster, same result)",
        choices=("float32", "float16"),
        config="basis_dtype",
    ),
    Setting(
        "device",
        str,
        None,
        "torch device for the back-projection and the optimiser (cpu, cuda, cuda:N)",
        config="device",
        default_text="cuda if present, else cpu",
    ),
    Setting(
        "oversample",
        int,
        16,
        "range-profile oversampling for the back-projection's interpolation",
        check="positive_int",
    ),
    Setting(
        "estimator",
        str,
        "auto",
        "how the phases are found from the reference (docs/beyond.md): 'paper' = the optimiser from zero; "
        "'projection' = alternating projections onto the template's amplitude, no optimiser (any template); "
        "'projection-refined' = that, then the optimiser (best past lambda/4, where phases wrap); "
        "'registered' = the optimiser after moving the template to where the scan puts the reference; "
        "'correlation' = registered + closed-form per-position phase, no optimiser (fastest); "
        "'correlation-refined' = that, then the optimiser. The last three need the template's phase (a "
        "physical twin: a template scan, or a template file with phase_rad). 'outline' = the reference's "
        "energy inside its outline, no texture, averaged over the outlines grown from its first estimate "
        "(needs a digital twin from a point cloud: rough references, camera clouds). auto: correlation when "
        "the template has a phase; outline for a point-cloud digital twin; else the projections, then the "
        "optimiser only when the projections' own phases show that the errors wrap (metrics.json "
        "estimator.refine_check says which and why)",
        choices=("auto",) + ESTIMATORS,
    ),
    Setting(
        "projection_iterations",
        int,
        30,
        "alternating-projection steps of {estimator} projection (~3 ms each)",
        config="projection_iterations",
        check="non_negative_int",
    ),
    Setting(
        "projection_restarts",
        int,
        0,
        "{estimator} projection also from this many random starts, the best by the loss going on (pays past "
        "lambda/4, ~0.1 s each at 780 x 100 x 100 on 2 cores)",
        config="projection_restarts",
        check="non_negative_int",
    ),
    Setting(
        "coarse_iterations",
        int,
        0,
        "coarse-to-fine: this many optimiser iterations on blurred images before the full-resolution ones "
        "(0: the paper's single stage)",
        config="coarse_iterations",
        check="non_negative_int",
    ),
    Setting(
        "model",
        str,
        "auto",
        "which corrections of the ladder to fit, simplest first: none, phase (one phase per position, the "
        "{estimator}'s closed form), refine (the paper's optimiser), placement (the estimate's ramp), range_errors "
        "(from the band's halves), drift (smooth, per pixel), tilt (the array's, with the drift); auto = each "
        "kept only where its rule says the reference asks for it (the drift and tilt on held-out halves of the "
        "reference); fast = stop at the cheapest rung whose reference passes the trust line (the optimiser and the "
        "drift only below it, no tilt, a physical twin's reference on pixels about a resolution cell apart); "
        "full = every rung fitted where it can run, each kept by its rule; a rung's name = that "
        "rung, those beneath it by their rules, none above it; {phase_ramp} and {space_variant} other than auto "
        "win for their rungs (metrics.json model records every rung, docs/model_ladder.md)",
        choices=MODEL_CHOICES,
    ),
    Setting(
        "phase_ramp",
        str,
        "auto",
        "the estimate's constant + linear-in-aperture phase, which moves the image, before the transfer: auto "
        "removes only what a misplaced template explains (nothing after registering a physical twin; a ramp "
        "worth at most 3 mm of shift otherwise; when the estimate's phases have wrapped or its ramp is larger, "
        "the ramp fitted with the range errors measured from the band's halves taken out, up to 10 mm), since a "
        "hand's drift puts real error in it; remove: always; keep: never (the source paper)",
        choices=("auto", "remove", "keep"),
    ),
    Setting(
        "space_variant",
        str,
        "auto",
        "a smooth drift fitted to the whole reference and transferred per pixel, for a hand's drift (needs a "
        "physical twin): auto = only when one phase per position leaves the reference unmatched "
        "(metrics.json space_variant says what was done)",
        choices=("auto", "on", "off"),
    ),
    Setting(
        "tracking_error_mm",
        float,
        0.5,
        "tracker position error assumed by the confidence report's transfer bound",
        unit="mm",
        check="non_negative",
    ),
)

SETTINGS_BY_NAME: dict[str, Setting] = {s.name: s for s in FOCUS_SETTINGS}


def default_settings() -> dict[str, Any]:
    """name -> default of every focus setting."""
    return {s.name: s.default for s in FOCUS_SETTINGS}


def config_default(field: str) -> Any:
    """The table's default of the AutofocusConfig field ``field``."""
    return next(s.default for s in FOCUS_SETTINGS if s.config == field)


def add_focus_options(parser: argparse.ArgumentParser) -> None:
    """Add every focus setting to ``parser`` as ``--name-with-dashes`` (attribute ``name``)."""

    def option(s: Setting) -> str:
        return s.option

    from twinfocus.option_types import (  # lazy: twinfocus.option_types (+0.03 s on twinfocus record --help)
        CHECKS,
        finite_float,
    )

    for s in FOCUS_SETTINGS:
        text = f"{s.describe(option)} (default {s.default_words(option)})"
        kind = CHECKS[s.check] if s.check else finite_float if s.type is float else s.type
        parser.add_argument(
            s.option, dest=s.name, type=kind, default=s.default, choices=s.choices, help=text.replace("%", "%%")
        )


# --- torch load ------------------------------------------------------------------------------


def preload_torch() -> threading.Thread:
    """Start ``import torch`` on a background thread; returns the thread.

    A run that will fit a hand's drift needs torch (on the CPU too). Started before the run forms
    its images, the import (0.8-0.9 s on the 2-core machine) runs in the gaps of their
    back-projection instead of inside the fit: on hand scans the template stage took about 0.8 s
    longer, the fit's stage 0.9-1.2 s less, the whole run 0.3 s less on average
    (docs/performance_field_fits.md, "Field fits"). The fit's own ``import torch`` waits for this one when it
    has not finished (Python's import lock), so nothing else changes. Not a daemon: a run that
    ends early waits for the import to finish rather than tear it down half done."""
    import importlib

    def load() -> None:
        try:
            importlib.import_module("torch")
        except BaseException:  # noqa: BLE001 - the run's own import says what is wrong, where it needs torch
            pass

    thread = threading.Thread(target=load, name="preload-torch")
    _PRELOADS.append(thread)
    thread.start()
    return thread


#: preload threads started (:func:`wait_for_preload` joins them)
_PRELOADS: list[threading.Thread] = []


def wait_for_preload() -> None:
    """Wait for every :func:`preload_torch` import to finish. The command line calls it before it
    returns, also after a refusal: at interpreter exit a still-running import cannot register its
    exit handlers and prints a traceback ("can't register atexit after shutdown")."""
    while _PRELOADS:
        _PRELOADS.pop().join()
