"""Where things are, on the demo scene: the corrected 3-D volume (100 x 100 x 40) and the target's
depth found without typing it.

Simulates the demo scene (``twinfocus simulate`` defaults: letters A and F at 0.6 m), then runs
``twinfocus focus`` twice with the physical twin (``--space-variant off``, so that the two runs
differ only in how the target's depth is set):

- ``volume``: both regions typed, ``--volume 0.5 0.695 0.005`` over both regions' x/y box at
  ``--size 100``: the volume's time against its estimate, and the depth of each letter's
  brightest voxel;
- ``depth``: the target's x/y box without Z: the depth found and the target SSIM against the
  typed run's.

Writes ``where.json`` (with the machine and its load) to the output folder.
Run: ``python -m benchmarks.bench_where --out benchmarks/results``.
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
from twinfocus.imaging.grid import ImageGrid
from twinfocus.jobs.machine import machine_info
from twinfocus.simulation.scenario import PAPER_REFERENCE_ROI, PAPER_TARGET_ROI

VOLUME = ("0.5", "0.695", "0.005")


def _focus(d: Path, out: Path, target: list[str], *extra: str) -> dict:
    rc = cli(
        focus_argv(
            d / "scan.npz",
            d / "tpl.npz",
            PAPER_REFERENCE_ROI,
            target,
            100,
            "--space-variant",
            "off",
            "--out",
            str(out),
            "--quiet",
            "--no-cache",
            "--pictures",
            "none",
            *extra,
        )
    )
    assert rc == 0
    return json.loads((out / "metrics.json").read_text())


def main(out_dir: str = "benchmarks/results") -> dict:
    load_at_start = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        assert cli(["simulate", "--out", str(d / "scan.npz"), "--template-out", str(d / "tpl.npz"), "--quiet"]) == 0
        box = [str(v) for v in PAPER_TARGET_ROI[:4]]
        typed = _focus(d, d / "typed", box + [str(PAPER_TARGET_ROI[4])], "--volume", *VOLUME)
        vol = np.abs(np.load(d / "typed" / "volume.npy"))
        v = typed["volume"]
        plane = ImageGrid.from_roi((*v["roi"], 1.0), vol.shape[1:])
        z = np.linspace(*v["z_m"], vol.shape[0])
        letters = {}
        for name, roi in (("reference", PAPER_REFERENCE_ROI), ("target", PAPER_TARGET_ROI)):
            cols = (plane.x_m >= roi[0]) & (plane.x_m <= roi[1])
            letters[name] = {
                "true_depth_m": roi[4],
                "brightest_depth_m": float(z[vol[:, :, cols].max(axis=(1, 2)).argmax()]),
            }
        found = _focus(d, d / "found", box)
    doc = {
        "command": "python -m benchmarks.bench_where --out benchmarks/results",
        "machine": machine_info(),
        "load_average_at_start": load_at_start,
        "volume": {
            "shape": v["shape"],
            "z_m": v["z_m"],
            "seconds": v["seconds"],
            "cpu_seconds": v["cpu_seconds"],
            "seconds_estimate": v["seconds_estimate"],
            "memory_bytes_estimate": v["memory_bytes_estimate"],
            "letters": letters,
        },
        "depth": {
            "true_depth_m": PAPER_TARGET_ROI[4],
            "found_depth_m": found["target_depth"]["depth_m"],
            "range_m": found["target_depth"]["range_m"],
            "search_seconds": found["timings_s"]["target_depth"],
            "target_ssim_typed": typed["target_ssim_corrected"],
            "target_ssim_found": found["target_ssim_corrected"],
            "focus_seconds_typed": sum(typed["timings_s"].values()) - typed["timings_s"]["volume"],
            "focus_seconds_found": sum(found["timings_s"].values()),
        },
    }
    return write_result(out_dir, "where.json", doc)


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="benchmarks/results")
    print(json.dumps(main(p.parse_args().out), indent=2))
