"""Offline focusing of one scan: the steps behind ``twinfocus focus`` and the solver node.

The focus plan runs them (:class:`twinfocus.focus.plan.FocusPlan`: ``focus_scan`` does steps 1-4
on a scan, ``focus_bases`` steps 3-4 on bases built elsewhere, as the solver node builds them
batch by batch); here are its inputs (:class:`Bases`, :class:`Reference`, :class:`Truth`), its
outputs (:class:`FocusOutputs`; :func:`twinfocus.focus.output_files.write_outputs` writes them), the bases it may ask for
(:func:`half_array_bases`, :func:`upper_band_basis`), the metrics and the confidence report.

1. sub-image bases of the reference and target regions (one back-projection each);
2. the reference template (file, motion-stage scan, digital twin) — or none for the baselines;
3. the ladder of correction models climbed on the reference (:mod:`twinfocus.focus.rungs`: one phase
   per position, the optimiser, the placement, the range errors, the drift, the tilt), or a
   reference-free autofocus of the target;
4. the kept model applied to the target, metrics against the truth when the scan carries it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.focus.autofocus import (
    MAX_TEMPLATE_OFFSET_RANGED_M,
    MIN_RANGED_RAMP_COHERENCE_SQRT_M,
)
from twinfocus.focus.band_delay import half_band_chirps, half_band_data
from twinfocus.focus.estimators import AUTO_REFINE_BELOW_COHERENCE, REFERENCE_FREE_RUNGS
from twinfocus.focus.ladder import DriftStarts, Model, Problem, complex_match, model_view
from twinfocus.focus.outline_fill import outline_fill
from twinfocus.focus.phase_ramp import ramp_free_coherence
from twinfocus.focus.rig_placement import rig_trust
from twinfocus.imaging import metrics
from twinfocus.imaging.backprojection.numba_backend import backproject, subimage_basis, subimage_basis_points
from twinfocus.imaging.basis import form_image
from twinfocus.imaging.grid import ImageGrid
from twinfocus.radar.fmcw import Chirp
from twinfocus.radar.scan import Scan

METHODS = ("twin",) + REFERENCE_FREE_RUNGS + ("none",)


@dataclass
class FocusOutputs:
    """Everything ``twinfocus focus`` writes. Images are complex64 on their grids."""

    reference_grid: ImageGrid
    target_grid: ImageGrid
    method: str
    phase_rad: np.ndarray
    reference: np.ndarray
    reference_uncorrected: np.ndarray
    target: np.ndarray
    target_uncorrected: np.ndarray
    template: np.ndarray | None
    loss_history: np.ndarray
    metrics: dict
    timings_s: dict
    target_truth: np.ndarray | None = None
    reference_truth: np.ndarray | None = None
    phase_oracle_rad: np.ndarray | None = None
    config: dict = field(default_factory=dict)
    #: float64 (M, 3) metres: the smooth drift of the space-variant correction, when it was used
    drift_m: np.ndarray | None = None
    #: complex (H, W) the target as each tried rung of the ladder left it, by rung name (pictures "all")
    rung_targets: dict = field(default_factory=dict)


def check_method(method: str, template: np.ndarray | None) -> None:
    if method not in METHODS:
        raise TwinFocusError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if method == "twin" and template is None:
        raise TwinFocusError("the twin method needs a template (--template, --template-scan or --digital-twin)")


def half_array_bases(
    data: np.ndarray | Callable[[], np.ndarray],
    positions: np.ndarray,
    chirp: Chirp,
    reference_grid: ImageGrid,
    target_grid: ImageGrid,
    bp_options: dict | None = None,
    progress_factory=None,
) -> Callable[[], tuple[np.ndarray, np.ndarray]] | None:
    """What :meth:`FocusPlan.focus_bases <twinfocus.focus.plan.FocusPlan.focus_bases>` calls for the half-array bases (``half_bases``): the reference's
    and the target's sub-image bases from the channels of
    :func:`twinfocus.focus.space_variant.array_half` alone, back-projected only when it is called.

    data : the scan's samples (M, K, N), or a callable that gives them (the solver node keeps them
    in batches); positions : float64 (M, K, 3). Returns None for an array with one channel or no
    extent (no tilt to see).
    """
    from twinfocus.focus.space_variant import array_half  # lazy: scipy.sparse (+0.5 s at import)

    try:
        half = array_half(positions)
    except TwinFocusError:
        return None
    prog = progress_factory or (lambda label: None)
    bp = dict(bp_options or {})

    def bases() -> tuple[np.ndarray, np.ndarray]:
        d, p = (data() if callable(data) else data)[:, half], positions[:, half]
        return (
            subimage_basis(d, p, chirp, reference_grid, progress=prog("reference half-array basis"), **bp),
            subimage_basis(d, p, chirp, target_grid, progress=prog("target half-array basis"), **bp),
        )

    return bases


def upper_band_basis(
    data: np.ndarray | Callable[[], np.ndarray],
    positions: np.ndarray,
    chirp: Chirp,
    reference_grid: ImageGrid,
    bp_options: dict | None = None,
    progress_factory=None,
) -> Callable[[np.ndarray], np.ndarray] | None:
    """What :meth:`FocusPlan.focus_bases <twinfocus.focus.plan.FocusPlan.focus_bases>` calls for the reference's sub-image basis from the upper half of
    the chirp's band (``upper_band``; the lower half's is the whole basis minus it): ``pixels`` bool
    (H, W) on ``reference_grid`` -> complex64 (M, pixels.sum()), back-projected only when called
    and only on those pixels (:mod:`twinfocus.focus.band_delay`).

    data : the scan's samples (M, K, N), or a callable that gives them (the solver node keeps them
    in batches); positions : float64 (M, K, 3). Returns None for a chirp too short to halve.
    """
    if int(chirp.n_samples) < 4:
        return None
    prog = progress_factory or (lambda label: None)
    bp = dict(bp_options or {})
    _, high = half_band_chirps(chirp)

    def basis(pixels: np.ndarray) -> np.ndarray:
        pixels = np.asarray(pixels, dtype=bool)
        if pixels.shape != reference_grid.shape:
            raise TwinFocusError(f"pixels must be a {reference_grid.shape} mask, got {pixels.shape}")
        _, d = half_band_data(data() if callable(data) else data, chirp)
        points = reference_grid.points()[pixels.ravel()]
        return subimage_basis_points(
            d, positions, high, points, progress=prog("reference basis, upper half of the band"), **bp
        )

    return basis


@dataclass
class Reference:
    """The twin's template, as the reference source gave it (all None for the reference-free
    methods). template : float (H, W) amplitude, or complex (H, W) image with its phase, on the
    reference's grid; support : bool (H, W) the reference's outline (a digital twin's), which the
    outline estimator needs and the corrected reference is read against
    (:func:`twinfocus.focus.outline_fill.outline_fill`, metrics.json ``reference_outline``); info : what
    a digital twin's cloud conditioning chose and why
    (:attr:`twinfocus.twins.digital_twin.condition.DigitalTwinReference.info`, metrics.json ``digital_twin``)."""

    template: np.ndarray | None = None
    support: np.ndarray | None = None
    info: dict | None = None


@dataclass
class Bases:
    """The sub-image bases of one scan and its geometry: what the ladder climbs on.

    ref, tgt : complex (M, H, W) sub-image bases of the reference and target regions
    (:func:`twinfocus.imaging.backprojection.numba_backend.subimage_basis`) on ``reference_grid`` / ``target_grid``;
    positions : float64 (M, K, 3) tracked phase centres, metres; chirp : the scan's
    :class:`~twinfocus.radar.fmcw.Chirp`; registration_scores : the template registration's scores when
    already accumulated (the solver node); half_bases, upper_band : the half-array bases and the
    upper band's basis, called only when the tilt and range-errors rungs run
    (:func:`half_array_bases`, :func:`upper_band_basis`); drift_starts : the drift rungs' warm
    starts (:class:`twinfocus.focus.ladder.DriftStarts`: the solver node's fits streamed during a
    sweep), None: cold fits, as ``twinfocus focus`` runs them."""

    ref: np.ndarray
    tgt: np.ndarray
    positions: np.ndarray
    chirp: Chirp
    reference_grid: ImageGrid
    target_grid: ImageGrid
    registration_scores: np.ndarray | None = None
    half_bases: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None
    upper_band: Callable[[np.ndarray], np.ndarray] | None = None
    drift_starts: DriftStarts | None = None

    @classmethod
    def of_scan(
        cls, scan: Scan, ref: np.ndarray, tgt: np.ndarray, reference_grid: ImageGrid, target_grid: ImageGrid
    ) -> Bases:
        """The bases of ``scan`` from its regions' sub-image bases ``ref``, ``tgt`` (complex (M, H, W)
        on ``reference_grid`` / ``target_grid``), with the half-array bases for the tilt rung
        (back-projected only when it calls them); no upper band's basis."""
        half = half_array_bases(scan.data, scan.positions, scan.chirp, reference_grid, target_grid)
        return cls(ref, tgt, scan.positions, scan.chirp, reference_grid, target_grid, half_bases=half)


