"""Twin-template builder node: publishes the reference's template on ``twin/template``.

Sources (``source`` parameter):

* ``file``: a template file (docs/architecture.md section 4), resampled onto the reference grid
  (:func:`twinfocus.twins.templates.load_template`); a digital twin's file (``twinfocus twin --out``)
  goes out as ``digital`` with its outline and conditioning;
* ``scan``: a physical twin from a motion-stage scan of the reference alone
  (:func:`twinfocus.twins.templates.template_from_scan`);
* ``sim``: the same from a simulated motion-stage scan of the scenario's reference
  (:func:`nodes.runtime.sim_backends.template_scan`);
* ``points``: a digital twin from a reference point cloud (``.npy``, scene frame, any camera's);
* ``stereo``: a live digital twin from the ``camera/stereo`` topic: the first frame (and every
  ``stereo_every``-th after it) goes through the stereo stages of :mod:`twinfocus.twins.digital_twin`
  (disparity, segmentation seeded by the reference region projected into the picture, point
  cloud: :func:`twinfocus.twins.digital_twin.pipeline.reference_from_stereo`); the camera's pose in the
  scene frame comes from ``path`` (a ``camera.json``, only its pose is used: the frames carry
  their own rectified intrinsics and baseline) or, without it, the ZED default pose.

A template scan's image (``scan``, ``sim``) is taken from the template cache
(:mod:`twinfocus.twins.cache`, the one ``twinfocus focus`` uses: ``$TWINFOCUS_CACHE_DIR``, else
``$XDG_CACHE_HOME/twinfocus``, else ``~/.cache/twinfocus``) when the same reference, grid and
back-projection options were computed before, by the node or by ``focus``; ``cache: false``
neither reads nor writes it. Keys: the template scan file's SHA-256 (``scan``, the key ``focus
--template-scan`` uses), the simulated scan's arrays (``sim``).

A digital twin's template depends on the aperture, so for ``points`` and ``stereo`` the node
listens to ``sar/measurement`` and, when a scan's last measurement arrives, conditions the cloud
and builds the template for that scan's positions
(:func:`twinfocus.twins.digital_twin.condition.digital_twin_reference`: outliers, holes, noise, the
surface model chosen by what the cloud supports). The reference's outline on the grid goes with
it (``TwinTemplate.support``), so the solver can take the outline estimator as ``twinfocus focus
--digital-twin`` does. A scan that ends before any stereo frame gave a
cloud gets no template, with a log line saying so.
"""

from __future__ import annotations

import sys

import numpy as np

from msgs import Header, SarMeasurement, StereoFrame, TwinTemplate, now_ns
from nodes.runtime.node import Node, run_node
from nodes.runtime.params import REQUIRED, Param
from twinfocus.errors import TwinFocusError
from twinfocus.imaging.grid import ImageGrid
from twinfocus.io.checksums import file_sha256
from twinfocus.radar.board import default_board
from twinfocus.radar.scan import Scan
from twinfocus.twins.cache import TemplateCache, array_sha256, template_key, template_scan_key
from twinfocus.twins.digital_twin.camera import DEFAULT_LEFT_CAMERA_POSITION_M, Intrinsics, StereoCamera, pose_matrix
from twinfocus.twins.digital_twin.rig import Rig, camera_identity
from twinfocus.twins.digital_twin.segment import box_from_scene_roi
from twinfocus.twins.digital_twin.template import load_points


