"""The mmWave SDK CLI: .cfg parsing, and configuring an emulated radar on a pseudo-terminal
that answers, and sometimes refuses, commands; plus the emulated rig end to end."""

from __future__ import annotations

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import Chirp
from twinfocus.sensors.emulators.fake_radar_cli import FakeRadarCli
from twinfocus.sensors.ti_cli import CliCommandError, RadarCliConfig, TiRadarCli, read_cfg

CFG = """% xWR1843, 3 TX TDM-MIMO, raw capture
sensorStop
flushCfg
dfeDataOutputMode 1
channelCfg 15 5 0
adcCfg 2 1
adcbufCfg -1 0 1 1 1
lowPower 0 0
profileCfg 0 77 7 6 60 0 0 60 1 128 5000 0 0 30
chirpCfg 0 0 0 0 0 0 0 4
chirpCfg 1 1 0 0 0 0 0 1
frameCfg 0 1 8 0 50 1 0
lvdsStreamCfg -1 0 1 0

sensorStart
"""


# Emulators and clients must stop every thread they start (conftest.py).
pytestmark = pytest.mark.usefixtures("no_stray_threads")


def test_cfg_gives_chirp_and_raw_layout():
    cfg = RadarCliConfig.from_cfg(CFG)
    chirp = cfg.chirp()
    # first ADC sample: 77 GHz + 60 MHz/us * 6 us; 5000 ksps; 128 samples
    assert chirp == Chirp(f0_hz=77e9 + 60e12 * 6e-6, slope_hz_per_s=60e12, fs_hz=5e6, n_samples=128)
    lay = cfg.raw_layout()
    # TX mask 5 enables TX0 and TX2; chirp 0 fires TX2 (2nd enabled), chirp 1 fires TX0 (1st)
    assert (lay.n_rx, lay.n_tx, lay.tx_of_chirp, lay.n_loops) == (4, 2, (1, 0), 8)
    assert lay.frame_bytes == 8 * 2 * 4 * 128 * 4
    assert cfg.frame_period_s == 0.05
    assert read_cfg(CFG)[0] == (2, "sensorStop")


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda s: s.replace("frameCfg 0 1 8 0 50 1 0\n", ""), "no frameCfg"),
        (lambda s: s.replace("profileCfg 0 77 7 6", "profileCfg 0 77 7"), r"line 9: profileCfg takes 14 values"),
        (lambda s: s.replace("channelCfg 15 5 0", "channelCfg 15 x 0"), "line 5: channelCfg values must be numbers"),
        (lambda s: s.replace("adcCfg 2 1", "adcCfg 1 1"), "16-bit"),
        (lambda s: s.replace("0 0 0 0 0 0 0 4", "0 0 0 0 0 0 0 5"), "exactly one TX per chirp"),
        (lambda s: s.replace("frameCfg 0 1", "frameCfg 0 2"), "no chirpCfg covers it"),
        (lambda s: s.replace("lvdsStreamCfg -1 0 1 0", "lvdsStreamCfg -1 1 1 0"), r"HSI headers \(0x0ADC\)"),
        (lambda s: s.replace("lvdsStreamCfg -1 0 1 0", "lvdsStreamCfg -1 0 4 0"), "dataFmt is 4"),
        (lambda s: s.replace("adcbufCfg -1 0 1 1 1", "adcbufCfg -1 0 1 0 1"), "ChanInterleave 0"),
        (lambda s: s.replace("adcbufCfg -1 0 1 1 1", "adcbufCfg -1 0 0 1 1"), "SampleSwap 0"),
        (lambda s: s.replace("adcbufCfg -1 0 1 1 1", "adcbufCfg -1 1 1 1 1"), "real"),
    ],
)
def test_bad_cfg_is_refused_with_line(edit, message):
    with pytest.raises(TwinFocusError, match=message):
        RadarCliConfig.from_cfg(edit(CFG)).raw_layout()


