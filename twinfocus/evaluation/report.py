"""The evaluation report: markdown tables, PNG figures and a summary JSON from the raw results.

:func:`write_report` reads ``OUT/raw/*.json`` (written by :mod:`twinfocus.evaluation.runner`),
aggregates the records with :mod:`twinfocus.evaluation.aggregate` (mean SSIM and its standard error
per condition and method, improvement over no correction as the ratio of paired means, as the
paper's +23.3 % = 0.74 / 0.60 - 1), draws the figures with :mod:`twinfocus.evaluation.figures`, and
writes ``report.md`` (or the path given), one PNG per figure beside it and ``summary.json``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from twinfocus.evaluation.aggregate import (
    HELP_THRESHOLD,
    METHOD_NAMES,
    METHOD_ORDER,
    conditions_of,
    crossing,
    draw_values,
    limit_rows,
    mean_sd,
    method_mean,
    method_stats,
    methods_in,
    pair_improvements,
    stops_helping,
    trade_means,
)
from twinfocus.evaluation.experiments import LIMIT_SWEEPS
from twinfocus.evaluation.figures import (
    baseline_figure,
    examples_figure,
    limit_figure,
    pairs_figure,
    pareto_figure,
    sweep_figure,
)
from twinfocus.evaluation.paper import PAPER, PAPER_TABLE1
from twinfocus.io.arrays import load_npz
from twinfocus.io.atomic import write_json_atomic, write_text_atomic

SECTION_ORDER = (
    "baseline",
    "tracking_error",
    "separation",
    "distance",
    "size",
    "material",
    "nlos",
    "environment",
    "handheld",
    "size_ratio",
)
#: What the simulation does and does not model for an experiment, printed under its table.
SECTION_NOTES = {
    "nlos": "In this simulator a sheet is a two-way attenuation of the target's returns (polyester 2 dB, paper and "
    "plastic 3 dB, one ray per scatterer); it neither reflects nor refracts. After max-normalisation and the "
    "back-projection's integration gain a uniform 2-3 dB loss changes almost nothing, so the three sheets give "
    "nearly the same numbers: the experiment checks that the phase transfer does not depend on the target being "
    "visible, not how real sheets distort.",
    "environment": "The cluttered room fills a box from 3 cm in front of the letters to 60 cm behind them with 2,000 weak "
    "(0.1) and 40 strong (0.5) point scatterers, so some of it falls inside the image plane's range cell; "
    "the room of `Clutter.room` (from 5 cm behind) would not show in the images at all. Multipath between "
    "objects is not simulated. The digital twin does not depend on the room.",
    "handheld": "The true path is a simulated hand sweep (uneven speed, 2-3 mm wander, 1 deg tilt); the tracker's error "
    "is VIO-like: random-walk drift (about 1.8 mm in z after the sweep) plus white jitter, on x, y and z.",
}


def load_raw(raw_dir: Path) -> dict:
    """{name: result} of every ``*.json`` in ``raw_dir``."""
    return {p.stem: json.loads(p.read_text()) for p in sorted(Path(raw_dir).glob("*.json"))}


# --- formatting ------------------------------------------------------------------------------------


def _f(v, digits=3) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _pct(v) -> str:
    return "-" if v is None else f"{v:+.1f} %"


def _mean_sd_cell(mean: float | None, sd: float | None) -> str:
    """The cell "mean ± sd", or the mean alone (one sample: no sd)."""
    return _f(mean) + ("" if sd is None or mean is None else f" ± {sd:.3f}")


def _ssim_cell(e: dict | None) -> str:
    if not e or e.get("mean") is None:
        return "failed" if e and e.get("failed") else "-"
    s = _mean_sd_cell(e["mean"], e.get("sd"))
    if e.get("improvement_pct") is not None:
        s += f" ({e['improvement_pct']:+.1f} %)"
    if e.get("failed"):
        s += f" [{e['failed']} failed]"
    return s


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"] + [
        "| " + " | ".join(str(c) for c in row) + " |" for row in rows
    ]


# --- the report ------------------------------------------------------------------------------------


def _rel(path: Path, md: Path) -> str:
    return os.path.relpath(path, md.parent).replace(os.sep, "/")


def _paper_cell(name: str, label: str, method: str) -> str:
    imp = PAPER.get(name, {}).get("improvement_pct", {})
    if label in imp and isinstance(imp[label], dict):
        v = imp[label].get(method)
        return "-" if v is None else f"{v:+.1f} %"
    for k, v in imp.items():
        if isinstance(v, dict) and label.startswith(k):
            return "-" if v.get(method) is None else f"{v[method]:+.1f} %"
    return "-"


def _section_sweep(name: str, doc: dict, out: Path, md: Path, lines: list[str]) -> dict:
    d = doc["definition"]
    rec = doc["records"]
    paper = PAPER.get(name, {})
    methods = methods_in(rec)
    lines += [f"### {d['title']} ({paper.get('figure', '')})", ""]
    if paper:
        lines += [f"Paper: {paper['setup']}. *{paper['claim']}.*", ""]
    roi = (
        "the paper's regions of interest (architecture.md section 2)"
        if d["roi"] == "paper"
        else f"regions of interest framing each letter with {d['roi'].split('+')[-1]} of margin (up to the middle of the gap between the letters)"
    )
    lines += [
        f"Ours: {len({(r['pair'], r['condition'], r['draw']) for r in rec})} draws "
        f"({d['draws']} per pair and condition), pairs {', '.join(sorted({r['pair'] for r in rec}))}; {roi}.",
        "",
    ]
    note = SECTION_NOTES.get(name)
    if note:
        lines += [note, ""]
    header = (
        ["condition", "n"]
        + [f"{METHOD_NAMES[m]} SSIM (gain)" for m in methods]
        + ["HOG sim. " + " / ".join(METHOD_NAMES[m].split()[0] for m in methods)]
    )
    has_paper_numbers = any(isinstance(v, dict) for v in paper.get("improvement_pct", {}).values())
    if has_paper_numbers:
        header += ["paper gain (digital / physical)"]
    rows = []
    summary = {}
    for c in conditions_of(doc):
        st = method_stats(rec, c["label"])
        summary[c["label"]] = st
        label = c["label"] + ("" if c["in_paper"] else " *(beyond paper)*")
        row = [label, str(max((e["n"] for e in st.values()), default=0))] + [_ssim_cell(st.get(m)) for m in methods]
        row.append(" / ".join(_f(st.get(m, {}).get("hog"), 2) for m in methods))
        if has_paper_numbers:
            row.append(f"{_paper_cell(name, c['label'], 'digital')} / {_paper_cell(name, c['label'], 'physical')}")
        rows.append(row)
    lines += _table(header, rows) + [""]
    fig = out / f"{name}.png"
    sweep_figure(doc, fig)
    lines += [f"![{d['title']}]({_rel(fig, md)})", ""]
    fails = [s["notes"]["digital_error"] for s in doc.get("scenes", []) if s.get("notes", {}).get("digital_error")]
    if fails:
        lines += [f"Digital twin failed on {len(fails)} scene(s): {fails[0]}", ""]
    ex = out / "raw" / f"{name}_examples.npz"
    if ex.exists() and name != "baseline":
        z = load_npz(ex)
        meta = json.loads(str(z.pop("meta")))
        p = out / f"{name}_examples.png"
        examples_figure(z, p, f"{meta['pair']}, {meta['condition']}")
        lines += [f"![examples]({_rel(p, md)})", ""]
    return summary


def _section_baseline(doc: dict, out: Path, md: Path, lines: list[str]) -> dict:
    rec = doc["records"]
    cond = conditions_of(doc)[0]["label"]
    st = method_stats(rec, cond)
    paper = PAPER["baseline"]
    n_draws = len({(r["pair"], r["draw"]) for r in rec})
    lines += [
        f"### Baseline set ({paper['figure']})",
        "",
        f"Paper: {paper['setup']}.",
        "",
        f"Ours: {n_draws} samples = {len({r['pair'] for r in rec})} ordered pairs x {doc['definition']['draws']} "
        f"error draw(s), simulated with speckle, 10 dB thermal noise, x/y/z tracking error sigma 0.5 mm, "
        f"physical twin captured separately with a 1 mm placement error, digital twin from the rendered stereo pair.",
        "",
    ]
    rows = []
    for m in METHOD_ORDER:
        if m not in st:
            continue
        e = st[m]
        raw_ssim = method_mean(rec, cond, m, "ssim_as_estimated")
        e["ssim_ramp_kept"] = raw_ssim  # the summary holds every figure of the table
        rows.append(
            [
                METHOD_NAMES[m],
                _f(paper["ssim"].get(m), 2),
                _pct(paper["improvement_pct"].get(m)) if m != "none" else "-",
                _mean_sd_cell(e["mean"], e.get("sd")),
                _pct(e.get("improvement_pct")) if m != "none" else "-",
                _f(raw_ssim),
                _f(e["hog"]),
                f"{e['n']}" + (f" ({e['failed']} failed)" if e["failed"] else ""),
            ]
        )
    for field, lab in (
        ("ssim_oracle_transfer", "ceiling: reference's true phase transferred"),
        ("ssim_oracle_target", "ceiling: target's true phase"),
    ):
        v, sd = mean_sd(draw_values(rec, cond, field))
        none = st.get("none", {}).get("mean")
        gain = None if (v is None or not none) else (v / none - 1) * 100
        st[field] = {"mean": v, "sd": sd, "improvement_pct": gain}
        rows.append(
            [
                f"*{lab}*",
                "-",
                "-",
                _mean_sd_cell(v, sd),
                _pct(gain),
                "-",
                "-",
                str(n_draws),
            ]
        )
    lines += _table(
        [
            "method",
            "paper SSIM",
            "paper gain",
            "our SSIM (mean ± sd)",
            "our gain",
            "our SSIM, ramp kept",
            "our HOG sim.",
            "n",
        ],
        rows,
    ) + [""]
    lines += [
        "*Ramp kept*: the estimated phase transferred as it is, as the paper does; our default (`twinfocus focus`) "
        "first removes its best constant + linear-in-aperture ramp, which only moves the image and which a misplaced "
        "template pulls in.",
        "",
    ]
    fig = out / "baseline.png"
    baseline_figure(doc, fig)
    lines += [f"![baseline]({_rel(fig, md)})", ""]
    st["shapes_median_improvement_pct"] = _section_shapes(doc, out, md, lines)
    _baseline_examples(out, md, lines)
    return st


def _section_shapes(doc: dict, out: Path, md: Path, lines: list[str]) -> dict:
    """Shapes (Fig. 13): each method's improvement per reference-target pair, and its figure.
    Returns {method: median improvement over the pairs, %}."""
    medians = {}
    rec = doc["records"]
    sp = PAPER["shapes"]
    rows = []
    for m in ("digital", "physical"):
        imp = pair_improvements(rec, m)
        if not imp:
            continue
        gains = np.array(list(imp.values()))
        medians[m] = float(np.median(gains))
        worst = min(imp, key=imp.__getitem__)
        rows.append(
            [
                METHOD_NAMES[m],
                _pct(sp["median_improvement_pct"][m]),
                _pct(float(np.median(gains))),
                f"{int((gains > 0).sum())} / {gains.size}",
                f"{worst} ({imp[worst]:+.1f} %)",
            ]
        )
    if rows:
        lines += [f"**Shapes ({sp['figure']})**: improvement per reference-target pair.", ""]
        lines += _table(["method", "paper median", "our median", "pairs improved", "worst pair"], rows) + [""]
        fig = out / "baseline_pairs.png"
        pairs_figure(doc, fig)
        lines += [f"![pairs]({_rel(fig, md)})", ""]
    return medians


def _baseline_examples(out: Path, md: Path, lines: list[str]) -> None:
    """The baseline's example images of one draw, when the run saved them."""
    ex = out / "raw" / "baseline_examples.npz"
    if ex.exists():
        z = load_npz(ex)
        meta = json.loads(str(z.pop("meta")))
        p = out / "baseline_examples.png"
        examples_figure(z, p, f"Target {meta['pair'].split('>')[1]} (reference {meta['pair'].split('>')[0]}), one draw")
        lines += [f"![examples]({_rel(p, md)})", ""]


