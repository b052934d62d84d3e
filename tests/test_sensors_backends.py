"""The hardware driver backends (nodes/runtime/sensor_backends.py) against the sensors area's emulators
and fixtures: every registered name resolves, and each adapter streams what the device gave."""

from __future__ import annotations

import socket
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from nodes.runtime.backends import RADAR_BACKENDS, VIO_BACKENDS, PoseSample, RadarSample, load_backend
from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
from twinfocus.sensors.frames import frame_to_virtual_channels

REPO = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize("registry,kind", [(RADAR_BACKENDS, "radar"), (VIO_BACKENDS, "VIO")])
def test_every_registered_backend_resolves_to_a_backend_class(registry, kind):
    for name in registry:
        cls = load_backend(registry, name, kind)
        assert callable(getattr(cls, "samples", None)) and callable(getattr(cls, "close", None)), name
    assert {"mmwcas", "dca1000"} <= set(RADAR_BACKENDS) and {"zed", "emulated"} <= set(VIO_BACKENDS)


def test_live_launch_file_names_registered_backends():
    args = yaml.safe_load((REPO / "launch" / "live.yaml").read_text())["arguments"]
    assert args["radar_backend"]["default"] in RADAR_BACKENDS
    assert args["vio_backend"]["default"] in VIO_BACKENDS


def test_mmwcas_backend_streams_the_capture_as_virtual_channels(tmp_path):
    from twinfocus.sensors.emulators.mmwcas_capture import write_mmwcas_capture
    from twinfocus.sensors.ti_mmwcas import MmwcasConfig

    chirp = Chirp(n_samples=16)
    iq = np.random.default_rng(2).integers(-2000, 2000, size=(5, 12, 16, 16, 2), dtype=np.int16)
    card_ts = 7_000_000_000 + np.arange(5) * 100_000_000
    write_mmwcas_capture(tmp_path / "cap", iq, card_ts, MmwcasConfig(chirp=chirp))
    cls = load_backend(RADAR_BACKENDS, "mmwcas", "radar")
    b = cls({"capture": str(tmp_path / "cap"), "n_samples": 16, "z0_m": 0.5, "time_offset_ns": 1000})
    try:
        got = list(b.samples())
    finally:
        b.close()
    assert b.chirp == chirp and b.channel_offsets_m.shape == (86, 3)
    # The card's garbage first frame (the writer adds one) is dropped; the rest in order, on the
    # shifted clock.
    assert [s.stamp_ns for s in got] == [int(t) + 1000 for t in card_ts]
    assert [s.index for s in got] == [0, 1, 2, 3, 4] and [s.last for s in got] == [False] * 4 + [True]
    assert all(s.scan_id == "cap" for s in got)
    for s, raw in zip(got, iq):
        frame = raw[..., 0] + 1j * raw[..., 1]  # (TX, RX, N) in the radar's TX/RX order
        np.testing.assert_allclose(s.data, frame_to_virtual_channels(frame, chirp, 0.5), rtol=1e-6)
    with pytest.raises(TwinFocusError, match="option 'capture' is required"):
        cls({})


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_dca1000_backend_and_emulated_vio_stream_the_emulated_rig(tmp_path):
    """CLI start -> DCA1000 stream -> 86 virtual channels; the emulated VIO follows the same
    trajectory from the rig's sync file."""
    from twinfocus.motion.trajectory import paper_raster, phase_centres
    from twinfocus.sensors.emulators.radar_scene import monostatic_if
    from twinfocus.sensors.emulators.rig import EMULATED_CFG, EmulatedRadar

    cfg = tmp_path / "radar.cfg"
    cfg.write_text(EMULATED_CFG.replace(" 256 8000 ", " 32 8000 "))
    chirp = Chirp(n_samples=32)
    traj = paper_raster(2, 4, column_pitch_m=0.04, row_pitch_m=0.004, frame_period_s=0.02)
    target = np.array([[0.01, -0.005, 0.6]])
    port = _free_udp_port()
    with EmulatedRadar(traj, target, chirp, host_data_addr=("127.0.0.1", port), sync_file=tmp_path / "sync") as rig:
        radar = load_backend(RADAR_BACKENDS, "dca1000", "radar")(
            {
                "cfg": str(cfg),
                "cli_port": rig.cli_port,
                "board": f"{rig.config_addr[0]}:{rig.config_addr[1]}",
                "host_ip": "127.0.0.1",
                "config_port": 0,
                "data_port": port,
                "z0_m": 0.6,
                "frames_per_scan": 4,
                "idle_timeout_s": 1.0,
            }
        )
        try:
            got = list(radar.samples())
        finally:
            radar.close()
        vio = load_backend(VIO_BACKENDS, "emulated", "VIO")(
            {
                "columns": 2,
                "rows": 4,
                "column_pitch_m": 0.04,
                "row_pitch_m": 0.004,
                "period_s": 0.02,
                "sync_file": str(tmp_path / "sync"),
                "rate_hz": 100,
                "start_timeout_s": 5,
            }
        )
        poses = list(vio.samples())
        vio.close()
    assert radar.chirp == chirp and radar.live and vio.child_frame_id == "radar"
    assert len(got) == 8 and all(isinstance(s, RadarSample) for s in got)
    assert [s.scan_id for s in got] == ["live_000"] * 4 + ["live_001"] * 4
    assert [s.index for s in got] == [0, 1, 2, 3] * 2 and [s.last for s in got] == [False, False, False, True] * 2
    assert np.all(np.diff([s.stamp_ns for s in got]) > 0)
    # Each frame is the monostatic model of the point at the virtual phase centres (quantised to
    # 16 bits; the near-field correction is exact at z0 only): correlation close to 1.
    centres = phase_centres(traj, mmwcas_virtual_array())
    for s, c in zip(got, centres):
        model = monostatic_if(chirp, c, target)
        corr = np.abs(np.vdot(model, s.data)) / (np.linalg.norm(model) * np.linalg.norm(s.data))
        assert corr > 0.99
    # The VIO: the trajectory's poses, on the same clock as the radar frames.
    assert all(isinstance(p, PoseSample) for p in poses)
    stamps = np.array([p.stamp_ns for p in poses])
    assert stamps[0] < got[0].stamp_ns and stamps[-1] > got[-1].stamp_ns - 50_000_000
    at = traj.interpolate(traj.timestamps_ns[0] + (stamps - stamps[0]) - 100_000_000)
    inside = (stamps - stamps[0] >= 100_000_000) & (
        stamps - stamps[0] - 100_000_000 <= traj.timestamps_ns[-1] - traj.timestamps_ns[0]
    )
    np.testing.assert_allclose(np.array([p.position_m for p in poses])[inside], at.position_m[inside], atol=1e-12)


