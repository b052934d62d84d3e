"""The ladder's trade: per rung, the target's SSIM against the time the ladder took to reach it,
on the field-like scenes the project simulates, and how often ``--model auto`` stops at the rung
the truth says is best; ``--model fast``, ``auto`` and ``full`` in time and SSIM.

    python -m benchmarks.bench_model_ladder --draws 5 --workers 2   (docs/model_ladder.md quotes it)

Each draw builds the scan's bases once and runs ``focus_bases`` once per rung (``--model RUNG``:
that rung forced, those beneath it by their rules; its time is the whole climb to it) and with
``--model auto``, ``fast`` and ``full``, its settings from the settings table (twinfocus/focus/settings.py) as
``twinfocus focus`` takes them. A rung that cannot run on the scene (``range_errors`` after a
physical twin's registration, ``drift`` without one) has no entry. Small scans so that five
draws of every scene fit a loaded 2-core machine in about 20 minutes: 3 columns of 20 positions,
20 x 20 pixels, the optimiser's 50 iterations (``--columns``, ``--rows``, ``--size``,
``--iterations``). Scenes (the paper's letters
unless said):

* paper protocol: 0.5 mm x/y/z jitter, the physical twin;
* hand drift + rotation: a hand's 0.8 mm drift and 0.15 deg rotation, letters H and S, 15 dB;
* 1.6 mm wraps: 1.6 mm along z (every phase wraps) + 0.3 mm x/y, an amplitude template;
* rough reference: every scatterer of the reference its own phase (+-90 deg), the physical twin;
* camera cloud: the rough reference's digital twin from a camera cloud (1 mm noise, 25 % holes,
  2 % outliers, 2.5 mm offset).

Writes ``model_ladder.json`` (one record per scene and draw, and the summary) and
docs/figures/model_ladder.png; prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

SIZE, COLUMNS, ROWS, ITERATIONS = 20, 3, 20, 50
HAND = dict(reference="H", target="S", separation_deg=16.3, snr_db=15, error_model="hand", error_sigma_m=(0.8e-3,) * 3)
SCENES = {
    "paper protocol": (dict(error_model="gaussian", error_sigma_m=(0.5e-3,) * 3), "physical"),
    "hand drift + rotation": (HAND, "physical"),
    "1.6 mm wraps": (dict(error_sigma_m=(0.3e-3, 0.3e-3, 1.6e-3), snr_db=15), "amplitude"),
    "rough reference": (
        dict(error_sigma_m=(0.2e-3, 0.2e-3, 0.5e-3), snr_db=15, reference_roughness_deg=90.0),
        "physical",
    ),
    "camera cloud": (dict(error_sigma_m=(0.2e-3, 0.2e-3, 0.5e-3), snr_db=15, reference_roughness_deg=90.0), "cloud"),
}
CLOUD = (1e-3, 0.25, 0.02, 2.5e-3)
MODELS = ("auto", "fast", "full")


def draw_inputs(scene: str, seed: int) -> dict:
    """One draw of ``scene`` (:data:`SCENES`) at the bench's size: ``sc`` (the Scenario), ``scan``,
    ``template`` (complex, or its amplitude, or a digital twin's) and ``support`` (the twin's
    outline or None) on ``rg``, the target grid ``tg``, the sub-image bases ``rb`` / ``tb``
    (complex (M, H, W)) and ``truth`` (the images on the true positions, the true positions)."""
    from twinfocus.focus.pipeline import Truth
    from twinfocus.imaging.backprojection.numba_backend import subimage_basis
    from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario
    from twinfocus.twins.templates import template_from_scan

    kw, kind = SCENES[scene]
    sc = Scenario(**kw, n_columns=COLUMNS, n_rows=ROWS, seed=seed)
    scan, tpl_scan = simulate_scenario(sc)
    rg, tg = scenario_grids(sc, SIZE)
    support = None
    if kind == "cloud":
        from twinfocus.twins.digital_twin.camera_cloud import camera_cloud
        from twinfocus.twins.digital_twin.condition import digital_twin_reference

        surface = sc.scene().object("reference").surface_points(1e-3)
        twin = digital_twin_reference(
            camera_cloud(surface, *CLOUD, rng=np.random.default_rng([seed, 14])), scan.positions, scan.chirp, rg
        )
        template, support = twin.template, twin.support
    else:
        template = template_from_scan(tpl_scan, rg, keep_phase=True)
        if kind == "amplitude":
            template = np.abs(template)
    rb = subimage_basis(scan.data, scan.positions, scan.chirp, rg)
    tb = subimage_basis(scan.data, scan.positions, scan.chirp, tg)
    truth = Truth.of_scan(scan, rg, tg)
    return dict(sc=sc, scan=scan, template=template, support=support, rg=rg, tg=tg, rb=rb, tb=tb, truth=truth)


def one_draw(scene: str, seed: int, only_models: tuple[str, ...] | None = None) -> dict:
    from twinfocus.errors import TwinFocusError
    from twinfocus.focus.estimators import TWIN_RUNGS
    from twinfocus.focus.pipeline import Bases, Reference, Truth, half_array_bases, upper_band_basis
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.focus.settings import default_settings

    d = draw_inputs(scene, seed)
    scan, template, support, rg, tg, rb, tb, truth = (
        d[k] for k in ("scan", "template", "support", "rg", "tg", "rb", "tb", "truth")
    )
    settings = {**default_settings(), "iterations": ITERATIONS, "device": "cpu"}
    rec: dict = {"scene": scene, "seed": seed, "rungs": {}}
    for model in TWIN_RUNGS + MODELS:
        if only_models is not None and model not in only_models:
            continue
        # what `twinfocus focus --model MODEL` runs: its plan for this template, and fast's
        # reference at its resolution (every pixel at this bench's 20 x 20): the slice of the bases
        plan = FocusPlan.from_settings({**settings, "model": model}).for_reference(template, support)
        g, reference, (ky, kx) = plan.reference_for(
            Reference(template, support), scan.positions, rg, scan.chirp.wavelength_m
        )
        t = time.perf_counter()
        try:
            needs = plan.needs
            bases = Bases(
                rb[:, ::ky, ::kx],
                tb,
                scan.positions,
                scan.chirp,
                g,
                tg,
                half_bases=half_array_bases(scan.data, scan.positions, scan.chirp, g, tg) if needs.half_bases else None,
                upper_band=upper_band_basis(scan.data, scan.positions, scan.chirp, g) if needs.upper_band else None,
            )
            out = plan.focus_bases(
                bases,
                reference,
                Truth(truth.target, truth.reference[::ky, ::kx], truth.positions),
            )
        except TwinFocusError as exc:  # the rung cannot run on this scene
            rec.setdefault("cannot run", {})[model] = str(exc)
            continue
        m = out.metrics
        r = {
            "ssim": m["target_ssim_corrected"],
            "time_s": time.perf_counter() - t,
            "result": m["model"]["result"],
            "reference_strides": [ky, kx],
            "kept": m["model"]["kept"],
            "trusted": m["confidence"]["trusted"],
            "heldout": {
                e["rung"]: e["evidence"]["heldout"] for e in m["model"]["rungs"] if "heldout" in e.get("evidence", {})
            },
            "earlier_rule": _earlier_rule(m["model"]),
        }
        if model in MODELS:
            rec[model] = r
        else:
            rec["rungs"][model] = r
        rec["uncorrected"] = m["target_ssim_uncorrected"]
        rec["oracle phase"] = m["target_ssim_oracle_phase"]
    if not rec["rungs"] or "auto" not in rec:
        return rec
    best = max(rec["rungs"], key=lambda r: rec["rungs"][r]["ssim"])
    rec["best rung by truth"] = best
    rec["auto picks best"] = rec["auto"]["result"] == best
    rec["auto within 0.005 of best"] = rec["auto"]["ssim"] >= rec["rungs"][best]["ssim"] - 0.005
    return rec


#: the drift's and tilt's keep rule before the held-out evidence: kept when the fit on the whole
#: reference took away at least this share of the unmatched reference
EARLIER_MIN_GAIN = 0.3


def _earlier_rule(section: dict) -> dict:
    """What the earlier keep rule says of each drift or tilt fit auto tried (``{rung: kept}``),
    from the same fit's record: where it agrees with the held-out evidence, auto's result on this
    draw is what the earlier rule gave."""
    out = {}
    for e in section["rungs"]:
        info = e.get("info", {})
        if e["rung"] in ("drift", "tilt") and e["tried"] and "residual_space_variant" in info:
            before, after = info["residual_scalar"], info["residual_space_variant"]
            out[e["rung"]] = bool(before > 0 and 1.0 - after / before >= EARLIER_MIN_GAIN)
    return out


def _stats(values: list[dict]) -> dict:
    return {
        "ssim_mean": float(np.mean([x["ssim"] for x in values])),
        "ssim_sd": float(np.std([x["ssim"] for x in values])),
        "time_s_mean": float(np.mean([x["time_s"] for x in values])),
        "draws": len(values),
    }


def summary(records: list[dict]) -> dict:
    from twinfocus.focus.estimators import TWIN_RUNGS

    out: dict = {}
    for scene in SCENES:
        recs = [r for r in records if r["scene"] == scene]
        if not recs:
            continue
        rungs = [n for n in TWIN_RUNGS if any(n in r["rungs"] for r in recs)]
        s: dict = {
            "draws": len(recs),
            "rungs": {n: _stats([r["rungs"][n] for r in recs if n in r["rungs"]]) for n in rungs},
        }
        for model in MODELS:
            s[model] = {**_stats([r[model] for r in recs]), "results": [r[model]["result"] for r in recs]}
        s["best rung by truth"] = [r["best rung by truth"] for r in recs]
        s["auto picks best"] = f"{sum(r['auto picks best'] for r in recs)}/{len(recs)}"
        s["auto within 0.005 of best"] = f"{sum(r['auto within 0.005 of best'] for r in recs)}/{len(recs)}"
        agree = [all(r["auto"]["heldout"][n]["kept"] == k for n, k in r["auto"]["earlier_rule"].items()) for r in recs]
        s["held-out and earlier rule agree"] = f"{sum(agree)}/{len(recs)}"
        s["uncorrected"] = float(np.mean([r["uncorrected"] for r in recs]))
        s["oracle phase"] = float(np.mean([r["oracle phase"] for r in recs]))
        out[scene] = s
    n = len(records)
    out["all scenes"] = {
        "draws": n,
        "auto picks best": f"{sum(r['auto picks best'] for r in records)}/{n}",
        "auto within 0.005 of best": f"{sum(r['auto within 0.005 of best'] for r in records)}/{n}",
    }
    return out


def table(summ: dict) -> str:
    """One row per scene: each rung's, auto's, fast's and full's target SSIM (mean +- sd) and
    mean seconds, and how often auto stopped at the rung the truth says is best."""
    from twinfocus.focus.estimators import TWIN_RUNGS

    cols = [*TWIN_RUNGS, *MODELS]
    lines = [
        "| scene (uncorrected / oracle phase) | "
        + " | ".join(f"`{c}`" if c in TWIN_RUNGS else f"**{c}**" for c in cols)
        + " | auto at the best rung |",
        "|---" * (len(cols) + 2) + "|",
    ]
    for scene, s in summ.items():
        if scene == "all scenes":
            continue
        cells = []
        for c in cols:
            v = s[c] if c in MODELS else s["rungs"].get(c)
            if v is None:
                cells.append("—")
                continue
            picks = f", {'/'.join(sorted(set(v['results'])))}" if c in MODELS else ""
            cells.append(f"{v['ssim_mean']:.3f} ± {v['ssim_sd']:.3f} ({v['time_s_mean']:.1f} s{picks})")
        lines.append(
            f"| {scene} ({s['uncorrected']:.3f} / {s['oracle phase']:.3f}) | "
            + " | ".join(cells)
            + f" | {s['auto picks best']} (within 0.005: {s['auto within 0.005 of best']}) |"
        )
    return "\n".join(lines)


def figure(summ: dict, path: Path) -> None:
    from twinfocus.io.png import pyplot

    plt = pyplot()
    scenes = {k: v for k, v in summ.items() if k != "all scenes"}
    fig, axes = plt.subplots(1, len(scenes), figsize=(3.2 * len(scenes), 3.4), squeeze=False)
    for ax, (scene, s) in zip(axes[0], scenes.items()):
        pts = [(v["time_s_mean"], v["ssim_mean"], n) for n, v in s["rungs"].items()]
        frontier, best = [], -1.0
        for t, q, n in sorted(pts):
            ax.plot(t, q, "o", color="tab:blue", ms=4)
            ax.annotate(n, (t, q), fontsize=6, xytext=(2, 2), textcoords="offset points")
            if q > best:
                frontier.append((t, q))
                best = q
        ax.step(*zip(*frontier), where="post", color="tab:blue", alpha=0.5, lw=1)
        for model, marker, colour in (
            ("auto", "*", "tab:red"),
            ("fast", "^", "tab:orange"),
            ("full", "s", "tab:green"),
        ):
            ax.errorbar(
                s[model]["time_s_mean"],
                s[model]["ssim_mean"],
                yerr=s[model]["ssim_sd"],
                fmt=marker,
                color=colour,
                ms=7,
                label=model,
            )
        ax.set_xscale("log")
        ax.set_title(scene, fontsize=8)
        ax.set_xlabel("time (s, loaded 2-core VM)", fontsize=7)
        ax.set_ylabel("target SSIM", fontsize=7)
        ax.tick_params(labelsize=6)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _draw(args: tuple) -> dict:
    t = time.perf_counter()
    rec = one_draw(*args)
    print(f"[model_ladder] {args[0]} draw {args[1]}: {time.perf_counter() - t:.0f} s", file=sys.stderr, flush=True)
    return rec


def main(
    out_dir: str | os.PathLike = "benchmarks/results",
    draws: int = 5,
    only: str | None = None,
    workers: int = 1,
    rerun: tuple[str, ...] | None = None,
) -> dict:
    """``rerun``: only these ``--model`` values, run again on the committed draws and put in
    place of theirs in ``model_ladder.json`` (the rest of each record kept)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    jobs = [(scene, seed, rerun) for scene in SCENES if not only or only in scene for seed in range(1, draws + 1)]
    earlier = json.loads((out_dir / "model_ladder.json").read_text()) if rerun else None
    t = time.perf_counter()
    records: list[dict] = []
    partial = out_dir / "model_ladder.partial.json"  # the draws so far, should the run be cut short
    from concurrent.futures import ProcessPoolExecutor, as_completed

    with ProcessPoolExecutor(max(workers, 1)) as pool:
        for done in as_completed([pool.submit(_draw, job) for job in jobs]):
            records.append(done.result())
            partial.write_text(json.dumps(records, default=float))
    records.sort(key=lambda r: (list(SCENES).index(r["scene"]), r["seed"]))
    partial.unlink()
    command = (
        f"python -m benchmarks.bench_model_ladder --draws {draws} --workers {workers} --columns {COLUMNS} "
        f"--rows {ROWS} --size {SIZE} --iterations {ITERATIONS}" + (f" --only '{only}'" if only else "")
    )
    if earlier is not None:
        assert rerun is not None
        fresh = {(r["scene"], r["seed"]): r for r in records}
        records = earlier["records"]
        for r in records:
            r.update({m: fresh[r["scene"], r["seed"]][m] for m in rerun if (r["scene"], r["seed"]) in fresh})
        command = f"{command}; then {command} --rerun {','.join(rerun)}"
    summ = summary(records)
    doc = {
        "command": command,
        "protocol": {
            "columns": COLUMNS,
            "rows": ROWS,
            "size_px": SIZE,
            "optimiser_iterations": ITERATIONS,
            "draws": draws,
            "wall_s": time.perf_counter() - t + (earlier["protocol"]["wall_s"] if earlier else 0),
            "note": "times on a loaded 2-core VM, shared with other work",
        },
        "summary": summ,
        "records": records,
    }
    (out_dir / "model_ladder.json").write_text(json.dumps(doc, indent=1, default=float))
    figure(summ, Path(__file__).resolve().parent.parent / "docs" / "figures" / "model_ladder.png")
    print(table(summ))
    return doc


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--draws", type=int, default=5)
    ap.add_argument("--only", help="scenes whose name holds this")
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--workers", type=int, default=1, help="draws run side by side (processes)")
    ap.add_argument("--columns", type=int, default=COLUMNS)
    ap.add_argument("--rows", type=int, default=ROWS)
    ap.add_argument("--size", type=int, default=SIZE)
    ap.add_argument("--iterations", type=int, default=ITERATIONS)
    ap.add_argument("--rerun", help="comma-separated --model values to run again on the committed draws")
    a = ap.parse_args()
    COLUMNS, ROWS, SIZE, ITERATIONS = a.columns, a.rows, a.size, a.iterations
    main(a.out, a.draws, a.only, a.workers, tuple(a.rerun.split(",")) if a.rerun else None)
