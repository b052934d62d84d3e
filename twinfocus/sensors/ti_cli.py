"""Single-chip TI radars (xWR16xx/18xx/68xx): the mmWave SDK command line and its ``.cfg`` files.

The radar's firmware (mmWave SDK out-of-box demo, or a raw-capture build) reads one command per
line on its CLI UART (115200 baud) and answers each with the echoed command, optional text and
``Done`` on success, ``Error <code>`` on a refused command, or ``'<cmd>' is not recognized as a
CLI command``; then it prints its prompt ``mmwDemo:/>``. A ``.cfg`` file lists the commands
(``%`` starts a comment). The ones that shape the raw ADC frames:

- ``channelCfg <rxEn> <txEn> <cascading>`` (bit masks)
- ``adcCfg <numADCBits: 2 = 16 bit> <adcOutputFmt: 1 = complex 1x, 2 = complex 2x>``
- ``profileCfg <id> <startFreq GHz> <idle us> <adcStart us> <rampEnd us> <txPower> <txPhase>
  <slope MHz/us> <txStart us> <numAdcSamples> <sampleRate ksps> <hpf1> <hpf2> <rxGain>``
- ``chirpCfg <startIdx> <endIdx> <profileId> <freqVar> <slopeVar> <idleVar> <adcStartVar> <txMask>``
- ``frameCfg <chirpStart> <chirpEnd> <numLoops> <numFrames> <period ms> <trigger> <trigDelay>``

Source: mmWave SDK User's Guide, "Configuration (.cfg) File Format" (see ``docs/sensors.md``).
"""

from __future__ import annotations

import os
import re
import time
from dataclasses import dataclass
from pathlib import Path

from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import Chirp
from twinfocus.sensors.chirp_profile import Profile, profile_chirp
from twinfocus.sensors.dca1000 import RawFrameLayout

CLI_PROMPT = "mmwDemo:/>"
CLI_BAUD = 115200
_ERROR_CODE = re.compile(r"^Error\s+-?\d+")


class CliCommandError(TwinFocusError):
    """The radar refused a command (``Error <code>`` / not recognised) or did not answer."""

    def __init__(self, message: str, command: str, reply: list[str]):
        super().__init__(message)
        self.command = command
        self.reply = reply


def read_cfg(cfg: str | os.PathLike | list[str]) -> list[tuple[int, str]]:
    """Commands of a ``.cfg`` file (path, text with newlines, or list of lines).

    Returns (line number, command) pairs; blank lines and ``%`` comments are dropped.
    """
    if isinstance(cfg, (list, tuple)):
        lines = list(cfg)
    elif isinstance(cfg, os.PathLike) or (
        isinstance(cfg, str) and "\n" not in cfg and (cfg.strip().endswith(".cfg") or Path(cfg).is_file())
    ):
        p = Path(cfg)
        if not p.is_file():
            raise TwinFocusError(f"{p}: no such radar configuration file")
        lines = p.read_text(errors="replace").splitlines()
    else:
        lines = str(cfg).splitlines()
    out = []
    for i, line in enumerate(lines, start=1):
        s = line.strip()
        if s and not s.startswith("%"):
            out.append((i, " ".join(s.split())))
    return out


@dataclass(frozen=True)
class ChirpEntry:
    start_idx: int
    end_idx: int
    profile_id: int
    tx_mask: int


