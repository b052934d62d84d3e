"""The ladder of correction models: each correction a small object of one shape, climbed from the
simplest, a richer one kept only when its rule says the reference asks for it: the drift and the
tilt on held-out evidence (fitted on one half of the reference's pixels, judged on the other:
:func:`heldout_split`, :func:`heldout_gain`, :func:`heldout_verdict`).

A rung (:class:`Rung`) is made from settings only (its ``mode``), ``fit`` on the reference
(:class:`Problem`: the sub-image bases, the scan's geometry, the template) starting from the
:class:`Model` the rungs beneath it left, and gives a new :class:`Model` that ``apply`` turns into
an image of any region's basis. :func:`climb` runs the rungs in order and records, per rung, what
it adds, whether it was tried, its evidence (the reference's match before and after, the
parameters it adds), whether it was kept and why, and its time: metrics.json's ``model`` section.

The twin's ladder (``TWIN_RUNGS``), simplest first:

    none -> phase -> refine -> placement -> range_errors -> drift -> tilt

* ``phase``: one phase per position from the reference, the estimator's closed form
  (registered correlation, projections or outline; :func:`twinfocus.autofocus.twin_autofocus`);
* ``refine``: the paper's optimiser from there (same parameters, a costlier fit);
* ``placement``: the estimate's constant + linear ramp, which moves the image, taken out where a
  misplaced template explains it (:func:`twinfocus.autofocus.transfer_phase`);
* ``range_errors``: the ramp fitted with each position's range error, read from the band's
  halves, taken out (:func:`twinfocus.band_delay.position_range_errors_m`);
* ``drift``: a smooth across-sight drift transferred per pixel
  (:func:`twinfocus.space_variant.fit_smooth_drift`);
* ``tilt``: the drift with the array's tilt, from the half-array bases (one fit with the drift).

Without a reference in view the reference-free rungs (``REFERENCE_FREE_RUNGS``: sharpness) stand
on ``none`` instead, each with the placement above it. :func:`build_ladder` makes the rungs from
the ``model`` setting (``auto``, ``fast``, ``full`` or one rung's name) and the rungs' own settings
(``phase_ramp``, ``space_variant``; an explicit value of those wins over ``model``). ``fast``
climbs a costly rung only while the reference is below the confidence report's trust line
(``Problem.trust``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np

from twinfocus import metrics
from twinfocus.autofocus import (
    RAMP_MODES,
    AutofocusConfig,
    refine_check,
    sharpness_autofocus,
    transfer_phase,
    twin_autofocus,
)
from twinfocus.band_delay import bright_pixels, position_range_errors_m
from twinfocus.basis import form_image
from twinfocus.errors import TwinFocusError
from twinfocus.estimators import MODEL_CHOICES, REFERENCE_FREE_RUNGS, TWIN_RUNGS
from twinfocus.grid import ImageGrid
from twinfocus.outline_fill import surface_from_positions
from twinfocus.phase_ramp import MIN_RAMP_COHERENCE_SQRT_M, ramp_free_coherence
from twinfocus.radar import Chirp
from twinfocus.settings import config_default

#: a rung's mode: "off" (not tried), "auto" (its rule decides whether to fit and whether to keep),
#: "try" (fitted whenever it can run, kept by its rule), "on" (fitted and kept; refused when it cannot run)
MODES = ("off", "auto", "try", "on")
SPACE_VARIANT_MODES = ("auto", "on", "off")
#: space-variant "auto": fit when the scalar estimate leaves more than this of the reference
#: unmatched (1 - normalised complex correlation with its template): 0.0008 on the paper's
#: protocol, 0.008 on the demo scene's 0.5 mm x/y/z jitter, 0.025-0.031 under a hand's drift.
#: A rule for the cost only: whether a fit is kept is the held-out evidence's
SPACE_VARIANT_MIN_RESIDUAL = 0.01
#: the held-out fits of the drift and tilt rungs: the knots' stage alone at half its steps, about a
#: quarter of a fit. They only decide keep or not, and a quarter of a fit tells a drift from noise
#: as well as a whole one: on the hand-drift scene of docs/performance.md's focus profile the gain
#: is 70x its noise (a whole fit: 30x), the `space_variant` stage 12 s instead of 20 s, the result
#: the same; on benchmarks/bench_model_ladder.py's draws every scene's `auto` as good or better
#: (the paper protocol's 0.884 -> 0.934: a tilt that fitted the reference but not the target is
#: no longer kept)
HELDOUT_FIT = {"iterations": 50, "refine_iterations": 0}
#: ``--model fast``'s drift fit: the held-out fits' knots' stage and 20 steps of the per-position
#: stage. On the hand draws 3 and 5 (780 positions x 100 x 100): target SSIM 0.944 / 0.944, as the
#: whole fit without the tilt gave, in 1.4 s against 4.2-4.6 s; the knots' stage alone (50
#: steps) 0.928 / 0.943, with 100 steps 0.914 / 0.936 (the per-position stage takes up what the
#: knots' straight segments miss; more knot steps without it fit the reference's noise)
FAST_FIT = {"iterations": 50, "refine_iterations": 20}
#: ``--model fast`` forms a reference whose template has phase (a physical twin's) on pixels up to
#: this share of the scan's resolution cell apart (:func:`fast_reference`), not on every pixel of
#: ``--size``: the reference is there to measure the errors, and the phase estimate and the quick
#: drift fit need its resolution cells, not several pixels in each. On the hand-drift scene (780
#: positions, reference 100 x 100, cells 2.3 mm across x, 4.4 mm across y; docs/performance.md)
#: every other row (0.72 of a cell apart) and every column gave target SSIM 0.945 / 0.945 / 0.906
#: / 0.927 on draws 3 / 5 / 8 / 11 against 0.944 / 0.944 / 0.905 / 0.930 on every pixel, the
#: ladder 1.1-1.3 s against 2.2-2.5 s; every other column too (0.86 of a cell) lost 0.002-0.035 on
#: draws 1, 2, 4, 6, 7 (0.016 on average), and pixels 1.3 cells apart (the family bench's 64 over
#: the same region) 0.03-0.23. An outline (a digital twin's) needs every pixel (family bench draws
#: 1001-1006, 64 -> 32 pixels a side: 0.65-0.84 against 0.80-0.98), so it keeps them
FAST_REFERENCE_CELL_SHARE = 0.8
#: ... and never fewer than this many pixels a side
FAST_REFERENCE_MIN_SIDE = 16


def fast_reference(
    model: str,
    template: np.ndarray | None,
    support: np.ndarray | None,
    positions_m: np.ndarray,
    grid: ImageGrid,
    wavelength_m: float,
) -> tuple[ImageGrid, np.ndarray | None, tuple[int, int]]:
    """The reference's grid and template for ``model``, and the strides (rows, columns) taken: as
    given, (1, 1), but for ``fast`` with a template with phase and no outline, where each axis
    takes the largest stride that keeps its pixels within ``FAST_REFERENCE_CELL_SHARE`` of a
    resolution cell (:func:`twinfocus.reference_free.resolution_cell_m`: lambda R / (2 L), L the
    aperture's extent on that axis), and at least ``FAST_REFERENCE_MIN_SIDE`` pixels a side; the grid
    is then ``grid.every(rows, columns)`` and the template ``template[::rows, ::columns]``.
    positions_m : float (M, K, 3) phase centres, metres; grid : the reference's grid at the
    user's size; template : (H, W) on it."""
    if model != "fast" or template is None or not np.iscomplexobj(template) or support is not None:
        return grid, template, (1, 1)
    from twinfocus.reference_free import resolution_cell_m

    strides = []
    cells = resolution_cell_m(positions_m, grid, wavelength_m)
    for cell, (lo, hi, n) in zip(cells, ((grid.y0, grid.y1, grid.height), (grid.x0, grid.x1, grid.width))):
        # (n - 1) // k + 1 pixels are kept: at least FAST_REFERENCE_MIN_SIDE while k <= (n - 1) // (MIN - 1)
        k = int(FAST_REFERENCE_CELL_SHARE * cell / ((hi - lo) / (n - 1)))
        strides.append(max(1, min(k, (n - 1) // (FAST_REFERENCE_MIN_SIDE - 1))))
    ky, kx = strides
    if (ky, kx) == (1, 1):
        return grid, template, (1, 1)
    return grid.every(ky, kx), template[::ky, ::kx], (ky, kx)


def complex_match(image: np.ndarray, template: np.ndarray) -> float:
    """Normalised complex correlation Re<image, template> / (|image| |template|): 1 when equal.
    Each at unit peak in complex128 first: the norms of complex64 images at 1e20 overflow."""
    a, t = (np.asarray(x).astype(np.complex128).ravel() for x in (image, template))
    a, t = a / max(np.abs(a).max(), 1e-300), t / max(np.abs(t).max(), 1e-300)
    num = np.vdot(t, a).real
    return float(num / max(np.linalg.norm(a) * np.linalg.norm(t), 1e-300))


@dataclass
class Problem:
    """What every rung sees (read only): the regions' bases and the scan's geometry.

    ref_basis, tgt_basis : complex (M, H, W) sub-image bases on ``reference_grid`` /
    ``target_grid``; positions : float64 (M, K, 3) tracked phase centres, metres; template :
    float or complex (H, W) on ``reference_grid`` or None; support : bool (H, W) the reference's
    outline or None; half_bases, upper_band : the callables of
    :func:`twinfocus.pipeline.half_array_bases` / :func:`~twinfocus.pipeline.upper_band_basis`."""

    ref_basis: np.ndarray
    tgt_basis: np.ndarray
    positions: np.ndarray
    chirp: Chirp
    reference_grid: ImageGrid
    target_grid: ImageGrid
    config: AutofocusConfig
    template: np.ndarray | None = None
    support: np.ndarray | None = None
    registration_scores: np.ndarray | None = None
    half_bases: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None
    upper_band: Callable[[np.ndarray], np.ndarray] | None = None
    progress_factory: Callable | None = None
    #: why the reference, as a model corrects it, is below the confidence report's trust line, or
    #: None when it passes (:func:`twinfocus.pipeline.reference_trust`); ``--model fast`` stops there
    trust: Callable[[Problem, Model], str | None] | None = None

    @property
    def centres(self) -> np.ndarray:
        """float64 (M, 3): each position's phase centre (its channels' mean), metres."""
        return self.positions.mean(axis=1)

    @cached_property
    def surface(self) -> dict | None:
        """What the scan says of the reference's surface, read once from its basis over its
        outline (:func:`twinfocus.outline_fill.surface_from_positions`), with ``aperture_m2``, the
        area the phase centres cover (their extent across x times across y, m^2), which that
        reading grows with; None without an outline."""
        if self.support is None:
            return None
        p = self.positions.reshape(-1, 3)
        aperture = float(np.ptp(p[:, 0]) * np.ptp(p[:, 1]))
        return {**surface_from_positions(self.ref_basis, self.support), "aperture_m2": round(aperture, 5)}

    def progress(self, label: str):
        return self.progress_factory(label) if self.progress_factory else None


@dataclass
class Model:
    """A correction, as the rungs kept it so far.

    phase_rad : float64 (M,) radians, what the target gets at the reference's line of sight;
    estimate_rad : float64 (M,) the reference's estimate before the placement; template : the
    template the phases were fitted to (moved when registered); drift_m : float64 (M, 3) metres
    and tilt_rad : float64 (M,) of the space-variant rungs, with ``halves`` the half-array bases
    (reference, target) when the tilt was fitted; extra : the estimator's record
    (:attr:`twinfocus.autofocus.AutofocusResult.extra`); ramp : the placement's record."""

    phase_rad: np.ndarray
    estimate_rad: np.ndarray
    template: np.ndarray | None = None
    registered: bool = False
    #: whether a rung has estimated phases (the placement and range errors need an estimate)
    estimated: bool = False
    loss_history: np.ndarray = field(default_factory=lambda: np.zeros(0))
    extra: dict = field(default_factory=dict)
    ramp: dict | None = None
    drift_m: np.ndarray | None = None
    tilt_rad: np.ndarray | None = None
    halves: tuple[np.ndarray, np.ndarray] | None = None
    #: the same model fitted on each half of :func:`heldout_split` (the rungs above judge
    #: themselves against them); None until a rung kept by held-out evidence sets it
    heldout: tuple[Model, ...] | None = None
    _images: dict = field(default_factory=dict, repr=False)

    def apply(self, problem: Problem, region: str) -> np.ndarray:
        """The corrected image of ``region`` ("reference" or "target"): complex (H, W) on its grid."""
        if region not in self._images:
            basis, grid, half = (
                (problem.ref_basis, problem.reference_grid, 0)
                if region == "reference"
                else (problem.tgt_basis, problem.target_grid, 1)
            )
            if self.drift_m is None:
                self._images[region] = form_image(basis, self.phase_rad)
            else:
                from twinfocus.space_variant import drift_image

                # formed from the tilted bases; the truth metrics keep the scan's own
                tilted = self.halves is not None and self.tilt_rad is not None
                self._images[region] = drift_image(
                    basis,
                    self.phase_rad,
                    self.drift_m,
                    problem.reference_grid.centre_m,
                    problem.centres,
                    grid,
                    problem.chirp.wavelength_m,
                    half_basis=self.halves[half] if tilted else None,  # type: ignore[index]
                    tilt_rad=self.tilt_rad if tilted else None,
                )
        return self._images[region]

    def target_phase(self, problem: Problem) -> np.ndarray:
        """float64 (M,): the one phase per position nearest to what the target got (with a drift,
        the per-pixel phase at the target's centre)."""
        if self.drift_m is None:
            return self.phase_rad
        from twinfocus.space_variant import lines_of_sight

        k = 4.0 * np.pi / problem.chirp.wavelength_m
        c = problem.centres
        du = lines_of_sight(c, problem.target_grid.centre_m) - lines_of_sight(c, problem.reference_grid.centre_m)
        return self.phase_rad + k * np.einsum("mc,mc->m", du, self.drift_m)

    def evolve(self, **changes) -> Model:
        """A copy with ``changes`` (its images formed anew; its held-out fit dropped unless given)."""
        return replace(self, **{"_images": {}, "heldout": None, **changes})


def heldout_split(problem: Problem) -> np.ndarray:
    """bool (H, W): the half of the reference's pixels a held-out fit sees (its complement the
    half it is judged on): square blocks of about one resolution cell (lambda R / (2 L) on each
    axis, L the aperture's extent there; at least 2 pixels, at most half the region; 1 on a
    region of one pixel's width) in a checkerboard. Blocks of a resolution cell keep a pixel's
    neighbours, which share its noise, on its own side."""
    grid = problem.reference_grid
    p = problem.positions.reshape(-1, 3)
    r = float(np.linalg.norm(grid.centre_m - p.mean(axis=0)))
    wl = problem.chirp.wavelength_m
    sides = []
    for axis, n, spacing in ((0, grid.width, grid.spacing_m[0]), (1, grid.height, grid.spacing_m[1])):
        cell = wl * r / (2.0 * max(float(np.ptp(p[:, axis])), wl / 2.0))
        sides.append(int(min(max(np.ceil(cell / max(spacing, 1e-12)), 2), max(n // 2, 1))))
    rows = np.arange(grid.height)[:, None] // sides[1]
    cols = np.arange(grid.width)[None, :] // sides[0]
    return (rows + cols) % 2 == 0


def heldout_gain(before: np.ndarray, after: np.ndarray, template: np.ndarray, judged: np.ndarray) -> dict:
    """How much better ``after`` matches ``template`` than ``before`` does on the ``judged`` pixels.

    before, after, template : complex (H, W) images on the reference's grid; judged : bool (H, W).
    Returns ``unmatched_before``, ``unmatched_after`` (1 - normalised complex correlation on the
    judged pixels; scale-free), ``gain`` (their difference: > 0 when ``after`` matches better)
    and ``pixels`` (how many were judged; with none, no gain)."""
    n = int(np.count_nonzero(judged))
    if n == 0:
        return {"unmatched_before": 0.0, "unmatched_after": 0.0, "gain": 0.0, "pixels": 0}
    t = np.asarray(template)[judged]
    u = [1.0 - complex_match(np.asarray(image)[judged], t) for image in (before, after)]
    return {"unmatched_before": u[0], "unmatched_after": u[1], "gain": u[0] - u[1], "pixels": n}


def heldout_verdict(folds: list[dict]) -> dict:
    """The held-out evidence of a rung from its folds (:func:`heldout_gain` each): the mean
    ``unmatched_before`` / ``unmatched_after`` / ``gain``, ``noise`` (half the folds' spread) and
    ``kept`` (gain > noise: the rung matches every held-out half better than the model beneath)."""
    gains = np.array([f["gain"] for f in folds])
    out: dict = {k: float(np.mean([f[k] for f in folds])) for k in ("unmatched_before", "unmatched_after", "gain")}
    out["noise"] = float(np.ptp(gains) / 2.0)
    out["kept"] = bool(out["gain"] > out["noise"])
    out["folds"] = folds
    return out


def sharpness(image: np.ndarray) -> float:
    """sum(I^2) / sum(I)^2 of I = |image|^2 (complex (H, W)): 1 / the number of pixels the energy
    spreads over, higher when sharper; scale-free (at unit peak in float64 first)."""
    a = np.abs(np.asarray(image)).astype(np.float64)
    inten = (a / max(a.max(), 1e-300)) ** 2
    return float((inten**2).sum() / max(inten.sum() ** 2, 1e-300))


def reference_evidence(problem: Problem, model: Model) -> dict:
    """How well ``model`` matches the reference to its template: for a template with phase the
    unmatched share 1 - complex correlation (lower is better), for an amplitude template the SSIM
    of the displayed images (higher is better); without a template the target's sharpness
    sum(I^2) / sum(I)^2, I = |image|^2 (higher is better)."""
    cfg = problem.config
    template = model.template if model.template is not None else problem.template
    if template is None:
        return {"target_sharpness": sharpness(model.apply(problem, "target"))}
    ref = model.apply(problem, "reference")
    if np.iscomplexobj(template):
        return {"reference_unmatched": 1.0 - complex_match(ref, template)}
    c, s = cfg.threshold_centre, cfg.threshold_steepness
    return {
        "reference_ssim_vs_template": metrics.ssim(
            metrics.display_image(ref, c, s), metrics.display_image(template, c, s)
        )
    }


class Rung:
    """One correction model. Subclasses set ``name``, ``adds`` (one line) and ``cheap`` (closed
    form: ``--model fast`` climbs it whatever the trust line says), and define :meth:`fit`; :meth:`cannot`, :meth:`skip` and
    :meth:`keep` default to "can", "fit" and "keep"."""

    name = ""
    adds = ""
    cheap = True

    def __init__(self, mode: str = "auto"):
        if mode not in MODES:
            raise TwinFocusError(f"rung mode must be one of {', '.join(MODES)}, got {mode!r}")
        self.mode = mode
        #: what the rung's checks and fit recorded (metrics.json ``model.rungs[].info``)
        self.info_: dict = {}
        #: the held-out evidence its keep rule read (``model.rungs[].evidence.heldout``), or None
        self.heldout_: dict | None = None
        #: ``--model fast``: the rung is climbed only while the model beneath is not trusted
        self.until_trusted = False

    def cannot(self, problem: Problem, model: Model) -> str | None:
        """Why this rung cannot run on ``problem`` (refused in mode "on"), or None."""
        return None

    def skip(self, problem: Problem, model: Model) -> str | None:
        """Why the fit is not run although it could (auto's checks before fitting), or None."""
        return None

    def fit(self, problem: Problem, model: Model) -> Model:
        """The richer model fitted on the reference from ``model``; ``self.info_`` says how."""
        raise NotImplementedError

    def keep(self, problem: Problem, before: Model, after: Model) -> tuple[bool, str]:
        """Whether the fitted model is kept, and why."""
        return True, "kept on request" if self.mode == "on" else "fitted"

    def parameters(self, problem: Problem) -> int:
        """How many numbers the rung adds to the model."""
        return 0

    def not_kept(self, before: Model, after: Model) -> Model:
        """The model the rungs above start from when this one's fit is not kept: ``before``."""
        return before

    def off_reason(self) -> str:
        return "off"


class NoCorrection(Rung):
    name, adds = "none", "nothing: every position's phase 0"

    def fit(self, problem: Problem, model: Model) -> Model:
        return model

    def keep(self, problem: Problem, before: Model, after: Model) -> tuple[bool, str]:
        return True, "the baseline the rungs above are measured against"


class PhasePerPosition(Rung):
    """One phase per position from the reference, the estimator's closed form (the config's
    ``init``: correlation after the registration, projections or outline); the paper's estimator
    ("zero") has none: its phases are the optimiser's (``refine``)."""

    name, adds = "phase", "one phase per position, the estimator's closed form"

    def cannot(self, problem: Problem, model: Model) -> str | None:
        return None if problem.template is not None else "needs a template"

    def parameters(self, problem: Problem) -> int:
        return int(problem.positions.shape[0])

    def fit(self, problem: Problem, model: Model) -> Model:
        cfg = problem.config
        assert problem.template is not None  # cannot() refuses without one
        if cfg.init == "zero":
            template, extra = problem.template, dict[str, Any]()
            if cfg.template_registration == "correlation":
                from twinfocus.template_match import register_template

                template, _, extra["registration"] = register_template(
                    problem.ref_basis,
                    template,
                    int(cfg.registration_max_shift_px),
                    scores=problem.registration_scores,
                )
            zero = np.zeros(problem.ref_basis.shape[0])
            self.info_ = {"closed_form": "none (the paper's estimator starts the optimiser from 0)", **extra}
            extra["template"] = template
            registered = "registration" in extra
            return model.evolve(
                phase_rad=zero, estimate_rad=zero, template=template, extra=extra, registered=registered, estimated=True
            )
        closed = replace(cfg, iterations=0, refine_below_coherence=0.0)
        result = twin_autofocus(
            problem.ref_basis,
            problem.template,
            closed,
            progress=problem.progress("autofocus"),
            support=problem.support,
            registration_scores=problem.registration_scores,
            aperture_m=problem.centres[:, :2],
        )
        extra = result.extra
        self.info_ = {"closed_form": cfg.init}
        self.info_.update(
            {k: extra[k] for k in ("registration", "projection_restarts", "outline", "outline_ensemble") if k in extra}
        )
        if "outline" in extra:
            # the scan can check where the outline put the reference only while the phases hold
            # together (their ramp is then seen, and the transfer takes a misplacement's out)
            self.info_["phase_coherence_sqrt_m"] = round(
                ramp_free_coherence(result.phase_rad, problem.centres[:, :2]), 3
            )
        return model.evolve(
            phase_rad=result.phase_rad,
            estimate_rad=result.phase_rad,
            template=result.extra.get("template", problem.template),
            registered="registration" in result.extra,
            loss_history=result.loss_history,
            extra=result.extra,
            estimated=True,
        )


class Refine(Rung):
    """The paper's optimiser (Adam on 1 - SSIM against the template) from the closed form's
    phases. Auto: the estimator decides (``config.iterations``; with ``refine_below_coherence`` and
    the projections, only when their phases have wrapped: :func:`twinfocus.autofocus.refine_check`)."""

    name, adds, cheap = "refine", "the same phases refined by the paper's optimiser", False

    def cannot(self, problem: Problem, model: Model) -> str | None:
        return None if problem.template is not None else "needs a template"

    def _iterations(self, problem: Problem) -> int:
        # a closed-form estimator's config has none: the settings table's then
        return int(problem.config.iterations or config_default("iterations"))

    def skip(self, problem: Problem, model: Model) -> str | None:
        cfg = problem.config
        if self.mode != "auto":
            return None
        if int(cfg.iterations) == 0:
            return f"the estimator is closed form ({cfg.init}): no optimiser"
        if cfg.init == "projection" and cfg.refine_below_coherence > 0:
            check = refine_check(model.estimate_rad, problem.centres[:, :2], cfg.refine_below_coherence)
            self.info_["refine_check"] = check
            return None if check["refined"] else check["why"]
        return None

    def fit(self, problem: Problem, model: Model) -> Model:
        cfg = replace(
            problem.config,
            init="zero",
            template_registration="none",
            refine_below_coherence=0.0,
            iterations=self._iterations(problem),
        )
        assert model.template is not None
        result = twin_autofocus(
            problem.ref_basis,
            model.template,
            cfg,
            progress=problem.progress("autofocus"),
            init_phase_rad=model.estimate_rad,
        )
        self.info_["iterations"] = int(cfg.iterations)
        return model.evolve(phase_rad=result.phase_rad, estimate_rad=result.phase_rad, loss_history=result.loss_history)

    def keep(self, problem: Problem, before: Model, after: Model) -> tuple[bool, str]:
        check = self.info_.get("refine_check")
        if self.mode == "auto" and check is not None:
            return True, check["why"]
        return True, "the estimator refines its phases with the optimiser" if self.mode == "auto" else "on request"


class ReferenceFree(Rung):
    """Autofocus of the target itself, no reference: ``estimate(basis, config, progress) ->
    (phase float (M,) radians, info dict, loss history)``."""

    cheap = False

    def __init__(self, name: str, estimate: Callable, adds: str, mode: str = "auto"):
        super().__init__(mode)
        self.name, self.estimate, self.adds = name, estimate, adds

    def parameters(self, problem: Problem) -> int:
        return int(problem.positions.shape[0])

    def fit(self, problem: Problem, model: Model) -> Model:
        phase, self.info_, losses = self.estimate(
            problem.tgt_basis, problem.config, problem.progress(f"{self.name} autofocus"), problem
        )
        return model.evolve(phase_rad=phase, estimate_rad=phase, loss_history=losses, estimated=True)


def _target_cells(problem: Problem) -> float:
    """The target region's resolution cells for the scan's aperture
    (:func:`twinfocus.reference_free.resolution_cells`)."""
    from twinfocus.reference_free import resolution_cells

    return resolution_cells(problem.positions, problem.target_grid, problem.chirp.wavelength_m)


def _sharpness(
    basis: np.ndarray, config: AutofocusConfig, progress, problem: Problem
) -> tuple[np.ndarray, dict, np.ndarray]:
    """The paper's sharpness optimiser as a rung's estimate; its info carries the region's
    resolution cells per position and a warning when they are too few, as the other
    reference-free rungs' do."""
    from twinfocus.reference_free import cells_summary

    result = sharpness_autofocus(basis, config, progress=progress)
    return result.phase_rad, cells_summary("sharpness", _target_cells(problem), basis.shape[0]), result.loss_history


def _free(method: str) -> Callable:
    """A :mod:`twinfocus.reference_free` method as a rung's estimate; its info carries the
    region's resolution cells per position and a warning when they are too few."""

    def estimate(
        basis: np.ndarray, config: AutofocusConfig, progress, problem: Problem
    ) -> tuple[np.ndarray, dict, np.ndarray]:
        from twinfocus.reference_free import reference_free_autofocus

        result = reference_free_autofocus(basis, method, cells=_target_cells(problem))
        return result.phase_rad, result.extra["reference_free"], result.loss_history

    return estimate


#: the reference-free rungs by name: (estimate, what it adds); ``estimate(basis, config,
#: progress, problem) -> (phase float (M,) radians, info dict, loss history float (n,))``
REFERENCE_FREE: dict[str, tuple[Callable, str]] = {
    "sharpness": (_sharpness, "one phase per position maximising the target's sharpness (no reference)"),
    "entropy": (_free("entropy"), "one phase per position minimising the target's entropy (no reference)"),
    "pga": (_free("pga"), "one phase per position from the target's brightest scatterers (no reference)"),
}


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
    misplacement explains it (:func:`twinfocus.autofocus.transfer_phase`; ``ramp_mode``
    ``--phase-ramp``). Always measured: off, the ramp is reported and transferred as is."""

    name, adds = "placement", "the template's place: the estimate's ramp taken out"
    ramp_mode = "auto"

    def __init__(self, mode: str = "auto"):
        super().__init__(mode)
        self.ramp_mode = {"on": "remove", "off": "keep"}.get(mode, "auto")

    def parameters(self, problem: Problem) -> int:
        return 3

    def cannot(self, problem: Problem, model: Model) -> str | None:
        return None if model.estimated else "no estimate to place"

    def fit(self, problem: Problem, model: Model) -> Model:
        phase, self.info_ = _transfer(problem, model, self.ramp_mode)
        return model.evolve(phase_rad=phase, ramp=self.info_)

    def keep(self, problem: Problem, before: Model, after: Model) -> tuple[bool, str]:
        assert after.ramp is not None
        return bool(after.ramp["removed"]), after.ramp["reason"]

    def not_kept(self, before: Model, after: Model) -> Model:
        # the ramp stays in the phase, and its measurement goes on to the rungs above
        return replace(before, ramp=after.ramp)


class RangeErrors(Rung):
    """Each position's range error read from the band's halves (on the pixels holding 99 % of the
    estimate's image energy), taken out of the estimate before its ramp is fitted
    (docs/digital_twin_autofocus.md, "Placing the reference by the band's halves"). Auto: only when the
    estimate's phases have wrapped (its ramp is out of sight) or its ramp is larger than a
    misplacement explains."""

    name, adds = "range_errors", "each position's range error from the band's halves, before the ramp fit"

    def __init__(self, mode: str = "auto", ramp_mode: str = "auto"):
        super().__init__(mode)
        self.ramp_mode = ramp_mode

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

    def skip(self, problem: Problem, model: Model) -> str | None:
        coherence = ramp_free_coherence(model.estimate_rad, problem.centres[:, :2])
        self.because_ = (
            "the estimate's phases have wrapped"
            if coherence < MIN_RAMP_COHERENCE_SQRT_M
            else "its ramp is larger than a misplacement explains"
            if model.ramp is not None and np.any(model.ramp["slope_rad_per_m"]) and not model.ramp["removed"]
            else None
        )
        if self.mode == "auto" and self.because_ is None:
            return "not needed: the estimate's ramp is in sight and within what a misplacement explains"
        return None

    def fit(self, problem: Problem, model: Model) -> Model:
        assert problem.upper_band is not None
        pixels = bright_pixels(form_image(problem.ref_basis, model.estimate_rad))
        high = problem.upper_band(pixels)
        range_errors = position_range_errors_m(
            problem.ref_basis[:, pixels] - high, high, model.estimate_rad, problem.chirp
        )
        phase, self.info_ = _transfer(problem, model, self.ramp_mode, range_errors)
        self.info_["asked_range_errors_because"] = self.because_ or "asked for"
        return model.evolve(phase_rad=phase, ramp=self.info_)

    def keep(self, problem: Problem, before: Model, after: Model) -> tuple[bool, str]:
        # the transfer's own rule: a ramp taken out only when it stands out of the range errors
        assert after.ramp is not None
        return True, after.ramp["reason"]


class SmoothDrift(Rung):
    """A smooth across-sight drift fitted to the whole reference and transferred per pixel
    (:func:`twinfocus.space_variant.fit_smooth_drift`); with ``tilt`` also the array's tilt, from
    the half-array bases, in the same fit. Needs a registered template with phase (a physical
    twin) and the whole estimate (its ramp kept). Auto: fitted only when the scalar phase leaves
    more than ``SPACE_VARIANT_MIN_RESIDUAL`` of the reference unmatched (the fit's cost); kept
    only on held-out evidence: fitted again on half of the reference's blocks
    (:func:`heldout_split`), it must match the other half better than the model beneath fitted on
    the same half, by more than the gain's noise (:func:`heldout_gain`). ``with_tilt_above``: the
    tilt rung above fits the drift too, so this one leaves it to that rung when the half-array
    bases are there."""

    cheap = False

    def __init__(self, mode: str = "auto", tilt: bool = False, with_tilt_above: bool = False, setting: str = "auto"):
        super().__init__(mode)
        self.tilt, self.with_tilt_above, self.setting = tilt, with_tilt_above, setting
        self.name = "tilt" if tilt else "drift"
        self.adds = (
            "the array's tilt per position, fitted with the drift (half-array bases)"
            if tilt
            else "a smooth across-sight drift per position, transferred per pixel"
        )
        self.info_: dict = {"mode": setting, "used": False}
        #: ``--model fast``: the fit itself is a quick one (``FAST_FIT``), and its held-out evidence
        #: comes from one half alone, where auto judges both
        self.quick = False

    def parameters(self, problem: Problem) -> int:
        m = int(problem.positions.shape[0])
        return 2 * m + (m // 10 + 1 if self.tilt else 0)

    def off_reason(self) -> str:
        self.info_["reason"] = "off on request"
        return "off on request"

    def cannot(self, problem: Problem, model: Model) -> str | None:
        why = None
        if model.template is None or not np.iscomplexobj(model.template) or not model.registered:
            why = "needs a template with phase registered to the scan (a physical twin)"
        elif model.ramp is not None and model.ramp["removed"]:
            why = "the phase ramp was removed before the transfer; the drift fit needs the whole estimate"
        if why:
            self.info_["reason"] = why
        return why

    def skip(self, problem: Problem, model: Model) -> str | None:
        if self.tilt and problem.half_bases is None:
            return "no half-array bases (an array of one channel, or none given)"
        if not self.tilt and self.with_tilt_above and problem.half_bases is not None:
            return "fitted with the array's tilt, one rung up"
        assert model.template is not None
        residual = 1.0 - complex_match(model.apply(problem, "reference"), model.template)
        self.info_["residual_scalar"] = residual
        if self.mode == "auto" and residual <= SPACE_VARIANT_MIN_RESIDUAL:
            self.info_["reason"] = (
                f"not needed: the scalar phase leaves {residual:.4f} of the reference "
                f"unmatched (<= {SPACE_VARIANT_MIN_RESIDUAL})"
            )
            return self.info_["reason"]
        return None

    def _fit(self, problem: Problem, model: Model, halves, fitted: np.ndarray | None = None, **settings):
        """fit_smooth_drift on the reference, or on its ``fitted`` pixels alone (bool (H, W))."""
        from twinfocus.space_variant import DriftFitSettings, fit_smooth_drift  # scipy: only on this path

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
        )

    def fit(self, problem: Problem, model: Model) -> Model:
        t = time.perf_counter()
        halves = problem.half_bases() if self.tilt and problem.half_bases is not None else None
        if halves is not None:
            # a back-projection like the whole bases', reported as a stage of its own
            self.info_["half_array_bases_s"] = time.perf_counter() - t
        phase, drift, tilt, fit = self._fit(problem, model, halves, None, **(FAST_FIT if self.quick else {}))
        if self.quick:
            self.info_["fit"] = (
                f"quick (--model fast): {FAST_FIT['iterations']} steps on the knots, "
                f"at most {FAST_FIT['refine_iterations']} per position"
            )
        self.info_.update(
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
        return model.evolve(phase_rad=phase, drift_m=drift, tilt_rad=tilt, halves=halves)

    def heldout(
        self, problem: Problem, before: Model, after: Model, halves_only: int = 2
    ) -> tuple[dict, tuple[Model, ...]]:
        """The held-out evidence (:func:`heldout_verdict`): on each half of :func:`heldout_split`
        (the first ``halves_only``) this rung and the model beneath, each fitted on that half,
        judged on the other half; and this rung's half fits (the rungs above judge themselves
        against them)."""
        from twinfocus.template_match import correlation_phase

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

    def keep(self, problem: Problem, before: Model, after: Model) -> tuple[bool, str]:
        if self.mode == "on":
            self.info_["used"] = True
            self.info_["reason"] = "on request"
            return True, "on request"
        evidence, half_fits = self.heldout(problem, before, after, halves_only=1 if self.quick else 2)
        self.info_["heldout_fit"] = (
            f"{'one half (--model fast)' if self.quick else 'two halves'}, "
            f"the knots' stage alone at {HELDOUT_FIT['iterations']} steps"
        )
        self.heldout_ = self.info_["heldout"] = evidence
        held = (
            f"fitted on one half of the reference's blocks and judged on the other, it leaves "
            f"{evidence['unmatched_after']:.4f} unmatched against {evidence['unmatched_before']:.4f} beneath it "
            f"(gain {evidence['gain']:.4f}, noise {evidence['noise']:.4f} over {len(evidence['folds'])} halves)"
        )
        if evidence["kept"]:
            self.info_["used"] = True
            after.heldout = None if self.quick else half_fits
            why = f"kept: {held}"
        else:
            why = f"fitted but not kept: {held}; the error is not a smooth drift this reference shows"
        self.info_["reason"] = why
        return self.info_["used"], why


def build_ladder(
    model: str = "auto",
    *,
    method: str = "twin",
    phase_ramp: str = "auto",
    space_variant: str = "auto",
) -> list[Rung]:
    """The rungs for one scan, simplest first, each with its mode.

    model : "auto" (each rung by its rule), "fast" (auto's rules, but a costly rung, the
        optimiser or the drift, only while the reference is below the trust line
        (``Problem.trust``), the drift as a quick fit (``FAST_FIT``) judged on one held-out
        half, and no tilt: the cheapest trusted rung), "full" (every rung fitted where it can run, each
        kept by its rule; the optimiser always) or a rung's name (that rung forced, those beneath
        it by their rules, none above it).
    method : "twin" (the twin's ladder), a reference-free rung's name, or "none".
    phase_ramp, space_variant : the placement's and the drift's own settings; other than "auto"
        they win over ``model`` for their rungs.
    """
    if model not in MODEL_CHOICES:
        raise TwinFocusError(f"model must be one of {', '.join(MODEL_CHOICES)}, got {model!r}")
    if space_variant not in SPACE_VARIANT_MODES:
        raise TwinFocusError(f"space_variant must be one of {', '.join(SPACE_VARIANT_MODES)}, got {space_variant!r}")
    if phase_ramp not in RAMP_MODES:
        raise TwinFocusError(f"phase ramp mode must be one of {', '.join(RAMP_MODES)}, got {phase_ramp!r}")
    if method == "none":
        names: tuple[str, ...] = ("none",)
    elif method == "twin":
        names = TWIN_RUNGS
    elif method in REFERENCE_FREE:
        names = ("none", method, "placement")
    else:
        raise TwinFocusError(f"unknown method {method!r}")
    if model in MODEL_CHOICES[3:] and model not in names:
        raise TwinFocusError(
            f"--model {model}: not a rung of this ladder ({', '.join(names)}): "
            + (
                "the reference-free rungs need --method"
                if model in REFERENCE_FREE_RUNGS
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
        modes["placement"] = {"remove": "on", "keep": "off"}[phase_ramp]
        modes["range_errors"] = "off"
    if space_variant != "auto":
        modes["drift"] = modes["tilt"] = space_variant
    rungs: list[Rung] = []
    for name in names:
        mode = modes[name]
        if name == "none":
            rungs.append(NoCorrection("on"))
        elif name == "phase":
            rungs.append(PhasePerPosition("on" if mode != "off" else "off"))
        elif name == "refine":
            rungs.append(Refine(mode))
        elif name == "placement":
            rungs.append(Placement(mode))
        elif name == "range_errors":
            rungs.append(RangeErrors(mode, ramp_mode=phase_ramp))
        elif name in ("drift", "tilt"):
            setting = space_variant if space_variant != "auto" or model == "auto" else model
            rungs.append(
                SmoothDrift(mode, tilt=name == "tilt", with_tilt_above=modes["tilt"] != "off", setting=setting)
            )
        else:
            estimate, adds = REFERENCE_FREE[name]
            rungs.append(ReferenceFree(name, estimate, adds, "on" if mode != "off" else "off"))
    if model == "fast":
        for rung in rungs:
            rung.until_trusted = not rung.cheap
            if isinstance(rung, SmoothDrift):
                rung.quick = True
    return rungs


def climbs_to(rung: str, model: str = "auto", space_variant: str = "auto") -> bool:
    """Whether the twin's ladder for ``model`` and ``space_variant`` (:func:`build_ladder`) has
    ``rung`` and may climb it (its mode not off): what a caller asks before paying for a rung's
    inputs ahead of the climb (torch for the drift, the half-array bases for the tilt). False for
    a ``model`` the twin's ladder refuses."""
    try:
        rungs = build_ladder(model, space_variant=space_variant)
    except TwinFocusError:
        return False
    return any(r.name == rung and r.mode != "off" for r in rungs)


def climb(problem: Problem, rungs: list[Rung]) -> tuple[Model, dict]:
    """Climb ``rungs`` (:func:`build_ladder`) on ``problem``: returns the kept model and
    metrics.json's ``model`` section: ``rungs``, one entry per rung (``rung``, ``adds``,
    ``mode``, ``tried``, ``kept``, ``why``, ``time_s``, and when tried ``evidence``: the
    reference's match before and after and the ``parameters`` it adds, and ``info``: what its
    fit recorded), ``kept`` (the kept rungs' names), ``result`` (the top kept rung) and
    ``time_s``; and ``targets``, each tried rung's target image (complex (H, W)), for the caller
    to take out."""
    m = problem.ref_basis.shape[0]
    model = Model(phase_rad=np.zeros(m), estimate_rad=np.zeros(m), template=problem.template)
    entries: list[dict] = []
    kept: list[str] = []
    targets: dict[str, np.ndarray] = {}
    t_all = time.perf_counter()
    for rung in rungs:
        entry: dict = {"rung": rung.name, "adds": rung.adds, "mode": rung.mode, "tried": False, "kept": False}
        t = time.perf_counter()
        measured = rung.name == "placement"  # the ramp is reported whatever is done with it
        why = rung.off_reason() if rung.mode == "off" and not measured else rung.cannot(problem, model)
        if why is None and rung.until_trusted and problem.trust is not None:
            below = problem.trust(problem, model)
            if below is None:
                why = f"fast: the reference passes the trust line at {kept[-1]}"
            else:
                entry["below_trust_line"] = below
        if why is None:
            why = rung.skip(problem, model)
        elif rung.mode == "on":
            what = "space-variant correction" if rung.name in ("drift", "tilt") else f"--model {rung.name}:"
            raise TwinFocusError(f"{what} {why}")
        if why is None:
            before = reference_evidence(problem, model) if rung.name != "none" else {}
            candidate = rung.fit(problem, model)
            keep, why = rung.keep(problem, model, candidate)
            after = reference_evidence(problem, candidate)
            entry.update(tried=True, kept=keep)
            targets[rung.name] = candidate.apply(problem, "target")
            entry["evidence"] = {"before": before, "after": after, "parameters": rung.parameters(problem)}
            if rung.heldout_ is not None:
                entry["evidence"]["heldout"] = rung.heldout_
            if keep:
                model = candidate
                kept.append(rung.name)
            else:
                model = rung.not_kept(model, candidate)
        entry.update(why=why, time_s=time.perf_counter() - t)
        if rung.info_:
            entry["info"] = rung.info_
        entries.append(entry)
    section = {"rungs": entries, "kept": kept, "result": kept[-1], "time_s": time.perf_counter() - t_all}
    section["targets"] = targets  # the images, for the pictures: not written to metrics.json
    return model, section


def rung_entry(section: dict, name: str) -> dict:
    """The ``model`` section's entry of rung ``name`` ({} when the ladder has none)."""
    return next((e for e in section.get("rungs", []) if e["rung"] == name), {})


def legacy_entries(problem: Problem, model: Model, section: dict) -> dict:
    """The metrics.json entries that came before the ``model`` section, now read-only aliases of
    it (docs/model_ladder.md): ``estimator`` (the config's estimator, with what ran: its
    ``iterations``, ``refine_check``, ``outline``...), ``template_registration``,
    ``projection_restarts``, ``phase_ramp``, ``phase_ramp_removed`` and ``space_variant``."""
    cfg, out = problem.config, {}
    phase = rung_entry(section, "phase")
    if phase.get("tried"):
        info, refine = phase.get("info", {}), rung_entry(section, "refine")
        est: dict = {"init": cfg.init, "template_registration": cfg.template_registration}
        # what ran: 0 when the optimiser did not
        est["iterations"] = int(refine["info"]["iterations"]) if refine.get("tried") else 0
        if cfg.init == "projection":
            est.update(
                projection_iterations=int(cfg.projection_iterations), projection_restarts=int(cfg.projection_restarts)
            )
        for knob in ("coarse_iterations", "smoothness_weight"):
            if getattr(cfg, knob):
                est[knob] = getattr(cfg, knob)
        est.update({k: info[k] for k in ("outline", "phase_coherence_sqrt_m", "outline_ensemble") if k in info})
        if "refine_check" in refine.get("info", {}):
            est["refine_check"] = refine["info"]["refine_check"]
        out["estimator"] = est
        if "projection_restarts" in info:
            out["projection_restarts"] = info["projection_restarts"]
        if "registration" in info:
            out["template_registration"] = info["registration"]
    if model.ramp is not None:
        out["phase_ramp"] = model.ramp
        out["phase_ramp_removed"] = model.ramp["removed"]
    sv = [rung_entry(section, n) for n in ("drift", "tilt")]
    if sv[0]:
        # the rung that decided: the tilt's when the drift left the fit to it
        deferred = sv[1] and sv[1]["info"].get("reason") and (sv[1]["tried"] or "with the array's tilt" in sv[0]["why"])
        out["space_variant"] = sv[1]["info"] if deferred else sv[0]["info"]
    return out
