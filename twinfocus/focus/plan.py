"""The focusing policy in one place: :class:`FocusPlan`.

A plan is made once from the focus settings (:data:`twinfocus.focus.settings.FOCUS_SETTINGS`: a parsed
``twinfocus focus`` or the solver node's parameters) and the method (``twin`` when a template
source is given, else the reference-free one). It

* builds the ladder's rungs once from the registry (:data:`twinfocus.focus.rungs.RUNGS`) with each
  rung's mode (:func:`ladder_modes`: ``--model``, ``--phase-ramp`` and ``--space-variant`` read
  here and nowhere else),
* says what a run needs before it pays for it (:attr:`FocusPlan.needs`: torch for the drift, the
  half-array bases for the tilt, the upper band for the range errors; the reference's strides for
  ``--model fast``: :meth:`FocusPlan.reference_for`),
* resolves the estimator for the template at hand (:meth:`FocusPlan.for_reference`: which named
  estimator, which :class:`~twinfocus.focus.autofocus.AutofocusConfig`),
* and focuses (:meth:`FocusPlan.focus_scan`, :meth:`FocusPlan.focus_bases`): the ladder climbed
  with the confidence report's trust line (``--model fast`` stops there), the outputs with
  metrics.json's ``model`` record and ``confidence`` report.

``twinfocus focus``, the solver node, ``twinfocus batch`` and the benchmarks gather their inputs
and hand them to a plan; none of them reads ``--model``, the estimator or a rung's name.

One vocabulary of modes inside: a rung's mode is "off", "auto", "try" or "on"
(:data:`twinfocus.focus.ladder.MODES`). The words users type keep working and are mapped here once:
``--phase-ramp`` auto / remove / keep is the placement rung's auto / on / off
(:data:`PHASE_RAMP_MODES`); ``--space-variant`` auto / on / off are already rung modes.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.focus.autofocus import RAMP_MODES, AutofocusConfig
from twinfocus.focus.drift_check import phase_concentration, step_coherence
from twinfocus.focus.estimators import (
    MODEL_CHOICES,
    REFERENCE_FREE_RUNGS,
    TWIN_RUNGS,
    estimator_settings,
    estimator_that_ran,
    resolve_estimator,
)
from twinfocus.focus.ladder import (
    SPACE_VARIANT_MODES,
    Model,
    Problem,
    fast_reference,
    legacy_entries,
    rung_entry,
    rung_timings,
)
from twinfocus.focus.outline_fill import outline_fill
from twinfocus.focus.pipeline import (
    Bases,
    FocusOutputs,
    Reference,
    Truth,
    add_template_metrics,
    add_truth_metrics,
    check_method,
    confidence_report,
    half_array_bases,
    reference_trust,
    upper_band_basis,
)
from twinfocus.focus.rig_placement import rig_placed
from twinfocus.focus.rungs import RUNGS, LadderSettings, Rung, climb, reference_free_rungs
from twinfocus.focus.settings import default_settings
from twinfocus.focus.signal_check import check_has_signal
from twinfocus.focus.target_focus import defocus_gain_nats
from twinfocus.imaging.backprojection.numba_backend import backproject, subimage_basis
from twinfocus.imaging.depth_search import DepthSearch, find_target_depth
from twinfocus.imaging.device import resolve_device
from twinfocus.imaging.grid import ImageGrid
from twinfocus.radar.fmcw import Chirp
from twinfocus.radar.scan import Scan

#: ``--phase-ramp``'s words as the placement rung's mode
PHASE_RAMP_MODES = {"auto": "auto", "remove": "on", "keep": "off"}


def ladder_modes(
    model: str = "auto", method: str = "twin", phase_ramp: str = "auto", space_variant: str = "auto"
) -> dict[str, str]:
    """The ladder for one scan, simplest first: rung name -> mode.

    model : "auto" (each rung by its rule), "fast" (auto's rules, but a costly rung, the
        optimiser or the drift, only while the reference is below the trust line, the drift as a
        quick fit judged on one held-out half, and no tilt: the cheapest trusted rung), "full"
        (every rung fitted where it can run, each kept by its rule; the optimiser always) or a
        rung's name (that rung forced, those beneath it by their rules, none above it).
    method : "twin" (the twin's ladder, ``TWIN_RUNGS``), a reference-free rung's name (a ladder
        of its own: none, it, the placement), or "none".
    phase_ramp, space_variant : the placement's and the drift's own settings; other than "auto"
        they win over ``model`` for their rungs.
    """
    if model not in MODEL_CHOICES:
        raise TwinFocusError(f"model must be one of {', '.join(MODEL_CHOICES)}, got {model!r}")
    if space_variant not in SPACE_VARIANT_MODES:
        raise TwinFocusError(f"space_variant must be one of {', '.join(SPACE_VARIANT_MODES)}, got {space_variant!r}")
    if phase_ramp not in RAMP_MODES:
        raise TwinFocusError(f"phase ramp mode must be one of {', '.join(RAMP_MODES)}, got {phase_ramp!r}")
    free = reference_free_rungs()
    if method == "none":
        names: tuple[str, ...] = ("none",)
    elif method == "twin":
        names = TWIN_RUNGS
    elif method in free:
        names = ("none", method, "placement")
    else:
        raise TwinFocusError(f"unknown method {method!r}")
    if model in MODEL_CHOICES[3:] and model not in names:
        raise TwinFocusError(
            f"--model {model}: not a rung of this ladder ({', '.join(names)}): "
            + (
                "the reference-free rungs need --method"
                if model in free
                else "it needs a template (--template, --template-scan or --digital-twin)"
            )
        )
    modes = {name: "auto" for name in names}
    if model == "fast":
        # the tilt, the costliest rung (the half-array bases and a fit with them), is left out
        modes.update(tilt="off")
    elif model == "full":
        modes.update(refine="on", range_errors="try", drift="try", tilt="try")
    elif model != "auto":
        above = names[names.index(model) + 1 :]
        modes.update({n: "off" for n in above})
        modes[model] = "on"
    # a rung's own explicit setting wins over the model
    if phase_ramp != "auto":
        modes["placement"] = PHASE_RAMP_MODES[phase_ramp]
        modes["range_errors"] = "off"
    if space_variant != "auto":
        modes["drift"] = modes["tilt"] = space_variant
    return {name: modes[name] for name in names}


def build_rungs(
    model: str = "auto", method: str = "twin", phase_ramp: str = "auto", space_variant: str = "auto"
) -> tuple[Rung, ...]:
    """The ladder's rungs (:func:`ladder_modes`), each made from the registry with its settings."""
    modes = ladder_modes(model, method, phase_ramp, space_variant)
    ladder = LadderSettings(model, phase_ramp, space_variant, modes)
    return tuple(RUNGS[name].made_for(mode, ladder) for name, mode in modes.items())


@dataclass(frozen=True)
class Target:
    """The target region: box (X0, X1, Y0, Y1) metres, its typed depth (metres; None when
    searched), the range its depth is searched over ((Z0, Z1) metres, or None: at the typed depth)
    and the image's pixels per side."""

    box: tuple[float, ...]
    depth: float | None
    depth_range: tuple[float, float] | None
    size: int


@dataclass(frozen=True)
class Needs:
    """What a run of the plan may use, known before the scan's images are formed: ``torch`` (a
    drift or tilt fit), ``half_bases`` (the tilt's half-array bases), ``upper_band`` (the range
    errors' upper-band basis). A need is only a may: the rung's rule decides on the data."""

    torch: bool
    half_bases: bool
    upper_band: bool


@dataclass(frozen=True)
class FocusPlan:
    """How one scan is focused (module docstring). Make it with :meth:`make`; a plan for the
    template at hand comes from :meth:`for_reference`.

    method : "twin", a reference-free rung's name or "none"; model, phase_ramp, space_variant :
    ``--model``, ``--phase-ramp``, ``--space-variant``; rungs : the ladder (built once);
    settings : the focus settings it was made from (name -> value; the device resolved);
    config : the AutofocusConfig (the estimator's fields in it once :meth:`for_reference` ran, or
    the one given to :meth:`make`); estimator : the named estimator that runs ("" without a
    template); tracking_error_m : what the confidence report assumes; bp_options : the
    back-projection's keywords; progress_factory : ``label -> progress callable``."""

    method: str
    model: str
    phase_ramp: str
    space_variant: str
    rungs: tuple[Rung, ...]
    settings: Mapping[str, Any] = field(default_factory=default_settings)
    config: AutofocusConfig = field(default_factory=AutofocusConfig)
    estimator: str = ""
    explicit_config: bool = False
    tracking_error_m: float = 0.5e-3
    bp_options: Mapping[str, Any] = field(default_factory=dict)
    progress_factory: Callable | None = None

    @classmethod
    def from_settings(
        cls,
        settings: Mapping[str, Any],
        method: str = "twin",
        *,
        bp_options: Mapping[str, Any] | None = None,
        progress_factory: Callable | None = None,
    ) -> FocusPlan:
        """The plan of ``twinfocus focus`` and the solver node: ``settings`` name -> value of
        :data:`~twinfocus.focus.settings.FOCUS_SETTINGS` (those left out take their defaults; a mapping
        with other keys too, such as a parsed command line, is fine) and ``method``; the config
        is made from the settings and the estimator for the template (:meth:`for_reference`).
        Refuses a bad model, phase ramp or space-variant setting before any work."""
        values = {**default_settings(), **settings}
        values["device"] = resolve_device(values["device"])
        return cls(
            method=method,
            model=values["model"],
            phase_ramp=values["phase_ramp"],
            space_variant=values["space_variant"],
            rungs=build_rungs(values["model"], method, values["phase_ramp"], values["space_variant"]),
            settings=values,
            tracking_error_m=float(values["tracking_error_mm"]) * 1e-3,
            bp_options=dict(bp_options or {}),
            progress_factory=progress_factory,
        )

    @classmethod
    def make(
        cls,
        method: str = "twin",
        *,
        config: AutofocusConfig | None = None,
        model: str = "auto",
        phase_ramp: str = "auto",
        space_variant: str = "auto",
        tracking_error_m: float = 0.5e-3,
        bp_options: Mapping[str, Any] | None = None,
        progress_factory: Callable | None = None,
    ) -> FocusPlan:
        """A plan with ``config`` used as is (None: the config's defaults; library and benchmark
        use: fields no setting exposes); the ladder's settings as :func:`ladder_modes` reads them.
        A bad configuration fails here, before any back-projection."""
        config = AutofocusConfig() if config is None else config
        config.validate()
        return cls(
            method=method,
            model=model,
            phase_ramp=phase_ramp,
            space_variant=space_variant,
            rungs=build_rungs(model, method, phase_ramp, space_variant),
            settings={**default_settings(), "model": model, "phase_ramp": phase_ramp, "space_variant": space_variant},
            config=config,
            explicit_config=True,
            tracking_error_m=tracking_error_m,
            bp_options=dict(bp_options or {}),
            progress_factory=progress_factory,
        )

    def varied(self, **settings: str) -> FocusPlan:
        """This plan with other ladder settings (``model``, ``phase_ramp``, ``space_variant``),
        its rungs made anew; the config and the estimator kept. What the depth search's probe
        runs: one phase per position, ``space_variant="off"``."""
        values = {**self.settings, **settings}
        rungs = build_rungs(values["model"], self.method, values["phase_ramp"], values["space_variant"])
        return replace(
            self,
            model=values["model"],
            phase_ramp=values["phase_ramp"],
            space_variant=values["space_variant"],
            rungs=rungs,
            settings=values,
        )

    def climbs(self, rung: str) -> bool:
        """Whether the ladder has ``rung`` and may climb it (its mode not off)."""
        return any(r.name == rung and r.mode != "off" for r in self.rungs)

    @property
    def needs(self) -> Needs:
        """What a run may use (:class:`Needs`)."""
        twin = self.method == "twin"
        return Needs(
            torch=twin and (self.climbs("drift") or self.climbs("tilt")),
            half_bases=twin and self.climbs("tilt"),
            upper_band=self.climbs("range_errors"),
        )

    def for_reference(self, template: np.ndarray | None, support: np.ndarray | None = None) -> FocusPlan:
        """This plan for a template (float or complex (H, W); complex: with its phase, a physical
        twin's) and the reference's outline (bool (H, W), a digital twin's, or None): the named
        estimator resolved (``estimator: auto`` by what the template is) and the config made from
        the settings with the estimator's fields (:func:`twinfocus.focus.estimators.estimator_settings`;
        an explicit ``loss_steepness`` wins). A config given to :meth:`make` is kept as is."""
        has_phase = template is not None and bool(np.iscomplexobj(template))
        twin = self.method == "twin" and template is not None
        estimator = resolve_estimator(self.settings["estimator"], has_phase, support is not None) if twin else ""
        if self.explicit_config:
            return replace(self, estimator=estimator)
        chosen = (
            estimator_settings(self.settings["estimator"], has_phase, support is not None, self.model) if twin else {}
        )
        if self.settings["loss_steepness"] is not None:
            chosen["loss_steepness"] = self.settings["loss_steepness"]
        config = AutofocusConfig.from_settings(self.settings, **chosen)  # validated
        return replace(self, estimator=estimator, config=config)

    def estimator_that_ran(self, metrics: dict) -> str:
        """The named estimator that found the phase (metrics.json's ``estimator`` says whether the
        optimiser of "projection-refined" ran), "" without one."""
        return estimator_that_ran(self.estimator, metrics.get("estimator", {})) if self.estimator else ""

    def reference_for(
        self, reference: Reference, positions_m: np.ndarray, grid: ImageGrid, wavelength_m: float
    ) -> tuple[ImageGrid, Reference, tuple[int, int]]:
        """The reference's grid and template for this plan, and the strides (rows, columns) taken:
        ``--model fast`` forms a physical twin's reference on pixels about a resolution cell apart
        (:func:`twinfocus.focus.ladder.fast_reference`); otherwise as given, (1, 1).
        positions_m : float (M, K, 3) phase centres, metres; grid : the reference's grid."""
        if self.method != "twin":
            return grid, reference, (1, 1)
        grid, template, strides = fast_reference(
            self.model, reference.template, reference.support, positions_m, grid, wavelength_m
        )
        return grid, replace(reference, template=template), strides

    def focus_scan(
        self, scan: Scan, reference_grid: ImageGrid, target_grid: ImageGrid, reference: Reference | None = None
    ) -> FocusOutputs:
        """Focus a validated scan: its sub-image bases (and the truth images when it carries
        ``positions_true``), then :meth:`focus_bases`."""
        return _focus_scan(self, scan, reference_grid, target_grid, reference or Reference())

    def focuser(self, reference_grid: ImageGrid, reference: Reference) -> Callable[..., FocusOutputs]:
        """``focus(scan, target_grid, space_variant)``: :meth:`focus_scan` with the reference bound,
        ``space_variant`` this plan's or "off" (the depth and box searches' probe: one phase per
        position, before any space-variant step)."""
        plans = {"off": self.varied(space_variant="off")}
        plans[self.space_variant] = self

        def focus(scan: Scan, target_grid: ImageGrid, space_variant: str | None = None) -> FocusOutputs:
            plan = plans[space_variant or self.space_variant]
            return plan.focus_scan(scan, reference_grid, target_grid, reference)

        return focus

    def focus_target(
        self, scan: Scan, reference_grid: ImageGrid, reference: Reference, target: Target
    ) -> tuple[FocusOutputs, DepthSearch | None]:
        """Focus ``target``: at its typed depth, or at the depth where its corrected image is
        sharpest (:func:`twinfocus.imaging.depth_search.find_target_depth`; metrics.json ``target_depth``,
        its time ``timings_s.target_depth``). Returns the outputs and the search (None: typed)."""
        focus = self.focuser(reference_grid, reference)
        search = None
        if target.depth_range is not None:
            t = time.perf_counter()
            search, info = find_target_depth(
                focus, scan, target.box, target.depth_range, self.method, dict(self.bp_options), self.progress_factory
            )
            seconds = time.perf_counter() - t
            grid = ImageGrid.from_roi((*target.box, search.depth_m), target.size)
        else:
            assert isinstance(target.depth, float)
            grid = ImageGrid.from_roi((*target.box, target.depth), target.size)
        out = focus(scan, grid, self.space_variant)
        if search is not None:
            out.metrics["target_depth"] = {**info, **search.to_dict()}
            out.timings_s = {"target_depth": seconds, **out.timings_s}
        return out, search

    def focus_bases(self, bases: Bases, reference: Reference | None = None, truth: Truth | None = None) -> FocusOutputs:
        """Focus on sub-image bases built elsewhere (the solver node streams them): the ladder
        climbed on the reference, the kept model applied to both regions, the metrics
        (metrics.json ``model`` records every rung) and the confidence report; with ``truth``, the
        metrics against it."""
        return _focus_bases(self, bases, reference or Reference(), truth)


def _focus_scan(
    plan: FocusPlan, scan: Scan, reference_grid: ImageGrid, target_grid: ImageGrid, reference: Reference
) -> FocusOutputs:
    """Run the offline focusing steps on a validated scan: the two sub-image bases (and the
    truth images when the scan carries ``positions_true``), then :func:`_focus_bases`. The
    back-projection's keywords are the plan's ``bp_options`` (oversample, precision, backend,
    device); ``--model fast`` forms the reference at its resolution (:meth:`FocusPlan.reference_for
    <twinfocus.focus.plan.FocusPlan.reference_for>`)."""
    check_method(plan.method, reference.template)
    bp = dict(plan.bp_options)
    prog = plan.progress_factory or (lambda label: None)
    timings: dict[str, float] = {}
    reference_grid, reference, strides = plan.reference_for(
        reference, scan.positions, reference_grid, scan.chirp.wavelength_m
    )

    t = time.perf_counter()
    ref_basis = subimage_basis(
        scan.data, scan.positions, scan.chirp, reference_grid, progress=prog("reference basis"), **bp
    )
    timings["reference_basis"] = time.perf_counter() - t
    # Fail before the second back-projection, not after it (focus_bases checks these again).
    check_has_signal(ref_basis.sum(axis=0), "the reference region", basis=ref_basis)
    if reference.template is not None:
        check_has_signal(reference.template, "the template")

    t = time.perf_counter()
    tgt_basis = subimage_basis(scan.data, scan.positions, scan.chirp, target_grid, progress=prog("target basis"), **bp)
    timings["target_basis"] = time.perf_counter() - t

    truth = None
    if scan.positions_true is not None:
        t = time.perf_counter()
        truth = Truth(
            backproject(scan.data, scan.positions_true, scan.chirp, target_grid, progress=prog("target truth"), **bp),
            backproject(
                scan.data, scan.positions_true, scan.chirp, reference_grid, progress=prog("reference truth"), **bp
            ),
            scan.positions_true,
        )
        truth_time = time.perf_counter() - t

    needs, geometry = plan.needs, (scan.data, scan.positions, scan.chirp, reference_grid)
    bases = Bases(
        ref_basis,
        tgt_basis,
        scan.positions,
        scan.chirp,
        reference_grid,
        target_grid,
        half_bases=half_array_bases(*geometry, target_grid, bp, plan.progress_factory) if needs.half_bases else None,
        upper_band=upper_band_basis(*geometry, bp, plan.progress_factory) if needs.upper_band else None,
    )
    out = _focus_bases(plan, bases, reference, truth)
    timings.update(out.timings_s)
    out.metrics["model"]["reference_strides"] = list(strides)
    if truth is not None:
        timings["truth_images"] = truth_time
    out.timings_s = timings
    out.metrics["timings_s"] = timings
    return out


def _focus_bases(plan: FocusPlan, bases: Bases, reference: Reference, truth: Truth | None = None) -> FocusOutputs:
    """The focusing steps that follow the sub-image bases: the plan's ladder of correction models
    (:mod:`twinfocus.focus.rungs`, docs/model_ladder.md) climbed on the reference, the kept model applied
    to both regions, the metrics (metrics.json ``model`` records every rung) and the confidence
    report; with ``truth``, the metrics against it.

    Shared by ``twinfocus focus`` (:func:`focus_scan`) and the solver node (bases streamed batch
    by batch), so both give the same phase, images and metrics keys. The plan's config is handed
    to the autofocus as is.

    Returns :class:`FocusOutputs` (``timings_s`` holds ``autofocus``; ``metrics`` has no
    ``timings_s``: the caller adds its own).
    """
    template, support, method = reference.template, reference.support, plan.method
    check_method(method, template)
    cfg = plan.config
    cfg.validate()
    check_has_signal(bases.ref.sum(axis=0), "the reference region", basis=bases.ref)
    if template is not None:
        check_has_signal(template, "the template")
    problem = Problem(bases.ref, bases.tgt, bases.positions, bases.chirp, bases.reference_grid, bases.target_grid,
                      cfg, template, support, bases.registration_scores, bases.half_bases, bases.upper_band,
                      plan.progress_factory, reference_trust, bases.drift_starts)  # fmt: skip
    kept, section = climb(problem, plan.rungs)
    kept = rig_placed(kept, problem, reference.info)  # a calibrated rig: the reference where the camera saw it
    targets = section.pop("targets")
    m: dict = {
        "method": method,
        "n_positions": int(bases.positions.shape[0]),
        "n_channels": int(bases.positions.shape[1]),
    }
    if reference.info is not None:
        m["digital_twin"] = reference.info
    m["model"] = {"asked": plan.model, **section}
    m.update(legacy_entries(problem, kept, section))
    free = [e["info"] for e in section["rungs"] if e["rung"] in REFERENCE_FREE_RUNGS and e["kept"] and e.get("info")]
    if free:
        m["reference_free"] = free[0]
    out = FocusOutputs(
        reference_grid=bases.reference_grid,
        target_grid=bases.target_grid,
        method=method,
        phase_rad=kept.target_phase(problem),
        reference=kept.apply(problem, "reference"),
        reference_uncorrected=bases.ref.sum(axis=0),
        target=kept.apply(problem, "target"),
        target_uncorrected=bases.tgt.sum(axis=0),
        template=None if template is None else np.abs(template).astype(np.float32),
        loss_history=kept.loss_history,
        metrics=m,
        timings_s=rung_timings(section),
        config={**cfg.to_dict(), **{f"bp_{k}": v for k, v in plan.bp_options.items()}},
        drift_m=kept.drift_m,
        rung_targets=targets,
    )
    # metrics against the template the phases were fitted to (moved when registered)
    add_template_metrics(m, out, kept.template, cfg.threshold_centre, cfg.threshold_steepness)
    if method == "twin":
        _twin_checks(m, out, problem, kept, support)
    m["confidence"] = confidence_report(
        m, bases.positions, bases.chirp, bases.reference_grid, bases.target_grid, plan.tracking_error_m
    )
    if truth is not None:
        add_truth_metrics(out, bases.tgt, bases.positions, bases.chirp, truth.target, truth.reference,
                          truth.positions, cfg.threshold_centre, cfg.threshold_steepness)  # fmt: skip
    return out


def _twin_checks(m: dict, out: FocusOutputs, problem: Problem, kept: Model, support: np.ndarray | None) -> None:
    """The twin's checks the confidence report reads, into ``m``: a digital twin's like-with-like
    reading of the reference against its outline, the phase's drift measures, and with one phase
    per position from an outline whether a defocus is left on the target."""
    if support is not None:
        m["reference_outline"] = {**outline_fill(out.reference, support), **(problem.surface or {})}
    m["phase_step_coherence"] = round(step_coherence(out.phase_rad), 4)
    m["phase_concentration"] = round(phase_concentration(out.phase_rad), 4)
    if support is not None and kept.drift_m is None:
        # the target formed by one phase per position: is a defocus left on it?
        t = time.perf_counter()
        gain, quadratic = defocus_gain_nats(problem.tgt_basis, out.phase_rad, problem.centres)
        m["target_defocus"] = {"entropy_gain_nats": round(gain, 4), "quadratic_rad": [round(float(q), 3) for q in quadratic],
                               "time_s": round(time.perf_counter() - t, 3)}  # fmt: skip


def place_estimate(
    phase: np.ndarray,
    ref_basis: np.ndarray,
    positions: np.ndarray,
    chirp: Chirp,
    reference_grid: ImageGrid,
    phase_ramp: str = "auto",
    *,
    registered: bool = False,
    upper_band: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, dict, float | None]:
    """The ladder's placement and range-errors rungs climbed on one estimate
    (:class:`~twinfocus.focus.rungs.Placement`, :class:`~twinfocus.focus.rungs.RangeErrors`): the phase
    :meth:`~twinfocus.focus.plan.FocusPlan.focus_bases` transfers to the target, its constant + linear ramp handled by
    :func:`~twinfocus.focus.autofocus.transfer_phase` (``phase_ramp``).

    The plain ramp fit cannot place the reference when the estimate's phases have wrapped (its
    ramp is out of sight) nor when its ramp is larger than a misplacement explains (it may be
    tracking error): with ``upper_band`` (:func:`~twinfocus.focus.pipeline.upper_band_basis`) and ``phase_ramp`` 'auto' the
    range errors from the band's halves then take the tracking error out along the line of sight
    and tell (docs/digital_twin_autofocus.md, "Placing the reference by the band's halves").

    phase : float (M,) radians; ref_basis : complex (M, H, W) on ``reference_grid``; positions :
    float64 (M, K, 3) phase centres, metres. Returns (float64 (M,) radians, the ``phase_ramp``
    metrics, seconds the range errors took or None when they were not read)."""
    problem = Problem(ref_basis, ref_basis, positions, chirp, reference_grid, reference_grid, AutofocusConfig(),
                      upper_band=upper_band)  # fmt: skip
    estimate = np.asarray(phase, dtype=np.float64)
    start = Model(estimate, estimate, registered=registered, estimated=True)
    rungs = [r for r in build_rungs(phase_ramp=phase_ramp) if r.name in ("placement", "range_errors")]
    model, section = climb(problem, rungs, start)
    ranged = rung_entry(section, "range_errors")
    assert model.ramp is not None
    return model.phase_rad, model.ramp, ranged["time_s"] if ranged.get("tried") else None


def climbs_to(rung: str, model: str = "auto", space_variant: str = "auto") -> bool:
    """Whether the twin's ladder for ``model`` and ``space_variant`` has ``rung`` and may climb
    it (:meth:`FocusPlan.climbs`); False for a ``model`` the twin's ladder refuses."""
    try:
        return FocusPlan.make(model=model, space_variant=space_variant).climbs(rung)
    except TwinFocusError:
        return False
