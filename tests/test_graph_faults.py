"""Fault injection on the node graph : every fault ends or recovers
within a bounded time, with one clear line, and loses no earlier log or result.

Faults: SIGTERM / SIGKILL to each node and to the launcher, a truncated log and a log damaged
in the middle, a busy broker port, a recording that fails over an existing log, a replay with a
start offset, and a node that is respawned. Graphs are small (2 x 30 positions, 16 px) so each
case is seconds of work; the per-node cases are marked slow (tests/test_graph.py's crashing node is the
quick check).
"""

import os
import re
import shutil
import signal
import socket
import time
from pathlib import Path

import numpy as np
import pytest

from msgs import Header, TwinTemplate
from msgs.mcap_log import LogReader, LogWriter
from nodes.runtime.testing import patience
from tests.test_graph import REPO, Launched, alive, free_port, run_cli

SMALL = ["columns:=2", "rows:=30", "size:=16", "iterations:=5", "web_port:=0"]


def pids_by_name(g: Launched) -> dict[str, int]:
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"started (\S+) \(\S+, pid (\d+)\)", g.text)}


def wait_text(g: Launched, pattern: str, timeout_s: float) -> None:
    timeout_s = patience(timeout_s)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if re.search(pattern, g.text):
            return
        if g.proc.poll() is not None:
            break
        time.sleep(0.1)
    raise AssertionError(f"{pattern!r} not seen within {timeout_s} s:\n{g.text}")


def ended_within(g: Launched, timeout_s: float) -> tuple[int, float]:
    t = time.monotonic()
    code = g.wait(timeout_s)
    return code, time.monotonic() - t


def sim_graph(tmp_path, *extra) -> Launched:
    # rate 0.5: the 60 frames take 12 s, so the graph is mid-scan when a fault comes
    return Launched("launch/sim.yaml", f"port:={free_port()}", f"out:={tmp_path}", *SMALL, "rate:=0.5", *extra)


NODES = ["radar", "vio", "synchronizer", "template", "solver", "visualizer"]


@pytest.mark.timeout(240)
# 8-12 s idle each (benchmarks/results/test_fast.json): all slow. make test stops every node once and
# uses both signals, alternating (a TERM goes through the one signal handler all nodes share,
# nodes.runtime.node; a KILL is never seen by the node, only by the launcher), which keeps the suite
# within its 15 minutes. make test-fast's quick cover:
# tests/test_graph.py::test_a_crashing_node_stops_the_graph_with_a_clear_message (a node that exits
# stops the graph with one line naming it, exit status its own, no process left).
@pytest.mark.slow
@pytest.mark.parametrize(
    ("node", "sig"),
    [(node, (signal.SIGTERM, signal.SIGKILL)[i % 2]) for i, node in enumerate(NODES)],
    ids=[f"{node}-{('TERM', 'KILL')[i % 2]}" for i, node in enumerate(NODES)],
)
def test_a_node_stopped_from_outside_stops_the_graph_with_one_line(tmp_path, node, sig):
    g = sim_graph(tmp_path)
    try:
        wait_text(g, r"\[solver\]\s+scan 'sim' started", 180)
        os.kill(pids_by_name(g)[node], sig)
        code, took = ended_within(g, 30)
    finally:
        g.kill()
    why = "was stopped by SIGTERM from outside the launcher" if sig == signal.SIGTERM else "was killed by SIGKILL"
    assert f"node {node!r} {why}" in g.text and "stopping the graph" in g.text, g.text
    assert code == 1, g.text
    assert took < patience(20), f"took {took:.1f} s to stop"  # bounded, whatever else runs beside it
    assert "Traceback" not in g.text, g.text
    assert not [p for p in pids_by_name(g).values() if alive(p)]


@pytest.mark.slow  # 11 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
@pytest.mark.timeout(240)
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["TERM", "KILL"])
def test_a_stopped_launcher_leaves_no_node_behind(tmp_path, sig):
    g = sim_graph(tmp_path)
    try:
        wait_text(g, r"\[solver\]\s+scan 'sim' started", 180)
        pids = pids_by_name(g)
        g.proc.send_signal(sig)
        g.wait(30)
        # Each node ends on its own (parent-death signal, parent polling): the bound only keeps a
        # broken build from hanging, so it grows with the machine's load (a node in a JIT compile
        # ends after it: ~5 s on an idle VM, several times that beside CPU-bound work).
        deadline = time.monotonic() + patience(30)
        while [p for p in pids.values() if alive(p)] and time.monotonic() < deadline:
            time.sleep(0.05)
        left = [n for n, p in pids.items() if alive(p)]
    finally:
        g.kill()
    assert not left, f"still running: {left}\n{g.text}"
    if sig == signal.SIGTERM:
        assert "SIGTERM received: stopping the graph" in g.text and g.proc.returncode == 0, g.text


