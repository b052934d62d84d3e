"""The runtime (bus, node base, parameters) and each node alone, fed constructed messages.

Nodes run in threads of this process around a loopback broker (:mod:`nodes.runtime.testing`); the
probe node publishes the inputs and records the outputs, over the real ZeroMQ bus.
"""

import json
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest
import zmq
from scipy.spatial.transform import Rotation, Slerp

from msgs import AutofocusResult, Header, Image, Pose, RadarFrame, TwinTemplate
from nodes.runtime.bus import Broker
from nodes.runtime.node import Node
from nodes.runtime.params import REQUIRED, Param, parse_assignment, resolve
from nodes.runtime.testing import Probe, local_broker, patience, running
from tests.helpers import sar_measurements
from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import Chirp

REPO = Path(__file__).resolve().parent.parent
CHIRP = Chirp(n_samples=64)


def pose(t, p=(0.0, 0.0, 0.0), q=(0.0, 0.0, 0.0, 1.0), child="radar"):
    return Pose(
        header=Header(stamp_ns=int(t), frame_id="scene"),
        position_m=np.asarray(p, float),
        quat_xyzw=np.asarray(q, float),
        child_frame_id=child,
    )


def frame(t, index, offsets, scan="s", last=False, fill=None):
    k = offsets.shape[0]
    data = np.full((k, CHIRP.n_samples), index if fill is None else fill, np.complex64)
    return RadarFrame(
        header=Header(stamp_ns=int(t), frame_id="radar"),
        data=data,
        f0_hz=CHIRP.f0_hz,
        slope_hz_per_s=CHIRP.slope_hz_per_s,
        fs_hz=CHIRP.fs_hz,
        channel_offsets_m=offsets,
        scan_id=scan,
        index=index,
        last=last,
    )


# --- parameters -------------------------------------------------------------------------------


def test_parameters_are_typed_by_their_defaults_and_errors_name_them():
    declared = {
        "rate": Param(1.0),
        "n": Param(3),
        "name": Param("x"),
        "on": Param(False),
        "roi": Param([], type="floats"),
        "must": Param(REQUIRED, "needed"),
    }
    got = resolve("demo", declared, {"rate": 2, "must": "yes"}, ["n:=7", "on:=true", "roi:=[1, 2.5]", "name:=007"])
    assert got == {"rate": 2.0, "n": 7, "name": "007", "on": True, "roi": [1.0, 2.5], "must": "yes"}
    assert parse_assignment("roi:=-0.1,0.2") == ("roi", "-0.1,0.2")
    assert resolve("demo", declared, {"must": 1, "roi": "-0.1,0.2"})["roi"] == [-0.1, 0.2]
    with pytest.raises(TwinFocusError, match="node 'demo': unknown parameter.*bogus"):
        resolve("demo", declared, {"must": 1, "bogus": 1})
    with pytest.raises(TwinFocusError, match="parameter 'must' is required"):
        resolve("demo", declared, {})
    with pytest.raises(TwinFocusError, match="parameter 'n' must be an integer"):
        resolve("demo", declared, {"must": 1, "n": 2.5})
    with pytest.raises(TwinFocusError, match="parameter 'on' must be true or false"):
        resolve("demo", declared, {"must": 1, "on": "maybe"})


def test_a_node_may_not_shadow_runtime_internals():
    with pytest.raises(TypeError, match="_dispatch"):

        class Bad(Node):  # noqa: F841
            def _dispatch(self, frames):
                pass


# --- bus semantics ----------------------------------------------------------------------------


class Burst(Node):
    """Publishes ``n`` poses on each of its topics as soon as the graph is ready."""

    NAME = "burst"

    def __init__(self, topics, n, skip_at=None, **kw):
        super().__init__(**kw)
        self.pubs = [self.create_publisher(t, Pose) for t in topics]
        self.n, self.skip_at = n, skip_at

    def on_start(self):
        for i in range(self.n):
            if i == self.skip_at:
                for p in self.pubs:
                    p.seq += 5  # as if five messages had been lost on the way
            for p in self.pubs:
                p.publish(pose(i, (i, 0, 0)))
        self.request_shutdown("done")


def test_exact_match_delivery_no_prefix_matching_and_no_slow_joiner_loss():
    with local_broker() as ep:
        exact = Probe(ep, listen=["vio/pose"], name="exact")
        burst = Burst(["vio/pose", "vio/pose_raw", "vio"], 300, broker=ep, params={"wait_for": ["exact"]})
        with running(exact):
            with running(burst):
                got = exact.wait_for("vio/pose", 300)
                time.sleep(0.3)
        # Published at once on start: none lost to the slow-joiner problem, none from the
        # prefix-sharing topics delivered.
        assert [m.header.seq for m in exact.received["vio/pose"]] == list(range(300))
        assert [m.position_m[0] for m in got] == list(range(300))
        assert exact._lost == {}


def test_wildcard_subscription_receives_every_topic():
    with local_broker() as ep:
        everything = []

        class All(Node):
            NAME = "all"

            def __init__(self, **kw):
                super().__init__(**kw)
                self.create_subscription("*", lambda topic, msg: everything.append(topic))

        sink = All(broker=ep)
        burst = Burst(["vio/pose", "vio/pose_raw"], 10, broker=ep, params={"wait_for": ["all"]})
        with running(sink):
            with running(burst):
                deadline = time.monotonic() + 10
                while sum(t.startswith("vio/") for t in everything) < 20 and time.monotonic() < deadline:
                    time.sleep(0.02)
        vio = [t for t in everything if t.startswith("vio/")]
        assert sorted(set(vio)) == ["vio/pose", "vio/pose_raw"] and len(vio) == 20
        assert "graph/status" in everything


def test_subscribers_detect_and_report_sequence_gaps(capfd):
    with local_broker() as ep:
        probe = Probe(ep, listen=["vio/pose"])
        burst = Burst(["vio/pose"], 20, skip_at=10, broker=ep, params={"wait_for": ["probe"]})
        with running(probe):
            with running(burst):
                probe.wait_for("vio/pose", 20)
        assert probe._lost == {"vio/pose": 5}
        seqs = [m.header.seq for m in probe.received["vio/pose"]]
        assert seqs == list(range(10)) + list(range(15, 25))
    assert "lost 5 message(s) on vio/pose from burst (seq 9 -> 15)" in capfd.readouterr().err


