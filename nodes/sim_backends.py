"""Simulated sources: the radar, the VIO tracker and the motion-stage template of one scene.

All three read the same ``scenario`` option (the fields of :class:`twinfocus.scenario.Scenario`:
letters, distance, trajectory, columns x rows, SNR, seed, ...) and derive every random stream
from its seed, so separate processes agree on the scene and the true trajectory:

* :class:`SimRadar` simulates the IF samples on the *true* phase centres, a block of frames
  at a time (:func:`twinfocus.simulate.simulate_if`, whose result does not depend on the
  blocking), with thermal noise at the scenario's SNR;
* :class:`SimVio` publishes the true trajectory at ``rate_hz`` plus a tracking error
  (``error_model``: ``vio`` = ZED-like jitter + drift, :func:`twinfocus.motion.vio_errors`;
  ``gaussian`` = the paper's per-pose jitter; ``drift``; ``none``);
* :func:`template_scan` is the reference alone on the motion stage's exact raster, moved by
  the scenario's placement error: the physical twin's capture.
"""
from __future__ import annotations

from dataclasses import fields, replace
from typing import Iterator

import numpy as np

from nodes.backends import PoseSample, RadarSample, check_unknown, option
from twinfocus.errors import TwinFocusError
from twinfocus.motion import drift_errors, gaussian_errors, vio_errors
from twinfocus.radar import Chirp, mmwcas_virtual_array
from twinfocus.scan import Scan
from twinfocus.scenario import Scenario
from twinfocus.scene import scatterer_spacing_m
from twinfocus.simulate import add_thermal_noise, simulate_if
from twinfocus.trajectory import Poses, handheld_zigzag, paper_raster, phase_centres


#: First radar stamp of a simulated scan: 10 s, so that poses before it keep positive stamps.
SIM_T0_NS = 10_000_000_000


