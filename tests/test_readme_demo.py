"""README's picture and its figures are what `make demo` draws and prints."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from benchmarks.demo_figure import FIGURES, PICTURE, demo_figures
from twinfocus.cli import main as twinfocus
from twinfocus.scenario import PAPER_IMAGE_SIZE, PAPER_REFERENCE_ROI, PAPER_TARGET_ROI

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
_CAPTION = re.compile(r"([01]\.\d{3}) uncorrected, ([01]\.\d{3}) corrected \(([01]\.\d{3}) with the true phase")


def test_the_caption_quotes_the_figures_file() -> None:
    found = _CAPTION.search(" ".join(README.read_text(encoding="utf-8").split()))
    assert found, "README's caption no longer quotes the demo's SSIMs in the form this test reads"
    quoted = [float(v) for v in found.groups()]
    figures = json.loads(FIGURES.read_text())
    assert quoted == [
        figures["target_ssim_uncorrected"],
        figures["target_ssim_corrected"],
        figures["target_ssim_oracle_phase"],
    ]
    assert f"]({PICTURE.relative_to(ROOT)})" in README.read_text(encoding="utf-8")


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
