"""The output folder of a focus (docs/architecture.md section 4): the images and phases as
``.npy``, ``metrics.json`` and the pictures, written beside the numerics that made them
(:class:`~twinfocus.focus.pipeline.FocusOutputs`), never by them."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.focus.pipeline import FocusOutputs
from twinfocus.io.atomic import record_written, remove_earlier
from twinfocus.outputs.plotting import write_focus_pictures


def write_outputs(out_dir: str | os.PathLike, outputs: FocusOutputs, pictures: str | bool = "summary") -> Path:
    """Write the output files of docs/architecture.md section 4 into ``out_dir``.

    pictures : "summary" (summary.png, the default), "all" (every picture), "none"; True/False
        mean "summary"/"none". Files of an earlier run (listed in its
        :data:`twinfocus.io.atomic.WRITTEN`) that this one does not write are removed, so the folder
        never shows images of another result; a file that no run wrote is never removed.

    Everything is first written to a temporary folder beside ``out_dir`` and moved in at the end,
    so a failure never leaves a mix of old and new results.
    """
    which = ("summary" if pictures else "none") if isinstance(pictures, bool) else pictures
    if which not in ("summary", "all", "none"):
        raise TwinFocusError(f"pictures must be 'summary', 'all' or 'none', got {pictures!r}")
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        np.save(tmp / "target.npy", outputs.target.astype(np.complex64))
        np.save(tmp / "target_uncorrected.npy", outputs.target_uncorrected.astype(np.complex64))
        np.save(tmp / "reference.npy", outputs.reference.astype(np.complex64))
        np.save(tmp / "reference_uncorrected.npy", outputs.reference_uncorrected.astype(np.complex64))
        np.save(tmp / "phase.npy", outputs.phase_rad.astype(np.float64))
        if outputs.drift_m is not None:
            np.save(tmp / "drift.npy", outputs.drift_m.astype(np.float64))
        if outputs.loss_history.size:
            np.save(tmp / "loss.npy", outputs.loss_history)
        doc = {
            **outputs.metrics,
            "reference_roi": list(outputs.reference_grid.roi),
            "target_roi": list(outputs.target_grid.roi),
            "size": list(outputs.reference_grid.shape),
            "config": outputs.config,
        }
        (tmp / "metrics.json").write_text(json.dumps(doc, indent=2, default=float))
        if which != "none":
            write_focus_pictures(tmp, outputs, which)
        out_dir.mkdir(parents=True, exist_ok=True)
        written = {f.name for f in tmp.iterdir()}
        for f in tmp.iterdir():
            os.replace(f, out_dir / f.name)
        # an earlier run's files that this one did not write go (so the folder never shows
        # pictures of another result); a file no run of ours listed stays
        remove_earlier(out_dir, written)
        record_written(out_dir, written)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out_dir
