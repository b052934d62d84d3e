"""Run the experiments and keep their raw results.

Each experiment's records go to ``OUT/raw/<name>.json`` as soon as it finishes (so a long run
that is stopped keeps what it finished, and ``resume`` skips experiments already done with the
same settings). The report (:mod:`twinfocus.evaluation.report`) is written from those files.
"""

from __future__ import annotations

import gc
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from twinfocus.evaluation.cases import (
    EvalScenario,
    EvalSettings,
    draw_seed,
    draw_shared,
    evaluate_methods,
    needs_digital_twin,
    needs_reference,
    paper_twin_estimates,
    prepare_scene,
    runs_paper_optimiser,
    template_key,
    tracked_positions,
)
from twinfocus.evaluation.experiments import Experiment, paper_experiments
from twinfocus.evaluation.report import write_report
from twinfocus.evaluation.trade import run_trade
from twinfocus.imaging import metrics
from twinfocus.io.atomic import atomic_writer, write_json_atomic
from twinfocus.io.atomic import json_default as _json_default
from twinfocus.jobs.cluster import dask_client, limit_threads, run_tasks
from twinfocus.jobs.machine import machine_info
from twinfocus.jobs.progress import remaining_text


def quick_settings() -> EvalSettings:
    """Small enough for ``make test``: 6 x 40 positions, 32 x 32 pixels, 60 iterations, scatterers
    every 2.4 mm."""
    return EvalSettings(size=32, iterations=60, n_rows=40, spacing_m=2.4e-3)


def _log(msg: str, stream=None) -> None:
    stream = stream or sys.stderr
    stream.write(msg + "\n")
    stream.flush()


def _scene_units(exp: Experiment) -> list[dict]:
    """Group the experiment's (condition, pair) by scene: conditions that share scene fields and a
    pair share one simulation."""
    units: dict = {}
    for cond in exp.conditions:
        for ref, tgt in cond.pairs:
            key = (json.dumps(cond.scene, sort_keys=True), ref, tgt)
            units.setdefault(key, {"scene": cond.scene, "pair": (ref, tgt), "conditions": []})["conditions"].append(
                cond
            )
    return list(units.values())


#: Experiments whose first draw keeps its images for the report's picture of the methods.
EXAMPLE_EXPERIMENTS = ("baseline", "nlos", "handheld")


def _prepare_unit(exp: Experiment, settings: EvalSettings, unit: dict, cache: dict):
    """One scene unit of ``exp`` simulated and prepared (:func:`prepare_scene`) for every
    condition's templates. Returns (scenario, case, the scene's record for the result)."""
    ref, tgt = unit["pair"]
    conds = unit["conditions"]
    sc = EvalScenario(
        reference=ref,
        target=tgt,
        seed=exp.seed,
        n_columns=settings.n_columns,
        n_rows=settings.n_rows,
        spacing_m=settings.spacing_m,
        **unit["scene"],
    )
    methods_all = {m for c in conds for m in (c.methods or exp.methods)}
    envs = tuple(sorted({c.template_env for c in conds}))
    case = prepare_scene(
        sc,
        settings,
        exp.roi,
        envs,
        digital=any(needs_digital_twin(m) for m in methods_all),
        template_cache=cache,
        roi_margin_m=exp.roi_margin_m,
    )
    scene = {
        "pair": f"{ref}>{tgt}",
        "scene": unit["scene"],
        "timings_s": case.timings_s,
        "notes": case.notes,
        "reference_roi": list(case.ref_grid.roi),
        "target_roi": list(case.tgt_grid.roi),
    }
    return sc, case, scene


def _record_keys(exp: Experiment, c, ref: str, tgt: str, d: int) -> dict:
    """What names a record: the experiment, its condition, the pair and the draw."""
    return {
        "experiment": exp.name,
        "condition": c.label,
        "x": c.x,
        "in_paper": c.in_paper,
        "template_env": c.template_env,
        "pair": f"{ref}>{tgt}",
        "reference": ref,
        "target": tgt,
        "draw": d,
    }


