"""Faults injected into logs, recordings and exports: each checks that the earlier log is
byte-identical, the one line that names the fault, and the exit status.

* damage: random bytes in the middle of a recorded log; the CRC names the chunk (offset,
  topic, time), the player publishes the rest and nothing damaged, a replay focuses the scan
  without the damaged frame and its metrics count it;
* a recorder under a launcher: the launcher SIGKILLed, a node SIGTERMed, or a node hung mid-run
  keeps the earlier log and leaves the recording beside it under a partial name; a run that
  ends as planned replaces it;
* a full disk while recording or exporting (the writer's file raises ENOSPC): one line, no
  partial file left, the earlier file kept; an export of a log with nothing to show refuses.
"""

from __future__ import annotations

import errno
import io
import json
import os
import re
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from msgs import Header, Pose, RadarFrame
from msgs.mcap_log import LogReader, LogWriter
from nodes.runtime.testing import Probe, local_broker, running
from tests.test_graph import Launched, free_port
from twinfocus.radar.fmcw import Chirp

N_FRAMES = 60


def frames_log(path: Path, n: int = N_FRAMES, spacing_ns: int = 50_000_000) -> Path:
    """A log as the recorder writes it: radar frames (data = index, so any damage shows) and a
    pose after each, ``spacing_ns`` apart."""
    c = Chirp()
    with LogWriter(path, overwrite=True) as w:
        for i in range(n):
            t = 10**18 + i * spacing_ns
            data = np.full((4, 64), i + 1j * i, np.complex64)
            w.write(
                "radar/frame",
                RadarFrame(
                    header=Header(t, i, "radar"),
                    data=data,
                    f0_hz=c.f0_hz,
                    slope_hz_per_s=c.slope_hz_per_s,
                    fs_hz=c.fs_hz,
                    channel_offsets_m=np.zeros((4, 3)),
                    scan_id="s",
                    index=i,
                    last=i == n - 1,
                ),
                log_time_ns=t,
            )
            w.write(
                "vio/pose",
                Pose(
                    header=Header(t + 1, i, "scene"),
                    position_m=np.array([0.001 * i, 0, 0]),
                    quat_xyzw=np.array([0, 0, 0, 1.0]),
                ),
                log_time_ns=t + 1,
            )
    return path


def damage_frame(path: Path, index: int, seed: int = 0) -> tuple[Path, int]:
    """Write random bytes over the samples of radar frame ``index``; returns the damaged copy
    and the offset hit."""
    logged = [m for m in LogReader(path).messages(["radar/frame"])]
    data = bytearray(path.read_bytes())
    hit = data.find(logged[index].blob) + len(logged[index].blob) // 2
    noise = np.random.default_rng(seed).integers(0, 256, 512, dtype=np.uint8).tobytes()
    data[hit : hit + len(noise)] = noise
    bad = path.with_name("damaged.mcap")
    bad.write_bytes(bytes(data))
    return bad, hit


# -- damage ---------------------------------------------------------------------------------------


def test_random_bytes_in_a_frame_cost_that_frame_named_by_topic_time_and_offset(tmp_path):
    log = frames_log(tmp_path / "run.mcap")
    bad, hit = damage_frame(log, 20)
    r = LogReader(bad)
    assert not r.complete and len(r.damage) == 1
    (d,) = r.damage
    assert d.offset <= hit < d.offset + d.length
    assert d.lost == {"radar/frame": 1}
    assert d.start_ns == d.end_ns == 10**18 + 20 * 50_000_000
    line = r.condition
    assert "\n" not in line and f"bytes {d.offset}-" in line and "radar/frame (1 message)" in line, line
    assert "1.000-1.000 s into the log" in line, line
    frames = [m.decode() for m in r.messages(["radar/frame"])]
    assert [f.index for f in frames] == [i for i in range(N_FRAMES) if i != 20]
    assert all(np.all(f.data == f.index + 1j * f.index) for f in frames)
    assert r.counts["vio/pose"] == N_FRAMES  # the other topic is whole