def _section_limits(raw: dict, out: Path, md: Path, lines: list[str]) -> dict:
    res: dict = {}
    lines += [
        "## Limits: where each method stops helping",
        "",
        "architecture.md section 1: to first order a position error dp changes the phase of a scatterer seen along the unit "
        "line of sight u by (4 pi / lambda) u . dp, so the correction estimated on the reference and applied to the "
        "target leaves (4 pi / lambda) (u_ref - u_tgt) . dp, at most (4 pi / lambda) |u_ref - u_tgt| |dp|. Every "
        "draw records this *first-order prediction* and *bound* (r.m.s. over radar positions), the *measured transfer "
        "floor* (the exact phase at the reference's centre applied to the target, against the exact phase at the "
        "target), and the SSIM a perfect reference estimate would give (*perfect reference estimate*, the ceiling of "
        "any twin method). The gains are SSIM differences, not percentages. A method stops helping where its mean SSIM gain over no "
        "correction falls below "
        f"{HELP_THRESHOLD}. For the size sweep the floor is taken at the target's corner farthest from the reference.",
        "",
    ]
    for name, what in LIMIT_SWEEPS.items():
        if name not in raw:
            continue
        doc = raw[name]
        rows = limit_rows(doc)
        methods = [m for m in ("digital", "physical") if any(m in r["stats"] for r in rows)]
        lines += [f"### {what.capitalize()} ({doc['definition']['axis']})", ""]
        tab = []
        for r in rows:
            tab.append(
                [r["label"] + ("" if r["in_paper"] else " *(beyond paper)*")]
                + [f"{_f(r['stats'].get(m, {}).get('gain'))}" for m in methods]
                + [_f(r["ceiling_gain"]), _f(r["transfer_loss"])]
                + [_f(r["estimation_loss"].get(m)) for m in methods]
                + [_f(r["uncorrected"], 2), _f(r["floor"], 2), _f(r["first_order"], 2), _f(r["bound"], 2)]
            )
        lines += _table(
            ["condition"]
            + [f"{METHOD_NAMES[m]} gain" for m in methods]
            + ["perfect-reference gain", "transfer loss"]
            + [f"{METHOD_NAMES[m]} estimation loss" for m in methods]
            + ["uncorrected rad", "transfer floor rad", "first-order rad", "bound rad"],
            tab,
        ) + [""]
        xs = [r["x"] for r in rows]
        floor_x = crossing(xs, [r["floor"] for r in rows], 1.0)
        sentences = []
        # the table's losses, for pages that quote them (docs/explanation/ceilings.md)
        res[name] = {
            "rows": [
                {k: r[k] for k in ("x", "label", "ceiling_gain", "transfer_loss", "estimation_loss")} for r in rows
            ]
        }
        for m in methods:
            s = stops_helping(rows, m)
            res[name][m] = s
            if s["x"] is None:
                sentences.append(
                    f"the {METHOD_NAMES[m]} helps over the whole sweep (gain >= {HELP_THRESHOLD} up to {rows[-1]['label']})"
                )
            else:
                sentences.append(f"the {METHOD_NAMES[m]} stops helping at {s['label']} (gain {s['gain']:+.3f})")
        lines += [
            "Measured: "
            + "; ".join(sentences)
            + ". "
            + (
                f"The measured transfer floor reaches 1 rad r.m.s. near {floor_x:.3g} ({doc['definition']['axis']})."
                if floor_x is not None
                else "The measured transfer floor stays below 1 rad r.m.s. over the sweep."
            )
            + " *Transfer loss* = SSIM with the target's exact phase minus SSIM with the reference's exact phase (what "
            "the separation costs even with a perfect reference estimate); *estimation loss* = the latter minus the "
            "twin's SSIM (what the estimate on the reference costs). Where the estimation loss grows while the "
            "transfer loss stays small, the reference estimate, not the transfer, is what fails.",
            "",
        ]
        fig = out / f"limits_{name}.png"
        limit_figure(doc, rows, fig)
        lines += [f"![limits {name}]({_rel(fig, md)})", ""]
    return res