@dataclass
class Truth:
    """What a simulated scan knows: complex (H, W) images of the target and the reference formed on
    the true positions, and those positions, float64 (M, K, 3) metres."""

    target: np.ndarray
    reference: np.ndarray
    positions: np.ndarray

    @classmethod
    def of_scan(cls, scan: Scan, reference_grid: ImageGrid, target_grid: ImageGrid) -> Truth:
        """The truth of a simulated ``scan`` (one with ``positions_true``): its target's and its
        reference's images back-projected on the true positions, on ``target_grid`` / ``reference_grid``."""
        true = scan.positions_true
        if true is None:
            raise TwinFocusError("only a simulated scan knows its true positions (positions_true)")
        return cls(
            backproject(scan.data, true, scan.chirp, target_grid),
            backproject(scan.data, true, scan.chirp, reference_grid),
            true,
        )


def add_template_metrics(
    m: dict, out: FocusOutputs, template: np.ndarray | None, centre: float, steepness: float
) -> None:
    """The reference against its template, uncorrected and corrected (SSIM of the displayed
    images), and for a template with phase the unmatched share ``reference_residual``."""
    if template is None:
        return
    tpl_disp = metrics.display_image(template, centre, steepness)
    for which, image in (("uncorrected", out.reference_uncorrected), ("corrected", out.reference)):
        m[f"reference_ssim_vs_template_{which}"] = metrics.ssim(
            metrics.display_image(image, centre, steepness), tpl_disp
        )
    if np.iscomplexobj(template):
        m["reference_residual"] = 1.0 - complex_match(out.reference, template)


