"""An emulated mmWave SDK radar CLI on a pseudo-terminal (no radar needed).

Answers like the SDK's CLI task: echoes the command, then ``Done``, or ``Error -1`` (with an
``Error: ...`` explanation line) for a command with the wrong number of arguments, or
``'<cmd>' is not recognized as a CLI command``; then the prompt ``mmwDemo:/>``. ``sensorStart``
is refused until channelCfg, adcCfg, profileCfg, chirpCfg and frameCfg have been given since the
last ``flushCfg``. ``refuse={"frameCfg": 1}`` refuses the next such command(s) once with
``Error -1`` (an injected transient failure). ``on_start(config)`` is called with the parsed
:class:`~twinfocus.sensors.ti_cli.RadarCliConfig` when the sensor starts, ``on_stop()`` when it
stops: the emulated capture board streams in between.

Open the emulated port with ``TiRadarCli(fake.port)`` (any pyserial client works).
"""

from __future__ import annotations

import os
import select
import threading
import tty

from twinfocus.errors import TwinFocusError
from twinfocus.sensors.ti_cli import CLI_PROMPT, RadarCliConfig

#: Commands of the SDK demo and their argument counts (None: any).
KNOWN_COMMANDS: dict[str, int | tuple[int, ...] | None] = {
    "sensorStop": 0,
    "sensorStart": (0, 1),
    "flushCfg": 0,
    "dfeDataOutputMode": 1,
    "channelCfg": 3,
    "adcCfg": 2,
    "adcbufCfg": 5,
    "profileCfg": 14,
    "chirpCfg": 8,
    "frameCfg": 7,
    "lowPower": 2,
    "lvdsStreamCfg": 4,
    "version": 0,
    "guiMonitor": None,
    "cfarCfg": None,
    "multiObjBeamForming": None,
    "clutterRemoval": None,
    "calibDcRangeSig": None,
    "compRangeBiasAndRxChanPhase": None,
    "measureRangeBiasAndRxChanPhase": None,
    "aoaFovCfg": None,
    "cfarFovCfg": None,
    "extendedMaxVelocity": None,
    "CQRxSatMonitor": None,
    "CQSigImgMonitor": None,
    "analogMonitor": None,
    "bpmCfg": None,
    "calibData": None,
    "advFrameCfg": None,
    "subFrameCfg": None,
}
_NEEDED_FOR_START = ("channelCfg", "adcCfg", "profileCfg", "chirpCfg", "frameCfg")


class FakeRadarCli:
    """The emulated CLI; ``port`` is the pseudo-terminal path to open."""

    def __init__(self, refuse: dict[str, int] | None = None, on_start=None, on_stop=None):
        self.refuse = dict(refuse or {})
        self.on_start = on_start
        self.on_stop = on_stop
        self.received: list[str] = []
        self.running = False
        self.config: RadarCliConfig | None = None
        self._cfg: list[str] = []
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="fake-radar-cli", daemon=True)
        self._thread.start()

    def __enter__(self) -> FakeRadarCli:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop answering and release the pseudo-terminal."""
        self._stop.set()
        self._thread.join(timeout=2.0)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def _serve(self) -> None:
        buf = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.05)
            if not ready:
                continue
            try:
                chunk = os.read(self._master, 4096)
            except OSError:
                continue
            buf += chunk
            while True:
                cut = min((i for i in (buf.find(b"\n"), buf.find(b"\r")) if i >= 0), default=-1)
                if cut < 0:
                    break
                line, buf = buf[:cut], buf[cut + 1 :]
                text = line.decode("ascii", errors="replace").strip()
                if not text:
                    continue
                reply = [text] + self.handle(text)
                try:
                    os.write(self._master, ("\r\n".join(reply) + "\r\n" + CLI_PROMPT).encode("ascii"))
                except OSError:
                    pass

    def handle(self, command: str) -> list[str]:
        """The reply lines to one command (without echo and prompt)."""
        self.received.append(command)
        parts = command.split()
        name, args = parts[0], parts[1:]
        if name not in KNOWN_COMMANDS:
            return [f"'{name}' is not recognized as a CLI command"]
        if self.refuse.get(name, 0) > 0:
            self.refuse[name] -= 1
            return ["Error -1"]
        want = KNOWN_COMMANDS[name]
        counts = (want,) if isinstance(want, int) else want
        if counts is not None and len(args) not in counts:
            return ["Error: Invalid usage of the CLI command", "Error -1"]
        if counts is not None and want != 0:
            try:
                [float(a) for a in args]
            except ValueError:
                return ["Error: Invalid usage of the CLI command", "Error -1"]
        if name == "flushCfg":
            if self.running:
                return ["Error: sensor must be stopped before flushCfg", "Error -1"]
            self._cfg = []
            return ["Done"]
        if name == "sensorStop":
            if not self.running:
                return ["Ignored: Sensor is already stopped", "Done"]
            self.running = False
            if self.on_stop is not None:
                self.on_stop()
            return ["Done"]
        if name == "sensorStart":
            if self.running:
                return ["Ignored: Sensor is already started", "Done"]
            given = {c.split()[0] for c in self._cfg}
            missing = [c for c in _NEEDED_FOR_START if c not in given]
            if missing:
                return [f"Error: configuration incomplete ({', '.join(missing)} missing)", "Error -1"]
            try:
                self.config = RadarCliConfig.from_cfg(self._cfg, source="fake radar")
                self.config.raw_layout()
            except TwinFocusError as exc:
                return [f"Error: {exc}", "Error -1"]
            self.running = True
            if self.on_start is not None:
                self.on_start(self.config)
            return ["Done"]
        if name == "version":
            return ["Platform                : xWR18xx (emulated)", "mmWave SDK Version      : 03.06.00.00", "Done"]
        if self.running and name in _NEEDED_FOR_START:
            return ["Error: sensor must be stopped before reconfiguring", "Error -1"]
        self._cfg.append(command)
        return ["Done"]
