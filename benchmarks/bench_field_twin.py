"""The digital twin on field-like scenes: a rough reference (every scatterer its own phase, spread
over +-90 degrees, and strength, +-30 %) and a camera cloud as it comes (1 mm noise, 25 % of the
surface missing in patches, 2 % outliers, 2.5 mm offset), per estimator, against the physical
twin and the oracle phase on the same draws, with each estimator's time.

    python -m benchmarks.bench_field_twin --draws 5            (docs/digital_twin.md quotes it)
    python -m benchmarks.bench_field_twin --growth-sweep       (the outline's growth rounds)
    python -m benchmarks.bench_field_twin --placement-ceiling   (what placing by the scan alone can reach)
    python -m benchmarks.bench_field_twin --range-error-floor --draws 3   (the band halves' range errors, true phase)

Scenes (the reference 'A', the target 'F' 10 degrees apart at 0.6 m):
  A: 0.5 mm z + 0.2 mm x/y tracking error, 15 dB;
  B: 1 mm z + 0.3 mm x/y, 10 dB, the target 10 cm deeper than the reference;
  C: 1.6 mm z (past lambda/4: every phase wraps) + 0.3 mm x/y, 15 dB;
and scene A with each cloud impairment alone. Writes ``field_twin.json`` (one record per
condition and draw) and prints a markdown table (mean +- sd).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

#: the scenes' tracking error and noise
SCENES = {
    "A": dict(error_sigma_m=(0.2e-3, 0.2e-3, 0.5e-3), snr_db=15),
    "B": dict(error_sigma_m=(0.3e-3, 0.3e-3, 1.0e-3), snr_db=10, target_depth_offset_m=0.1),
    "C": dict(error_sigma_m=(0.3e-3, 0.3e-3, 1.6e-3), snr_db=15),
}
#: camera-cloud impairments: (noise m, hole fraction, outlier fraction, offset m)
ALL = (1e-3, 0.25, 0.02, 2.5e-3)
CONDITIONS = {
    "A, camera cloud": ("A", ALL, True),
    "B, camera cloud": ("B", ALL, True),
    "C, camera cloud": ("C", ALL, True),
    "A, 1 mm noise only": ("A", (1e-3, 0.0, 0.0, 0.0), False),
    "A, 25 % holes only": ("A", (0.0, 0.25, 0.0, 0.0), False),
    "A, 2 % outliers only": ("A", (0.0, 0.0, 0.02, 0.0), False),
    "A, 2.5 mm offset only": ("A", (0.0, 0.0, 0.0, 2.5e-3), False),
}


def field_draw(kw: dict, seed: int, impairments: tuple = ALL) -> SimpleNamespace:
    """One draw of a field scene as every field benchmark builds it: the rough reference's scan
    (``scan``, and the physical twin's ``tpl_scan``), the grids ``rg`` / ``tg`` (100 x 100), the
    reference's exact ``surface`` points, the digital ``twin`` from its camera cloud (``impairments``:
    noise m, hole fraction, outlier fraction, offset m; the cloud drawn from ``[seed, 14]``) and the
    sub-image bases ``rb`` / ``tb``. kw: Scenario keywords (e.g. ``SCENES["B"]``)."""
    from twinfocus.imaging.backprojection.numba_backend import subimage_basis
    from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario
    from twinfocus.twins.digital_twin.camera_cloud import camera_cloud
    from twinfocus.twins.digital_twin.condition import digital_twin_reference

    sc = Scenario(**kw, reference_roughness_deg=90.0, reference_amplitude_spread=0.3, seed=seed)
    scan, tpl_scan = simulate_scenario(sc)
    rg, tg = scenario_grids(sc, 100)
    surface = sc.scene().object("reference").surface_points(1e-3)
    cloud = camera_cloud(surface, *impairments, rng=np.random.default_rng([seed, 14]))
    twin = digital_twin_reference(cloud, scan.positions, scan.chirp, rg)
    rb = subimage_basis(scan.data, scan.positions, scan.chirp, rg)
    tb = subimage_basis(scan.data, scan.positions, scan.chirp, tg)
    return SimpleNamespace(sc=sc, scan=scan, tpl_scan=tpl_scan, rg=rg, tg=tg, surface=surface, twin=twin, rb=rb, tb=tb)


def one_draw(scene: str, impairments: tuple, full: bool, seed: int) -> dict:
    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.estimators import estimator_settings
    from twinfocus.focus.phase_ramp import fit_linear_phase
    from twinfocus.focus.pipeline import Bases, Reference, Truth, upper_band_basis
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.imaging.basis import form_image
    from twinfocus.imaging.metrics import image_ssim, oracle_phase
    from twinfocus.twins.digital_twin.condition import digital_twin_reference
    from twinfocus.twins.templates import template_from_scan

    d = field_draw(SCENES[scene], seed, impairments)
    sc, scan, tpl_scan, rg, tg, twin, rb, tb = d.sc, d.scan, d.tpl_scan, d.rg, d.tg, d.twin, d.rb, d.tb
    exact = digital_twin_reference(d.surface, scan.positions, scan.chirp, rg)
    truth = Truth.of_scan(scan, rg, tg)
    wl = scan.chirp.wavelength_m
    # the earlier auto for an amplitude template: chosen from the tracking error the user states
    old_auto = estimator_settings(
        "projection" if float(np.linalg.norm(sc.error_sigma_m)) <= wl / 4 else "projection-refined", False
    )
    outline = estimator_settings("outline", False, has_support=True)
    # "default" is what `--estimator auto` takes for a point-cloud twin (the averaged outlines)
    runs = {
        "default": (twin.template, twin.support, estimator_settings("auto", False, has_support=True)),
        "outline, one": (twin.template, twin.support, {**outline, "outline_ensemble": False}),
        # the default before the outline was grown first (template_match.grown_outline)
        "default, outline not grown": (
            twin.template,
            twin.support,
            {**estimator_settings("auto", False, has_support=True), "outline_growth_rounds": 0},
        ),
        "projection": (twin.template, None, estimator_settings("projection", False)),
        "old auto": (twin.template, None, old_auto),
        "exact points (outline)": (
            exact.template,
            exact.support,
            estimator_settings("outline", False, has_support=True),
        ),
        "physical twin": (
            template_from_scan(tpl_scan, rg, keep_phase=True),
            None,
            estimator_settings("correlation", True),
        ),
    }
    if full:
        runs["paper"] = (twin.template, None, estimator_settings("paper", False))
    rec: dict = {"seed": seed, "surface": twin.info.get("surface")}
    # what `twinfocus focus` hands focus_bases: the upper half-band basis, built when a run needs it
    upper = upper_band_basis(scan.data, scan.positions, scan.chirp, rg)
    for name, (template, support, settings) in runs.items():
        # what `twinfocus focus --digital-twin` hands on of the cloud's conditioning (the confidence report reads it)
        info = twin.info if support is twin.support else None
        out = FocusPlan.make(config=AutofocusConfig(**settings)).focus_bases(
            Bases(rb, tb, scan.positions, scan.chirp, rg, tg, upper_band=upper),
            Reference(template=template, support=support, info=info),
            truth,
        )
        rec[name] = out.metrics["target_ssim_corrected"]
        rec[f"{name} time_s"] = out.timings_s["autofocus"]
        if name == "default":
            rec["default trusted"] = out.metrics["confidence"]["trusted"]
            rec["default phase coherence"] = out.metrics["estimator"].get("phase_coherence_sqrt_m")
            rec["default ramp coherence, band halves"] = out.metrics["phase_ramp"].get("ramp_coherence_sqrt_m")
            rec["default range errors time_s"] = out.timings_s.get("range_errors")
            default_phase = out.phase_rad
    rec["uncorrected"] = out.metrics["target_ssim_uncorrected"]
    rec["oracle phase"] = out.metrics["target_ssim_oracle_phase"]
    reference_true = oracle_phase(scan.positions_true, scan.positions, rg.centre_m, scan.chirp)
    rec["reference true phase"] = image_ssim(form_image(tb, reference_true), truth.target)
    # Diagnostic, from the truth: the default with its image moved to where the reference really
    # is (the constant + linear-in-aperture part of its difference from the reference's true phase
    # taken out). What is left between this and the default is the reference's position alone.
    aperture = scan.positions.mean(axis=1)[:, :2]
    ramp, coeffs = fit_linear_phase(np.angle(np.exp(1j * (default_phase - reference_true))), aperture)
    rec["default, position from the truth"] = image_ssim(form_image(tb, default_phase - ramp), truth.target)
    rec["default position error_mm"] = (
        coeffs[1:] * float(rg.z - scan.positions[..., 2].mean()) * wl / (4 * np.pi) * 1e3
    ).tolist()
    return rec


COLUMNS = [
    "uncorrected",
    "paper",
    "old auto",
    "projection",
    "outline, one",
    "default, outline not grown",
    "default",
    "default, position from the truth",
    "exact points (outline)",
    "physical twin",
    "reference true phase",
    "oracle phase",
]
#: whose estimate times the table gives (mean over the draws)
TIMED = ["outline, one", "default, outline not grown", "default"]


def main(out_dir: str | os.PathLike = "benchmarks/results", draws: int = 5, only: str | None = None) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "field_twin.json"
    # --only adds to (or replaces) its conditions in an earlier file, keeping the others
    results: dict = json.loads(path.read_text()) if only and path.is_file() else {}
    ran = set()
    for cond, (scene, imp, full) in CONDITIONS.items():
        if only and only not in cond:
            continue
        results[cond] = []
        ran.add(cond)
        for seed in range(1, draws + 1):
            print(f"[field twin] {cond}, draw {seed}/{draws}", file=sys.stderr, flush=True)
            results[cond].append(one_draw(scene, imp, full, seed))
            path.write_text(json.dumps(results, indent=2))
    print(
        "| condition | "
        + " | ".join(COLUMNS + [f"{n} time (s)" for n in TIMED])
        + " |\n|---|"
        + "---|" * (len(COLUMNS) + len(TIMED))
    )
    for cond, recs in results.items():
        cells = []
        for c in COLUMNS:
            vals = [r[c] for r in recs if c in r]
            cells.append(f"{np.mean(vals):.3f} ± {np.std(vals):.3f}" if vals else "")
        for n in TIMED:
            t = [r[f"{n} time_s"] for r in recs if f"{n} time_s" in r]
            cells.append(f"{np.mean(t):.2f}" if t else "")
        print(f"| {cond} | " + " | ".join(cells) + " |")
    return results


#: the outline's growth rounds the sweep measures (template_match.grown_outline; the default is 2)
GROWTH_ROUNDS = (0, 1, 2, 3, 4)


def keep_draw(path: Path, results: dict, key: str, record: dict) -> None:
    """Add a draw's ``record`` to ``results[key]`` and write all of ``results`` to ``path``
    (indented JSON) at once: a sweep stopped part way keeps the draws it finished."""
    results[key].append(record)
    path.write_text(json.dumps(results, indent=1))


def bench_draws(label: str, draws: int, results: dict):
    """(scene, seed, :func:`field_draw`) for the camera-cloud scenes A, B, C, draws 1..``draws``,
    each announced on stderr; ``results`` gets an empty list per scene for its records."""
    for scene in SCENES:
        results[scene] = []
        for seed in range(1, draws + 1):
            print(f"[field twin, {label}] {scene}, draw {seed}/{draws}", file=sys.stderr, flush=True)
            yield scene, seed, field_draw(SCENES[scene], seed)


def growth_sweep(out_dir: str | os.PathLike = "benchmarks/results", draws: int = 5) -> dict:
    """The knob ``AutofocusConfig.outline_growth_rounds`` against what it costs: on the camera-cloud
    scenes A, B, C (draws 1..``draws``), the averaged outline estimate after each number of growth
    rounds, timed, its target SSIM with the image placed by the truth (the estimate alone, as the
    diagnostic column of the main table) and the outline's size. Writes ``field_twin_growth.json``."""
    import time

    from twinfocus.focus.phase_ramp import fit_linear_phase
    from twinfocus.focus.template_match import averaged_outline_phase
    from twinfocus.imaging.backprojection.numba_backend import backproject
    from twinfocus.imaging.basis import form_image
    from twinfocus.imaging.metrics import image_ssim, oracle_phase

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    for scene, seed, d in bench_draws("growth rounds", draws, results):
        scan, rg, tg, twin, rb, tb = d.scan, d.rg, d.tg, d.twin, d.rb, d.tb
        truth = backproject(scan.data, scan.positions_true, scan.chirp, tg)
        reference_true = oracle_phase(scan.positions_true, scan.positions, rg.centre_m, scan.chirp)
        aperture = scan.positions.mean(axis=1)[:, :2]
        rec: dict = {"seed": seed}
        for rounds in GROWTH_ROUNDS:
            t0 = time.perf_counter()
            phase, info = averaged_outline_phase(rb, twin.support, aperture, growth_rounds=rounds)
            took = time.perf_counter() - t0
            ramp, _ = fit_linear_phase(np.angle(np.exp(1j * (phase - reference_true))), aperture)
            rec[str(rounds)] = {
                "placed by the truth": image_ssim(form_image(tb, phase - ramp), truth),
                "time_s": took,
                "outline_px": info["growth_px"][-1],
            }
        keep_draw(out_dir / "field_twin_growth.json", results, scene, rec)
    print(
        "| growth rounds | "
        + " | ".join(results)
        + " | estimate's time (s, mean) |\n|---|"
        + "---|" * (len(results) + 1)
    )
    for rounds in GROWTH_ROUNDS:
        k = str(rounds)
        cells = [f"{np.mean([r[k]['placed by the truth'] for r in recs]):.3f}" for recs in results.values()]
        t = np.mean([r[k]["time_s"] for recs in results.values() for r in recs])
        print(f"| {rounds} | " + " | ".join(cells) + f" | {t:.2f} |")
    return results