class TemplateBuilder(Node):
    """Publish the reference template."""

    NAME = "template_builder"
    PARAMS = {
        **Node.PARAMS,
        "source": Param(
            "file", "file, scan, sim, points or stereo", choices=("file", "scan", "sim", "points", "stereo")
        ),
        "path": Param(
            "",
            "template file, template scan, point cloud (.npy) or, for stereo, camera.json (pose; optional)",
            type="str",
        ),
        "rig": Param(
            "",
            "for source points or stereo: rig file (twinfocus rig), the camera's offset applied to the cloud",
            type="str",
        ),
        "stereo_every": Param(0, "for source stereo: rebuild the cloud from every n-th frame (0: the first only)"),
        "scenario": Param({}, "for source sim: the Scenario fields (as the simulated drivers)", type="any"),
        "reference_roi": Param(REQUIRED, "reference region X0 X1 Y0 Y1 Z, metres", type="floats"),
        "size": Param(100, "template size in pixels per side (the solver's size)"),
        "oversample": Param(16, "range-profile oversampling of the back-projection"),
        "precision": Param("float32", "float32 or float64", choices=("float32", "float64")),
        "cache": Param(
            True, "reuse a template scan's image from the template cache (twinfocus.twins.cache) and store it there"
        ),
        "republish_s": Param(
            0.0, "publish the template again this often (0: once; the topic is latched, so late joiners still get it)"
        ),
    }

    def __init__(self, **kw):
        super().__init__(**kw)

        p = self.params
        if len(p["reference_roi"]) != 5:
            raise TwinFocusError(
                f"node {self.name!r}: reference_roi needs 5 numbers X0 X1 Y0 Y1 Z, got {p['reference_roi']}"
            )
        self.grid = ImageGrid.from_roi(p["reference_roi"], p["size"])
        self.bp = {"oversample": p["oversample"], "precision": p["precision"]}
        # latched: a node that starts (or restarts) after the template went out still gets it
        self.pub = self.create_publisher("twin/template", latched=True)
        self.msg: TwinTemplate | None = None
        self.cache_status: str | None = None  # of a template scan's image: "hit", "miss" or "off"
        src, path = p["source"], p["path"]
        if src in ("file", "scan", "points") and not path:
            raise TwinFocusError(f"node {self.name!r}: source {src!r} needs the 'path' parameter")
        self.rig = None  # (offset (3,) metres, its record) from the 'rig' parameter
        if p["rig"]:
            if src not in ("points", "stereo"):
                raise TwinFocusError(f"node {self.name!r}: 'rig' moves a camera's cloud: source points or stereo")

            rig = Rig.load(p["rig"])
            rig.check(default_board().name, camera_identity(path) if src == "points" else None, p["rig"])
            self.rig = (rig.offset_m, {"path": p["rig"], "sha256": file_sha256(p["rig"]),
                                       "reference_moved_m": rig.offset_m.tolist(), "sd_m": rig.sd_m.tolist()})  # fmt: skip
        if src in ("points", "stereo"):
            self.points = None
            self.positions: list[np.ndarray] = []
            self.scan_id = None
            if src == "points":
                self.points = load_points(path, allow_non_finite=True)
            else:
                self.pose = (
                    StereoCamera.load(path).scene_from_left
                    if path
                    else pose_matrix(None, DEFAULT_LEFT_CAMERA_POSITION_M)
                )
                self.frames = 0
                self.cloud_info: dict = {}
                self.create_subscription("camera/stereo", self.on_stereo)
            self.create_subscription("sar/measurement", self.on_measurement)
        else:
            # Built before the graph starts, so it is ready when the first scan ends.
            self.msg = self._build_static(src, path)

    def _build_static(self, src: str, path: str) -> TwinTemplate:
        from twinfocus.twins.templates import load_template, template_from_scan  # lazy: numba (+2.1 s at import)

        # a physical twin's phase travels with it (TwinTemplate.phase_rad): the solver's closed form needs it
        if src == "file":
            image, support, info = load_template(path, self.grid, with_outline=True)
            # a digital twin's file (twinfocus twin --out) brings its outline: the solver's outline estimator
            return self._message(image, "physical" if support is None else "digital", path, support, info)
        cache = TemplateCache(enabled=bool(self.params["cache"]))
        if src == "scan":
            key = template_scan_key(path, self.grid, self.bp, cache.root) if cache.enabled else None
            load = lambda: Scan.load(path)  # noqa: E731 (only on a miss)
            source = path
        else:
            from nodes.runtime.sim_backends import scenario_from, template_scan  # lazy: numba, cv2 (+2.1 s at import)

            sc = scenario_from({"scenario": self.params["scenario"] or {}}, f"node {self.name!r}")
            scan = template_scan(sc)
            c = scan.chirp
            # keyed by what was simulated, not by the scenario's fields: a changed simulator is a miss
            key = (
                template_key(
                    "template_scan",
                    {
                        "scan_sha256": array_sha256(scan.data, scan.positions),
                        "keep_phase": True,
                        "chirp": [c.f0_hz, c.slope_hz_per_s, c.fs_hz, c.n_samples],
                    },
                    self.grid,
                    self.bp,
                )
                if cache.enabled
                else None
            )
            load = lambda: scan  # noqa: E731
            source = "simulated motion-stage scan"
        image, self.cache_status = cache.get_or_compute(
            key, self.grid, lambda: template_from_scan(load(), self.grid, keep_phase=True, **self.bp)
        )
        if self.cache_status == "hit" and key is not None:  # a hit has a key
            self.log(f"template scan's image from the cache ({cache.path(key)})")
        if cache.warning:
            self.log(f"warning: {cache.warning}")
        return self._message(image, "physical", source)

    def _message(
        self, image: np.ndarray, kind: str, source: str, support: np.ndarray | None = None, info: dict | None = None
    ) -> TwinTemplate:
        g = self.grid
        image = np.asarray(image)
        phase = np.angle(image).astype(np.float32) if np.iscomplexobj(image) else None
        return TwinTemplate(
            header=Header(stamp_ns=now_ns(), frame_id="scene"),
            image=np.abs(image).astype(np.float32),
            phase_rad=phase,
            support=support,
            x_m=g.x_m,
            y_m=g.y_m,
            z_m=g.z,
            kind=kind,
            source=str(source),
            surface=str((info or {}).get("surface", "")),
            curved=bool((info or {}).get("curved", False)),
            curvature_m=float((info or {}).get("curvature_m", 0.0)),
        )

    def on_start(self) -> None:
        if self.msg is not None:
            self._send()
            if self.params["republish_s"] > 0:
                self.create_timer(self.params["republish_s"], self._send)

    def _send(self) -> None:
        assert self.msg is not None, "scheduled only once the template is built"
        self.msg.header.stamp_ns = now_ns()
        self.pub.publish(self.msg)
        self.status_message = f"published {self.msg.kind} template from {self.msg.source}"
        if self.pub.seq == 1:
            self.log(self.status_message)

    def on_stereo(self, f: StereoFrame) -> None:
        every = int(self.params["stereo_every"])
        self.frames += 1
        if self.points is not None and (every <= 0 or (self.frames - 1) % every):
            return
        try:
            points, info = stereo_cloud(f, self.pose, self.params["reference_roi"])
        except TwinFocusError as exc:
            self.log(f"stereo frame {self.frames}: no reference cloud ({exc}); trying the next frame")
            return
        self.points, self.cloud_info = points, info
        self.log(
            f"reference cloud from stereo frame {self.frames}: {points.shape[0]} points ({info['surface']} surface)"
        )

    def on_measurement(self, m: SarMeasurement) -> None:
        from twinfocus.twins.digital_twin.condition import (
            digital_twin_reference,  # lazy: open3d, scipy.ndimage (+4.3 s at import)
        )

        if m.scan_id != self.scan_id:
            self.scan_id, self.positions = m.scan_id, []
        self.positions.append(np.asarray(m.positions_m))
        if m.last:
            positions = np.stack(self.positions)
            self.positions = []
            if self.points is None:
                self.log(f"scan {m.scan_id} ended before any camera/stereo frame gave a reference cloud: no template")
                return
            try:
                offset = None if self.rig is None else self.rig[0]
                ref = digital_twin_reference(self.points, positions, m.chirp(), self.grid, offset_m=offset, **self.bp)
                if self.rig is not None:
                    ref.info["rig"] = self.rig[1]
            except TwinFocusError as exc:
                self.log(f"scan {m.scan_id}: no digital-twin template ({exc})")
                return
            source = self.params["path"] if self.params["source"] == "points" else f"camera/stereo frame {self.frames}"
            self.twin_info = ref.info
            # the outline travels with the template: with it the solver's auto takes the outline estimator
            self.msg = self._message(
                ref.template,
                "digital",
                f"{source} (scan {m.scan_id}, {ref.surface} surface)",
                support=ref.support,
                info=ref.info,
            )
            self._send()