def add_truth_metrics(
    out: FocusOutputs,
    tgt_basis: np.ndarray,
    positions: np.ndarray,
    chirp: Chirp,
    truth_target: np.ndarray,
    truth_reference: np.ndarray,
    positions_true: np.ndarray,
    centre: float,
    steepness: float,
) -> None:
    """The metrics against the truth, into ``out.metrics`` (and the truth images and oracle phase
    into ``out``): SSIMs of the target and reference against the images formed on the true
    positions, the oracle-phase ceiling at the target's centre and the phase error against it.

    tgt_basis : complex (M, H, W) the target's basis; positions, positions_true : float64
    (M, K, 3) tracked and true phase centres, metres; truth_* : complex (H, W) images on the true
    positions; centre, steepness : the display threshold of the SSIMs. Also run by the solver node
    after it has published its image."""
    m = out.metrics
    out.target_truth, out.reference_truth = truth_target, truth_reference
    out.phase_oracle_rad = metrics.oracle_phase(positions_true, positions, out.target_grid.centre_m, chirp)
    m["target_ssim_uncorrected"] = metrics.image_ssim(out.target_uncorrected, truth_target, centre, steepness)
    m["target_ssim_corrected"] = metrics.image_ssim(out.target, truth_target, centre, steepness)
    m["target_ssim_oracle_phase"] = metrics.image_ssim(
        form_image(tgt_basis, out.phase_oracle_rad), truth_target, centre, steepness
    )
    m["reference_ssim_uncorrected"] = metrics.image_ssim(out.reference_uncorrected, truth_reference, centre, steepness)
    m["reference_ssim_corrected"] = metrics.image_ssim(out.reference, truth_reference, centre, steepness)
    m["phase_error_rms_rad_vs_oracle"] = metrics.phase_error_rms(out.phase_rad, out.phase_oracle_rad)
    m["phase_error_rms_rad_uncorrected"] = metrics.phase_error_rms(np.zeros_like(out.phase_rad), out.phase_oracle_rad)


