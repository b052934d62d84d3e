"""DCA1000EVM capture files: ``adc_data.bin`` from mmWave Studio, the DCA1000EVM CLI's files.

Three byte layouts reach a user (sources in ``docs/sensors.md``, section "DCA1000 capture files"):

``raw``
    The LVDS stream as the board sent it, frames back to back: 2-lane, I0 I1 Q0 Q1 I2 I3 Q2 Q3
    ... (the ``adc_data.bin`` that mmWave Studio's ``Packet_Reorder_Zerofill`` leaves, read by
    TI's ``readDCA1000.m``; SWRA581 section "xWR16xx/IWR6843 with DCA1000 data format").
``reordered``
    What the DCA1000EVM CLI (``DCA1000EVM_CLI_Record``) writes when ``reorderEnable`` is on —
    and it is on when the JSON omits it (``cli_record_main.cpp``: "Reordering is enabled if the
    field is missing in JSON file"). Its ``ReorderAlgorithm`` (``recorddatarecv.cpp``) moves
    value k of each group of 2 x lanes int16 to position ``(k % lanes) * 2 + k // lanes``: for 2
    lanes I0 I1 Q0 Q1 becomes I0 Q0 I1 Q1 (plain interleaved I/Q). With ``MSBToggle`` on it also
    adds 0x8000 to every value.
``records``
    The sequence-number record format (``sequenceNumberEnable`` in the post-processing build,
    ``recorddatarecv.cpp`` ``writeDataToFile``): per UDP packet ``u32 sequence number | u32
    payload size | 48-bit byte count | payload``, little-endian, packets in arrival order, lost
    ones absent. These are reassembled exactly like the live stream
    (:class:`~twinfocus.sensors.dca1000.FrameAssembler`), so a lost packet becomes a
    zero-filled, flagged frame here too.

Files larger than ``maxRecFileSize_MB`` are split: ``<prefix>_Raw_0.bin``, ``_Raw_1.bin``, ...
(``setFileName`` / ``writeDataToFile_Inline``: prefix + ``_Raw_`` + counter + ``.bin``); the
CLI cuts them at multiples of a packet's 1456-byte payload so I/Q groups never straddle files.
They are read here as one stream in counter order.

No capture file holds a time stamp: frame ``i`` is stamped ``i`` frame periods after the
first, on a clock that starts at 0 (``twinfocus convert`` then aligns the first frame to the
first pose unless told otherwise).
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.sensors.dca1000 import MAX_PAYLOAD_BYTES, AssemblerStats, FrameAssembler, RawFrameLayout
from twinfocus.sensors.frames import FrameFlag, RadarFrame

FORMATS = ("raw", "reordered", "records")
#: u32 sequence number, u32 payload size, 48-bit byte count (``recorddatarecv.cpp``).
RECORD_HEADER_BYTES = 14
_SPLIT_RE = re.compile(r"^(?P<prefix>.*)_Raw_(?P<n>\d+)\.bin$")


@dataclass(frozen=True)
class CliCaptureSettings:
    """What a DCA1000EVM CLI JSON says about the files it wrote (defaults: the CLI's own)."""

    reorder: bool = True
    msb_toggle: bool = False
    sequence_numbers: bool = False
    lvds_lanes: int = 2
    file_prefix: str | None = None
    source: str | None = None


def read_cli_json(path: str | os.PathLike) -> CliCaptureSettings:
    """The layout settings of a DCA1000EVM CLI configuration JSON (``DCA1000Config``).

    ``dataFormatConfig.reorderEnable`` (default on when absent), ``dataFormatConfig.MSBToggle``
    (default off), ``captureConfig.sequenceNumberEnable``, ``lvdsMode`` (1: 4 lanes, 2: 2 lanes),
    ``captureConfig.filePrefix`` — names and defaults as ``cli_record_main.cpp`` parses them.
    """
    path = Path(path)
    try:
        root = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise TwinFocusError(f"{path}: cannot read the DCA1000 CLI JSON ({exc})") from None
    cfg = root.get("DCA1000Config", root) if isinstance(root, dict) else None
    if not isinstance(cfg, dict):
        raise TwinFocusError(f"{path}: not a DCA1000 CLI JSON (no DCA1000Config object)")
    fmt = cfg.get("dataFormatConfig") or {}
    cap = cfg.get("captureConfig") or {}

    def flag(d, key, default):
        v = d.get(key, default)
        if str(v) not in ("0", "1", "True", "False", "true", "false"):
            raise TwinFocusError(f"{path}: {key} must be 0 or 1, got {v!r}")
        return str(v) in ("1", "True", "true")

    lanes = {1: 4, 2: 2}.get(int(cfg.get("lvdsMode", 2)))
    if lanes is None:
        raise TwinFocusError(f"{path}: lvdsMode must be 1 (4 lanes) or 2 (2 lanes), got {cfg.get('lvdsMode')!r}")
    return CliCaptureSettings(
        reorder=flag(fmt, "reorderEnable", 1),
        msb_toggle=flag(fmt, "MSBToggle", 0),
        sequence_numbers=flag(cap, "sequenceNumberEnable", 0),
        lvds_lanes=lanes,
        file_prefix=cap.get("filePrefix"),
        source=str(path),
    )


def capture_files(path: str | os.PathLike) -> list[Path]:
    """The files of one capture, in stream order.

    path : an ``adc_data.bin``-like file; a ``<prefix>_Raw_N.bin`` file (all its siblings
    ``_Raw_0``, ``_Raw_1``, ... are taken, in counter order); or a folder holding either
    (``adc_data.bin`` preferred, as mmWave Studio leaves both it and ``adc_data_Raw_0.bin``).
    """
    path = Path(path)
    if path.is_dir():
        if (path / "adc_data.bin").is_file():
            return [path / "adc_data.bin"]
        firsts = sorted(p for p in path.iterdir() if p.name.endswith("_Raw_0.bin"))
        if len(firsts) > 1:
            raise TwinFocusError(f"{path}: holds several captures ({', '.join(p.name for p in firsts)}); name one file")
        if not firsts:
            raise TwinFocusError(f"{path}: no DCA1000 capture here (expected adc_data.bin or <prefix>_Raw_0.bin)")
        path = firsts[0]
    if not path.is_file():
        raise TwinFocusError(f"{path}: no such capture file")
    m = _SPLIT_RE.match(path.name)
    if not m:
        return [path]
    parts = {}
    for p in path.parent.iterdir():
        mm = _SPLIT_RE.match(p.name)
        if mm and mm.group("prefix") == m.group("prefix"):
            parts[int(mm.group("n"))] = p
    n = 0
    files = []
    while n in parts:
        files.append(parts[n])
        n += 1
    if len(files) != len(parts):
        raise TwinFocusError(f"{path.parent}: split files of {m.group('prefix')} skip a number after _Raw_{n - 1}.bin")
    return files


def looks_like_records(head: bytes) -> bool:
    """True when the bytes begin with at least two consistent sequence-number records.

    A record's size is 1..1456, the next record's sequence number is higher and its byte count
    is this one's plus its size when no packet was lost in between. ADC samples pass all of
    this by chance with negligible probability.
    """
    pos, prev = 0, None
    seen = 0
    while pos + RECORD_HEADER_BYTES <= len(head) and seen < 8:
        seq = int.from_bytes(head[pos : pos + 4], "little")
        size = int.from_bytes(head[pos + 4 : pos + 8], "little")
        count = int.from_bytes(head[pos + 8 : pos + 14], "little")
        if not 0 < size <= MAX_PAYLOAD_BYTES or size % 2:
            return False
        if prev is not None:
            pseq, psize, pcount = prev
            if seq <= pseq or count < pcount + psize or (seq == pseq + 1 and count != pcount + psize):
                return False
        prev = (seq, size, count)
        seen += 1
        pos += RECORD_HEADER_BYTES + size
    return seen >= 2


def iter_records(data: np.ndarray) -> Iterator[tuple[int, int, memoryview]]:
    """(sequence number, byte count, payload) of each record of a sequence-number file stream."""
    buf = memoryview(data).cast("B")  # type: ignore[arg-type]  # numpy arrays export the buffer protocol
    pos, n = 0, len(buf)
    while pos + RECORD_HEADER_BYTES <= n:
        seq = int.from_bytes(buf[pos : pos + 4], "little")
        size = int.from_bytes(buf[pos + 4 : pos + 8], "little")
        count = int.from_bytes(buf[pos + 8 : pos + 14], "little")
        if size > MAX_PAYLOAD_BYTES or pos + RECORD_HEADER_BYTES + size > n:
            raise TwinFocusError(
                f"sequence-number record at byte {pos} announces a {size}-byte payload "
                f"({n - pos - RECORD_HEADER_BYTES} bytes left); the file is damaged or not in the record format"
            )
        yield seq, count, buf[pos + RECORD_HEADER_BYTES : pos + RECORD_HEADER_BYTES + size]
        pos += RECORD_HEADER_BYTES + size
    if pos != n:
        raise TwinFocusError(f"sequence-number file ends inside a record header ({n - pos} bytes left)")


def undo_reorder(values: np.ndarray, lanes: int = 2, msb_toggle: bool = False) -> np.ndarray:
    """int16 values as the CLI wrote them with ``reorderEnable`` -> the LVDS order.

    The CLI put LVDS value k of each group of 2 x lanes at ``(k % lanes) * 2 + k // lanes``;
    this reads it back from there (and takes the 0x8000 of ``MSBToggle`` off again).
    """
    v = np.asarray(values, dtype="<i2")
    g = 2 * lanes
    if v.size % g:
        raise TwinFocusError(f"reordered data hold {v.size} values, not a multiple of {g} (2 x {lanes} lanes)")
    src = np.array([(k % lanes) * 2 + k // lanes for k in range(g)])
    out = v.reshape(-1, g)[:, src].reshape(-1)
    if msb_toggle:
        out = (out.view("<u2") ^ np.uint16(0x8000)).view("<i2")
    return out


@dataclass
class Dca1000FileCapture:
    """A DCA1000 capture file (or split set) cut into frames.

    Parameters
    ----------
    path : file or folder (see :func:`capture_files`).
    layout : :class:`~twinfocus.sensors.dca1000.RawFrameLayout` of one frame.
    frame_period_s : the frame period (stamps are ``i * frame_period_s``, seconds from 0).
    file_format : ``"raw"``, ``"reordered"``, ``"records"`` or ``"auto"`` (records when the
        bytes parse as records, else ``reordered`` when a CLI JSON says so, else ``raw``).
    settings : the CLI JSON's :class:`CliCaptureSettings` when there is one (its
        ``reorderEnable`` default is on).

    Attributes: ``frames`` (list of :class:`RadarFrame`, complex64 (n_tx, n_rx, N), stamps
    ``i * frame_period`` in ns), ``stats`` (:class:`AssemblerStats`: lost / zero-filled frames
    and bytes), ``format`` (the layout used), ``warnings``.
    """

    path: str | os.PathLike
    layout: RawFrameLayout
    frame_period_s: float
    file_format: str = "auto"
    settings: CliCaptureSettings | None = None
    loop: int | None = 0
    frames: list = field(default_factory=list, init=False)
    stats: AssemblerStats = field(default_factory=AssemblerStats, init=False)
    warnings: list = field(default_factory=list, init=False)
    format: str = field(default="", init=False)

    def __post_init__(self) -> None:
        if self.file_format not in FORMATS + ("auto",):
            raise TwinFocusError(
                f"DCA1000 file format must be one of {', '.join(FORMATS)} or auto, got {self.file_format!r}"
            )
        if not self.frame_period_s > 0:
            raise TwinFocusError(f"frame period must be positive, got {self.frame_period_s}")
        s = self.settings or CliCaptureSettings(reorder=False)
        if s.lvds_lanes != 2:
            raise TwinFocusError(
                f"{s.source}: lvdsMode gives {s.lvds_lanes} LVDS lanes; only the 2-lane layout of xWR16xx/18xx/68xx is read here"
            )
        files = capture_files(self.path)
        data = (
            np.concatenate([np.fromfile(f, np.uint8) for f in files])
            if len(files) > 1
            else np.fromfile(files[0], np.uint8)
        )
        fmt = self.file_format
        if fmt == "auto":
            fmt = (
                "records"
                if looks_like_records(bytes(data[: 4 * (RECORD_HEADER_BYTES + MAX_PAYLOAD_BYTES)]))
                else ("reordered" if s.reorder and self.settings is not None else "raw")
            )
        self.format = fmt
        lay = self.layout
        fb = lay.frame_bytes
        raws: list[tuple[bytes | np.ndarray, FrameFlag]] = []
        if fmt == "records":
            # The live path's assembler with its default reorder window: a frame with a hole is given
            # out once the records have run the window past it, exactly as a live stream would.
            asm = FrameAssembler(fb)
            got = []
            for seq, count, payload in iter_records(data):
                got += asm.push(seq, count, payload)
            got += asm.flush()
            self.stats = asm.stats
            raws = [(np.frombuffer(f.raw, "<i2"), f.flags) for f in got]
            if s.reorder and self.settings is not None and self.file_format == "auto":
                self.warnings.append(
                    "records hold the board's LVDS order (the CLI reorders only when it writes without sequence numbers); "
                    "reorderEnable ignored"
                )
        else:
            n, rest = divmod(data.size, fb)
            if rest:
                self.warnings.append(f"the capture ends inside frame {n} ({rest} of {fb} bytes); that frame is dropped")
            values = data[: n * fb].view("<i2")
            if fmt == "reordered":
                values = undo_reorder(values, 2, s.msb_toggle)
            values = values.reshape(n, -1)
            raws = [(values[i], FrameFlag.OK) for i in range(n)]
            self.stats = AssemblerStats(bytes=int(data.size), frames=n)
        period_ns = int(round(self.frame_period_s * 1e9))
        self.frames = [
            RadarFrame(i * period_ns, lay.to_mimo(lay.decode(r), self.loop), flags) for i, (r, flags) in enumerate(raws)
        ]
        if not self.frames:
            raise TwinFocusError(f"{self.path}: holds no complete frame of {fb} bytes ({data.size} bytes read)")


def find_cli_json(path: str | os.PathLike) -> Path | None:
    """A DCA1000EVM CLI JSON (an object with ``DCA1000Config``) beside the capture, if one is there."""
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    found = []
    for p in sorted(folder.glob("*.json")):
        try:
            doc = json.loads(p.read_text())
        except (OSError, ValueError):
            continue
        if isinstance(doc, dict) and "DCA1000Config" in doc:
            found.append(p)
    if len(found) > 1:
        raise TwinFocusError(
            f"{folder}: several DCA1000 CLI JSON files ({', '.join(p.name for p in found)}); name one with --dca-json"
        )
    return found[0] if found else None