@dataclass(frozen=True)
class RadarCliConfig:
    """What a ``.cfg`` file configures (the parts that shape raw ADC frames).

    Build with :meth:`from_cfg`; :meth:`chirp` and :meth:`raw_layout` give what the readers
    need. ``commands`` keeps every command in file order.
    """

    commands: tuple[str, ...]
    rx_mask: int
    tx_mask: int
    adc_bits: int
    adc_format: int
    profiles: dict
    chirps: tuple[ChirpEntry, ...]
    frame_chirp_start: int
    frame_chirp_end: int
    n_loops: int
    n_frames: int
    frame_period_ms: float
    #: lvdsStreamCfg (enableHeader, dataFmt, enableSW) and adcbufCfg (adcOutputFmt, SampleSwap,
    #: ChanInterleave) when the file has them: they change the bytes on the LVDS stream.
    lvds_stream: tuple[int, int, int] | None = None
    adcbuf: tuple[int, int, int] | None = None

    @classmethod
    def from_cfg(cls, cfg, source: str | None = None) -> RadarCliConfig:
        """Parse a ``.cfg`` (see :func:`read_cfg`); errors name the file, line and field."""
        name = source or (
            str(cfg) if isinstance(cfg, (str, os.PathLike)) and "\n" not in str(cfg) else "radar configuration"
        )
        cmds = read_cfg(cfg)
        vals: dict = {"profiles": {}, "chirps": []}

        def nums(line_no, parts, n_expected, what):
            if len(parts) - 1 != n_expected:
                raise TwinFocusError(
                    f"{name} line {line_no}: {parts[0]} takes {n_expected} values ({what}), got {len(parts) - 1}"
                )
            try:
                return [float(p) for p in parts[1:]]
            except ValueError:
                raise TwinFocusError(
                    f"{name} line {line_no}: {parts[0]} values must be numbers, got {' '.join(parts[1:])!r}"
                ) from None

        for line_no, cmd in cmds:
            parts = cmd.split()
            key = parts[0]
            if key == "channelCfg":
                v = nums(line_no, parts, 3, "rxChannelEn txChannelEn cascading")
                vals["rx_mask"], vals["tx_mask"] = int(v[0]), int(v[1])
            elif key == "adcCfg":
                v = nums(line_no, parts, 2, "numADCBits adcOutputFmt")
                vals["adc_bits"], vals["adc_format"] = int(v[0]), int(v[1])
            elif key == "profileCfg":
                v = nums(
                    line_no,
                    parts,
                    14,
                    "profileId startFreq idleTime adcStartTime rampEndTime txOutPower "
                    "txPhaseShifter freqSlopeConst txStartTime numAdcSamples digOutSampleRate hpfCornerFreq1 "
                    "hpfCornerFreq2 rxGain",
                )
                vals["profiles"][int(v[0])] = Profile(v[1], v[2], v[3], v[4], v[7], int(v[9]), v[10])
            elif key == "chirpCfg":
                v = nums(
                    line_no,
                    parts,
                    8,
                    "startIdx endIdx profileId startFreqVar freqSlopeVar idleTimeVar adcStartTimeVar txEnable",
                )
                vals["chirps"].append(ChirpEntry(int(v[0]), int(v[1]), int(v[2]), int(v[7])))
            elif key == "frameCfg":
                v = nums(
                    line_no,
                    parts,
                    7,
                    "chirpStartIdx chirpEndIdx numLoops numFrames framePeriodicity triggerSelect frameTriggerDelay",
                )
                vals["frame"] = (int(v[0]), int(v[1]), int(v[2]), int(v[3]), v[4])
            elif key == "lvdsStreamCfg":
                v = nums(line_no, parts, 4, "subFrameIdx enableHeader dataFmt enableSW")
                vals["lvds_stream"] = (int(v[1]), int(v[2]), int(v[3]))
            elif key == "adcbufCfg":
                v = nums(line_no, parts, 5, "subFrameIdx adcOutputFmt SampleSwap ChanInterleave ChirpThreshold")
                vals["adcbuf"] = (int(v[1]), int(v[2]), int(v[3]))
        for key, what in (("rx_mask", "channelCfg"), ("adc_bits", "adcCfg"), ("frame", "frameCfg")):
            if key not in vals:
                raise TwinFocusError(f"{name}: no {what} command; the raw frame layout cannot be known without it")
        if not vals["profiles"]:
            raise TwinFocusError(f"{name}: no profileCfg command")
        if not vals["chirps"]:
            raise TwinFocusError(f"{name}: no chirpCfg command")
        fs, fe, loops, n_frames, period = vals["frame"]
        return cls(
            commands=tuple(c for _, c in cmds),
            rx_mask=vals["rx_mask"],
            tx_mask=vals["tx_mask"],
            adc_bits=vals["adc_bits"],
            adc_format=vals["adc_format"],
            profiles=vals["profiles"],
            chirps=tuple(vals["chirps"]),
            frame_chirp_start=fs,
            frame_chirp_end=fe,
            n_loops=loops,
            n_frames=n_frames,
            frame_period_ms=period,
            lvds_stream=vals.get("lvds_stream"),
            adcbuf=vals.get("adcbuf"),
        )

    @property
    def frame_period_s(self) -> float:
        return self.frame_period_ms * 1e-3

    def _chirp_entry(self, idx: int) -> ChirpEntry:
        for c in self.chirps:
            if c.start_idx <= idx <= c.end_idx:
                return c
        raise TwinFocusError(f"frameCfg uses chirp {idx} but no chirpCfg covers it")

    def profile(self) -> Profile:
        """The chirp profile of the frame's first chirp."""
        entry = self._chirp_entry(self.frame_chirp_start)
        if entry.profile_id not in self.profiles:
            raise TwinFocusError(f"chirpCfg uses profile {entry.profile_id} but no profileCfg defines it")
        return self.profiles[entry.profile_id]

    def chirp(self) -> Chirp:
        """The chirp of the frame's first chirp profile (first ADC sample at start + slope x ADC start)."""
        return profile_chirp(self.profile())

    def check_stream_format(self) -> None:
        """Refuse settings that change the LVDS byte layout from the one read here.

        The layout read (TI SWRA581, DCA1000 data format of xWR16xx/18xx/68xx) is that of the
        SDK demos' raw-capture settings ``lvdsStreamCfg -1 0 1 0`` (no header, ADC data only)
        and ``adcbufCfg -1 0 1 1 1`` (complex, the demo's sample swap, non-interleaved). An HSI
        header (``enableHeader`` 1) puts 0x0ADC-tagged headers into the stream (TI E2E 708709:
        "starting with DC 0A DC 0A"); ``dataFmt`` other than 1 adds chirp parameter / quality
        data; real ADC output, the other sample swap or interleaved channels reorder the
        samples. Each is refused with the setting to use; a file without these commands passes.
        """
        if self.lvds_stream is not None:
            header, fmt, _sw = self.lvds_stream
            if header:
                raise TwinFocusError(
                    "lvdsStreamCfg enableHeader is 1: HSI headers (0x0ADC) sit in the LVDS stream between "
                    "the samples; record with lvdsStreamCfg -1 0 1 0"
                )
            if fmt != 1:
                raise TwinFocusError(
                    f"lvdsStreamCfg dataFmt is {fmt}: the stream carries more than ADC samples "
                    "(1 = ADC only is read); record with lvdsStreamCfg -1 0 1 0"
                )
        if self.adcbuf is not None:
            out_fmt, swap, interleave = self.adcbuf
            if out_fmt != 0:
                raise TwinFocusError(
                    f"adcbufCfg adcOutputFmt is {out_fmt} (real); the raw layout read here is complex (0)"
                )
            if swap != 1 or interleave != 1:
                raise TwinFocusError(
                    f"adcbufCfg SampleSwap {swap} / ChanInterleave {interleave}: only the SDK demo's "
                    "adcbufCfg -1 0 1 1 1 (non-interleaved) layout is read"
                )

    def raw_layout(self) -> RawFrameLayout:
        """How the frames arrive from the capture board (16-bit complex output only)."""
        self.check_stream_format()
        if self.adc_bits != 2:
            raise TwinFocusError(f"adcCfg numADCBits is {self.adc_bits}; raw capture here needs 2 (16-bit samples)")
        if self.adc_format != 1:
            raise TwinFocusError(f"adcCfg adcOutputFmt is {self.adc_format}; raw capture here needs 1 (complex 1x)")
        tx_bits = [b for b in range(8) if self.tx_mask >> b & 1]
        tx_of_chirp = []
        for idx in range(self.frame_chirp_start, self.frame_chirp_end + 1):
            mask = self._chirp_entry(idx).tx_mask
            bits = [b for b in range(8) if mask >> b & 1]
            if len(bits) != 1:
                raise TwinFocusError(
                    f"chirp {idx} enables TX mask {mask}: TDM-MIMO needs exactly one TX per chirp (BPM is not supported)"
                )
            if bits[0] not in tx_bits:
                raise TwinFocusError(
                    f"chirp {idx} fires TX{bits[0]} which channelCfg does not enable (mask {self.tx_mask})"
                )
            tx_of_chirp.append(tx_bits.index(bits[0]))
        n_rx = bin(self.rx_mask).count("1")
        return RawFrameLayout(self.chirp().n_samples, n_rx, tuple(tx_of_chirp), self.n_loops, len(tx_bits))