def _ssim_summary(recs: list[dict]) -> str:
    """``method SSIM`` of each record, ``method failed`` where it has none, for the progress line."""
    return " ".join(
        f"{r['method']} {r['ssim']:.3f}" if r["ssim"] is not None else f"{r['method']} failed" for r in recs
    )


def run_experiment(
    exp: Experiment,
    settings: EvalSettings,
    template_cache: dict | None = None,
    log=_log,
    units: list[int] | None = None,
) -> dict:
    """Run one experiment; returns {"definition", "settings", "records", "scenes", "seconds",
    "examples"}.

    units : indices into the experiment's scenes (pairs and scene fields, :func:`_scene_units`) to
    run, default all; every draw's seed comes from the definition, so the parts of a split run
    concatenated in scene order (:func:`merge_parts`) are the whole run's records.

    A record is one (condition, pair, draw, method): the method's metrics plus the draw's shared
    fields (:func:`twinfocus.evaluation.cases.draw_shared`). ``examples`` (experiments of
    :data:`EXAMPLE_EXPERIMENTS`): the display images of the first draw, {"truth" | method: float32
    (H, W)}, plus "pair" and "condition".
    """
    t_start = time.perf_counter()
    cache = template_cache if template_cache is not None else {}
    records: list[dict] = []
    scenes: list[dict] = []
    examples: dict = {}
    all_units = _scene_units(exp)
    chosen = range(len(all_units)) if units is None else units
    total = sum(len(all_units[i]["conditions"]) for i in chosen) * exp.draws
    done = 0
    for i in chosen:
        unit = all_units[i]
        ref, tgt = unit["pair"]
        sc, case, scene = _prepare_unit(exp, settings, unit, cache)
        scenes.append(scene)
        conds = unit["conditions"]
        # Conditions with the same tracking error share each draw's positions and bases.
        by_errors: dict = {}
        for c in conds:
            by_errors.setdefault(json.dumps(c.errors, sort_keys=True), []).append(c)
        for group in by_errors.values():
            err_sc = replace(sc, **group[0].errors)
            for d in range(exp.draws):
                tracked = tracked_positions(case.scan, err_sc, draw_seed(exp.name, ref, tgt, d))
                bases = draw_shared(
                    case,
                    tracked,
                    settings,
                    need_reference=any(needs_reference(m) for c in group for m in (c.methods or exp.methods)),
                )
                # Every condition's paper-optimiser estimates on this draw's reference basis in one batch.
                cfg = settings.autofocus_config()
                estimates = paper_twin_estimates(
                    case,
                    bases,
                    [
                        template_key(m, c.template_env)
                        for c in group
                        for m in (c.methods or exp.methods)
                        if runs_paper_optimiser(m, cfg)
                    ],
                    cfg,
                )
                for c in group:
                    keep = exp.name in EXAMPLE_EXPERIMENTS and not examples
                    recs = evaluate_methods(
                        case,
                        bases,
                        c.methods or exp.methods,
                        settings,
                        c.template_env,
                        keep_images=keep,
                        estimates=estimates,
                    )
                    if keep:
                        examples = {
                            "pair": f"{ref}>{tgt}",
                            "condition": c.label,
                            "truth": metrics.display_image(case.truth_target).astype(np.float32),
                            **{r["method"]: r.pop("image") for r in recs if "image" in r},
                        }
                    records += [{**_record_keys(exp, c, ref, tgt, d), **bases.shared, **r} for r in recs]
                    done += 1
                    summary = _ssim_summary(recs)
                    spent = time.perf_counter() - t_start
                    left = f", about {remaining_text(spent * (total - done) / done)} left" if done < total else ""
                    log(
                        f"[{exp.name}] {done}/{total} scene {i + 1}/{len(all_units)} {ref}>{tgt} {c.label} draw {d + 1}: "
                        f"{summary} ({spent:.0f} s{left})"
                    )
                del bases
        del case
        gc.collect()
    return {
        "definition": exp.to_dict(),
        "settings": settings.to_dict(),
        "records": records,
        "scenes": scenes,
        "seconds": time.perf_counter() - t_start,
        "examples": examples,
    }


