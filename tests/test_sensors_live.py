"""The emulated live rig end to end without the node graph: CLI start -> DCA1000 stream of a
simulated point target + emulated VIO poses -> scan -> the target focuses where it is."""

from __future__ import annotations

import numpy as np

from twinfocus.motion.trajectory import paper_raster
from twinfocus.radar.fmcw import C_M_PER_S, Chirp
from twinfocus.sensors.capture_to_scan import scan_from_frames
from twinfocus.sensors.dca1000 import Dca1000
from twinfocus.sensors.emulators.rig import EMULATED_CFG, EmulatedRadar, EmulatedVio
from twinfocus.sensors.ti_cli import TiRadarCli
from twinfocus.sensors.zed import poses_from_samples


def _coherence(scan, point):
    """|matched filter at point| / sum |data|: 1 for a perfectly focused single scatterer."""
    r = np.linalg.norm(scan.positions - point, axis=-1)  # (M, K)
    ref = np.exp(1j * 2 * np.pi * scan.chirp.frequencies_hz * 2 * r[..., None] / C_M_PER_S)
    return float(np.abs(np.sum(scan.data * np.conj(ref))) / np.sum(np.abs(scan.data)))


def test_live_emulation_focuses_a_point_target(tmp_path):
    chirp = Chirp(n_samples=64)
    traj = paper_raster(2, 20, column_pitch_m=0.04, row_pitch_m=0.004, frame_period_s=0.02)
    target = np.array([0.01, -0.005, 0.6])
    with Dca1000(board_addr=("127.0.0.1", 9), host_ip="127.0.0.1", config_port=0, data_port=0) as host:
        with EmulatedRadar(
            traj, target[None], chirp, host_data_addr=host.data_addr, sync_file=tmp_path / "sync"
        ) as rig:
            host.board_addr = rig.config_addr
            host.setup()
            host.start_record()
            with TiRadarCli(rig.cli_port) as cli:
                cli.configure(EMULATED_CFG)
            frames = list(host.frames(rig.layout, max_frames=len(traj), idle_timeout_s=2.0))
            samples = list(EmulatedVio(traj, sync_file=tmp_path / "sync", rate_hz=200).poses(paced=False, timeout_s=1))
    poses = poses_from_samples(samples)
    scan, _, report = scan_from_frames(frames, chirp, poses, 0.6, align="none", scene_frame="world")
    assert report.n_used == len(traj) == 40
    focus = _coherence(scan, target)
    assert focus > 0.9
    # The brightest point of a small grid around the target is the target.
    grid = [target + [dx, dy, 0.0] for dx in (-0.004, 0.0, 0.004) for dy in (-0.008, 0.0, 0.008)]
    assert int(np.argmax([_coherence(scan, p) for p in grid])) == 4
    # Control: poses two frames late (a clock error) defocus it.
    late, _, _ = scan_from_frames(
        frames, chirp, poses, 0.6, time_offset_ns=40_000_000, align="none", scene_frame="world"
    )
    assert _coherence(late, target) < 0.7 * focus