class TiRadarCli:
    """The radar's CLI over a serial port (any pyserial URL: ``/dev/ttyACM0``, ``COM3``, a pty).

    Each :meth:`send` writes one command and reads until ``Done`` (success) or ``Error <code>`` /
    not-recognised (raises :class:`CliCommandError` with the reply), within ``timeout_s``.
    """

    def __init__(self, port: str, baudrate: int = CLI_BAUD, timeout_s: float = 2.0):
        import serial  # pyserial; imported here so that the rest of the package works without it

        self.port = port
        self.timeout_s = float(timeout_s)
        try:
            self._ser = serial.serial_for_url(port, baudrate=int(baudrate), timeout=0.05)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TwinFocusError(
                f"cannot open the radar CLI port {port}: {exc}; check the cable, the port name "
                "(the CLI is the lower-numbered of the EVM's two ports) and permissions (group dialout)"
            ) from None

    def __enter__(self) -> TiRadarCli:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        try:
            self._ser.close()
        except Exception:  # noqa: BLE001 - closing a vanished port must not mask the real error
            pass

    def send(self, command: str, timeout_s: float | None = None) -> list[str]:
        """Send one command; return the reply lines (without echo, ``Done`` and prompt)."""
        command = " ".join(str(command).split())
        self._ser.reset_input_buffer()
        self._ser.write((command + "\n").encode("ascii"))
        self._ser.flush()
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else float(timeout_s))
        pending = b""
        reply: list[str] = []
        while True:
            # read(1) waits for the first byte (up to the port timeout), then take what is queued.
            chunk = self._ser.read(1)
            if chunk and self._ser.in_waiting:
                chunk += self._ser.read(self._ser.in_waiting)
            if chunk:
                pending += chunk
                *lines, pending = pending.replace(b"\r", b"\n").split(b"\n")
                for raw in lines:
                    line = raw.decode("ascii", errors="replace").strip()
                    if line.startswith(CLI_PROMPT):
                        line = line[len(CLI_PROMPT) :].strip()
                    if not line or line == command:
                        continue
                    if line == "Done":
                        return reply
                    reply.append(line)
                    if _ERROR_CODE.match(line) or "not recognized as a CLI command" in line:
                        raise CliCommandError(f"radar refused {command!r}: {' / '.join(reply)}", command, reply)
            elif time.monotonic() > deadline:
                got = " / ".join(reply + ([pending.decode("ascii", "replace").strip()] if pending.strip() else []))
                raise CliCommandError(
                    f"radar did not answer {command!r} with Done within {self.timeout_s:g} s"
                    + (
                        f" (got: {got})"
                        if got
                        else " (no reply: is this the CLI port, and is the radar flashed and booted?)"
                    ),
                    command,
                    reply,
                )

    def configure(self, cfg, start: bool = True, retries: int = 1) -> RadarCliConfig:
        """Send a whole ``.cfg``; each refused command is retried ``retries`` times.

        The file is parsed first (a wrong file never half-configures the radar). With
        ``start=False`` the ``sensorStart`` lines are left out. Returns the parsed configuration.
        """
        config = RadarCliConfig.from_cfg(cfg)
        name = str(cfg) if isinstance(cfg, (str, os.PathLike)) and "\n" not in str(cfg) else "configuration"
        for line_no, cmd in read_cfg(cfg):
            if not start and cmd.split()[0] == "sensorStart":
                continue
            for attempt in range(int(retries) + 1):
                try:
                    self.send(cmd)
                    break
                except CliCommandError as exc:
                    if attempt == int(retries):
                        raise CliCommandError(
                            f"{name} line {line_no}: {exc} (after {attempt + 1} attempt(s))", exc.command, exc.reply
                        ) from None
        return config

    def start(self) -> None:
        self.send("sensorStart")

    def stop(self) -> None:
        self.send("sensorStop")
