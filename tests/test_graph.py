"""End to end: whole graphs started from the launch files, as a user would.

* sim.yaml: the simulated graph focuses a scan; the live page is checked in a real headless
  browser (Debian's chromium); Ctrl-C stops every process cleanly.
* replay.yaml: a recorded log through player -> synchronizer -> solver gives the same phase
  vector as ``twinfocus focus`` on the equivalent scan file.
* a crashing node stops the graph with a clear message.
"""

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from msgs.mcap_log import LogWriter
from nodes.runtime.testing import Probe, patience, running, write_driver_messages

REPO = Path(__file__).resolve().parent.parent
CLI = [sys.executable, "-c", "import sys; from twinfocus.cli import main; sys.exit(main())"]


def run_cli(*args: str) -> tuple[int, str]:
    """``twinfocus ARGS`` in a process of its own, run from the repository with it on PYTHONPATH
    (at most 120 s): the exit code and stdout then stderr as one text."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = subprocess.run([*CLI, *args], cwd=REPO, capture_output=True, timeout=120, env=env)
    return out.returncode, (out.stdout + out.stderr).decode()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def offline_simulate_and_focus(
    tmp_path: Path, scene: list[str], sc, size: str, iterations: str, focus_timeout_s: float
) -> Path:
    """``twinfocus simulate SCENE`` and ``twinfocus focus --template-scan`` of that scan on the
    scenario ``sc``'s regions, each in its own process as a user runs them: the offline side of a
    live-versus-offline test. Returns the focus folder (``tmp_path / "offline"``)."""
    roi = [str(v) for v in sc.reference_roi()], [str(v) for v in sc.target_roi()]
    scan, ref, out = tmp_path / "scan.npz", tmp_path / "ref.npz", tmp_path / "offline"
    sim = subprocess.run(
        [*CLI, "simulate", *scene, "--out", str(scan), "--template-out", str(ref), "--quiet"],
        cwd=REPO,
        capture_output=True,
        timeout=300,
    )
    assert sim.returncode == 0, sim.stderr.decode()
    focus = subprocess.run(
        [
            *CLI,
            "focus",
            str(scan),
            "--template-scan",
            str(ref),
            "--reference-roi",
            *roi[0],
            "--target-roi",
            *roi[1],
            "--size",
            size,
            "--iterations",
            iterations,
            "--out",
            str(out),
            "--no-pictures",
            "--quiet",
        ],  # fmt: skip
        cwd=REPO,
        capture_output=True,
        timeout=focus_timeout_s,
    )
    assert focus.returncode == 0, focus.stderr.decode()
    return out


def sim_graph(tmp_path: Path, sc, size: str, iterations: str, *args: str, rate: str = "0") -> "Launched":
    """``twinfocus launch launch/sim.yaml`` of one scan (``exit_after:=1``, as fast as it is made:
    ``rate:=0``, or at ``rate``) on the scenario ``sc``'s regions, writing under ``tmp_path /
    "graph"``; ``args``: the scene's own launch arguments (columns, rows, seed, ...)."""
    yaml_list = lambda r: "[" + ",".join(str(v) for v in r) + "]"  # noqa: E731
    return Launched(
        "launch/sim.yaml", f"port:={free_port()}", "web_port:=0", f"out:={tmp_path / 'graph'}", *args,
        f"size:={size}", f"iterations:={iterations}", f"rate:={rate}", "exit_after:=1",
        f"reference_roi:={yaml_list(sc.reference_roi())}", f"target_roi:={yaml_list(sc.target_roi())}",
    )  # fmt: skip


class Launched:
    """``twinfocus launch ...`` in a subprocess, its output collected by a thread."""

    def __init__(self, *args, cwd=REPO):
        self.proc = subprocess.Popen(
            [*CLI, "launch", *args],
            cwd=cwd,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONPATH": str(REPO)},
        )
        self.lines: list[str] = []
        self.thread = threading.Thread(target=self._pump, daemon=True)
        self.thread.start()

    def _pump(self):
        for raw in iter(self.proc.stdout.readline, b""):
            self.lines.append(raw.decode(errors="replace").rstrip())

    @property
    def text(self) -> str:
        return "\n".join(self.lines)

    def pids(self) -> list[int]:
        return [int(p) for p in re.findall(r"started \S+ \(\S+, pid (\d+)\)", self.text)]

    def wait(self, timeout):
        try:
            return self.proc.wait(patience(timeout))  # an outer bound: stretched on a busy machine
        finally:
            self.thread.join(5)

    def exit_code(self, timeout, first=None):
        """The launcher's exit code, waited for up to ``timeout`` s (:meth:`wait`) after
        ``first(self)`` if given; the graph is killed (:meth:`kill`) whatever happens."""
        try:
            if first is not None:
                first(self)
            return self.wait(timeout)
        finally:
            self.kill()

    def kill(self):
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        for pid in self.pids():  # children die with the launcher (parent-death signal); make sure
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie is not alive
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip(
            "Debian's chromium is not installed and could not be installed (make test installs it: apt-get install chromium)"
        )
    return exe


