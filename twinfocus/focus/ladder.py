"""The ladder of correction models: each correction a small object of one shape, climbed from the
simplest, a richer one kept only when its rule says the reference asks for it: the drift and the
tilt on held-out evidence (fitted on one half of the reference's pixels, judged on the other:
:func:`heldout_split`, :func:`heldout_gain`, :func:`heldout_verdict`).

A rung (:class:`twinfocus.focus.rungs.Rung`, a plain estimator: settings in its constructor) is
``fit`` on the reference (:class:`Problem`: the sub-image bases, the scan's geometry, the
template) starting from the :class:`Model` the rungs beneath it left, and gives a new
:class:`Model` that ``apply`` turns into an image of any region's basis. :func:`climb` runs the rungs in order and records, per rung, what
it adds, whether it was tried, its evidence (the reference's match before and after, the
parameters it adds), whether it was kept and why, and its time: metrics.json's ``model`` section.

The twin's ladder (``TWIN_RUNGS``), simplest first:

    none -> phase -> refine -> placement -> range_errors -> drift -> tilt

* ``phase``: one phase per position from the reference, the estimator's closed form
  (registered correlation, projections or outline; :func:`twinfocus.focus.autofocus.twin_autofocus`);
* ``refine``: the paper's optimiser from there (same parameters, a costlier fit);
* ``placement``: the estimate's constant + linear ramp, which moves the image, taken out where a
  misplaced template explains it (:func:`twinfocus.focus.autofocus.transfer_phase`);
* ``range_errors``: the ramp fitted with each position's range error, read from the band's
  halves, taken out (:func:`twinfocus.focus.band_delay.position_range_errors_m`);
* ``drift``: a smooth across-sight drift transferred per pixel
  (:func:`twinfocus.focus.space_variant.fit_smooth_drift`);
* ``tilt``: the drift with the array's tilt, from the half-array bases (one fit with the drift).

Without a reference in view the reference-free rungs (``REFERENCE_FREE_RUNGS``: sharpness) stand
on ``none`` instead, each with the placement above it. The focus plan
(:class:`twinfocus.focus.plan.FocusPlan`) makes the rungs from the registry
(:data:`twinfocus.focus.rungs.RUNGS`) and the ``model`` setting (``auto``, ``fast``, ``full`` or one
rung's name) and the rungs' own settings (``phase_ramp``, ``space_variant``; an explicit value of
those wins over ``model``). ``fast``
climbs a costly rung only while the reference is below the confidence report's trust line
(``Problem.trust``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from twinfocus.focus.autofocus import AutofocusConfig
from twinfocus.focus.outline_fill import surface_from_positions
from twinfocus.focus.reference_free import resolution_cell_m
from twinfocus.imaging import metrics
from twinfocus.imaging.basis import form_image
from twinfocus.imaging.grid import ImageGrid
from twinfocus.radar.fmcw import Chirp

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
#: a warm-started drift fit after a sweep's last frame (the solver node's, :class:`DriftStarts`): a
#: few steps of each stage from the latest fit streamed while the sweep arrived. On the paper-size
#: hand sweep (benchmarks/bench_bus.py, bus.json ``live_hand_sweep``) the fit after the last frame
#: is a tenth of the scan's fitting, its target SSIM 0.960-0.976 over three runs against the offline
#: fit's 0.965; replayed
#: offline from fits every 100 positions, the image 0.985-0.989 SSIM from the cold fit's (a
#: streamed fit sees part of the aperture against the whole one's template)
WARM_FIT = {"iterations": 10, "refine_iterations": 10}
#: ... and the fits streamed during the sweep, each warm-started from the one before: enough steps
#: that the fits together climb as far as one cold fit (``DriftFitSettings``' 100 + 100)
STREAMED_FIT = {"iterations": 30, "refine_iterations": 30}
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
    resolution cell (:func:`twinfocus.focus.reference_free.resolution_cell_m`: lambda R / (2 L), L the
    aperture's extent on that axis), and at least ``FAST_REFERENCE_MIN_SIDE`` pixels a side; the grid
    is then ``grid.every(rows, columns)`` and the template ``template[::rows, ::columns]``.
    positions_m : float (M, K, 3) phase centres, metres; grid : the reference's grid at the
    user's size; template : (H, W) on it."""
    if model != "fast" or template is None or not np.iscomplexobj(template) or support is not None:
        return grid, template, (1, 1)
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
    :func:`twinfocus.focus.pipeline.half_array_bases` / :func:`~twinfocus.focus.pipeline.upper_band_basis`."""

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
    #: None when it passes (:func:`twinfocus.focus.pipeline.reference_trust`); ``--model fast`` stops there
    trust: Callable[[Problem, Model], str | None] | None = None
    #: the drift rungs' warm starts (the solver node's streamed fits), or None: every fit cold
    drift_starts: DriftStarts | None = None

    @property
    def centres(self) -> np.ndarray:
        """float64 (M, 3): each position's phase centre (its channels' mean), metres."""
        return self.positions.mean(axis=1)

    @cached_property
    def surface(self) -> dict | None:
        """What the scan says of the reference's surface, read once from its basis over its
        outline (:func:`twinfocus.focus.outline_fill.surface_from_positions`), with ``aperture_m2``, the
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
class DriftStarts:
    """The drift rungs' warm starts across the fits of one growing scan (the solver node fits the
    drift on a sweep's positions as they arrive): ``states`` rung name ->
    :class:`twinfocus.focus.space_variant.DriftStart`, the end of that rung's fit on the whole
    reference, which its next fit starts from (the held-out fits stay cold); ``warm``: the steps a
    warm-started fit takes (``iterations``, ``refine_iterations``: :data:`WARM_FIT` after the last
    frame, :data:`STREAMED_FIT` while the sweep arrives; a fit given fewer steps keeps its own, as
    ``--model fast``'s per-position stage). One object shared by the fits of one scan, on one
    thread at a time."""

    states: dict = field(default_factory=dict)
    warm: dict = field(default_factory=lambda: dict(WARM_FIT))

    def settings(self, rung: str, settings: dict) -> dict:
        """``settings`` (DriftFitSettings fields) for ``rung``'s fit: the warm steps when it has
        a start."""
        if rung not in self.states:
            return settings
        steps = {"iterations": 100, "refine_iterations": 100, **settings}
        return {**settings, **{k: min(int(v), int(steps[k])) for k, v in self.warm.items()}}