#: range_error_floor's cases: the reference's texture (Scenario keywords) ...
FLOOR_TEXTURES = {
    "rough (the field's)": dict(reference_roughness_deg=90.0, reference_amplitude_spread=0.3),
    "smooth plate": dict(reference_roughness_deg=None, reference_amplitude_spread=0.0, speckle=False),
}
#: ... and the tracking error (x, y, z sigma, m) and noise
FLOOR_ERRORS = {
    "none": ((0.0, 0.0, 0.0), 15),
    "0.5 mm z": ((0.3e-3, 0.3e-3, 0.5e-3), 15),
    "1.6 mm z": ((0.3e-3, 0.3e-3, 1.6e-3), 15),
    "1.6 mm z, no noise": ((0.3e-3, 0.3e-3, 1.6e-3), None),
}


def range_error_floor(out_dir: str | os.PathLike = "benchmarks/results", draws: int = 3) -> dict:
    """How well the band's halves read each position's range error when the estimate is exact.

    On scene C's geometry, for a rough and a smooth reference and tracking errors from none to
    1.6 mm: the range errors :func:`~twinfocus.focus.band_delay.position_range_errors_m` reads with the
    true phase as the estimate, on the bright pixels of the focused reference, against the true
    ones (each position's mean over its channels of the range change to the reference's centre).
    Reports the error's sd (mm), the slope of measured on true, and the image shift (mm) that the
    ramp fit with them taken out asks for, which with the true phase should be none: the floor of
    the placement by the band's halves (docs/digital_twin.md). Writes ``field_twin_range_floor.json``."""
    from twinfocus.focus.band_delay import bright_pixels, half_band_chirps, half_band_data, position_range_errors_m
    from twinfocus.focus.phase_ramp import fit_linear_phase
    from twinfocus.imaging.backprojection.numba_backend import backproject, subimage_basis_points
    from twinfocus.imaging.metrics import oracle_phase, true_range_errors_m
    from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    for texture, tkw in FLOOR_TEXTURES.items():
        for error, (sigma, snr) in FLOOR_ERRORS.items():
            if texture != "rough (the field's)" and snr is None:
                continue
            key = f"{texture}, {error}"
            results.setdefault(key, [])
            for seed in range(1, draws + 1):
                print(f"[range-error floor] {texture}, {error}, draw {seed}/{draws}", file=sys.stderr, flush=True)
                sc = Scenario(**{**SCENES["C"], "error_sigma_m": sigma, "snr_db": snr}, **tkw, seed=seed)
                scan, _ = simulate_scenario(sc)
                rg, _ = scenario_grids(sc, 100)
                centre = rg.centre_m
                true_phase = oracle_phase(scan.positions_true, scan.positions, centre, scan.chirp)
                true_m = true_range_errors_m(scan.positions_true, scan.positions, centre)
                pixels = bright_pixels(backproject(scan.data, scan.positions_true, scan.chirp, rg)).ravel()
                points = rg.points()[pixels]
                halves = [
                    subimage_basis_points(d, scan.positions, c, points)
                    for d, c in zip(half_band_data(scan.data, scan.chirp), half_band_chirps(scan.chirp))
                ]
                measured = position_range_errors_m(*halves, true_phase, scan.chirp)
                err = (measured - measured.mean()) - (true_m - true_m.mean())
                aperture = scan.positions.mean(axis=1)[:, :2]
                ranged = true_phase + 4.0 * np.pi / scan.chirp.wavelength_m * measured
                ramp, coeffs = fit_linear_phase(ranged, aperture, min_coherence_sqrt_m=0.0)
                range_m = float(np.linalg.norm(centre - scan.positions.mean(axis=(0, 1))))
                shift = coeffs[1:] * range_m * scan.chirp.wavelength_m / (4.0 * np.pi)
                keep_draw(
                    out_dir / "field_twin_range_floor.json",
                    results,
                    key,
                    {
                        "seed": seed,
                        "error_sd_mm": 1e3 * float(err.std()),
                        "slope": float(np.polyfit(true_m, measured, 1)[0]) if true_m.std() > 0 else None,
                        "asked_shift_mm": (1e3 * shift).tolist(),
                        "ramp_coherence_sqrt_m": float(
                            np.abs(np.exp(1j * (ranged - ramp)).mean()) * np.sqrt(ranged.size)
                        ),
                        "bright_px": int(pixels.sum()),
                    },
                )
    print(
        "| reference, tracking error | range-error error, sd (mm) | slope "
        "| shift asked with the true phase (mm, mean abs x, y) | coherence x sqrt(M) |"
    )
    print("|---|---|---|---|---|")
    for name, recs in results.items():
        slopes = [r["slope"] for r in recs if r["slope"] is not None]
        shifts = np.abs([r["asked_shift_mm"] for r in recs]).mean(axis=0)
        print(
            f"| {name} | {np.mean([r['error_sd_mm'] for r in recs]):.2f} | "
            + (f"{np.mean(slopes):.2f}" if slopes else "-")
            + f" | {shifts[0]:.1f}, {shifts[1]:.1f} | {np.mean([r['ramp_coherence_sqrt_m'] for r in recs]):.1f} |"
        )
    return results