#: below this reference-vs-template SSIM the reference was not matched and the phase is suspect:
#: an amplitude template (a digital twin's) against a speckled reference matches at 0.77-0.99 even
#: when the target is at its ceiling; a physical twin's own image, registered and fitted in closed
#: form, matches at 0.97-1.0 when the estimate is right (docs/handheld.md), so less is a warning
MIN_REFERENCE_MATCH = 0.8
MIN_REFERENCE_MATCH_PHYSICAL = 0.95
#: above this 1 - complex correlation of the corrected reference with a template that has phase,
#: the correction is incomplete: 0.0008-0.008 under jitter and the live default's VIO error (targets
#: within 0.02 of their ceilings), 0.025-0.031 under a hand's drift with one phase per position
#: (0.83 against 0.97), and above 0.01 after the space-variant fit too (0.86-0.95 against 0.97,
#: every one of 10 draws flagged)
MAX_REFERENCE_RESIDUAL = 0.01
#: a digital twin's reference is read against its outline, not its template's picture
#: (:mod:`twinfocus.focus.outline_fill`): one with a coherent part (smooth, or rough) is flagged when its
#: energy's contrast over the outline is above this. Focused right it sits at 1.5-2.6, piled by a
#: wrong estimate at 2.9-3.9. On the family bench's draws (benchmarks/bench_dtwin_family.py:
#: smooth, rough and speckled references, 390 positions, 64 x 64 pixels) 2.8 is the largest
#: threshold that trusts no result below 0.90 (3.0 trusted a smooth H at 0.878, contrast 2.83);
#: checked on held-out draws (docs/digital_twin_field.md). A speckled one in focus reaches 2.8-3.3,
#: whether its target reached 0.86 or 0.98, so the check is not made on a reference the scan reads
#: as speckled (:func:`twinfocus.focus.outline_fill.surface_from_positions`; on the bench draws that
#: removed 2 false alarms and added no false trust)
MAX_OUTLINE_CONTRAST = 2.8
#: ... or when each radar position's energy over the outline varies across the scan by more than
#: this contrast (:func:`twinfocus.focus.outline_fill.surface_from_positions`): the reference sends most
#: of its return to a few positions (a flat plate's or disc's glint), and the outline leaves the
#: others' phase free. Family bench draws: 2.7-3.8 on every reference but a smooth washer (4.50,
#: its target 0.53-0.84 though its outline looked filled); held out, a rough disc at 4.98
#: (0.61-0.87). 4.1 lies in the bench's gap. It holds for the bench's scans, whose positions cover
#: ``GLINT_APERTURE_M2``; a longer scan sees more of a coherent reference's lobe come and go, and
#: its contrast grows (:func:`glint_threshold`)
MAX_POSITION_ENERGY_CONTRAST = 4.1
#: the family bench's aperture: its phase centres span 0.494 m x 0.129 m (390 positions)
GLINT_APERTURE_M2 = 0.0635
#: how the glint threshold grows with the aperture's area: the same bench references (seeds
#: 1001-1006, smooth) scanned over twice the length (780 positions, 0.128 m^2) read 1.64-1.82x the
#: contrast (rough ones 1.39-1.55x, speckled ones the same), 2^0.8 = 1.74
GLINT_APERTURE_EXPONENT = 0.8
#: ... or when the estimates from the outline's grown variants agree less than this
#: (:func:`twinfocus.focus.template_match.averaged_outline_phase`'s ``agreement``; family bench: below it
#: on six results of 0.62-0.77 and on two of 0.946 and 0.948) ...
MIN_OUTLINE_AGREEMENT = 0.95
#: ... or when a quadratic phase across the aperture lowers the corrected target's entropy by more
#: than this many nats (:func:`twinfocus.focus.target_focus.defocus_gain_nats`): the estimate left a
#: defocus that the reference's outline did not show (family bench's trusted results: 0.002-0.040
#: at and above 0.95 of target SSIM, 0.10 and 0.12 on two of the six below 0.90)
MAX_TARGET_DEFOCUS_GAIN_NATS = 0.06
#: either twin is flagged when its phase moves smoothly along the scan
#: (:func:`twinfocus.focus.drift_check.step_coherence` above this): a drift (family bench: 0.01-0.11
#: under jitter, 0.41-0.50 under a hand's drift, where neither twin reached 0.95)
MAX_STEP_COHERENCE = 0.3
#: ... and its phases spread, their concentration below this (a scan tracked to 0.1 mm: about 0.95;
#: a drift of 0.5 mm and more: below 0.5, tests/test_drift_check.py)
MAX_DRIFT_CONCENTRATION = 0.5
#: what a digital twin's user can do when its result is flagged
DIGITAL_TWIN_NEXT = (
    "to get this scene at its ceiling, scan the reference alone on a motion stage and focus with "
    "--template-scan, or rescan holding the radar steadier"
)


def unchecked_warning(method: str) -> str:
    """The confidence report's warning on every reference-free result: nothing checks it. The
    field benches' reference-free results (benchmarks/bench_dtwin_family.py, bench and held-out
    draws, 720 results) gained 0.12-0.15 SSIM over no correction on average, and only one
    reached 0.90; the three trusted by the resolution cells alone were 0.47-0.69
    (docs/digital_twin_field.md, "Without a reference")."""
    return (
        f"no reference checks the {method} correction: reference-free autofocus on the field benches "
        "gained 0.12-0.15 SSIM over no correction on average and reached 0.90 on 1 of 720 results "
        "(docs/digital_twin_field.md); focus with a twin (--template-scan or --digital-twin) for a "
        "result this report can check"
    )


