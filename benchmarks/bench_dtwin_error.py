"""Where the digital twin's phase goes wrong: the structure of its error against the reference's
true phase, on the family bench's draws (``benchmarks/bench_dtwin_family.py``, bench seeds only).

Per draw, the digital twin as ``twinfocus focus --digital-twin`` runs it, and against the
reference's true phase (one phase per position, :func:`twinfocus.imaging.metrics.oracle_phase`):

- ``error_rms_rad``: its error's r.m.s. over the positions (the error's mean phase taken out);
- ``step_error_rms_rad``: the r.m.s. of its error's change from one position to the next along a
  sweep, and ``neighbour_step_error_rms_rad`` the same for the phase difference that neighbouring
  positions' sub-images give by themselves (``arg sum_p conj(B_m(p)) B_m+1(p)``, 2 mm apart along
  the sweep: nearly the same view of the reference, so its texture cancels);
- ``without_degree_N``: the target's SSIM once the error's least-squares polynomial of degree N
  (1: a ramp; 2: + the quadratic terms; 3: + the cubic ones) in the positions' aperture
  coordinates is taken out of the estimate (an oracle: it needs the truth), which says how much of
  the target's loss is smooth across the aperture;
- ``blind_degree_2``: the target's SSIM once the estimate's *own* polynomial of degree 2 (fitted to
  its wrapped phases, :func:`own_polynomial`; no truth) is taken out, with ``ramp_free_coherence``
  (:func:`twinfocus.focus.phase_ramp.ramp_free_coherence`: whether the phases hold together enough to
  fit it) and ``step_coherence`` (:func:`twinfocus.focus.drift_check.step_coherence`: jitter near 0.1,
  a hand's drift near 0.45). Under jitter the true error has no smooth part beyond what 390
  random values project onto six terms, so the estimate's smooth part is mostly its own error;
- ``self_template_drift`` (with ``--self-template``): the target's SSIM after the drift + tilt fit
  (:func:`twinfocus.focus.space_variant.fit_smooth_drift`) to the reference's own corrected image as
  the template, and ``self_template_match`` the fit's match at its end (1: it never left its
  start);
- ``subaperture_shift_px``: how far apart the images of the two halves of the aperture (along the
  sweeps, y; across them, x) sit on the reference's true phase, by their intensities' cross
  correlation, and ``shift_per_rad_px`` how far one radian of quadratic phase over the half
  aperture moves them (what a map-drift estimate of the quadratic term would read).

    python -m benchmarks.bench_dtwin_error --draws 5
    python -m benchmarks.bench_dtwin_error --draws 3 --conditions paper,hand
    python -m benchmarks.bench_dtwin_error --draws 10 --conditions paper --heldout  (a check only)

Writes ``dtwin_error_structure.json`` (``dtwin_error_structure_heldout.json``) and prints a table per condition.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_dtwin_family import (
    BENCH_SEED,
    BENCH_SHAPES,
    CONDITIONS,
    HELDOUT_SEED,
    HELDOUT_SHAPES,
    digital_twin_focus,
    draw_inputs,
    surface_of,
)
from twinfocus.focus.phase_ramp import aperture_polynomial
from twinfocus.focus.reference_free import _centred as centred
from twinfocus.imaging.subpixel import parabola_vertex

#: consecutive positions further apart than this start a new sweep, metres (the scans' steps along
#: a sweep are ~2 mm; the sweeps are one array length, 83 mm, apart)
SWEEP_GAP_M = 0.01


def sweeps(centres_m: np.ndarray) -> list[np.ndarray]:
    """The positions' indices, sweep by sweep, from (M, 3) phase centres in capture order."""
    step = np.linalg.norm(np.diff(centres_m, axis=0), axis=1)
    starts = np.r_[0, np.nonzero(step > SWEEP_GAP_M)[0] + 1, len(centres_m)]
    return [np.arange(a, b) for a, b in zip(starts[:-1], starts[1:])]


def wrapped(phase: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * phase))


def own_polynomial(phase_rad: np.ndarray, centres_m: np.ndarray, degree: int) -> np.ndarray:
    """The least-squares fit of :func:`aperture_polynomial` to wrapped phases (M,), radians: from
    the coherent ramp (:func:`twinfocus.focus.phase_ramp.fit_linear_phase`), Gauss-Newton steps on the
    wrapped residual, so wrapping does not bias it."""
    from twinfocus.focus.phase_ramp import fit_linear_phase

    columns = aperture_polynomial(centres_m, degree)
    ramp, _ = fit_linear_phase(phase_rad, centres_m[:, :2], min_coherence_sqrt_m=0.0)
    coef = np.linalg.lstsq(columns, ramp, rcond=None)[0]
    for _ in range(20):
        coef = coef + np.linalg.lstsq(columns, wrapped(phase_rad - columns @ coef), rcond=None)[0]
    return columns @ coef