def _section_trade(doc: dict, out: Path, md: Path, lines: list[str], machine: dict) -> dict:
    rows = doc["rows"]
    means = trade_means(rows)
    lines += [
        "## Speed/accuracy trade",
        "",
        "One knob at a time from the paper's configuration, physical-twin autofocus, on "
        f"{len({r['pair'] for r in rows})} scene(s) ({', '.join(sorted({r['pair'] for r in rows}))}), one tracking-error draw "
        "(sigma 0.5 mm) each. Time = reference sub-image basis + optimiser (+ template for the digital twin); SSIM of "
        "the 100 x 100 target focused with the estimated phase (for the array size: the target formed from the same "
        "positions, against its own truth). Means over the scenes.",
        "",
    ]
    for knob in ("image size", "positions", "optimiser", "precision", "digital twin", "preset"):
        ks = [m for m in means if m["knob"] == knob]
        if not ks:
            continue
        lines += [f"**{knob}**", ""]
        hdr = (
            ["setting", "basis s", "optimiser s"]
            + (["template s"] if knob == "digital twin" else [])
            + ["total s", "target SSIM", "HOG sim."]
        )
        tab = []
        for m in ks:
            tab.append(
                [m["label"], _f(m["reference_basis_s"], 2), _f(m["autofocus_s"], 2)]
                + ([_f(m["template_s"], 2)] if knob == "digital twin" else [])
                + [_f(m["time_s"], 2), _f(m["ssim"]), _f(m["hog"])]
            )
        lines += _table(hdr, tab) + [""]
    unc = [m for m in means if m["knob"] == "uncorrected"]
    if unc:
        lines += [f"No correction: target SSIM {unc[0]['ssim']:.3f}.", ""]
    fig = out / "pareto.png"
    pareto_figure(means, fig)
    lines += [f"![pareto]({_rel(fig, md)})", ""]
    presets = doc.get("presets", {})
    if presets:
        _presets_table(presets, means, lines)
    _table1(doc, rows, means, machine, lines)
    return {"means": means, "presets": presets}


