"""Hardware sources: thin adapters from :mod:`twinfocus.sensors` to the driver backend interface.

Radar (:data:`nodes.runtime.backends.RADAR_BACKENDS`):

* ``mmwcas`` — :class:`MmwcasRadar`: a TI MMWCAS cascade capture folder
  (:class:`twinfocus.sensors.ti_mmwcas.MmwcasCapture`), replayed at its index time stamps. The
  MMWCAS-DSP-EVM writes captures to its own disk; it does not stream.
* ``dca1000`` — :class:`Dca1000Radar`: the raw ADC stream of a DCA1000EVM
  (:class:`twinfocus.sensors.dca1000.Dca1000`), the radar configured and started over its CLI
  (:class:`twinfocus.sensors.ti_cli.TiRadarCli`) when ``cli_port`` is given. Also the way to the
  emulated rig (``python -m twinfocus.sensors.emulators radar``).

Both turn each MIMO frame into the 86 monostatic-equivalent channels of
:func:`twinfocus.radar.fmcw.mmwcas_virtual_array` (:func:`twinfocus.sensors.frames.frame_to_virtual_channels`)
and drop frames flagged unusable (lost or zero-filled packets, device skew) unless
``keep_flagged``. The DCA1000 stream's gaps (frames lost, zero-filled, bytes lost) travel on every
sample (``RadarSample.gaps`` -> ``RadarFrame.frames_lost`` ...) and are said on stderr.

VIO (:data:`nodes.runtime.backends.VIO_BACKENDS`):

* ``zed`` — :class:`ZedVio`: ZED 2i positional tracking through the ZED SDK
  (:class:`twinfocus.sensors.zed.ZedSdkCamera`); poses are the left camera's
  (``child_frame_id = "camera"``: the synchronizer applies its ``extrinsics``).
* ``emulated`` — :class:`EmulatedRigVio`: the emulated rig's tracker
  (:class:`twinfocus.sensors.emulators.rig.EmulatedVio`), started by the emulated radar's sync file.

The ZED's raw UVC stereo stream (:class:`twinfocus.sensors.zed.ZedUvcStereo`) gives images, not
poses, so it is no VIO backend.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from nodes.runtime.backends import PoseSample, RadarSample, check_unknown, option
from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import paper_raster
from twinfocus.radar.board import load_board
from twinfocus.radar.calibration import calibration_for
from twinfocus.radar.fmcw import Chirp, VirtualArray, mmwcas_virtual_array
from twinfocus.sensors.dca1000 import BOARD_IP, CONFIG_PORT, DATA_PORT, HOST_IP, Dca1000, RawFrameLayout
from twinfocus.sensors.emulators.rig import EMULATED_CFG, EmulatedVio, default_sync_file
from twinfocus.sensors.frames import FrameFlag, frame_to_virtual_channels
from twinfocus.sensors.ti_cli import RadarCliConfig, TiRadarCli
from twinfocus.sensors.ti_mmwcas import MmwcasCapture, resolve_config
from twinfocus.sensors.zed import ZedSdkCamera


def _address(value: str, where: str, name: str) -> tuple[str, int]:
    host, sep, port = str(value).rpartition(":")
    if not sep or not port.isdigit():
        raise TwinFocusError(f"{where}: option {name!r} must be HOST:PORT, got {value!r}")
    return host, int(port)


def _virtual_channels(
    frame: np.ndarray,
    chirp: Chirp,
    z0_m: float,
    array: VirtualArray | None = None,
    correction: np.ndarray | None = None,
) -> np.ndarray:

    x = frame_to_virtual_channels(frame, chirp, z0_m, array)
    return (x if correction is None else x * correction).astype(np.complex64, copy=False)


def _channel_calibration(options: dict, chirp: Chirp, array: VirtualArray, where: str) -> np.ndarray | None:
    """The ``calibration`` option's correction (K, N) (``twinfocus calibrate``), refused when made
    for another array or chirp; none: a one-line warning, the channels uncorrected."""

    path = option(options, "calibration", "", str, where)
    if not path:
        print(
            f"[{where}] warning: no 'calibration': the channels' own phase, gain and delay errors stay in the data",
            file=sys.stderr,
            flush=True,
        )
        return None

    correction, _ = calibration_for(path, chirp, array)
    return correction


class MmwcasRadar:
    """Options: ``capture`` (folder, required), ``z0_m`` (0.6: range of the multistatic
    correction), ``scan_id`` (default the folder name), ``f0_hz`` ``slope_hz_per_s`` ``fs_hz``
    ``n_samples`` (the chirp; default the capture configuration's profile, else
    :class:`~twinfocus.radar.fmcw.Chirp`'s; one given overrides the configuration, with a note), ``n_loops`` (1), ``loop``
    (0), ``timestamp_unit_ns`` (1000), ``time_offset_ns`` (0: added to every stamp, onto the
    poses' clock), ``keep_first_frame`` (False), ``keep_flagged`` (False); the chirp layout
    (``tx_order``: TI's TxToEnable, e.g. "12,11,...,1"; ``n_loops``; ``frame_period_s``) comes
    from the capture's mmWave Studio JSON when it has one, these options otherwise;
    ``setup`` (the configuration file, default the one found), ``drop_first_frame_of_each_slice``
    (False) as TI's cascade processing does; ``board`` (a board file of the antenna layout,
    default TI's MMWCAS-RF-EVM); ``calibration`` (a ``twinfocus calibrate`` file; none: a warning)."""

    live = False

    def __init__(self, options: dict):

        where = "radar backend 'mmwcas'"
        check_unknown(
            options,
            {
                "capture",
                "z0_m",
                "scan_id",
                "f0_hz",
                "slope_hz_per_s",
                "fs_hz",
                "n_samples",
                "n_loops",
                "loop",
                "timestamp_unit_ns",
                "time_offset_ns",
                "keep_first_frame",
                "keep_flagged",
                "tx_order",
                "frame_period_s",
                "drop_first_frame_of_each_slice",
                "setup",
                "board",
                "calibration",
            },
            where,
        )
        folder = option(options, "capture", None, str, where)
        board = load_board(option(options, "board", "", str, where) or None)
        self.array = mmwcas_virtual_array(board)
        d = Chirp()

        def given(name, default, kind):  # a chirp option the user set, else None (the capture's own)
            return None if options.get(name) is None else kind(option(options, name, default, kind, where))

        loops = options.get("n_loops")
        period = options.get("frame_period_s")
        config, notes = resolve_config(
            folder,
            f0_hz=given("f0_hz", d.f0_hz, float),
            slope_hz_per_s=given("slope_hz_per_s", d.slope_hz_per_s, float),
            fs_hz=given("fs_hz", d.fs_hz, float),
            n_samples=given("n_samples", d.n_samples, int),
            n_loops=None if loops is None else int(option(options, "n_loops", 1, int, where)),
            tx_order=option(options, "tx_order", "", str, where) or None,
            frame_period_s=None if period is None else option(options, "frame_period_s", 0.1, float, where),
            timestamp_unit_ns=int(option(options, "timestamp_unit_ns", 1000, int, where)),
            setup=option(options, "setup", "", str, where) or None,
        )
        for note in notes:
            print(f"{where}: {note}", file=sys.stderr)
        self.chirp = config.chirp
        self.loop = int(option(options, "loop", 0, int, where))
        self.z0_m = option(options, "z0_m", 0.6, float, where)
        self.offset_ns = int(option(options, "time_offset_ns", 0, int, where))
        self.scan_id = str(option(options, "scan_id", Path(folder).name, str, where))
        self.capture = MmwcasCapture(
            folder,
            config,
            skip_first_frame=not option(options, "keep_first_frame", False, bool, where),
            skip_first_frame_of_each_slice=bool(option(options, "drop_first_frame_of_each_slice", False, bool, where)),
        )
        keep = bool(option(options, "keep_flagged", False, bool, where))
        self.frames = [i for i in range(len(self.capture)) if keep or FrameFlag(int(self.capture.flags[i])).usable]
        if not self.frames:
            raise TwinFocusError(f"{where}: {folder} holds no usable frame")
        self.channel_offsets_m = self.array.offsets_m
        self.correction = _channel_calibration(options, self.chirp, self.array, where)

    def samples(self) -> Iterator[RadarSample]:
        for m, i in enumerate(self.frames):
            (frame,) = self.capture.frames(self.loop, start=i, stop=i + 1)
            yield RadarSample(
                stamp_ns=frame.stamp_ns + self.offset_ns,
                data=_virtual_channels(frame.data, self.chirp, self.z0_m, self.array, self.correction),
                scan_id=self.scan_id,
                index=m,
                last=m == len(self.frames) - 1,
                gaps=self._gaps(i),
            )

    def _gaps(self, i: int) -> tuple[int, int, int]:
        """The capture's gaps up to frame i, as a stream's: (frames missing from every device,
        frames holding only zeros, 0 bytes)."""

        zero = int(np.count_nonzero(self.capture.flags[: i + 1] & int(FrameFlag.ZERO_FILLED)))
        return int(self.capture.frames_missing_before[i]), zero, 0

    def close(self) -> None:
        self.capture.close()


class Dca1000Radar:
    """Options: ``cfg`` (mmWave SDK ``.cfg`` file, or ``emulated`` for the emulated rig's; gives
    the chirp and, with ``layout: cfg``, the frame layout), ``cli_port`` (serial port of the
    radar's CLI; empty: the radar is started by other means), ``board`` (``192.168.33.180:4096``),
    ``host_ip`` (``192.168.33.30``), ``config_port`` (4096), ``data_port`` (4098), ``lvds_lanes``
    (2), ``layout`` (``mmwcas``: 12 chirps = TX 0..11, 16 RX, as the emulated rig streams;
    ``cfg``: from the ``.cfg``, which must then describe a 12 TX x 16 RX radar), ``z0_m`` (0.6),
    ``scan_id`` ("live"), ``frames_per_scan`` (0: one scan until the stream ends; N: every N
    frames end a scan, the next gets ``scan_id_001``...), ``idle_timeout_s`` (5: the stream has
    ended after this long without packets), ``keep_flagged`` (False), ``calibration`` (a
    ``twinfocus calibrate`` file; none: a warning)."""

    live = True

    def __init__(self, options: dict):

        where = "radar backend 'dca1000'"
        check_unknown(
            options,
            {
                "cfg",
                "cli_port",
                "board",
                "host_ip",
                "config_port",
                "data_port",
                "lvds_lanes",
                "layout",
                "z0_m",
                "scan_id",
                "frames_per_scan",
                "idle_timeout_s",
                "keep_flagged",
                "calibration",
            },
            where,
        )
        cfg = option(options, "cfg", None, str, where)
        if cfg == "emulated":
            cfg = EMULATED_CFG
        self.cfg = cfg
        config = RadarCliConfig.from_cfg(cfg)
        config.check_stream_format()
        self.chirp = config.chirp()
        self.frame_period_s = config.frame_period_s
        layout = option(options, "layout", "mmwcas", str, where)
        if layout == "mmwcas":
            self.layout = RawFrameLayout(self.chirp.n_samples, 16, tuple(range(12)), 1, 12)
        elif layout == "cfg":
            self.layout = config.raw_layout()
        else:
            raise TwinFocusError(f"{where}: layout must be 'mmwcas' or 'cfg', got {layout!r}")
        if self.layout.n_tx is None or self.layout.n_tx < 12 or self.layout.n_rx < 16:
            raise TwinFocusError(
                f"{where}: the frames have {self.layout.n_tx} TX x {self.layout.n_rx} RX; the 86 virtual "
                "channels of the MMWCAS array need 12 x 16 (use layout: mmwcas for the emulated rig)"
            )
        self.cli_port = option(options, "cli_port", "", str, where)
        self.lvds_lanes = int(option(options, "lvds_lanes", 2, int, where))
        self.z0_m = option(options, "z0_m", 0.6, float, where)
        self.scan_id = str(option(options, "scan_id", "live", str, where))
        self.per_scan = int(option(options, "frames_per_scan", 0, int, where))
        self.idle_timeout_s = option(options, "idle_timeout_s", 5.0, float, where)
        self.keep_flagged = bool(option(options, "keep_flagged", False, bool, where))
        self.array = mmwcas_virtual_array()
        self.channel_offsets_m = self.array.offsets_m
        self.correction = _channel_calibration(options, self.chirp, self.array, where)
        self._stop = threading.Event()
        self._cli: TiRadarCli | None = None
        self.host = Dca1000(
            _address(option(options, "board", f"{BOARD_IP}:{CONFIG_PORT}", str, where), where, "board"),
            option(options, "host_ip", HOST_IP, str, where),
            int(option(options, "config_port", CONFIG_PORT, int, where)),
            int(option(options, "data_port", DATA_PORT, int, where)),
        )

    def samples(self) -> Iterator[RadarSample]:
        try:
            self.host.setup(self.lvds_lanes)
            self.host.start_record()
            if self.cli_port:
                self._cli = TiRadarCli(self.cli_port)
                self._cli.configure(self.cfg)
            yield from self._stream()
        except OSError:
            if not self._stop.is_set():  # sockets closed by close() end the stream quietly
                raise

    def gaps(self) -> tuple[int, int, int]:
        """(frames lost, frames zero-filled, bytes lost) of the stream so far (the host's assembler)."""
        st = self.host.stats
        return st.frames_lost, st.frames_zero_filled, st.lost_bytes

    def _stream(self) -> Iterator[RadarSample]:

        scan, index, pending = 0, 0, None
        said, unsaid = 0.0, 0
        for frame in self.host.frames(
            self.layout, idle_timeout_s=self.idle_timeout_s, frame_period_s=self.frame_period_s, stop=self._stop
        ):
            if not frame.flags.usable:
                # Counted in host.stats and carried on every later frame (RadarFrame.frames_lost ...);
                # said on stderr at most once a second so a burst does not flood the log.
                unsaid += 1
                if time.monotonic() - said >= 1.0:
                    lost, zero_filled, nbytes = self.gaps()
                    print(
                        f"[dca1000] {unsaid} flagged frame(s) ({frame.flags!r}) "
                        f"{'kept' if self.keep_flagged else 'dropped'}; so far {lost} lost, {zero_filled} zero-filled, "
                        f"{nbytes} bytes lost",
                        file=sys.stderr,
                        flush=True,
                    )
                    said, unsaid = time.monotonic(), 0
                if not self.keep_flagged:
                    continue
            # One frame held back, so that the scan's last frame can say so when the stream ends.
            if pending is not None:
                yield pending
            scan_id = self.scan_id if not self.per_scan else f"{self.scan_id}_{scan:03d}"
            last = bool(self.per_scan) and index == self.per_scan - 1
            pending = RadarSample(
                frame.stamp_ns,
                _virtual_channels(frame.data, self.chirp, self.z0_m, self.array, self.correction),
                scan_id,
                index,
                last,
                gaps=self.gaps(),
            )
            index += 1
            if last:
                yield pending
                pending, scan, index = None, scan + 1, 0
        if pending is not None:
            pending.last = True
            pending.gaps = self.gaps()  # gaps after the last usable frame still reach the user
            yield pending

    def close(self) -> None:
        self._stop.set()
        try:
            if self._cli is not None:
                try:
                    self._cli.stop()
                except TwinFocusError:
                    pass
                self._cli.close()
            try:
                self.host.stop_record()
            except TwinFocusError:
                pass
        finally:
            self.host.close()


class ZedVio:
    """Options: ``resolution`` ("HD720"), ``fps`` (60), ``serial`` (open that camera),
    ``svo_path`` (replay a ZED recording instead: paced by its stamps)."""

    frame_id = "scene"
    child_frame_id = "camera"

    def __init__(self, options: dict):

        where = "VIO backend 'zed'"
        check_unknown(options, {"resolution", "fps", "serial", "svo_path"}, where)
        svo = option(options, "svo_path", "", str, where) or None
        serial = option(options, "serial", 0, int, where) or None
        self.live = svo is None
        self._stop = threading.Event()
        self.camera = ZedSdkCamera(
            option(options, "resolution", "HD720", str, where), int(option(options, "fps", 60, int, where)), serial, svo
        )

    def samples(self) -> Iterator[PoseSample]:
        for s in self.camera.poses():
            if self._stop.is_set():
                return
            yield PoseSample(s.stamp_ns, s.position_m, s.quat_xyzw, s.confidence)

    def close(self) -> None:
        self._stop.set()
        self.camera.close()


class EmulatedRigVio:
    """Options as ``python -m twinfocus.sensors.emulators radar`` was started: ``columns`` (3),
    ``rows`` (40), ``column_pitch_m`` (0.082), ``row_pitch_m`` (0.002), ``period_s`` (0.05),
    ``config_port`` (4096; names the default sync file) or ``sync_file``; plus ``rate_hz`` (60),
    ``noise_sigma_m`` ([0, 0, 0]: tracking error per axis), ``start_timeout_s`` (60: wait this
    long for the emulated radar to start streaming)."""

    live = True
    frame_id = "scene"
    child_frame_id = "radar"

    def __init__(self, options: dict):

        where = "VIO backend 'emulated'"
        check_unknown(
            options,
            {
                "columns",
                "rows",
                "column_pitch_m",
                "row_pitch_m",
                "period_s",
                "config_port",
                "sync_file",
                "rate_hz",
                "noise_sigma_m",
                "start_timeout_s",
            },
            where,
        )
        traj = paper_raster(
            int(option(options, "columns", 3, int, where)),
            int(option(options, "rows", 40, int, where)),
            option(options, "column_pitch_m", 0.082, float, where),
            option(options, "row_pitch_m", 0.002, float, where),
            frame_period_s=option(options, "period_s", 0.05, float, where),
        )
        sync = option(options, "sync_file", "", str, where) or default_sync_file(
            int(option(options, "config_port", 4096, int, where))
        )
        noise = option(options, "noise_sigma_m", [0.0, 0.0, 0.0], list, where)
        self.timeout_s = option(options, "start_timeout_s", 60.0, float, where)
        self._stop = threading.Event()
        self.vio = EmulatedVio(
            traj, sync_file=sync, rate_hz=option(options, "rate_hz", 60.0, float, where), noise_sigma_m=noise
        )

    def samples(self) -> Iterator[PoseSample]:
        if self.vio.wait_for_start(self.timeout_s, self._stop) is None:
            if self._stop.is_set():
                return
            raise TwinFocusError(
                f"VIO backend 'emulated': the emulated radar did not start within {self.timeout_s:g} s "
                f"(no {self.vio.sync_file}); is `python -m twinfocus.sensors.emulators radar` running?"
            )
        for s in self.vio.poses(stop=self._stop):
            yield PoseSample(s.stamp_ns, s.position_m, s.quat_xyzw, s.confidence)

    def close(self) -> None:
        self._stop.set()