def glint_threshold(aperture_m2: float | None) -> float:
    """The position energy contrast above which :func:`outline_warnings` calls a reference a glint,
    for a scan whose phase centres cover ``aperture_m2`` (the product of their extents across x
    and y, m^2; None: the family bench's): ``MAX_POSITION_ENERGY_CONTRAST`` scaled by the area over
    ``GLINT_APERTURE_M2`` to the power ``GLINT_APERTURE_EXPONENT``, never below it (a smaller
    scan than the bench's was not measured)."""
    if aperture_m2 is None or not aperture_m2 > GLINT_APERTURE_M2:
        return MAX_POSITION_ENERGY_CONTRAST
    return MAX_POSITION_ENERGY_CONTRAST * (float(aperture_m2) / GLINT_APERTURE_M2) ** GLINT_APERTURE_EXPONENT


def outline_warnings(fill: dict, agreement: float | None) -> list[str]:
    """The digital twin's own checks (docs/digital_twin_field.md), each a warning that says what
    to do. fill : metrics.json ``reference_outline``: ``contrast``, the corrected reference's
    energy contrast over its outline (:func:`twinfocus.focus.outline_fill.outline_fill`), judged unless
    ``surface`` is ``"speckled"``, and ``position_energy_contrast``
    (:func:`twinfocus.focus.outline_fill.surface_from_positions`; either absent: not judged by it),
    judged against :func:`glint_threshold` of ``aperture_m2`` (absent: the family bench's);
    agreement, how far the estimates from the outline's grown variants agree
    (:func:`twinfocus.focus.template_match.averaged_outline_phase`) or None.
    """
    out = []
    contrast, glint = fill["contrast"], fill.get("position_energy_contrast")
    most = glint_threshold(fill.get("aperture_m2"))
    if fill.get("surface") != "speckled" and contrast > MAX_OUTLINE_CONTRAST:
        out.append(
            f"the corrected reference does not fill its outline as a focused reference with a coherent part does: "
            f"its energy's contrast over the outline is {contrast:.1f} (> {MAX_OUTLINE_CONTRAST}; 1.5-2.6 "
            "for a smooth or rough reference in focus): the outline estimate piled the energy into a few bright pixels instead of finding the "
            f"reference's phase; expect the target below its ceiling; {DIGITAL_TWIN_NEXT} (docs/digital_twin_field.md)"
        )
    if glint is not None and glint > most:
        out.append(
            f"the reference sends most of its return to a few radar positions (each position's energy over its "
            f"outline varies by a contrast of {glint:.1f}, > {most:.1f} for this scan's aperture: the glint of a flat "
            "plate or disc), so the outline cannot pin the phase of the others; expect the target below its "
            f"ceiling; {DIGITAL_TWIN_NEXT} (docs/digital_twin_field.md)"
        )
    if agreement is not None and agreement < MIN_OUTLINE_AGREEMENT:
        out.append(
            f"the outline estimate is not sure of the reference's phase: the outlines grown from the camera's "
            f"pulled it apart (agreement {agreement:.2f} < {MIN_OUTLINE_AGREEMENT}); expect the "
            f"target below its ceiling; {DIGITAL_TWIN_NEXT} (docs/digital_twin_field.md)"
        )
    return out


def drift_warnings(step: float, concentration: float | None, digital: bool, separation_deg: float) -> list[str]:
    """A warning when the estimate moves smoothly along the scan (``step``,
    :func:`twinfocus.focus.drift_check.step_coherence`, above ``MAX_STEP_COHERENCE``) and its phases
    spread (``concentration``, :func:`~twinfocus.focus.drift_check.phase_concentration`, below
    ``MAX_DRIFT_CONCENTRATION``; None: not measured): the tracking drifted. A digital twin's one
    phase per position cannot follow a drift across the scene; a physical twin's drift fit follows
    it on the reference, and its transfer to a target ``separation_deg`` away is an extrapolation
    (bench draws: 0.78-0.94 of target SSIM)."""
    if step <= MAX_STEP_COHERENCE or (concentration is not None and concentration >= MAX_DRIFT_CONCENTRATION):
        return []
    what = (
        "one phase per position from an outline cannot undo it across the scene; scan the reference alone on "
        "a motion stage and focus with --template-scan (its drift fit follows a drift), or rescan"
        if digital
        else f"the drift fit followed it on the reference, but carrying it to a target {separation_deg:.0f} deg away "
        "is an extrapolation; put the reference nearer the target, or rescan"
    )
    return [
        f"the tracking drifted: the estimate changes smoothly from one position to the next (step coherence "
        f"{step:.2f} > {MAX_STEP_COHERENCE}), as a drift or a hand's rotation makes it; {what} on a stage or holding "
        "the radar steadier; expect the target below its ceiling (docs/digital_twin_field.md)"
    ]