def _presets_table(presets: dict, means: list, lines: list[str]) -> None:
    """The recommended presets, as measured, with the ``twinfocus focus`` options that give each."""
    lines += [
        "**Recommended presets** (per knob, the cheapest setting within 0.02 (fast) or 0.003 (accurate) of that "
        "knob's best mean SSIM, combined and measured):",
        "",
    ]
    tab = []
    for name, p in presets.items():
        measured = next((x for x in means if x["knob"] == "preset" and x["label"] == name), None)
        coarse = p.get("coarse_iterations", 0)
        cli = f"`--size {p['size']} --iterations {p['iterations']} --lr {p['lr']:g} --basis-dtype {p['basis_dtype']}`"
        if p["precision"] != "float32":
            cli = cli[:-1] + f" --precision {p['precision']}`"
        if coarse:
            cli = cli[:-1] + f" --coarse-iterations {coarse}`"
        tab.append(
            [
                name,
                f"{p['size']} x {p['size']}",
                str(p["iterations"]),
                str(coarse),
                f"{p['lr']:g}",
                p["basis_dtype"],
                p["precision"],
                _f(measured["time_s"] if measured else None, 2),
                _f(measured["ssim"] if measured else None),
                cli,
            ]
        )
    lines += _table(
        [
            "preset",
            "reference image",
            "iterations",
            "coarse it.",
            "lr",
            "basis",
            "arithmetic",
            "total s",
            "target SSIM",
            "`twinfocus focus` options",
        ],
        tab,
    ) + [""]
    lines += [
        "`--size` sets both regions in `twinfocus focus`; the estimated phase focuses a target image of any size "
        "(the table's SSIM is on the 100 x 100 target). The choice rests on the scene(s) above: rerun with "
        "`--trade-scenes 2` before relying on it.",
        "",
    ]


