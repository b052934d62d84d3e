"""Where the time of ``twinfocus bench paper`` goes, per experiment, against an earlier version of
the evaluation, side by side on the same scenes and draws.

    python -m benchmarks.bench_paper_time --draws 1            (--only baseline,handheld)
    python -m benchmarks.run --only paper_time

After a warm-up of each version (numba compiles its kernels once per folder), for each experiment
its first scene (one pair, its conditions, ``--draws`` error draws) runs in a
fresh process on one thread (a Dask worker's share of 2 cores with ``--workers 2``), once with the
earlier version (``--baseline``, a git revision: its ``twinfocus/`` as it was) and at once after
it with the current one, so both see the same load. Each stage is timed in CPU seconds (what the
process computed: on an idle core its wall time) and wall seconds (what it waited, load included):
simulation, the truth image, the physical and digital templates (per scene), the sub-image bases,
the sharpness and twin optimisers, the metrics (per draw). Both versions' SSIM per record are kept.

The estimate of a whole ``--draws 5 --workers 2`` run: each scene's CPU seconds split into its
scene (simulation, truth image, templates) and one draw; the ratio old / new for a scene with 5
draws (scene once, five draws); the committed report's compute time per experiment
(``docs/results/raw/*.json``, a 5-draw run on two Dask workers) divided by the ratio of the
measured experiment of its kind (the four methods: baseline; templates of two rooms: environment;
the three twin methods: handheld), halved for the two workers, plus the speed/accuracy trade as
the report timed it (unchanged here). Writes ``paper_time.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import collections
import functools
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: the evaluation before the twins' estimates were batched
BASELINE = "2ec245c"
SCENE_STAGES = ("simulation", "truth_image", "template_physical", "template_digital")
FULL_DRAWS = 5
WORKERS = 2


def _worker(name: str, draws: int, warmup: bool = False) -> dict:
    """One scene of experiment ``name`` with stage timers, in this process on one thread."""
    from twinfocus.jobs.cluster import limit_threads

    limit_threads(1)
    import twinfocus.evaluation.cases as cases
    import twinfocus.evaluation.runner as runner
    from twinfocus.evaluation.cases import EvalSettings
    from twinfocus.evaluation.experiments import paper_experiments

    wall: dict = collections.defaultdict(float)
    cpu: dict = collections.defaultdict(float)

    def timed(module, attr: str, stage: str) -> None:
        if not hasattr(module, attr):
            return
        fn = getattr(module, attr)

        @functools.wraps(fn)
        def run(*a, **k):
            w, c = time.perf_counter(), time.process_time()
            try:
                return fn(*a, **k)
            finally:
                wall[stage] += time.perf_counter() - w
                cpu[stage] += time.process_time() - c

        setattr(module, attr, run)

    for attr, stage in (
        ("simulate_scenario", "simulation"),
        ("backproject", "truth_image"),
        ("template_from_scan", "template_physical"),
        ("digital_twin_for", "template_digital"),
        ("subimage_basis", "bases"),
        ("sharpness_autofocus", "optimiser_sharpness"),
        ("twin_autofocus", "optimiser_twin"),
        ("paper_estimates", "optimiser_twin"),
        ("hog_similarity", "metrics"),
    ):
        timed(cases, attr, stage)
    timed(cases.metrics, "image_ssim", "metrics")
    if warmup:  # numba compiles its kernels on first use into the version's folder: not a stage's time
        runner.run_experiment(
            paper_experiments(quick=True, only=[name])[0], runner.quick_settings(), {}, lambda m: None
        )
        return {}
    exp = paper_experiments(draws=draws, only=[name])[0]
    w0, c0 = time.perf_counter(), time.process_time()
    res = runner.run_experiment(exp, EvalSettings(), {}, log=lambda m: None, units=[0])
    return {
        "wall_s": time.perf_counter() - w0,
        "cpu_s": time.process_time() - c0,
        "stages_cpu_s": dict(cpu),
        "stages_wall_s": dict(wall),
        "scenes": len(runner._scene_units(exp)),
        "twinfocus": str(Path(cases.__file__).parents[2]),
        "ssim": [[r["condition"], r["method"], r["draw"], r["ssim"]] for r in res["records"]],
    }


def _baseline_tree(rev: str) -> Path | None:
    """``twinfocus/`` at git revision ``rev`` in a temporary folder (None without git or it)."""
    tmp = Path(tempfile.mkdtemp(prefix=f"twinfocus_{rev}_"))
    try:
        tar = subprocess.run(["git", "archive", rev, "twinfocus"], capture_output=True, check=True, cwd=ROOT).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    (tmp / "t.tar").write_bytes(tar)
    with tarfile.open(tmp / "t.tar") as t:
        t.extractall(tmp, filter="data")
    return tmp


def _run(version_path: Path, name: str, draws: int, warmup: bool = False) -> dict:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(version_path), str(ROOT)])}
    load = os.getloadavg()[0]
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.bench_paper_time", "--worker", name, "--draws", str(draws)]
        + (["--warmup"] if warmup else []),
        # run from the version's folder: ``-m`` puts the working folder first on the path
        capture_output=True,
        text=True,
        check=True,
        cwd=version_path,
        env=env,
    ).stdout
    return {**json.loads(out.strip().splitlines()[-1]), "load_average_before": round(load, 2)}


def split_cpu(run: dict, draws: int) -> dict:
    """One scene's CPU seconds split into what its scene costs once and what each draw costs."""
    stages = run["stages_cpu_s"]
    scene = sum(stages.get(s, 0.0) for s in SCENE_STAGES)
    return {"scene_cpu_s": round(scene, 2), "draw_cpu_s": round((run["cpu_s"] - scene) / draws, 2)}


