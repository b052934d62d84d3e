"""The live digital twin's outline (TwinTemplate.support) over the node runtime: the template
builder sends the outline of the reference it conditions, and the solver resamples it with the
template and runs the outline estimator, as ``twinfocus focus --digital-twin`` does; a template
without one keeps the projections; an outline that does not fit loses no scan."""

import json
import time

import msgpack
import numpy as np
import pytest

from msgs import Header, TwinTemplate, encode_frames
from nodes.runtime.testing import Probe, local_broker, running
from tests.helpers import sar_measurements
from twinfocus.imaging.grid import ImageGrid
from twinfocus.motion.trajectory import paper_raster, phase_centres
from twinfocus.radar.fmcw import Chirp, uniform_virtual_array
from twinfocus.simulation.if_simulator import simulate_if

CHIRP = Chirp(n_samples=64)
REF_ROI = [-0.045, -0.005, -0.02, 0.02, 0.3]
TGT_ROI = [0.01, 0.05, -0.03, 0.01, 0.3]
SIZE = 24


def _letter(step_m):
    """An 'F' 20 mm tall in the reference region at z = 0.3 m, points ``step_m`` apart: float64 (N, 3)."""
    s = np.arange(-0.010, 0.0101, step_m)
    xy = [(-0.010, y) for y in s] + [(x, 0.010) for x in s] + [(x * 0.6, 0.0) for x in s]
    return np.array([(x - 0.025, y, 0.3) for x, y in xy])


@pytest.fixture(scope="module")
def scene():
    """The 'F' of speckled scatterers 2 mm apart scanned by a 16-channel array on 2 x 24 positions
    tracked with 0.3 mm of z error; its camera cloud: the same 'F' sampled every millimetre."""
    rng = np.random.default_rng(1)
    k = 16
    poses = paper_raster(n_columns=2, n_rows=24, column_pitch_m=0.008 * k, row_pitch_m=0.004)
    true = phase_centres(poses, uniform_virtual_array(k, 0.002))
    scatterers = _letter(0.002)
    data = simulate_if(scatterers, np.exp(2j * np.pi * rng.random(len(scatterers))), true, CHIRP)
    tracked = (
        true
        + np.stack([np.zeros(true.shape[0]), np.zeros(true.shape[0]), rng.normal(0, 0.3e-3, true.shape[0])], axis=1)[
            :, None, :
        ]
    )
    return data, tracked, _letter(0.001)


def _solver(ep, tmp_path, **params):
    from nodes.solver import Solver

    return Solver(
        broker=ep,
        params={
            "reference_roi": REF_ROI,
            "target_roi": TGT_ROI,
            "size": SIZE,
            "warm_up": False,
            "out_dir": str(tmp_path),
            "pictures": False,
            **params,
        },
    )


def _twin_template(reference, support):
    grid = ImageGrid.from_roi(REF_ROI, SIZE)
    return TwinTemplate(
        header=Header(stamp_ns=1, frame_id="scene"),
        image=reference.template,
        support=support,
        x_m=grid.x_m,
        y_m=grid.y_m,
        z_m=grid.z,
        kind="digital",
        source="F.npy",
    )


@pytest.fixture(scope="module")
def reference(scene):
    """What ``twinfocus focus --digital-twin`` builds from the cloud for this scan."""
    from twinfocus.twins.digital_twin.condition import digital_twin_reference

    _, tracked, cloud = scene
    return digital_twin_reference(
        cloud, tracked, CHIRP, ImageGrid.from_roi(REF_ROI, SIZE), oversample=16, precision="float32"
    )