def placement_ceiling(out_dir: str | os.PathLike = "benchmarks/results", draws: int = 5, heldout: int = 10) -> dict:
    """The most a digital twin placed by the scan alone can reach on scenes A, B and C.

    A constant + linear trend of the positions' range errors across the aperture moves the image
    as a misplaced reference does, so nothing measured on the reference (its estimate, the band's
    halves) can tell the two apart: a twin that knows where the reference is only to the camera's
    2.5 mm takes that part of the errors for its misplacement and removes it with it. Per draw:
    the target's SSIM formed with the reference's true phase (the physical twin's ceiling) and
    with the same phase less the phase of the range errors' least-squares constant + linear part
    (each position's mean over its channels of the range change to the reference's centre), and
    the image shift (mm) that part stands for. The bench's draws (seeds 1 to ``draws``) and the
    held-out ones (``benchmarks.heldout_field_twin``'s seeds, 6 on, ``heldout`` of them).

    And what the product's own placement (:func:`twinfocus.focus.plan.place_estimate`: the plain
    ramp fit, then the band's halves) makes of an exact estimate: the true phase as it stands, and
    moved by the ramp of that draw's camera offset (the x, y part of ``ALL``'s 2.5 mm in the
    direction the camera cloud draws), as an outline the camera put there would move it; and that
    moved phase kept as it is. Writes ``field_twin_placement_ceiling.json``."""
    from twinfocus.focus.pipeline import upper_band_basis
    from twinfocus.focus.plan import place_estimate
    from twinfocus.imaging.backprojection.numba_backend import backproject, subimage_basis
    from twinfocus.imaging.basis import form_image
    from twinfocus.imaging.metrics import image_ssim, oracle_phase, true_range_errors_m
    from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario
    from twinfocus.twins.digital_twin.camera_cloud import camera_cloud

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    seeds = {"bench": list(range(1, draws + 1)), "held-out": list(range(6, 6 + heldout))}
    placed = (
        "exact, placed by the product",
        "exact moved by the camera's offset, placed by the product",
        "exact moved by the camera's offset, kept",
    )
    results: dict = {}
    for scene in SCENES:
        results[scene] = []
        for which, chosen in seeds.items():
            for seed in chosen:
                print(f"[field twin, placement ceiling] {scene}, {which} seed {seed}", file=sys.stderr, flush=True)
                sc = Scenario(**SCENES[scene], reference_roughness_deg=90.0, reference_amplitude_spread=0.3, seed=seed)
                scan, _ = simulate_scenario(sc)
                rg, tg = scenario_grids(sc, 100)
                tb = subimage_basis(scan.data, scan.positions, scan.chirp, tg)
                truth = backproject(scan.data, scan.positions_true, scan.chirp, tg)
                centre = rg.centre_m
                true_phase = oracle_phase(scan.positions_true, scan.positions, centre, scan.chirp)
                range_errors = true_range_errors_m(scan.positions_true, scan.positions, centre)
                aperture = scan.positions.mean(axis=1)[:, :2]
                design = np.c_[np.ones(len(aperture)), aperture - aperture.mean(axis=0)]
                coeffs, *_ = np.linalg.lstsq(design, range_errors, rcond=None)
                trend_phase = -4.0 * np.pi / scan.chirp.wavelength_m * (design @ coeffs)
                range_m = float(np.linalg.norm(centre - scan.positions.mean(axis=(0, 1))))
                rec = {
                    "draws": which,
                    "seed": seed,
                    "true phase": image_ssim(form_image(tb, true_phase), truth),
                    "true phase less the errors' linear part": image_ssim(
                        form_image(tb, true_phase - trend_phase), truth
                    ),
                    "linear part's shift_mm": (1e3 * coeffs[1:] * range_m).tolist(),
                }
                # the camera's offset as field_draw's cloud draws it (the same generator, the same order)
                surface = sc.scene().object("reference").surface_points(1e-3)
                _, cam = camera_cloud(surface, *ALL, rng=np.random.default_rng([seed, 14]), return_truth=True)
                offset = np.asarray(cam["offset_m"])[:2]
                moved = true_phase + 4.0 * np.pi / (scan.chirp.wavelength_m * range_m) * (design[:, 1:] @ offset)
                rb = subimage_basis(scan.data, scan.positions, scan.chirp, rg)
                upper = upper_band_basis(scan.data, scan.positions, scan.chirp, rg)
                for name, phase in zip(placed[:2], (true_phase, moved)):
                    out, info, _ = place_estimate(phase, rb, scan.positions, scan.chirp, rg, upper_band=upper)
                    rec[name] = image_ssim(form_image(tb, out), truth)
                    rec[name + ", removed"] = bool(info["removed"])
                rec[placed[2]] = image_ssim(form_image(tb, moved), truth)
                rec["camera offset_mm"] = (1e3 * offset).tolist()
                keep_draw(out_dir / "field_twin_placement_ceiling.json", results, scene, rec)
    print(
        "| scene, draws | true phase | less the range errors' linear part (mean +- sd, lowest) | its shift (mm, mean \\|x\\|, \\|y\\|) | "
        + " | ".join(placed)
        + " (mean +- sd, lowest) |"
    )
    print("|---|---|---|---|" + "---|" * len(placed))
    for scene, recs in results.items():
        for which in seeds:
            mine = [r for r in recs if r["draws"] == which]
            if not mine:
                continue
            less = [r["true phase less the errors' linear part"] for r in mine]
            shift = np.abs([r["linear part's shift_mm"] for r in mine]).mean(axis=0)
            cells = [[r[name] for r in mine] for name in placed]
            print(
                f"| {scene}, {which} ({len(mine)}) | {np.mean([r['true phase'] for r in mine]):.3f} | "
                f"{np.mean(less):.3f} +- {np.std(less):.3f}, {np.min(less):.3f} | {shift[0]:.2f}, {shift[1]:.2f} | "
                + " | ".join(f"{np.mean(v):.3f} +- {np.std(v):.3f}, {np.min(v):.3f}" for v in cells)
                + " |"
            )
    return results