def _table1(doc: dict, rows: list, means: list, machine: dict, lines: list[str]) -> None:
    """The paper's Table 1 row by row beside our seconds."""

    def af(knob, label):
        m = next((x for x in means if x["knob"] == knob and x["label"] == label), None)
        return None if m is None else m["autofocus_s"]

    dt = [r for r in rows if r["knob"] == "digital twin" and r.get("status") == "ok"]

    def stage(key):
        vals = [r["stages_s"][key] for r in dt if key in r.get("stages_s", {})]
        return float(np.mean(vals)) if vals else None

    def tmpl(value):
        vals = [r["template_s"] for r in dt if r["value"] == value]
        return float(np.mean(vals)) if vals else None

    t1 = []
    for s, v in PAPER_TABLE1["image_size"].items():
        t1.append([f"optimisation, image {s} x {s} (780 x 86)", f"{v:.2f}", _f(af("image size", f"{s} x {s}"), 2)])
    for n, v in PAPER_TABLE1["array_size"].items():
        t1.append([f"optimisation, array {n} x 86 (100 x 100)", f"{v:.2f}", _f(af("positions", f"{n} x 86"), 2)])
    t1.append(
        [
            "digital twin: visual segmentation",
            f"{PAPER_TABLE1['digital_twin']['visual segmentation']:.2f}",
            _f(stage("segmentation"), 2),
        ]
    )
    t1.append(
        [
            "digital twin: point cloud extraction",
            f"{PAPER_TABLE1['digital_twin']['point cloud extraction']:.2f}",
            _f(stage("point_cloud"), 2),
        ]
    )
    t1.append(["digital twin: stereo disparity (inside the ZED SDK in the paper)", "-", _f(stage("disparity"), 2)])
    t1.append(
        [
            "digital twin: array signal simulation, exact (simulate + back-project)",
            f"{PAPER_TABLE1['digital_twin']['array signal simulation']:.2f}",
            _f(tmpl("exact"), 2),
        ]
    )
    t1.append(["digital twin: array signal simulation, PSF convolution (our default)", "-", _f(tmpl("psf"), 2)])
    hw = machine.get("cpu_model") or "this machine"
    lines += [
        "**Table 1 of the paper, row by row** (seconds; paper: NVIDIA RTX 4090; ours: "
        f"{hw}, {machine.get('cpu_count')} cores, {'GPU ' + machine['cuda'] if machine.get('cuda') else 'no GPU'}, "
        f"optimiser with {doc['settings']['basis_dtype']} basis storage, 300 iterations):",
        "",
    ]
    lines += _table(["operation", "paper s", "ours s"], t1) + [""]