class HoldingBroker(Broker):
    """A broker whose forwarding of published messages can be held back (``hold``); libzmq's
    steerable proxy cannot be paused reliably (4.3.5 forwards through PAUSE)."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.hold = threading.Event()

    def _proxy_thread(self):
        xsub, xpub, steer = self.ctx.socket(zmq.XSUB), self.ctx.socket(zmq.XPUB), self.ctx.socket(zmq.PAIR)
        steer.connect(self._ctrl_addr)
        self.xsub_port = xsub.bind_to_random_port(f"tcp://{self.host}")
        self.xpub_port = xpub.bind_to_random_port(f"tcp://{self.host}")
        self._ready.set()
        poller = zmq.Poller()
        for sock in (xsub, xpub, steer):
            poller.register(sock, zmq.POLLIN)
        while True:
            events = dict(poller.poll(20))
            if steer in events:
                break
            if xpub in events:  # subscriptions always pass
                xsub.send_multipart(xpub.recv_multipart())
            if xsub in events and not self.hold.is_set():
                xpub.send_multipart(xsub.recv_multipart())
            elif self.hold.is_set():
                time.sleep(0.02)
        for sock in (xsub, xpub, steer):
            sock.close(linger=0)


@pytest.mark.slow  # 1.6 s (2 cores, idle): out of make test-fast (benchmarks/results/test_fast.json)
def test_a_node_leaves_only_after_the_broker_has_passed_on_what_it_published():
    # A publisher that exits the moment its queue is handed to the kernel can lose its tail
    # (CI lost the last two radar frames of a scan this way): shutdown waits until the node's
    # final heartbeat has come back through the broker, which a held broker holds back.
    broker = HoldingBroker("tcp://127.0.0.1:0").start()

    class HoldingBurst(Burst):
        def on_start(self):
            broker.hold.set()
            super().on_start()

    try:
        probe = Probe(broker.endpoint, listen=["vio/pose"])
        burst = HoldingBurst(["vio/pose"], 50, broker=broker.endpoint, params={"wait_for": ["probe"], "linger_s": 30})
        with running(probe):
            t = threading.Thread(target=burst.spin, daemon=True)
            t.start()
            time.sleep(1.5)
            assert t.is_alive()  # published everything and asked to stop, but still waiting
            assert len(probe.received.get("vio/pose", [])) <= 1  # the one in flight when the hold began
            broker.hold.clear()
            t.join(10)
            assert not t.is_alive() and burst.exit_code == 0
            assert [m.header.seq for m in probe.wait_for("vio/pose", 50)] == list(range(50))
    finally:
        broker.stop()


def test_a_node_process_stops_cleanly_on_sigint():
    with local_broker() as ep:
        watcher = Probe(ep, listen=["graph/status"], name="watcher")
        with running(watcher):
            proc = subprocess.Popen(
                [sys.executable, "-m", "nodes.synchronizer", "--broker", ep, "--name", "sync_proc"],
                cwd=REPO,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
            )
            try:
                watcher.wait_for(
                    "graph/status", 1, timeout_s=60, where=lambda s: s.node == "sync_proc" and s.state == "running"
                )
                proc.send_signal(signal.SIGINT)
                out, _ = proc.communicate(timeout=20)
            finally:
                if proc.poll() is None:
                    proc.kill()
            assert proc.returncode == 0, out.decode()
            final = watcher.wait_for("graph/status", 1, where=lambda s: s.node == "sync_proc" and s.state == "stopped")
            assert "SIGINT" in final[-1].message
        assert b"Traceback" not in out


# --- synchronizer -----------------------------------------------------------------------------


def test_synchronizer_interpolates_poses_and_reports_what_it_cannot_pair(capfd):
    from nodes.synchronizer import Synchronizer

    offsets = np.stack([np.linspace(-0.04, 0.04, 5), np.zeros(5), np.zeros(5)], axis=1)
    # Poses every 33 ms with a curving path and a turning orientation; a 0.5 s hole in the middle.
    t_pose = np.arange(0, 2_000_000_000, 33_333_333)
    t_pose = t_pose[(t_pose < 800_000_000) | (t_pose > 1_300_000_000)]
    pos = np.stack([0.1 * np.sin(t_pose / 1e9), 0.05 * t_pose / 1e9, 1e-3 * np.cos(3 * t_pose / 1e9)], axis=1)
    rot = Rotation.from_rotvec(np.stack([0.1 * t_pose / 1e9, 0.05 * np.sin(t_pose / 1e9), 0.2 * t_pose / 1e9], axis=1))
    quats = rot.as_quat()  # scipy: (x, y, z, w)
    t_frames = [-50_000_000, 100_000_000, 433_333_333, 700_000_000, 1_000_000_000, 1_500_000_000, 2_050_000_000]
    with local_broker() as ep:
        sync = Synchronizer(broker=ep, params={"max_pose_gap_s": 0.1, "max_wait_s": 1.0})
        probe = Probe(ep, listen=["sar/measurement"], publish=["vio/pose", "radar/frame"], wait_for=["synchronizer"])
        with running(sync, probe):
            for i in range(len(t_pose)):
                probe.send("vio/pose", pose(t_pose[i], pos[i], quats[i]))
            for i, t in enumerate(t_frames):
                probe.send("radar/frame", frame(t, i, offsets, last=i == len(t_frames) - 1))
            got = probe.wait_for("sar/measurement", 4, timeout_s=20)
            # the last frame (after every pose) is reported once max_wait_s of wall clock is over
            deadline = time.monotonic() + patience(60)
            while sync.unpaired < 3 and time.monotonic() < deadline:
                time.sleep(0.05)
            got = probe.received["sar/measurement"]
    err = capfd.readouterr().err
    # Frame 0 precedes the first pose, frame 4 falls in the hole, frame 6 has no later pose.
    assert [m.index for m in got] == [1, 2, 3, 5]
    assert "cannot pair radar frame 0" in err and "earlier than the oldest pose" in err
    assert "cannot pair radar frame 4" in err and "0.533 s apart" in err
    assert "cannot pair radar frame 6" in err and "no pose after it" in err
    # The scan's last frame could not be paired: the last one sent carries the end of scan.
    assert [m.last for m in got] == [False, False, False, True]
    truth_pos = lambda t: np.array([np.interp(t, t_pose, pos[:, j]) for j in range(3)])  # noqa: E731
    slerp = Slerp(t_pose.astype(float), rot)
    for m in got:
        t = m.header.stamp_ns
        expect = slerp([float(t)]).as_matrix()[0] @ offsets.T + truth_pos(t)[:, None]
        np.testing.assert_allclose(m.positions_m, expect.T, atol=1e-12)
        assert np.array_equal(m.data, np.full((5, CHIRP.n_samples), m.index, np.complex64))
        assert m.pose_gap_ns == 33_333_333 or m.pose_gap_ns == 33_333_334


def test_synchronizer_applies_camera_extrinsics():
    from nodes.synchronizer import Synchronizer
    from twinfocus.sensors.extrinsics import RadarCameraExtrinsics

    ext = RadarCameraExtrinsics(Rotation.from_rotvec([0, 0, 0.3]).as_matrix(), np.array([0.05, -0.02, 0.01]))
    offsets = np.array([[-0.01, 0, 0], [0.01, 0, 0.0]])
    q = Rotation.from_rotvec([0.1, 0.0, 0.2]).as_quat()
    with local_broker() as ep:
        sync = Synchronizer(broker=ep, params={"extrinsics": ext.to_dict()})
        probe = Probe(ep, listen=["sar/measurement"], publish=["vio/pose", "radar/frame"], wait_for=["synchronizer"])
        with running(sync, probe):
            probe.send("vio/pose", pose(0, (0.1, 0.2, 0.3), q, child="camera"))
            probe.send("vio/pose", pose(100, (0.1, 0.2, 0.3), q, child="camera"))
            probe.send("radar/frame", frame(50, 0, offsets, last=True))
            (m,) = probe.wait_for("sar/measurement", 1)
    r_wc = Rotation.from_quat(q).as_matrix()
    expect = (r_wc @ (ext.rotation @ offsets.T + ext.translation_m[:, None])).T + np.array([0.1, 0.2, 0.3])
    np.testing.assert_allclose(m.positions_m, expect, atol=1e-12)


# --- drivers ----------------------------------------------------------------------------------


def small_scan(m=12, k=6, seed=0):
    from twinfocus.radar.scan import Scan

    rng = np.random.default_rng(seed)
    data = (rng.standard_normal((m, k, CHIRP.n_samples)) + 1j * rng.standard_normal((m, k, CHIRP.n_samples))).astype(
        np.complex64
    )
    pos = np.zeros((m, k, 3))
    pos[:, :, 0] = np.linspace(-0.01, 0.01, k)[None, :]
    pos[:, :, 1] = np.linspace(-0.05, 0.05, m)[:, None]
    return Scan(data, pos, CHIRP, timestamps_ns=np.arange(m, dtype=np.int64) * 100_000_000 + 5)


def _driven(driver, topic, count, **params):
    """The first ``count`` messages a driver node (class ``driver``, its ``params`` with
    ``wait_for`` the probe) publishes on ``topic``, and when each arrived (``time.monotonic`` s)."""
    with local_broker() as ep:
        probe = Probe(ep, listen=[topic])
        drv = driver(broker=ep, params={**params, "wait_for": ["probe"]})
        with running(probe):
            with running(drv):
                got = probe.wait_for(topic, count)
                return got, list(probe.arrival[topic])


def test_radar_driver_replays_a_scan_file_row_by_row(tmp_path):
    from nodes.radar_driver import RadarDriver

    scan = small_scan()
    scan.save(tmp_path / "s.npz")
    options = {"path": str(tmp_path / "s.npz"), "array": "scan"}
    got, _ = _driven(RadarDriver, "radar/frame", scan.n_positions, backend="scan_file", rate=0, options=options)
    assert [f.index for f in got] == list(range(scan.n_positions))
    assert [f.last for f in got] == [False] * (scan.n_positions - 1) + [True]
    for m, f in enumerate(got):
        assert np.array_equal(f.data, scan.data[m]) and f.header.stamp_ns == scan.timestamps_ns[m]
        assert f.chirp() == CHIRP and f.scan_id == "s"
        np.testing.assert_allclose(f.channel_offsets_m + scan.positions[0].mean(axis=0), scan.positions[0], atol=1e-15)


@pytest.mark.slow  # 1.4 s x
def test_vio_driver_replays_a_tum_file_paced_by_its_stamps(tmp_path):
    from nodes.vio_driver import VioDriver
    from twinfocus.motion.trajectory import Poses
    from twinfocus.sensors.trajectory_files import write_tum

    n = 8
    q = Rotation.from_rotvec(np.outer(np.arange(n), [0, 0, 0.1])).as_quat()
    poses = Poses(np.arange(n, dtype=np.int64) * 150_000_000, np.outer(np.arange(n), [0.01, 0.02, 0.0]), q)
    write_tum(tmp_path / "traj.txt", poses)
    options = {"path": str(tmp_path / "traj.txt"), "time_offset_ns": 7}
    got, arrival = _driven(VioDriver, "vio/pose", n, backend="trajectory_file", rate=1.0, options=options)
    assert [p.header.stamp_ns for p in got] == list(poses.timestamps_ns + 7)
    np.testing.assert_allclose(np.stack([p.position_m for p in got]), poses.position_m)
    np.testing.assert_allclose(np.abs(np.sum(np.stack([p.quat_xyzw for p in got]) * poses.quat_xyzw, axis=1)), 1.0)
    # Paced by the stamps: 7 intervals of 150 ms go out over ~1.05 s, where all at once would take
    # milliseconds; half of it leaves room for the first pose's delivery to lag on a busy machine.
    assert arrival[-1] - arrival[0] > 0.5


class ClockedPoses:
    """A backend whose clock starts at 10 s with two poses stamped before it (as a tracker's
    from before the radar's first frame) and one 0.3 s after."""

    live = False
    clock_start_ns = 10_000_000_000

    def __init__(self, options):
        pass

    def samples(self):
        from nodes.runtime.backends import PoseSample

        for dt_s in (-5.0, -2.5, 0.0, 0.3):
            yield PoseSample(self.clock_start_ns + int(dt_s * 1e9), np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))

    def close(self):
        pass


