"""Visualizer node: PNGs on disk and a small live web page on localhost.

Listens to ``vio/pose`` and ``sar/measurement`` (the trajectory and the phase centres actually
used), ``image/focused`` (defocused and focused images) and ``autofocus/result`` (loss curve,
metrics). Writes into ``out_dir`` (each file replaced atomically):

* ``defocused.png`` / ``focused.png``: the target before / after the correction,
  ``reference_defocused.png`` / ``reference.png``: the reference region. Pixel (i, j) is image
  pixel (i, j) (row 0 = Y0 at the top, x to the right: the scene seen from the radar), value
  ``|image| / max |image|`` through OpenCV's inferno colour map;
* ``trajectory.png``: tracked poses and phase-centre positions in the aperture plane;
* ``loss.png``: the optimiser's loss per iteration.

The page at ``http://HOST:PORT/`` (loopback by default) shows them and refreshes itself from
``/state.json`` once a second; each ``<img>`` records ``data-loaded`` and its natural size
when it has loaded (the browser test reads these).
"""

from __future__ import annotations

import html
import io
import json
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np

from msgs import AutofocusResult, Image, Pose, SarMeasurement
from nodes.runtime.node import Node, run_node
from nodes.runtime.params import Param
from twinfocus.errors import TwinFocusError
from twinfocus.io.atomic import write_bytes_atomic

PANELS = (
    ("trajectory", "trajectory (aperture plane)"),
    ("defocused", "target, uncorrected"),
    ("focused", "target, focused"),
    ("reference_defocused", "reference, uncorrected"),
    ("reference", "reference, focused"),
    ("loss", "loss per iteration"),
)
IMAGE_FILES = {
    "target_uncorrected": "defocused",
    "target": "focused",
    "reference_uncorrected": "reference_defocused",
    "reference": "reference",
}


def amplitude_png(image: np.ndarray) -> bytes:
    """PNG of |image| / max through the inferno colour map, pixel (i, j) = image (i, j)."""
    import cv2

    amp = np.abs(np.asarray(image)).astype(np.float64)
    peak = amp.max()
    u8 = np.round(255.0 * (amp / peak if peak > 0 else amp)).astype(np.uint8)
    ok, buf = cv2.imencode(".png", cv2.applyColorMap(u8, cv2.COLORMAP_INFERNO))
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def _figure_png(draw) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.2, 3.4))
    draw(ax)
    fig.tight_layout()
    bio = io.BytesIO()
    fig.savefig(bio, format="png", dpi=100)
    plt.close(fig)
    return bio.getvalue()


PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>TwinFocus</title>
<style>
body {{ font-family: sans-serif; margin: 1em; background: #111; color: #ddd; }}
.panels {{ display: flex; flex-wrap: wrap; gap: 1em; }}
figure {{ margin: 0; }}
figure img {{ width: 320px; image-rendering: pixelated; background: #222; min-height: 40px; }}
figcaption {{ font-size: 0.9em; }}
pre {{ font-size: 0.85em; }}
</style></head>
<body>
<h1>TwinFocus</h1>
<div id="status">{status}</div>
<div class="panels">
{figures}
</div>
<pre id="metrics">{metrics}</pre>
<script>
function loaded(img) {{
  img.dataset.loaded = "1";
  img.dataset.naturalWidth = img.naturalWidth;
  img.dataset.naturalHeight = img.naturalHeight;
}}
async function poll() {{
  try {{
    const s = await (await fetch("/state.json", {{cache: "no-store"}})).json();
    for (const [name, v] of Object.entries(s.versions)) {{
      const img = document.getElementById(name);
      if (img && img.dataset.v !== String(v)) {{ img.dataset.v = String(v); img.src = "/" + name + ".png?v=" + v; }}
    }}
    document.getElementById("status").textContent = s.status;
    document.getElementById("metrics").textContent = s.metrics;
  }} catch (e) {{ document.getElementById("status").textContent = "visualizer not reachable"; }}
}}
setInterval(poll, 1000);
</script>
</body></html>
"""


class Visualizer(Node):
    """Write PNGs and serve a live page."""

    NAME = "visualizer"
    PARAMS = {
        **Node.PARAMS,
        "out_dir": Param("visualizer_out", "folder for the PNGs", type="str"),
        "host": Param("127.0.0.1", "address the web page listens on (loopback by default)", type="str"),
        "port": Param(8765, "port of the web page; 0 = any free port (printed)"),
        "serve": Param(True, "serve the web page"),
        "exit_after_results": Param(
            0,
            "end the node after this many scans (images and final result, or the solver's word that "
            "it dropped one: then with status 1; 0: never)",
        ),
        "max_points": Param(20000, "trajectory points kept for the plot"),
    }

    def __init__(self, **kw):
        super().__init__(**kw)
        self.out_dir = Path(self.params["out_dir"])
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.lock = threading.Lock()
        self.pngs: dict[str, bytes] = {}
        self.versions: dict[str, int] = {}
        self.status = "waiting for data"
        self.metrics_text = ""
        self.poses: list[np.ndarray] = []
        self.centres: list[np.ndarray] = []
        self.trajectory_dirty = False
        self.results = 0
        self.dropped: list[str] = []  # why each scan that was not focused was not
        self.server: ThreadingHTTPServer | None = None
        self.create_subscription("vio/pose", self.on_pose)
        self.create_subscription("sar/measurement", self.on_measurement)
        self.create_subscription("image/focused", self.on_image)
        self.create_subscription("autofocus/result", self.on_result)
        # Capture gaps (sensors helper): the radar frames carry the capture board's loss counts.
        self.gaps_text = ""
        self.create_subscription("radar/frame", self.on_radar_frame)
        if self.params["serve"]:
            self._start_server()

    # -- web page -----------------------------------------------------------------------------
    def _start_server(self) -> None:
        node = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):  # quiet: the launcher's output is for the nodes
                pass

            def _send(self, code: int, body: bytes, ctype: str) -> None:
                self.send_response(code)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

            def do_GET(self):
                path = self.path.split("?", 1)[0]
                if path in ("/", "/index.html"):
                    self._send(200, node.page().encode(), "text/html; charset=utf-8")
                elif path == "/state.json":
                    self._send(200, json.dumps(node.page_state()).encode(), "application/json")
                elif path.endswith(".png") and path[1:-4] in node.pngs:
                    with node.lock:
                        body = node.pngs[path[1:-4]]
                    self._send(200, body, "image/png")
                else:
                    self._send(404, b"not found", "text/plain")

        try:
            self.server = ThreadingHTTPServer((self.params["host"], int(self.params["port"])), Handler)
        except OSError as exc:
            raise TwinFocusError(
                f"node {self.name!r}: cannot serve the page on {self.params['host']}:{self.params['port']} ({exc.strerror})"
            ) from None
        self.server.daemon_threads = True
        threading.Thread(target=self.server.serve_forever, name="visualizer-http", daemon=True).start()
        host, port = self.server.socket.getsockname()[:2]  # the TCP server's (host, port) as bound
        self.url = f"http://{host}:{port}/"
        self.log(f"live page at {self.url}")
        self.status_message = f"page at {self.url}"

    def page_state(self) -> dict:
        with self.lock:
            return {
                "versions": dict(self.versions),
                "status": self.status + self.gaps_text,
                "metrics": self.metrics_text,
            }

    def page(self) -> str:
        with self.lock:
            figs = []
            for name, caption in PANELS:
                v = self.versions.get(name)
                src = f' src="/{name}.png?v={v}" data-v="{v}"' if v is not None else ""
                figs.append(
                    f'<figure><img id="{name}" alt="{html.escape(caption)}"{src} onload="loaded(this)">'
                    f"<figcaption>{html.escape(caption)}</figcaption></figure>"
                )
            return PAGE.format(
                status=html.escape(self.status + self.gaps_text),
                figures="\n".join(figs),
                metrics=html.escape(self.metrics_text),
            )

    # -- outputs ------------------------------------------------------------------------------
    def _store(self, name: str, png: bytes) -> None:
        write_bytes_atomic(self.out_dir / f"{name}.png", png)
        with self.lock:
            self.pngs[name] = png
            self.versions[name] = self.versions.get(name, 0) + 1

    def on_start(self) -> None:
        self.create_timer(1.0, self._render_trajectory)

    def on_pose(self, p: Pose) -> None:
        if len(self.poses) < self.params["max_points"]:
            self.poses.append(np.asarray(p.position_m))
            self.trajectory_dirty = True

    def on_measurement(self, m: SarMeasurement) -> None:
        if len(self.centres) < self.params["max_points"]:
            self.centres.append(np.asarray(m.positions_m).mean(axis=0))
            self.trajectory_dirty = True
        with self.lock:
            self.status = f"scan {m.scan_id!r}: {len(self.centres)} radar positions"

    # -- capture gaps (sensors helper) ---------------------------------------------------------
    def on_radar_frame(self, f) -> None:
        """Show the capture board's lost / zero-filled frames next to the status line."""
        if f.frames_lost or f.frames_zero_filled or f.bytes_lost:
            text = (
                f" | capture gaps: {f.frames_lost} frame(s) lost, {f.frames_zero_filled} zero-filled, "
                f"{f.bytes_lost} bytes missing"
            )
            with self.lock:
                self.gaps_text = text

    def _render_trajectory(self) -> None:
        if not self.trajectory_dirty:
            return
        self.trajectory_dirty = False
        poses = np.array(self.poses) if self.poses else np.zeros((0, 3))
        centres = np.array(self.centres) if self.centres else np.zeros((0, 3))

        def draw(ax):
            if len(poses):
                ax.plot(poses[:, 0] * 1e3, poses[:, 1] * 1e3, lw=0.6, color="0.6", label="tracked poses")
            if len(centres):
                ax.plot(
                    centres[:, 0] * 1e3, centres[:, 1] * 1e3, ".", ms=2, color="tab:orange", label="radar positions"
                )
            ax.set_xlabel("x (mm)")
            ax.set_ylabel("y (mm)")
            ax.invert_yaxis()  # the images' convention: y down
            ax.set_aspect("equal", adjustable="datalim")
            ax.legend(fontsize=7, loc="upper right")

        self._store("trajectory", _figure_png(draw))

    def on_image(self, msg: Image) -> None:
        name = IMAGE_FILES.get(msg.name)
        if name is None:
            return
        self._store(name, amplitude_png(msg.image))
        if msg.name == "target":
            self._render_trajectory()
            with self.lock:
                self.status = f"scan {msg.scan_id!r} focused"

    def on_result(self, r: AutofocusResult) -> None:
        if r.dropped:  # the scan will have no image: it still counts, and ends a run waiting for it
            with self.lock:
                self.status = f"scan {r.scan_id!r} not focused: {r.dropped}"
            self.dropped.append(f"scan {r.scan_id!r} not focused: {r.dropped}")
            self._count_result()
            return
        loss = np.asarray(r.loss_history)
        estimator = f" ({r.estimator} estimator)" if r.estimator else ""
        lines = [f"scan {r.scan_id}: method {r.method}{estimator}, {r.phase_rad.size} positions"]
        if r.latency_s > 0:
            lines.append(f"latency: {r.latency_s:.2f} s from the scan's last measurement to its focused image")
        if r.metrics_pending:
            lines.append("metrics against the truth: being computed")
        lines += [f"{k}: {v:.4g}" for k, v in sorted(r.metrics.items())]
        lines += [f"time {k}: {v:.3f} s" for k, v in sorted(r.timing_s.items())]
        with self.lock:
            self.metrics_text = "\n".join(lines)

        def draw(ax):
            if loss.size:
                ax.plot(np.arange(1, loss.size + 1), loss, color="tab:blue")
            ax.set_xlabel("iteration")
            ax.set_ylabel("loss (1 - SSIM)")
            ax.set_title(f"scan {r.scan_id} ({r.method})", fontsize=9)

        self._store("loss", _figure_png(draw))
        if not r.metrics_pending:  # the scan's last result: its images came before it
            self._count_result()

    def _count_result(self) -> None:
        self.results += 1
        n = int(self.params["exit_after_results"])
        if n and self.results >= n:
            if self.dropped:  # a run that stops here did not give what it was run for
                self.log(f"error: {self.dropped[-1]}")
                self.request_shutdown(self.dropped[-1], 1)
            else:
                self.request_shutdown(f"{self.results} focused scan(s) shown")

    def on_shutdown(self) -> None:
        if self.server is not None:
            self.server.shutdown()
            self.server.server_close()


def main(argv: list[str] | None = None) -> int:
    return run_node(Visualizer, argv)


if __name__ == "__main__":
    sys.exit(main())
