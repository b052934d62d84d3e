"""The rungs that always keep their fit, against a held-out rule: how often it would refuse them.

    python -m benchmarks.bench_rung_keeps --seeds 9201 9202 9203   (the rungs' ``keeps_because`` quote it)

The drift and the tilt are kept only on held-out evidence (fitted on one half of the
reference's blocks, :func:`twinfocus.focus.ladder.heldout_split`, and judged on the other against
the model beneath fitted on the same half: :func:`~twinfocus.focus.ladder.heldout_gain`,
:func:`~twinfocus.focus.ladder.heldout_verdict`: kept when the gain is above its noise). The
other rungs that fit phases keep them whatever they give: ``phase`` (the estimator's closed form),
``refine`` (the optimiser, once its checks let it run) and the reference-free ``sharpness``,
``entropy`` and ``pga``. On each draw of benchmarks/bench_model_ladder.py's scenes (its size: 3
columns of 20 positions, 20 x 20 pixels, 50 optimiser iterations; seeds of their own) this fits
each of them on each half with the very rung the plan builds (``--model auto``'s settings; the
half's basis and template zero elsewhere) and judges it on the other half by the same rule:

* ``phase``: against no correction, by the reference's unmatched share against the template
  (with phase: the rung's own record, ``evidence.heldout``, for the correlation's closed form;
  for an amplitude template or a digital twin, the image's magnitude against it);
* ``refine``, where ``--model auto`` climbs it: against the closed form on the same half;
* ``sharpness``, ``entropy``, ``pga`` (``--method``): against no correction, by the target's
  sharpness (:func:`twinfocus.imaging.metrics.image_sharpness`, the evidence these rungs
  record) on the held-out half of the target's blocks, the gain relative to no correction's;
  once per scan (the camera cloud's scan is the rough reference's).

The placement and the range errors are not measured: their keep is the transfer's own rule
(``ramp.reason``), and their fit moves the reference off a misplaced template on purpose.

Writes ``rung_keeps.json``: per rung the draws, how many a held-out rule would have kept, the
gains (mean, least, largest), and the draws it would have refused with their gain and noise.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks import bench_model_ladder as ladder_bench
from twinfocus.focus.estimators import REFERENCE_FREE_RUNGS

SEEDS = (9201, 9202, 9203)
#: every reference-free rung of the registry (a new one is measured with no line here)
FREE = REFERENCE_FREE_RUNGS


def _half(problem, fitted: np.ndarray, region: str = "reference"):
    """``problem`` seen on the ``fitted`` pixels of ``region`` alone (bool (H, W)): that region's
    basis, and for the reference its template and outline, zero elsewhere."""
    if region == "target":
        return replace(problem, tgt_basis=problem.tgt_basis * fitted)
    return replace(
        problem,
        ref_basis=problem.ref_basis * fitted,
        template=None if problem.template is None else problem.template * fitted,
        support=None if problem.support is None else problem.support & fitted,
        registration_scores=None,  # the whole reference's: registered again on the half
    )


def _verdict(folds: list[dict]) -> dict:
    from twinfocus.focus.ladder import heldout_verdict

    out = heldout_verdict(folds)
    return {k: out[k] for k in ("gain", "noise", "kept")}


def _reference_folds(problem, rungs: dict, climbed: list[str], judge: np.ndarray) -> dict[str, dict]:
    """Held-out verdicts of the ``climbed`` rungs among phase and refine, each against the rung
    beneath on the same half; ``judge``: the template the ladder fitted to (the registered one)."""
    from twinfocus.focus.ladder import Model, heldout_gain, heldout_split
    from twinfocus.imaging.basis import form_image

    m = problem.ref_basis.shape[0]
    first = heldout_split(problem)
    folds: dict[str, list[dict]] = {n: [] for n in climbed}
    amplitude = not np.iscomplexobj(judge)
    for fitted in (first, ~first):
        hp = _half(problem, fitted)
        model = Model(phase_rad=np.zeros(m), estimate_rad=np.zeros(m), template=hp.template)
        image = form_image(problem.ref_basis, model.phase_rad)
        for name in climbed:
            model = rungs[name].fit(hp, model).model
            after = form_image(problem.ref_basis, model.phase_rad)
            if amplitude:
                folds[name].append(heldout_gain(np.abs(image), np.abs(after), judge, ~fitted))
            else:
                folds[name].append(heldout_gain(image, after, judge, ~fitted))
            image = after
    return {n: _verdict(f) for n, f in folds.items()}


def _free_verdict(problem, rung) -> dict:
    """The held-out verdict of a reference-free rung on the target's blocks, by sharpness."""
    from twinfocus.focus.ladder import Model, heldout_split
    from twinfocus.imaging.basis import form_image
    from twinfocus.imaging.metrics import image_sharpness

    basis = problem.tgt_basis
    m = basis.shape[0]
    first = heldout_split(replace(problem, reference_grid=problem.target_grid))
    folds = []
    for fitted in (first, ~first):
        start = Model(phase_rad=np.zeros(m), estimate_rad=np.zeros(m))
        phase = rung.fit(_half(problem, fitted, "target"), start).model.phase_rad
        before = image_sharpness(form_image(basis, np.zeros(basis.shape[0]))[~fitted])
        after = image_sharpness(form_image(basis, phase)[~fitted])
        folds.append({"unmatched_before": before, "unmatched_after": after, "gain": after / before - 1.0})
    return _verdict(folds)