def test_a_driver_paces_from_its_backends_clock_start_so_simulated_sensors_share_one_clock():
    from nodes.runtime.sim_backends import SimRadar, SimVio
    from nodes.vio_driver import VioDriver

    _, arrival = _driven(VioDriver, "vio/pose", 4, backend=f"{__name__}:ClockedPoses", rate=1.0)
    t = np.asarray(arrival) - arrival[0]
    # the poses stamped before the clock's start go out at once, the last one 0.3 s after it
    # (paced from the first pose's stamp they would come 5 and 5.3 s after the first: the gap
    # leaves seconds for a busy machine's delays either way)
    assert t[2] < 2.5 and 0.25 < t[3] < 2.5, t
    # the simulated tracker starts its clock at the radar's first frame, not at its own first pose
    opts = {"scenario": {"n_columns": 1, "n_rows": 3, "snr_db": None}}
    radar, vio = SimRadar(opts), SimVio(opts)
    first_frame = next(radar.samples()).stamp_ns
    assert radar.clock_start_ns == vio.clock_start_ns == first_frame > next(vio.samples()).stamp_ns


def test_unknown_backend_is_a_clear_error():
    from nodes.radar_driver import RadarDriver

    with pytest.raises(TwinFocusError, match="unknown radar backend 'dca9000'; known: sim, scan_file, mmwcas, dca1000"):
        RadarDriver(params={"backend": "dca9000"})