def template_file(out_dir: str | os.PathLike = "benchmarks/results", draws: int = 5) -> dict:
    """The two-step way (``twinfocus twin --out FILE`` then ``focus --template FILE``) on the
    bench's camera-cloud draws: the digital twin's template written to a template file and read
    back as focus reads it, once as the image alone (what a file held before it carried the
    outline: ``--estimator auto`` then takes the projections of an amplitude template) and once
    with its outline and conditioning (the outline estimator, as ``--digital-twin``). Target SSIM
    and the autofocus stage's time per draw; writes ``field_twin_template_file.json``."""
    import tempfile

    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.estimators import estimator_settings
    from twinfocus.focus.pipeline import Bases, Reference, upper_band_basis
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.imaging.backprojection.numba_backend import backproject
    from twinfocus.imaging.metrics import image_ssim
    from twinfocus.twins.templates import load_template, save_template

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    for scene, seed, d in bench_draws("template file", draws, results):
        scan, rg, tg, twin = d.scan, d.rg, d.tg, d.twin
        truth = backproject(scan.data, scan.positions_true, scan.chirp, tg)
        upper = upper_band_basis(scan.data, scan.positions, scan.chirp, rg)
        rec: dict = {"seed": seed}
        with tempfile.TemporaryDirectory() as tmp:
            for name, extra in (
                ("image alone", {}),
                ("with its outline", {"support": twin.support, "info": twin.info}),
            ):
                path = Path(tmp) / "template.npz"
                save_template(path, twin.template, rg, **extra)
                template, support, info = load_template(path, rg, with_outline=True)
                settings = estimator_settings("auto", False, has_support=support is not None)
                out = FocusPlan.make(config=AutofocusConfig(**settings)).focus_bases(
                    Bases(d.rb, d.tb, scan.positions, scan.chirp, rg, tg, upper_band=upper),
                    Reference(template=template, support=support, info=info),
                )
                rec[name] = image_ssim(out.target, truth)
                rec[f"{name} trusted"] = out.metrics["confidence"]["trusted"]
                rec[f"{name} time_s"] = out.timings_s["autofocus"]
        keep_draw(out_dir / "field_twin_template_file.json", results, scene, rec)
    print(
        "| scene | template file, image alone (before) | **with its outline and conditioning** | time (s) before / now |"
    )
    print("|---|---|---|---|")
    for scene, recs in results.items():
        cells = [[r[name] for r in recs] for name in ("image alone", "with its outline")]
        times = [np.mean([r[f"{name} time_s"] for r in recs]) for name in ("image alone", "with its outline")]
        print(
            f"| {scene} ({len(recs)}) | "
            + " | ".join(f"{np.mean(v):.3f} +- {np.std(v):.3f}" for v in cells)
            + f" | {times[0]:.2f} / {times[1]:.2f} |"
        )
    return results


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument(
        "--growth-sweep",
        action="store_true",
        help="measure the outline's growth rounds instead (field_twin_growth.json, ~6 min)",
    )
    ap.add_argument(
        "--range-error-floor",
        action="store_true",
        help="how well the band's halves read the range errors with the true phase (field_twin_range_floor.json, ~8 min)",
    )
    ap.add_argument(
        "--placement-ceiling",
        action="store_true",
        help="what a twin placed by the scan alone can reach on A, B and C, and what the product's "
        "placement makes of an exact estimate (field_twin_placement_ceiling.json, ~25 min)",
    )
    ap.add_argument(
        "--template-file",
        action="store_true",
        help="the two-step way through a template file, before and with its outline (field_twin_template_file.json, ~3 min)",
    )
    ap.add_argument("--draws", type=int, default=5)
    ap.add_argument("--only", default=None, help="run only the conditions whose name contains this")
    a = ap.parse_args()
    if a.growth_sweep:
        growth_sweep(a.out, a.draws)
    elif a.placement_ceiling:
        placement_ceiling(a.out, a.draws)
    elif a.template_file:
        template_file(a.out, a.draws)
    elif a.range_error_floor:
        range_error_floor(a.out, a.draws)
    else:
        main(a.out, a.draws, a.only)