def _same_run(doc: dict, exp_def: dict, settings: dict) -> bool:
    return (
        json.loads(json.dumps(doc.get("definition"), default=_json_default))
        == json.loads(json.dumps(exp_def, default=_json_default))
        and doc.get("settings") == settings
    )


def _save_examples(path: Path, examples: dict) -> None:
    arrays = {k: np.asarray(v, np.float16) for k, v in examples.items() if isinstance(v, np.ndarray)}
    meta = json.dumps({k: v for k, v in examples.items() if not isinstance(v, np.ndarray)})
    with atomic_writer(path) as f:
        np.savez_compressed(f, meta=np.array(meta), **arrays)  # type: ignore[arg-type]  # numpy stubs type **kwds as the flag


def merge_parts(parts: list[dict]) -> dict:
    """One experiment's result from its parts (:func:`run_experiment` on disjoint ``units``), given
    in scene order: records and scenes concatenated, the first part's examples, seconds summed
    (compute time, not wall time)."""
    out = dict(parts[0])
    out["records"] = [r for p in parts for r in p["records"]]
    out["scenes"] = [sc for p in parts for sc in p["scenes"]]
    out["seconds"] = sum(p["seconds"] for p in parts)
    out["examples"] = next((p["examples"] for p in parts if p.get("examples")), {})
    return out


#: A Dask worker's templates across its tasks (:func:`prepare_scene`'s ``template_cache``): the
#: scenes of one reference reuse its twins, as in a serial run. Keyed by the stage scan's data.
_WORKER_TEMPLATES: dict = {}


def _experiment_task(part: tuple[Experiment, int], threads, settings: EvalSettings) -> dict:
    """One scene of an experiment on a Dask worker (threads limited to its share of the machine)."""
    limit_threads(threads)
    exp, unit = part
    return run_experiment(exp, settings, _WORKER_TEMPLATES, log=lambda msg: None, units=[unit])


def run_experiments(
    exps: list[Experiment],
    settings: EvalSettings,
    raw: Path,
    *,
    resume: bool = False,
    log=_log,
    cluster: dict | None = None,
    keep_examples: bool = True,
) -> list[dict]:
    """Run ``exps`` into ``raw/<name>.json`` (each written as soon as it is done), skipping those
    already there with the same definition and settings when ``resume``.

    cluster : None runs them here one after the other; ``{"scheduler": ...}`` or ``{"workers": N}``
        spreads them over Dask workers, one scene (pair) of an experiment per task, merged per
        experiment once all its scenes are back (:func:`merge_parts`). Every draw's seed comes from the
        experiment's definition (:func:`twinfocus.evaluation.cases.draw_seed`), so the records are
        the serial run's. A task that fails is logged and returned as {"experiment", "error"}; the
        others go on.
    """
    pending = []
    for exp in exps:
        path = raw / f"{exp.name}.json"
        if resume and path.exists():
            try:
                if _same_run(json.loads(path.read_text()), exp.to_dict(), settings.to_dict()):
                    log(f"[{exp.name}] kept from an earlier run ({path})")
                    continue
            except (OSError, ValueError):
                pass
        pending.append(exp)

    def keep(exp: Experiment, res: dict) -> None:
        examples = res.pop("examples", None)
        if examples and keep_examples:
            _save_examples(raw / f"{exp.name}_examples.npz", examples)
        write_json_atomic(raw / f"{exp.name}.json", res)
        log(f"[{exp.name}] done in {res['seconds'] / 60:.1f} min")

    failed: list[dict] = []
    if cluster is None:
        cache: dict = {}  # templates shared across experiments (speed only: each is deterministic)
        for exp in pending:
            log(f"[{exp.name}] {exp.n_draws()} draws ...")
            keep(exp, run_experiment(exp, settings, cache, log))
        return failed

    n_scenes = {exp.name: len(_scene_units(exp)) for exp in pending}
    parts = [(exp, u) for exp in pending for u in range(n_scenes[exp.name])]
    got: dict[str, dict[int, dict]] = {exp.name: {} for exp in pending}
    errors: dict[str, str] = {}

    def on_result(part, res, err):
        exp, unit = part
        if err is not None:
            log(f"[{exp.name}] scene {unit + 1} failed: {err}")
            errors.setdefault(exp.name, err)
            return
        got[exp.name][unit] = res
        n = n_scenes[exp.name]
        finished = sum(len(g) for g in got.values())
        spent = time.perf_counter() - t_tasks
        left = (
            f", about {remaining_text(spent * (len(parts) - finished) / finished)} left in all"
            if finished < len(parts)
            else ""
        )
        log(f"[{exp.name}] {len(got[exp.name])}/{n} scenes done ({res['seconds'] / 60:.1f} min this one{left})")
        if len(got[exp.name]) == n and exp.name not in errors:
            keep(exp, merge_parts([got[exp.name][u] for u in range(n)]))

    t_tasks = time.perf_counter()
    log(
        f"[bench] {len(pending)} experiments as {len(parts)} Dask tasks, one per scene "
        f"({sum(e.n_draws() for e in pending)} draws)"
    )
    with dask_client(cluster.get("scheduler"), cluster.get("workers"), log) as client:
        run_tasks(
            client, _experiment_task, parts, [f"bench-{exp.name}-{u}" for exp, u in parts], on_result, extra=(settings,)
        )
    failed.extend({"experiment": name, "error": err} for name, err in errors.items())
    return failed