@dataclass
class Model:
    """A correction, as the rungs kept it so far.

    phase_rad : float64 (M,) radians, what the target gets at the reference's line of sight;
    estimate_rad : float64 (M,) the reference's estimate before the placement; template : the
    template the phases were fitted to (moved when registered); drift_m : float64 (M, 3) metres
    and tilt_rad : float64 (M,) of the space-variant rungs, with ``halves`` the half-array bases
    (reference, target) when the tilt was fitted; extra : the estimator's record
    (:attr:`twinfocus.focus.autofocus.AutofocusResult.extra`); ramp : the placement's record."""

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
                from twinfocus.focus.space_variant import drift_image  # lazy: scipy.sparse (+0.5 s at import)

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
        from twinfocus.focus.space_variant import lines_of_sight  # lazy: scipy.sparse (+0.5 s at import)

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


def reference_evidence(problem: Problem, model: Model) -> dict:
    """How well ``model`` matches the reference to its template: for a template with phase the
    unmatched share 1 - complex correlation (lower is better), for an amplitude template the SSIM
    of the displayed images (higher is better); without a template the target's sharpness
    sum(I^2) / sum(I)^2, I = |image|^2 (higher is better)."""
    cfg = problem.config
    template = model.template if model.template is not None else problem.template
    if template is None:
        return {"target_sharpness": metrics.image_sharpness(model.apply(problem, "target"))}
    ref = model.apply(problem, "reference")
    if np.iscomplexobj(template):
        return {"reference_unmatched": 1.0 - complex_match(ref, template)}
    c, s = cfg.threshold_centre, cfg.threshold_steepness
    return {
        "reference_ssim_vs_template": metrics.ssim(
            metrics.display_image(ref, c, s), metrics.display_image(template, c, s)
        )
    }


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


def rung_timings(section: dict) -> dict[str, float]:
    """The timings_s entries of the ladder's rungs (read-only aliases of the ``model`` section's
    ``time_s``): ``autofocus`` (the estimate: phase and refine, or a reference-free rung),
    ``range_errors``, ``half_array_bases`` (the tilt's back-projection of one half of the array's
    channels, when it ran) and ``space_variant`` (the drift or tilt kept, less those bases)."""
    seconds = {e["rung"]: e["time_s"] for e in section["rungs"] if e["tried"]}
    out = {
        "autofocus": sum(
            v for k, v in seconds.items() if k not in ("none", "placement", "range_errors", "drift", "tilt")
        )
    }
    if "range_errors" in seconds:
        out["range_errors"] = seconds["range_errors"]
    for e in section["rungs"]:
        halves_s = e.get("info", {}).get("half_array_bases_s") if e["tried"] else None
        if halves_s is not None:
            out["half_array_bases"] = halves_s
        if e["rung"] in ("drift", "tilt") and e["kept"] and "space_variant" not in out:
            out["space_variant"] = e["time_s"] - (halves_s or 0.0)
    return out


def model_view(m: dict) -> tuple[dict, dict, dict | None]:
    """What the confidence report reads of the correction: (the estimate's record: the phase
    rung's info with the refine rung's ``refine_check``; the placement's record: the range
    errors' when they were read, else the placement's; the template registration or None), from
    metrics.json's ``model`` section, or from the older entries when a metrics dict has none."""
    if "model" not in m:
        return m.get("estimator") or {}, m.get("phase_ramp") or {}, m.get("template_registration")
    section = m["model"]
    est = dict(rung_entry(section, "phase").get("info", {}))
    est.update({k: v for k, v in rung_entry(section, "refine").get("info", {}).items() if k == "refine_check"})
    ranged = rung_entry(section, "range_errors")
    ramp = (ranged if ranged.get("tried") else rung_entry(section, "placement")).get("info", {})
    return est, ramp, est.get("registration")
