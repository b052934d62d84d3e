"""Offline focusing of one scan: the steps behind ``twinfocus focus`` and the solver node.

:func:`focus_scan` does steps 1-4 on a scan; :func:`focus_bases` does steps 3-4 on bases built
elsewhere (the solver node builds them batch by batch as measurements arrive).

1. sub-image bases of the reference and target regions (one back-projection each);
2. the reference template (file, motion-stage scan, digital twin) — or none for the baselines;
3. autofocus: phase per radar position from the reference (or sharpness of the target);
4. phase transfer to the target, metrics against the truth when the scan carries it.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinfocus import metrics
from twinfocus.autofocus import (
    MAX_TEMPLATE_OFFSET_RANGED_M,
    MIN_RANGED_RAMP_COHERENCE_SQRT_M,
    AutofocusConfig,
    AutofocusResult,
    no_correction,
    sharpness_autofocus,
    transfer_phase,
    twin_autofocus,
)
from twinfocus.backprojection import backproject, subimage_basis, subimage_basis_points
from twinfocus.band_delay import bright_pixels, half_band_chirps, half_band_data, position_range_errors_m
from twinfocus.basis import form_image, form_image_space_variant
from twinfocus.errors import TwinFocusError
from twinfocus.estimators import AUTO_REFINE_BELOW_COHERENCE
from twinfocus.grid import ImageGrid
from twinfocus.phase_ramp import MIN_RAMP_COHERENCE_SQRT_M, ramp_free_coherence
from twinfocus.radar import Chirp
from twinfocus.scan import Scan
from twinfocus.templates import check_has_signal

METHODS = ("twin", "sharpness", "none")


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


def _check_method(method: str, template: np.ndarray | None) -> None:
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
    """What :func:`focus_bases` calls for the half-array bases (``half_bases``): the reference's
    and the target's sub-image bases from the channels of
    :func:`twinfocus.space_variant.array_half` alone, back-projected only when it is called.

    data : the scan's samples (M, K, N), or a callable that gives them (the solver node keeps them
    in batches); positions : float64 (M, K, 3). Returns None for an array with one channel or no
    extent (no tilt to see).
    """
    from twinfocus.space_variant import array_half

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
    """What :func:`focus_bases` calls for the reference's sub-image basis from the upper half of
    the chirp's band (``upper_band``; the lower half's is the whole basis minus it): ``pixels`` bool
    (H, W) on ``reference_grid`` -> complex64 (M, pixels.sum()), back-projected only when called
    and only on those pixels (:mod:`twinfocus.band_delay`).

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