@pytest.mark.slow  # 16 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
@pytest.mark.timeout(240)
def test_a_respawned_node_comes_back_and_the_graph_focuses(tmp_path):
    launch = (
        (REPO / "launch" / "sim.yaml")
        .read_text()
        .replace(
            "  - name: synchronizer\n    node: synchronizer\n",
            "  - name: synchronizer\n    node: synchronizer\n    respawn: true\n    respawn_delay: 0.2\n",
        )
    )
    path = tmp_path / "respawn.yaml"
    path.write_text(launch)
    shutil.copy(REPO / "launch" / "paper.yaml", tmp_path / "paper.yaml")  # what sim.yaml includes, beside it
    g = Launched(str(path), f"port:={free_port()}", f"out:={tmp_path}", *SMALL, "rate:=1", "exit_after:=1")
    try:
        wait_text(g, r"\[solver\]\s+scan 'sim' started", 180)
        os.kill(pids_by_name(g)["synchronizer"], signal.SIGKILL)
        wait_text(g, r"node 'synchronizer' was killed by SIGKILL; respawning it in 0.2 s \(respawn 1 of 3\)", 20)
        code = g.wait(180)
    finally:
        g.kill()
    assert code == 0, g.text
    # The frames sent while it was down are lost; the scan is focused with the others, and says so.
    assert re.search(r"focused scan 'sim': \d+ positions", g.text), g.text


# -- logs -----------------------------------------------------------------------------------------


def small_log(path: Path, n_frames: int = 30, template: bool = True, seed: int = 0) -> None:
    """A replayable log: poses at 30 Hz around n_frames radar frames of a point scene."""
    from nodes.runtime.testing import write_driver_messages
    from twinfocus.imaging.backprojection.numba_backend import backproject
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.motion.trajectory import phase_centres
    from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
    from twinfocus.simulation.if_simulator import simulate_if
    from twinfocus.simulation.scenario import Scenario, scenario_poses, scenario_scatterers

    sc = Scenario(n_columns=1, n_rows=n_frames, seed=seed, snr_db=None)
    chirp, array = Chirp(), mmwcas_virtual_array()
    radar = scenario_poses(sc, t0_ns=10**10)
    t_vio = np.arange(radar.timestamps_ns[0] - 10**8, radar.timestamps_ns[-1] + 2 * 10**8, 33_333_333, dtype=np.int64)
    vio = radar.interpolate(t_vio)
    pts, amps = scenario_scatterers(sc)
    data = simulate_if(pts, amps, phase_centres(radar, array), chirp)
    grid = ImageGrid.from_roi(sc.reference_roi(), 16)
    image = np.abs(backproject(data, phase_centres(radar, array), chirp, grid)).astype(np.float32)
    with LogWriter(path, overwrite=True) as w:
        if template:
            w.write(
                "twin/template",
                TwinTemplate(
                    header=Header(10**10 - 10**9, 0, "scene"),
                    kind="physical",
                    source="test",
                    image=image,
                    x_m=grid.x_m,
                    y_m=grid.y_m,
                    z_m=grid.z,
                ),
                log_time_ns=10**10 - 10**9,
            )
        write_driver_messages(w, radar, vio, data, chirp, array)


def replay(tmp_path, log: Path, *extra) -> Launched:
    roi = lambda r: "[" + ",".join(str(v) for v in r) + "]"  # noqa: E731
    from twinfocus.simulation.scenario import Scenario

    sc = Scenario(n_columns=1, n_rows=30)
    return Launched(
        "launch/replay.yaml",
        f"log:={log}",
        f"out:={tmp_path / 'out'}",
        f"port:={free_port()}",
        "web_port:=0",
        "size:=16",
        "iterations:=5",
        f"reference_roi:={roi(sc.reference_roi())}",
        f"target_roi:={roi(sc.target_roi())}",
        *extra,
    )