# --- template builder, solver, visualizer -----------------------------------------------------


def point_scene_scan(m_side=10, k=8):
    """Noise-free scan of a few point scatterers, on positions with a known error."""
    from twinfocus.motion.trajectory import paper_raster, phase_centres
    from twinfocus.radar.fmcw import uniform_virtual_array
    from twinfocus.radar.scan import Scan
    from twinfocus.simulation.if_simulator import simulate_if

    poses = paper_raster(n_columns=2, n_rows=m_side, column_pitch_m=0.008 * k, row_pitch_m=0.004)
    true = phase_centres(poses, uniform_virtual_array(k, 0.002))
    pts = np.array([[-0.03, 0.0, 0.3], [-0.02, 0.01, 0.3], [0.03, -0.01, 0.3]])
    data = simulate_if(pts, np.ones(3), true, CHIRP)
    err = np.zeros((true.shape[0], 3))
    err[:, 2] = np.random.default_rng(1).normal(0, 0.3e-3, true.shape[0])
    return Scan(data, true + err[:, None, :], CHIRP, positions_true=true, timestamps_ns=poses.timestamps_ns)


REF_ROI = [-0.045, -0.005, -0.02, 0.02, 0.3]
TGT_ROI = [0.01, 0.05, -0.03, 0.01, 0.3]


def _published_template(path, size=12):
    """What a template builder with ``source: file`` publishes on twin/template."""
    from nodes.template_builder import TemplateBuilder

    with local_broker() as ep:
        probe = Probe(ep, listen=["twin/template"])
        tb = TemplateBuilder(
            broker=ep,
            params={"source": "file", "path": str(path), "reference_roi": REF_ROI, "size": size, "wait_for": ["probe"]},
        )
        with running(probe, tb):
            (t,) = probe.wait_for("twin/template", 1)
    return t


def test_template_builder_publishes_the_resampled_template_file(tmp_path):
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.twins.templates import load_template, save_template

    fine = ImageGrid.from_roi([-0.05, 0.0, -0.03, 0.03, 0.3], (31, 26))
    image = np.random.default_rng(0).random(fine.shape).astype(np.float32)
    save_template(tmp_path / "t.npz", image, fine)
    t = _published_template(tmp_path / "t.npz")
    grid = ImageGrid.from_roi(REF_ROI, 12)
    assert np.array_equal(t.image, load_template(tmp_path / "t.npz", grid))
    assert np.array_equal(t.x_m, grid.x_m) and np.array_equal(t.y_m, grid.y_m) and t.z_m == 0.3
    assert t.kind == "physical" and t.source.endswith("t.npz") and t.phase_rad is None


def test_a_digital_twins_template_file_goes_out_with_its_outline_and_conditioning(tmp_path):
    """A template file written by twinfocus twin (outline and conditioning in it): the builder sends
    it as a digital twin with both, so the solver runs the outline estimator and keeps the
    conditioning its confidence report needs."""
    from nodes.solver import Solver
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.twins.templates import save_template

    grid = ImageGrid.from_roi(REF_ROI, 12)
    support = np.zeros(grid.shape, bool)
    support[3:9, 2:8] = True
    info = {"surface": "smooth", "curved": True, "curvature_m": 0.004, "surface_reason": "curved"}
    save_template(tmp_path / "t.npz", support.astype(np.float32), grid, support=support, info=info)
    t = _published_template(tmp_path / "t.npz")
    assert t.kind == "digital" and np.array_equal(t.support, support)
    assert (t.surface, t.curved, t.curvature_m) == ("smooth", True, 0.004)
    with local_broker() as ep:
        solver = Solver(
            broker=ep, params={"reference_roi": REF_ROI, "target_roi": TGT_ROI, "size": 12, "warm_up": False}
        )
        solver.on_template(t)
        assert solver._plan().estimator == "outline" and solver.twin_info == {
            "surface": "smooth",
            "curved": True,
            "curvature_m": 0.004,
        }


def test_a_physical_twins_phase_travels_to_the_solver(tmp_path):
    """A template file with its phase: the builder sends it along (TwinTemplate.phase_rad), and the
    solver rebuilds the complex template, so auto picks the registered closed form."""
    from nodes.solver import Solver
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.twins.templates import load_template, save_template

    grid = ImageGrid.from_roi(REF_ROI, 12)
    rng = np.random.default_rng(4)
    image = (rng.random(grid.shape) * np.exp(1j * rng.uniform(-3, 3, grid.shape))).astype(np.complex64)
    save_template(tmp_path / "t.npz", image, grid)
    t = _published_template(tmp_path / "t.npz")
    want = load_template(tmp_path / "t.npz", grid)
    np.testing.assert_allclose(t.image * np.exp(1j * t.phase_rad.astype(np.float64)), want, atol=1e-5)
    with local_broker() as ep:
        for size in (12, 9):  # the solver's own grid, then another one (resampled)
            solver = Solver(
                broker=ep, params={"reference_roi": REF_ROI, "target_roi": TGT_ROI, "size": size, "warm_up": False}
            )
            solver.on_template(t)
            assert solver.template.dtype == np.complex64 and solver.template.shape == (size, size)
            assert solver._config(Chirp()).init == "correlation"
        np.testing.assert_allclose(
            solver.template, load_template(tmp_path / "t.npz", ImageGrid.from_roi(REF_ROI, 9)), atol=1e-5
        )


@pytest.mark.slow  # 3 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_discover_says_at_once_that_it_waits_and_gives_up_naming_both_ways_to_name_a_broker():
    import io

    from nodes.runtime.bus import discover
    from tests.test_graph import free_port

    dead = f"tcp://127.0.0.1:{free_port()}"
    said: list[float] = []

    class Stream(io.StringIO):
        def write(self, text):
            said.append(time.monotonic())
            return super().write(text)

    stream, t0 = Stream(), time.monotonic()
    with pytest.raises(TwinFocusError) as err:
        discover(dead, zmq.Context.instance(), timeout_s=3.0, stream=stream)
    gave_up = time.monotonic()
    assert stream.getvalue().count("\n") == 1 and f"waiting for a broker at {dead}" in stream.getvalue()
    # said while waiting, well before giving up (the first poll is half a second)
    assert said and said[0] - t0 < gave_up - t0 - 1.0
    msg = str(err.value)
    assert "\n" not in msg and dead in msg and "--broker" in msg and "$TWINFOCUS_BROKER" in msg

    with local_broker() as ep:  # a running broker answers at once, without a word
        quiet = io.StringIO()
        discover(ep, zmq.Context.instance(), timeout_s=3.0, stream=quiet)
        assert quiet.getvalue() == ""