def focus_scan(
    scan: Scan,
    reference_grid: ImageGrid,
    target_grid: ImageGrid,
    *,
    template: np.ndarray | None = None,
    support: np.ndarray | None = None,
    reference_info: dict | None = None,
    method: str = "twin",
    config: AutofocusConfig | None = None,
    bp_options: dict | None = None,
    progress_factory=None,
    phase_ramp: str = "auto",
    space_variant: str = "auto",
    tracking_error_m: float = 0.5e-3,
) -> FocusOutputs:
    """Run the offline focusing steps on a validated scan: the two sub-image bases (and the
    truth images when the scan carries ``positions_true``), then :func:`focus_bases`.

    bp_options : keywords of :func:`twinfocus.backprojection.subimage_basis` (oversample,
        precision, backend, device). Other arguments as :func:`focus_bases`.
    """
    _check_method(method, template)
    if config is not None:  # a bad configuration fails before the back-projections
        config.validate()
    bp = dict(bp_options or {})
    prog = progress_factory or (lambda label: None)
    timings: dict[str, float] = {}

    t = time.perf_counter()
    ref_basis = subimage_basis(
        scan.data, scan.positions, scan.chirp, reference_grid, progress=prog("reference basis"), **bp
    )
    timings["reference_basis"] = time.perf_counter() - t
    # Fail before the second back-projection, not after it (focus_bases checks these again).
    check_has_signal(ref_basis.sum(axis=0), "the reference region")
    if template is not None:
        check_has_signal(template, "the template")

    t = time.perf_counter()
    tgt_basis = subimage_basis(scan.data, scan.positions, scan.chirp, target_grid, progress=prog("target basis"), **bp)
    timings["target_basis"] = time.perf_counter() - t

    truth_tgt = truth_ref = None
    if scan.positions_true is not None:
        t = time.perf_counter()
        truth_tgt = backproject(
            scan.data, scan.positions_true, scan.chirp, target_grid, progress=prog("target truth"), **bp
        )
        truth_ref = backproject(
            scan.data, scan.positions_true, scan.chirp, reference_grid, progress=prog("reference truth"), **bp
        )
        truth_time = time.perf_counter() - t

    out = focus_bases(
        ref_basis,
        tgt_basis,
        scan.positions,
        scan.chirp,
        reference_grid,
        target_grid,
        template=template,
        support=support,
        reference_info=reference_info,
        method=method,
        config=config,
        bp_options=bp,
        progress_factory=progress_factory,
        phase_ramp=phase_ramp,
        space_variant=space_variant,
        tracking_error_m=tracking_error_m,
        truth_target=truth_tgt,
        truth_reference=truth_ref,
        positions_true=scan.positions_true,
        half_bases=half_array_bases(
            scan.data, scan.positions, scan.chirp, reference_grid, target_grid, bp, progress_factory
        ),
        upper_band=upper_band_basis(scan.data, scan.positions, scan.chirp, reference_grid, bp, progress_factory),
    )
    timings.update(out.timings_s)
    if truth_tgt is not None:
        timings["truth_images"] = truth_time
    out.timings_s = timings
    out.metrics["timings_s"] = timings
    return out


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
    coherence_sqrt_m: float | None = None,
) -> tuple[np.ndarray, dict, float | None]:
    """The phase :func:`focus_bases` transfers to the target from the reference's estimate: its
    constant + linear ramp handled by :func:`~twinfocus.autofocus.transfer_phase` (``phase_ramp``).

    The plain ramp fit cannot place the reference when the estimate's phases have wrapped (its
    ramp is out of sight) nor when its ramp is larger than a misplacement explains (it may be
    tracking error): with ``upper_band`` (:func:`upper_band_basis`) and ``phase_ramp`` 'auto' the
    range errors from the band's halves then take the tracking error out along the line of sight
    and tell (docs/digital_twin.md, "Placing the reference by the band's halves").

    phase : float (M,) radians; ref_basis : complex (M, H, W) on ``reference_grid``; positions :
    float64 (M, K, 3) phase centres, metres; coherence_sqrt_m : the estimate's
    :func:`~twinfocus.phase_ramp.ramp_free_coherence` when the caller has it. Returns (float64 (M,)
    radians, the ``phase_ramp`` metrics, seconds the range errors took or None when they were not
    read)."""
    centres = positions.mean(axis=1)
    transfer = functools.partial(
        transfer_phase,
        phase,
        centres[:, :2],
        float(reference_grid.z - centres[:, 2].mean()),
        chirp.wavelength_m,
        phase_ramp,
        registered=registered,
    )
    transferred, info = transfer()
    if coherence_sqrt_m is None:
        coherence_sqrt_m = ramp_free_coherence(phase, centres[:, :2])
    out_of_sight = coherence_sqrt_m < MIN_RAMP_COHERENCE_SQRT_M
    too_large = np.any(info["slope_rad_per_m"]) and not info["removed"]
    if upper_band is None or phase_ramp != "auto" or registered or not (out_of_sight or too_large):
        return transferred, info, None
    t = time.perf_counter()
    pixels = bright_pixels(form_image(ref_basis, phase))
    high = upper_band(pixels)
    range_errors = position_range_errors_m(ref_basis[:, pixels] - high, high, phase, chirp)
    seconds = time.perf_counter() - t
    transferred, info = transfer(range_errors_m=range_errors)
    info["asked_range_errors_because"] = (
        "the estimate's phases have wrapped" if out_of_sight else "its ramp is larger than a misplacement explains"
    )
    return transferred, info, seconds