@pytest.mark.slow  # 15 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
@pytest.mark.timeout(240)
def test_an_incomplete_log_is_focused_with_what_arrived_and_the_replay_ends(tmp_path):
    full = tmp_path / "full.mcap"
    small_log(full)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full.read_bytes()[: int(full.stat().st_size * 0.6)])
    g = replay(tmp_path, cut, "scan_timeout:=2")
    try:
        code, took = ended_within(g, 150)
    finally:
        g.kill()
    assert code == 1, g.text  # focused, but not every position arrived: no clean run
    assert "not closed cleanly" in g.text
    assert "no measurement for 2 s and no last one" in g.text, g.text
    m = re.search(r"focused scan 'run': (\d+) positions", g.text)
    assert m and 5 < int(m.group(1)) < 30, g.text


def test_a_log_damaged_in_the_middle_reads_on_past_the_damage(tmp_path):
    path = tmp_path / "log.mcap"
    small_log(path)
    whole = LogReader(path)
    logged = list(whole.messages(["radar/frame"]))
    frames = [m.decode() for m in logged]
    data = bytearray(path.read_bytes())
    # Overwrite the record header of frame 12 (opcode, length, then channel, sequence, times:
    # 9 + 22 bytes before its payload) and the start of its payload: the walk breaks there.
    hit = data.find(logged[12].blob) - 9 - 22
    assert hit > 0
    data[hit : hit + 40] = b"\xff" * 40
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    r = LogReader(bad)
    assert r.skipped and not r.complete and "damaged" in r.condition
    got = [m.decode() for m in r.messages(["radar/frame"])]
    # Only the damaged frame is lost; everything after it is read.
    assert [f.index for f in got] == [f.index for f in frames if f.index != 12]
    for f in got:
        np.testing.assert_array_equal(f.data, frames[f.index].data)


@pytest.mark.timeout(240)
def test_a_replay_with_a_start_offset_keeps_the_template(tmp_path):
    log = tmp_path / "log.mcap"
    small_log(log)
    # The template is logged 1 s before the first pose: an offset of 1.5 s starts past it.
    from nodes.player import Player
    from nodes.runtime.testing import Probe, local_broker, running

    with local_broker() as endpoint:
        probe = Probe(endpoint, listen=["twin/template", "radar/frame"], name="probe")
        player = Player(
            params={"log": str(log), "rate": 0.0, "start_offset_s": 1.5, "wait_for": ["probe"]}, broker=endpoint
        )
        with running(probe, player):
            (tpl,) = probe.wait_for("twin/template", 1, timeout_s=30)
            frames = probe.wait_for("radar/frame", 1, timeout_s=30)
    assert tpl.source == "test" and frames


# -- recordings and ports -------------------------------------------------------------------------


@pytest.mark.slow  # 11 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_a_failed_recording_keeps_the_earlier_log_and_leaves_no_file(tmp_path):
    earlier = tmp_path / "y.mcap"
    small_log(earlier, n_frames=3)
    before = earlier.read_bytes()
    dead = f"tcp://127.0.0.1:{free_port()}"  # no broker there
    t = time.monotonic()
    code, text = run_cli("record", "-o", str(earlier), "--overwrite", "--broker", dead)
    assert code == 2, text
    assert "no broker answered" in text and "--broker" in text and "Traceback" not in text, text
    assert f"waiting for a broker at {dead}" in text, text
    (gave_up,) = [line for line in text.splitlines() if "no broker answered" in line]
    assert "--broker" in gave_up and "$TWINFOCUS_BROKER" in gave_up, text
    assert earlier.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["y.mcap"]  # no partial, no empty file
    assert time.monotonic() - t < 60


@pytest.mark.timeout(240)
def test_a_busy_port_is_one_line_and_the_earlier_log_survives(tmp_path):
    earlier = tmp_path / "graph.mcap"
    small_log(earlier, n_frames=3)
    before = earlier.read_bytes()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        g = Launched("launch/sim.yaml", f"port:={port}", f"out:={tmp_path}", *SMALL, "record:=true")
        try:
            code, took = ended_within(g, 60)
        finally:
            g.kill()
    assert code == 2, g.text
    assert "Traceback" not in g.text and f"{port}" in g.text, g.text
    assert earlier.read_bytes() == before