def placement_warnings(coherence: float, ranged: float | None, removed: bool, outline: bool = True) -> list[str]:
    """A warning when the estimate's phases have wrapped (``coherence``, its ramp-free coherence x
    sqrt(M), :func:`twinfocus.focus.phase_ramp.ramp_free_coherence`, below ``AUTO_REFINE_BELOW_COHERENCE``):
    its ramp, where it puts the reference, is then out of the scan's sight. The band's halves may
    still place it (``ranged``, their ramp coherence x sqrt(M), or None where they were not read;
    ``removed``: the ramp they found was taken out), but their reading carries the reference's
    own delay structure. On the family bench's 27 draws placed so (1 mm and 1.6 mm, and two of the
    paper's protocol) the target sat off across the axis one radar position does not resolve by
    1.0 mm (median), 2.0 mm (one in four) and up to 8 mm, and 3 of the 15 the report had trusted were
    below 0.90 of target SSIM; nothing in the scan tells which, so the report flags a wrapped
    estimate either way (docs/digital_twin_field.md). ``outline``: the estimate came from a digital
    twin's outline (its user is told what to do next)."""
    if coherence >= AUTO_REFINE_BELOW_COHERENCE:
        return []
    wrapped = (
        f"the estimate's phases have wrapped (coherence x sqrt(M) {coherence:.1f} < {AUTO_REFINE_BELOW_COHERENCE}), "
    )
    then = (
        f"{DIGITAL_TWIN_NEXT} " if outline else ""
    ) + '(docs/digital_twin_autofocus.md, "Placing the reference by the band\'s halves")'
    if ranged is not None and ranged >= MIN_RANGED_RAMP_COHERENCE_SQRT_M and removed:
        return [
            wrapped + f"and the band's halves placed the reference (ramp coherence x sqrt(M) {ranged:.1f}), but their "
            "reading carries the reference's own delay structure: across the axis one radar position does not "
            "resolve the target can sit a millimetre or more off (on the field bench: 1 mm typically, more than "
            "2 mm on one draw in four), which costs it as much as a blur, and the scan cannot tell by how much; "
            f"{then}"
        ]
    tried = (
        f"; the band's halves did not place it either (ramp coherence x sqrt(M) {ranged:.2f}, at least "
        f"{MIN_RANGED_RAMP_COHERENCE_SQRT_M} needed, and a shift of at most {MAX_TEMPLATE_OFFSET_RANGED_M * 1e3:.0f} mm)"
        if ranged is not None
        else ""
    )
    return [
        wrapped + "so the scan cannot check where the outline put the reference: across the axis one radar position "
        f"does not resolve it sits where the cloud puts it, and the target can be a few mm off there{tried}; {then}"
    ]


def confidence_report(
    m: dict,
    positions: np.ndarray,
    chirp: Chirp,
    reference_grid: ImageGrid,
    target_grid: ImageGrid,
    tracking_error_m: float,
) -> dict:
    """How far to trust the correction of this scan: the reference match, the first-order
    transfer bound for this geometry (paper eq. 7) and warnings when either is poor.

    m : the metrics so far: ``reference_ssim_vs_template_corrected``, ``reference_residual``,
    ``digital_twin`` and the ``model`` section (:func:`twinfocus.focus.ladder.model_view`); positions :
    float64 (M, K, 3) phase centres, metres."""
    est, ramp, reg = model_view(m)
    out = _transfer_checks(positions, chirp, reference_grid, target_grid, tracking_error_m)
    out["reference_match_ssim"] = m.get("reference_ssim_vs_template_corrected")
    out["warnings"] = out.pop("warnings")  # after the match, as the report has always listed them
    match = out["reference_match_ssim"]
    least = MIN_REFERENCE_MATCH_PHYSICAL if reg else MIN_REFERENCE_MATCH
    fill = m.get("reference_outline")
    if fill is not None:
        _outline_fill_checks(out, m, est, fill)
    elif match is not None and match < least:
        out["warnings"].append(
            f"the corrected reference matches its template poorly (SSIM {match:.2f} < {least}); "
            "check the template, the reference region and the template's placement"
        )
    if "refine_check" in est:
        # what auto chose for an amplitude template, from the projections' own phases
        out["estimator_choice"] = est["refine_check"]["why"]
    _placement_checks(out, est, ramp)
    if "outline" in est:
        _outline_estimator_checks(out, m, est)
    _residual_and_drift_checks(out, m, fill is not None)
    free = (m.get("reference_free") or {}).get("warning")
    if free:
        out["warnings"].append(free)
    if m.get("method") in REFERENCE_FREE_RUNGS:
        out["warnings"].append(unchecked_warning(m["method"]))
    if reg and reg.get("at_limit"):
        out["warnings"].append(
            f"the template registration stopped at its search limit (shift {reg['shift_px'][0]:+.1f}, "
            f"{reg['shift_px'][1]:+.1f} px): the template is placed farther off than that; check its placement"
        )
    if "model" in m:
        out["model"] = m["model"]["result"]
    out.update(rig_trust((m.get("digital_twin") or {}).get("rig")))
    out["trusted"] = not out["warnings"]
    return out


