"""The evaluation report's figures: one PNG per sweep, the baseline and its pairs, example images,
the limits and the speed/accuracy trade, drawn with matplotlib (Agg) from the raw results and the
aggregates of :mod:`twinfocus.evaluation.aggregate`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from twinfocus.evaluation.aggregate import (
    HELP_THRESHOLD,
    METHOD_NAMES,
    METHOD_ORDER,
    conditions_of,
    method_stats,
    methods_in,
    ok_records,
    pair_improvements,
    pareto_front,
)
from twinfocus.evaluation.paper import PAPER
from twinfocus.io.atomic import atomic_writer
from twinfocus.io.png import pyplot

METHOD_COLOURS = {"none": "#777777", "sharpness": "#d08c2e", "digital": "#3b7dd8", "physical": "#c23b3b"}
DPI = 60


def _save(fig, path: Path) -> None:
    with atomic_writer(path) as f:
        fig.savefig(f, format="png", dpi=DPI, bbox_inches="tight")
    pyplot().close(fig)


def baseline_figure(doc: dict, path: Path) -> None:
    plt = pyplot()
    rec = doc["records"]
    cond = conditions_of(doc)[0]["label"]
    st = method_stats(rec, cond)
    methods = [m for m in METHOD_ORDER if m in st]
    fig, ax = plt.subplots(figsize=(5.2, 3.0))
    x = np.arange(len(methods))
    means = [st[m]["mean"] or 0 for m in methods]
    errs = [st[m]["sem"] or 0 for m in methods]
    ax.bar(x, means, yerr=errs, color=[METHOD_COLOURS[m] for m in methods], capsize=3, label="ours (simulation)")
    paper = PAPER["baseline"]["ssim"]
    px = [i for i, m in enumerate(methods) if m in paper]
    ax.plot(px, [paper[methods[i]] for i in px], "kD", label="paper (real data)")
    ax.set_xticks(x, [METHOD_NAMES[m] for m in methods], fontsize=8)
    ax.set_ylabel("mean target SSIM")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title("Baseline set: our simulation vs the paper", fontsize=9)
    _save(fig, path)


def pairs_figure(doc: dict, path: Path) -> None:
    plt = pyplot()
    rec = doc["records"]
    letters = sorted({r["reference"] for r in rec} | {r["target"] for r in rec})
    methods = [m for m in ("digital", "physical") if any(r["method"] == m for r in rec)]
    fig, axes = plt.subplots(1, len(methods), figsize=(3.0 * len(methods), 2.8), squeeze=False)
    for ax, m in zip(axes[0], methods):
        imp = pair_improvements(rec, m)
        grid = np.full((len(letters), len(letters)), np.nan)
        for pair, v in imp.items():
            r, t = pair.split(">")
            grid[letters.index(r), letters.index(t)] = v
        im = ax.imshow(grid, cmap="RdBu", vmin=-60, vmax=60)
        ax.set_xticks(range(len(letters)), letters)
        ax.set_yticks(range(len(letters)), letters)
        ax.set_xlabel("target")
        ax.set_ylabel("reference")
        ax.set_title(f"{METHOD_NAMES[m]}: SSIM gain %", fontsize=8)
        for i in range(len(letters)):
            for j in range(len(letters)):
                if np.isfinite(grid[i, j]):
                    ax.text(j, i, f"{grid[i, j]:.0f}", ha="center", va="center", fontsize=6)
    fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8)
    _save(fig, path)


def examples_figure(examples: dict, path: Path, title: str) -> None:
    plt = pyplot()
    keys = ["truth"] + [m for m in METHOD_ORDER if m in examples]
    fig, axes = plt.subplots(1, len(keys), figsize=(1.6 * len(keys), 1.9))
    for ax, k in zip(np.atleast_1d(axes), keys):
        ax.imshow(examples[k], cmap="gray", origin="upper")
        ax.set_title("true positions" if k == "truth" else METHOD_NAMES[k], fontsize=7)
        ax.axis("off")
    fig.suptitle(title, fontsize=8)
    _save(fig, path)


def sweep_figure(doc: dict, path: Path) -> None:
    plt = pyplot()
    d = doc["definition"]
    rec = doc["records"]
    conds = conditions_of(doc)
    methods = methods_in(rec)
    fig, ax = plt.subplots(figsize=(5.0, 3.0))
    if d["numeric"]:
        xs = [c["x"] for c in conds]
        for m in methods:
            st = [method_stats(rec, c["label"]).get(m, {}) for c in conds]
            ys = [s.get("mean") if s else None for s in st]
            es = [s.get("sem") or 0 if s else 0 for s in st]
            ok = [i for i, y in enumerate(ys) if y is not None]
            ax.errorbar(
                [xs[i] for i in ok],
                [ys[i] for i in ok],
                yerr=[es[i] for i in ok],
                marker="o",
                ms=4,
                capsize=2,
                color=METHOD_COLOURS[m],
                label=METHOD_NAMES[m],
            )
        out = [c["x"] for c in conds if not c["in_paper"]]
        if out:
            inside = [c["x"] for c in conds if c["in_paper"]]
            lo_out = [x for x in out if not inside or x > max(inside)]
            hi_out = [x for x in out if inside and x < min(inside)]
            if lo_out:
                ax.axvspan(
                    max(inside) if inside else min(lo_out),
                    max(lo_out),
                    color="#eeeeee",
                    zorder=0,
                    label="beyond the paper",
                )
            if hi_out:
                ax.axvspan(min(hi_out), min(inside), color="#eeeeee", zorder=0)
        ax.set_xlabel(d["axis"])
    else:
        labels = [c["label"] for c in conds]
        w = 0.8 / max(1, len(methods))
        for k, m in enumerate(methods):
            st = [method_stats(rec, c["label"]).get(m, {}) for c in conds]
            ax.bar(
                np.arange(len(conds)) + (k - (len(methods) - 1) / 2) * w,
                [s.get("mean") or 0 for s in st],
                w,
                yerr=[s.get("sem") or 0 for s in st],
                capsize=2,
                color=METHOD_COLOURS[m],
                label=METHOD_NAMES[m],
            )
        ax.set_xticks(np.arange(len(conds)), [lab.replace(", ", ",\n") for lab in labels], fontsize=7)
    ax.set_ylabel("mean target SSIM")
    lo = min([r["ssim"] for r in ok_records(rec)] or [0.0])
    ax.set_ylim(max(0.0, lo - 0.1), 1.0)
    ax.legend(fontsize=7, loc="lower left")
    ax.set_title(d["title"], fontsize=9)
    _save(fig, path)


def limit_figure(doc: dict, rows: list[dict], path: Path) -> None:
    plt = pyplot()
    d = doc["definition"]
    xs = [r["x"] for r in rows]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(8.0, 3.0))
    for m in ("digital", "physical"):
        g = [r["stats"].get(m, {}).get("gain") for r in rows]
        ok = [i for i, v in enumerate(g) if v is not None]
        if ok:
            a1.plot([xs[i] for i in ok], [g[i] for i in ok], "o-", ms=4, color=METHOD_COLOURS[m], label=METHOD_NAMES[m])
    cg = [r["ceiling_gain"] for r in rows]
    ok = [i for i, v in enumerate(cg) if v is not None]
    a1.plot([xs[i] for i in ok], [cg[i] for i in ok], "k--", lw=1, label="perfect reference estimate")
    a1.axhline(0, color="#999999", lw=0.8)
    a1.axhline(HELP_THRESHOLD, color="#999999", lw=0.8, ls=":")
    a1.set_xlabel(d["axis"])
    a1.set_ylabel("SSIM gain over no correction")
    a1.legend(fontsize=7)
    for key, style, lab in (
        ("uncorrected", "s-", "uncorrected (target oracle)"),
        ("floor", "^-", "transfer floor (measured)"),
        ("first_order", ":", "first-order prediction"),
        ("bound", "--", "first-order bound"),
    ):
        v = [r[key] for r in rows]
        ok = [i for i, y in enumerate(v) if y is not None]
        a2.plot(
            [xs[i] for i in ok],
            [v[i] for i in ok],
            style,
            ms=4,
            lw=1,
            color="#555555" if key == "uncorrected" else "k",
            label=lab,
        )
    a2.axhline(1.0, color="#999999", lw=0.8, ls=":")
    a2.set_xlabel(d["axis"])
    a2.set_ylabel("r.m.s. phase error on the target (rad)")
    a2.legend(fontsize=6)
    fig.suptitle(f"Limits: {d['title']}", fontsize=9)
    _save(fig, path)


def pareto_figure(means: list[dict], path: Path) -> None:
    plt = pyplot()
    colours = {
        "image size": "#3b7dd8",
        "optimiser": "#c23b3b",
        "precision": "#2e9d57",
        "preset": "#000000",
        "positions": "#d08c2e",
        "digital twin": "#8a4fb5",
    }
    pts = [m for m in means if m["knob"] in ("image size", "optimiser", "precision", "preset")]
    fig, ax = plt.subplots(figsize=(6.0, 3.6))
    for knob in ("image size", "optimiser", "precision", "positions", "digital twin", "preset"):
        ks = [m for m in means if m["knob"] == knob]
        if not ks:
            continue
        ax.scatter(
            [m["time_s"] for m in ks],
            [m["ssim"] for m in ks],
            s=60 if knob == "preset" else 18,
            marker="*" if knob == "preset" else "o",
            color=colours[knob],
            label=knob,
            zorder=3,
        )
        for m in ks:
            ax.annotate(m["label"], (m["time_s"], m["ssim"]), fontsize=5, xytext=(2, 2), textcoords="offset points")
    if pts:
        front = pareto_front([(m["time_s"], m["ssim"]) for m in pts])
        ax.plot(
            [pts[i]["time_s"] for i in front],
            [pts[i]["ssim"] for i in front],
            "k-",
            lw=0.8,
            zorder=2,
            label="Pareto front",
        )
    unc = [m for m in means if m["knob"] == "uncorrected"]
    if unc:
        ax.axhline(unc[0]["ssim"], color="#777777", ls=":", lw=1, label="no correction")
    ax.set_xscale("log")
    ax.set_xlabel("time from scan to phase estimate (s): reference basis + optimiser")
    ax.set_ylabel("target SSIM (100 x 100)")
    ax.legend(fontsize=6, loc="lower right")
    ax.set_title("Speed/accuracy trade (physical twin)", fontsize=9)
    _save(fig, path)