def one_draw(scene: str, seed: int) -> dict:
    from twinfocus.focus.ladder import Problem
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.focus.rungs import climb
    from twinfocus.focus.settings import default_settings

    d = ladder_bench.draw_inputs(scene, seed)
    scan, rb, tb, rg, tg = d["scan"], d["rb"], d["tb"], d["rg"], d["tg"]
    settings = {**default_settings(), "iterations": ladder_bench.ITERATIONS, "device": "cpu"}
    plan = FocusPlan.from_settings(settings).for_reference(d["template"], d["support"])
    problem = Problem(rb, tb, scan.positions, scan.chirp, rg, tg, plan.config, d["template"], d["support"])
    rungs = {r.name: r for r in plan.rungs}
    # auto's own climb of the rungs that fit the phases (those above decide nothing of them)
    model, section = climb(problem, [rungs[n] for n in ("none", "phase", "refine")])
    entries = {e["rung"]: e for e in section["rungs"]}
    climbed = [n for n in ("phase", "refine") if entries[n]["tried"]]
    rec: dict = {"scene": scene, "seed": seed, "estimator": plan.estimator, "rungs": {}}
    t = time.perf_counter()
    rec["rungs"] = _reference_folds(problem, rungs, climbed, model.template)
    recorded = entries["phase"].get("evidence", {}).get("heldout")
    if recorded is not None:  # the rung's own record, which the half fit above repeats
        rec["rungs"]["phase"] = {"recorded": True, **{k: recorded[k] for k in ("gain", "noise", "kept")}}
    # the reference-free rungs see the scan alone: once per scan (the camera cloud's is the rough reference's)
    scans = [kw for kw, _ in ladder_bench.SCENES.values()]
    for name in FREE if scans.index(ladder_bench.SCENES[scene][0]) == list(ladder_bench.SCENES).index(scene) else ():
        free = FocusPlan.from_settings(settings, method=name).for_reference(None)
        fp = replace(problem, config=free.config, template=None, support=None)
        rung = next(r for r in free.rungs if r.name == name)
        rec["rungs"][name] = _free_verdict(fp, rung)
    rec["time_s"] = time.perf_counter() - t
    return rec


def summary(records: list[dict]) -> dict:
    names = [n for n in ("phase", "refine", *FREE) if any(n in r["rungs"] for r in records)]
    out = {}
    for n in names:
        rows = [(r["scene"], r["seed"], r["rungs"][n]) for r in records if n in r["rungs"]]
        gains = np.array([v["gain"] for _, _, v in rows])
        out[n] = {
            "draws": len(rows),
            "kept": sum(bool(v["kept"]) for _, _, v in rows),
            "gain_mean": float(gains.mean()),
            "gain_min": float(gains.min()),
            "gain_max": float(gains.max()),
            "refused": [
                {"scene": s, "seed": k, "gain": v["gain"], "noise": v["noise"]} for s, k, v in rows if not v["kept"]
            ],
        }
    return out


def main(out_dir: str, seeds: tuple[int, ...]) -> dict:
    t = time.perf_counter()
    records = []
    for scene in ladder_bench.SCENES:
        for seed in seeds:
            records.append(one_draw(scene, seed))
            print(scene, seed, {n: round(v["gain"], 4) for n, v in records[-1]["rungs"].items()}, flush=True)
    doc = {
        "command": "python -m benchmarks.bench_rung_keeps --seeds " + " ".join(str(s) for s in seeds),
        "protocol": {
            "scenes": list(ladder_bench.SCENES),
            "seeds": list(seeds),
            "columns": ladder_bench.COLUMNS,
            "rows": ladder_bench.ROWS,
            "size_px": ladder_bench.SIZE,
            "optimiser_iterations": ladder_bench.ITERATIONS,
            "wall_s": time.perf_counter() - t,
            "gain": "phase / refine: the held-out half's unmatched share, less the rung beneath's; "
            "sharpness / entropy / pga: the held-out half's target sharpness over no correction's, less 1",
        },
        "rungs": summary(records),
        "records": records,
    }
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    (Path(out_dir) / "rung_keeps.json").write_text(json.dumps(doc, indent=1, default=float))
    print(json.dumps(doc["rungs"], indent=1, default=float))
    return doc


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    ap.add_argument("--out", default="benchmarks/results")
    a = ap.parse_args()
    main(a.out, tuple(a.seeds))
