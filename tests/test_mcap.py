"""MCAP logs: round trips, compatibility with the reference reader, crash safety of the recorder."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from test_msgs import assert_same, one_of_each

from msgs import Header, Pose, RadarFrame, decode
from msgs.mcap_log import LogReader, LogWriter, read_messages
from nodes.runtime.node import Node
from nodes.runtime.testing import local_broker, running
from tests.helpers import cli
from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import Chirp

REPO = Path(__file__).resolve().parent.parent


def write_log(path, msgs):
    with LogWriter(path) as w:
        w.add_metadata("calibration", {"translation_m": [0.01, 0.0, -0.02], "note": "bench"})
        for i, m in enumerate(msgs):
            w.write(m.TOPIC, m, log_time_ns=1_000_000 + i)
    return path


def test_round_trip_of_every_type_and_metadata(tmp_path):
    msgs = one_of_each()
    path = write_log(tmp_path / "a.mcap", msgs)
    r = LogReader(path)
    assert r.complete and r.ordered
    assert r.metadata["calibration"] == {"translation_m": [0.01, 0.0, -0.02], "note": "bench"}
    assert r.channels == {m.TOPIC: m.TYPE for m in msgs}
    back = read_messages(path)
    assert [t for t, _ in back] == [m.TOPIC for m in msgs]
    for m, (_, b) in zip(msgs, back):
        assert_same(m, b)
    assert (r.start_ns, r.end_ns) == (1_000_000, 1_000_000 + len(msgs) - 1)


def test_the_reference_mcap_reader_reads_our_files(tmp_path):
    msgs = one_of_each()
    path = write_log(tmp_path / "b.mcap", msgs)
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary.statistics.message_count == len(msgs)
        # indexed, one message per chunk (a crash loses at most one), each chunk with its CRC
        assert len(summary.chunk_indexes) == summary.statistics.chunk_count == len(msgs)
        assert all(ci.message_index_offsets for ci in summary.chunk_indexes)
        assert {c.topic for c in summary.channels.values()} == {m.TOPIC for m in msgs}
        assert all(c.message_encoding == "msgpack" for c in summary.channels.values())
        got = list(reader.iter_messages())
    assert len(got) == len(msgs)
    for (_schema, channel, rec), m in zip(got, msgs):
        assert channel.topic == m.TOPIC and rec.sequence == m.header.seq
        assert_same(m, decode(rec.data))
        # one clock per field: publish time is the log time (wall clock), never a sensor stamp,
        # which may be simulated; the stamp stays in the message's header
        assert rec.publish_time == rec.log_time


@pytest.mark.slow  # 1.5 s x
def test_every_cut_of_a_file_reads_as_a_prefix(tmp_path):
    msgs = [
        Pose(header=Header(i, i, "scene"), position_m=np.array([i, 0.0, 0.0]), quat_xyzw=np.array([0, 0, 0, 1.0]))
        for i in range(40)
    ]
    full = write_log(tmp_path / "c.mcap", msgs).read_bytes()
    cut_path = tmp_path / "cut.mcap"
    seen = set()
    for cut in range(8, len(full), 37):
        cut_path.write_bytes(full[:cut])
        r = LogReader(cut_path)
        back = [m.decode() for m in r.messages()]
        n = len(back)
        assert [b.header.seq for b in back] == list(range(n))  # a prefix, nothing corrupted
        assert not r.complete or cut == len(full)
        seen.add(n)
    assert min(seen) == 0 and max(seen) >= 39


def test_writer_refuses_to_overwrite_and_reader_rejects_non_mcap(tmp_path):
    p = tmp_path / "d.mcap"
    p.write_bytes(b"precious")
    with pytest.raises(TwinFocusError, match="already exists"):
        LogWriter(p)
    assert p.read_bytes() == b"precious"
    with pytest.raises(TwinFocusError, match="not an MCAP file"):
        LogReader(p)
    with pytest.raises(TwinFocusError, match="no such file"):
        LogReader(tmp_path / "missing.mcap")


def test_a_recorder_refused_at_start_leaves_no_file(tmp_path):
    from nodes.recorder import Recorder

    with pytest.raises(TwinFocusError, match="calibration' must be a mapping"):
        Recorder(params={"out": str(tmp_path / "r.mcap"), "calibration": [1, 2]}, broker="tcp://127.0.0.1:1")
    assert list(tmp_path.iterdir()) == []


class _Ticker(Node):
    """Publishes one radar frame every millisecond (frames are small to keep the test quick)."""

    NAME = "ticker"

    def __init__(self, **kw):
        super().__init__(**kw)
        self.pub = self.create_publisher("radar/frame")
        self.sent = 0
        c = Chirp()
        self.template = dict(
            f0_hz=c.f0_hz,
            slope_hz_per_s=c.slope_hz_per_s,
            fs_hz=c.fs_hz,
            channel_offsets_m=np.zeros((4, 3)),
            scan_id="k",
        )

    def on_start(self):
        self.create_timer(0.001, self.tick)

    def tick(self):
        data = np.full((4, 256), self.sent, np.complex64)
        self.pub.publish(RadarFrame(header=Header(stamp_ns=self.sent), data=data, index=self.sent, **self.template))
        self.sent += 1


def _partial_frames(folder, stem):
    """Radar frames readable so far in the one partial log ``STEM.partial-*.mcap`` (0 if none yet)."""
    found = list(Path(folder).glob(f"{stem}.partial-*.mcap"))
    if not found:
        return 0
    return LogReader(found[0]).counts.get("radar/frame", 0)


def test_a_killed_recorder_leaves_a_readable_log(tmp_path):
    out = tmp_path / "killed.mcap"
    with local_broker() as endpoint:
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        rec = subprocess.Popen(
            [
                sys.executable,
                "-c",
                "import sys; from twinfocus.cli import main; sys.exit(main())",
                "record",
                "-o",
                str(out),
                "--broker",
                endpoint,
            ],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        try:
            ticker = _Ticker(broker=endpoint, params={"wait_for": ["recorder"], "ready_timeout_s": 60})
            with running(ticker):
                # Wait on what the recorder has written (not on what was sent: a loaded
                # machine may hold frames in the queues), then kill it mid-stream.
                deadline = time.monotonic() + 120
                while _partial_frames(tmp_path, "killed") < 300:
                    assert time.monotonic() < deadline and rec.poll() is None, "the recorder never wrote 300 frames"
                    time.sleep(0.05)
                rec.send_signal(signal.SIGKILL)  # no chance to write the summary
                rec.wait(10)
        finally:
            if rec.poll() is None:
                rec.kill()
                rec.wait()
    # Written under a name that says partial until the recorder closes it: a killed one leaves
    # that file (stamp and pid in the name) and nothing at the destination.
    assert not out.exists()
    (partial,) = tmp_path.glob(f"killed.partial-*-{rec.pid}.mcap")
    r = LogReader(partial)
    assert not r.complete and not r.damage and "not closed cleanly" in r.condition
    frames = [m.decode() for m in r.messages(["radar/frame"])]
    n = len(frames)
    assert n >= 300, f"only {n} frames survived"
    # Every surviving frame is intact and they are the first n the ticker sent, in order.
    assert [f.index for f in frames] == list(range(n))
    assert all(np.all(f.data == f.index) for f in frames)
    assert r.metadata["radar"]["n_channels"] == 4 and r.metadata["radar"]["f0_hz"] == Chirp().f0_hz


def test_converted_and_recorded_logs_carry_the_same_metadata(tmp_path, capsys):
    """``twinfocus convert --mcap`` writes the recorder's metadata convention: a converted log
    played through the recorder (as launch/live.yaml records) gives back equal ``radar``
    records, and both read back into the capture's chirp, array and extrinsics."""
    from nodes.player import Player
    from nodes.recorder import Recorder
    from twinfocus.motion.trajectory import Poses
    from twinfocus.radar.fmcw import mmwcas_virtual_array
    from twinfocus.radar.scan import Scan
    from twinfocus.sensors.emulators.mmwcas_capture import write_mmwcas_capture
    from twinfocus.sensors.extrinsics import RadarCameraExtrinsics
    from twinfocus.sensors.ti_mmwcas import MmwcasConfig
    from twinfocus.sensors.trajectory_files import write_tum

    chirp = Chirp(f0_hz=77.1e9, n_samples=16)  # not the default: the chirp must come from the file
    iq = np.random.default_rng(1).integers(-2000, 2000, size=(5, 12, 16, 16, 2), dtype=np.int16)
    write_mmwcas_capture(tmp_path / "cap", iq, 5_000_000_000 + np.arange(5) * 100_000_000, MmwcasConfig(chirp=chirp))
    t = 1_700_000_000_000_000_000 + np.arange(11) * 50_000_000
    write_tum(
        tmp_path / "traj.txt",
        Poses(t, np.c_[np.arange(11) * 1e-3, np.zeros(11), np.zeros(11)], np.tile([0, 0, 0, 1.0], (11, 1))),
    )
    extrinsics = {"translation_m": [0.0, 0.05, -0.01], "rotation_xyzw": [0.0, 0.0, 0.0, 1.0]}
    (tmp_path / "ext.yaml").write_text(
        f"translation_m: {extrinsics['translation_m']}\nrotation_xyzw: {extrinsics['rotation_xyzw']}\n"
    )
    converted, recorded = tmp_path / "converted.mcap", tmp_path / "recorded.mcap"
    capture = (tmp_path / "cap", "--trajectory", tmp_path / "traj.txt", "--extrinsics", tmp_path / "ext.yaml")
    options = "--n-samples 16 --f0-hz 77.1e9 --quiet"
    assert cli("convert", *capture, "--out", tmp_path / "scan.npz", "--mcap", converted, options) == 0
    capsys.readouterr()

    with local_broker() as ep:
        # The recorder's parameters as launch/live.yaml sets them.
        rec = Recorder(
            broker=ep, name="recorder", params={"out": str(recorded), "calibration": {"extrinsics": extrinsics}}
        )
        player = Player(broker=ep, params={"log": str(converted), "rate": 0, "wait_for": ["recorder"]})
        with running(rec):
            assert player.spin() == 0
            want = sum(LogReader(converted).counts.values())
            deadline = time.monotonic() + 20
            while (
                sum(n for t, n in rec.writer.counts.items() if t != "graph/status") < want
                and time.monotonic() < deadline
            ):
                time.sleep(0.02)

    logs = {"converted": LogReader(converted), "recorded": LogReader(recorded)}
    n_frames = Scan.load(tmp_path / "scan.npz").n_positions
    recorded = {t: n for t, n in logs["recorded"].counts.items() if t != "graph/status"}  # the nodes' states beside
    assert recorded == logs["converted"].counts and logs["converted"].counts["radar/frame"] == n_frames
    assert logs["converted"].metadata["radar"] == logs["recorded"].metadata["radar"]
    for name, log in logs.items():
        radar, calib = log.metadata["radar"], log.metadata["calibration"]
        assert Chirp(**{k: radar[k] for k in ("f0_hz", "slope_hz_per_s", "fs_hz", "n_samples")}) == chirp, name
        assert radar["n_channels"] == 86 and radar["source_topic"] == "radar/frame", name
        np.testing.assert_array_equal(np.array(radar["channel_offsets_m"]), mmwcas_virtual_array().offsets_m)
        ext = RadarCameraExtrinsics.from_dict(calib["extrinsics"])
        np.testing.assert_array_equal(ext.translation_m, extrinsics["translation_m"])
        np.testing.assert_allclose(ext.rotation, np.eye(3), atol=1e-15)
