"""An emulated handheld rig: radar CLI + capture board streaming a simulated scene, and a VIO.

:class:`EmulatedRadar` couples a :class:`FakeRadarCli` and a :class:`FakeDca1000`: when the
radar driver sends ``sensorStart`` over the CLI, the board streams MMWCAS-shaped frames
(12 TX x 16 RX x N, one per radar position of ``trajectory``) simulated from point scatterers,
on the trajectory's schedule, and writes the wall-clock time of frame 0 to ``sync_file``.
:class:`EmulatedVio` reads that time and reports the same trajectory's poses on the wall clock
(optionally with tracking noise), so that a live graph on loopback sees a consistent scan.

The real MMWCAS streams through its DSP board, not a DCA1000; carrying its 12 x 16 frames over
the DCA1000 protocol is an emulation convenience (the layout is a
:class:`~twinfocus.sensors.dca1000.RawFrameLayout` like any other).
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.io.atomic import write_text_atomic
from twinfocus.motion.trajectory import Poses, matrix_to_quat, paper_raster
from twinfocus.radar.fmcw import Chirp
from twinfocus.sensors.dca1000 import RawFrameLayout
from twinfocus.sensors.emulators.fake_dca1000 import FakeDca1000, LinkFaults
from twinfocus.sensors.emulators.fake_radar_cli import FakeRadarCli
from twinfocus.sensors.emulators.radar_scene import quantize_iq, simulate_mimo_frames
from twinfocus.sensors.extrinsics import RadarCameraExtrinsics
from twinfocus.sensors.zed import PoseSample

#: What the emulated board streams: MMWCAS-shaped frames, chirp c = TX c, 16 RX, 256 samples.
MMWCAS_STREAM_LAYOUT = RawFrameLayout(256, 16, tuple(range(12)), 1, 12)

#: A cfg for the emulated radar's CLI. The CLI checks it and starts the stream with it, but the
#: board keeps streaming :data:`MMWCAS_STREAM_LAYOUT` (a single-chip cfg cannot describe 12 x 16).
EMULATED_CFG = """% emulated TI radar (TwinFocus), 256 complex 16-bit samples, 3 TX TDM
sensorStop
flushCfg
dfeDataOutputMode 1
channelCfg 15 7 0
adcCfg 2 1
adcbufCfg -1 0 1 1 1
lowPower 0 0
profileCfg 0 76 100 5 40 0 0 120 1 256 8000 0 0 30
chirpCfg 0 0 0 0 0 0 0 1
chirpCfg 1 1 0 0 0 0 0 2
chirpCfg 2 2 0 0 0 0 0 4
frameCfg 0 2 1 0 100 1 0
lvdsStreamCfg -1 0 1 0
sensorStart
"""


#: The first rows of :func:`demo_scatterers` are the reference 'T'; the rest the target 'L'.
N_REFERENCE_SCATTERERS = 11


def demo_scatterers(z_m: float = 0.6) -> np.ndarray:
    """A small 'T' of point scatterers (reference) and an 'L' (target) on the plane z, float64 (J, 3)."""
    s = 0.012
    t_bar = [(-0.07 + i * s, 0.03, z_m) for i in range(6)]
    t_stem = [(-0.04, 0.03 - (i + 1) * s, z_m) for i in range(5)]
    l_stem = [(0.05, 0.03 - i * s, z_m) for i in range(6)]
    l_foot = [(0.05 + (i + 1) * s, 0.03 - 5 * s, z_m) for i in range(3)]
    return np.array(t_bar + t_stem + l_stem + l_foot, dtype=np.float64)


def default_sync_file(config_port: int) -> Path:
    return Path(tempfile.gettempdir()) / f"twinfocus_emulated_radar_{int(config_port)}.start_ns"


class EmulatedRadar:
    """Fake radar CLI + fake DCA1000 streaming a simulated scene along ``trajectory``.

    trajectory : radar body poses in the scene frame, one per frame (default a small raster:
    3 columns x 40 rows, 2 mm rows, 0.05 s frames); scatterers_m : (J, 3) (default
    :func:`demo_scatterers`); host_data_addr : where the host's data socket listens;
    config_port : the emulated board's config port (0: free port); sync_file : where the
    wall-clock start of frame 0 is written (default in the temp folder, keyed by the port).
    loss / reorder : random packet faults.
    """

    def __init__(
        self,
        trajectory: Poses | None = None,
        scatterers_m: np.ndarray | None = None,
        chirp: Chirp | None = None,
        host_data_addr: tuple[str, int] = ("127.0.0.1", 4098),
        config_port: int = 0,
        sync_file: str | os.PathLike | None = None,
        loss: float = 0.0,
        reorder: float = 0.0,
        frame_period_s: float | None = None,
    ):
        self.trajectory = trajectory or paper_raster(3, 40, 0.082, 0.002, frame_period_s=0.05)
        self.scatterers_m = demo_scatterers() if scatterers_m is None else np.asarray(scatterers_m, np.float64)
        self.chirp = chirp or Chirp()
        ts = self.trajectory.timestamps_ns
        period = frame_period_s or (float(np.median(np.diff(ts))) * 1e-9 if len(ts) > 1 else 0.1)
        if len(ts) > 1 and np.ptp(np.diff(ts)) > 0.01 * np.median(np.diff(ts)):
            raise TwinFocusError(
                "the emulated radar streams at a fixed frame period: give a uniformly timed trajectory"
            )
        self.layout = RawFrameLayout(self.chirp.n_samples, 16, tuple(range(12)), 1, 12)
        self._full_scale = float(self.scatterers_m.shape[0])
        self.board = FakeDca1000(
            self.layout,
            frame_source=self._frame,
            host_data_addr=host_data_addr,
            frame_period_s=period,
            n_frames=len(self.trajectory),
            faults=LinkFaults(loss=loss, reorder=reorder),
            sensor_running=False,
            config_port=config_port,
            on_stream_start=self._started,
        )
        self.sync_file = Path(sync_file) if sync_file else default_sync_file(self.board.config_addr[1])
        self.sync_file.unlink(missing_ok=True)
        self.cli = FakeRadarCli(on_start=lambda cfg: self.board.sensor_start(None), on_stop=self.board.sensor_stop)

    @property
    def cli_port(self) -> str:
        return self.cli.port

    @property
    def config_addr(self) -> tuple[str, int]:
        return self.board.config_addr

    def _frame(self, k: int, layout: RawFrameLayout) -> bytes:
        data = simulate_mimo_frames(self.chirp, self.trajectory.select([k]), self.scatterers_m)[0]
        iq = quantize_iq(data, full_scale=self._full_scale, headroom=0.9)
        return layout.encode(iq[None])

    def _started(self, start_ns: int) -> None:
        write_text_atomic(self.sync_file, str(int(start_ns)))

    def __enter__(self) -> EmulatedRadar:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.cli.close()
        self.board.close()
        self.sync_file.unlink(missing_ok=True)


class EmulatedVio:
    """The trajectory's poses on the wall clock, as a VIO would report them.

    trajectory : radar body poses (the same as the :class:`EmulatedRadar`'s); start_ns : wall
    time of the trajectory's first pose, or ``sync_file`` to read it from (waits for it);
    rate_hz : pose rate (60, the ZED 2i's); noise_sigma_m : tracking error per axis (x, y, z);
    confidence : reported confidence; extrinsics : report the *camera* pose of a rig with this
    ``T_camera_radar`` instead of the radar's; margin_s : poses also this long before the first
    and after the last frame (the hand holds still), so every frame lies inside the pose stream.
    """

    def __init__(
        self,
        trajectory: Poses,
        start_ns: int | None = None,
        sync_file: str | os.PathLike | None = None,
        rate_hz: float = 60.0,
        noise_sigma_m=(0.0, 0.0, 0.0),
        confidence: float = 1.0,
        extrinsics: RadarCameraExtrinsics | None = None,
        rng: int | None = 0,
        margin_s: float = 0.1,
    ):
        if start_ns is None and sync_file is None:
            raise TwinFocusError("EmulatedVio needs start_ns or a sync_file to read it from")
        self.trajectory = trajectory
        self.start_ns = start_ns
        self.sync_file = None if sync_file is None else Path(sync_file)
        self.rate_hz = float(rate_hz)
        self.noise = np.broadcast_to(np.asarray(noise_sigma_m, np.float64), (3,))
        self.confidence = float(confidence)
        self.inverse = None if extrinsics is None else extrinsics.inverse()
        self._rng = np.random.default_rng(rng)
        self.margin_ns = int(round(float(margin_s) * 1e9))

    def wait_for_start(self, timeout_s: float | None = None, stop=None) -> int | None:
        """The start time, waiting for the sync file when needed (None on timeout / stop)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while self.start_ns is None:
            if self.sync_file is not None and self.sync_file.is_file():
                try:
                    self.start_ns = int(self.sync_file.read_text().strip())
                    break
                except ValueError:
                    pass
            if (deadline is not None and time.monotonic() > deadline) or (stop is not None and stop.is_set()):
                return None
            time.sleep(0.01)
        return self.start_ns

    def poses(self, stop=None, timeout_s: float | None = None, paced: bool = True) -> Iterator[PoseSample]:
        """Yield :class:`PoseSample` at ``rate_hz`` over the trajectory's span (plus the margins),
        on the wall clock (``paced=False``: at once, with the same stamps)."""
        start = self.wait_for_start(timeout_s, stop)
        if start is None:
            return
        ts = self.trajectory.timestamps_ns
        rel = np.arange(
            -self.margin_ns, int(ts[-1] - ts[0]) + self.margin_ns + 1, int(1e9 / self.rate_hz), dtype=np.int64
        )
        at = self.trajectory.interpolate(ts[0] + rel)
        pos = at.position_m.copy()
        rot = at.rotation_matrices()
        if self.inverse is not None:
            pos = pos + np.einsum("mij,j->mi", rot, self.inverse.translation_m)
            rot = np.einsum("mij,jk->mik", rot, self.inverse.rotation)
        pos = pos + self._rng.normal(size=pos.shape) * self.noise
        quat = matrix_to_quat(rot)
        for i in range(len(rel)):
            stamp = int(start + rel[i])
            if paced:
                delay = (stamp - time.time_ns()) * 1e-9
                if delay > 0:
                    if stop is not None:
                        if stop.wait(delay):
                            return
                    else:
                        time.sleep(delay)
            elif stop is not None and stop.is_set():
                return
            yield PoseSample(stamp, pos[i], quat[i], self.confidence)