def _field_cell(recs: list, key: str) -> str:
    """The cell of ``key`` over the draws that have it: mean ± sd, the value alone for one draw."""
    return _mean_sd_cell(*mean_sd(np.array([r[key] for r in recs if key in r])))


#: the field section's tables: (file beside the raw results, intro, [(column, record key)])
_FIELD_TABLES = (
    (
        "field_handheld.json",
        "**Physical twin under a hand's drift** (H/S 16 degrees apart, 15 dB; hand = 0.8 mm Gauss-Markov drift "
        "on x/y/z over 2 s + 0.2 mm jitter + 0.15 degree array rotation):",
        [
            ("uncorrected", "uncorrected"),
            ("one phase per position", "closed_form_auto"),
            ("default (space-variant auto)", "default"),
            ("default, the scan's mean error taken out (diagnostic)", "default_mean_offset_removed"),
            ("reference's true phase", "reference_true_phase"),
            ("target's own phase", "ceiling_target_phase"),
        ],
    ),
    (
        "field_twin.json",
        "**Digital twin from a camera cloud of a rough reference** (A: 0.5 mm z, 15 dB; B: 1 mm z, 10 dB, target "
        "10 cm deeper; C: 1.6 mm z, 15 dB; cloud: 1 mm noise, 25 % holes, 2 % outliers, 2.5 mm offset):",
        [
            ("uncorrected", "uncorrected"),
            ("paper", "paper"),
            ("old auto", "old auto"),
            ("one outline", "outline, one"),
            ("default before growing the outline", "default, outline not grown"),
            ("default (outline grown, averaged, placed by the band's halves)", "default"),
            ("default, the reference's position from the truth (diagnostic)", "default, position from the truth"),
            ("physical twin", "physical twin"),
            ("target's own phase", "oracle phase"),
        ],
    ),
)


