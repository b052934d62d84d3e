"""The live graph's hand sweep against ``twinfocus focus`` of the same scan.

``twinfocus launch sim trajectory:=zigzag error_model:=hand``: the simulated tracker carries the
hand's drift and the array's turn in its poses (nodes/runtime/sim_backends.py), so the solver fits the
drift + tilt on a hand-held scan; ``twinfocus simulate --trajectory zigzag --error-model hand`` +
``twinfocus focus`` is the same scan offline (its phase centres within 0.4 um of the live ones:
the tracked pose turns the array exactly where the simulation turns it to first order). Live, at
``rate:=1``, the solver fits the drift while the sweep arrives and refines from the latest fit
after the last frame (or fits again cold when that start leads it below where a cold fit
begins); the two images must still be the same image, within 0.005 SSIM.
"""

import json

import numpy as np
import pytest

from tests.test_graph import offline_simulate_and_focus, sim_graph
from twinfocus.imaging.metrics import image_ssim
from twinfocus.simulation.scenario import Scenario


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_live_hand_sweep_equals_offline_focus(tmp_path):
    seed, cols, rows = "2", "2", "30"
    sc = Scenario(n_columns=2, n_rows=30, seed=2, trajectory="zigzag", error_model="hand")
    size, iterations = "32", "30"
    scene = ["--columns", cols, "--rows", rows, "--seed", seed, "--trajectory", "zigzag", "--error-model", "hand"]
    offline_simulate_and_focus(tmp_path, scene, sc, size, iterations, focus_timeout_s=600)
    g = sim_graph(
        tmp_path, sc, size, iterations,
        f"columns:={cols}", f"rows:={rows}", f"seed:={seed}", "trajectory:=zigzag", "error_model:=hand",
        # slower than a hand (rate 1: 6 s) so that a loaded machine still finishes the first fit on
        # 40 positions before the last of the 60 arrives
        rate="0.4",
    )  # fmt: skip
    code = g.exit_code(600)
    assert code == 0, g.text

    live_dir, off_dir = tmp_path / "graph" / "focus" / "sim", tmp_path / "offline"
    live_m = json.loads((live_dir / "metrics.json").read_text())
    off_m = json.loads((off_dir / "metrics.json").read_text())
    assert live_m["n_positions"] == off_m["n_positions"] == 60
    # the same hand-held scan: the uncorrected images (no estimator) agree to the 0.4 um of the
    # turn's second order; a rigid offset without the turn moves the array's ends by ~0.1 mm
    a, b = np.load(live_dir / "target_uncorrected.npy"), np.load(off_dir / "target_uncorrected.npy")
    np.testing.assert_allclose(a, b, rtol=0, atol=2e-3 * np.abs(b).max())
    # the drift + tilt fit ran on both, and gave the same image
    assert off_m["space_variant"].get("tilt_fitted"), off_m["space_variant"]
    assert live_m["space_variant"].get("tilt_fitted"), live_m["space_variant"]
    # live, the fit ran while the sweep arrived and refined from there after its last frame
    streamed = live_m["space_variant_streamed"]
    assert streamed["used"] and streamed["fits"] >= 1, streamed
    # ... and started from the latest streamed fit, or refused it (its 10 + 10 steps ended below
    # where a cold fit begins: with OpenCV 5.1's letters this scene's first 40 positions led the
    # fit astray) and fitted cold, as offline
    sv = live_m["space_variant"]
    assert sv.get("warm_start_positions", sv.get("warm_start_refused", {}).get("positions", 0)) >= 40, sv
    live, off = np.load(live_dir / "target.npy"), np.load(off_dir / "target.npy")
    assert image_ssim(live, off) > 0.995, image_ssim(live, off)
    assert abs(live_m["target_ssim_corrected"] - off_m["target_ssim_corrected"]) < 0.005, (
        live_m["target_ssim_corrected"],
        off_m["target_ssim_corrected"],
    )
