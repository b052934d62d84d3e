"""Capture gaps reach the user: the DCA1000 backend counts the frames and bytes an emulated board
never delivered, the radar frame message carries the counts (and old logs without them still
decode), and the visualizer's status line shows them."""

from __future__ import annotations

import socket

import msgpack
import numpy as np
import pytest

from msgs import Header, RadarFrame, decode, encode
from nodes.radar_driver import _gap_fields
from nodes.runtime.backends import RADAR_BACKENDS, load_backend
from twinfocus.radar.fmcw import mmwcas_virtual_array
from twinfocus.sensors.dca1000 import MAX_PAYLOAD_BYTES, RawFrameLayout
from twinfocus.sensors.emulators.fake_dca1000 import FakeDca1000, LinkFaults


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_dropped_packets_are_counted_and_carried(tmp_path, capfd):
    from twinfocus.sensors.emulators.rig import EMULATED_CFG

    n = 32
    cfg = tmp_path / "radar.cfg"
    cfg.write_text(EMULATED_CFG.replace(" 256 8000 ", f" {n} 8000 "))
    layout = RawFrameLayout(n, 16, tuple(range(12)), 1, 12)
    fb = layout.frame_bytes
    # Sequence numbers count from 1: packet s carries bytes (s-1)*1456 ... s*1456-1. Packet 20 lies
    # inside frame 1; packets of frame 3 that lie wholly inside it are all dropped (frame 3 keeps
    # the edges its neighbours' packets share, so it is zero-filled, not lost).
    in_frame3 = [s for s in range(1, 100) if (s - 1) * MAX_PAYLOAD_BYTES >= 3 * fb and s * MAX_PAYLOAD_BYTES <= 4 * fb]
    drop = {20, *in_frame3}
    port = _free_udp_port()
    with FakeDca1000(
        layout,
        host_data_addr=("127.0.0.1", port),
        frame_period_s=0.01,
        n_frames=6,
        faults=LinkFaults(drop_packets=drop),
    ) as board:
        radar = load_backend(RADAR_BACKENDS, "dca1000", "radar")(
            {
                "cfg": str(cfg),
                "board": f"{board.config_addr[0]}:{board.config_addr[1]}",
                "host_ip": "127.0.0.1",
                "config_port": 0,
                "data_port": port,
                "idle_timeout_s": 1.0,
            }
        )
        try:
            got = list(radar.samples())
        finally:
            radar.close()
    # Truth from the drop list alone: frames 1 and 3 zero-filled, 1 + len(in_frame3) packets missing.
    assert len(got) == 4
    assert got[-1].gaps == (0, 2, (1 + len(in_frame3)) * MAX_PAYLOAD_BYTES)
    assert got[0].gaps == (0, 0, 0)
    assert "flagged frame(s)" in capfd.readouterr().err


def _frame(**gaps):
    """An empty frame of the cascade's 86 virtual channels (4 samples) with the ``gaps`` fields."""
    offsets = mmwcas_virtual_array().offsets_m
    data = np.zeros((86, 4), np.complex64)
    chirp = {"f0_hz": 77e9, "slope_hz_per_s": 1e14, "fs_hz": 8e6}
    return RadarFrame(header=Header(5, 0, "radar"), data=data, **chirp, channel_offsets_m=offsets, scan_id="s", **gaps)


def test_radar_frame_carries_gaps_and_old_logs_still_decode():
    msg = _frame(**_gap_fields((1, 2, 3000)))
    back = decode(encode(msg))
    assert (back.frames_lost, back.frames_zero_filled, back.bytes_lost) == (1, 2, 3000)
    env = msgpack.unpackb(encode(msg), raw=False)
    for k in ("frames_lost", "frames_zero_filled", "bytes_lost"):
        del env["fields"][k]  # a log written before the fields existed
    old = decode(msgpack.packb(env, use_bin_type=True))
    assert (old.frames_lost, old.frames_zero_filled, old.bytes_lost) == (0, 0, 0)
    assert _gap_fields(None) == {}


@pytest.mark.slow  # 1.7 s (2 cores, idle): out of make test-fast (benchmarks/results/test_fast.json)
def test_visualizer_status_shows_gaps(tmp_path):
    """A radar frame with gaps sent over the node graph; the served state shows them."""
    import json
    import time
    import urllib.request

    from nodes.runtime.testing import Probe, local_broker, running
    from nodes.visualizer import Visualizer

    frame = _frame(frames_lost=1, frames_zero_filled=2, bytes_lost=3000)
    with local_broker() as ep:
        viz = Visualizer(broker=ep, params={"out_dir": str(tmp_path), "port": 0})
        probe = Probe(ep, publish=["radar/frame"], wait_for=["visualizer"])
        with running(viz, probe):
            probe.send("radar/frame", frame)
            deadline = time.monotonic() + 20
            while not viz.gaps_text and time.monotonic() < deadline:
                time.sleep(0.05)
            state = json.loads(urllib.request.urlopen(viz.url + "state.json", timeout=10).read())
    assert state["status"].endswith("capture gaps: 1 frame(s) lost, 2 zero-filled, 3000 bytes missing")


