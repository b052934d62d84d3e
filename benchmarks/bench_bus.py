"""Node-graph benchmark: the message bus, and the solver's latency after a scan. Writes
``bus.json`` (and ``bus.md``, the same figures as a table) to the output folder.

    python -m benchmarks.bench_bus --out benchmarks/results [--quick]

1. Bus: a publisher process sends MMWCAS-sized radar frames (86 x 256 complex64 = 176 KB, the
   paper's radar at 10 Hz is 1.76 MB/s) through the broker to a subscriber process; the header
   stamp is the send time, so the subscriber measures the one-way latency (same clock).
   *Throughput*: frames sent back to back, MB/s and frames/s received (nothing may be lost:
   the count is checked). *Latency*: frames sent at a steady rate, p50 / p99 of send->callback.
   Small messages (poses) are measured the same way for the per-message overhead.
2. Scan end -> focused image: a solver process receives a scan's SAR measurements at the
   radar's rate and focuses it; the time from sending the last measurement to receiving the
   focused target image, with the sub-image basis accumulated as measurements arrive
   (``basis:=stream``) and computed after the scan (``basis:=after_scan``).
3. Live graph latency: ``launch/sim.yaml`` at the paper's size (780 positions x 86
   channels, 100 x 100) with the simulated sensors at real time (``rate:=1``); a probe on the
   bus takes the wall time the sweep's last ``radar/frame`` reaches it and the time the focused
   ``target`` image does. Also reported: the solver's own ``latency_s`` (last measurement in ->
   result out, the field the visualizer shows) and its step timings.

    python -m benchmarks.bench_bus --out benchmarks/results --graph-only [--repeat 3]   # part 3 alone

4. Live hand sweep: part 3 with ``trajectory:=zigzag error_model:=hand`` (the simulated tracker
   carries the hand's drift and the array's turn), so the solver fits the drift + tilt: the time
   from the last radar frame to the image, as ``live_hand_sweep``.

    python -m benchmarks.bench_bus --out benchmarks/results --hand-only [--quick] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path

import numpy as np

K, N = 86, 256


def _radar_frame(i: int):
    from msgs import Header, RadarFrame
    from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array

    c = Chirp()
    data = np.full((K, N), i, np.complex64)
    return RadarFrame(
        header=Header(frame_id="radar"),
        data=data,
        f0_hz=c.f0_hz,
        slope_hz_per_s=c.slope_hz_per_s,
        fs_hz=c.fs_hz,
        channel_offsets_m=mmwcas_virtual_array().offsets_m,
        index=i,
    )


def _pose(i: int):
    from msgs import Pose

    return Pose(position_m=np.array([i, 0.0, 0.0]), quat_xyzw=np.array([0.0, 0.0, 0.0, 1.0]))


def _publisher(endpoint: str, kind: str, n: int, rate_hz: float) -> None:
    from nodes.runtime.node import Node

    class Pub(Node):
        NAME = "bench_pub"

        def __init__(self, **kw):
            super().__init__(**kw)
            self.topic = "radar/frame" if kind == "radar" else "vio/pose"
            self.pub = self.create_publisher(self.topic)
            self.msgs = [(_radar_frame if kind == "radar" else _pose)(i) for i in range(min(n, 64))]
            self.i = 0

        def on_start(self):
            if rate_hz > 0:
                self.create_timer(1.0 / rate_hz, self.one)
            else:
                self.call_later(0, self.burst)

        def _send(self):
            m = self.msgs[self.i % len(self.msgs)]
            m.header.stamp_ns = time.time_ns()
            self.pub.publish(m)
            self.i += 1
            if self.i >= n:
                self.request_shutdown("done")

        def one(self):
            self._send()

        def burst(self):
            for _ in range(200):
                self._send()
                if self.i >= n:
                    return
            self.call_later(0, self.burst)

    Pub(broker=endpoint, params={"wait_for": ["bench_sub"], "heartbeat_s": 0.5}).spin()


def _subscriber(endpoint: str, kind: str, n: int, out) -> None:
    from nodes.runtime.node import Node

    class Sub(Node):
        NAME = "bench_sub"

        def __init__(self, **kw):
            super().__init__(**kw)
            self.lat = np.empty(n)
            self.t = np.empty(n)
            self.k = 0
            self.create_subscription("radar/frame" if kind == "radar" else "vio/pose", self.got)

        def got(self, msg):
            now = time.time_ns()
            self.lat[self.k] = (now - msg.header.stamp_ns) / 1e9
            self.t[self.k] = now / 1e9
            self.k += 1
            if self.k >= n:
                self.request_shutdown("done")

    s = Sub(broker=endpoint, params={"heartbeat_s": 0.5, "ready_timeout_s": 60})
    code = s.spin()
    out.put(
        {"code": code, "received": s.k, "lat": s.lat[: s.k].tolist(), "t": s.t[: s.k].tolist(), "lost": dict(s._lost)}
    )


def bus_run(kind: str, n: int, rate_hz: float) -> dict:
    from nodes.runtime.bus import Broker

    ctx = mp.get_context("spawn")  # a fork would inherit the broker's ZeroMQ context
    q = ctx.Queue()
    with Broker("tcp://127.0.0.1:0") as b:
        sub = ctx.Process(target=_subscriber, args=(b.endpoint, kind, n, q))
        sub.start()
        pub = ctx.Process(target=_publisher, args=(b.endpoint, kind, n, rate_hz))
        pub.start()
        res = q.get(timeout=300)
        pub.join(60)
        sub.join(60)
    lat = np.asarray(res["lat"])
    t = np.asarray(res["t"])
    nbytes = K * N * 8 if kind == "radar" else 7 * 8
    span = t[-1] - t[0] if t.size > 1 else float("nan")
    return {
        "message": "RadarFrame 86x256 complex64 (176 KB)" if kind == "radar" else "Pose",
        "sent": n,
        "received": res["received"],
        "lost": res["lost"],
        "send_rate_hz": rate_hz or "max",
        "msgs_per_s": (t.size - 1) / span,
        "payload_MB_per_s": (t.size - 1) * nbytes / span / 1e6,
        "latency_p50_ms": float(np.percentile(lat, 50) * 1e3),
        "latency_p99_ms": float(np.percentile(lat, 99) * 1e3),
        "latency_max_ms": float(lat.max() * 1e3),
    }


# --- scan end -> focused image -----------------------------------------------------------------


def _scan(columns: int, rows: int):
    from twinfocus.motion.trajectory import paper_raster, phase_centres
    from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
    from twinfocus.simulation.if_simulator import add_thermal_noise, simulate_if

    pos = phase_centres(paper_raster(columns, rows), mmwcas_virtual_array())
    # A few bright points in each region: enough signal for the solver's checks, cheap to simulate.
    pts = np.array([[-0.10, -0.05, 0.6], [-0.05, 0.05, 0.6], [-0.08, 0.0, 0.6], [0.05, 0.0, 0.6], [0.1, -0.05, 0.6]])
    data = add_thermal_noise(simulate_if(pts, np.ones(len(pts)), pos, Chirp()), 10.0, 0)
    return data, pos


def latency_run(mode: str, columns: int, rows: int, size: int, iterations: int, rate_hz: float) -> dict:
    import subprocess

    from msgs import Header, SarMeasurement, TwinTemplate
    from nodes.runtime.bus import Broker
    from nodes.runtime.testing import Probe, running
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.radar.fmcw import Chirp

    data, pos = _scan(columns, rows)
    c = Chirp()
    ref, tgt = [-0.15, 0.0, -0.11, 0.12, 0.6], [0.02, 0.13, -0.11, 0.12, 0.6]
    g = ImageGrid.from_roi(ref, size)
    from twinfocus.imaging.backprojection.numba_backend import backproject

    tpl = np.abs(backproject(data, pos, c, g)).astype(np.float32)  # the reference as focused on exact positions
    with Broker("tcp://127.0.0.1:0") as b:
        params = {
            "reference_roi": ref,
            "target_roi": tgt,
            "size": size,
            "iterations": iterations,
            "basis": mode,
            "truth_metrics": False,
            "wait_for": [],
        }
        repo = str(Path(__file__).resolve().parent.parent)
        solver = subprocess.Popen(
            [sys.executable, "-m", "nodes.solver", "--broker", b.endpoint, "--params", json.dumps(params)],
            cwd=repo,
            env={**os.environ, "PYTHONPATH": repo},
        )
        try:
            probe = Probe(
                b.endpoint,
                listen=["image/focused", "autofocus/result"],
                publish=["sar/measurement", "twin/template"],
                wait_for=["solver"],
                name="bench_probe",
                params={"ready_timeout_s": 120},
            )
            with running(probe, start_timeout_s=120):
                probe.send("twin/template", TwinTemplate(image=tpl, x_m=g.x_m, y_m=g.y_m, z_m=0.6))
                m_total = data.shape[0]
                t0 = time.monotonic()
                for m in range(m_total):
                    due = t0 + m / rate_hz
                    while time.monotonic() < due:
                        time.sleep(0.001)
                    probe.send(
                        "sar/measurement",
                        SarMeasurement(
                            header=Header(stamp_ns=m),
                            data=data[m],
                            positions_m=pos[m],
                            f0_hz=c.f0_hz,
                            slope_hz_per_s=c.slope_hz_per_s,
                            fs_hz=c.fs_hz,
                            scan_id="bench",
                            index=m,
                            last=m == m_total - 1,
                        ),
                    )
                probe.sent_all(60)
                t_last = time.monotonic()
                probe.wait_for(
                    "image/focused",
                    1,
                    timeout_s=float(os.environ.get("BENCH_TIMEOUT", 1800)),
                    where=lambda i: i.name == "target",
                )
                t_image = probe.arrival["image/focused"][-1]
                (res,) = probe.wait_for("autofocus/result", 1)
        finally:
            solver.terminate()
            solver.wait(30)
    return {
        "basis": mode,
        "positions": int(data.shape[0]),
        "image": f"{size}x{size} (reference and target)",
        "iterations": iterations,
        "feed_rate_hz": rate_hz,
        "last_measurement_to_focused_image_s": t_image - t_last,
        "solver_timing_s": res.timing_s,
    }


def graph_latency_run(
    columns: int, rows: int, size: int, rate: float, iterations: int = 300, hand: bool = False
) -> dict:
    """``twinfocus launch sim`` with a probe: last radar frame of the sweep -> focused target image.
    ``hand``: a hand sweep (``trajectory:=zigzag error_model:=hand``: the hand's drift and the
    array's turn in the tracked poses), whose drift + tilt fit runs in the solver."""
    import socket
    import subprocess
    import tempfile

    from nodes.runtime.testing import Probe, running

    def free_port() -> int:
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            return sock.getsockname()[1]

    repo = str(Path(__file__).resolve().parent.parent)
    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [
            sys.executable,
            "-c",
            "import sys; from twinfocus.cli import main; sys.exit(main())",
            "launch",
            "sim",
            f"port:={port}",
            "web_port:=0",
            f"out:={tmp}",
            f"columns:={columns}",
            f"rows:={rows}",
            f"size:={size}",
            f"rate:={rate}",
            f"iterations:={iterations}",
            "exit_after:=1",
        ]
        if hand:
            cmd += ["trajectory:=zigzag", "error_model:=hand"]
        log = Path(tmp) / "graph.log"
        with open(log, "wb") as out:
            g = subprocess.Popen(
                cmd, cwd=repo, env={**os.environ, "PYTHONPATH": repo}, stdout=out, stderr=subprocess.STDOUT
            )
        try:
            probe = Probe(
                f"tcp://127.0.0.1:{port}",
                name="bench_graph_probe",
                params={"ready_timeout_s": 300},
                listen=["radar/frame", "vio/pose", "sar/measurement", "image/focused", "autofocus/result"],
            )
            with running(probe, start_timeout_s=300):
                load_before = os.getloadavg()
                deadline = time.monotonic() + float(os.environ.get("BENCH_TIMEOUT", 1800))
                while True:  # the graph's image, unless the graph ended without one (a node refused to start)
                    try:
                        probe.wait_for("image/focused", 1, timeout_s=2, where=lambda i: i.name == "target")
                        break
                    except TimeoutError:
                        if g.poll() is not None:
                            tail = log.read_text(errors="replace").strip().splitlines()[-5:]
                            raise RuntimeError(
                                f"the graph ended (status {g.returncode}) before its image: " + " / ".join(tail)
                            ) from None
                        if time.monotonic() > deadline:
                            raise
                res = probe.wait_for("autofocus/result", 1, timeout_s=60)[0]  # the one published with the image
                load_after = os.getloadavg()
                # the truth metrics (simulation) follow in a second result
                final = probe.wait_for("autofocus/result", 1, timeout_s=300, where=lambda r: not r.metrics_pending)[0]
                frames = probe.received["radar/frame"]
                last = [i for i, f in enumerate(frames) if f.last]
                t_last = probe.arrival["radar/frame"][last[0]] if last else float("nan")
                # the first pose at or after the last frame's stamp: what the synchronizer waits for
                stamp = frames[last[0]].header.stamp_ns if last else None
                after = [
                    i
                    for i, p in enumerate(probe.received["vio/pose"])
                    if stamp is not None and p.header.stamp_ns >= stamp
                ]
                t_pose = probe.arrival["vio/pose"][after[0]] if after else float("nan")
                ends = [i for i, m in enumerate(probe.received["sar/measurement"]) if m.last]
                t_meas = probe.arrival["sar/measurement"][ends[0]] if ends else float("nan")
                names = [i.name for i in probe.received["image/focused"]]
                t_image = probe.arrival["image/focused"][names.index("target")]
        finally:
            g.wait(120)
    return {
        "graph": "launch/sim.yaml" + (" trajectory:=zigzag error_model:=hand" if hand else ""),
        "positions": int(res.phase_rad.size),
        "frames_seen_by_probe": len(frames),
        "image": f"{size}x{size}",
        "sensor_rate": rate,
        "last_radar_frame_to_focused_image_s": t_image - t_last,
        # the same span cut where the probe saw each step (the pose the last frame needs, the
        # synchronizer's last measurement, the image); a negative wait: the pose came first
        "stages_s": {
            "last_frame_to_its_pose": t_pose - t_last,
            "pose_to_last_measurement": t_meas - max(t_pose, t_last),
            "last_measurement_to_focused_image": t_image - t_meas,
        },
        "solver_latency_s": float(res.latency_s),
        "solver_timing_s": res.timing_s,
        "target_ssim": {k: final.metrics.get(f"target_ssim_{k}") for k in ("uncorrected", "corrected")},
        "solver_metrics": {k: v for k, v in final.metrics.items() if k.startswith("space_variant_streamed.")},
        "load_average_1min": [load_before[0], load_after[0]],
    }


def graph_latency(repeat: int, *args) -> dict:
    """:func:`graph_latency_run` ``repeat`` times (the load of a shared machine moves the figures):
    the mean of each time, its range over the runs (``spread_s``), and every run."""
    runs = [graph_latency_run(*args) for _ in range(max(1, repeat))]
    if len(runs) == 1:
        return runs[0]
    mean = {
        k: float(np.mean([r[k] for r in runs])) for k in ("last_radar_frame_to_focused_image_s", "solver_latency_s")
    }
    return {
        **{k: v for k, v in runs[0].items() if k in ("graph", "positions", "image", "sensor_rate")},
        **mean,
        "spread_s": {k: [float(min(r[k] for r in runs)), float(max(r[k] for r in runs))] for k in mean},
        "stages_s": {k: float(np.mean([r["stages_s"][k] for r in runs])) for k in runs[0]["stages_s"]},
        "runs": runs,
    }


def hand_sweep(out: Path, quick: bool, repeat: int) -> dict:
    """The live graph's hand sweep (:func:`graph_latency_run` with ``hand``), added to bus.json as
    ``live_hand_sweep``: the time from the sweep's last radar frame to the focused image, with the
    drift + tilt fit in it."""
    sizes = (2, 40, 40, 1.0) if quick else (6, 130, 100, 1.0)
    runs = [graph_latency_run(*sizes, hand=True) for _ in range(max(1, repeat))]
    key = "last_radar_frame_to_focused_image_s"
    timing, metrics = runs[0]["solver_timing_s"], runs[0].get("solver_metrics", {})
    after, streamed = timing.get("space_variant", 0.0), timing.get("space_variant_streamed", 0.0)
    hand = {
        **runs[0],
        # the drift + tilt fit: after the last frame (warm-started) against all of its work for the
        # scan (the fits streamed during the sweep too), in the same run
        "drift_fit_s": {
            "after_last_frame": after,
            "streamed": streamed,
            "streamed_fits": metrics.get("space_variant_streamed.fits", 0.0),
            "warm_start_positions": metrics.get("space_variant_streamed.warm_start_positions", 0.0),
            "after_share_of_whole": after / (after + streamed) if after + streamed > 0 else None,
        },
        "runs": len(runs),
        key: float(np.mean([r[key] for r in runs])),
        "spread_s": [float(min(r[key] for r in runs)), float(max(r[key] for r in runs))],
        "command": "python -m benchmarks.bench_bus --hand-only"
        + (" --quick" if quick else "")
        + (f" --repeat {repeat}" if repeat > 1 else ""),
    }
    prev = json.loads((out / "bus.json").read_text()) if (out / "bus.json").is_file() else {}
    prev["live_hand_sweep"] = hand
    (out / "bus.json").write_text(json.dumps(prev, indent=2, default=float))
    print(json.dumps(hand, indent=2, default=float))
    return hand


def main(
    out_dir: str | Path = "benchmarks/results",
    quick: bool = False,
    graph_only: bool = False,
    repeat: int = 1,
    hand_only: bool = False,
) -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if hand_only:
        return hand_sweep(out, quick, repeat)
    graph = graph_latency(repeat, *((2, 40, 40, 1.0) if quick else (6, 130, 100, 1.0)))
    if graph_only:
        prev = json.loads((out / "bus.json").read_text()) if (out / "bus.json").is_file() else {}
        prev["live_graph"] = graph
        (out / "bus.json").write_text(json.dumps(prev, indent=2, default=float))
        print(json.dumps(graph, indent=2, default=float))
        return prev
    n_big = 300 if quick else 2000
    results = {
        "bus": [
            bus_run("radar", n_big, 0.0),
            bus_run("radar", 200 if quick else 1000, 100.0),
            bus_run("pose", 5000 if quick else 50000, 0.0),
            bus_run("pose", 500 if quick else 2000, 200.0),
        ],
        "scan_end_to_image": [],
        "live_graph": graph,
    }
    prev_hand = (
        json.loads((out / "bus.json").read_text()).get("live_hand_sweep") if (out / "bus.json").is_file() else None
    )
    if prev_hand is not None:  # measured by --hand-only (minutes of its own): kept
        results["live_hand_sweep"] = prev_hand
    cols, rows, size, iters, rate = (2, 40, 40, 30, 20.0) if quick else (6, 130, 100, 300, 10.0)
    for mode in ("stream", "after_scan"):
        results["scan_end_to_image"].append(latency_run(mode, cols, rows, size, iters, rate))
    results["command"] = "python -m benchmarks.bench_bus" + (" --quick" if quick else "")
    (out / "bus.json").write_text(json.dumps(results, indent=2, default=float))
    lines = ["| message | send rate | received | msgs/s | MB/s | p50 ms | p99 ms |", "|---|---|---|---|---|---|---|"]
    for r in results["bus"]:
        lines.append(
            f"| {r['message']} | {r['send_rate_hz']} | {r['received']}/{r['sent']} | {r['msgs_per_s']:.0f} | "
            f"{r['payload_MB_per_s']:.1f} | {r['latency_p50_ms']:.2f} | {r['latency_p99_ms']:.2f} |"
        )
    lines += [
        "",
        "| basis | positions | image | iterations | feed Hz | last measurement -> focused image (s) |",
        "|---|---|---|---|---|---|",
    ]
    for r in results["scan_end_to_image"]:
        lines.append(
            f"| {r['basis']} | {r['positions']} | {r['image']} | {r['iterations']} | {r['feed_rate_hz']:g} | "
            f"{r['last_measurement_to_focused_image_s']:.2f} |"
        )
    lines += [
        "",
        "| graph | positions | image | sensor rate | last radar frame -> focused image (s) | solver latency_s |",
        "|---|---|---|---|---|---|",
        f"| {graph['graph']} | {graph['positions']} | {graph['image']} | {graph['sensor_rate']:g} | "
        f"{graph['last_radar_frame_to_focused_image_s']:.2f} | {graph['solver_latency_s']:.2f} |",
    ]
    (out / "bus.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return results


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--quick", action="store_true", help="small sizes (a minute), for checking the script")
    ap.add_argument(
        "--graph-only", action="store_true", help="only the live graph's latency (part 3), added to bus.json"
    )
    ap.add_argument(
        "--repeat", type=int, default=1, help="run the live graph this many times (mean, spread and each run)"
    )
    ap.add_argument(
        "--hand-only",
        action="store_true",
        help="only the live graph's hand sweep (trajectory:=zigzag error_model:=hand), added to bus.json",
    )
    a = ap.parse_args()
    main(a.out, a.quick, a.graph_only, a.repeat, a.hand_only)