def test_template_builder_computes_a_template_scan_once_then_takes_it_from_the_cache(tmp_path, monkeypatch):
    """source scan: the first node computes the image and stores it; a later node (a later run)
    gets the same image from the cache without back-projecting; no cache or another grid computes it."""
    import twinfocus.twins.templates
    from nodes.template_builder import TemplateBuilder
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.twins.templates import template_from_scan

    monkeypatch.setenv("TWINFOCUS_CACHE_DIR", str(tmp_path / "cache"))
    scan = point_scene_scan()
    scan.save(tmp_path / "ref.npz")
    want = template_from_scan(scan, ImageGrid.from_roi(REF_ROI, 12), keep_phase=True)  # independent: direct call
    params = {"source": "scan", "path": str(tmp_path / "ref.npz"), "reference_roi": REF_ROI, "size": 12}
    with local_broker() as ep:
        first = TemplateBuilder(broker=ep, params=params)
        assert first.cache_status == "miss" and len(list((tmp_path / "cache" / "templates").glob("*.npz"))) == 1

        def no_backprojection(*a, **k):
            raise AssertionError("the template scan was back-projected again")

        monkeypatch.setattr(twinfocus.twins.templates, "template_from_scan", no_backprojection)
        second = TemplateBuilder(broker=ep, params=params)
        assert second.cache_status == "hit"
        with pytest.raises(AssertionError, match="back-projected again"):
            TemplateBuilder(broker=ep, params={**params, "cache": False})
        with pytest.raises(AssertionError, match="back-projected again"):  # another grid: another entry
            TemplateBuilder(broker=ep, params={**params, "size": 10})
    for b in (first, second):
        got = b.msg.image * np.exp(1j * b.msg.phase_rad.astype(np.float64))
        np.testing.assert_allclose(got, want, atol=1e-5 * np.abs(want).max())


def measurements(scan, scan_id="p"):
    """The scan's measurements as the synchronizer publishes them, with their true positions."""
    return sar_measurements(scan.data, scan.positions, CHIRP, scan_id, scan.timestamps_ns, scan.positions_true)


def solver_and_probe(ep, listen=("autofocus/result",), **params):
    """A solver node on broker ``ep`` (``params``, no warm-up) and a probe that feeds it
    measurements and templates and listens on ``listen``."""
    from nodes.solver import Solver

    solver = Solver(broker=ep, params={**params, "warm_up": False})
    probe = Probe(ep, listen=list(listen), publish=["sar/measurement", "twin/template"], wait_for=["solver"])
    return solver, probe


def twin_template(template, grid, phase=True):
    """The TwinTemplate of an image on ``grid`` at 0.3 m: a complex one (a physical twin's) as its
    magnitude with its phase (``phase``) or without, a real one as it is."""
    if np.iscomplexobj(template):
        phase_rad = np.angle(template).astype(np.float32) if phase else None
        return TwinTemplate(image=np.abs(template), phase_rad=phase_rad, x_m=grid.x_m, y_m=grid.y_m, z_m=0.3)
    return TwinTemplate(image=template, x_m=grid.x_m, y_m=grid.y_m, z_m=0.3)


def send_scan(probe, template, scan, scan_id="p"):
    """The twin's ``template`` (a TwinTemplate), then every measurement of ``scan``."""
    probe.send("twin/template", template)
    for m in measurements(scan, scan_id=scan_id):
        probe.send("sar/measurement", m)


def test_a_streamed_drift_fit_that_fails_says_so_in_one_line_and_a_stopped_one_says_nothing(capsys):
    """The solver's streamed drift fit (a worker thread): a ladder that refuses the partial scan
    leaves one log line naming the error and counts no fit; a fit superseded by the scan's last
    frame ends quietly."""
    from nodes.solver import Solver, _DriftStream, _Superseded
    from twinfocus.focus.ladder import DriftStarts

    class Plan:
        def __init__(self, error):
            self.error = error

        def focus_bases(self, bases, reference):
            raise self.error

    with local_broker() as ep:
        solver = Solver(broker=ep, params={"reference_roi": REF_ROI, "target_roi": TGT_ROI, "warm_up": False})
        capsys.readouterr()
        d = _DriftStream(DriftStarts(), rows=40)
        solver._drift_worker(d, Plan(TwinFocusError("the reference is too small")), None, None)
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "streamed drift fit on 40 positions stopped" in err, err
        assert "TwinFocusError: the reference is too small" in err and d.fits == 0
        solver._drift_worker(d, Plan(_Superseded()), None, None)
        assert capsys.readouterr().err == "" and d.fits == 0


def test_solver_streams_the_basis_and_focuses_with_the_template(tmp_path):
    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.imaging.backprojection.numba_backend import backproject
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.twins.templates import template_from_scan

    scan = point_scene_scan()
    ref_grid, tgt_grid = ImageGrid.from_roi(REF_ROI, 16), ImageGrid.from_roi(TGT_ROI, 16)
    template = template_from_scan(scan, ref_grid)  # the reference focused on the true positions
    params = {"reference_roi": REF_ROI, "target_roi": TGT_ROI, "size": 16, "iterations": 40, "estimator": "paper"}
    with local_broker() as ep:
        listen = ("autofocus/result", "image/focused")
        solver, probe = solver_and_probe(ep, listen, **params, out_dir=str(tmp_path / "out"), pictures=False)
        with running(solver, probe):
            send_scan(probe, twin_template(template, ref_grid), scan)
            first, res = probe.wait_for("autofocus/result", 2, timeout_s=60)
            images = {i.name: i for i in probe.wait_for("image/focused", 4)}
    # The image and a first result go out before the metrics against the truth; the
    # second result adds them to the same phase.
    assert first.metrics_pending and not res.metrics_pending and first.latency_s > 0
    assert "target_ssim_corrected" not in first.metrics and np.array_equal(first.phase_rad, res.phase_rad)
    assert res.latency_s == first.latency_s and "truth_metrics_after_result" in res.timing_s
    assert res.scan_id == "p" and res.phase_rad.shape == (scan.n_positions,) and res.loss_history.shape == (40,)
    # The streamed basis sums to the batch back-projection of the whole scan.
    unc = backproject(scan.data, scan.positions, CHIRP, tgt_grid)
    np.testing.assert_allclose(images["target_uncorrected"].image, unc, atol=3e-3 * np.abs(unc).max())
    # The correction helps, and the files are those of `twinfocus focus`.
    assert res.metrics["target_ssim_corrected"] > res.metrics["target_ssim_uncorrected"]
    assert res.loss_history[-1] < res.loss_history[0]
    assert np.array_equal(np.load(tmp_path / "out" / "p" / "phase.npy"), res.phase_rad)
    assert np.array_equal(np.load(tmp_path / "out" / "p" / "target.npy"), images["target"].image)
    assert set(res.timing_s) >= {"autofocus", "basis_streamed", "last_measurement_to_result"}
    assert AutofocusConfig().iterations == 300  # the node's default is the paper's, tests ask for fewer