def _transfer_checks(
    positions: np.ndarray, chirp: Chirp, reference_grid: ImageGrid, target_grid: ImageGrid, tracking_error_m: float
) -> dict:
    """The report's geometry: the regions' separation seen from the scan's centre, the transfer
    bound for ``tracking_error_m`` (paper eq. 7), and a warning when the bound passes pi/4."""
    bound = metrics.transfer_bound_rad(
        positions, reference_grid.centre_m, target_grid.centre_m, chirp.wavelength_m, tracking_error_m
    )
    centre = positions.reshape(-1, 3).mean(axis=0)
    sep = np.degrees(
        np.arccos(
            np.clip(
                np.dot(
                    (reference_grid.centre_m - centre) / np.linalg.norm(reference_grid.centre_m - centre),
                    (target_grid.centre_m - centre) / np.linalg.norm(target_grid.centre_m - centre),
                ),
                -1,
                1,
            )
        )
    )
    out: dict = {
        "separation_deg": float(sep),
        "tracking_error_m_assumed": float(tracking_error_m),
        "transfer_bound_rad_max": float(bound.max()),
        "transfer_bound_rad_rms": float(np.sqrt((bound**2).mean())),
        "warnings": [],
    }
    if bound.max() > np.pi / 4:
        out["warnings"].append(
            f"reference and target are {sep:.0f} deg apart: their phase errors may differ by up to "
            f"{bound.max():.2f} rad (> pi/4) for {tracking_error_m * 1e3:.1f} mm tracking error; the transfer is not to be trusted"
        )
    return out


def _outline_fill_checks(out: dict, m: dict, est: dict, fill: dict) -> None:
    """A digital twin: its template is an outline, which a speckled reference never matches as a
    picture; the reference is read against the outline instead, and the target for a defocus."""
    out["reference_outline"] = fill
    agreement = (est.get("outline_ensemble") or {}).get("agreement")
    out["warnings"] += outline_warnings(fill, agreement)
    defocus = m.get("target_defocus")
    if defocus is not None:
        out["target_defocus_gain_nats"] = defocus["entropy_gain_nats"]
        if defocus["entropy_gain_nats"] > MAX_TARGET_DEFOCUS_GAIN_NATS:
            out["warnings"].append(
                f"the corrected target is not at its focus: a quadratic phase across the aperture lowers its "
                f"entropy by {defocus['entropy_gain_nats']:.2f} nats (> {MAX_TARGET_DEFOCUS_GAIN_NATS}; at most 0.04 "
                "on bench results that reached 0.95), so the outline estimate left a defocus that the "
                f"reference did not show; expect the target below its ceiling; {DIGITAL_TWIN_NEXT} "
                "(docs/digital_twin_field.md)"
            )


def _placement_checks(out: dict, est: dict, ramp: dict) -> None:
    """Where the estimate put the reference: the band's halves' ramp when they were read, and a
    warning when the estimate's phases have wrapped."""
    coherence = est.get("phase_coherence_sqrt_m")
    ranged = ramp.get("ramp_coherence_sqrt_m")
    if ranged is not None:
        # the ramp fitted with the range errors from the band's halves taken out: how clearly it
        # stood out (below the fit's threshold nothing was taken)
        out["placement_by_band_halves"] = {
            "ramp_coherence_sqrt_m": ranged,
            "implied_shift_m": ramp.get("implied_shift_m"),
            "removed": bool(ramp.get("removed")) and ranged >= MIN_RANGED_RAMP_COHERENCE_SQRT_M,
        }
    if coherence is not None:
        out["phase_coherence_sqrt_m"] = coherence
        out["warnings"] += placement_warnings(coherence, ranged, bool(ramp.get("removed")), "outline" in est)