@pytest.mark.slow  # 1.5 s (2 cores, idle): out of make test-fast (benchmarks/results/test_fast.json)
def test_a_points_twin_carries_its_outline_and_the_solver_runs_the_outline_estimator(scene, reference, tmp_path):
    """source points -> twin/template with the cloud's outline -> the solver's auto takes the
    outline estimator and finds the phase focus_bases finds offline with the same outline."""
    from nodes.template_builder import TemplateBuilder
    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.estimators import estimator_settings
    from twinfocus.focus.pipeline import Bases, Reference, upper_band_basis
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.imaging.backprojection.numba_backend import subimage_basis

    data, tracked, cloud = scene
    np.save(tmp_path / "F.npy", cloud)
    with local_broker() as ep:
        builder = TemplateBuilder(
            broker=ep,
            params={"source": "points", "path": str(tmp_path / "F.npy"), "reference_roi": REF_ROI, "size": SIZE},
        )
        solver = _solver(ep, tmp_path / "out")
        probe = Probe(
            ep,
            listen=["twin/template", "autofocus/result"],
            publish=["sar/measurement"],
            wait_for=["template_builder", "solver"],
        )
        with running(builder, solver, probe):
            for m in sar_measurements(data, tracked, CHIRP, "s1"):
                probe.send("sar/measurement", m)
            (template,) = probe.wait_for("twin/template", 1, timeout_s=60)
            (res,) = probe.wait_for("autofocus/result", 1, timeout_s=60)
    # the builder's outline is digital_twin_reference's for the same cloud and aperture
    assert template.kind == "digital" and template.support is not None
    assert template.support.dtype == bool and np.array_equal(template.support, reference.support)
    np.testing.assert_array_equal(template.image, reference.template)
    # and what the conditioning chose travels with it into the solver's metrics.json
    assert (
        (template.surface, template.curved) == (reference.info["surface"], reference.info["curved"]) == ("plane", False)
    )
    metrics = json.loads((tmp_path / "out" / "s1" / "metrics.json").read_text())
    assert metrics["digital_twin"] == {
        "surface": "plane",
        "curved": False,
        "curvature_m": pytest.approx(reference.info["curvature_m"]),
    }
    assert not any("curved" in w for w in metrics["confidence"]["warnings"])
    # the solver ran the outline estimator (averaged outlines), and says so
    assert res.estimator == "outline" and res.method == "twin"
    est = json.loads((tmp_path / "out" / "s1" / "metrics.json").read_text())["estimator"]
    assert est["init"] == "outline" and est["iterations"] == 0
    assert "energy_inside" in est["outline"] and len(est["outline_ensemble"]["outlines_px"]) > 1
    assert est["outline_ensemble"]["growth_px"][0] == reference.support.sum()
    # the phase focus_bases gives offline with the same template and outline
    ref_grid, tgt_grid = ImageGrid.from_roi(REF_ROI, SIZE), ImageGrid.from_roi(TGT_ROI, SIZE)
    cfg = AutofocusConfig(**estimator_settings("auto", False, has_support=True))
    want = FocusPlan.make(
        config=cfg,
        phase_ramp=solver.params["phase_ramp"],
        space_variant=solver.params["space_variant"],
    ).focus_bases(
        Bases(
            subimage_basis(data, tracked, CHIRP, ref_grid),
            subimage_basis(data, tracked, CHIRP, tgt_grid),
            tracked,
            CHIRP,
            ref_grid,
            tgt_grid,
            upper_band=upper_band_basis(data, tracked, CHIRP, ref_grid),
        ),
        Reference(template=reference.template, support=reference.support),
    )
    np.testing.assert_allclose(np.angle(np.exp(1j * (res.phase_rad - want.phase_rad))), 0.0, atol=1e-3)


def test_without_an_outline_the_solver_keeps_the_projections(scene, reference, tmp_path):
    data, tracked, _ = scene
    with local_broker() as ep:
        solver = _solver(ep, tmp_path)
        probe = Probe(
            ep, listen=["autofocus/result"], publish=["sar/measurement", "twin/template"], wait_for=["solver"]
        )
        with running(solver, probe):
            probe.send("twin/template", _twin_template(reference, None))  # a template file's, or an old log's
            for m in sar_measurements(data, tracked, CHIRP, "s1"):
                probe.send("sar/measurement", m)
            (res,) = probe.wait_for("autofocus/result", 1, timeout_s=60)
    est = json.loads((tmp_path / "s1" / "metrics.json").read_text())["estimator"]
    assert est["init"] == "projection" and "outline" not in est
    # auto: the optimiser after the projections only where their phases have wrapped, and the
    # result names what ran
    assert res.estimator == ("projection-refined" if est["refine_check"]["refined"] else "projection")


def test_the_outline_is_resampled_with_the_template_and_an_empty_one_is_dropped(reference, capfd):
    from nodes.solver import Solver
    from twinfocus.twins.templates import resample_support

    msg = _twin_template(reference, reference.support)
    with local_broker() as ep:
        solver = Solver(
            broker=ep, params={"reference_roi": REF_ROI, "target_roi": TGT_ROI, "size": 17, "warm_up": False}
        )
        solver.on_template(msg)  # another grid than the builder's: resampled, still a mask
        want = resample_support(reference.support, msg.x_m, msg.y_m, ImageGrid.from_roi(REF_ROI, 17))
        assert (
            solver.support.dtype == bool and np.array_equal(solver.support, want) and solver.template.shape == (17, 17)
        )
        assert 0.7 < want.sum() / (reference.support.sum() * (17 / SIZE) ** 2) < 1.3  # about the same area
        assert solver._config(CHIRP).init == "outline" and solver._plan().estimator == "outline"
        solver.on_template(_twin_template(reference, np.zeros_like(reference.support)))
        assert solver.support is None and solver.template.shape == (17, 17)  # the template alone is kept
        assert solver._config(CHIRP).init == "projection"
    err = capfd.readouterr().err
    assert (
        "ignored the outline of the digital template from F.npy: the outline covers 0% of the reference "
        "region on its grid (needs some but not all)"
    ) in err