def test_configure_over_pty_with_a_transient_refusal():
    started = []
    with (
        FakeRadarCli(refuse={"profileCfg": 1}, on_start=started.append) as fake,
        TiRadarCli(fake.port, timeout_s=2) as cli,
    ):
        cfg = cli.configure(CFG, retries=1)
        assert fake.running and len(started) == 1
        assert started[0].raw_layout() == cfg.raw_layout()
        assert fake.received.count("profileCfg 0 77 7 6 60 0 0 60 1 128 5000 0 0 30") == 2
        assert cli.send("sensorStop") == []
        assert not fake.running
        assert cli.send("sensorStop") == ["Ignored: Sensor is already stopped"]


def test_refusals_raise_with_the_reply():
    with FakeRadarCli(refuse={"frameCfg": 5}) as fake, TiRadarCli(fake.port, timeout_s=2) as cli:
        with pytest.raises(
            CliCommandError, match=r"line 12: radar refused 'frameCfg 0 1 8 0 50 1 0': Error -1 \(after 2 attempt"
        ):
            cli.configure(CFG, retries=1)
        assert not fake.running
        with pytest.raises(CliCommandError, match="not recognized as a CLI command") as info:
            cli.send("bogusCmd 1 2")
        assert info.value.reply == ["'bogusCmd' is not recognized as a CLI command"]
        with pytest.raises(CliCommandError, match="Invalid usage"):
            cli.send("chirpCfg 0 0 0")
        cli.send("flushCfg")
        with pytest.raises(CliCommandError, match="configuration incomplete"):
            cli.send("sensorStart")


def test_silent_port_times_out_clearly():
    # pyserial's loop:// echoes what is written: a port that echoes but never says Done.
    with TiRadarCli("loop://", timeout_s=0.2) as cli:
        with pytest.raises(CliCommandError, match="did not answer 'sensorStop' with Done"):
            cli.send("sensorStop")
    with pytest.raises(TwinFocusError, match="cannot open the radar CLI port"):
        TiRadarCli("/dev/does-not-exist")


def test_emulated_rig_streams_the_simulated_scene_on_schedule(tmp_path):
    """CLI sensorStart -> board streams MMWCAS frames of the scene; the VIO shares the clock."""
    from twinfocus.motion.trajectory import paper_raster
    from twinfocus.sensors.dca1000 import Dca1000
    from twinfocus.sensors.emulators.radar_scene import quantize_iq, simulate_mimo_frames
    from twinfocus.sensors.emulators.rig import EMULATED_CFG, EmulatedRadar, EmulatedVio, demo_scatterers

    chirp = Chirp(n_samples=32)
    traj = paper_raster(1, 4, frame_period_s=0.05)
    pts = demo_scatterers()[:4]
    with Dca1000(board_addr=("127.0.0.1", 9), host_ip="127.0.0.1", config_port=0, data_port=0) as host:
        with EmulatedRadar(traj, pts, chirp, host_data_addr=host.data_addr, sync_file=tmp_path / "sync") as rig:
            host.board_addr = rig.config_addr
            host.setup()
            host.start_record()
            with TiRadarCli(rig.cli_port) as cli:
                cli.configure(EMULATED_CFG)
            frames = list(host.frames(rig.layout, max_frames=4, idle_timeout_s=2.0))
            vio = EmulatedVio(traj, sync_file=tmp_path / "sync", rate_hz=100)
            poses = list(vio.poses(paced=False, timeout_s=1.0))
    truth = simulate_mimo_frames(chirp, traj, pts)
    iq = quantize_iq(truth, full_scale=float(len(pts)), headroom=0.9)
    for k, fr in enumerate(frames):
        assert fr.flags.usable
        np.testing.assert_array_equal(fr.data.real, iq[k, ..., 0])
        np.testing.assert_array_equal(fr.data.imag, iq[k, ..., 1])
    # frame k leaves at start + k * 50 ms; the pose reported at that time is pose k
    start = vio.start_ns
    for k, fr in enumerate(frames):
        assert abs(fr.stamp_ns - (start + k * 50_000_000)) < 20_000_000
    p_at = {p.stamp_ns - start: p.position_m for p in poses}
    for k in range(4):
        np.testing.assert_allclose(p_at[k * 50_000_000], traj.position_m[k], atol=1e-12)