@pytest.mark.slow  # 2.8 s x
def test_solver_streams_the_half_array_bases_only_when_the_tilt_may_be_fitted():
    """With a template that has phase the ladder may fit the array's tilt: the solver
    back-projects the half-array bases batch by batch as the scan arrives, and hands the fit the
    same bases as the whole scan's (pipeline.half_array_bases, what twinfocus focus forms). With
    an amplitude template (no drift or tilt rung can run) it streams none."""
    from twinfocus.focus.pipeline import half_array_bases
    from twinfocus.imaging.backprojection.numba_backend import backproject
    from twinfocus.imaging.grid import ImageGrid

    scan = point_scene_scan()
    ref_grid, tgt_grid = ImageGrid.from_roi(REF_ROI, 16), ImageGrid.from_roi(TGT_ROI, 16)
    template = backproject(scan.data, scan.positions_true, CHIRP, ref_grid)
    for phase in (True, False):
        with local_broker() as ep:
            solver, probe = solver_and_probe(ep, reference_roi=REF_ROI, target_roi=TGT_ROI, size=16)
            handed: dict = {}
            own = solver._half_bases

            def spy(s, positions, own=own, handed=handed):
                bases = own(s, positions)
                handed.update(streamed=s.half_handed, bases=bases() if bases is not None else None)
                return bases

            solver._half_bases = spy
            with running(solver, probe):
                send_scan(probe, twin_template(template, ref_grid, phase=phase), scan)
                probe.wait_for("autofocus/result", 1, timeout_s=60, where=lambda r: not r.metrics_pending)
        assert handed["streamed"] == phase
        if phase:
            want = half_array_bases(scan.data, scan.positions, CHIRP, ref_grid, tgt_grid, solver.bp)()
            for got, w in zip(handed["bases"], want):
                # float32 sums in another order (batches of what had arrived): up to 1.6e-5 seen
                np.testing.assert_allclose(got, w, rtol=0, atol=1e-4 * np.abs(w).max())


def test_solver_registers_a_template_that_comes_mid_scan_as_focus_does_on_the_whole_basis():
    """A physical twin's template (with its phase) arriving after the first half of the scan: the
    solver scores the registration on the rows it already has, then on each batch
    (none of it after the last measurement but the last batch's), and gets the phase that
    focus_bases gives on the whole scan's bases."""
    from twinfocus.focus.pipeline import Bases, Reference
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.imaging.backprojection.numba_backend import backproject, subimage_basis
    from twinfocus.imaging.grid import ImageGrid

    scan = point_scene_scan(m_side=20)  # 40 positions: the 20 before the template are scored at once
    ref_grid, tgt_grid = ImageGrid.from_roi(REF_ROI, 16), ImageGrid.from_roi(TGT_ROI, 16)
    template = backproject(scan.data, scan.positions_true, CHIRP, ref_grid)  # complex: a physical twin's
    msgs = measurements(scan)
    half = len(msgs) // 2
    with local_broker() as ep:
        solver, probe = solver_and_probe(ep, reference_roi=REF_ROI, target_roi=TGT_ROI, size=16)
        with running(solver, probe):
            for m in msgs[:half]:
                probe.send("sar/measurement", m)
            probe.sent_all()
            deadline = time.monotonic() + 30
            while (solver.scan is None or solver.scan.ref_rows.n < half) and time.monotonic() < deadline:
                time.sleep(0.01)
            assert solver.scan.ref_rows.n == half and solver.scan.scores is None  # rows kept, no template yet
            probe.send("twin/template", twin_template(template, ref_grid))
            for m in msgs[half:]:
                probe.send("sar/measurement", m)
            res = probe.wait_for("autofocus/result", 1, timeout_s=60, where=lambda r: not r.metrics_pending)[0]
            cfg = solver._config(CHIRP)
    assert cfg.template_registration == "correlation" and "registration_streamed" in res.timing_s
    p = solver.params
    want = FocusPlan.make(
        config=cfg,
        phase_ramp=p["phase_ramp"],
        space_variant=p["space_variant"],
        tracking_error_m=p["tracking_error_mm"] * 1e-3,
    ).focus_bases(
        Bases(
            subimage_basis(scan.data, scan.positions, CHIRP, ref_grid),
            subimage_basis(scan.data, scan.positions, CHIRP, tgt_grid),
            scan.positions,
            CHIRP,
            ref_grid,
            tgt_grid,
        ),
        Reference(template=solver.template),
    )
    assert "template_registration" in want.metrics
    np.testing.assert_allclose(np.angle(np.exp(1j * (res.phase_rad - want.phase_rad))), 0.0, atol=1e-3)


@pytest.mark.slow  # 1.3 s x
def test_solver_with_model_fast_forms_the_reference_as_focus_does():
    """``model: fast`` with a physical twin's template on a reference finer than the scan resolves:
    the solver streams the whole reference's rows and hands the ladder every other pixel's
    (ladder.fast_reference), and gets the phase that ``focus_scan`` (twinfocus focus) gets from
    the reference back-projected on those pixels alone."""
    from twinfocus.focus.pipeline import Reference
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.imaging.backprojection.numba_backend import backproject
    from twinfocus.imaging.grid import ImageGrid

    scan = point_scene_scan(m_side=20)
    ref_grid, tgt_grid = ImageGrid.from_roi(REF_ROI, 32), ImageGrid.from_roi(TGT_ROI, 32)
    template = backproject(scan.data, scan.positions_true, CHIRP, ref_grid)
    with local_broker() as ep:
        solver, probe = solver_and_probe(ep, reference_roi=REF_ROI, target_roi=TGT_ROI, size=32, model="fast")
        with running(solver, probe):
            send_scan(probe, twin_template(template, ref_grid), scan)
            res = probe.wait_for("autofocus/result", 1, timeout_s=60, where=lambda r: not r.metrics_pending)[0]
            cfg = solver._config(CHIRP)
    p = solver.params
    scan.positions_true = None
    want = FocusPlan.make(
        config=cfg,
        model="fast",
        phase_ramp=p["phase_ramp"],
        space_variant=p["space_variant"],
        tracking_error_m=p["tracking_error_mm"] * 1e-3,
    ).focus_scan(
        scan,
        ref_grid,
        tgt_grid,
        Reference(template=solver.template),
    )
    assert want.metrics["model"]["reference_strides"] == [2, 2] and want.reference.shape == (16, 16)
    np.testing.assert_allclose(np.angle(np.exp(1j * (res.phase_rad - want.phase_rad))), 0.0, atol=1e-3)