def self_template_drift(d: dict, dt) -> tuple[float, float]:
    """(target SSIM, the fit's final match) of the drift + tilt fit to the reference's own image as
    the digital twin corrected it (the template a reference with no phase template could have)."""
    from twinfocus.focus.pipeline import half_array_bases
    from twinfocus.focus.space_variant import drift_image, fit_smooth_drift
    from twinfocus.imaging.metrics import image_ssim

    scan, rg, tg = d["scan"], d["rg"], d["tg"]
    c, wl = scan.positions.mean(axis=1), scan.chirp.wavelength_m
    halves = half_array_bases(scan.data, scan.positions, scan.chirp, rg, tg)()
    phase, drift, tilt, fit = fit_smooth_drift(d["rb"], dt.reference, dt.phase_rad, c, rg, wl, half_basis=halves[0])
    image = drift_image(d["tb"], phase, drift, rg.centre_m, c, tg, wl, half_basis=halves[1], tilt_rad=tilt)
    return image_ssim(image, d["truth"].target), float(fit["match_after"])


def intensity_shift(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(rows, columns) by which ``b``'s intensity sits from ``a``'s: the peak of their cross
    correlation (zero-padded), refined by a parabola through it and its neighbours."""
    fa, fb = (np.abs(v) ** 2 - (np.abs(v) ** 2).mean() for v in (a, b))
    h, w = fa.shape
    cc = np.real(np.fft.ifft2(np.conj(np.fft.fft2(fa, (2 * h, 2 * w))) * np.fft.fft2(fb, (2 * h, 2 * w))))
    i, j = np.unravel_index(int(np.argmax(cc)), cc.shape)

    def refined(line: np.ndarray, k: int) -> float:
        n = line.size
        v = k + parabola_vertex(line[(k - 1) % n], line[k], line[(k + 1) % n])
        return v - n if v > n / 2 else v

    return refined(cc[:, j], i), refined(cc[i, :], j)


def one_draw(
    condition: str, seed: int, rows: int, size: int, shapes: tuple = BENCH_SHAPES, self_template: bool = False
) -> dict:
    from twinfocus.focus.drift_check import step_coherence
    from twinfocus.focus.phase_ramp import ramp_free_coherence
    from twinfocus.imaging.basis import form_image
    from twinfocus.imaging.metrics import image_ssim, oracle_phase

    d = draw_inputs(condition, seed, shapes, rows, size)
    scan, rb, tb = d["scan"], d["rb"], d["tb"]
    truth = d["truth"].target
    centres = scan.positions.mean(axis=1)
    runs = sweeps(centres)
    true_phase = oracle_phase(scan.positions_true, scan.positions, d["rg"].centre_m, scan.chirp)
    dt = digital_twin_focus(d)
    error = wrapped(dt.phase_rad - true_phase)
    rec: dict = {
        "seed": seed,
        "reference": d["kw"]["reference"],
        "surface": surface_of(d["kw"]),
        "sweeps": len(runs),
        "digital": round(float(dt.metrics["target_ssim_corrected"]), 4),
        "reference true phase": round(image_ssim(form_image(tb, true_phase), truth), 4),
        "error_rms_rad": round(float(np.sqrt(np.mean(centred(error) ** 2))), 3),
    }
    b = rb.reshape(rb.shape[0], -1)
    own, neighbours = [], []
    for s in runs:
        own.append(wrapped(error[s[1:]] - error[s[:-1]]))
        given = -np.angle(np.sum(np.conj(b[s[:-1]]) * b[s[1:]], axis=1))
        neighbours.append(wrapped(given - (true_phase[s[1:]] - true_phase[s[:-1]])))
    rec["step_error_rms_rad"] = round(float(np.sqrt(np.mean(np.concatenate(own) ** 2))), 3)
    rec["neighbour_step_error_rms_rad"] = round(float(np.sqrt(np.mean(np.concatenate(neighbours) ** 2))), 3)
    for degree in (1, 2, 3):
        a = aperture_polynomial(centres, degree)
        smooth = a @ np.linalg.lstsq(a, centred(error), rcond=None)[0]
        rec[f"without_degree_{degree}"] = round(image_ssim(form_image(tb, dt.phase_rad - smooth), truth), 4)
    own = own_polynomial(dt.phase_rad, centres, 2)
    rec["blind_degree_2"] = round(image_ssim(form_image(tb, dt.phase_rad - own), truth), 4)
    rec["ramp_free_coherence"] = round(ramp_free_coherence(dt.phase_rad, centres[:, :2]), 2)
    rec["step_coherence"] = round(step_coherence(dt.phase_rad), 3)
    if self_template:
        ssim, match = self_template_drift(d, dt)
        rec["self_template_drift"], rec["self_template_match"] = round(ssim, 4), round(match, 5)
    ramp = aperture_polynomial(centres, 1)  # columns 1, y, x
    x, y = ramp[:, 2], ramp[:, 1]
    shifts, per_rad = {}, {}
    for axis, coord, k in (("y", y, 0), ("x", x, 1)):
        low = coord < 0

        def apart(phase: np.ndarray, low=low, k=k) -> float:
            return intensity_shift(form_image(rb[low], phase[low]), form_image(rb[~low], phase[~low]))[k]

        at_truth = apart(true_phase)
        shifts[axis] = round(at_truth, 2)
        per_rad[axis] = round(apart(true_phase + coord**2) - at_truth, 2)
    rec["subaperture_shift_px"], rec["shift_per_rad_px"] = shifts, per_rad
    return rec


def table(results: dict) -> str:
    lines = [
        "| condition | draws | digital twin | error rms rad | its step error | neighbours' step error | "
        "without ramp | without degree 2 | without degree 3 | true phase | its own degree 2 out |"
        " self-template drift |",
        "|---" * 12 + "|",
    ]
    for cond, recs in results.items():

        def mean(key: str, recs: list = recs) -> float:
            return float(np.mean([r[key] for r in recs]))

        lines.append(
            f"| {cond} | {len(recs)} | {mean('digital'):.3f} | {mean('error_rms_rad'):.2f} | "
            f"{mean('step_error_rms_rad'):.2f} | {mean('neighbour_step_error_rms_rad'):.2f} | "
            f"{mean('without_degree_1'):.3f} | {mean('without_degree_2'):.3f} | "
            f"{mean('without_degree_3'):.3f} | {mean('reference true phase'):.3f} | "
            f"{mean('blind_degree_2'):.3f} | "
            + (f"{mean('self_template_drift'):.3f} |" if all("self_template_drift" in r for r in recs) else "- |")
        )
    return "\n".join(lines)


def main(
    out_dir: str | os.PathLike = "benchmarks/results",
    draws: int = 5,
    conditions: tuple[str, ...] = tuple(CONDITIONS),
    rows: int = 65,
    size: int = 64,
    heldout: bool = False,
    self_template: bool = False,
) -> dict:
    results: dict = {}
    t0 = time.perf_counter()
    first, shapes = (HELDOUT_SEED, HELDOUT_SHAPES) if heldout else (BENCH_SEED, BENCH_SHAPES)
    for cond in conditions:
        results[cond] = []
        for seed in range(first, first + draws):
            results[cond].append(one_draw(cond, seed, rows, size, shapes, self_template))
            print(f"[dtwin_error] {cond} seed {seed}: {json.dumps(results[cond][-1])}", file=sys.stderr, flush=True)
    out = {
        "command": "python -m benchmarks.bench_dtwin_error " + " ".join(sys.argv[1:]),
        "rows": rows,
        "size": size,
        "wall_s": round(time.perf_counter() - t0, 1),
        "results": results,
    }
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    name = "dtwin_error_structure_heldout.json" if heldout else "dtwin_error_structure.json"
    (Path(out_dir) / name).write_text(json.dumps(out, indent=2))
    print(table(results))
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--draws", type=int, default=5)
    ap.add_argument("--conditions", default=",".join(CONDITIONS), help="comma-separated, of " + ", ".join(CONDITIONS))
    ap.add_argument("--rows", type=int, default=65)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--heldout", action="store_true", help="the held-out draws (a check of what the bench chose)")
    ap.add_argument(
        "--self-template", action="store_true", help="also the drift + tilt fit to the reference's own image"
    )
    a = ap.parse_args()
    main(a.out, a.draws, tuple(a.conditions.split(",")), a.rows, a.size, a.heldout, a.self_template)