def test_a_template_whose_outline_does_not_fit_is_dropped_and_the_waiting_scan_takes_the_next(
    scene, reference, tmp_path, capfd
):
    """A malformed twin/template (an outline of another shape than the image) is dropped with a
    line naming the field and both shapes; the scan waiting for a template is kept, and focused
    with the outline estimator when a good template comes."""
    data, tracked, _ = scene
    good = _twin_template(reference, reference.support)
    frames = encode_frames(good, publisher="probe")
    env = msgpack.unpackb(frames[0], raw=False)
    env["fields"]["support"]["shape"] = [SIZE // 2, SIZE * 2]  # the same bytes, another shape than the image's
    bad = [msgpack.packb(env, use_bin_type=True), *frames[1:]]
    with local_broker() as ep:
        solver = _solver(ep, tmp_path)
        probe = Probe(
            ep, listen=["autofocus/result"], publish=["sar/measurement", "twin/template"], wait_for=["solver"]
        )
        with running(solver, probe):
            for m in sar_measurements(data, tracked, CHIRP, "s1"):
                probe.send("sar/measurement", m)
            deadline = time.monotonic() + 60
            while not solver.waiting and time.monotonic() < deadline:
                time.sleep(0.05)
            assert solver.waiting, "the scan did not end"
            probe.send_frames("twin/template", bad)
            deadline, err = time.monotonic() + 20, ""
            while "dropped a malformed message" not in err and time.monotonic() < deadline:
                time.sleep(0.05)
                err += capfd.readouterr().err
            assert solver.template is None and len(solver.waiting) == 1  # not taken, the scan still waits
            probe.send("twin/template", good)
            (res,) = probe.wait_for("autofocus/result", 1, timeout_s=60)
    assert (
        "dropped a malformed message: twin/template" in err
        and "field 'support' must be bool array of shape (H, W)" in err
    )
    assert f"got shape ({SIZE // 2}, {SIZE * 2}) (already bound: H={SIZE}, W={SIZE})" in err
    assert res.scan_id == "s1" and res.estimator == "outline"


@pytest.mark.slow  # 3.4 s CPU (2 cores, load ~9): out of make test-fast
def test_a_curved_reference_is_reported_and_not_trusted(scene, reference):
    """A digital twin whose conditioning found the reference curved (tests/test_digital_twin_condition:
    a bent plate and a cylinder section are): the confidence report, offline and in the solver from
    the twin/template's fields, says the outline estimator is not at its ceiling there and does not
    trust the result; the flat reference's report carries no such warning."""
    from nodes.solver import Solver
    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.estimators import estimator_settings
    from twinfocus.focus.pipeline import Bases, Reference
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.imaging.backprojection.numba_backend import subimage_basis

    data, tracked, _ = scene
    ref_grid, tgt_grid = ImageGrid.from_roi(REF_ROI, SIZE), ImageGrid.from_roi(TGT_ROI, SIZE)
    bent = {**reference.info, "surface": "smooth", "curved": True, "curvature_m": 6.3e-3}
    rb, tb = subimage_basis(data, tracked, CHIRP, ref_grid), subimage_basis(data, tracked, CHIRP, tgt_grid)
    cfg = AutofocusConfig(**estimator_settings("auto", False, has_support=True))
    reports = {}
    for name, info in (("flat", reference.info), ("bent", bent)):
        out = FocusPlan.make(config=cfg).focus_bases(
            Bases(rb, tb, tracked, CHIRP, ref_grid, tgt_grid),
            Reference(template=reference.template, support=reference.support, info=info),
        )
        assert out.metrics["digital_twin"] == info
        reports[name] = (
            [w for w in out.metrics["confidence"]["warnings"] if "is curved" in w],
            out.metrics["confidence"]["trusted"],
        )
    assert reports["flat"][0] == [] and len(reports["bent"][0]) == 1 and not reports["bent"][1]
    assert "departs 6.3 mm from a plane" in reports["bent"][0][0]
    # the solver takes the same from the message's fields (an older log's template has none)
    msg = _twin_template(reference, reference.support)
    msg.surface, msg.curved, msg.curvature_m = "smooth", True, 6.3e-3
    with local_broker() as ep:
        solver = Solver(
            broker=ep, params={"reference_roi": REF_ROI, "target_roi": TGT_ROI, "size": SIZE, "warm_up": False}
        )
        solver.on_template(msg)
        assert solver.twin_info == {"surface": "smooth", "curved": True, "curvature_m": 6.3e-3}
        solver.on_template(_twin_template(reference, reference.support))
        assert solver.twin_info is None