@pytest.mark.slow  # 1.7 s (2 cores, idle): out of make test-fast (benchmarks/results/test_fast.json)
def test_solver_without_a_template_says_so_and_drops_the_scan(capfd):
    from nodes.solver import Solver

    scan = point_scene_scan(m_side=3, k=4)
    with local_broker() as ep:
        solver = Solver(
            broker=ep,
            params={
                "reference_roi": REF_ROI,
                "target_roi": TGT_ROI,
                "size": 8,
                "template_wait_s": 0.5,
                "warm_up": False,
            },
        )
        probe = Probe(ep, publish=["sar/measurement"], wait_for=["solver"])
        with running(solver, probe):
            for m in measurements(scan):
                probe.send("sar/measurement", m)
            deadline = time.monotonic() + 20
            while solver.done < 1 and time.monotonic() < deadline:
                time.sleep(0.05)
    assert "no template arrived on twin/template within 0.5 s" in capfd.readouterr().err


@pytest.mark.slow  # 1.4 s x
def test_visualizer_writes_and_serves_the_focused_image(tmp_path):
    from nodes.visualizer import Visualizer

    rng = np.random.default_rng(5)
    img = (rng.standard_normal((20, 30)) + 1j * rng.standard_normal((20, 30))).astype(np.complex64)
    with local_broker() as ep:
        viz = Visualizer(broker=ep, params={"out_dir": str(tmp_path), "port": 0})
        probe = Probe(ep, publish=["image/focused", "autofocus/result", "vio/pose"], wait_for=["visualizer"])
        with running(viz, probe):
            for i in range(5):
                probe.send("vio/pose", pose(i, (0.01 * i, 0.0, 0.0)))
            probe.send(
                "image/focused",
                Image(
                    name="target", scan_id="v", image=img, x_m=np.linspace(0, 1, 30), y_m=np.linspace(0, 1, 20), z_m=0.5
                ),
            )
            probe.send(
                "autofocus/result",
                AutofocusResult(
                    scan_id="v",
                    method="twin",
                    phase_rad=np.zeros(4),
                    loss_history=np.linspace(1, 0.2, 10),
                    metrics={"ssim": 0.5},
                    latency_s=0.25,
                ),
            )
            deadline = time.monotonic() + 20
            while viz.results < 1 and time.monotonic() < deadline:
                time.sleep(0.05)
            served = urllib.request.urlopen(viz.url + "focused.png", timeout=10).read()
            page = urllib.request.urlopen(viz.url, timeout=10).read().decode()
            state = json.loads(urllib.request.urlopen(viz.url + "state.json", timeout=10).read())
    expect = cv2.applyColorMap(np.round(255 * np.abs(img) / np.abs(img).max()).astype(np.uint8), cv2.COLORMAP_INFERNO)
    on_disk = cv2.imread(str(tmp_path / "focused.png"))
    assert np.array_equal(on_disk, expect)
    assert np.array_equal(cv2.imdecode(np.frombuffer(served, np.uint8), cv2.IMREAD_COLOR), expect)
    assert 'id="focused"' in page and "/focused.png?v=1" in page
    assert state["versions"]["focused"] == 1 and "ssim: 0.5" in state["metrics"]
    assert "latency: 0.25 s" in state["metrics"]
    assert (tmp_path / "loss.png").stat().st_size > 0 and (tmp_path / "trajectory.png").stat().st_size > 0


# --- recorder, player, introspection ----------------------------------------------------------


@pytest.mark.slow  # 2.3 s (2 cores, idle): out of make test-fast (benchmarks/results/test_fast.json)
def test_record_then_play_back_with_topic_selection_offset_and_loop(tmp_path):
    from nodes.player import Player
    from nodes.recorder import Recorder

    log = tmp_path / "r.mcap"
    offsets = np.zeros((3, 3))
    with local_broker() as ep:
        rec = Recorder(broker=ep, params={"out": str(log), "calibration": {"lever_arm_m": [0.0, 0.01, 0.0]}})
        probe = Probe(ep, publish=["vio/pose", "radar/frame"], wait_for=["recorder"])
        with running(rec, probe):
            for i in range(30):
                probe.send("vio/pose", pose(i * 10_000_000, (i, 0, 0)))
                if i % 3 == 0:
                    probe.send("radar/frame", frame(i * 10_000_000, i, offsets))
                time.sleep(0.01)
            assert probe.sent_all()
            deadline = time.monotonic() + 10
            while (
                rec.writer.counts.get("vio/pose", 0) + rec.writer.counts.get("radar/frame", 0) < 40
                and time.monotonic() < deadline
            ):
                time.sleep(0.02)
    from msgs.mcap_log import LogReader

    r = LogReader(log)
    # with no topic list the nodes' state changes are recorded beside (Foxglove's log panel)
    assert r.complete and {t: n for t, n in r.counts.items() if t != "graph/status"} == {
        "vio/pose": 30,
        "radar/frame": 10,
    }
    assert all(m.decode().node in ("recorder", "probe") for m in r.messages(["graph/status"]))
    assert r.metadata["calibration"] == {"lever_arm_m": [0.0, 0.01, 0.0]} and r.metadata["radar"]["n_channels"] == 3
    # the offset of the 15th pose: the recorded node states lie before and after the poses by
    # however long the nodes took to start and stop, so half the log's span says nothing of them
    pose_times = [m.log_time_ns for m in r.messages(["vio/pose"])]
    middle_s = (pose_times[15] - r.start_ns) / 1e9

    def play(**params):
        with local_broker() as ep:
            probe = Probe(ep, listen=["vio/pose", "radar/frame"], name="listener")
            player = Player(broker=ep, params={"log": str(log), "wait_for": ["listener"], **params})
            with running(probe):
                t0 = time.monotonic()
                code = player.spin()
                elapsed = time.monotonic() - t0
                # its final heartbeat follows everything it published on the one path to the probe
                deadline = time.monotonic() + patience(30)
                while getattr(probe.graph.get(player.name), "state", "") != "stopped" and time.monotonic() < deadline:
                    time.sleep(0.02)
            assert code == 0
            return probe.received, elapsed

    got, _ = play(rate=0)
    assert [p.position_m[0] for p in got["vio/pose"]] == list(range(30))
    assert [f.index for f in got["radar/frame"]] == list(range(0, 30, 3))
    assert [p.header.seq for p in got["vio/pose"]] == list(range(30))
    got, _ = play(rate=0, topics=["radar/frame"])
    assert got["vio/pose"] == [] and len(got["radar/frame"]) == 10
    got, _ = play(rate=0, topics=["vio/pose"], start_offset_s=middle_s)
    assert [p.position_m[0] for p in got["vio/pose"]] == list(range(15, 30))
    got, elapsed = play(rate=1.0, topics=["vio/pose"])
    # paced by the log's times from the first pose played: the node states logged before and
    # after the poses widen the log's span by however long the nodes took to start and stop
    pose_span_s = (pose_times[-1] - pose_times[0]) / 1e9
    assert len(got["vio/pose"]) == 30 and elapsed > 0.9 * pose_span_s
    with local_broker() as ep:
        probe = Probe(ep, listen=["vio/pose"], name="listener")
        looping = Player(
            broker=ep,
            params={"log": str(log), "rate": 0, "loop": True, "topics": ["vio/pose"], "wait_for": ["listener"]},
        )
        with running(probe, looping):
            probe.wait_for("vio/pose", 75, timeout_s=20)
    poses = probe.received["vio/pose"]
    assert [p.position_m[0] for p in poses[:75]] == list(range(30)) * 2 + list(range(15))
    assert [p.header.seq for p in poses] == list(range(len(poses)))  # numbered afresh across passes