def kind_of(exp) -> str:
    """Which measured experiment stands for ``exp``: the four methods (baseline), templates from
    two rooms on one basis (environment), or the three twin methods (handheld)."""
    if "sharpness" in exp.methods:
        return "baseline"
    if any(c.template_env != "open" for c in exp.conditions):
        return "environment"
    return "handheld"


def main(out_dir=None, only: str = "baseline,environment,handheld", draws: int = 1, baseline: str = BASELINE) -> dict:
    from twinfocus.evaluation.experiments import EXPERIMENT_NAMES, paper_experiments
    from twinfocus.jobs.machine import machine_info

    names = [n for n in EXPERIMENT_NAMES if not only or n in only.split(",")]
    old = _baseline_tree(baseline)
    if old is None:
        raise SystemExit(f"git revision {baseline} is not at hand: nothing to compare with")
    for version in (old, ROOT):
        _run(version, "baseline", 1, warmup=True)
    rows = []
    for name in names:
        row: dict = {"experiment": name, "baseline": _run(old, name, draws), "current": _run(ROOT, name, draws)}
        for v in ("baseline", "current"):
            row[v].update(split_cpu(row[v], draws))
        b, c = row["baseline"], row["current"]
        row["max_abs_ssim_change"] = max(abs((x[3] or 0) - (y[3] or 0)) for x, y in zip(b["ssim"], c["ssim"]))
        row["cpu_ratio_measured"] = round(b["cpu_s"] / c["cpu_s"], 2)
        # the same scene with FULL_DRAWS draws: its scene once, FULL_DRAWS times a draw
        row["cpu_ratio_draws5"] = round(
            (b["scene_cpu_s"] + FULL_DRAWS * b["draw_cpu_s"]) / (c["scene_cpu_s"] + FULL_DRAWS * c["draw_cpu_s"]), 2
        )
        rows.append(row)
        print(
            json.dumps({k: v for k, v in row.items() if k not in ("baseline", "current")}), file=sys.stderr, flush=True
        )
    # The committed report's run (5 draws, two Dask workers) per experiment, each divided by the
    # measured ratio of its kind.
    ratio = {r["experiment"]: r["cpu_ratio_draws5"] for r in rows}
    raw = ROOT / "docs" / "results" / "raw"
    committed = []
    for exp in paper_experiments():
        path = raw / f"{exp.name}.json"
        kind = exp.name if exp.name in ratio else kind_of(exp)
        if not path.is_file() or kind not in ratio:
            continue
        doc = json.loads(path.read_text())
        committed.append(
            {
                "experiment": exp.name,
                "draws": doc["definition"]["draws"],
                "committed_min": round(doc["seconds"] / 60, 1),
                "ratio_from": kind,
                "estimated_min": round(doc["seconds"] / 60 / ratio[kind], 1),
            }
        )
    trade = raw / "trade.json"
    trade_min = json.loads(trade.read_text())["seconds"] / 60 if trade.is_file() else 0.0
    run_json = raw / "run.json"
    totals = {
        "committed_compute_min": round(sum(c["committed_min"] for c in committed), 1),
        "estimated_compute_min": round(sum(c["estimated_min"] for c in committed), 1),
        "trade_min": round(trade_min, 1),
    }
    totals["committed_wall_min_workers2"] = round(totals["committed_compute_min"] / WORKERS + trade_min, 1)
    totals["estimated_wall_min_workers2"] = round(totals["estimated_compute_min"] / WORKERS + trade_min, 1)
    doc = {
        "command": "python -m benchmarks.bench_paper_time --only " + only + f" --draws {draws}",
        "baseline_revision": baseline,
        "draws_measured": draws,
        "experiments": rows,
        "committed_run": committed,
        "committed_run_machine": json.loads(run_json.read_text()).get("machine") if run_json.is_file() else None,
        "totals": totals,
        "machine": machine_info(),
        "load_average_end": list(os.getloadavg()),
    }
    if out_dir is not None:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        (Path(out_dir) / "paper_time.json").write_text(json.dumps(doc, indent=1))
    print(f"{'experiment':12} {'old cpu s':>9} {'new cpu s':>9} {'ratio':>5} {'5 draws':>7} {'max dSSIM':>9}")
    for r in rows:
        print(
            f"{r['experiment']:12} {r['baseline']['cpu_s']:9.1f} {r['current']['cpu_s']:9.1f} "
            f"{r['cpu_ratio_measured']:5.2f} {r['cpu_ratio_draws5']:7.2f} {r['max_abs_ssim_change']:9.4f}"
        )
    print(json.dumps(totals))
    return doc


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--only", default="baseline,environment,handheld", help="comma-separated experiments")
    ap.add_argument("--draws", type=int, default=1, help="error draws of the scene measured (default 1)")
    ap.add_argument("--baseline", default=BASELINE, help="git revision of the earlier version")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--warmup", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        print(json.dumps(_worker(a.worker, a.draws, a.warmup)))
    else:
        main(a.out, a.only, a.draws, a.baseline)