def focus_bases(
    ref_basis: np.ndarray,
    tgt_basis: np.ndarray,
    positions: np.ndarray,
    chirp: Chirp,
    reference_grid: ImageGrid,
    target_grid: ImageGrid,
    *,
    template: np.ndarray | None = None,
    support: np.ndarray | None = None,
    reference_info: dict | None = None,
    method: str = "twin",
    config: AutofocusConfig | None = None,
    bp_options: dict | None = None,
    progress_factory=None,
    phase_ramp: str = "auto",
    space_variant: str = "auto",
    tracking_error_m: float = 0.5e-3,
    truth_target: np.ndarray | None = None,
    truth_reference: np.ndarray | None = None,
    positions_true: np.ndarray | None = None,
    registration_scores: np.ndarray | None = None,
    half_bases: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None,
    upper_band: Callable[[np.ndarray], np.ndarray] | None = None,
) -> FocusOutputs:
    """The focusing steps that follow the sub-image bases: autofocus, transfer, metrics.

    Shared by ``twinfocus focus`` (:func:`focus_scan`) and the solver node (bases streamed batch
    by batch), so both give the same phase, images and metrics keys.

    ref_basis, tgt_basis : complex (M, H, W) sub-image bases of the reference and target regions
        (:func:`twinfocus.backprojection.subimage_basis`) on ``reference_grid`` / ``target_grid``.
    positions : float64 (M, K, 3) tracked phase centres, metres (the ramp fit, the confidence
        report); chirp : the scan's :class:`~twinfocus.radar.Chirp`.
    template : float (H, W) amplitude, or complex (H, W) image with its phase, on
        ``reference_grid`` (required for ``method="twin"``; the phase is what
        ``config.template_registration`` / ``config.init="correlation"`` need).
    support : bool (H, W) the reference's outline on ``reference_grid`` (a digital twin's), which
        ``config.init="outline"`` needs.
    reference_info : what a digital twin's cloud conditioning chose and why
        (:attr:`twinfocus.digital_twin.condition.DigitalTwinReference.info`): written to metrics.json
        as ``digital_twin``; the confidence report reads its ``curved``.
    method : ``"twin"`` (reference vs template), ``"sharpness"`` (of the target) or ``"none"``.
    config : :class:`~twinfocus.autofocus.AutofocusConfig`, handed to the autofocus as is.
    bp_options : the back-projection options the bases were built with (recorded in ``config``).
    phase_ramp : "auto", "remove" or "keep": the estimate's constant + linear-in-aperture ramp
        before the transfer (:func:`twinfocus.autofocus.transfer_phase`). That ramp moves the
        image; "auto" removes only what a template's misplacement explains (none after a
        registration; a fitted ramp only when it stands for a shift of at most 3 mm), since a
        hand's drift puts real error in it. "keep" transfers the phase as is (the source paper).
    space_variant : "auto", "on" or "off": a smooth across-sight drift fitted to the whole
        reference and transferred per pixel (:func:`twinfocus.space_variant.fit_smooth_drift`)
        instead of one phase per position. Needs a registered template with phase (a physical
        twin). "auto" fits it only when the scalar estimate leaves more than
        ``SPACE_VARIANT_MIN_RESIDUAL`` of the reference unmatched, and keeps it only when it
        takes away at least ``SPACE_VARIANT_MIN_GAIN`` of that residual; metrics.json
        ``space_variant`` says what was done and why.
    tracking_error_m : the tracker's position error magnitude assumed by the confidence report.
    progress_factory : ``label -> progress callable`` (see :class:`twinfocus.progress.Progress`).
    truth_target, truth_reference : complex (H, W) images formed on the true positions, and
        positions_true : float64 (M, K, 3); with all three the metrics include the SSIMs
        against the truth and the phase error against the oracle phase.
    registration_scores : the template registration's scores against all of ``ref_basis``
        when already accumulated (the solver node, as the scan arrives); see
        :func:`~twinfocus.autofocus.twin_autofocus`.
    half_bases : ``() -> (reference, target)`` sub-image bases, complex (M, H, W) each, of the
        channels on one side of the array's middle (:func:`twinfocus.space_variant.array_half`),
        called only when the space-variant fit runs: with them it also follows the array's tilt
        (:func:`half_array_bases` makes one from a scan).
    upper_band : ``pixels -> reference basis`` complex (M, pixels.sum()) from the upper half of the
        chirp's band on a bool (H, W) mask of ``reference_grid`` (:func:`upper_band_basis` makes
        one), called only when a template that was not registered gives phases whose ramp cannot
        be seen (wrapped) or is larger than a misplacement explains (``phase_ramp="auto"``), on
        the pixels holding 99 % of the estimate's image energy: the
        positions' range errors measured from the band's halves
        (:func:`twinfocus.band_delay.position_range_errors_m`) then let the transfer find and take
        out the template's misplacement.

    Returns :class:`FocusOutputs` (``timings_s`` holds ``autofocus``; ``metrics`` has no
    ``timings_s``: the caller adds its own).
    """
    _check_method(method, template)
    cfg = config or AutofocusConfig()
    cfg.validate()
    bp = dict(bp_options or {})
    prog = progress_factory or (lambda label: None)
    ref_unc = ref_basis.sum(axis=0)
    tgt_unc = tgt_basis.sum(axis=0)
    check_has_signal(ref_unc, "the reference region")
    if template is not None:
        check_has_signal(template, "the template")
    centres = positions.mean(axis=1)  # each position's phase centre (M, 3): its place in the aperture

    t = time.perf_counter()
    if method == "twin":
        assert template is not None  # _check_method: "twin" needs a template
        result: AutofocusResult = twin_autofocus(
            ref_basis,
            template,
            cfg,
            progress=prog("autofocus"),
            support=support,
            registration_scores=registration_scores,
            aperture_m=centres[:, :2],
        )
    elif method == "sharpness":
        result = sharpness_autofocus(tgt_basis, cfg, progress=prog("sharpness autofocus"))
    else:
        result = no_correction(ref_basis)
    timings = {"autofocus": time.perf_counter() - t}

    phase = result.phase_rad
    # how well a twin estimate's phases hold together once their ramp is out (below the ramp fit's
    # threshold its ramp, the image's place, is out of the fit's sight)
    coherence = ramp_free_coherence(phase, centres[:, :2]) if method == "twin" else float("inf")
    m: dict = {"method": method, "n_positions": int(positions.shape[0]), "n_channels": int(positions.shape[1])}
    if reference_info is not None:
        m["digital_twin"] = reference_info
    if method == "twin":
        m["estimator"] = {
            "init": cfg.init,
            "template_registration": cfg.template_registration,
            "iterations": int(cfg.iterations),
        }
        if cfg.init == "projection":
            m["estimator"].update(
                projection_iterations=int(cfg.projection_iterations), projection_restarts=int(cfg.projection_restarts)
            )
        for knob in ("coarse_iterations", "smoothness_weight"):
            if getattr(cfg, knob):
                m["estimator"][knob] = getattr(cfg, knob)
        if "outline" in result.extra:
            m["estimator"]["outline"] = result.extra["outline"]
            # the scan can check where the outline put the reference only while the phases hold
            # together (their ramp is then seen, and the transfer takes a misplacement's out)
            m["estimator"]["phase_coherence_sqrt_m"] = round(coherence, 3)
        if "outline_ensemble" in result.extra:
            m["estimator"]["outline_ensemble"] = result.extra["outline_ensemble"]
        if "refine_check" in result.extra:
            m["estimator"]["refine_check"] = result.extra["refine_check"]
            if not result.extra["refine_check"]["refined"]:
                m["estimator"]["iterations"] = 0  # what ran: the optimiser was skipped
        if "projection_restarts" in result.extra:
            m["projection_restarts"] = result.extra["projection_restarts"]
        if "registration" in result.extra:
            m["template_registration"] = result.extra["registration"]
        # metrics and pictures against the template the phases were fitted to (moved when registered)
        template = result.extra.get("template", template)
    if method != "none":
        transferred, m["phase_ramp"], ranged_s = place_estimate(
            phase,
            ref_basis,
            positions,
            chirp,
            reference_grid,
            phase_ramp,
            registered="registration" in result.extra,
            upper_band=upper_band if method == "twin" else None,
            coherence_sqrt_m=coherence,
        )
        if ranged_s is not None:
            timings["range_errors"] = ranged_s
        phase = transferred
        m["phase_ramp_removed"] = m["phase_ramp"]["removed"]
    drift = None
    ref_sv_basis, tgt_sv_basis = ref_basis, tgt_basis
    if method == "twin":
        t = time.perf_counter()
        sv = _space_variant(
            ref_basis,
            template,
            phase,
            positions,
            chirp,
            reference_grid,
            space_variant,
            registered="registration" in result.extra,
            ramp_removed=bool(m["phase_ramp"]["removed"]),
            progress=prog("space-variant fit"),
            half_bases=half_bases,
            device=cfg.device,
        )
        m["space_variant"] = sv.pop("info")
        if sv:
            timings["space_variant"] = time.perf_counter() - t
            phase, drift = sv["phase"], sv["drift"]
            if sv["halves"] is not None:
                from twinfocus.space_variant import tilted_basis

                # the images are formed from the tilted bases; the ceiling below keeps the scan's own
                ref_half, tgt_half = sv["halves"]
                ref_sv_basis = tilted_basis(ref_basis, ref_half, sv["tilt"])
                tgt_sv_basis = tilted_basis(tgt_basis, tgt_half, sv["tilt"])
    if drift is None:
        ref_cor = form_image(ref_basis, phase)
        tgt_cor = form_image(tgt_basis, phase)
    else:
        from twinfocus.space_variant import lines_of_sight, pixel_phases

        ref_cor = form_image_space_variant(
            ref_sv_basis,
            pixel_phases(phase, drift, reference_grid.centre_m, centres, reference_grid, chirp.wavelength_m),
        )
        tgt_cor = form_image_space_variant(
            tgt_sv_basis,
            pixel_phases(phase, drift, reference_grid.centre_m, centres, target_grid, chirp.wavelength_m),
        )
        # the scalar phase nearest to what the target got: the per-pixel phase at its centre
        k = 4.0 * np.pi / chirp.wavelength_m
        du = lines_of_sight(centres, target_grid.centre_m) - lines_of_sight(centres, reference_grid.centre_m)
        phase = phase + k * np.einsum("mc,mc->m", du, drift)
    centre, steep = cfg.threshold_centre, cfg.threshold_steepness

    if template is not None:
        tpl_disp = metrics.display_image(template, centre, steep)
        m["reference_ssim_vs_template_uncorrected"] = metrics.ssim(
            metrics.display_image(ref_unc, centre, steep), tpl_disp
        )
        m["reference_ssim_vs_template_corrected"] = metrics.ssim(
            metrics.display_image(ref_cor, centre, steep), tpl_disp
        )
        if np.iscomplexobj(template):
            m["reference_residual"] = 1.0 - _complex_match(ref_cor, template)
    out = FocusOutputs(
        reference_grid=reference_grid,
        target_grid=target_grid,
        method=method,
        phase_rad=phase,
        reference=ref_cor,
        reference_uncorrected=ref_unc,
        target=tgt_cor,
        target_uncorrected=tgt_unc,
        template=None if template is None else np.abs(template).astype(np.float32),
        loss_history=result.loss_history,
        metrics=m,
        timings_s=timings,
        config={**cfg.to_dict(), **{f"bp_{k}": v for k, v in bp.items()}},
        drift_m=drift,
    )
    m["confidence"] = confidence_report(m, positions, chirp, reference_grid, target_grid, tracking_error_m)
    if truth_target is not None and truth_reference is not None and positions_true is not None:
        add_truth_metrics(
            out, tgt_basis, positions, chirp, truth_target, truth_reference, positions_true, centre, steep
        )
    return out


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


