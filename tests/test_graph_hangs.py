"""Faults that used to hang the graph or end it with a wrong status, each bounded in time.

* a latched topic (the template) reaches its subscriber whatever order the nodes start in, with
  a subscriber of every topic (the recorder) beside them and the CPU kept busy;
* a scan dropped for want of a template ends ``exit_after:=1`` with a non-zero status and the
  reason;
* a node that stops answering (SIGSTOP) is named within seconds and the graph ends non-zero with
  the result marked incomplete, or the node is restarted where the launch file says ``respawn``;
* a memory check refuses before it allocates (``twinfocus simulate --height 1000``, ``render``).

Time bounds here are outer limits that keep a broken build from hanging the suite; what each
test asserts is a status, a line or a count.
"""

from __future__ import annotations

import itertools
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from nodes.runtime.node import Node
from nodes.runtime.testing import Probe, local_broker
from tests.test_graph import CLI, REPO, Launched, free_port
from tests.test_graph_faults import wait_text

REF_ROI = [-0.045, -0.005, -0.02, 0.02, 0.3]


@pytest.fixture
def cpu_hog():
    """Two busy processes beside the test, one per core of the 2-core machine."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    yield
    for h in hogs:
        h.kill()
        h.wait()


def wait_until(what: str, done, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not done():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout_s:g} s")
        time.sleep(0.01)


class Everything(Node):
    """A subscriber of every topic, as the recorder and the Foxglove bridge are."""

    NAME = "everything"

    def __init__(self, **kw):
        super().__init__(**kw)
        self.create_subscription("*", lambda topic, msg: None)


def _template_file(tmp_path: Path) -> Path:
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.twins.templates import save_template

    grid = ImageGrid.from_roi(REF_ROI, 12)
    path = tmp_path / "t.npz"
    save_template(path, np.random.default_rng(0).random(grid.shape).astype(np.float32), grid)
    return path


@pytest.mark.timeout(600)
@pytest.mark.parametrize("graph", [True, False], ids=["one-graph", "late-joiners"])
def test_the_template_reaches_its_subscriber_whatever_the_start_order(tmp_path, cpu_hog, graph):
    """Each order of builder, subscriber and a subscriber of every topic; ``one-graph``: each node
    waits for the others (as under the launcher); ``late-joiners``: none waits, each starts once the
    one before it runs, so a subscriber may come long after the template went out."""
    from nodes.template_builder import TemplateBuilder

    path = _template_file(tmp_path)
    names = ["template", "probe", "everything"]
    for order in itertools.permutations(names):
        with local_broker() as ep:
            wait_for = names if graph else []
            made = {
                "template": lambda wait_for=wait_for: TemplateBuilder(
                    name="template",
                    broker=ep,
                    params={
                        "source": "file",
                        "path": str(path),
                        "reference_roi": REF_ROI,
                        "size": 12,
                        "wait_for": wait_for,
                        "heartbeat_s": 0.2,
                    },
                ),
                "probe": lambda wait_for=wait_for: Probe(ep, listen=["twin/template"], wait_for=wait_for),
                "everything": lambda wait_for=wait_for: Everything(
                    broker=ep, params={"wait_for": wait_for, "heartbeat_s": 0.2}
                ),
            }
            nodes, threads = {}, []
            try:
                for name in order:
                    n = nodes[name] = made[name]()
                    t = threading.Thread(target=n.spin, daemon=True)
                    t.start()
                    threads.append(t)
                    if not graph:
                        wait_until(f"{name} running ({order})", lambda n=n: n.state == "running")
                got = nodes["probe"].wait_for("twin/template", 1, timeout_s=120)
                assert got[0].source == str(path), order
            finally:
                for n in nodes.values():
                    n.stop()
                for t in threads:
                    t.join(60)
            assert not any(t.is_alive() for t in threads), order


@pytest.mark.timeout(300)
def test_a_node_is_ready_only_once_its_own_subscriptions_reached_the_broker(tmp_path):
    """A subscriber of every topic is already there (the recorder): its subscription reaches a new
    node's publisher at once and covers the new node's private echo topic by prefix. The new
    node's own subscription socket is held off the broker for a second; until it is connected the
    node must not say it is ready, or what is published for it on its ready heartbeat is lost
    (the template the solver never got)."""
    import zmq

    from msgs import Header, Image
    from nodes.runtime.bus import discover

    with local_broker() as ep:
        everything = Everything(broker=ep, params={"heartbeat_s": 0.2})
        sender = Probe(ep, publish=["image/focused"], name="sender")
        late = Probe(ep, listen=["image/focused"], name="late")
        _, xpub = discover(ep, zmq.Context.instance(), 10)
        connect, poll = late._connect, late._poll
        held = {"since": None}

        def connect_held_off():
            # The node's SUB socket is not connected at all until the replug: connected and then
            # unplugged, its subscriptions could reach the broker first, and their round trip
            # back (\x01echo) be read by the node before the withdrawal (\x00echo) on a busy
            # machine: a ready node whose subscriber is off the broker (1 of 6 tries beside two
            # CPU hogs). This node's thread runs connect(); the others are connected already.
            real = zmq.Socket.connect

            def sub_held(sock, addr):
                return None if sock.type == zmq.SUB else real(sock, addr)

            zmq.Socket.connect = sub_held
            try:
                connect()
            finally:
                zmq.Socket.connect = real
            held["since"] = time.monotonic()

        def poll_and_replug(*a, **k):
            if held["since"] is not None and time.monotonic() - held["since"] > 1.0:
                held["since"] = None
                late._sub_sock.connect(xpub)
            return poll(*a, **k)

        late._connect, late._poll = connect_held_off, poll_and_replug
        threads = [threading.Thread(target=n.spin, daemon=True) for n in (everything, sender)]
        for t in threads:
            t.start()
        try:
            wait_until("sender running", lambda: sender.state == "running")
            t = threading.Thread(target=late.spin, daemon=True)
            t.start()
            threads.append(t)
            wait_until("late ready", lambda: late.state != "starting")
            img = np.zeros((2, 2), np.complex64)
            sender.send(
                "image/focused",
                Image(header=Header(), name="x", image=img, x_m=np.arange(2.0), y_m=np.arange(2.0), z_m=0.3),
            )
            assert late.wait_for("image/focused", 1, timeout_s=60)[0].name == "x"
        finally:
            for n in (everything, sender, late):
                n.stop()
            for t in threads:
                t.join(60)


# -- whole graphs ------------------------------------------------------------------------------

SMALL = ["columns:=2", "rows:=30", "size:=16", "iterations:=5", "web_port:=0"]


def _sim_launch_file(tmp_path: Path, edit) -> Path:
    """launch/sim.yaml with its node list edited by ``edit(nodes)``, beside a copy of what it includes."""
    import shutil

    import yaml

    doc = yaml.safe_load((REPO / "launch" / "sim.yaml").read_text())
    edit(doc["nodes"])
    path = tmp_path / "graph.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    shutil.copy(REPO / "launch" / "paper.yaml", tmp_path / "paper.yaml")
    return path


def _node(nodes: list, name: str) -> dict:
    return next(n for n in nodes if n["name"] == name)


@pytest.mark.slow  # 11 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
@pytest.mark.timeout(400)
def test_a_dropped_last_scan_ends_the_graph_non_zero_with_the_reason(tmp_path):
    """No template ever comes (the builder is left out): the solver drops the scan after its wait,
    and ``exit_after:=1``, waiting for that scan, ends with status 1 instead of waiting forever."""

    def no_template(nodes):
        nodes.remove(_node(nodes, "template"))
        _node(nodes, "solver")["parameters"]["template_wait_s"] = 2

    path = _sim_launch_file(tmp_path, no_template)
    g = Launched(str(path), f"port:={free_port()}", f"out:={tmp_path / 'out'}", *SMALL, "rate:=0", "exit_after:=1")
    code = g.exit_code(300)
    assert code == 1, g.text
    assert "dropped scan 'sim': no template arrived on twin/template within 2 s" in g.text, g.text
    assert re.search(r"node 'visualizer' exited with status 1: scan 'sim' not focused: no template", g.text), g.text
    assert "Traceback" not in g.text, g.text


def _stop_synchronizer_mid_scan(g: Launched) -> int:
    wait_text(g, r"\[solver\]\s+scan 'sim' started", 240)
    time.sleep(2)  # the radar publishes 5 frames a second: the solver holds part of the scan, not all of it
    pid = int(re.search(r"started synchronizer \(\S+, pid (\d+)\)", g.text).group(1))
    os.kill(pid, signal.SIGSTOP)
    return pid


@pytest.mark.slow  # 15 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
@pytest.mark.timeout(400)
def test_a_stopped_node_is_named_and_the_result_is_marked_incomplete(tmp_path):
    out = tmp_path / "out"
    # rate 0.5: the 60 frames take 12 s, so the graph is mid-scan when the node stops
    g = Launched("launch/sim.yaml", f"port:={free_port()}", f"out:={out}", *SMALL, "rate:=0.5", "exit_after:=1")
    code = g.exit_code(300, first=_stop_synchronizer_mid_scan)
    assert code == 1, g.text
    assert re.search(
        r"node 'synchronizer' stopped answering \(no heartbeat for [\d.]+ s; its process is stopped", g.text
    ), g.text
    assert "Traceback" not in g.text, g.text
    m = json.loads((out / "focus" / "sim.incomplete" / "metrics.json").read_text())
    assert m["complete"] is False and "before its last measurement" in m["incomplete_reason"]
    # every position the radar published is counted: those focused plus those that never arrived
    published = 60
    assert 0 < m["n_positions"] < published
    assert m["n_positions"] + m["n_positions_missing"] == m["n_positions_expected"] <= published
    assert m["n_positions_missing"] > 0
    assert not (out / "focus" / "sim").exists()  # a complete result's folder is never written by a partial scan


@pytest.mark.slow  # 22 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
@pytest.mark.timeout(400)
def test_a_stopped_node_that_may_respawn_is_replaced_and_the_graph_focuses(tmp_path):
    def respawn(nodes):
        _node(nodes, "synchronizer").update({"respawn": True, "respawn_delay": 0.2})

    path = _sim_launch_file(tmp_path, respawn)
    g = Launched(str(path), f"port:={free_port()}", f"out:={tmp_path / 'out'}", *SMALL, "rate:=0.5", "exit_after:=1")
    code = g.exit_code(300, first=_stop_synchronizer_mid_scan)
    assert code == 0, g.text
    assert re.search(r"node 'synchronizer' stopped answering .*; respawning it in 0.2 s \(respawn 1 of 3\)", g.text), (
        g.text
    )
    assert re.search(r"focused scan 'sim': \d+ positions", g.text), g.text


@pytest.mark.timeout(120)
@pytest.mark.parametrize(
    "command, words",
    [
        # the tallest letters the options allow (5 m), close up: 0.1 mm scatterer spacing
        (
            ["simulate", "--out", "{tmp}/s.npz", "--height", "5", "--target-height", "5", "--distance", "0.05"],
            "placing this scene's",
        ),
        (["render", "--out", "{tmp}/r", "--width", "1000000", "--height-px", "1000000"], "this rendering needs about"),
    ],
    ids=["simulate-height", "render-picture"],
)
def test_what_cannot_fit_in_memory_is_refused_before_it_allocates(tmp_path, command, words):
    """Terabytes asked for: one line, status 2, nothing written (before, the check itself
    allocated them and ended in a traceback)."""
    argv = [a.format(tmp=tmp_path) for a in command]
    r = subprocess.run([*CLI, *argv], capture_output=True, text=True, timeout=100, cwd=REPO)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and words in lines[0] and "GiB is available" in lines[0], r.stderr
    assert list(tmp_path.iterdir()) == []
