"""README's picture and its figures are what `make demo` draws and prints."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks.demo_figure import FIGURES, PICTURE, demo_figures
from twinfocus.cli import main as twinfocus
from twinfocus.simulation.scenario import PAPER_IMAGE_SIZE, PAPER_REFERENCE_ROI, PAPER_TARGET_ROI

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def test_the_caption_quotes_the_demos_figures() -> None:
    # tests/test_docs_figures.py checks each marked figure against the file.
    text = README.read_text(encoding="utf-8")
    for key in ("target_ssim_uncorrected", "target_ssim_corrected", "target_ssim_oracle_phase"):
        assert f"<!-- figure: {FIGURES.relative_to(ROOT)}#{key} -->" in text
    assert f"]({PICTURE.relative_to(ROOT)})" in text


def _rgb(path: Path) -> np.ndarray:
    import matplotlib.image

    image = np.asarray(matplotlib.image.imread(path), dtype=np.float64)
    return image[..., :3]


@pytest.mark.slow
def test_make_demo_draws_the_committed_picture(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # make demo's two commands (Makefile, target demo), in-process.
    monkeypatch.setenv("TWINFOCUS_CACHE_DIR", str(tmp_path / "cache"))
    scan, template, out = tmp_path / "scan.npz", tmp_path / "template_scan.npz", tmp_path / "focus"
    assert twinfocus(["simulate", "--out", str(scan), "--template-out", str(template)]) == 0
    rois = ["--reference-roi", *map(str, PAPER_REFERENCE_ROI), "--target-roi", *map(str, PAPER_TARGET_ROI)]
    argv = ["focus", str(scan), "--template-scan", str(template), *rois, "--size", str(PAPER_IMAGE_SIZE)]
    assert twinfocus([*argv, "--out", str(out)]) == 0

    assert demo_figures(json.loads((out / "metrics.json").read_text())) == json.loads(FIGURES.read_text())
    drawn, committed = _rgb(out / "summary.png"), _rgb(PICTURE)
    assert drawn.shape == committed.shape
    # Fonts and anti-aliasing may differ by a level here and there; a picture of another run
    # differs wherever the speckle is.
    assert np.abs(drawn - committed).mean() < 0.01
