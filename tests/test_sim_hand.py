"""The simulated tracker's hand model: the tracked pose carries the hand's drift and the array's
turn, so the synchronizer's phase centres are the hand-held scan's (twinfocus.simulation.scenario)."""

import numpy as np
import pytest

from nodes.runtime.sim_backends import SIM_T0_NS, SimVio
from twinfocus.motion.trajectory import phase_centres
from twinfocus.radar.fmcw import mmwcas_virtual_array
from twinfocus.simulation.scenario import Scenario, scenario_positions


def _vio_centres(sc: Scenario, **options):
    vio = SimVio(
        {
            "scenario": {
                "n_columns": sc.n_columns,
                "n_rows": sc.n_rows,
                "trajectory": sc.trajectory,
                "seed": sc.seed,
                "error_model": sc.error_model,
            },
            **options,
        }
    )
    _, tracked, stamps = scenario_positions(sc, frame_period_s=0.1, t0_ns=SIM_T0_NS)
    at = vio.poses.interpolate(stamps)  # the poses at the radar stamps, as the synchronizer takes them
    return (
        phase_centres(at, mmwcas_virtual_array()),
        tracked,
        scenario_positions(sc, frame_period_s=0.1, t0_ns=SIM_T0_NS)[0],
    )


def test_hand_pose_carries_the_turn():
    sc = Scenario(n_columns=2, n_rows=20, trajectory="zigzag", error_model="hand", seed=3)
    live, tracked, true = _vio_centres(sc)
    arm = true - true.mean(axis=1, keepdims=True)
    turned = (tracked - true) - (tracked - true).mean(axis=1, keepdims=True)
    # the turn moves the array's ends apart by ~0.1 mm: a rigid offset alone would leave it out
    assert np.abs(turned).max() > 3e-5, np.abs(turned).max()
    # second order of 0.15 degree turns over the 83 mm array: under a micrometre
    np.testing.assert_allclose(live, tracked, rtol=0, atol=1e-6)
    assert np.abs(live - (tracked - turned)).max() > 3e-5  # and not the translation alone
    assert np.abs(arm).max() > 0.03


@pytest.mark.parametrize("model", ["vio", "drift", "gaussian"])
def test_models_without_turn_are_exact(model):
    sc = Scenario(n_columns=2, n_rows=10, error_model=model, seed=1)
    live, tracked, _ = _vio_centres(sc)
    np.testing.assert_allclose(live, tracked, rtol=0, atol=1e-12)
