"""Copy what ``make demo`` drew into the README's picture and write the figures its caption quotes.

    python -m benchmarks.demo_figure demo_out/focus      # make demo runs this after `focus`

README.md shows ``docs/images/demo_summary.png`` and quotes the target's SSIM before and after
the correction; both come from the demo's own output folder, so the page shows the run a user
gets. ``docs/images/demo_summary.json`` holds the quoted figures (read from the run's
metrics.json); ``tests/test_readme_demo.py`` checks that README says what that file holds and
that a fresh demo draws the committed picture.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from twinfocus.io.atomic import write_text_atomic

ROOT = Path(__file__).resolve().parents[1]
PICTURE = ROOT / "docs" / "images" / "demo_summary.png"
FIGURES = ROOT / "docs" / "images" / "demo_summary.json"
# The metrics.json keys the README caption quotes.
QUOTED = ("target_ssim_uncorrected", "target_ssim_corrected", "target_ssim_oracle_phase")


def demo_figures(metrics: dict) -> dict:
    """The caption's figures from a demo run's metrics.json, rounded as README prints them."""
    return {key: round(float(metrics[key]), 3) for key in QUOTED}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("focus_dir", type=Path, help="the demo's `focus --out` folder")
    args = parser.parse_args(argv)
    summary = args.focus_dir / "summary.png"
    metrics_file = args.focus_dir / "metrics.json"
    if not summary.is_file() or not metrics_file.is_file():
        print(f"demo_figure: {args.focus_dir} has no summary.png and metrics.json; run `make demo` first")
        return 2
    figures = demo_figures(json.loads(metrics_file.read_text()))
    tmp = PICTURE.with_name(f".{PICTURE.name}.tmp")
    shutil.copyfile(summary, tmp)
    tmp.replace(PICTURE)
    write_text_atomic(FIGURES, json.dumps(figures, indent=2) + "\n")
    print(f"[make] README's picture and figures refreshed: {PICTURE.relative_to(ROOT)}, {FIGURES.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