#: space-variant "auto": fit when the scalar estimate leaves more than this of the reference
#: unmatched (1 - normalised complex correlation with its template): 0.0008 on the paper's
#: protocol, 0.008 on the demo scene's 0.5 mm x/y/z jitter, 0.025-0.031 under a hand's drift
SPACE_VARIANT_MIN_RESIDUAL = 0.01
#: ... and keep the fit when it takes away at least this fraction of that residual (0.4-0.6 under
#: a hand's drift, docs/handheld.md)
SPACE_VARIANT_MIN_GAIN = 0.3
SPACE_VARIANT_MODES = ("auto", "on", "off")


def _space_variant(
    ref_basis: np.ndarray,
    template: np.ndarray | None,
    phase: np.ndarray,
    positions: np.ndarray,
    chirp: Chirp,
    grid: ImageGrid,
    mode: str,
    registered: bool,
    ramp_removed: bool,
    progress=None,
    half_bases=None,
    device: str = "cpu",
) -> dict:
    """The space-variant step of :func:`focus_bases`: {"info": what was done and why} plus, when
    it is used, "phase" (M,), "drift" (M, 3), "tilt" (M,) and "halves" (the half-array bases of
    the reference and the target, or None)."""
    if mode not in SPACE_VARIANT_MODES:
        raise TwinFocusError(f"space_variant must be one of {', '.join(SPACE_VARIANT_MODES)}, got {mode!r}")
    info: dict = {"mode": mode, "used": False}
    if mode == "off":
        return {"info": {**info, "reason": "off on request"}}
    why_not = None
    if template is None or not np.iscomplexobj(template) or not registered:
        why_not = "needs a template with phase registered to the scan (a physical twin)"
    elif ramp_removed:
        why_not = "the phase ramp was removed before the transfer; the drift fit needs the whole estimate"
    if why_not:
        if mode == "on":
            raise TwinFocusError(f"space-variant correction {why_not}")
        return {"info": {**info, "reason": why_not}}
    assert template is not None  # why_not is set when it is None
    residual = 1.0 - _complex_match(form_image(ref_basis, phase), template)
    info["residual_scalar"] = residual
    if mode == "auto" and residual <= SPACE_VARIANT_MIN_RESIDUAL:
        return {
            "info": {
                **info,
                "reason": f"not needed: the scalar phase leaves {residual:.4f} of the reference "
                f"unmatched (<= {SPACE_VARIANT_MIN_RESIDUAL})",
            }
        }
    from twinfocus.space_variant import fit_smooth_drift  # torch and scipy: only on this path

    halves = half_bases() if half_bases is not None else None
    new_phase, drift, tilt, fit = fit_smooth_drift(
        ref_basis,
        template,
        phase,
        positions.mean(axis=1),
        grid,
        chirp.wavelength_m,
        half_basis=None if halves is None else halves[0],
        device=device,
        progress=progress,
    )
    after = 1.0 - fit["match_after"]
    info.update(
        residual_space_variant=after,
        knot_spacing_positions=fit["knot_spacing_positions"],
        iterations=fit["iterations"],
        refine_iterations=fit["refine_iterations"],
        smoothness_per_mm2=fit["smoothness_per_mm2"],
        time_s=fit["time_s"],
        drift_rms_mm=[float(v) for v in np.sqrt((drift[:, :2] ** 2).mean(axis=0)) * 1e3],
        tilt_fitted=bool(fit["tilt_fitted"]),
        tilt_rms_rad=float(np.sqrt((tilt**2).mean())),
    )
    gain = 1.0 - after / residual if residual > 0 else 0.0
    if mode == "auto" and gain < SPACE_VARIANT_MIN_GAIN:
        return {
            "info": {
                **info,
                "reason": f"fitted but not kept: it took away {gain:.0%} of the unmatched reference "
                f"(< {SPACE_VARIANT_MIN_GAIN:.0%}); the error is not a smooth drift",
            }
        }
    info.update(
        used=True,
        reason=(
            "on request"
            if mode == "on"
            else f"the scalar phase left {residual:.4f} of the reference unmatched; a smooth "
            f"drift takes away {gain:.0%} of it"
        ),
    )
    return {"info": info, "phase": new_phase, "drift": drift, "tilt": tilt, "halves": halves}


