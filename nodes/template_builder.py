"""Twin-template builder node: publishes the reference's template on ``twin/template``.

Sources (``source`` parameter):

* ``file``: a template file (DESIGN.md section 4), resampled onto the reference grid
  (:func:`twinfocus.templates.load_template`);
* ``scan``: a physical twin from a motion-stage scan of the reference alone
  (:func:`twinfocus.templates.template_from_scan`);
* ``sim``: the same from a simulated motion-stage scan of the scenario's reference
  (:func:`nodes.sim_backends.template_scan`);
* ``points``: a digital twin from a reference point cloud (``.npy``, scene frame). Its template
  depends on the aperture, so the node listens to ``sar/measurement`` and builds the template
  for each scan when the scan's last measurement arrives
  (:func:`twinfocus.digital_twin.template.digital_twin_template`).

The digital twin straight from ``camera/stereo`` frames is left for when the stereo-to-cloud
pipeline of :mod:`twinfocus.digital_twin` is complete; until then, make the cloud with the
digital-twin tools and use ``source: points``.
"""
from __future__ import annotations

import sys

import numpy as np

from msgs import Header, SarMeasurement, TwinTemplate, now_ns
from nodes.node import Node, run_node
from nodes.params import REQUIRED, Param
from twinfocus.errors import TwinFocusError


class TemplateBuilder(Node):
    """Publish the reference template."""

    NAME = "template_builder"
    PARAMS = {
        **Node.PARAMS,
        "source": Param("file", "file, scan, sim or points", choices=("file", "scan", "sim", "points")),
        "path": Param("", "template file, template scan or point cloud (.npy), by source", type="str"),
        "scenario": Param({}, "for source sim: the Scenario fields (as the simulated drivers)", type="any"),
        "reference_roi": Param(REQUIRED, "reference region X0 X1 Y0 Y1 Z, metres", type="floats"),
        "size": Param(100, "template size in pixels per side (the solver's size)"),
        "oversample": Param(16, "range-profile oversampling of the back-projection"),
        "precision": Param("float32", "float32 or float64", choices=("float32", "float64")),
        "republish_s": Param(0.0, "publish the template again this often (0: once; late joiners then miss it)"),
    }

    def __init__(self, **kw):
        super().__init__(**kw)
        from twinfocus.grid import ImageGrid

        p = self.params
        if len(p["reference_roi"]) != 5:
            raise TwinFocusError(f"node {self.name!r}: reference_roi needs 5 numbers X0 X1 Y0 Y1 Z, got {p['reference_roi']}")
        self.grid = ImageGrid.from_roi(p["reference_roi"], p["size"])
        self.bp = {"oversample": p["oversample"], "precision": p["precision"]}
        self.pub = self.create_publisher("twin/template")
        self.msg: TwinTemplate | None = None
        src, path = p["source"], p["path"]
        if src in ("file", "scan", "points") and not path:
            raise TwinFocusError(f"node {self.name!r}: source {src!r} needs the 'path' parameter")
        if src == "points":
            from twinfocus.digital_twin.template import load_points

            self.points = load_points(path)
            self.positions: list[np.ndarray] = []
            self.scan_id = None
            self.create_subscription("sar/measurement", self.on_measurement)
        else:
            # Built before the graph starts, so it is ready when the first scan ends.
            self.msg = self._build_static(src, path)

    def _build_static(self, src: str, path: str) -> TwinTemplate:
        from twinfocus.scan import Scan
        from twinfocus.templates import load_template, template_from_scan

        # a physical twin's phase travels with it (TwinTemplate.phase_rad): the solver's closed form needs it
        if src == "file":
            image, kind = load_template(path, self.grid), "physical"
        elif src == "scan":
            image, kind = template_from_scan(Scan.load(path), self.grid, keep_phase=True, **self.bp), "physical"
        else:
            from nodes.sim_backends import scenario_from, template_scan

            sc = scenario_from({"scenario": self.params["scenario"] or {}}, f"node {self.name!r}")
            image, kind, path = (template_from_scan(template_scan(sc), self.grid, keep_phase=True, **self.bp), "physical",
                                 "simulated motion-stage scan")
        return self._message(image, kind, path)

    def _message(self, image: np.ndarray, kind: str, source: str) -> TwinTemplate:
        g = self.grid
        image = np.asarray(image)
        phase = np.angle(image).astype(np.float32) if np.iscomplexobj(image) else None
        return TwinTemplate(header=Header(stamp_ns=now_ns(), frame_id="scene"), image=np.abs(image).astype(np.float32),
                            phase_rad=phase, x_m=g.x_m, y_m=g.y_m, z_m=g.z, kind=kind, source=str(source))

    def on_start(self) -> None:
        if self.msg is not None:
            self._send()
            if self.params["republish_s"] > 0:
                self.create_timer(self.params["republish_s"], self._send)

    def _send(self) -> None:
        self.msg.header.stamp_ns = now_ns()
        self.pub.publish(self.msg)
        self.status_message = f"published {self.msg.kind} template from {self.msg.source}"
        if self.pub.seq == 1:
            self.log(self.status_message)

    def on_measurement(self, m: SarMeasurement) -> None:
        from twinfocus.digital_twin.template import digital_twin_template

        if m.scan_id != self.scan_id:
            self.scan_id, self.positions = m.scan_id, []
        self.positions.append(np.asarray(m.positions_m))
        if m.last:
            positions = np.stack(self.positions)
            image = digital_twin_template(self.points, positions, m.chirp(), self.grid, **self.bp)
            self.msg = self._message(image, "digital", f"{self.params['path']} (scan {m.scan_id})")
            self._send()
            self.positions = []


def main(argv: list[str] | None = None) -> int:
    return run_node(TemplateBuilder, argv)


if __name__ == "__main__":
    sys.exit(main())