def scenario_from(options: dict, where: str) -> Scenario:
    spec = option(options, "scenario", {}, dict, where)
    known = {f.name for f in fields(Scenario)}
    unknown = sorted(set(spec) - known)
    if unknown:
        raise TwinFocusError(f"{where}: unknown scenario field(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    spec = {k: tuple(v) if isinstance(v, list) else v for k, v in spec.items()}
    return Scenario(**spec)


def _stream(sc: Scenario, purpose: int) -> np.random.Generator:
    """Independent random stream ``purpose`` of the scenario's seed (1 trajectory, 2 scene,
    3 radar noise, 4 tracking error, 5 template noise)."""
    return np.random.default_rng([int(sc.seed), purpose])


def true_poses(sc: Scenario, frame_period_s: float = 0.1, t0_ns: int = 0) -> Poses:
    """The true radar poses, one per radar frame."""
    if sc.trajectory == "raster":
        return paper_raster(sc.n_columns, sc.n_rows, frame_period_s=frame_period_s, t0_ns=t0_ns)
    if sc.trajectory == "zigzag":
        return handheld_zigzag(sc.n_columns, sc.n_rows, frame_period_s=frame_period_s, rng=_stream(sc, 1), t0_ns=t0_ns)
    raise TwinFocusError(f"unknown trajectory {sc.trajectory!r}; use 'raster' or 'zigzag'")


def scene_points(sc: Scenario, reference_only: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Scatterers (P, 3) and complex amplitudes (P,) of the scene (or of the reference alone,
    moved by the template placement error)."""
    scene = sc.scene()
    seed = int(_stream(sc, 2).integers(0, 2**31))
    if reference_only:
        scene = scene.select("reference", occluders=False)
        ref = scene.objects[0]
        scene.objects[0] = replace(ref, centre_m=np.asarray(ref.centre_m) + np.asarray(sc.template_offset_m, float))
    spacing = sc.spacing_m or scatterer_spacing_m(sc.distance_m)
    return scene.scatterers(spacing, seed, speckle=sc.speckle)


def _sim_kw(sc: Scenario) -> dict:
    return {} if sc.range_step_m is None else {"range_step_m": sc.range_step_m}


def template_scan(sc: Scenario, chirp: Chirp | None = None) -> Scan:
    """The reference alone on the motion stage's raster (exact positions): physical-twin capture."""
    chirp = chirp or Chirp()
    stage = phase_centres(paper_raster(sc.n_columns, sc.n_rows), mmwcas_virtual_array())
    pts, amps = scene_points(sc, reference_only=True)
    data = simulate_if(pts, amps, stage, chirp, **_sim_kw(sc))
    if sc.snr_db is not None:
        data = add_thermal_noise(data, sc.snr_db, _stream(sc, 5))
    return Scan(data, stage, chirp, positions_true=stage)


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
        self.scan_id = str(option(options, "scan_id", "sim", str, where))
        self.scans = int(option(options, "scans", 1, int, where))
        self.block = max(1, int(option(options, "block", 16, int, where)))
        self.chirp = Chirp()
        array = mmwcas_virtual_array()
        self.channel_offsets_m = array.offsets_m
        self.poses = true_poses(self.sc, self.frame_period_s, self.t0_ns)
        self.centres = phase_centres(self.poses, array)
        self.points, self.amps = scene_points(self.sc)
        self.noise = _stream(self.sc, 3)

    def samples(self) -> Iterator[RadarSample]:
        m_total = self.centres.shape[0]
        span_ns = int(self.poses.timestamps_ns[-1] - self.poses.timestamps_ns[0]) + int(round(self.frame_period_s * 1e9))
        for s in range(self.scans):
            scan_id = self.scan_id if self.scans == 1 else f"{self.scan_id}_{s:03d}"
            for b0 in range(0, m_total, self.block):
                b1 = min(m_total, b0 + self.block)
                data = simulate_if(self.points, self.amps, self.centres[b0:b1], self.chirp, **_sim_kw(self.sc))
                if self.sc.snr_db is not None:
                    data = add_thermal_noise(data, self.sc.snr_db, self.noise)
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
    """Simulated tracker: the scenario's true trajectory at ``rate_hz`` plus a tracking error.

    Options: ``scenario``, ``frame_period_s``, ``t0_ns``, ``scans`` (as :class:`SimRadar`),
    ``rate_hz`` (30), ``error_model`` ("vio" | "gaussian" | "drift" | "none"; default "vio"),
    ``error_sigma_m`` (gaussian/drift sigma per axis; default the scenario's), ``margin_s``
    (0.5: poses start this long before the first radar frame and end after the last).
    """

    live = False
    frame_id = "scene"
    child_frame_id = "radar"

    def __init__(self, options: dict):
        where = "VIO backend 'sim'"
        check_unknown(options, {"scenario", "frame_period_s", "t0_ns", "scans", "rate_hz", "error_model", "error_sigma_m", "margin_s"}, where)
        self.sc = scenario_from(options, where)
        period = option(options, "frame_period_s", 0.1, float, where)
        t0 = int(option(options, "t0_ns", SIM_T0_NS, int, where))
        scans = int(option(options, "scans", 1, int, where))
        rate = option(options, "rate_hz", 30.0, float, where)
        model = option(options, "error_model", "vio", str, where)
        sigma = option(options, "error_sigma_m", list(self.sc.error_sigma_m), list, where)
        margin = option(options, "margin_s", 0.5, float, where)
        if not rate > 0:
            raise TwinFocusError(f"{where}: rate_hz must be positive, got {rate}")
        radar = true_poses(self.sc, period, t0)
        span_ns = int(radar.timestamps_ns[-1] - radar.timestamps_ns[0]) + int(round(period * 1e9))
        start = int(radar.timestamps_ns[0] - margin * 1e9)
        end = int(radar.timestamps_ns[-1] + (scans - 1) * span_ns + margin * 1e9)
        ts = start + np.round(np.arange(0.0, (end - start) / 1e9 + 1e-9, 1.0 / rate) * 1e9).astype(np.int64)
        # Later sweeps repeat the first one's path (the driver's scans are back to back).
        t_first = int(radar.timestamps_ns[0])
        local = np.where(ts < t_first + span_ns, ts, t_first + (ts - t_first) % span_ns).astype(np.int64)
        order = np.argsort(local, kind="stable")
        at = radar.interpolate(local[order])  # interpolate() wants sorted times
        position = np.empty((ts.size, 3))
        quat = np.empty((ts.size, 4))
        position[order], quat[order] = at.position_m, at.quat_xyzw
        rng = _stream(self.sc, 4)
        if model == "vio":
            err = vio_errors(ts, rng=rng)
        elif model == "gaussian":
            err = gaussian_errors(ts.size, sigma, rng)
        elif model == "drift":
            err = drift_errors(ts, sigma, rng=rng)
        elif model == "none":
            err = np.zeros((ts.size, 3))
        else:
            raise TwinFocusError(f"{where}: unknown error_model {model!r}; use vio, gaussian, drift or none")
        self.poses = Poses(ts, position + err, quat)

    def samples(self) -> Iterator[PoseSample]:
        p = self.poses
        for i in range(len(p)):
            yield PoseSample(int(p.timestamps_ns[i]), p.position_m[i], p.quat_xyzw[i], 1.0)

    def close(self) -> None:
        pass