def test_dca1000_backend_refuses_a_layout_without_the_mmwcas_array(tmp_path):
    from twinfocus.sensors.emulators.rig import EMULATED_CFG

    cfg = tmp_path / "radar.cfg"
    cfg.write_text(EMULATED_CFG)
    with pytest.raises(TwinFocusError, match="3 TX x 4 RX.*need 12 x 16"):
        load_backend(RADAR_BACKENDS, "dca1000", "radar")({"cfg": str(cfg), "layout": "cfg"})


def test_zed_backend_streams_the_sdk_poses_as_camera_poses(monkeypatch):
    sys.path.insert(0, str(Path(__file__).parent))
    from test_sensors_zed import _fake_pyzed

    pkg, sl = _fake_pyzed(["OK", "SEARCHING", "OK"])
    monkeypatch.setitem(sys.modules, "pyzed", pkg)
    monkeypatch.setitem(sys.modules, "pyzed.sl", sl)
    b = load_backend(VIO_BACKENDS, "zed", "VIO")({"svo_path": "rec.svo"})
    got = list(b.samples())
    b.close()
    assert not b.live and b.child_frame_id == "camera" and sl.Camera.last.closed
    assert [p.stamp_ns for p in got] == [1_000_000, 2_000_000, 3_000_000]
    assert [p.confidence for p in got] == [0.8, 0.0, 0.8]
    np.testing.assert_allclose([p.position_m[0] for p in got], [0.0, 0.1, 0.2])
    np.testing.assert_allclose(got[2].quat_xyzw, [0, 0, np.sin(0.1), np.cos(0.1)])
