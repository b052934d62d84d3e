"""Where things are, evaluated: each way ``twinfocus focus`` finds what the user no longer types,
as a row against both regions typed.

``twinfocus bench where`` simulates scenes of the baseline letters with the realistic
impairments of the paper evaluation (:class:`twinfocus.simulation.scenario.Scenario`'s defaults: speckle,
10 dB noise, 0.5 mm x/y/z tracking error, a physical twin captured 1 mm off), and focuses each
with the physical twin (:meth:`twinfocus.focus.plan.FocusPlan.focus_scan`, one phase per position):

* ``typed``: both regions typed (the baseline of every other row);
* ``reference found``: the reference's region from a coarse search of the twin's own scan
  (:func:`twinfocus.focus.reference_search.region_from_scan`);
* ``depth found``: the target's x/y box alone, its depth searched over the reference's +- 25 cm
  (:func:`twinfocus.imaging.depth_search.find_target_depth`);
* ``depth 5 cm off``: the target's depth typed 5 cm too far and searched within +- 10 cm;
* ``both found``: only the target's x/y box typed: the reference's region as in ``reference
  found``, the target's depth as in ``depth found`` (around the found reference's depth);
* ``best of two twins``: the reference's twin and another letter's twin as candidates, the
  better scored (:func:`twinfocus.focus.reference_search.candidate_score`) used.

Each row records the target SSIM against the truth image (as metrics.json's
``target_ssim_corrected``), the depth error for the depth rows and whether the right twin was
chosen. The report: one table row each, with its mean SSIM and its difference from ``typed``.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from twinfocus.evaluation.experiments import BASELINE_LETTERS
from twinfocus.imaging.grid import ImageGrid
from twinfocus.io.atomic import write_json_atomic, write_text_atomic

ROWS = ("typed", "reference found", "depth found", "depth 5 cm off", "both found", "best of two twins")
ROW_TEXT = {
    "typed": "both regions typed (X0 X1 Y0 Y1 Z each)",
    "reference found": "reference region from the twin's scan (--reference-roi left out)",
    "depth found": "target's x/y box only (--target-roi X0 X1 Y0 Y1)",
    "depth 5 cm off": "target's Z typed 5 cm too far, --refine-depth 0.1",
    "both found": "target's x/y box only, --reference-roi left out",
    "best of two twins": "two --template-scan candidates (the reference's, another letter's)",
}
#: (reference, target) pairs of the baseline letters; the quick run takes the first
PAIRS = tuple(zip(BASELINE_LETTERS, BASELINE_LETTERS[1:] + BASELINE_LETTERS[:1]))
#: the depth error a depth row's target SSIM starts to pay for, metres: a row is read against it
DEPTH_OFF_M = 0.05


def where_case(
    reference: str, target: str, seed: int, *, size: int = 48, iterations: int = 150, rows: int = 40, columns: int = 3
) -> list[dict]:
    """Every row of :data:`ROWS` on one simulated scene: one record each with ``row``,
    ``ssim``, ``seconds`` and, per row, ``depth_error_m``, ``reference_roi``, ``right_twin``."""
    from twinfocus.focus.autofocus import AutofocusConfig  # lazy: scipy.fft (+0.8 s at import)
    from twinfocus.focus.pipeline import Reference  # lazy: numba, scipy.fft (+2.1 s at import)
    from twinfocus.focus.plan import FocusPlan  # lazy: numba, scipy.fft (+2.1 s at import)
    from twinfocus.focus.reference_search import (  # lazy: twinfocus.focus (+0.03 s on twinfocus bench --help)
        candidate_score,
        region_from_scan,
    )
    from twinfocus.imaging.depth_search import (  # lazy: twinfocus.imaging.depth_search (+0.03 s on twinfocus bench --help)
        default_range,
        find_target_depth,
        range_to_search,
    )
    from twinfocus.simulation.scenario import (  # lazy: numba, cv2 (+2.1 s at import)
        Scenario,
        scenario_grids,
        simulate_scenario,
        template_scan,
    )
    from twinfocus.twins.templates import template_from_scan  # lazy: numba (+2.1 s at import)

    sc = Scenario(reference=reference, target=target, seed=seed, n_columns=columns, n_rows=rows)
    scan, twin = simulate_scenario(sc)
    ref_grid, tgt_grid = scenario_grids(sc, size)
    cfg = AutofocusConfig(iterations=iterations)
    box, true_z = tgt_grid.roi[:4], tgt_grid.z

    def focus(ref: ImageGrid, twin_scan, tgt: ImageGrid | None = None, depth_range=None) -> tuple[dict, ImageGrid]:
        reference = Reference(template_from_scan(twin_scan, ref, keep_phase=True))
        run = FocusPlan.make(config=cfg, space_variant="off").focuser(ref, reference)
        if depth_range is not None:
            search, _ = find_target_depth(run, scan, box, depth_range, "twin", {})
            tgt = ImageGrid.from_roi((*box, search.depth_m), size)
        assert tgt is not None
        return run(scan, target_grid=tgt).metrics, tgt

    records = []

    def record(row: str, t0: float, metrics: dict, **extra) -> None:
        records.append(
            {"row": row, "ssim": float(metrics["target_ssim_corrected"]), "seconds": time.perf_counter() - t0, **extra}
        )

    t = time.perf_counter()
    typed, _ = focus(ref_grid, twin, tgt_grid)
    record("typed", t, typed)
    t = time.perf_counter()
    roi, _ = region_from_scan(twin.data, twin.positions, twin.chirp)
    m, _ = focus(ImageGrid.from_roi(roi, size), twin, tgt_grid)
    record("reference found", t, m, reference_roi=list(roi))
    for row, depth_range in (
        ("depth found", default_range(ref_grid.z)),
        ("depth 5 cm off", range_to_search(true_z + DEPTH_OFF_M, 0.1, ref_grid.z)),
    ):
        t = time.perf_counter()
        m, tgt = focus(ref_grid, twin, depth_range=depth_range)
        record(row, t, m, depth_error_m=float(tgt.z - true_z))
    t = time.perf_counter()  # the reference's region as found above
    m, tgt = focus(ImageGrid.from_roi(roi, size), twin, depth_range=default_range(roi[4]))
    record("both found", t, m, reference_roi=list(roi), depth_error_m=float(tgt.z - true_z))
    t = time.perf_counter()
    other = BASELINE_LETTERS[(BASELINE_LETTERS.index(reference) + 3) % len(BASELINE_LETTERS)]
    wrong = template_scan(replace(sc, reference=other if other != target else BASELINE_LETTERS[0]), scan.chirp)
    wrong_m, _ = focus(ref_grid, wrong, tgt_grid)
    scores = [candidate_score(typed["confidence"]), candidate_score(wrong_m["confidence"])]
    chosen = typed if scores[0] >= scores[1] else wrong_m
    record("best of two twins", t, chosen, right_twin=bool(scores[0] >= scores[1]), scores=scores)
    for r in records:
        r.update(reference=reference, target=target, seed=seed)
    return records


def summarise(records: list[dict]) -> dict:
    """{row: {"mean_ssim", "minus_typed" (mean over scenes of the row's SSIM less the typed
    one's), "n", "seconds", and "depth_error_mm" (mean |error|) or "right_twin" (share)}}."""
    typed = {(r["reference"], r["target"], r["seed"]): r["ssim"] for r in records if r["row"] == "typed"}
    out = {}
    for row in ROWS:
        rs = [r for r in records if r["row"] == row]
        if not rs:
            continue
        s = {
            "mean_ssim": float(np.mean([r["ssim"] for r in rs])),
            "minus_typed": float(np.mean([r["ssim"] - typed[(r["reference"], r["target"], r["seed"])] for r in rs])),
            "n": len(rs),
            "seconds": float(np.mean([r["seconds"] for r in rs])),
        }
        if "depth_error_m" in rs[0]:
            s["depth_error_mm"] = float(np.mean([abs(r["depth_error_m"]) for r in rs]) * 1e3)
        if "right_twin" in rs[0]:
            s["right_twin"] = float(np.mean([r["right_twin"] for r in rs]))
        out[row] = s
    return out


def where_markdown(doc: dict) -> str:
    """The report: one table row per :data:`ROWS` entry."""
    lines = [
        "# Where things are: focus given less to type",
        "",
        f"{doc['scenes']} simulated scene(s) (pairs {', '.join('>'.join(p) for p in doc['pairs'])}; "
        f"{doc['settings']['columns']} x {doc['settings']['rows']} positions, {doc['settings']['size']} x "
        f"{doc['settings']['size']} pixels), physical twin. Command: `{doc['command']}`.",
        "",
        "| row | what is typed | mean target SSIM | less typed | depth error (mm) | right twin | seconds |",
        "|---|---|---|---|---|---|---|",
    ]
    for row, s in doc["summary"].items():
        depth = f"{s['depth_error_mm']:.1f}" if "depth_error_mm" in s else ""
        right = f"{s['right_twin']:.0%}" if "right_twin" in s else ""
        lines.append(
            f"| {row} | {ROW_TEXT[row]} | {s['mean_ssim']:.3f} | {s['minus_typed']:+.3f} | {depth} | {right} | "
            f"{s['seconds']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def run_where(
    out_dir: str,
    *,
    draws: int = 1,
    quick: bool = False,
    markdown: str | None = None,
    command: str | None = None,
    log=None,
) -> str:
    """Run :func:`where_case` on the pairs (the first only with ``quick``) x ``draws`` seeds;
    write ``OUT/raw/where.json`` and the report (``OUT/report.md`` unless ``markdown``); return
    the report."""
    from twinfocus.jobs.machine import machine_info  # lazy: twinfocus.jobs (+0.05 s on twinfocus bench --help)

    say = log or (lambda msg: None)
    pairs = PAIRS[:1] if quick else PAIRS
    settings = {"size": 32, "iterations": 60, "rows": 30, "columns": 3} if quick else {}
    settings = {"size": 48, "iterations": 150, "rows": 40, "columns": 3, **settings}
    records = []
    for ref, tgt in pairs:
        for seed in range(int(draws)):
            say(f"[where] {ref} > {tgt}, draw {seed}")
            records += where_case(ref, tgt, seed, **settings)
    doc = {
        "command": command or "twinfocus bench where",
        "machine": machine_info(),
        "settings": settings,
        "pairs": [list(p) for p in pairs],
        "scenes": len(pairs) * int(draws),
        "records": records,
        "summary": summarise(records),
    }
    write_json_atomic(Path(out_dir) / "raw" / "where.json", doc)
    return write_where_report(out_dir, markdown)


def write_where_report(out_dir: str, markdown: str | None = None) -> str:
    """The report from ``OUT/raw/where.json``, written to ``markdown`` (default ``OUT/report.md``)."""
    doc = json.loads((Path(out_dir) / "raw" / "where.json").read_text())
    md = where_markdown(doc)
    write_text_atomic(markdown or Path(out_dir) / "report.md", md)
    return md