def stereo_cloud(frame: StereoFrame, scene_from_left: np.ndarray, reference_roi) -> tuple[np.ndarray, dict]:
    """The reference's cloud (float64 (N, 3), scene frame) from one rectified stereo frame, with
    the stages of :mod:`twinfocus.twins.digital_twin` seeded by ``reference_roi`` projected into the
    left picture; and a summary dict."""
    import cv2

    from twinfocus.twins.digital_twin.pipeline import reference_from_stereo  # lazy: open3d (+4.3 s at import)

    k = np.asarray(frame.camera_matrix, dtype=np.float64)
    h, w = frame.left.shape[:2]
    eye = Intrinsics(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]), int(w), int(h))
    camera = StereoCamera(eye, eye, np.eye(3), np.array([-float(frame.baseline_m), 0.0, 0.0]), scene_from_left)
    # StereoFrame carries RGB (or grey); the stages take OpenCV's BGR.
    left, right = (
        cv2.cvtColor(x, cv2.COLOR_GRAY2BGR if x.ndim == 2 else cv2.COLOR_RGB2BGR) for x in (frame.left, frame.right)
    )
    twin = reference_from_stereo(left, right, camera, box_from_scene_roi(list(reference_roi), camera))
    return twin.points_m, twin.summary()


def main(argv: list[str] | None = None) -> int:
    return run_node(TemplateBuilder, argv)


if __name__ == "__main__":
    sys.exit(main())