def _outline_estimator_checks(out: dict, m: dict, est: dict) -> None:
    """How sure the outline estimator is: the energy it put inside the outline, and how many of
    its starts ended within 0.01 of the chosen one (several far-apart maxima: less sure); a
    warning for a curved reference."""
    info = est["outline"]
    inside = info["energy_inside"]
    out["outline_energy_inside"] = inside[info.get("chosen", int(np.argmax(inside)))]
    if "contrast" in info:
        # the starts that ended within 5 % of the chosen end's speckle contrast
        least = min(info["contrast"])
        out["outline_starts_agreeing"] = f"{sum(c <= 1.05 * least for c in info['contrast'])}/{len(inside)}"
    else:
        best = max(inside)
        out["outline_starts_agreeing"] = f"{sum(v >= best - 0.01 for v in inside)}/{len(inside)}"
    if "outline_ensemble" in est:
        out["outline_agreement"] = est["outline_ensemble"]["agreement"]
    twin = m.get("digital_twin") or {}
    if twin.get("curved"):
        # measured, not modelled: the outline is drawn on the region's plane, which a curved
        # reference leaves, and no draw of a bent plate came near its ceiling
        out["warnings"].append(
            f"the reference is curved (its cloud departs {1e3 * float(twin.get('curvature_m', 0.0)):.1f} mm from a "
            "plane): the outline estimator reached 0.86 +- 0.06 of target SSIM on a bent plate and 0.87 +- 0.06 "
            "on a cylinder section in held-out field scenes, against 0.94 flat and 0.99 with a physical twin; "
            'expect the target below its ceiling (docs/digital_twin_autofocus.md, "Curved references")'
        )


def _residual_and_drift_checks(out: dict, m: dict, digital: bool) -> None:
    """The reference left unmatched by a template with phase, and the phase's drift along the scan."""
    residual = m.get("reference_residual")
    out["reference_residual"] = residual
    if residual is not None and residual > MAX_REFERENCE_RESIDUAL:
        out["warnings"].append(
            f"the corrected reference leaves {residual:.3f} of its template unmatched (> {MAX_REFERENCE_RESIDUAL}): "
            "the error is not all one phase per position (a hand's drift, rotation); expect the target below its ceiling"
        )
    step = m.get("phase_step_coherence")
    if step is not None:
        out["phase_step_coherence"] = step
        out["phase_concentration"] = m.get("phase_concentration")
        drifted = drift_warnings(step, m.get("phase_concentration"), digital, out["separation_deg"])
        out["warnings"] += drifted
        out["drift_warnings"] = len(drifted)


def reference_trust(problem: Problem, model: Model) -> str | None:
    """Why the reference, as ``model`` corrects it, is below the confidence report's trust line,
    or None when it passes: for a digital twin (``problem.support``) the outline checks of
    :func:`outline_warnings` (the grown outlines' agreement aside), otherwise its SSIM against the template at least
    ``MIN_REFERENCE_MATCH`` (``MIN_REFERENCE_MATCH_PHYSICAL`` when registered); with a template that
    has phase at most ``MAX_REFERENCE_RESIDUAL`` unmatched; for an unregistered template phases
    that hold together (ramp-free coherence x sqrt(M) at least ``AUTO_REFINE_BELOW_COHERENCE``).
    What ``--model fast`` stops at (:func:`twinfocus.focus.ladder.climb`)."""
    template = model.template if model.template is not None else problem.template
    if template is None:
        return "no template to judge the reference by"
    reference = model.apply(problem, "reference")
    if problem.support is not None:
        fill = {**outline_fill(reference, problem.support), **(problem.surface or {})}
        warnings = outline_warnings(fill, None)
        if warnings:
            return warnings[0]
    else:
        cfg = problem.config
        least = MIN_REFERENCE_MATCH_PHYSICAL if model.registered else MIN_REFERENCE_MATCH
        c, k = cfg.threshold_centre, cfg.threshold_steepness
        match = metrics.ssim(metrics.display_image(reference, c, k), metrics.display_image(template, c, k))
        if match < least:
            return f"it matches its template at SSIM {match:.2f} (< {least})"
    if np.iscomplexobj(template):
        residual = 1.0 - complex_match(reference, template)
        if residual > MAX_REFERENCE_RESIDUAL:
            return f"it leaves {residual:.3f} of its template unmatched (> {MAX_REFERENCE_RESIDUAL})"
    if not model.registered and model.estimated:
        coherence = ramp_free_coherence(model.estimate_rad, problem.centres[:, :2])
        if coherence < AUTO_REFINE_BELOW_COHERENCE:
            return f"the estimate's phases have wrapped (coherence x sqrt(M) {coherence:.1f} < {AUTO_REFINE_BELOW_COHERENCE})"
    return None
