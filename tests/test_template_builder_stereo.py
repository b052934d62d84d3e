"""The template-builder node's live digital twin: camera/stereo -> cloud ->
conditioned template for the scan's aperture, over the node runtime."""

import time

import cv2
import numpy as np
import pytest

from msgs import Header, StereoFrame
from nodes.runtime.testing import Probe, local_broker, running
from tests.helpers import sar_measurements
from twinfocus.imaging.grid import ImageGrid
from twinfocus.motion.trajectory import paper_raster, phase_centres
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
from twinfocus.scene import paper_scene
from twinfocus.simulation.scenario import PAPER_REFERENCE_ROI
from twinfocus.twins.digital_twin.render import render_scene
from twinfocus.twins.digital_twin.template import digital_twin_template

CHIRP = Chirp()


def _frame(r) -> StereoFrame:
    e = r.camera.left
    k = np.array([[e.fx, 0.0, e.cx], [0.0, e.fy, e.cy], [0.0, 0.0, 1.0]])
    rgb = lambda x: cv2.cvtColor(x, cv2.COLOR_BGR2RGB)
    return StereoFrame(
        header=Header(stamp_ns=1), left=rgb(r.left), right=rgb(r.right), camera_matrix=k, baseline_m=r.camera.baseline_m
    )


def _measurements(positions, scan_id):
    zeros = np.zeros((*positions.shape[:2], 8), np.complex64)  # the builder reads positions only
    return sar_measurements(zeros, positions, CHIRP, scan_id)


@pytest.mark.slow  # 4 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_template_builder_builds_the_digital_twin_from_the_stereo_topic(tmp_path, capfd):
    from nodes.template_builder import TemplateBuilder

    scene = paper_scene()
    r = render_scene(scene, seed=2)
    r.camera.save(tmp_path / "camera.json")
    positions = phase_centres(paper_raster(3, 40, row_pitch_m=0.004), mmwcas_virtual_array())
    grid = ImageGrid.from_roi(PAPER_REFERENCE_ROI, 40)
    with local_broker() as ep:
        probe = Probe(
            ep, listen=["twin/template"], publish=["camera/stereo", "sar/measurement"], wait_for=["template_builder"]
        )
        tb = TemplateBuilder(
            broker=ep,
            params={
                "source": "stereo",
                "path": str(tmp_path / "camera.json"),
                "reference_roi": list(PAPER_REFERENCE_ROI),
                "size": 40,
                "oversample": 4,
            },
        )
        with running(tb, probe):
            # A scan that ends before any camera frame: no template, and the log says why.
            for m in _measurements(positions[:3], "early"):
                probe.send("sar/measurement", m)
            deadline, err = time.monotonic() + 20, ""
            while "ended before any camera/stereo frame" not in err and time.monotonic() < deadline:
                time.sleep(0.2)
                err += capfd.readouterr().err
            assert "scan early ended before any camera/stereo frame gave a reference cloud: no template" in err
            probe.send("camera/stereo", _frame(r))
            deadline = time.monotonic() + 120
            while tb.points is None and time.monotonic() < deadline:
                time.sleep(0.2)
            assert tb.points is not None, "no cloud from the stereo frame"
            for m in _measurements(positions, "s1"):
                probe.send("sar/measurement", m)
            (t,) = probe.wait_for("twin/template", 1, timeout_s=120)
    assert t.kind == "digital" and "camera/stereo" in t.source and "scan s1" in t.source
    assert t.image.shape == grid.shape and np.array_equal(t.x_m, grid.x_m)
    # Independent truth: the template of the reference's true surface for the same aperture.
    truth = digital_twin_template(scene.object("reference").surface_points(1e-3), positions, CHIRP, grid, oversample=4)
    corr = np.corrcoef(t.image.ravel(), truth.ravel())[0, 1]
    assert corr > 0.85, corr
    print(f"stereo twin vs true-surface template: corr {corr:.3f}, surface {tb.twin_info['surface']}")
    assert tb.twin_info["surface"] in ("plane", "smooth", "outline")