def _section_field(out: Path, lines: list) -> None:
    """Field conditions beyond the paper's protocol, from the benchmarks' figures copied beside
    the raw results (``field_handheld.json``: ``handheld.json`` of ``benchmarks.bench_handheld``, ``field_twin.json``
    from ``benchmarks.bench_field_twin``), when they are there."""
    present = [(out / name, intro, cols) for name, intro, cols in _FIELD_TABLES if (out / name).is_file()]
    if not present:
        return
    lines += [
        "## Field conditions: a hand's drift and rotation, camera clouds of rough references",
        "",
        "Beyond the paper's protocol (independent jitter along z). Target SSIM, mean ± sd over the draws, both "
        "ceilings on the same draws: the reference's true per-position phase transferred as is, and the target's "
        "own true phase. Details and commands: docs/handheld.md, docs/digital_twin.md.",
        "",
    ]
    for path, intro, cols in present:
        doc = json.loads(path.read_text())
        rows = [[cond, str(len(recs))] + [_field_cell(recs, key) for _, key in cols] for cond, recs in doc.items()]
        lines += [intro, ""]
        lines += _table(["condition", "draws"] + [name for name, _ in cols], rows) + [""]


def write_report(out_dir, markdown_path=None) -> Path:
    """Write the report from ``out_dir/raw``. Returns the markdown path (default ``out_dir/report.md``)."""
    out = Path(out_dir)
    raw_dir = out / "raw"

    raw = load_raw(raw_dir)
    run = raw.pop("run", {})
    md = Path(markdown_path) if markdown_path else out / "report.md"
    machine = run.get("machine", {})
    lines = ["# TwinFocus evaluation: the paper's experiments in simulation", ""]
    lines += [
        "This page is generated from the raw results in docs/results/raw/ by `twinfocus bench paper --report-only "
        "--out docs/results --markdown docs/results.md` (which also draws the figures beside it); an edit by hand is "
        "overwritten. To rerun the experiments: `make bench-paper` (= `twinfocus bench paper --draws 5 --workers 2 "
        "--out docs/results --markdown docs/results.md`: the paper's five error draws on two Dask workers; add "
        "`--resume` to keep finished experiments). "
        f"Last invocation: `{run.get('command') or 'twinfocus bench paper'}`.",
        "",
    ]
    total = sum(doc.get("seconds", 0.0) for doc in raw.values())
    per = ", ".join(f"{k} {v.get('seconds', 0) / 60:.1f} min" for k, v in raw.items())
    draws = {k: v["definition"]["draws"] for k, v in raw.items() if "draws" in v.get("definition", {})}
    if len(set(draws.values())) == 1:
        n = next(iter(draws.values()))
        per += f"; every experiment with {n} error draw{'s' if n > 1 else ''} per pair and condition"
    elif draws:
        per += "; error draws per pair and condition: " + ", ".join(f"{k} {d}" for k, d in draws.items())
    lines += [
        f"Machine: {machine.get('cpu_model', '?')}, {machine.get('cpu_count', '?')} cores "
        f"(shared with other jobs; load average {', '.join(f'{x:.1f}' for x in machine.get('load_average') or [])} at the start), "
        f"{'GPU ' + machine['cuda'] if machine.get('cuda') else 'no GPU'}, torch {machine.get('torch', '?')} "
        f"({machine.get('torch_threads', '?')} threads), Python {machine.get('python', '?')}.",
        "",
        f"Compute time: {total / 60:.1f} min in all ({per}). Last invocation started {run.get('started', '?')}.",
        "",
    ]
    settings: dict = next((doc["settings"] for doc in raw.values() if "settings" in doc), {})
    if settings:
        lines += [
            f"Settings: {settings.get('n_columns')} x {settings.get('n_rows')} radar positions x 86 channels, "
            f"{settings.get('size')} x {settings.get('size')} images, Adam lr 5e-2 with cosine annealing, "
            f"{settings.get('iterations')} iterations, basis stored as {settings.get('basis_dtype')}, "
            f"{settings.get('precision')} arithmetic"
            + (", **quick smoke settings**" if run.get("quick") else "")
            + ".",
            "",
        ]
    lines += [
        "Methods: *no correction*; *sharpness autofocus* (maximises sum I^2 / (sum I)^2 of the target itself, same "
        "optimiser); *physical twin* (template = the reference scanned alone on exact positions, 1 mm misplaced); "
        "*digital twin* (template simulated from the reference's point cloud, which the digital-twin pipeline "
        "extracts from a rendered ZED 2i-like stereo pair: SGBM disparity, classical segmentation, plane fit).",
        "",
        "Metrics: **SSIM** is the paper's (soft-thresholded, max-normalised target image against the image formed "
        "with the true positions). The paper's second metric, cosine similarity of ResNet features, needs downloaded "
        "network weights; in its place we report **HOG similarity**: the cosine similarity of Histogram-of-Oriented-"
        "Gradients descriptors (9 orientations, 8 px cells, 2 x 2-cell L2-Hys blocks) of the same two images: a "
        "weight-free descriptor of local edge structure that, like early CNN layers, ignores gain and sub-cell "
        "shifts. Gains are ratios of paired means (the paper's +23.3 % = 0.74 / 0.60 - 1). Every SSIM cell with more "
        "than one sample is mean ± sd (standard deviation over the n samples: pairs x draws; the mean's standard error "
        "is sd / sqrt(n)).",
        "",
        "Absolute SSIM levels are not comparable with the paper's: the paper's are measured on real data (real "
        "multipath, antenna patterns, specular letters), ours on point-scatterer simulation, and the soft threshold "
        "sigmoid(a - 0.4) compresses the display range, so SSIM of an uncorrected image depends strongly on how much "
        "energy the defocus spreads. Compare the ordering of methods, the gains and the trends.",
        "",
    ]
    summary: dict = {"run": run}
    if "baseline" in raw or any(k in raw for k in SECTION_ORDER):
        lines += ["## The paper's experiments, ours beside theirs", ""]
    for name in SECTION_ORDER:
        if name not in raw:
            continue
        if name == "baseline":
            summary[name] = _section_baseline(raw[name], out, md, lines)
        else:
            summary[name] = _section_sweep(name, raw[name], out, md, lines)
    summary["limits"] = _section_limits(raw, out, md, lines)
    _section_field(out, lines)
    if "trade" in raw:
        summary["trade"] = _section_trade(raw["trade"], out, md, lines, machine)
    write_text_atomic(md, "\n".join(lines) + "\n")
    write_json_atomic(out / "summary.json", summary)
    return md