@pytest.mark.slow  # 8 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_loss_thousands_of_messages_replayed_at_full_speed_all_arrive(tmp_path):
    """5,000 poses and 100 MMWCAS-sized radar frames (18 MB) through the bus as fast as it goes."""
    from msgs.mcap_log import LogWriter

    log = tmp_path / "many.mcap"
    offsets = np.zeros((86, 3))
    big = Chirp()
    with LogWriter(log) as w:
        t = 0
        for i in range(5000):
            w.write("vio/pose", pose(i, (i, 0, 0)), log_time_ns=t)
            t += 1000
            if i % 50 == 0:
                f = RadarFrame(
                    data=np.full((86, 256), i, np.complex64),
                    f0_hz=big.f0_hz,
                    slope_hz_per_s=big.slope_hz_per_s,
                    fs_hz=big.fs_hz,
                    channel_offsets_m=offsets,
                    index=i,
                )
                w.write("radar/frame", f, log_time_ns=t)
    with local_broker() as ep:
        slow = Probe(ep, listen=["vio/pose", "radar/frame"], name="slow")
        # A slow subscriber on the same topics must not cost the others any message either.
        slow._got = lambda topic, msg, orig=slow._got: (time.sleep(0.0002), orig(topic, msg))
        fast = Probe(ep, listen=["vio/pose", "radar/frame"], name="fast")
        with running(slow, fast):
            # The player in its own process, which exits as soon as it has sent the last message:
            # what is still queued must get out before the process ends.
            play = subprocess.run(
                [
                    sys.executable,
                    "-c",
                    "import sys; from twinfocus.cli import main; sys.exit(main())",
                    "play",
                    str(log),
                    "--rate",
                    "0",
                    "--wait-for",
                    "slow",
                    "fast",
                    "--broker",
                    ep,
                ],
                cwd=REPO,
                capture_output=True,
                timeout=120,
            )
            assert play.returncode == 0, play.stderr.decode()
            for p in (slow, fast):
                p.wait_for("vio/pose", 5000, timeout_s=60)
                p.wait_for("radar/frame", 100, timeout_s=60)
    for p in (slow, fast):
        assert [m.header.seq for m in p.received["vio/pose"]] == list(range(5000))
        assert [m.position_m[0] for m in p.received["vio/pose"]] == list(range(5000))
        assert [int(f.data[0, 0].real) for f in p.received["radar/frame"]] == list(range(0, 5000, 50))
        assert p._lost == {}


@pytest.mark.slow  # 3 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_topic_list_echo_and_hz(tmp_path):
    import io

    from nodes.runtime.introspect import TopicEcho, TopicHz, TopicList

    with local_broker() as ep:
        src = Probe(ep, publish=["vio/pose"], name="src")
        with running(src):
            out = io.StringIO()
            assert TopicList(out, duration_s=1.5, verbose=True, broker=ep).spin() == 0
            listing = out.getvalue()
            echo_out, hz_out = io.StringIO(), io.StringIO()
            echo = TopicEcho(echo_out, "vio/pose", count=2, broker=ep)
            hz = TopicHz(hz_out, "vio/pose", window_s=0.5, duration_s=1.6, broker=ep)
            import threading

            th = [threading.Thread(target=n.spin) for n in (echo, hz)]
            for t in th:
                t.start()
            for i in range(60):
                src.send("vio/pose", pose(i, (i * 1e-3, 0, 0)))
                time.sleep(0.025)
            for t in th:
                t.join(20)
    assert "vio/pose  [Pose]" in listing and "publishers: src" in listing
    assert echo_out.getvalue().count("type: Pose") == 2 and "position_m: float64 (3,)" in echo_out.getvalue()
    assert "vio/pose: average rate" in hz_out.getvalue()


@pytest.mark.parametrize("scan_id", ["../../escaped", "/tmp/absolute"])
def test_a_scan_id_from_the_bus_never_writes_outside_out_dir(tmp_path, scan_id):
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.twins.templates import template_from_scan

    scan = point_scene_scan()
    ref_grid = ImageGrid.from_roi(REF_ROI, 16)
    template = template_from_scan(scan, ref_grid)
    out = tmp_path / "run" / "out"
    out.mkdir(parents=True)
    (out / "earlier.png").write_bytes(b"not the solver's")
    params = {"reference_roi": REF_ROI, "target_roi": TGT_ROI, "size": 16, "iterations": 10, "estimator": "paper"}
    with local_broker() as ep:
        solver, probe = solver_and_probe(ep, **params, out_dir=str(out), pictures=False)
        with running(solver, probe):
            send_scan(probe, twin_template(template, ref_grid), scan, scan_id=scan_id)
            probe.wait_for("autofocus/result", 2, timeout_s=60)  # the result still goes out on the bus
    # nothing was written for it, inside out_dir or where the name points, and nothing deleted
    assert sorted(p.name for p in out.iterdir()) == ["earlier.png"]
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["out"]
    assert not (tmp_path / "escaped").exists() and not __import__("pathlib").Path("/tmp/absolute").exists()
