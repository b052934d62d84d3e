"""The speed/accuracy trade of the physical-twin autofocus, one knob at a time, and two presets.

Each knob changes one setting of the paper's configuration (780 positions x 86 channels, 100 x 100
reference region, Adam lr 5e-2, 300 iterations, float32) and records the time from the scan to
the phase estimate (reference sub-image basis + optimiser) and the quality of that estimate: the
target SSIM when the estimated phase focuses the *same* 100 x 100 target image (for the array-size
knob, fewer positions make a different image: there the target and its truth use the same
positions). Knobs:

- image size of the reference region (50, 75, 100, 200);
- array size: the central rows of each raster column (200, 400, 600, 780 positions);
- optimiser: iterations and Adam learning rate (cosine annealing to 1e-5 in every case);
- precision: float16 basis storage, float32, float64 (basis, optimiser and back-projection);
- digital-twin fidelity: the PSF-convolution template (coherent and speckle-averaged) against the
  exact one (every point simulated and back-projected), with the digital-twin method.

Optimiser times are the best of short timed runs scaled to the iteration count
(:func:`optimiser_seconds`): the machine is shared, so a single long run's wall time includes
other jobs' bursts.

Presets: per knob (image size, optimiser, precision) the cheapest value within ``tol`` of that
knob's best mean SSIM — ``tol`` 0.003 for "accurate", 0.02 for "fast" — combined and measured.
Table 1 of the paper gets its counterpart rows from the same measurements.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.evaluation.cases import (
    EvalScenario,
    EvalSettings,
    case_grids,
    digital_twin_points,
    draw_seed,
    tracked_positions,
    transfer_phase,
)
from twinfocus.evaluation.features import hog_similarity
from twinfocus.focus.autofocus import twin_autofocus
from twinfocus.imaging import metrics
from twinfocus.imaging.backprojection.numba_backend import backproject, subimage_basis
from twinfocus.imaging.basis import form_image
from twinfocus.imaging.grid import ImageGrid
from twinfocus.radar.scan import Scan
from twinfocus.simulation.scenario import simulate_scenario
from twinfocus.twins.digital_twin.template import digital_twin_template
from twinfocus.twins.templates import template_from_scan

TRADE_PAIRS = (("A", "F"), ("R", "X"))
PRESET_TOLERANCE = {"accurate": 0.003, "fast": 0.02}

FULL_KNOBS: dict[str, list[Any]] = {
    "image size": [50, 75, 100, 200],
    "positions": [200, 400, 600, 780],
    # (iterations, Adam lr, coarse-to-fine iterations on blurred images before them)
    "optimiser": [
        (25, 0.05, 0),
        (50, 0.05, 0),
        (100, 0.05, 0),
        (200, 0.05, 0),
        (300, 0.05, 0),
        (500, 0.05, 0),
        (50, 0.2, 0),
        (100, 0.1, 0),
        (100, 0.2, 0),
        (300, 0.1, 0),
        (200, 0.05, 100),
    ],
    "precision": ["float16", "float32", "float64"],
    "digital twin": ["psf", "psf-incoherent", "exact"],
}
QUICK_KNOBS: dict[str, list[Any]] = {
    "image size": [24, 32],
    "positions": [120, 240],
    "optimiser": [(20, 0.05, 0), (60, 0.05, 0)],
    "precision": ["float16", "float32"],
    "digital twin": ["psf"],
}


def central_rows(positions_true: np.ndarray, n: int) -> np.ndarray:
    """Indices of about ``n`` radar positions: the rows nearest y = 0 in every column (a shorter
    aperture with the same sampling). positions_true (M, K, 3); returns int (n',) sorted."""
    y = np.round(np.asarray(positions_true)[:, :, 1].mean(axis=1), 6)
    rows = np.unique(y)
    per_column = max(1, int(round(n * rows.size / y.size)))
    keep = rows[np.argsort(np.abs(rows), kind="stable")[:per_column]]
    return np.flatnonzero(np.isin(y, keep))


def _subset(scan: Scan, idx: np.ndarray, positions: np.ndarray | None = None) -> Scan:
    pos = scan.positions if positions is None else positions
    return Scan(
        scan.data[idx],
        pos[idx],
        scan.chirp,
        positions_true=None if scan.positions_true is None else scan.positions_true[idx],
        timestamps_ns=None if scan.timestamps_ns is None else scan.timestamps_ns[idx],
    )


def _knob_config(knob: str, value, settings: EvalSettings) -> dict:
    """(size, AutofocusConfig overrides, back-projection precision) of one knob value."""
    size, bp_prec = settings.size, settings.precision
    over: dict[str, Any] = {}
    if knob == "image size":
        size = int(value)
    elif knob == "optimiser":
        over = {"iterations": int(value[0]), "lr": float(value[1]), "coarse_iterations": int(value[2])}
    elif knob == "precision":
        if value == "float16":
            over = {"basis_dtype": "float16", "precision": "float32"}
        elif value == "float32":
            over = {"basis_dtype": "float32", "precision": "float32"}
        else:
            over = {"basis_dtype": "float32", "precision": "float64"}
            bp_prec = "float64"
    return {"size": size, "overrides": over, "bp_precision": bp_prec}


def _label(knob: str, value) -> str:
    if knob == "image size":
        return f"{value} x {value}"
    if knob == "positions":
        return f"{value} x 86"
    if knob == "optimiser":
        coarse = f" + {value[2]} coarse" if value[2] else ""
        return f"{value[0]} it{coarse}, lr {value[1]:g}"
    return str(value)


class _Scene:
    """One simulated scan with a tracking-error draw, and the fixed 100 x 100 evaluation."""

    def __init__(self, ref: str, tgt: str, settings: EvalSettings, draw: int):
        self.sc = EvalScenario(
            reference=ref,
            target=tgt,
            seed=0,
            n_columns=settings.n_columns,
            n_rows=settings.n_rows,
            spacing_m=settings.spacing_m,
        )
        self.pair = f"{ref}>{tgt}"
        self.settings = settings
        self.scan, self.template_scan = simulate_scenario(self.sc)
        self.tracked = tracked_positions(self.scan, self.sc, draw_seed("trade", ref, tgt, draw))
        self.ref_grid, self.tgt_grid = case_grids(self.sc, settings.size, "paper")
        bp = settings.bp_options()
        self.truth = backproject(self.scan.data, self.scan.positions_true, self.scan.chirp, self.tgt_grid, **bp)
        self.tgt_basis = subimage_basis(self.scan.data, self.tracked, self.scan.chirp, self.tgt_grid, **bp)
        self._ref_bases: dict = {}

    def reference_basis(self, size: int, precision: str) -> tuple[np.ndarray, float]:
        key = (size, precision)
        if key not in self._ref_bases:
            grid = ImageGrid.from_roi(self.ref_grid.roi, size)
            bp = {**self.settings.bp_options(), "precision": precision}
            t = time.perf_counter()
            basis = subimage_basis(self.scan.data, self.tracked, self.scan.chirp, grid, **bp)
            self._ref_bases = {k: v for k, v in self._ref_bases.items() if k[0] == self.settings.size}  # bound memory
            self._ref_bases[key] = (basis, time.perf_counter() - t, template_from_scan(self.template_scan, grid, **bp))
        basis, secs, _ = self._ref_bases[key]
        return basis, secs

    def template(self, size: int, precision: str) -> np.ndarray:
        self.reference_basis(size, precision)
        return self._ref_bases[(size, precision)][2]

    def score(self, phase: np.ndarray) -> dict:
        image = form_image(
            self.tgt_basis, transfer_phase(phase, self.tracked, self.settings.phase_ramp, range_m=self.ref_grid.z)
        )
        return {"ssim": metrics.image_ssim(image, self.truth), "hog": hog_similarity(image, self.truth)}


#: Optimiser timing: best of TIMING_REPEATS short runs of TIMING_ITERATIONS, scaled to the
#: configured iterations (an iteration costs the same all along: the schedule only changes the
#: step size). The machine is shared, so one long run's wall time carries other jobs' bursts.
TIMING_ITERATIONS = 40
TIMING_REPEATS = 2


def optimiser_seconds(basis: np.ndarray, template: np.ndarray, cfg) -> float:
    """Wall time of the twin autofocus with ``cfg`` on ``basis`` (s), measured as the best of
    :data:`TIMING_REPEATS` runs of at most :data:`TIMING_ITERATIONS` plain iterations, scaled to
    ``cfg.iterations + cfg.coarse_iterations`` (a coarse iteration costs a plain one plus two small
    blur products)."""
    total = int(cfg.iterations) + int(cfg.coarse_iterations)
    n = min(total, TIMING_ITERATIONS)
    short = replace(cfg, iterations=n, coarse_iterations=0)
    best = min(twin_autofocus(basis, template, short).time_s for _ in range(TIMING_REPEATS))
    return best * total / n


def _run_config(scene: _Scene, size: int, overrides: dict, bp_precision: str) -> dict:
    settings = scene.settings
    basis, basis_s = scene.reference_basis(size, bp_precision)
    tpl = scene.template(size, bp_precision)
    cfg = settings.autofocus_config(**overrides)
    res = twin_autofocus(basis, tpl, cfg)
    return {
        "reference_basis_s": basis_s,
        "autofocus_s": optimiser_seconds(basis, tpl, cfg),
        "autofocus_run_s": res.time_s,
        **scene.score(res.phase_rad),
    }


def _positions_row(scene: _Scene, n: int) -> dict:
    """Array-size knob: everything (basis, template, target, truth) on the central rows only."""
    settings = scene.settings
    truth = scene.scan.positions_true
    assert truth is not None  # a simulated scene knows where its positions really were
    idx = central_rows(truth, n)
    bp = settings.bp_options()
    sub = _subset(scene.scan, idx, scene.tracked)
    stage = _subset(scene.template_scan, idx)
    t = time.perf_counter()
    basis = subimage_basis(sub.data, sub.positions, sub.chirp, scene.ref_grid, **bp)
    basis_s = time.perf_counter() - t
    tpl = template_from_scan(stage, scene.ref_grid, **bp)
    res = twin_autofocus(basis, tpl, settings.autofocus_config())
    tgt = subimage_basis(sub.data, sub.positions, sub.chirp, scene.tgt_grid, **bp)
    truth = backproject(sub.data, sub.positions_true, sub.chirp, scene.tgt_grid, **bp)
    image = form_image(tgt, transfer_phase(res.phase_rad, sub.positions, settings.phase_ramp, range_m=scene.ref_grid.z))
    return {
        "n_positions": int(idx.size),
        "reference_basis_s": basis_s,
        "autofocus_s": optimiser_seconds(basis, tpl, settings.autofocus_config()),
        "autofocus_run_s": res.time_s,
        "ssim": metrics.image_ssim(image, truth),
        "hog": hog_similarity(image, truth),
        "ssim_uncorrected": metrics.image_ssim(tgt.sum(axis=0), truth),
    }


def _digital_rows(scene: _Scene, values) -> list[dict]:
    settings = scene.settings
    try:
        points, info = digital_twin_points(scene.sc, scene.ref_grid.roi, seed=0)
    except TwinFocusError as exc:
        return [{"knob": "digital twin", "value": v, "label": v, "status": f"failed: {exc}"} for v in values]
    basis, basis_s = scene.reference_basis(settings.size, settings.precision)
    rows = []
    for v in values:
        method = "exact" if v == "exact" else "psf"
        t = time.perf_counter()
        tpl = digital_twin_template(
            points,
            scene.tracked,
            scene.scan.chirp,
            scene.ref_grid,
            method=method,
            coherent=v != "psf-incoherent",
            **settings.bp_options(),
        )
        tpl_s = time.perf_counter() - t
        res = twin_autofocus(basis, tpl, settings.autofocus_config())
        rows.append(
            {
                "knob": "digital twin",
                "value": v,
                "label": v,
                "status": "ok",
                "template_s": tpl_s,
                "reference_basis_s": basis_s,
                "autofocus_s": res.time_s,
                "autofocus_run_s": res.time_s,
                "stages_s": info,
                **scene.score(res.phase_rad),
            }
        )
    return rows


def _knob_means(rows: list[dict], knob: str) -> list[dict]:
    out: dict[str, dict[str, Any]] = {}
    for r in rows:
        if r["knob"] != knob or r.get("status", "ok") != "ok":
            continue
        key = r["label"]
        e = out.setdefault(key, {"label": key, "value": r["value"], "ssim": [], "time": []})
        e["ssim"].append(r["ssim"])
        e["time"].append(r["reference_basis_s"] + r["autofocus_s"])
    return [
        {
            "label": e["label"],
            "value": e["value"],
            "ssim": float(np.mean(e["ssim"])),
            "time_s": float(np.mean(e["time"])),
        }
        for e in out.values()
    ]


def choose_presets(rows: list[dict], settings: EvalSettings, tolerance: dict | None = None) -> dict:
    """{"fast": {...}, "accurate": {...}}: per knob (image size, optimiser, precision) the
    cheapest measured value whose mean SSIM is within the preset's tolerance of that knob's best;
    each preset as {"size", "iterations", "lr", "basis_dtype", "precision", "choices"}."""
    tolerance = tolerance or PRESET_TOLERANCE
    presets = {}
    for name, tol in tolerance.items():
        choice = {}
        for knob in ("image size", "optimiser", "precision"):
            means = _knob_means(rows, knob)
            if not means:
                continue
            best = max(m["ssim"] for m in means)
            ok = [m for m in means if m["ssim"] >= best - tol]
            choice[knob] = min(ok, key=lambda m: m["time_s"])["value"]
        size = int(choice.get("image size", settings.size))
        it, lr, coarse = choice.get("optimiser", (settings.iterations, 0.05, 0))
        prec = _knob_config("precision", choice.get("precision", settings.basis_dtype), settings)
        presets[name] = {
            "size": size,
            "iterations": int(it),
            "lr": float(lr),
            "coarse_iterations": int(coarse),
            "basis_dtype": prec["overrides"].get("basis_dtype", settings.basis_dtype),
            "precision": prec["overrides"].get("precision", settings.precision),
            "bp_precision": prec["bp_precision"],
            "choices": {k: (list(v) if isinstance(v, tuple) else v) for k, v in choice.items()},
        }
    return presets


def run_trade(settings: EvalSettings, quick: bool = False, scenes: int = 2, log=None) -> dict:
    """Measure every knob on ``scenes`` scenes (pairs A>F, R>X; one tracking-error draw each, sigma
    0.5 mm) and the two presets. Returns {"rows", "presets", "settings", "seconds"}; a row has
    knob, value, label, pair, reference_basis_s, autofocus_s, ssim, hog (and template_s for the
    digital twin)."""
    log = log or (lambda msg: None)
    knobs = QUICK_KNOBS if quick else FULL_KNOBS
    t0 = time.perf_counter()
    rows: list[dict] = []
    scene_objs = []
    for i, (ref, tgt) in enumerate(TRADE_PAIRS[: max(1, int(scenes))]):
        scene = _Scene(ref, tgt, settings, draw=i)
        scene_objs.append(scene)
        if i == 0:  # warm-up: the first optimiser call of a process pays torch's start-up
            basis, _ = scene.reference_basis(settings.size, settings.precision)
            twin_autofocus(
                basis, scene.template(settings.size, settings.precision), settings.autofocus_config(iterations=3)
            )
        unc = scene.score(np.zeros(scene.scan.n_positions))
        rows.append(
            {
                "knob": "uncorrected",
                "value": "none",
                "label": "no correction",
                "pair": scene.pair,
                "reference_basis_s": 0.0,
                "autofocus_s": 0.0,
                **unc,
            }
        )
        for knob in ("image size", "optimiser", "precision"):
            for v in knobs[knob]:
                cfg = _knob_config(knob, v, settings)
                r = _run_config(scene, cfg["size"], cfg["overrides"], cfg["bp_precision"])
                rows.append(
                    {
                        "knob": knob,
                        "value": list(v) if isinstance(v, tuple) else v,
                        "label": _label(knob, v),
                        "pair": scene.pair,
                        **r,
                    }
                )
                log(
                    f"[trade] {scene.pair} {knob} {_label(knob, v)}: SSIM {r['ssim']:.3f}, basis {r['reference_basis_s']:.1f} s, "
                    f"autofocus {r['autofocus_s']:.1f} s ({time.perf_counter() - t0:.0f} s)"
                )
        for n in knobs["positions"]:
            r = _positions_row(scene, n)
            rows.append({"knob": "positions", "value": n, "label": _label("positions", n), "pair": scene.pair, **r})
            log(
                f"[trade] {scene.pair} positions {r['n_positions']}: SSIM {r['ssim']:.3f}, autofocus {r['autofocus_s']:.1f} s"
            )
        for r in _digital_rows(scene, knobs["digital twin"]):
            rows.append({**r, "pair": scene.pair})
            if r["status"] == "ok":
                log(
                    f"[trade] {scene.pair} digital twin {r['label']}: SSIM {r['ssim']:.3f}, template {r['template_s']:.1f} s"
                )
        # Keep only the scan and the evaluation: the reference bases are rebuilt for the presets.
        scene._ref_bases = {}
    # JSON keeps tuples as lists: normalise the values the presets are chosen from.
    presets = choose_presets(
        [{**r, "value": tuple(r["value"]) if isinstance(r["value"], list) else r["value"]} for r in rows], settings
    )
    for name, p in presets.items():
        for scene in scene_objs:
            r = _run_config(
                scene,
                p["size"],
                {
                    "iterations": p["iterations"],
                    "lr": p["lr"],
                    "coarse_iterations": p["coarse_iterations"],
                    "basis_dtype": p["basis_dtype"],
                    "precision": p["precision"],
                },
                p["bp_precision"],
            )
            rows.append({"knob": "preset", "value": name, "label": name, "pair": scene.pair, **r})
            log(
                f"[trade] {scene.pair} preset {name}: SSIM {r['ssim']:.3f}, basis {r['reference_basis_s']:.1f} s, autofocus {r['autofocus_s']:.1f} s"
            )
        for scene in scene_objs:
            scene._ref_bases = {}
    return {
        "rows": rows,
        "presets": presets,
        "settings": settings.to_dict(),
        "knobs": {k: [list(x) if isinstance(x, tuple) else x for x in v] for k, v in knobs.items()},
        "seconds": time.perf_counter() - t0,
    }
