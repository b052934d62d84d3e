"""Simulated sources: the radar, the VIO tracker and the motion-stage template of one scene.

All three read the same ``scenario`` option (the fields of :class:`twinfocus.simulation.scenario.Scenario`:
letters, distance, trajectory, columns x rows, SNR, error model, seed, ...) and build everything
through :mod:`twinfocus.simulation.scenario`, whose random streams are one per purpose, so separate
processes agree on the scene and the trajectory, and the graph draws the very scan
``twinfocus simulate`` writes for the same scenario (tests/test_graph_offline.py):

* :class:`SimRadar` simulates the IF samples on the *true* phase centres, a block of frames
  at a time (:func:`twinfocus.simulation.if_simulator.simulate_if`, whose result does not depend on the
  blocking), with thermal noise at the scenario's SNR (noise level from
  :func:`twinfocus.simulation.scenario.scenario_noise_power`, drawn block after block from one stream);
* :class:`SimVio` publishes the scenario's *tracked* trajectory
  (:func:`twinfocus.simulation.scenario.scenario_tracked_poses`: ``error_model`` vio = ZED-like jitter +
  drift, gaussian, drift, hand = drift + jitter + the array's turn, carried in the pose's
  orientation) at every radar frame's stamp, and between them at ``rate_hz`` with the
  tracking error interpolated; the synchronizer's interpolation at a radar stamp is then exact;
* :func:`template_scan` is the reference alone on the motion stage's exact raster, moved by
  the scenario's placement error: the physical twin's capture.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import fields, replace

import numpy as np

from nodes.runtime.backends import PoseSample, RadarSample, check_unknown, option
from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import Poses, phase_centres
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
from twinfocus.simulation.if_simulator import add_thermal_noise, simulate_if
from twinfocus.simulation.scenario import (
    RADAR_NOISE_STREAM,
    Scenario,
    scenario_noise_power,
    scenario_poses,
    scenario_scatterers,
    scenario_stream,
    scenario_tracked_poses,
    simulator_options,
    template_scan,
)

__all__ = ["SIM_T0_NS", "SimRadar", "SimVio", "scenario_from", "template_scan"]

#: First radar stamp of a simulated scan: 10 s, so that poses before it keep positive stamps.
SIM_T0_NS = 10_000_000_000


def scenario_from(options: dict, where: str) -> Scenario:
    spec = option(options, "scenario", {}, dict, where)
    known = {f.name for f in fields(Scenario)}
    unknown = sorted(set(spec) - known)
    if unknown:
        raise TwinFocusError(
            f"{where}: unknown scenario field(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}"
        )
    spec = {k: tuple(v) if isinstance(v, list) else v for k, v in spec.items()}
    return Scenario(**spec)


class SimRadar:
    """Simulated MMWCAS radar over the scenario's true trajectory.

    Options: ``scenario`` (mapping of Scenario fields), ``frame_period_s`` (0.1), ``t0_ns`` (10 s),
    ``scan_id`` ("sim"), ``scans`` (1: how many times to sweep; scan k starts after scan k-1),
    ``block`` (16: frames simulated per call).
    """

    live = False

    def __init__(self, options: dict):
        where = "radar backend 'sim'"
        check_unknown(options, {"scenario", "frame_period_s", "t0_ns", "scan_id", "scans", "block"}, where)
        self.sc = scenario_from(options, where)
        self.frame_period_s = option(options, "frame_period_s", 0.1, float, where)
        self.t0_ns = int(option(options, "t0_ns", SIM_T0_NS, int, where))
        self.clock_start_ns = self.t0_ns  # the first frame's stamp; SimVio paces from the same one
        self.scan_id = str(option(options, "scan_id", "sim", str, where))
        self.scans = int(option(options, "scans", 1, int, where))
        self.block = max(1, int(option(options, "block", 16, int, where)))
        self.chirp = Chirp()
        array = mmwcas_virtual_array()
        self.channel_offsets_m = array.offsets_m
        self.poses = scenario_poses(self.sc, self.frame_period_s, self.t0_ns)
        self.centres = phase_centres(self.poses, array)
        self.points, self.amps = scenario_scatterers(self.sc)
        self.power = None
        if self.sc.snr_db is not None:
            self.power = scenario_noise_power(
                self.centres.shape[0],
                lambda idx: simulate_if(
                    self.points, self.amps, self.centres[idx], self.chirp, **simulator_options(self.sc)
                ),
            )

    def samples(self) -> Iterator[RadarSample]:
        m_total = self.centres.shape[0]
        noise = scenario_stream(self.sc, RADAR_NOISE_STREAM)  # sweep 0 is simulate_scenario's scan
        span_ns = int(self.poses.timestamps_ns[-1] - self.poses.timestamps_ns[0]) + int(
            round(self.frame_period_s * 1e9)
        )
        for s in range(self.scans):
            scan_id = self.scan_id if self.scans == 1 else f"{self.scan_id}_{s:03d}"
            for b0 in range(0, m_total, self.block):
                b1 = min(m_total, b0 + self.block)
                data = simulate_if(
                    self.points, self.amps, self.centres[b0:b1], self.chirp, **simulator_options(self.sc)
                )
                if self.sc.snr_db is not None:
                    data = add_thermal_noise(data, self.sc.snr_db, noise, signal_power=self.power)
                for i, m in enumerate(range(b0, b1)):
                    yield RadarSample(
                        stamp_ns=int(self.poses.timestamps_ns[m]) + s * span_ns,
                        data=data[i],
                        scan_id=scan_id,
                        index=m,
                        last=m == m_total - 1,
                        positions_true_m=self.centres[m],
                    )

    def close(self) -> None:
        pass


class SimVio:
    """Simulated tracker: the scenario's tracked trajectory (truth + its tracking error).

    Options: ``scenario``, ``frame_period_s``, ``t0_ns``, ``scans`` (as :class:`SimRadar`),
    ``rate_hz`` (30: poses between radar frames), ``error_model`` (overrides the scenario's:
    "vio" | "gaussian" | "drift" | "hand" | "none"), ``error_sigma_m`` (gaussian/drift/hand sigma per axis;
    default the scenario's), ``margin_s`` (0.5: poses start this long before the first radar
    frame and end after the last).

    At each radar frame's stamp the pose is :func:`twinfocus.simulation.scenario.scenario_tracked_poses`'
    tracked one, whose phase centres are :func:`twinfocus.simulation.scenario.scenario_positions`' (exactly
    without a rotation error; within 0.4 um with the hand's turn); between them the tracked poses
    are interpolated (positions linearly, orientations by slerp).
    """

    live = False
    frame_id = "scene"
    child_frame_id = "radar"

    def __init__(self, options: dict):
        where = "VIO backend 'sim'"
        check_unknown(
            options,
            {"scenario", "frame_period_s", "t0_ns", "scans", "rate_hz", "error_model", "error_sigma_m", "margin_s"},
            where,
        )
        sc = scenario_from(options, where)
        period = option(options, "frame_period_s", 0.1, float, where)
        t0 = int(option(options, "t0_ns", SIM_T0_NS, int, where))
        scans = int(option(options, "scans", 1, int, where))
        rate = option(options, "rate_hz", 30.0, float, where)
        model = option(options, "error_model", sc.error_model, str, where)
        sigma = option(options, "error_sigma_m", list(sc.error_sigma_m), list, where)
        margin = option(options, "margin_s", 0.5, float, where)
        if not rate > 0:
            raise TwinFocusError(f"{where}: rate_hz must be positive, got {rate}")
        if model == "none":
            sc = replace(sc, error_model="gaussian", error_sigma_m=(0.0, 0.0, 0.0))
        elif model in ("vio", "gaussian", "drift", "hand"):
            sc = replace(sc, error_model=model, error_sigma_m=tuple(float(v) for v in sigma))
        else:
            raise TwinFocusError(f"{where}: unknown error_model {model!r}; use vio, gaussian, drift, hand or none")
        self.sc = sc
        # paced on the radar's clock (its first frame's stamp starts it, nodes/runtime/driver.py): a pose
        # goes out when the radar frame of the same stamp does, as from a live tracker; the
        # margin's poses before it go out at once
        self.clock_start_ns = t0
        # the tracked pose per radar frame: the translation error, and the hand's turn of the array
        radar, tracked_poses = scenario_tracked_poses(sc, period, t0)
        span_ns = int(radar.timestamps_ns[-1] - radar.timestamps_ns[0]) + int(round(period * 1e9))
        start = int(radar.timestamps_ns[0] - margin * 1e9)
        end = int(radar.timestamps_ns[-1] + (scans - 1) * span_ns + margin * 1e9)
        step = 1e9 / rate
        grid = start + np.round(np.arange(0, int((end - start) / step) + 1) * step).astype(np.int64)
        frames = (radar.timestamps_ns[None, :] + span_ns * np.arange(scans)[:, None]).ravel()
        ts = np.union1d(grid, frames).astype(np.int64)
        # Later sweeps repeat the first one's path (the driver's scans are back to back).
        t_first = int(radar.timestamps_ns[0])
        local = np.where(ts < t_first + span_ns, ts, t_first + (ts - t_first) % span_ns).astype(np.int64)
        order = np.argsort(local, kind="stable")
        at_tracked = tracked_poses.interpolate(local[order])  # interpolate() wants sorted times
        position = np.empty((ts.size, 3))
        quat = np.empty((ts.size, 4))
        position[order], quat[order] = at_tracked.position_m, at_tracked.quat_xyzw
        self.poses = Poses(ts, position, quat)

    def samples(self) -> Iterator[PoseSample]:
        p = self.poses
        for i in range(len(p)):
            yield PoseSample(int(p.timestamps_ns[i]), p.position_m[i], p.quat_xyzw[i], 1.0)

    def close(self) -> None:
        pass
