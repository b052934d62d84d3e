"""``python -m twinfocus.sensors.emulators capture``: the trajectory file holds the camera's track
(the true raster plus the requested tracking error), and ``--reference-only`` leaves the target out."""

from __future__ import annotations

import numpy as np

from twinfocus.motion.trajectory import paper_raster
from twinfocus.sensors.emulators.__main__ import main
from twinfocus.sensors.emulators.rig import N_REFERENCE_SCATTERERS, demo_scatterers
from twinfocus.sensors.trajectory_files import read_tum


def test_the_track_carries_the_requested_error_and_the_stage_scan_only_the_reference(tmp_path):
    size = ["--columns", "2", "--rows", "30", "--n-samples", "16"]
    assert main(["capture", str(tmp_path / "hand"), *size, "--tracking-error-mm", "0.5", "--seed", "3"]) == 0
    assert main(["capture", str(tmp_path / "stage"), *size, "--reference-only"]) == 0

    truth = paper_raster(2, 30, 0.082, 0.002, frame_period_s=0.05).position_m
    hand = read_tum(tmp_path / "hand" / "trajectory.txt").position_m
    stage = read_tum(tmp_path / "stage" / "trajectory.txt").position_m
    np.testing.assert_allclose(stage, truth, atol=1e-9)  # a motion stage's positions are exact
    err_mm = (hand - truth) * 1e3
    assert err_mm.shape == (60, 3) and abs(err_mm.mean()) < 0.15 and 0.4 < err_mm.std() < 0.6

    pts = demo_scatterers()
    np.testing.assert_array_equal(np.load(tmp_path / "stage" / "scatterers.npy"), pts[:N_REFERENCE_SCATTERERS])
    np.testing.assert_array_equal(np.load(tmp_path / "hand" / "scatterers.npy"), pts)
    # the reference is the T on the left, the target the L on the right
    assert pts[:N_REFERENCE_SCATTERERS, 0].max() < 0 < pts[N_REFERENCE_SCATTERERS:, 0].min()
