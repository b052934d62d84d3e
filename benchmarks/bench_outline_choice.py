"""How the outline estimator picks one of its starts' ends, on the same draws: the most energy
inside the outline ("energy"), the least contrast of that energy ("speckle") and the default rule
("auto": the most energy unless that end piled it; :data:`twinfocus.focus.template_match.OUTLINE_CHOICE`).

Draws of the digital-twin family bench (:mod:`benchmarks.bench_dtwin_family`: shapes, places,
camera clouds, conditions), each run once per surface of the family (smooth, rough, speckled), so
that each surface meets every shape and condition. Bench draws (seeds 1001 on, the bench's shapes)
are what the rule's threshold was chosen on; held-out draws (seeds 3001 on, the held-out shapes,
seeds no other bench uses) check it.

    python -m benchmarks.bench_outline_choice --draws 6 --workers 2              (bench draws)
    python -m benchmarks.bench_outline_choice --draws 4 --workers 2 --heldout    (held-out draws)

Writes ``outline_choice.json`` (``outline_choice_heldout.json``): per draw and choice the target
SSIM, the rule's pick and the seconds the digital twin took; prints mean target SSIM per surface
and choice.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from benchmarks.bench_dtwin_family import BENCH_SEED, BENCH_SHAPES, CONDITIONS, HELDOUT_SHAPES, SURFACES

CHOICES = ("energy", "speckle", "auto")
#: the held-out draws' first seed (the family bench's own held-out draws start at 2001)
HELDOUT_SEED = 3001


def one_draw(job: tuple) -> dict:
    """(condition, seed, surface, heldout) -> the record of each choice on that draw."""
    import torch

    from benchmarks.bench_dtwin_family import digital_twin_focus, draw_inputs
    from twinfocus.errors import TwinFocusError

    torch.set_num_threads(1)  # one draw per worker
    cond, seed, surface, heldout = job
    rec: dict = {"condition": cond, "seed": seed, "surface": surface}
    try:
        d = draw_inputs(cond, seed, HELDOUT_SHAPES if heldout else BENCH_SHAPES, 65, 64, surface=surface)
    except TwinFocusError as e:
        return {**rec, "refused": str(e)}
    rec.update(reference=d["kw"]["reference"], target=d["kw"]["target"])
    for choice in CHOICES:
        t0 = time.perf_counter()
        try:
            out = digital_twin_focus(d, outline_choice=choice)
        except TwinFocusError as e:  # the uncorrected reference region shows no object: what a user is told
            return {**rec, "refused": str(e)}
        first = out.metrics["estimator"]["outline"]
        rec[choice] = round(out.metrics["target_ssim_corrected"], 4)
        rec[f"{choice} chosen_by"] = first["chosen_by"]
        rec[f"{choice} trusted"] = out.metrics["confidence"]["trusted"]
        rec[f"{choice} s"] = round(time.perf_counter() - t0, 2)
    rec["oracle"] = round(out.metrics["target_ssim_oracle_phase"], 4)
    print(
        f"[outline choice] {cond}, seed {seed}, {surface}: " + ", ".join(f"{c} {rec[c]:.3f}" for c in CHOICES),
        file=sys.stderr,
        flush=True,
    )
    return rec


def table(records: list[dict]) -> str:
    """Markdown: mean target SSIM (and worst) per surface and choice over the scored draws."""
    lines = ["| reference | draws | " + " | ".join(CHOICES) + " |", "|---|---|" + "---|" * len(CHOICES)]
    for surface in SURFACES:
        recs = [r for r in records if r["surface"] == surface and "refused" not in r]
        if recs:
            cells = [f"{np.mean([r[c] for r in recs]):.3f} (worst {min(r[c] for r in recs):.3f})" for c in CHOICES]
            lines.append(f"| {surface} | {len(recs)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(out_dir: str = "benchmarks/results", draws: int = 6, heldout: bool = False, workers: int = 2) -> list[dict]:
    first = HELDOUT_SEED if heldout else BENCH_SEED
    jobs = [(c, s, surface, heldout) for s in range(first, first + draws) for surface in SURFACES for c in CONDITIONS]
    with ProcessPoolExecutor(workers) as ex:
        records = list(ex.map(one_draw, jobs))
    path = Path(out_dir) / ("outline_choice_heldout.json" if heldout else "outline_choice.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"scan": {"positions": 390, "pixels": 64}, "records": records}, indent=1))
    print(table(records))
    return records


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--draws", type=int, default=6, help="seeds; each runs every condition and surface")
    ap.add_argument("--heldout", action="store_true", help="the held-out draws (other shapes, other seeds)")
    ap.add_argument("--workers", type=int, default=2, help="draws at once, one process each")
    a = ap.parse_args()
    main(a.out, a.draws, a.heldout, a.workers)
