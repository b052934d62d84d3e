"""Several reference candidates: is the best one's phase beaten by the candidates' estimates
combined, weighted by their scores?

Each scene is the small demo scan (3 columns x 40 rows, seeds 3 and 4) with two template scans
of its reference as candidates: the simulator's own (placed 1 mm off on the motion stage) and a
second one (placed exactly, 3 mm off, or another letter where the reference stands). Each
candidate is fitted by ``twinfocus focus --template-scan`` alone and scored
(:func:`twinfocus.focus.reference_search.candidate_score`); the combined phase is
angle(sum_i w_i exp(j (phi_i - c_i))) with w_i the candidate's reference match SSIM when it has
no more warnings than the best-scored one (else 0) and c_i its constant offset from the best one's
phase (an estimate is defined up to a constant). Each phase is scored by the target's SSIM
against the truth image, as metrics.json's ``target_ssim_corrected``.

Writes ``reference_combine.json`` (with the machine and its load) to the output folder.
Run: ``python -m benchmarks.bench_reference_combine --out benchmarks/results``.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import focus_argv, write_result
from twinfocus.cli import main as cli
from twinfocus.focus.autofocus import AutofocusConfig
from twinfocus.imaging.backprojection.numba_backend import backproject
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.metrics import image_ssim
from twinfocus.imaging.volume import corrected_image
from twinfocus.jobs.machine import machine_info
from twinfocus.radar.scan import Scan
from twinfocus.simulation.scenario import PAPER_REFERENCE_ROI, PAPER_TARGET_ROI

SIZE = 48
SECOND = {"exact twin": ["--template-offset-mm", "0", "0", "0"], "3 mm off": ["--template-offset-mm", "3", "0", "0"],
          "letter B": ["--reference", "B"]}  # fmt: skip


def combined_phase(phases: list[np.ndarray], confidences: list[dict]) -> np.ndarray:
    """The candidates' phases combined (module docstring): float64 (M,) radians from (M,) each
    and their confidence reports (``reference_match_ssim``, ``warnings``)."""
    from twinfocus.focus.reference_search import candidate_score

    scores = [candidate_score(c) for c in confidences]
    best = int(np.argmax(scores))
    fewest = len(confidences[best]["warnings"])
    acc = np.zeros(phases[0].shape, np.complex128)
    for p, c in zip(phases, confidences):
        w = max(float(c.get("reference_match_ssim") or 0.0), 0.0) if len(c["warnings"]) <= fewest else 0.0
        offset = np.angle(np.sum(np.exp(1j * (p - phases[best]))))
        acc += w * np.exp(1j * (p - offset))
    return np.angle(acc) if np.abs(acc).max() > 0 else phases[best]


def _focus(d: Path, template: Path, out: Path) -> tuple[np.ndarray, dict]:
    rc = cli(focus_argv(d / "scan.npz", template, PAPER_REFERENCE_ROI, PAPER_TARGET_ROI, SIZE,
                        "--iterations", "150", "--space-variant", "off", "--out", str(out), "--quiet",
                        "--no-cache", "--pictures", "none"))  # fmt: skip
    assert rc == 0
    return np.load(out / "phase.npy"), json.loads((out / "metrics.json").read_text())


def main(out_dir: str = "benchmarks/results") -> dict:
    from twinfocus.focus.reference_search import candidate_score

    load_at_start = os.getloadavg()[0]
    cfg = AutofocusConfig()
    grid = ImageGrid.from_roi(PAPER_TARGET_ROI, SIZE)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in ("3", "4"):
            d = Path(tmp) / seed
            sim = ["--columns", "3", "--rows", "40", "--quiet", "--seed", seed]
            assert cli(["simulate", "--out", str(d / "scan.npz"), "--template-out", str(d / "a.npz"), *sim]) == 0
            scan = Scan.load(d / "scan.npz")
            truth = backproject(scan.data, scan.positions_true, scan.chirp, grid)

            def ssim(phase: np.ndarray, scan: Scan = scan, truth: np.ndarray = truth) -> float:
                img = corrected_image(scan.data, scan.positions, scan.chirp, grid, phase)
                return image_ssim(img, truth, cfg.threshold_centre, cfg.threshold_steepness)

            pa, ma = _focus(d, d / "a.npz", d / "fa")
            for name, extra in SECOND.items():
                b = d / f"b_{len(rows)}.npz"
                assert cli(["simulate", "--out", str(d / "other.npz"), "--template-out", str(b), *sim, *extra]) == 0
                pb, mb = _focus(d, b, d / f"fb_{len(rows)}")
                scores = [candidate_score(ma["confidence"]), candidate_score(mb["confidence"])]
                best = [pa, pb][int(np.argmax(scores))]
                rows.append(
                    {
                        "seed": int(seed),
                        "second": name,
                        "scores": scores,
                        "ssim_each": [ssim(pa), ssim(pb)],
                        "ssim_best": ssim(best),
                        "ssim_combined": ssim(combined_phase([pa, pb], [ma["confidence"], mb["confidence"]])),
                    }
                )
                print(json.dumps(rows[-1]))
    gain = [r["ssim_combined"] - r["ssim_best"] for r in rows]
    doc = {
        "command": "python -m benchmarks.bench_reference_combine --out benchmarks/results",
        "machine": machine_info(),
        "load_average_at_start": load_at_start,
        "scenes": rows,
        "combined_minus_best_ssim": {
            "mean": float(np.mean(gain)),
            "min": float(np.min(gain)),
            "max": float(np.max(gain)),
        },
    }
    return write_result(out_dir, "reference_combine.json", doc)


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="benchmarks/results")
    print(json.dumps(main(p.parse_args().out)["combined_minus_best_ssim"], indent=2))
