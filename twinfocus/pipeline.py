"""Offline focusing of one scan: the steps behind ``twinfocus focus``.

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
    """Run the offline focusing steps on a validated scan.

    template : float (H, W) amplitude on ``reference_grid`` (required for ``method="twin"``).
    remove_phase_ramp : transfer the estimated phase without its best constant + linear-in-
        aperture ramp (:func:`twinfocus.autofocus.fit_linear_phase`). That ramp only moves the
        image; a template placed off by a millimetre pulls one in, and transferring it would shift
        the target. False transfers the optimiser's phase as is (the source paper).
    tracking_error_m : the tracker's position error magnitude assumed by the confidence report.
    progress_factory : ``label -> progress callable`` (see :class:`twinfocus.progress.Progress`).
    """
    if method not in METHODS:
        raise TwinFocusError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if method == "twin" and template is None:
        raise TwinFocusError("the twin method needs a template (--template, --template-scan or --digital-twin)")
    cfg = config or AutofocusConfig()
    cfg.validate()
    bp = dict(bp_options or {})
    prog = progress_factory or (lambda label: None)
    timings: dict[str, float] = {}

    t = time.perf_counter()
    ref_basis = subimage_basis(scan.data, scan.positions, scan.chirp, reference_grid, progress=prog("reference basis"), **bp)
    timings["reference_basis"] = time.perf_counter() - t
    ref_unc = ref_basis.sum(axis=0)
    check_has_signal(ref_unc, "the reference region")
    if template is not None:
        check_has_signal(template, "the template")

    t = time.perf_counter()
    tgt_basis = subimage_basis(scan.data, scan.positions, scan.chirp, target_grid, progress=prog("target basis"), **bp)
    timings["target_basis"] = time.perf_counter() - t
    tgt_unc = tgt_basis.sum(axis=0)

    t = time.perf_counter()
    if method == "twin":
        result: AutofocusResult = twin_autofocus(ref_basis, template, cfg, progress=prog("autofocus"))
    elif method == "sharpness":
        result = sharpness_autofocus(tgt_basis, cfg, progress=prog("sharpness autofocus"))
    else:
        result = no_correction(ref_basis)
    timings["autofocus"] = time.perf_counter() - t

    phase = result.phase_rad
    m: dict = {"method": method, "n_positions": scan.n_positions, "n_channels": scan.n_channels,
               "phase_ramp_removed": bool(remove_phase_ramp and method != "none")}
    if remove_phase_ramp and method != "none":
        ramp, coeffs = fit_linear_phase(phase, scan.positions.mean(axis=1)[:, :2])
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
        template=None if template is None else np.asarray(template, np.float32),
        loss_history=result.loss_history,
        metrics=m,
        timings_s=timings,
        config={**cfg.to_dict(), **{f"bp_{k}": v for k, v in bp.items()}},
    )
    m["confidence"] = confidence_report(m, scan, reference_grid, target_grid, tracking_error_m)
    if scan.positions_true is not None:
        t = time.perf_counter()
        out.target_truth = backproject(scan.data, scan.positions_true, scan.chirp, target_grid, progress=prog("target truth"), **bp)
        out.reference_truth = backproject(scan.data, scan.positions_true, scan.chirp, reference_grid, progress=prog("reference truth"), **bp)
        timings["truth_images"] = time.perf_counter() - t
        out.phase_oracle_rad = metrics.oracle_phase(scan.positions_true, scan.positions, target_grid.centre_m, scan.chirp)
        m["target_ssim_uncorrected"] = metrics.image_ssim(tgt_unc, out.target_truth, centre, steep)
        m["target_ssim_corrected"] = metrics.image_ssim(tgt_cor, out.target_truth, centre, steep)
        m["target_ssim_oracle_phase"] = metrics.image_ssim(form_image(tgt_basis, out.phase_oracle_rad), out.target_truth, centre, steep)
        m["reference_ssim_uncorrected"] = metrics.image_ssim(ref_unc, out.reference_truth, centre, steep)
        m["reference_ssim_corrected"] = metrics.image_ssim(ref_cor, out.reference_truth, centre, steep)
        m["phase_error_rms_rad_vs_oracle"] = metrics.phase_error_rms(phase, out.phase_oracle_rad)
        m["phase_error_rms_rad_uncorrected"] = metrics.phase_error_rms(np.zeros_like(phase), out.phase_oracle_rad)
    m["timings_s"] = timings
    return out


#: below this reference-vs-template SSIM the reference was not matched and the phase is suspect
MIN_REFERENCE_MATCH = 0.8


def confidence_report(m: dict, scan: Scan, reference_grid: ImageGrid, target_grid: ImageGrid, tracking_error_m: float) -> dict:
    """How far to trust the correction of this scan: the reference match, the first-order
    transfer bound for this geometry (paper eq. 7) and warnings when either is poor."""
    bound = metrics.transfer_bound_rad(scan.positions, reference_grid.centre_m, target_grid.centre_m,
                                       scan.chirp.wavelength_m, tracking_error_m)
    centre = scan.positions.reshape(-1, 3).mean(axis=0)
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