def run_paper(
    out_dir,
    *,
    quick: bool = False,
    draws: int | None = None,
    only=None,
    resume: bool = False,
    markdown=None,
    device: str = "cpu",
    trade_scenes: int | None = None,
    command: str | None = None,
    log=_log,
    cluster: dict | None = None,
) -> Path:
    """``twinfocus bench paper``: run the experiments (and the speed/accuracy trade), keep their raw
    results in ``out_dir/raw`` and write the report. Returns the report's path.

    only : experiment names (see :data:`twinfocus.evaluation.experiments.EXPERIMENT_NAMES`, plus
        ``trade``); default all. The report covers every raw result in ``out_dir/raw``, so runs of
        parts add up.
    resume : skip experiments whose raw result exists with the same definition and settings.
    cluster : None (one after the other, here) or ``{"scheduler": "tcp://HOST:PORT"}`` /
        ``{"workers": N}``: the experiments run as Dask tasks (:func:`run_experiments`).
    """
    settings = quick_settings() if quick else EvalSettings()
    settings.device = device
    exps = paper_experiments(quick=quick, draws=draws, only=only)  # checks the names before any work
    out = Path(out_dir)
    raw = out / "raw"
    raw.mkdir(parents=True, exist_ok=True)
    do_trade = not only or "trade" in only
    t0 = time.perf_counter()
    run: dict[str, Any] = {
        "command": command,
        "quick": quick,
        "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "machine": machine_info(),
    }
    failed = run_experiments(exps, settings, raw, resume=resume, log=log, cluster=cluster, keep_examples=True)
    if failed:
        run["failed"] = failed
    if do_trade:
        path = raw / "trade.json"
        scenes = trade_scenes if trade_scenes is not None else 1
        keep = False
        if resume and path.exists():
            try:
                doc = json.loads(path.read_text())
                keep = (
                    doc.get("settings") == settings.to_dict()
                    and doc.get("quick") == quick
                    and doc.get("scenes") == scenes
                )
            except (OSError, ValueError):
                keep = False
        if keep:
            log(f"[trade] kept from an earlier run ({path})")
        else:
            log("[trade] speed/accuracy knobs ...")
            res = run_trade(settings, quick=quick, scenes=scenes, log=log)
            res.update({"quick": quick, "scenes": scenes})
            write_json_atomic(path, res)
            log(f"[trade] done in {res['seconds'] / 60:.1f} min")
    run["seconds"] = time.perf_counter() - t0
    run["machine"]["load_average_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    write_json_atomic(raw / "run.json", run)
    md = write_report(out, markdown)
    log(f"[bench] report {md} ({run['seconds'] / 60:.1f} min)")
    return md