def test_live_scans_carry_their_capture_gaps_to_the_solver_metrics(tmp_path):
    """Radar frames carrying the stream's gap counts (since the stream began) go through
    the synchronizer and the solver; each scan's metrics (the result message and metrics.json)
    hold the gaps counted during that scan, under `capture` as a converted scan's focus has them.
    Scan b's last frame comes after every pose (unpaired): its counts still reach the scan."""
    import json

    from msgs import Pose
    from nodes.runtime.testing import Probe, local_broker, running
    from nodes.solver import Solver
    from nodes.synchronizer import Synchronizer
    from twinfocus.radar.fmcw import Chirp
    from twinfocus.simulation.if_simulator import simulate_if

    chirp = Chirp(n_samples=64)
    offsets = np.stack([np.linspace(-0.028, 0.028, 8), np.zeros(8), np.zeros(8)], axis=1)
    period_ns = 50_000_000
    # (frames lost, zero-filled, bytes lost) since the stream began, on each of the 12 frames
    counts = [
        (0, 0, 0),
        (0, 1, 1000),
        (0, 1, 1000),
        (1, 1, 6000),
        (1, 1, 6000),
        (1, 1, 6000),  # scan a
        (2, 1, 11000),
        (2, 1, 11000),
        (2, 3, 13000),
        (2, 3, 13000),
        (2, 3, 13000),
        (2, 4, 14000),
    ]  # scan b
    want = {"a": (1, 1, 6000), "b": (1, 3, 8000)}  # b: from a's last counts to its own
    stamps = (np.arange(12) + 1) * period_ns

    def y_m(t):  # both scans sweep the same 5 cm (the frames fall on poses)
        return 0.01 * ((t / period_ns - 1) % 6)

    positions = offsets[None] + np.stack([np.zeros(12), y_m(stamps), np.zeros(12)], axis=1)[:, None]
    data = simulate_if(np.array([[0.0, 0.025, 0.3]]), np.ones(1), positions, chirp)  # a point in the region
    frames = []
    for i, (lost, zero_filled, nbytes) in enumerate(counts):
        frames.append(
            RadarFrame(
                header=Header(int(stamps[i]), 0, "radar"),
                data=data[i],
                f0_hz=chirp.f0_hz,
                slope_hz_per_s=chirp.slope_hz_per_s,
                fs_hz=chirp.fs_hz,
                channel_offsets_m=offsets,
                scan_id="a" if i < 6 else "b",
                index=i % 6,
                last=i % 6 == 5,
                frames_lost=lost,
                frames_zero_filled=zero_filled,
                bytes_lost=nbytes,
            )
        )
    pose_stamps = range(0, 11 * period_ns + period_ns // 2 + 1, period_ns // 2)  # none after the last frame
    poses = [
        Pose(
            header=Header(t, 0, "scene"),
            position_m=np.array([0.0, y_m(t), 0.0]),
            quat_xyzw=np.array([0.0, 0.0, 0.0, 1.0]),
        )
        for t in pose_stamps
    ]
    roi = [-0.03, 0.03, -0.005, 0.055, 0.3]
    with local_broker() as ep:
        sync = Synchronizer(broker=ep, params={"max_wait_s": 0.5})
        solver = Solver(
            broker=ep,
            params={
                "reference_roi": roi,
                "target_roi": roi,
                "size": 16,
                "method": "none",
                "out_dir": str(tmp_path),
                "pictures": False,
                "warm_up": False,
            },
        )
        probe = Probe(
            ep, listen=["autofocus/result"], publish=["vio/pose", "radar/frame"], wait_for=["synchronizer", "solver"]
        )
        with running(sync, solver, probe):
            for p in poses:
                probe.send("vio/pose", p)
            for f in frames:
                probe.send("radar/frame", f)
            results = probe.wait_for("autofocus/result", 2, timeout_s=60)
    got = {r.scan_id: r for r in results}
    assert sorted(got) == ["a", "b"] and got["b"].phase_rad.shape == (5,)
    for scan_id, (lost, zero_filled, nbytes) in want.items():
        entry = {"frames_lost": lost, "frames_zero_filled": zero_filled, "bytes_lost": nbytes}
        assert json.loads((tmp_path / scan_id / "metrics.json").read_text())["capture"] == entry
        assert {k: got[scan_id].metrics[f"capture.{k}"] for k in entry} == entry
