"""Offline focusing of one scan: the steps behind ``twinfocus focus`` and the solver node.

:func:`focus_scan` does steps 1-4 on a scan; :func:`focus_bases` does steps 3-4 on bases built
elsewhere (the solver node builds them batch by batch as measurements arrive).

1. sub-image bases of the reference and target regions (one back-projection each);
2. the reference template (file, motion-stage scan, digital twin) — or none for the baselines;
3. autofocus: phase per radar position from the reference (or sharpness of the target);
4. phase transfer to the target, metrics against the truth when the scan carries it.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinfocus import metrics
from twinfocus.autofocus import (
    AutofocusConfig,
    AutofocusResult,
    fit_linear_phase,
    form_image,
    no_correction,
    sharpness_autofocus,
    twin_autofocus,
)
from twinfocus.backprojection import backproject, subimage_basis
from twinfocus.errors import TwinFocusError
from twinfocus.grid import ImageGrid
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


def _check_method(method: str, template: np.ndarray | None) -> None:
    if method not in METHODS:
        raise TwinFocusError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if method == "twin" and template is None:
        raise TwinFocusError("the twin method needs a template (--template, --template-scan or --digital-twin)")


def focus_scan(
    scan: Scan,
    reference_grid: ImageGrid,
    target_grid: ImageGrid,
    *,
    template: np.ndarray | None = None,
    method: str = "twin",
    config: AutofocusConfig | None = None,
    bp_options: dict | None = None,
    progress_factory=None,
    remove_phase_ramp: bool = True,
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
    ref_basis = subimage_basis(scan.data, scan.positions, scan.chirp, reference_grid, progress=prog("reference basis"), **bp)
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
        truth_tgt = backproject(scan.data, scan.positions_true, scan.chirp, target_grid, progress=prog("target truth"), **bp)
        truth_ref = backproject(scan.data, scan.positions_true, scan.chirp, reference_grid, progress=prog("reference truth"), **bp)
        truth_time = time.perf_counter() - t

    out = focus_bases(
        ref_basis, tgt_basis, scan.positions, scan.chirp, reference_grid, target_grid,
        template=template, method=method, config=config, bp_options=bp, progress_factory=progress_factory,
        remove_phase_ramp=remove_phase_ramp, tracking_error_m=tracking_error_m,
        truth_target=truth_tgt, truth_reference=truth_ref, positions_true=scan.positions_true,
    )
    timings.update(out.timings_s)
    if truth_tgt is not None:
        timings["truth_images"] = truth_time
    out.timings_s = timings
    out.metrics["timings_s"] = timings
    return out


def focus_bases(
    ref_basis: np.ndarray,
    tgt_basis: np.ndarray,
    positions: np.ndarray,
    chirp: Chirp,
    reference_grid: ImageGrid,
    target_grid: ImageGrid,
    *,
    template: np.ndarray | None = None,
    method: str = "twin",
    config: AutofocusConfig | None = None,
    bp_options: dict | None = None,
    progress_factory=None,
    remove_phase_ramp: bool = True,
    tracking_error_m: float = 0.5e-3,
    truth_target: np.ndarray | None = None,
    truth_reference: np.ndarray | None = None,
    positions_true: np.ndarray | None = None,
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
    method : ``"twin"`` (reference vs template), ``"sharpness"`` (of the target) or ``"none"``.
    config : :class:`~twinfocus.autofocus.AutofocusConfig`, handed to the autofocus as is.
    bp_options : the back-projection options the bases were built with (recorded in ``config``).
    remove_phase_ramp : transfer the estimated phase without its best constant + linear-in-
        aperture ramp (:func:`twinfocus.autofocus.fit_linear_phase`). That ramp only moves the
        image; a template placed off by a millimetre pulls one in, and transferring it would shift
        the target. False transfers the optimiser's phase as is (the source paper).
    tracking_error_m : the tracker's position error magnitude assumed by the confidence report.
    progress_factory : ``label -> progress callable`` (see :class:`twinfocus.progress.Progress`).
    truth_target, truth_reference : complex (H, W) images formed on the true positions, and
        positions_true : float64 (M, K, 3); with all three the metrics include the SSIMs
        against the truth and the phase error against the oracle phase.

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

    t = time.perf_counter()
    if method == "twin":
        result: AutofocusResult = twin_autofocus(ref_basis, template, cfg, progress=prog("autofocus"))
    elif method == "sharpness":
        result = sharpness_autofocus(tgt_basis, cfg, progress=prog("sharpness autofocus"))
    else:
        result = no_correction(ref_basis)
    timings = {"autofocus": time.perf_counter() - t}

    phase = result.phase_rad
    m: dict = {"method": method, "n_positions": int(positions.shape[0]), "n_channels": int(positions.shape[1]),
               "phase_ramp_removed": bool(remove_phase_ramp and method != "none")}
    if method == "twin":
        m["estimator"] = {"init": cfg.init, "template_registration": cfg.template_registration, "iterations": int(cfg.iterations)}
        if cfg.init == "projection":
            m["estimator"].update(projection_iterations=int(cfg.projection_iterations), projection_restarts=int(cfg.projection_restarts))
        for knob in ("coarse_iterations", "smoothness_weight"):
            if getattr(cfg, knob):
                m["estimator"][knob] = getattr(cfg, knob)
        if "projection_restarts" in result.extra:
            m["projection_restarts"] = result.extra["projection_restarts"]
        if "registration" in result.extra:
            m["template_registration"] = result.extra["registration"]
        # metrics and pictures against the template the phases were fitted to (moved when registered)
        template = result.extra.get("template", template)
    if remove_phase_ramp and method != "none":
        ramp, coeffs = fit_linear_phase(phase, positions.mean(axis=1)[:, :2])
        phase = np.angle(np.exp(1j * (phase - ramp)))
        m["phase_ramp_rad_per_m"] = coeffs[1:].tolist()
    ref_cor = form_image(ref_basis, phase)
    tgt_cor = form_image(tgt_basis, phase)
    centre, steep = cfg.threshold_centre, cfg.threshold_steepness

    if template is not None:
        tpl_disp = metrics.display_image(template, centre, steep)
        m["reference_ssim_vs_template_uncorrected"] = metrics.ssim(metrics.display_image(ref_unc, centre, steep), tpl_disp)
        m["reference_ssim_vs_template_corrected"] = metrics.ssim(metrics.display_image(ref_cor, centre, steep), tpl_disp)
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
    )
    m["confidence"] = confidence_report(m, positions, chirp, reference_grid, target_grid, tracking_error_m)
    if truth_target is not None and truth_reference is not None and positions_true is not None:
        out.target_truth, out.reference_truth = truth_target, truth_reference
        out.phase_oracle_rad = metrics.oracle_phase(positions_true, positions, target_grid.centre_m, chirp)
        m["target_ssim_uncorrected"] = metrics.image_ssim(tgt_unc, truth_target, centre, steep)
        m["target_ssim_corrected"] = metrics.image_ssim(tgt_cor, truth_target, centre, steep)
        m["target_ssim_oracle_phase"] = metrics.image_ssim(form_image(tgt_basis, out.phase_oracle_rad), truth_target, centre, steep)
        m["reference_ssim_uncorrected"] = metrics.image_ssim(ref_unc, truth_reference, centre, steep)
        m["reference_ssim_corrected"] = metrics.image_ssim(ref_cor, truth_reference, centre, steep)
        m["phase_error_rms_rad_vs_oracle"] = metrics.phase_error_rms(phase, out.phase_oracle_rad)
        m["phase_error_rms_rad_uncorrected"] = metrics.phase_error_rms(np.zeros_like(phase), out.phase_oracle_rad)
    return out


#: below this reference-vs-template SSIM the reference was not matched and the phase is suspect
MIN_REFERENCE_MATCH = 0.8


def confidence_report(m: dict, positions: np.ndarray, chirp: Chirp, reference_grid: ImageGrid, target_grid: ImageGrid,
                      tracking_error_m: float) -> dict:
    """How far to trust the correction of this scan: the reference match, the first-order
    transfer bound for this geometry (paper eq. 7) and warnings when either is poor.

    m : the metrics so far (reads ``reference_ssim_vs_template_corrected``); positions : float64
    (M, K, 3) phase centres, metres."""
    bound = metrics.transfer_bound_rad(positions, reference_grid.centre_m, target_grid.centre_m,
                                       chirp.wavelength_m, tracking_error_m)
    centre = positions.reshape(-1, 3).mean(axis=0)
    sep = np.degrees(np.arccos(np.clip(np.dot(
        (reference_grid.centre_m - centre) / np.linalg.norm(reference_grid.centre_m - centre),
        (target_grid.centre_m - centre) / np.linalg.norm(target_grid.centre_m - centre)), -1, 1)))
    out = {
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
    if match is not None and match < MIN_REFERENCE_MATCH:
        out["warnings"].append(
            f"the corrected reference matches its template poorly (SSIM {match:.2f} < {MIN_REFERENCE_MATCH}); "
            "check the template, the reference region and the template's placement"
        )
    reg = m.get("template_registration")
    if reg and reg.get("at_limit"):
        out["warnings"].append(
            f"the template registration stopped at its search limit (shift {reg['shift_px'][0]:+.1f}, "
            f"{reg['shift_px'][1]:+.1f} px): the template is placed farther off than that; check its placement"
        )
    out["trusted"] = not out["warnings"]
    return out


def write_outputs(out_dir: str | os.PathLike, outputs: FocusOutputs, pictures: bool = True) -> Path:
    """Write DESIGN.md's output files into ``out_dir``.

    Everything is first written to a temporary folder beside ``out_dir`` and moved in at the end,
    so a failure never leaves a mix of old and new results.
    """
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        np.save(tmp / "target.npy", outputs.target.astype(np.complex64))
        np.save(tmp / "target_uncorrected.npy", outputs.target_uncorrected.astype(np.complex64))
        np.save(tmp / "reference.npy", outputs.reference.astype(np.complex64))
        np.save(tmp / "reference_uncorrected.npy", outputs.reference_uncorrected.astype(np.complex64))
        np.save(tmp / "phase.npy", outputs.phase_rad.astype(np.float64))
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
        if pictures:
            from twinfocus.plotting import write_focus_pictures

            write_focus_pictures(tmp, outputs)
        out_dir.mkdir(parents=True, exist_ok=True)
        for f in tmp.iterdir():
            os.replace(f, out_dir / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out_dir