def browser_dom(url: str) -> str:
    """The page's DOM after its scripts ran, from a fresh headless chromium profile."""
    with tempfile.TemporaryDirectory() as profile:
        cmd = [
            chromium(),
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--no-first-run",
            f"--user-data-dir={profile}",
            "--virtual-time-budget=5000",
            "--dump-dom",
            url,
        ]
        out = subprocess.run(cmd, capture_output=True, timeout=90)
    return out.stdout.decode(errors="replace")


@pytest.mark.slow
def test_sim_launch_focuses_shows_the_page_in_a_browser_and_stops_on_ctrl_c(tmp_path):
    port, web = free_port(), free_port()
    g = Launched(
        "launch/sim.yaml",
        f"port:={port}",
        f"web_port:={web}",
        f"out:={tmp_path}",
        "columns:=2",
        "rows:=24",
        "size:=24",
        "iterations:=10",
        "rate:=0",
    )
    try:
        probe = Probe(
            f"tcp://127.0.0.1:{port}",
            listen=["image/focused", "autofocus/result"],
            name="e2e_probe",
            params={"ready_timeout_s": 120},
        )
        with running(probe, start_timeout_s=120):
            target = probe.wait_for("image/focused", 1, timeout_s=180, where=lambda m: m.name == "target")[0]
            (result,) = probe.wait_for("autofocus/result", 1, where=lambda r: not r.metrics_pending)
        assert target.image.shape == (24, 24) and result.phase_rad.shape == (48,)
        assert result.metrics["target_ssim_corrected"] > result.metrics["target_ssim_uncorrected"]

        # The live page in a real browser: it loads, and shows this focused image.
        dom = browser_dom(f"http://127.0.0.1:{web}/")
        tag = re.search(r'<img[^>]*id="focused"[^>]*>', dom)
        assert tag, dom[:2000]
        assert 'data-loaded="1"' in tag.group(0) and 'data-natural-width="24"' in tag.group(0), tag.group(0)
        png = cv2.imread(str(tmp_path / "pictures" / "focused.png"))
        amp = np.abs(target.image)
        expect = cv2.applyColorMap(np.round(255 * amp / amp.max()).astype(np.uint8), cv2.COLORMAP_INFERNO)
        assert np.array_equal(png, expect)
        phase_file = tmp_path / "focus" / "sim" / "phase.npy"
        deadline = time.monotonic() + 120  # written after the result is published
        while not phase_file.is_file() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert np.array_equal(np.load(phase_file), result.phase_rad)

        # Ctrl-C: the launcher stops every node cleanly.
        g.proc.send_signal(signal.SIGINT)
        assert g.wait(60) == 0, g.text
    finally:
        g.kill()
    assert "SIGINT received: stopping the graph" in g.text and "graph stopped" in g.text, g.text
    assert "Traceback" not in g.text, g.text
    pids = g.pids()
    assert len(pids) == 6
    assert not [p for p in pids if alive(p)]


@pytest.mark.slow  # 1.7 s (2 cores, idle): out of make test-fast (benchmarks/results/test_fast.json)
def test_a_crashing_node_stops_the_graph_with_a_clear_message(tmp_path):
    launch = tmp_path / "crash.yaml"
    launch.write_text(
        "arguments:\n  port: {default: 7447}\n"
        "broker: tcp://127.0.0.1:$(arg port)\n"
        "nodes:\n"
        "  - {name: sync, node: synchronizer}\n"
        f"  - {{name: player, node: player, parameters: {{log: {tmp_path / 'missing.mcap'}}}}}\n"
    )
    g = Launched(str(launch), f"port:={free_port()}")
    code = g.exit_code(120)
    assert code == 2, g.text  # the player's user error is the launch's
    assert "missing.mcap: no such file" in g.text
    assert "node 'player' exited with status 2; stopping the graph" in g.text
    assert not [p for p in g.pids() if alive(p)]