def _complex_match(image: np.ndarray, template: np.ndarray) -> float:
    """Normalised complex correlation Re<image, template> / (|image| |template|): 1 when equal."""
    num = np.vdot(template.ravel(), image.ravel()).real
    return float(num / max(np.linalg.norm(image) * np.linalg.norm(template), 1e-300))


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

    m : the metrics so far (reads ``reference_ssim_vs_template_corrected``); positions : float64
    (M, K, 3) phase centres, metres."""
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
        "reference_match_ssim": m.get("reference_ssim_vs_template_corrected"),
        "warnings": [],
    }
    if bound.max() > np.pi / 4:
        out["warnings"].append(
            f"reference and target are {sep:.0f} deg apart: their phase errors may differ by up to "
            f"{bound.max():.2f} rad (> pi/4) for {tracking_error_m * 1e3:.1f} mm tracking error; the transfer is not to be trusted"
        )
    match = out["reference_match_ssim"]
    least = MIN_REFERENCE_MATCH_PHYSICAL if m.get("template_registration") else MIN_REFERENCE_MATCH
    if match is not None and match < least:
        out["warnings"].append(
            f"the corrected reference matches its template poorly (SSIM {match:.2f} < {least}); "
            "check the template, the reference region and the template's placement"
        )
    est = m.get("estimator") or {}
    if "refine_check" in est:
        # what auto chose for an amplitude template, from the projections' own phases
        out["estimator_choice"] = est["refine_check"]["why"]
    coherence = est.get("phase_coherence_sqrt_m")
    ramp = m.get("phase_ramp") or {}
    ranged = ramp.get("ramp_coherence_sqrt_m")
    if ranged is not None:
        # the ramp fitted with the range errors from the band's halves taken out: how clearly it
        # stood out (below the fit's threshold nothing was taken)
        out["placement_by_band_halves"] = {
            "ramp_coherence_sqrt_m": ranged,
            "implied_shift_m": ramp.get("implied_shift_m"),
            "removed": bool(ramp.get("removed")) and ranged >= MIN_RANGED_RAMP_COHERENCE_SQRT_M,
        }
    placed = ranged is not None and ranged >= MIN_RANGED_RAMP_COHERENCE_SQRT_M and bool(ramp.get("removed"))
    if coherence is not None and coherence < AUTO_REFINE_BELOW_COHERENCE and not placed:
        tried = (
            f"; the band's halves did not place it either (ramp coherence x sqrt(M) {ranged:.2f}, at least "
            f"{MIN_RANGED_RAMP_COHERENCE_SQRT_M} needed, and a shift of at most "
            f"{MAX_TEMPLATE_OFFSET_RANGED_M * 1e3:.0f} mm)"
            if ranged is not None
            else ""
        )
        out["warnings"].append(
            f"the estimate's phases have wrapped (coherence x sqrt(M) {coherence:.1f} < {AUTO_REFINE_BELOW_COHERENCE}), "
            "so the scan cannot check where the outline put the reference: across the axis one radar position "
            f"does not resolve it sits where the cloud puts it, and the target can be a few mm off there{tried} "
            '(docs/digital_twin.md, "Placing the reference by the band\'s halves")'
        )
    if "outline" in est:
        # how sure the outline estimator is: the energy it put inside the outline, and how many of
        # its starts ended within 0.01 of the chosen one (several far-apart maxima: less sure)
        inside = est["outline"]["energy_inside"]
        best = max(inside)
        out["outline_energy_inside"] = best
        out["outline_starts_agreeing"] = f"{sum(v >= best - 0.01 for v in inside)}/{len(inside)}"
        if "outline_ensemble" in est:
            out["outline_agreement"] = est["outline_ensemble"]["agreement"]
        twin = m.get("digital_twin") or {}
        if twin.get("curved"):
            # measured, not modelled: the outline is drawn on the region's plane, which a curved
            # reference leaves, and no draw of a bent plate came near its ceiling
            out["warnings"].append(
                f"the reference is curved (its cloud departs {1e3 * float(twin.get('curvature_m', 0.0)):.1f} mm from a "
                "plane): the outline estimator reached 0.82 +- 0.05 of target SSIM on a bent plate and 0.90 +- 0.05 "
                "on a cylinder section in held-out field scenes, against 0.93 flat and 0.99 with a physical twin; "
                'expect the target below its ceiling (docs/digital_twin.md, "Curved references")'
            )
    residual = m.get("reference_residual")
    out["reference_residual"] = residual
    if residual is not None and residual > MAX_REFERENCE_RESIDUAL:
        out["warnings"].append(
            f"the corrected reference leaves {residual:.3f} of its template unmatched (> {MAX_REFERENCE_RESIDUAL}): "
            "the error is not all one phase per position (a hand's drift, rotation); expect the target below its ceiling"
        )
    reg = m.get("template_registration")
    if reg and reg.get("at_limit"):
        out["warnings"].append(
            f"the template registration stopped at its search limit (shift {reg['shift_px'][0]:+.1f}, "
            f"{reg['shift_px'][1]:+.1f} px): the template is placed farther off than that; check its placement"
        )
    out["trusted"] = not out["warnings"]
    return out


def write_outputs(out_dir: str | os.PathLike, outputs: FocusOutputs, pictures: str | bool = "summary") -> Path:
    """Write the output files of docs/architecture.md section 4 into ``out_dir``.

    pictures : "summary" (summary.png, the default), "all" (every picture), "none"; True/False
        mean "summary"/"none". Pictures of an earlier run that this one does not write are removed,
        so the folder never shows images of another result.

    Everything is first written to a temporary folder beside ``out_dir`` and moved in at the end,
    so a failure never leaves a mix of old and new results.
    """
    which = ("summary" if pictures else "none") if isinstance(pictures, bool) else pictures
    if which not in ("summary", "all", "none"):
        raise TwinFocusError(f"pictures must be 'summary', 'all' or 'none', got {pictures!r}")
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        np.save(tmp / "target.npy", outputs.target.astype(np.complex64))
        np.save(tmp / "target_uncorrected.npy", outputs.target_uncorrected.astype(np.complex64))
        np.save(tmp / "reference.npy", outputs.reference.astype(np.complex64))
        np.save(tmp / "reference_uncorrected.npy", outputs.reference_uncorrected.astype(np.complex64))
        np.save(tmp / "phase.npy", outputs.phase_rad.astype(np.float64))
        if outputs.drift_m is not None:
            np.save(tmp / "drift.npy", outputs.drift_m.astype(np.float64))
        if outputs.loss_history.size:
            np.save(tmp / "loss.npy", outputs.loss_history)
        doc = {
            **outputs.metrics,
            "reference_roi": list(outputs.reference_grid.roi),
            "target_roi": list(outputs.target_grid.roi),
            "size": list(outputs.reference_grid.shape),
            "config": outputs.config,
        }
        (tmp / "metrics.json").write_text(json.dumps(doc, indent=2, default=float))
        if which != "none":
            from twinfocus.plotting import write_focus_pictures

            write_focus_pictures(tmp, outputs, which)
        out_dir.mkdir(parents=True, exist_ok=True)
        written = {f.name for f in tmp.iterdir()}
        for f in tmp.iterdir():
            os.replace(f, out_dir / f.name)
        for old in out_dir.glob("*.png"):
            if old.name not in written:
                old.unlink()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out_dir
