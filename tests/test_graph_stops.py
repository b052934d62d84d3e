"""A stopped node, a cut log and a bad launch argument: each run that did not finish its work
ends non-zero, names what stopped it first, keeps the earlier log byte for byte and counts what
was lost (beside tests/test_log_faults.py, whose fixtures these reuse).

* the solver SIGTERMed or SIGKILLed mid-scan while recording over an earlier log: the launcher
  names the solver (not the visualizer that finished after it), exits 1, the earlier log's
  SHA-256 is unchanged and the recording lies beside it under a partial name; after SIGTERM the
  incomplete scan counts expected = the measurements the synchronizer paired (its own line
  says how many), missing = those not focused;
* a replay of a log cut at half its bytes, or with one frame damaged: exit 1, the loss in one
  line and in metrics.json; ``twinfocus play`` of a cut log exits 1 and says where it was cut;
* ``rows:=abc``, ``rows:=-5``, ``rate:=nan``: one line, exit 2, before any node starts.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import time
from pathlib import Path

import pytest

from msgs.mcap_log import LogReader
from nodes.runtime.testing import patience
from tests.test_graph import Launched, free_port, run_cli
from tests.test_graph_faults import SMALL, pids_by_name, replay, small_log
from tests.test_log_faults import damage_frame, frames_log


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _partials(folder: Path) -> list[Path]:
    return sorted(folder.glob("graph.partial-*.mcap"))


def wait_recorded(g: Launched, folder: Path, topic: str, n: int, timeout_s: float = 180) -> None:
    """Until the recorder's partial file has a readable header and ``n`` messages on ``topic``
    (a file still being written is read again, not taken for a broken one)."""
    deadline = time.monotonic() + patience(timeout_s)
    while True:
        for p in _partials(folder):
            try:
                if LogReader(p).counts.get(topic, 0) >= n:
                    return
            except Exception:  # its first bytes not written yet
                pass
        assert g.proc.poll() is None and time.monotonic() < deadline, g.text
        time.sleep(0.1)


@pytest.mark.slow
@pytest.mark.timeout(400)
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["TERM", "KILL"])
def test_a_stopped_solver_fails_the_run_keeps_the_earlier_log_and_counts_the_scan(tmp_path, sig):
    out = tmp_path / "out"
    earlier = frames_log(out / "graph.mcap", n=5)  # a good earlier log where the recorder writes
    before = sha256(earlier)
    # rate 0.5: the 60 frames take 12 s, so the solver is mid-scan when it is stopped
    g = Launched(
        "launch/sim.yaml", f"port:={free_port()}", f"out:={out}", *SMALL, "rate:=0.5", "exit_after:=1", "record:=true"
    )
    try:
        wait_recorded(g, out, "sar/measurement", 10)
        os.kill(pids_by_name(g)["solver"], sig)
        code = g.wait(240)
    finally:
        g.kill()
    assert code == 1, g.text
    why = "was stopped by SIGTERM from outside the launcher" if sig == signal.SIGTERM else "was killed by SIGKILL"
    (named,) = [ln for ln in g.lines if "[launch]" in ln and "stopping the graph" in ln]
    assert f"node 'solver' {why}; stopping the graph" in named, g.text
    assert f"graph stopped: failed (node 'solver' {why}" in g.text, g.text
    assert "Traceback" not in g.text, g.text
    # the earlier log byte for byte, the recording beside it
    assert sha256(earlier) == before, g.text
    (partial,) = _partials(out)
    assert 10 <= LogReader(partial).counts["sar/measurement"] < 60
    (kept,) = [ln for ln in g.lines if "[recorder]" in ln and "stopped before the run ended as planned" in ln]
    assert "node 'solver'" in kept and partial.name in kept and "is the earlier log, unchanged" in kept, kept
    assert not (out / "focus" / "sim").exists()  # never a complete result's folder
    if sig == signal.SIGKILL:
        return
    m = json.loads((out / "focus" / "sim.incomplete" / "metrics.json").read_text())
    paired = int(re.search(r"\[synchronizer\]\s+paired (\d+) radar frame", g.text).group(1))
    assert m["complete"] is False and "before its last measurement" in m["incomplete_reason"], m
    assert m["n_positions_expected"] == paired, (m, paired)
    assert m["n_positions_missing"] == paired - m["n_positions"] >= 0, m
    if m["n_positions_missing"]:
        assert (
            f"scan 'sim': {m['n_positions_missing']} of its {paired} positions never reached the solver "
            f"before it stopped; focused the {m['n_positions']} that did"
        ) in g.text, g.text


# -- replays of cut and damaged logs --------------------------------------------------------------


@pytest.mark.timeout(300)
# 10 s idle: out of make test-fast (a whole graph replays a log); the reading of a cut log is
# tests/test_mcap.py::test_every_cut_of_a_file_reads_as_a_prefix, quick
@pytest.mark.slow
def test_a_replay_of_a_log_cut_in_half_exits_non_zero_and_says_what_it_lacked(tmp_path):
    full = tmp_path / "full.mcap"
    small_log(full)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    arrived = LogReader(cut).counts["radar/frame"]  # what the cut file still holds
    assert 0 < arrived < 30
    g = replay(tmp_path, cut, "scan_timeout:=2")
    code = g.exit_code(200)
    assert code == 1, g.text
    m = json.loads((tmp_path / "out" / "focus" / "run.incomplete" / "metrics.json").read_text())
    assert m["complete"] is False and m["n_positions"] == arrived, m
    (named,) = [ln for ln in g.lines if "[launch]" in ln and "stopping the graph" in ln]
    assert "node 'solver' exited with status 1" in named, g.text
    assert f"scan 'run': {arrived} positions focused, its end never arrived" in named, named
    (end,) = [ln for ln in g.lines if "[player]" in ln and "end of log" in ln]
    assert "the log is cut at byte" in end and f"radar/frame seq {arrived - 1}" in end, end


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_replay_of_a_log_with_a_damaged_frame_exits_non_zero_and_counts_it(tmp_path):
    log = tmp_path / "log.mcap"
    small_log(log)
    bad, _ = damage_frame(log, 12)  # one frame's bytes: exactly one position lost
    g = replay(tmp_path, bad)
    code = g.exit_code(200)
    assert code == 1, g.text
    m = json.loads((tmp_path / "out" / "focus" / "run" / "metrics.json").read_text())
    assert m["n_positions_missing"] == 1 and m["n_positions_expected"] == 30, m
    (named,) = [ln for ln in g.lines if "[launch]" in ln and "stopping the graph" in ln]
    assert "scan 'run': 1 of 30 positions missing" in named, named


def test_play_of_a_cut_log_exits_1_and_says_where_it_was_cut(tmp_path, capfd):
    from nodes.runtime.testing import local_broker
    from twinfocus.cli import main

    log = frames_log(tmp_path / "run.mcap", n=40)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log.read_bytes()[: log.stat().st_size // 2])
    last = LogReader(cut).counts["radar/frame"] - 1
    with local_broker() as ep:
        assert main(["play", str(cut), "--rate", "0", "--broker", ep]) == 1
    err = capfd.readouterr().err
    (end,) = [ln for ln in err.splitlines() if "end of log" in ln]
    assert "the log is cut at byte" in end and f"radar/frame seq {last}" in end, err
    with local_broker() as ep:  # the whole log: status 0
        assert main(["play", str(log), "--rate", "0", "--broker", ep]) == 0


# -- launch arguments -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "arg, words",
    [
        ("rows:=abc", "argument rows (default 130) must be an integer, got 'abc'"),
        ("record:=maybe", "argument record (default False) must be true or false, got 'maybe'"),
        ("estimator:=bogus", "node 'solver': parameter 'estimator' must be one of auto"),
        ("rows:=-5", "argument rows (default 130) must be >= 2, got -5"),
        ("rate:=nan", "argument rate (default 4.0) must be a number, got 'nan'"),
        ("web_port:=70000", "argument web_port (default 8765) must be >= 0 and <= 65535, got 70000"),
    ],
)
def test_a_bad_launch_argument_is_one_line_and_exit_2_before_any_node_starts(tmp_path, arg, words):
    t = time.monotonic()
    code, text = run_cli("launch", "launch/sim.yaml", f"port:={free_port()}", f"out:={tmp_path}", arg)
    assert code == 2, text
    assert len(text.strip().splitlines()) == 1 and words in text, text
    assert "started" not in text and "broker on" not in text and "Traceback" not in text, text
    assert list(tmp_path.iterdir()) == []
    assert time.monotonic() - t < patience(30)
