"""Field-like scenarios: Scenario fields and ``twinfocus simulate`` options."""

import json

import numpy as np
import pytest

from twinfocus.cli import main
from twinfocus.simulation.scenario import Scenario


def test_scenario_fields_reach_the_scene():
    sc = Scenario(
        reference_roughness_deg=90.0,
        reference_amplitude_spread=0.3,
        reference_shape="bent",
        reference_shape_parameter=20.0,
        target_depth_offset_m=0.1,
    )
    scene = sc.scene()
    ref, tgt = scene.object("reference"), scene.object("target")
    assert ref.roughness_deg == 90.0 and ref.amplitude_spread == 0.3 and ref.depth_m is not None
    base = Scenario().scene().object("target")
    # Deeper by 0.1 m along its own ray: same direction from the aperture.
    assert tgt.centre_m[2] == pytest.approx(base.centre_m[2] + 0.1)
    np.testing.assert_allclose(
        tgt.centre_m / np.linalg.norm(tgt.centre_m), base.centre_m / np.linalg.norm(base.centre_m), atol=1e-12
    )
    roi = sc.target_roi()
    assert roi[4] == pytest.approx(0.7) and roi[0] < tgt.centre_m[0] < roi[1]
    assert Scenario().scene().object("reference").roughness_deg is None


@pytest.mark.slow  # 1.9 s x
def test_simulate_writes_camera_cloud(tmp_path, capsys):
    out, cloud = tmp_path / "s.npz", tmp_path / "c.npy"
    rc = main(
        [
            "simulate",
            "--out",
            str(out),
            "--rows",
            "4",
            "--columns",
            "2",
            "--quiet",
            "--reference-roughness-deg",
            "90",
            "--reference-shape",
            "cylinder",
            "--reference-cloud-out",
            str(cloud),
            "--cloud-noise-mm",
            "0",
            "--cloud-holes",
            "0.2",
            "--cloud-outliers",
            "0",
            "--cloud-offset-mm",
            "0",
            "0",
            "0",
        ]
    )
    assert rc == 0
    info = json.loads(capsys.readouterr().err.strip().splitlines()[-1])
    pts = np.load(cloud)
    assert info["reference_cloud_points"] == pts.shape[0]
    full = Scenario(reference_shape="cylinder").scene().object("reference").surface_points(1e-3)
    assert pts.shape[0] == pytest.approx(0.8 * full.shape[0], abs=2)
    # Exactly points of the cylinder-shaped surface (no noise, no offset asked).
    assert set(map(tuple, np.round(pts, 9))) <= set(map(tuple, np.round(full, 9)))


def test_simulate_cloud_option_errors(tmp_path):
    out = str(tmp_path / "s.npz")
    assert main(["simulate", "--out", out, "--reference-cloud-out", str(tmp_path / "c.txt")]) == 2
    assert (
        main(["simulate", "--out", out, "--reference-cloud-out", str(tmp_path / "c.npy"), "--cloud-noise-mm", "1", "2"])
        == 2
    )
    assert (
        main(["simulate", "--out", out, "--reference-cloud-out", str(tmp_path / "c.npy"), "--cloud-holes", "1.5"]) == 2
    )
    assert not (tmp_path / "s.npz").exists()


def test_simulate_refuses_what_cannot_fit_before_any_work(tmp_path, capsys):
    import time

    t = time.perf_counter()
    assert main(["simulate", "--out", str(tmp_path / "s.npz"), "--rows", "100000"]) == 2
    assert time.perf_counter() - t < 20  # refused up front, not after minutes of simulating
    err = capsys.readouterr().err
    assert "GiB" in err and "available" in err and "Traceback" not in err
    assert not (tmp_path / "s.npz").exists()


def test_simulation_cost_covers_the_arrays_it_makes():
    from twinfocus.radar.fmcw import Chirp
    from twinfocus.simulation.if_simulator import add_thermal_noise, simulate_if, simulation_cost

    pos = np.random.default_rng(0).normal(size=(5, 7, 3)) * 0.01
    data = add_thermal_noise(simulate_if(np.array([[0.0, 0.0, 0.6]]), None, pos, Chirp()), 10.0, 0)
    peak, secs = simulation_cost(5, 7, Chirp().n_samples, 1)
    assert peak >= data.nbytes * 2 and secs > 0  # result plus at least one noise transient
    assert simulation_cost(10, 7, 256, 1)[0] == 2 * simulation_cost(5, 7, 256, 1)[0]


@pytest.mark.slow  # 2.1 s CPU (2 cores, load ~9): out of make test-fast
def test_render_and_simulate_read_the_same_layout_options(tmp_path, capsys):
    """``twinfocus render`` takes the scene's layout from the options ``simulate`` takes: the regions
    it prints are the scenario's own for the same options."""
    layout = ["--reference", "H", "--target", "S", "--distance", "0.5", "--separation-deg", "14", "--height", "0.1"]
    assert main(["render", "--out", str(tmp_path / "cam"), "--width", "160", "--height-px", "90", *layout]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    sc = Scenario(reference="H", target="S", distance_m=0.5, separation_deg=14.0, height_m=0.1)
    assert printed["reference_roi"] == pytest.approx(list(sc.reference_roi()))
    assert printed["target_roi"] == pytest.approx(list(sc.target_roi()))
    assert (tmp_path / "cam" / "camera.json").is_file()
