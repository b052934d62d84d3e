"""The solver node finds what ``twinfocus focus`` finds: the reference's region from the template,
the target's depth from the scan, and the corrected volume, with the same answer."""

import numpy as np
import pytest

from nodes.runtime.testing import local_broker, running
from tests.helpers import cli, metrics
from tests.test_nodes import CHIRP, REF_ROI, TGT_ROI, point_scene_scan, send_scan, solver_and_probe, twin_template
from twinfocus.errors import TwinFocusError

VOLUME = [0.26, 0.34, 0.01]


@pytest.mark.slow  # 2.7 s CPU (2 cores, load ~9): out of make test-fast
def test_solver_finds_the_region_the_depth_and_the_volume_as_focus_does(tmp_path):
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.imaging.volume import projections, volume_grid
    from twinfocus.twins.templates import save_template, template_from_scan

    scan = point_scene_scan()
    ref_grid = ImageGrid.from_roi(REF_ROI, 16)
    template = template_from_scan(scan, ref_grid)
    scan.save(tmp_path / "scan.npz")
    save_template(tmp_path / "tpl.npz", template, ref_grid)
    box = [str(v) for v in TGT_ROI[:4]]
    inputs = (tmp_path / "scan.npz", "--template", tmp_path / "tpl.npz", "--target-roi", *box)
    volume = ("--volume", *VOLUME)
    options = "--size 16 --iterations 40 --quiet --no-cache --pictures none"
    assert cli("focus", *inputs, *volume, options, "--out", tmp_path / "off") == 0
    off = metrics(tmp_path / "off")

    with local_broker() as ep:
        # no reference region and no depth: both found, as focus finds them
        listen = ("autofocus/result", "image/focused")
        params = {"target_roi": TGT_ROI[:4], "size": 16, "iterations": 40, "volume": VOLUME, "pictures": False}
        solver, probe = solver_and_probe(ep, listen, **params, out_dir=str(tmp_path / "live"))
        with running(solver, probe):
            send_scan(probe, twin_template(template, ref_grid), scan)
            res = probe.wait_for("autofocus/result", 1, timeout_s=120, where=lambda r: not r.metrics_pending)[0]
            images = {i.name: i for i in probe.wait_for("image/focused", 5)}
    assert not res.dropped, res.dropped
    live = metrics(tmp_path / "live" / "p")
    assert live["reference_search"]["roi"] == off["reference_search"]["roi"] == pytest.approx(REF_ROI)
    # the same depth, near the points' 0.3 m (within a tenth of this chirp's 16 cm range
    # resolution), on the result topic and in the target image's plane
    depth = off["target_depth"]["depth_m"]
    assert depth == pytest.approx(0.3, abs=0.1 * CHIRP.range_resolution_m)
    assert res.metrics["target_depth.depth_m"] == pytest.approx(depth, abs=1e-6)
    assert images["target"].z_m == pytest.approx(depth, abs=1e-6)
    # the same phase and images
    live_phase, off_phase = res.phase_rad, np.load(tmp_path / "off" / "phase.npy")
    np.testing.assert_allclose(np.angle(np.exp(1j * (live_phase - off_phase))), 0.0, atol=1e-3)
    want = np.load(tmp_path / "off" / "target.npy")
    np.testing.assert_allclose(images["target"].image, want, atol=1e-3 * np.abs(want).max())
    # the volume's maximum-intensity projection: focus's volume.npy projected
    grid = volume_grid(ImageGrid(*off["volume"]["roi"], z=1.0, height=16, width=16), *VOLUME)
    mip, _ = projections(np.load(tmp_path / "off" / "volume.npy"), grid)
    np.testing.assert_allclose(images["volume_mip"].image, mip, atol=1e-3 * mip.max())
    assert (
        np.array_equal(images["volume_mip"].x_m, grid.plane.x_m) and live["volume"]["shape"] == off["volume"]["shape"]
    )


def test_solver_refuses_regions_it_cannot_use():
    from nodes.solver import Solver

    with local_broker() as ep:
        base = {"target_roi": TGT_ROI, "size": 8, "warm_up": False}
        for bad, word in (
            ({"target_roi": TGT_ROI[:3]}, "target_roi"),
            ({"reference_roi": REF_ROI[:4]}, "reference_roi"),
            ({"volume": [0.2, 0.3]}, "volume"),
            ({"target_roi": [*TGT_ROI[:4], 0.4, 0.3]}, "Z0 < Z1"),
        ):
            with pytest.raises(TwinFocusError, match=word):
                Solver(broker=ep, params={**base, **bad})
        # typed region and depth: streamed as before; a range: focused whole at the end
        assert not Solver(broker=ep, params={**base, "reference_roi": REF_ROI}).whole_scan
        assert Solver(
            broker=ep, params={**base, "reference_roi": REF_ROI, "target_roi": [*TGT_ROI[:4], 0.2, 0.4]}
        ).whole_scan
