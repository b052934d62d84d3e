"""One simulated case of channel calibration: the same scene and tracking errors focused through a
perfect array, an imperfect one, and the imperfect one after a corner calibration.

The scene scan and the physical twin's motion-stage scan are simulated through the perfect array
and through an imperfect one (:func:`twinfocus.simulation.scenario.simulate_scenario`, the same scene,
tracking errors and noise; :mod:`twinfocus.radar.array_errors`, ``twinfocus simulate --array-errors``);
a still capture of a
corner reflector on the array's axis through the same array gives the calibration
(:func:`twinfocus.radar.calibration.make_calibration`, the path of ``twinfocus calibrate SCAN.npz``).
Every target image is scored against the perfect array's image on the true positions.
"""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.focus.pipeline import Reference
from twinfocus.focus.plan import FocusPlan
from twinfocus.imaging.backprojection.numba_backend import backproject
from twinfocus.imaging.metrics import image_ssim
from twinfocus.radar.array_errors import (
    TYPICAL,
    ArrayErrorLevels,
    apply_array_errors_to_channels,
    array_errors_stream,
    draw_array_errors,
)
from twinfocus.radar.calibration import apply_calibration, find_corner, make_calibration
from twinfocus.radar.fmcw import mmwcas_virtual_array
from twinfocus.radar.scan import Scan
from twinfocus.simulation.if_simulator import add_thermal_noise, simulate_if_exact
from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario
from twinfocus.twins.templates import template_from_scan

#: Frames of the corner capture and their per-sample SNR, dB.
CORNER_FRAMES = 4
CORNER_SNR_DB = 20.0


def calibration_case(
    seed: int,
    levels: ArrayErrorLevels = TYPICAL,
    n_columns: int = 2,
    n_rows: int = 50,
    size: int = 64,
    corner_range_m: float = 0.6,
) -> dict:
    """Target SSIMs (against the perfect array's truth image) of one draw, autofocus on.

    seed : the scenario's seed (scene, tracking errors, noise) and the array's draw; n_columns,
    n_rows : the raster (positions = n_columns x n_rows); size : image side, pixels.
    Returns {"perfect", "uncalibrated", "calibrated": target SSIM after autofocus,
    "*_no_autofocus": before it, "*_autofocus_refused": why focus refused a variant (its score is
    then the image without autofocus), "residual_phase_deg_rms", "phase_spread_before_deg"}.
    """
    sc = Scenario(n_columns=n_columns, n_rows=n_rows, seed=seed)
    errors = draw_array_errors(levels, array_errors_stream(seed))
    scan, template_scan = simulate_scenario(sc)
    bad_scan, bad_template = simulate_scenario(sc, array_errors=errors)
    chirp = scan.chirp
    array = mmwcas_virtual_array()
    still = np.broadcast_to(array.offsets_m, (CORNER_FRAMES, *array.offsets_m.shape)).copy()
    corner = simulate_if_exact(
        np.array([[0.0, 0.0, corner_range_m]]), None, still, chirp, pattern_exponent=errors.pattern_exponent
    )
    corner = add_thermal_noise(corner, CORNER_SNR_DB, np.random.default_rng([seed, 39]))
    corner = apply_array_errors_to_channels(corner, chirp, errors, array, corner_range_m)
    peak = find_corner(corner, chirp, corner_range_m)
    cal, _ = make_calibration(corner, still, chirp, peak, array, array, "simulated")
    correction = cal.correction()

    def calibrated(s: Scan) -> Scan:
        return s.with_data(apply_calibration(s.data, correction))

    ref_grid, tgt_grid = scenario_grids(sc, size)
    variants = {
        "perfect": (scan, template_scan),
        "uncalibrated": (bad_scan, bad_template),
        "calibrated": (calibrated(bad_scan), calibrated(bad_template)),
    }
    out: dict = {}
    truth = None
    for name, (s, t) in variants.items():
        template = template_from_scan(t, ref_grid, keep_phase=True)
        try:
            focused = FocusPlan.make().focus_scan(s, ref_grid, tgt_grid, Reference(template=template))
        except TwinFocusError as exc:
            # An uncalibrated array can smear the reference past recognition: focus refuses, and
            # what the user has is the image without autofocus.
            image = backproject(s.data, s.positions, s.chirp, tgt_grid)
            assert truth is not None
            out[name] = out[f"{name}_no_autofocus"] = image_ssim(image, truth)
            out[f"{name}_autofocus_refused"] = str(exc)
            continue
        if truth is None:
            truth = focused.target_truth
        assert truth is not None  # the simulated scan carries its true positions
        out[name] = image_ssim(focused.target, truth)
        out[f"{name}_no_autofocus"] = image_ssim(focused.target_uncorrected, truth)
    out["residual_phase_deg_rms"] = cal.quality["residual_phase_deg_rms"]
    out["phase_spread_before_deg"] = cal.quality["phase_spread_before_deg"]
    return out