@pytest.mark.parametrize("seed", range(6))
def test_4_kb_of_random_bytes_anywhere_in_the_middle_cost_only_the_messages_they_hit(tmp_path, seed):
    """Record headers, chunk headers, message indexes and samples alike: whatever the bytes
    hit, every message read back is intact, everything clear of the damage is read, and the
    damage is named."""
    log = frames_log(tmp_path / "run.mcap")
    whole = bytes(log.read_bytes())
    rng = np.random.default_rng(seed)
    hit = int(rng.integers(len(whole) // 4, len(whole) // 2))
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(whole[:hit] + rng.integers(0, 256, 4096, dtype=np.uint8).tobytes() + whole[hit + 4096 :])
    r = LogReader(bad)
    assert r.damage and "damaged" in r.condition and "\n" not in r.condition
    assert any(d.offset <= hit + 4095 and hit < d.offset + d.length for d in r.damage)
    got = {(m.topic, m.decode().header.seq): m.decode() for m in r.messages()}
    for (topic, seq), msg in got.items():  # nothing garbled
        if topic == "radar/frame":
            assert msg.index == seq and np.all(msg.data == seq + 1j * seq)
        else:
            assert np.allclose(msg.position_m, [0.001 * seq, 0, 0])
    # a message whose chunk is clear of the damage (chunks are < 3 kB here) is read
    for m in LogReader(log).messages():
        at = whole.find(m.blob)
        if at + len(m.blob) < hit - 3000 or at > hit + 4096 + 3000:
            assert (m.topic, m.sequence) in got, (m.topic, m.sequence)


def test_the_player_publishes_what_survives_and_later_frames_count_the_lost_one(tmp_path, capfd):
    from nodes.player import Player

    bad, _ = damage_frame(frames_log(tmp_path / "run.mcap"), 20)
    with local_broker() as ep:
        probe = Probe(ep, listen=["radar/frame", "vio/pose"], name="probe")
        player = Player(broker=ep, params={"log": str(bad), "rate": 0, "wait_for": ["probe"]})
        with running(probe):
            assert player.spin() == 0
            frames = probe.wait_for("radar/frame", N_FRAMES - 1, timeout_s=60)
            poses = probe.wait_for("vio/pose", N_FRAMES, timeout_s=60)
    assert [f.index for f in frames] == [i for i in range(N_FRAMES) if i != 20]
    assert all(np.isfinite(f.data).all() and np.all(f.data == f.index + 1j * f.index) for f in frames)
    assert [f.frames_lost for f in frames] == [0] * 20 + [1] * (N_FRAMES - 21)
    assert len(poses) == N_FRAMES
    err = capfd.readouterr().err
    (start,) = [ln for ln in err.splitlines() if "playing" in ln]
    assert "damaged" in start and "radar/frame (1 message)" in start, err
    assert "radar/frame: 1 message(s) missing from the log before seq 21" in err, err
    assert "end of log: published" in err and "missing from the log or damaged: radar/frame: 1" in err, err


def test_an_unchunked_log_with_nan_in_a_frame_plays_without_it(tmp_path, capfd):
    """Logs written before chunks had CRCs: a frame whose samples decode to NaN is skipped."""
    from nodes.player import Player

    log = frames_log(tmp_path / "run.mcap", n=6)
    logged = list(LogReader(log).messages(["radar/frame"]))
    data = bytearray(log.read_bytes())
    at = data.find(np.complex64(2 + 2j).tobytes(), data.find(logged[2].blob))  # frame 2's first sample
    data[at : at + 4] = np.array([np.nan], np.float32).tobytes()
    bad = tmp_path / "nan.mcap"
    bad.write_bytes(bytes(data))
    # the CRC catches it in a chunked log; here the check on the samples must
    import msgs.mcap_log as mcap_log

    orig = mcap_log.breakup_chunk
    mcap_log.breakup_chunk = lambda chunk, validate_crc=False: orig(chunk, validate_crc=False)
    try:
        with local_broker() as ep:
            probe = Probe(ep, listen=["radar/frame"], name="probe")
            player = Player(broker=ep, params={"log": str(bad), "rate": 0, "wait_for": ["probe"]})
            with running(probe):
                assert player.spin() == 0
                frames = probe.wait_for("radar/frame", 5, timeout_s=60)
    finally:
        mcap_log.breakup_chunk = orig
    assert [f.index for f in frames] == [0, 1, 3, 4, 5]
    err = capfd.readouterr().err
    assert "radar/frame seq 2" in err and "NaN or inf" in err, err


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_replay_of_a_damaged_log_focuses_the_scan_without_the_frame_and_counts_it(tmp_path):
    from tests.test_graph_faults import replay, small_log

    log = tmp_path / "log.mcap"
    small_log(log)
    bad, _ = damage_frame(log, 12)
    g = replay(tmp_path, bad)
    code = g.exit_code(240)
    assert code == 1, g.text  # focused without the damaged frame: not every position arrived
    assert "damaged" in g.text and "radar/frame (1 message)" in g.text, g.text
    assert "NaN" not in g.text, g.text
    (metrics_file,) = (tmp_path / "out" / "focus").glob("*/metrics.json")
    metrics = json.loads(metrics_file.read_text())
    assert metrics["n_positions_missing"] == 1 and metrics["n_positions_expected"] == 30, metrics
    assert metrics["capture"]["frames_lost"] == 1, metrics


# -- a recorder under a launcher ------------------------------------------------------------------


def _graph(tmp_path: Path, src: Path, out: Path, rate: float) -> Path:
    """player (on_exit: shutdown: its end is the run's planned end) -> recorder."""
    path = tmp_path / "rec.yaml"
    path.write_text(
        "arguments:\n  port: {default: 7447}\n"
        "broker: tcp://127.0.0.1:$(arg port)\n"
        "nodes:\n"
        f"  - {{name: player, node: player, on_exit: shutdown, parameters: {{log: '{src}', rate: {rate}}}}}\n"
        f"  - {{name: recorder, node: recorder, parameters: {{out: '{out}', overwrite: true}}}}\n"
    )
    return path


def _partials(folder: Path) -> list[Path]:
    return sorted(folder.glob("graph.partial-*.mcap"))


def _wait_frames_recorded(g: Launched, folder: Path, n: int, timeout_s: float = 120) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        found = _partials(folder)
        if found and LogReader(found[0]).counts.get("radar/frame", 0) >= n:
            return
        assert g.proc.poll() is None and time.monotonic() < deadline, g.text
        time.sleep(0.1)


@pytest.fixture
def good_log(tmp_path):
    """A first run that ended as planned: out/graph.mcap holds every frame."""
    src = frames_log(tmp_path / "src.mcap", n=100)
    out = tmp_path / "out" / "graph.mcap"
    g = Launched(str(_graph(tmp_path, src, out, rate=0)), f"port:={free_port()}")
    assert g.exit_code(180) == 0, g.text
    assert LogReader(out).complete and LogReader(out).counts["radar/frame"] == 100, g.text
    assert _partials(out.parent) == [] and "wrote " in g.text and str(out) in g.text, g.text
    return src, out, out.read_bytes()


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_a_killed_launcher_keeps_the_earlier_log_and_the_recording_beside_it(tmp_path, good_log):
    src, out, before = good_log
    g = Launched(str(_graph(tmp_path, src, out, rate=0.5)), f"port:={free_port()}")  # 10 s of frames
    try:
        _wait_frames_recorded(g, out.parent, 10)
        g.proc.send_signal(signal.SIGKILL)
        g.proc.wait(10)
        # The recorder notices (parent-death signal) and finishes its file under the partial name.
        deadline = time.monotonic() + 60
        while not LogReader(_partials(out.parent)[0]).complete:
            assert time.monotonic() < deadline, "the partial recording was never finished"
            time.sleep(0.1)
    finally:
        g.kill()
    assert out.read_bytes() == before
    (partial,) = _partials(out.parent)
    n = LogReader(partial).counts["radar/frame"]
    assert 10 <= n < 100


def _stopped_mid_run(tmp_path, src, out, stop):
    """A graph replaying ``src`` at half speed and recording into ``out``, ``stop(g)`` called once
    10 frames are recorded: its exit code (within 120 s) and the launched graph."""
    g = Launched(str(_graph(tmp_path, src, out, rate=0.5)), f"port:={free_port()}")

    def first(g):
        _wait_frames_recorded(g, out.parent, 10)
        stop(g)

    return g.exit_code(120, first=first), g


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_a_node_stopped_mid_run_keeps_the_earlier_log_and_says_so(tmp_path, good_log):
    src, out, before = good_log
    player = lambda g: int(re.search(r"started player \(\S+, pid (\d+)\)", g.text).group(1))
    code, g = _stopped_mid_run(tmp_path, src, out, lambda g: os.kill(player(g), signal.SIGTERM))
    assert code != 0, g.text
    assert out.read_bytes() == before
    (partial,) = _partials(out.parent)
    assert LogReader(partial).complete and 10 <= LogReader(partial).counts["radar/frame"] < 100
    lines = [ln for ln in g.lines if "[recorder]" in ln and "stopped before the run ended as planned" in ln]
    assert len(lines) == 1, g.text
    # the launcher's word (it names the player as soon as its heartbeat says SIGTERM), or the
    # recorder's own when the player had ended before the stop
    named = ("node 'player' was stopped by SIGTERM from outside the launcher", "node player (received SIGTERM) failed")
    assert any(n in lines[0] for n in named) and partial.name in lines[0], lines[0]
    assert f"{out} is the earlier log, unchanged" in lines[0], lines[0]


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_a_run_that_ends_as_planned_replaces_the_earlier_log(tmp_path, good_log):
    src, out, before = good_log
    short = frames_log(tmp_path / "short.mcap", n=7)
    g = Launched(str(_graph(tmp_path, short, out, rate=0)), f"port:={free_port()}")
    assert g.exit_code(180) == 0, g.text
    assert out.read_bytes() != before and LogReader(out).counts["radar/frame"] == 7
    assert _partials(out.parent) == []


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_ctrl_c_ends_a_run_as_planned_and_replaces_the_earlier_log(tmp_path, good_log):
    """Run until Ctrl-C is the plan of `launch sim` without exit_after: the log is the recording."""
    src, out, before = good_log
    code, g = _stopped_mid_run(tmp_path, src, out, lambda g: g.proc.send_signal(signal.SIGINT))
    assert code == 0, g.text
    assert _partials(out.parent) == [], g.text
    assert out.read_bytes() != before and 10 <= LogReader(out).counts["radar/frame"] < 100, g.text
    assert "stopped before the run ended as planned" not in g.text, g.text


@pytest.mark.slow  # 5 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_a_silent_node_marks_the_stop_unplanned(tmp_path, monkeypatch):
    """The recorder's own judgement, from heartbeats: a node not heard from for silent_s before
    the launcher stopped the graph had hung."""
    from msgs import NodeStatus
    from nodes.recorder import Recorder
    from nodes.runtime.node import ENV_LAUNCHER_PID, Shutdown

    monkeypatch.setenv(ENV_LAUNCHER_PID, str(os.getppid()))
    rec = Recorder(params={"out": str(tmp_path / "x.mcap"), "silent_s": 3.0}, broker="tcp://127.0.0.1:1")
    monkeypatch.setattr(rec, "launcher_gone", lambda: False)
    now = 10**18
    rec.graph.update(
        {
            "recorder": NodeStatus(header=Header(now, 9), node="recorder", state="running"),
            "solver": NodeStatus(header=Header(now - 10**9, 3), node="solver", state="running"),
            "finished": NodeStatus(header=Header(now - 60 * 10**9, 3), node="finished", state="stopped"),
        }
    )
    rec._signalled_ns = now
    rec._gone_at_signal = set()  # every node still running when the launcher's signal came
    rec._stop = Shutdown(128 + signal.SIGTERM, "received SIGTERM")
    assert rec.unplanned_stop() == ""
    rec.graph["synchronizer"] = NodeStatus(header=Header(now - 5 * 10**9, 3), node="synchronizer", state="running")
    assert rec.unplanned_stop() == "node synchronizer (silent 5.0 s) stopped answering"
    # an error stamped after the launcher's signal is the launcher's own stop, not a failure
    del rec.graph["synchronizer"]
    rec.graph["vio"] = NodeStatus(header=Header(now - 10**6, 4), node="vio", state="error", message="received SIGTERM")
    assert rec.unplanned_stop() == ""
    # ... unless the node had already ended when the launcher stopped the graph: it was stopped first
    rec._gone_at_signal = {"vio"}
    assert rec.unplanned_stop() == "node vio (received SIGTERM) failed"
    rec._gone_at_signal = set()
    rec.graph["solver"] = NodeStatus(header=Header(now - 10**6, 4), node="solver", state="error", message="crashed")
    assert rec.unplanned_stop() == "node solver (crashed) failed"
    rec.writer.discard()


# -- a full disk ----------------------------------------------------------------------------------


class _Disk(io.FileIO):
    """A file on a disk with ``room`` bytes left: the write past it raises ENOSPC."""

    room = 0

    def write(self, b):
        if self.tell() + len(b) > self.room:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return super().write(b)


def _small_disk(monkeypatch, room: int) -> None:
    import msgs.mcap_log as mcap_log

    def fake_open(path, mode="r", *a, **kw):
        if mode != "wb":
            return open(path, mode, *a, **kw)
        disk = _Disk(path, "wb")
        disk.room = room
        return io.BufferedWriter(disk)

    monkeypatch.setattr(mcap_log, "open", fake_open, raising=False)


def test_a_full_disk_while_recording_is_one_line_and_leaves_no_partial(tmp_path, monkeypatch, capfd):
    from nodes.recorder import Recorder

    out = tmp_path / "graph.mcap"
    frames_log(out, n=3)
    before = out.read_bytes()
    src = frames_log(tmp_path / "src" / "big.mcap", n=200)
    _small_disk(monkeypatch, room=40_000)  # room for a few dozen frames
    with local_broker() as ep:
        rec = Recorder(broker=ep, params={"out": str(out), "overwrite": True, "topics": ["radar/frame"]})
        from nodes.player import Player

        player = Player(broker=ep, params={"log": str(src), "rate": 0, "wait_for": ["recorder"]})
        import threading

        codes = []
        t = threading.Thread(target=lambda: codes.append(rec.spin()))
        t.start()
        try:
            player.spin()
            t.join(60)
        finally:
            rec.stop()
            t.join(10)
    assert codes == [2]
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["graph.mcap", "src"]  # no partial filling the disk
    err = capfd.readouterr().err
    lines = [ln for ln in err.splitlines() if "[recorder]" in ln and "No space left on device" in ln]
    assert (
        len(lines) == 1 and "deleted its partial file" in lines[0] and "the earlier graph.mcap is kept" in lines[0]
    ), err
    assert "Traceback" not in err, err


def _export_refused(log, out, capsys, *needles):
    """``export`` of ``log`` to Foxglove over the earlier export ``out`` is refused (exit 2) in one
    line holding every one of ``needles``, and ``out`` keeps its bytes."""
    from twinfocus.cli import main

    assert main(["export", str(log), "--to", "foxglove", str(out), "--overwrite", "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and all(n in err[0] for n in needles), err
    assert out.read_bytes() == b"an earlier export"


def test_a_full_disk_while_exporting_is_one_line_and_keeps_the_old_export(tmp_path, monkeypatch, capsys):
    log = frames_log(tmp_path / "run.mcap", n=200)
    out = tmp_path / "fox.mcap"
    out.write_bytes(b"an earlier export")
    _small_disk(monkeypatch, room=2_000)
    _export_refused(log, out, capsys, "No space left on device", "deleted its partial file")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fox.mcap", "run.mcap"]


def test_an_export_of_a_log_with_no_messages_refuses_and_keeps_the_old_export(tmp_path, capsys):
    empty = tmp_path / "empty.mcap"
    with LogWriter(empty) as w:
        w.add_metadata("calibration", {"note": "no messages"})
    out = tmp_path / "fox.mcap"
    out.write_bytes(b"an earlier export")
    _export_refused(empty, out, capsys, "holds no messages", "left as it was")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.mcap", "fox.mcap"]


def test_a_failed_export_leaves_no_file_behind(tmp_path, capsys):
    """A log whose messages do not convert fails part way: no hidden or partial file is left."""
    from twinfocus.cli import main

    log = frames_log(tmp_path / "run.mcap", n=5)
    out = tmp_path / "fox.mcap"
    import nodes.foxglove_convert as fc

    def boom(self, msg, t):
        raise KeyboardInterrupt

    orig = fc.FoxgloveConverter._pose
    fc.FoxgloveConverter._pose = boom
    try:
        assert main(["export", str(log), "--to", "foxglove", str(out), "-q"]) == 130
    finally:
        fc.FoxgloveConverter._pose = orig
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]