@pytest.mark.slow
def test_replayed_log_gives_the_phase_of_twinfocus_focus_on_the_equivalent_scan(tmp_path):
    from twinfocus.imaging.backprojection.numba_backend import backproject
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.motion.tracking_errors import gaussian_errors
    from twinfocus.motion.trajectory import Poses, handheld_zigzag, phase_centres
    from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
    from twinfocus.radar.scan import Scan
    from twinfocus.scene import scatterer_spacing_m
    from twinfocus.simulation.if_simulator import add_thermal_noise, simulate_if
    from twinfocus.simulation.scenario import Scenario
    from twinfocus.twins.templates import save_template

    # A small hand sweep of the paper's scene; VIO poses at 30 Hz with jitter, radar at 10 Hz.
    sc = Scenario(n_columns=2, n_rows=20, seed=4)
    rng = np.random.default_rng(4)
    chirp, array = Chirp(), mmwcas_virtual_array()
    radar = handheld_zigzag(2, 20, rng=rng, t0_ns=10**10, column_change_s=0.3)
    t_vio = np.arange(radar.timestamps_ns[0] - 10**8, radar.timestamps_ns[-1] + 10**8, 33_333_333, dtype=np.int64)
    truth_vio = radar.interpolate(t_vio)
    vio = Poses(
        t_vio, truth_vio.position_m + gaussian_errors(t_vio.size, (0.3e-3, 0.3e-3, 0.5e-3), rng), truth_vio.quat_xyzw
    )
    pts, amps = sc.scene().scatterers(scatterer_spacing_m(0.6), 1, speckle=True)
    data = add_thermal_noise(simulate_if(pts, amps, phase_centres(radar, array), chirp), 20.0, rng)

    # The equivalent scan file: the same samples on the poses interpolated at the radar stamps.
    tracked = phase_centres(vio.interpolate(radar.timestamps_ns), array)
    Scan(data, tracked, chirp, timestamps_ns=radar.timestamps_ns).save(tmp_path / "scan.npz")
    ref_roi, tgt_roi = sc.reference_roi(), sc.target_roi()
    ref_grid = ImageGrid.from_roi(ref_roi, 24)
    template = np.abs(backproject(data, phase_centres(radar, array), chirp, ref_grid))
    save_template(tmp_path / "template.npz", template, ref_grid)

    # The log: what the drivers would have published, in the order it would have arrived.
    with LogWriter(tmp_path / "run.mcap") as w:
        write_driver_messages(w, radar, vio, data, chirp, array)

    # projections, then the optimiser: both steps of an amplitude template's estimate
    common = ["--size", "24", "--iterations", "40", "--precision", "float64", "--estimator", "projection-refined"]
    roi = lambda r: [str(v) for v in r]  # noqa: E731
    focus = subprocess.run(
        [
            *CLI,
            "focus",
            str(tmp_path / "scan.npz"),
            "--reference-roi",
            *roi(ref_roi),
            "--target-roi",
            *roi(tgt_roi),
            "--template",
            str(tmp_path / "template.npz"),
            "--out",
            str(tmp_path / "offline"),
            "--no-pictures",
            "--quiet",
            *common,
        ],
        cwd=REPO,
        capture_output=True,
        timeout=300,
    )
    assert focus.returncode == 0, focus.stderr.decode()

    yaml_list = lambda r: "[" + ",".join(roi(r)) + "]"  # noqa: E731
    g = Launched(
        "launch/replay.yaml",
        f"log:={tmp_path / 'run.mcap'}",
        f"out:={tmp_path / 'graph'}",
        f"template:={tmp_path / 'template.npz'}",
        f"port:={free_port()}",
        "web_port:=0",
        "size:=24",
        "iterations:=40",
        "precision:=float64",
        "estimator:=projection-refined",
        f"reference_roi:={yaml_list(ref_roi)}",
        f"target_roi:={yaml_list(tgt_roi)}",
        "rate:=4",
    )
    code = g.exit_code(300)
    assert code == 0, g.text
    assert "paired 40 radar frame(s), could not pair 0" in g.text, g.text
    offline = np.load(tmp_path / "offline" / "phase.npy")
    streamed = np.load(tmp_path / "graph" / "focus" / "run" / "phase.npy")
    assert streamed.shape == offline.shape == (40,)
    # Replayed at 4x (not all at once), so the solver really built its basis in many batches.
    assert json.loads((tmp_path / "graph" / "focus" / "run" / "metrics.json").read_text())["basis_batches"] > 5
    # Both build the same sub-image basis rows (the back-projection's range window starts on the
    # global lattice dr * integer, so a batch's profiles are samples of the whole scan's) and run
    # the same FocusPlan.focus_bases; what differs is float64 rounding (each batch's window starts
    # at another lattice node), which 40 Adam steps carry to the phase. Measured: 5.7e-7 rad
    # (float64, this case); the tolerance is ~10x that. (Before the lattice, each batch sampled
    # its profiles on its own grid and this test needed 1e-2 rad.)
    np.testing.assert_allclose(np.angle(np.exp(1j * (streamed - offline))), 0.0, rtol=0, atol=5e-6)
