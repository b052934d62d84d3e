"""TI MMWCAS-RF-EVM cascade captures: the four devices' ``_data.bin`` / ``_idx.bin`` files.

The MMWCAS-DSP-EVM (TDA2) capture card writes, per capture "slice" ``NNNN``, one pair of files
per AWR2243 device: ``master_NNNN_data.bin``, ``master_NNNN_idx.bin``, then ``slave1``, ``slave2``,
``slave3``. Layouts as implemented (sources in ``docs/sensors.md``):

Index file (little-endian, TI ``Bucket::Info`` and ``Bucket::BuffIdx``)::

    header, 24 bytes: u32 tag ('bckt'), u32 version, u32 flags, u32 numIdx (frames),
                      u64 dataFileSize (bytes written to the data file)
    entry,  48 bytes: u16 tag ('id'), u16 version, u32 flags, u16 width, u16 height,
                      u32 pitchOrMetaSize[4], u32 size (bytes of this frame),
                      u64 timestamp, u64 offset (of the frame in the data file)

Data file: frames back to back; one device frame is int16 pairs (I then Q) with RX fastest
(4 per device), then ADC sample, then chirp, then loop — TI's ``readBinFile`` reshapes it to
(4 RX, N samples, chirps, loops) in MATLAB (column-major) order.

The 16 receive channels are master RX1-4, slave1 RX1-4, slave2 RX1-4, slave3 RX1-4 (data
channels 1..16); the antennas in ascending position along the board are data channels
13-16, 1-4, 9-12, 5-8 (TI's ``TI_Cascade_RX_ID``), which is the RX order of
:mod:`twinfocus.radar.fmcw`. With TI's default chirp order (``TxToEnable = [12 11 ... 1]``) chirp c
fires the TX that :mod:`twinfocus.radar.fmcw` numbers c; other orders are given as ``tx_of_chirp``.

The capture card's first frame is known to be bad (TI's scripts skip it "due to TDA2"): it is
dropped unless ``skip_first_frame=False``. Truncated files (a capture cut short) keep their
complete frames; what was cut is reported in :attr:`MmwcasCapture.warnings`.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.radar.board import RX_ARRAY_ORDER as BOARD_RX_ARRAY_ORDER
from twinfocus.radar.fmcw import Chirp
from twinfocus.sensors.chirp_profile import (
    Profile,
    describe_chirp,
    profile_chirp,
    profile_fields_from_lua,
    profile_fields_from_studio_json,
    resolve_chirp,
)
from twinfocus.sensors.frames import FrameFlag, RadarFrame

DEVICES: tuple[str, ...] = ("master", "slave1", "slave2", "slave3")
RX_PER_DEVICE = 4
N_TX = 12
N_RX = 16

#: Array RX a (0-based, ascending along the board, the order of twinfocus.radar.fmcw) is data channel
#: RX_ARRAY_ORDER[a] (0-based; data channel = 4 * device + device RX). TI: TI_Cascade_RX_ID - 1.
RX_ARRAY_ORDER = BOARD_RX_ARRAY_ORDER

IDX_HEADER_DTYPE = np.dtype(
    [("tag", "<u4"), ("version", "<u4"), ("flags", "<u4"), ("num_idx", "<u4"), ("data_file_size", "<u8")]
)
IDX_ENTRY_DTYPE = np.dtype(
    [
        ("tag", "<u2"),
        ("version", "<u2"),
        ("flags", "<u4"),
        ("width", "<u2"),
        ("height", "<u2"),
        ("pitch_or_meta_size", "<u4", (4,)),
        ("size", "<u4"),
        ("timestamp", "<u8"),
        ("offset", "<u8"),
    ]
)
assert IDX_HEADER_DTYPE.itemsize == 24 and IDX_ENTRY_DTYPE.itemsize == 48

#: TI Bucket tags: 'b' 'c' 'k' 't' and 'i' 'd', little-endian.
INFO_TAG = 0x746B6362
BUFF_IDX_TAG = 0x6469

_SLICE_RE = re.compile(r"^master_(\d{4})_idx\.bin$")


@dataclass(frozen=True)
class MmwcasConfig:
    """What the capture's frames hold (the radar configuration of the cascade scripts).

    chirp : the chirp (defaults: the paper's 76 GHz, 5 us ADC start, 120 MHz/us, 8 Msps, 256).
    n_chirps : chirps per loop (one per TX used).
    n_loops : loops per frame.
    tx_of_chirp : TX index (order of :mod:`twinfocus.radar.fmcw`) fired by each chirp of a loop;
        default chirp c -> TX c, TI's default ``TxToEnable = [12 11 ... 1]``.
    timestamp_unit_ns : nanoseconds per tick of the index files' time stamps (default 1000:
        microseconds, the TDA2 Vision SDK's buffer time stamps).
    frame_period_s : nominal frame period (0.1 s in the paper); used to flag device skew.
    profile : the chirp profile of the capture's configuration (None: there was none).
    """

    chirp: Chirp = field(default_factory=Chirp)
    n_chirps: int = N_TX
    n_loops: int = 1
    tx_of_chirp: tuple[int, ...] = tuple(range(N_TX))
    timestamp_unit_ns: int = 1000
    frame_period_s: float | None = 0.1
    profile: Profile | None = None

    def __post_init__(self) -> None:
        if int(self.n_chirps) < 1 or int(self.n_loops) < 1:
            raise TwinFocusError(f"n_chirps and n_loops must be >= 1, got {self.n_chirps}, {self.n_loops}")
        tx = tuple(int(t) for t in self.tx_of_chirp)
        if len(tx) != int(self.n_chirps):
            raise TwinFocusError(f"tx_of_chirp lists {len(tx)} TX but there are {self.n_chirps} chirps per loop")
        if len(set(tx)) != len(tx) or min(tx) < 0 or max(tx) >= N_TX:
            raise TwinFocusError(f"tx_of_chirp must name distinct TX in 0..{N_TX - 1}, got {tx}")
        object.__setattr__(self, "tx_of_chirp", tx)
        if int(self.timestamp_unit_ns) < 1:
            raise TwinFocusError(f"timestamp_unit_ns must be a positive integer, got {self.timestamp_unit_ns}")

    @property
    def n_samples(self) -> int:
        return int(self.chirp.n_samples)

    @property
    def device_frame_values(self) -> int:
        """int16 values in one device's frame: loops x chirps x samples x 4 RX x (I, Q)."""
        return int(self.n_loops) * int(self.n_chirps) * self.n_samples * RX_PER_DEVICE * 2

    @property
    def device_frame_bytes(self) -> int:
        return 2 * self.device_frame_values


# --- index files ------------------------------------------------------------------------------


@dataclass
class IndexFile:
    """One ``*_idx.bin`` file: its header and the entries of its complete frames."""

    path: Path
    header: np.void
    entries: np.ndarray  # IDX_ENTRY_DTYPE (n,)
    warnings: list[str]


def read_index(path: str | os.PathLike) -> IndexFile:
    """Read a capture index file; malformed files raise, truncated ones warn.

    Raises :class:`TwinFocusError` when the file is missing, shorter than its header, has the
    wrong tag, or its first entry is not an index entry. A last entry cut short, entries the
    header does not count, or an entry with a bad tag end the list with a warning.
    """
    path = Path(path)
    if not path.is_file():
        raise TwinFocusError(f"{path}: no such index file")
    raw = path.read_bytes()
    if len(raw) < IDX_HEADER_DTYPE.itemsize:
        raise TwinFocusError(
            f"{path}: index file is {len(raw)} bytes, shorter than its {IDX_HEADER_DTYPE.itemsize}-byte header"
        )
    header = np.frombuffer(raw, IDX_HEADER_DTYPE, count=1)[0]
    if int(header["tag"]) != INFO_TAG:
        raise TwinFocusError(
            f"{path}: not a TI capture index file (header tag 0x{int(header['tag']):08x}, expected 0x{INFO_TAG:08x} 'bckt')"
        )
    warnings: list[str] = []
    body = len(raw) - IDX_HEADER_DTYPE.itemsize
    n_complete, partial = divmod(body, IDX_ENTRY_DTYPE.itemsize)
    if partial:
        warnings.append(f"{path.name}: last index entry is cut short ({partial} of {IDX_ENTRY_DTYPE.itemsize} bytes)")
    entries = np.frombuffer(raw, IDX_ENTRY_DTYPE, count=n_complete, offset=IDX_HEADER_DTYPE.itemsize)
    num_idx = int(header["num_idx"])
    if num_idx < n_complete:
        entries = entries[:num_idx]
    elif num_idx > n_complete:
        warnings.append(f"{path.name}: header counts {num_idx} frames but the file holds {n_complete} entries")
    bad = np.flatnonzero(entries["tag"] != BUFF_IDX_TAG)
    if bad.size:
        if bad[0] == 0:
            raise TwinFocusError(
                f"{path}: first index entry has tag 0x{int(entries['tag'][0]):04x}, expected 0x{BUFF_IDX_TAG:04x} 'id'"
            )
        warnings.append(f"{path.name}: index entry {int(bad[0])} has a bad tag; entries from there on are ignored")
        entries = entries[: bad[0]]
    return IndexFile(path, header, entries.copy(), warnings)


# --- frame decoding ---------------------------------------------------------------------------


def decode_device_frame(raw: np.ndarray, config: MmwcasConfig) -> np.ndarray:
    """One device's frame as complex samples.

    raw : int16 (..., device_frame_values), I/Q pairs, RX fastest, then sample, chirp, loop.
    Returns complex64 (..., n_loops, n_chirps, N, 4): [loop, chirp, sample, device RX].
    """
    raw = np.asarray(raw)
    lead = raw.shape[:-1]
    if raw.shape[-1] != config.device_frame_values:
        raise TwinFocusError(
            f"device frame holds {raw.shape[-1]} int16 values, the configuration expects {config.device_frame_values}"
        )
    pairs = np.ascontiguousarray(raw, dtype=np.int16).astype(np.float32).reshape(*lead, -1, 2)
    iq = pairs.view(np.complex64)[..., 0]
    return iq.reshape(*lead, config.n_loops, config.n_chirps, config.n_samples, RX_PER_DEVICE)


def assemble_cascade_frame(devices: np.ndarray, config: MmwcasConfig) -> np.ndarray:
    """The four devices' frames as one MIMO frame in array order.

    devices : complex (4, n_loops, n_chirps, N, 4) from :func:`decode_device_frame`, in the
        order master, slave1, slave2, slave3.
    Returns complex64 (n_loops, 12, 16, N): [loop, TX, RX, sample]; TX that no chirp fires are 0.
    """
    devices = np.asarray(devices)
    want = (len(DEVICES), config.n_loops, config.n_chirps, config.n_samples, RX_PER_DEVICE)
    if devices.shape != want:
        raise TwinFocusError(f"device frames must have shape {want}, got {devices.shape}")
    # (dev, loop, chirp, sample, rx) -> (loop, chirp, dev, rx, sample) -> data channel = 4 dev + rx
    x = devices.transpose(1, 2, 0, 4, 3).reshape(config.n_loops, config.n_chirps, N_RX, config.n_samples)
    x = x[:, :, RX_ARRAY_ORDER, :]
    out = np.zeros((config.n_loops, N_TX, N_RX, config.n_samples), dtype=np.complex64)
    out[:, list(config.tx_of_chirp)] = x
    return out


def cascade_frame_to_device_iq(frame_iq: np.ndarray, config: MmwcasConfig) -> np.ndarray:
    """Inverse of decode + assemble, on integers: what each device writes for a frame.

    frame_iq : int16 (n_loops, 12, 16, N, 2), (I, Q) of every [loop, TX, RX (array order), sample].
    Returns int16 (4, device_frame_values), the data-file bytes of master, slave1..3.
    """
    frame_iq = np.asarray(frame_iq)
    want = (config.n_loops, N_TX, N_RX, config.n_samples, 2)
    if frame_iq.shape != want:
        raise TwinFocusError(f"frame I/Q must have shape {want}, got {frame_iq.shape}")
    if frame_iq.dtype != np.int16:
        raise TwinFocusError(f"frame I/Q must be int16, got {frame_iq.dtype}")
    chirps = frame_iq[:, list(config.tx_of_chirp)]  # (loop, chirp, array RX, sample, 2)
    data_ch = np.empty_like(chirps)
    data_ch[:, :, RX_ARRAY_ORDER] = chirps  # back to data-channel order
    x = data_ch.reshape(config.n_loops, config.n_chirps, len(DEVICES), RX_PER_DEVICE, config.n_samples, 2)
    # (loop, chirp, dev, rx, sample, iq) -> (dev, loop, chirp, sample, rx, iq)
    x = x.transpose(2, 0, 1, 4, 3, 5)
    return np.ascontiguousarray(x).reshape(len(DEVICES), -1)


# --- the capture's configuration ------------------------------------------------------------

#: Units a capture's index time stamps might be in, nanoseconds per tick, and their names.
TIMESTAMP_UNITS = {1: "ns", 1000: "us", 1_000_000: "ms"}


def check_timestamp_unit(master_ticks: np.ndarray, unit_ns: int, frame_period_s: float | None) -> None:
    """Refuse a time-stamp unit that does not fit the frame period, naming the one that does.

    master_ticks : int64 (F,) the master's index stamps, in ticks; unit_ns : the unit assumed;
    frame_period_s : nominal period (None: nothing to check against). The median tick spacing
    times each candidate unit (ns, us, ms, a factor 1000 apart) is compared with the period on a
    log scale: the assumed unit is refused when it is more than a factor 30 off (a nominal period
    that is merely wrong, 100 ms for a 33 ms capture, passes) and the unit that lands nearest is
    named.
    """
    t = np.asarray(master_ticks, np.int64)
    if frame_period_s is None or t.size < 3:
        return
    step = float(np.median(np.diff(t)))
    if step <= 0:
        raise TwinFocusError(f"the master's index time stamps do not increase (median step {step:g} ticks)")

    def off(u: int) -> float:
        return abs(np.log10(step * u * 1e-9 / frame_period_s))

    if off(int(unit_ns)) <= 1.5:
        return
    best = min(TIMESTAMP_UNITS, key=off)
    have = f"{step * unit_ns * 1e-9:.6g} s per frame with {unit_ns} ns per tick"
    if off(best) <= 1.5:
        raise TwinFocusError(
            f"index time stamps advance {step:.6g} ticks per frame: {have}, but the frame period is {frame_period_s * 1e3:g} ms; "
            f"the stamps are in {TIMESTAMP_UNITS[best]} (--timestamp-unit-ns {best})"
        )
    raise TwinFocusError(
        f"index time stamps advance {step:.6g} ticks per frame: {have}; no unit (ns, us, ms) fits the frame period "
        f"{frame_period_s * 1e3:g} ms; check --frame-period-s"
    )


def tx_order_to_tx_of_chirp(tx_numbers) -> tuple[int, ...]:
    """TI's ``TxToEnable`` (TX numbers 1..12 in chirp order) -> ``tx_of_chirp`` (0-based, order of
    :mod:`twinfocus.radar.fmcw`). The default ``[12 11 ... 1]`` maps chirp c to TX c, so TI TX n is
    index 12 - n."""
    nums = [int(n) for n in tx_numbers]
    bad = [n for n in nums if not 1 <= n <= N_TX]
    if bad or len(set(nums)) != len(nums) or not nums:
        raise TwinFocusError(f"TX order must list distinct TX numbers 1..{N_TX}, got {nums}")
    return tuple(N_TX - n for n in nums)


def parse_tx_order(text: str) -> tuple[int, ...]:
    """``"12,11,10"`` or ``"[12 11 10]"`` (MATLAB form) -> TX numbers."""
    parts = re.split(r"[\s,;]+", str(text).strip().strip("[]").strip())
    try:
        return tuple(int(p) for p in parts if p)
    except ValueError:
        raise TwinFocusError(f"TX order must be TX numbers 1..12 separated by commas, got {text!r}") from None


def _num(v) -> float:
    return float(int(v, 16)) if isinstance(v, str) and v.lower().startswith("0x") else float(v)


def read_studio_json(path: str | os.PathLike) -> dict:
    """The chirp layout of an mmWave Studio configuration JSON (``*.mmwave.json``).

    Keys followed (mmWave Studio's JSON export; the mmwavelink names ``rlFrameCfg_t``,
    ``rlChirpCfg_t``, ``rlProfileCfg_t``): ``mmWaveDevices[d].rfConfig.rlFrameCfg_t``
    (``chirpStartIdx``, ``chirpEndIdx``, ``numLoops``, ``framePeriodicity_msec``),
    ``rlChirps[].rlChirpCfg_t`` (``chirpStartIdx``, ``chirpEndIdx``, ``txEnable``) per device,
    the chirps' profile in ``rlProfiles[].rlProfileCfg_t`` (:mod:`twinfocus.sensors.chirp_profile`),
    ``rawDataCaptureConfig.rlDevDataFmtCfg_t``.
    Device d (``devId`` 0..3: master, slave1..3) TX bit b is cascade TX ``3 d + b + 1`` (TI's
    cascade Lua enables TX12 as device 4's TX3 for the first chirp of the default order).

    Returns {tx_numbers, n_loops, frame_period_s, n_samples, profile (the chirp profile's fields),
    iq_swap, ch_interleave, source}.
    """
    path = Path(path)
    try:
        doc = __import__("json").loads(path.read_text())
        devs = doc["mmWaveDevices"]
        devs = sorted(devs, key=lambda d: int(d.get("mmWaveDeviceId", d.get("devId", 0))))
        rf0 = devs[0]["rfConfig"]
        frame = rf0["rlFrameCfg_t"]
        c0, c1 = int(_num(frame["chirpStartIdx"])), int(_num(frame["chirpEndIdx"]))
        tx_numbers = []
        profile_ids = []
        for c in range(c0, c1 + 1):
            fired = []
            for d, dev in enumerate(devs):
                for ch in dev["rfConfig"].get("rlChirps", []):
                    cc = ch.get("rlChirpCfg_t", ch)
                    if int(_num(cc["chirpStartIdx"])) <= c <= int(_num(cc["chirpEndIdx"])):
                        profile_ids.append(int(_num(cc.get("profileId", 0))))
                        mask = int(_num(cc["txEnable"]))
                        fired += [3 * d + b + 1 for b in range(3) if mask >> b & 1]
            if len(fired) != 1:
                raise TwinFocusError(f"{path}: chirp {c} fires TX {fired}; TDM-MIMO needs exactly one TX per chirp")
            tx_numbers.append(fired[0])
        fmt = devs[0].get("rawDataCaptureConfig", {}).get("rlDevDataFmtCfg_t", {})
        profile = profile_fields_from_studio_json(rf0, profile_ids[0] if len(set(profile_ids)) == 1 else None)
        return {
            "tx_numbers": tuple(tx_numbers),
            "n_loops": int(_num(frame["numLoops"])),
            "frame_period_s": _num(frame["framePeriodicity_msec"]) * 1e-3,
            "n_samples": int(profile["n_samples"]),
            "profile": profile,
            "iq_swap": int(_num(fmt.get("iqSwapSel", 0))),
            "ch_interleave": int(_num(fmt.get("chInterleave", 0))),
            "source": str(path),
        }
    except TwinFocusError:
        raise
    except (OSError, ValueError, KeyError, IndexError, TypeError) as exc:
        raise TwinFocusError(f"{path}: not a readable mmWave Studio JSON ({type(exc).__name__}: {exc})") from None


_LUA_ASSIGN = re.compile(
    r"^\s*(?:local\s+)?(nchirp_loops|Inter_Frame_Interval|start_chirp_tx|end_chirp_tx|adc_samples)\s*=\s*"
    r"([-+0-9.eE]+)",
    re.M,
)
_LUA_DEVICE_BLOCK = re.compile(r"\b(?:else)?if\s*\(?\s*i\s*==\s*(\d)\s*\)?\s*then")
_LUA_CHIRP = re.compile(
    r"ar1\.ChirpConfig_mult\(\s*([^,]+?)\s*,\s*(\d+)\s*,\s*(\d+)\s*,(?:\s*[-+0-9.]+\s*,){5}"
    r"\s*(\d)\s*,\s*(\d)\s*,\s*(\d)\s*\)"
)


def read_cascade_lua(path: str | os.PathLike) -> dict:
    """The chirp layout of TI's cascade setup Lua (mmWave Studio ``Cascade_Configuration_*.lua``).

    Followed as TI's script writes it: assignments ``nchirp_loops = 64``,
    ``Inter_Frame_Interval = 100`` (ms), ``start_chirp_tx = 0``, ``end_chirp_tx = 11``,
    ``adc_samples = 256``; the chirp profile of ``ar1.ProfileConfig_mult`` / ``ar1.ProfileConfig``
    (:func:`~twinfocus.sensors.chirp_profile.profile_fields_from_lua`); chirps ``ar1.ChirpConfig_mult(RadarDeviceId, chirpStartIdx,
    chirpEndIdx, profileId, startFreqVar, freqSlopeVar, idleTimeVar, adcStartTimeVar, tx0Enable,
    tx1Enable, tx2Enable)`` inside ``Configure_Chirps(i)``'s ``if (i == k) then`` blocks (device
    k - 1), or with a literal device mask 1, 2, 4, 8. Device d's TX b is cascade TX 3 d + b + 1.
    Returns the keys of :func:`read_studio_json` that the script sets.
    """
    path = Path(path)
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise TwinFocusError(f"{path}: cannot read ({exc.strerror})") from None
    text = re.sub(r"--\[\[.*?\]\]", "", text, flags=re.S)  # block comments (TI's chirp table)
    text = re.sub(r"--[^\n]*", "", text)
    vals = {k: float(v) for k, v in _LUA_ASSIGN.findall(text)}
    blocks = [(m.start(), int(m.group(1)) - 1) for m in _LUA_DEVICE_BLOCK.finditer(text)]
    fired: dict[int, list[int]] = {}
    for m in _LUA_CHIRP.finditer(text):
        dev_arg = m.group(1).strip()
        if dev_arg.isdigit() and int(dev_arg) in (1, 2, 4, 8):
            dev = int(dev_arg).bit_length() - 1
        else:
            before = [d for pos, d in blocks if pos < m.start()]
            if not before:
                continue  # a call for all devices at once (e.g. TX beamforming) gives no TDM order
            dev = before[-1]
        for c in range(int(m.group(2)), int(m.group(3)) + 1):
            fired.setdefault(c, [])
            fired[c] += [3 * dev + b + 1 for b in range(3) if m.group(4 + b) == "1"]
    c0 = int(vals.get("start_chirp_tx", min(fired) if fired else 0))
    c1 = int(vals.get("end_chirp_tx", max(fired) if fired else -1))
    out: dict = {"source": str(path)}
    if fired:
        tx = []
        for c in range(c0, c1 + 1):
            if len(fired.get(c, [])) != 1:
                raise TwinFocusError(
                    f"{path}: chirp {c} fires TX {fired.get(c, [])}; TDM-MIMO needs exactly one TX per chirp"
                )
            tx.append(fired[c][0])
        out["tx_numbers"] = tuple(tx)
    if "nchirp_loops" in vals:
        out["n_loops"] = int(vals["nchirp_loops"])
    if "Inter_Frame_Interval" in vals:
        out["frame_period_s"] = vals["Inter_Frame_Interval"] * 1e-3
    profile = profile_fields_from_lua(text, str(path))
    if profile:
        out["profile"] = profile
    if "n_samples" in profile:
        out["n_samples"] = int(profile["n_samples"])
    elif "adc_samples" in vals:
        out["n_samples"] = int(vals["adc_samples"])
    return out


def find_capture_setup(folder: str | os.PathLike) -> Path | None:
    """The capture's configuration: an mmWave Studio ``*.mmwave.json`` in the capture folder or
    its parent, else a cascade setup ``*.lua`` in the folder (None if none)."""
    folder = Path(folder)
    for where, pattern in ((folder, "*.mmwave.json"), (folder.parent, "*.mmwave.json"), (folder, "*.lua")):
        found = sorted(where.glob(pattern))
        if len(found) > 1:
            raise TwinFocusError(
                f"{where}: several capture configurations ({', '.join(p.name for p in found)}); name one with --setup"
            )
        if found:
            return found[0]
    return None


def read_capture_setup(path: str | os.PathLike) -> dict:
    """:func:`read_studio_json` or :func:`read_cascade_lua` by the file's name."""
    return read_cascade_lua(path) if str(path).endswith(".lua") else read_studio_json(path)


def resolve_config(
    folder,
    chirp: Chirp | None = None,
    n_loops: int | None = None,
    tx_order: str | None = None,
    frame_period_s: float | None = None,
    timestamp_unit_ns: int = 1000,
    setup: str | os.PathLike | None = None,
    f0_hz: float | None = None,
    slope_hz_per_s: float | None = None,
    fs_hz: float | None = None,
    n_samples: int | None = None,
) -> tuple[MmwcasConfig, list[str]]:
    """The capture's :class:`MmwcasConfig`: its configuration (``setup``, else what
    :func:`find_capture_setup` finds) where there is one, else the options; an option that
    disagrees with the configuration wins, with a note. The chirp is the configuration's
    profile (:func:`~twinfocus.sensors.chirp_profile.resolve_chirp`); ``f0_hz`` ...
    ``n_samples`` are its options, and a ``chirp`` given stands for all four of them.
    Returns (config, notes)."""
    notes: list[str] = []
    js = Path(setup) if setup else find_capture_setup(folder)
    got = read_capture_setup(js) if js else {}
    if js:
        notes.append(
            f"chirp layout from {js}: "
            + ", ".join(f"{k} {v}" for k, v in got.items() if k not in ("source", "profile"))
        )
        if got.get("iq_swap") or got.get("ch_interleave"):
            raise TwinFocusError(
                f"{js}: rlDevDataFmtCfg_t iqSwapSel={got['iq_swap']} chInterleave={got['ch_interleave']}; only I-first, "
                "non-interleaved samples (both 0, the cascade default) are read"
            )

    def pick(name, option, default):
        if option is not None:
            if name in got and got[name] != option:
                notes.append(f"--{name.replace('_', '-')} {option} overrides the configuration's {got[name]}")
            return option
        return got.get(name, default)

    tx_numbers = pick("tx_numbers", parse_tx_order(tx_order) if tx_order else None, tuple(range(N_TX, 0, -1)))
    fields = dict(got.get("profile", {}))
    if "n_samples" in got:
        fields.setdefault("n_samples", got["n_samples"])
    if chirp is not None:
        f0_hz = chirp.f0_hz if f0_hz is None else f0_hz
        slope_hz_per_s = chirp.slope_hz_per_s if slope_hz_per_s is None else slope_hz_per_s
        fs_hz = chirp.fs_hz if fs_hz is None else fs_hz
        n_samples = chirp.n_samples if n_samples is None else n_samples
    the_chirp, profile, chirp_notes = resolve_chirp(
        fields, str(js) if js else None, f0_hz, slope_hz_per_s, fs_hz, n_samples
    )
    if js:
        notes.append(f"chirp from {js}: {describe_chirp(profile_chirp(profile))}")
        lacking = [
            k
            for k in ("start_freq_ghz", "adc_start_time_us", "slope_mhz_per_us", "sample_rate_ksps")
            if k not in fields
        ]
        if lacking:
            notes.append(f"{js} gives no {', '.join(lacking)}: the chirp options or the defaults stand in for them")
    notes += chirp_notes
    tx = tx_order_to_tx_of_chirp(tx_numbers)
    config = MmwcasConfig(
        chirp=the_chirp,
        profile=profile if js else None,
        n_chirps=len(tx),
        n_loops=pick("n_loops", n_loops, 1),
        tx_of_chirp=tx,
        timestamp_unit_ns=timestamp_unit_ns,
        frame_period_s=pick("frame_period_s", frame_period_s, 0.1),
    )
    return config, notes


# --- captures ---------------------------------------------------------------------------------


def _missing_before(stamps_ns: np.ndarray, frame_period_s: float | None) -> np.ndarray:
    """Frames missing before each frame, cumulative: int64 (F,).

    stamps_ns : int64 (F,) the frames' time stamps. A step of k frame periods (k >= 2, rounded)
    between two frames means k - 1 frames were never written. The period is the median step when
    there are at least three frames (a nominal period that is wrong does not count frames), else
    ``frame_period_s`` (None: nothing is counted).
    """
    t = np.asarray(stamps_ns, np.int64)
    if t.size < 2:
        return np.zeros(t.size, np.int64)
    steps = np.diff(t).astype(np.float64)
    period = float(np.median(steps)) if t.size >= 3 else (frame_period_s or 0.0) * 1e9
    if not period > 0:
        return np.zeros(t.size, np.int64)
    lost = np.where(steps >= 1.5 * period, np.rint(steps / period) - 1, 0).astype(np.int64)
    return np.concatenate([[0], np.cumsum(lost)])


@dataclass(frozen=True)
class _FrameRef:
    slice_pos: int
    local: int
    offsets: tuple[int, ...]
    stamp_ns: int
    flags: FrameFlag


class MmwcasCapture:
    """A folder of MMWCAS captures, read frame by frame.

    Parameters
    ----------
    folder : the capture folder (all slices ``0000``, ``0001``, ... found there, in order).
    config : :class:`MmwcasConfig` describing the frames.
    skip_first_frame : drop the capture card's first frame, known to be bad (default True).

    Attributes
    ----------
    timestamps_ns : int64 (F,), capture times of the frames (the master's index time stamps in
        the capture card's clock, which starts at the DSP board's boot, not the epoch).
    warnings : what was cut or ignored (truncated files, uncounted entries, device skew).

    Use as ``with MmwcasCapture(folder, cfg) as cap: for frame in cap.frames(): ...``.
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        config: MmwcasConfig | None = None,
        skip_first_frame: bool = True,
        skip_first_frame_of_each_slice: bool = False,
    ):
        self.folder = Path(folder)
        self.config = config or MmwcasConfig()
        self.warnings: list[str] = []
        if not self.folder.is_dir():
            raise TwinFocusError(f"{self.folder}: no such capture folder")
        slices = sorted(m.group(1) for p in self.folder.iterdir() if (m := _SLICE_RE.match(p.name)))
        if not slices:
            raise TwinFocusError(
                f"{self.folder}: no MMWCAS capture here (expected master_0000_idx.bin and master_0000_data.bin, "
                "slave1_..., slave2_..., slave3_...)"
            )
        self._data_paths: list[list[Path]] = []
        self._maps: list[list[np.ndarray | None]] = []
        refs: list[_FrameRef] = []
        raw: list[tuple[int, int, tuple[int, ...], list[int]]] = []
        fb = self.config.device_frame_bytes
        for pos, sid in enumerate(slices):
            raw += self._index_slice(pos, sid, fb)
        # TI's cascade processing (cascade_MIMO_signalProcessing.m) skips the first frame of every
        # slice file it reads; the capture card writes slices back to back, so only the capture's
        # very first frame is known bad and that is all the default drops (docs/sensors.md).
        first_of_slice = {(pos, 0) for pos in range(len(slices))}
        # Frames dropped on purpose are not gaps: missing frames are counted over the frames the
        # card indexed, less only the capture's first.
        indexed = raw[1:] if (skip_first_frame or skip_first_frame_of_each_slice) else list(raw)
        missing_before = _missing_before(
            np.array([r[3][0] for r in indexed], dtype=np.int64) * int(self.config.timestamp_unit_ns),
            self.config.frame_period_s,
        )
        missing_of = {(r[0], r[1]): int(n) for r, n in zip(indexed, missing_before)}
        if skip_first_frame_of_each_slice:
            raw = [r for r in raw if (r[0], r[1]) not in first_of_slice]
        elif skip_first_frame and raw:
            raw = raw[1:]
        unit = int(self.config.timestamp_unit_ns)
        master = np.array([r[3][0] for r in raw], dtype=np.int64)
        check_timestamp_unit(master, unit, self.config.frame_period_s)
        # A slave one frame late is one frame period off; half the period is the threshold. The
        # period is measured from the master's stamps (median spacing) when there are enough, so
        # a 33 ms capture is checked at 33 ms whatever the configuration's nominal period.
        period_ns = None if self.config.frame_period_s is None else self.config.frame_period_s * 1e9
        if master.size >= 3:
            measured = float(np.median(np.diff(master))) * unit
            if measured > 0:
                period_ns = measured if period_ns is None else min(period_ns, measured)
        for pos, i, offs, ticks in raw:
            stamps_ns = np.array(ticks, dtype=np.int64) * unit
            flags = FrameFlag.OK
            if period_ns is not None and stamps_ns.max() - stamps_ns.min() > period_ns / 2:
                flags |= FrameFlag.DEVICE_SKEW
            refs.append(_FrameRef(pos, i, offs, int(stamps_ns[0]), flags))
        self._refs = [self._flag_if_zero(r) for r in refs]
        refs = self._refs
        skewed = sum(1 for r in refs if r.flags & FrameFlag.DEVICE_SKEW)
        if skewed:
            self.warnings.append(f"{skewed} frame(s) have device time stamps more than half a frame period apart")
        zero = [k for k, r in enumerate(refs) if r.flags & FrameFlag.ZERO_FILLED]
        if zero:
            self.warnings.append(
                f"{len(zero)} frame(s) hold only zeros on some device (frame {', '.join(map(str, zero[:5]))}"
                f"{', ...' if len(zero) > 5 else ''}): the capture card wrote them without data"
            )
        self.timestamps_ns = np.array([r.stamp_ns for r in refs], dtype=np.int64)
        self.flags = np.array([int(r.flags) for r in refs], dtype=np.int64)
        #: int64 (F,): frames missing from every device (time stamps two or more frame periods
        #: apart) between the capture's start and frame i.
        self.frames_missing_before = np.array([missing_of.get((r.slice_pos, r.local), 0) for r in refs], np.int64)
        self.frames_missing = int(missing_before[-1]) if missing_before.size else 0
        if self.frames_missing:
            self.warnings.append(
                f"{self.frames_missing} frame(s) missing from every device (index time stamps jump by two or more "
                "frame periods)"
            )

    def _index_slice(self, pos: int, sid: str, fb: int) -> list[tuple[int, int, tuple[int, ...], list[int]]]:
        """The frames of capture slice ``sid`` (the ``pos``-th) that all four devices hold whole:
        (pos, frame in the slice, each device's byte offset, each device's time stamp ticks).
        Reads the slice's index files, notes its data files and adds its warnings."""
        frames: list[tuple[int, int, tuple[int, ...], list[int]]] = []
        idx_files, data_paths, sizes = [], [], []
        for dev in DEVICES:
            ip = self.folder / f"{dev}_{sid}_idx.bin"
            dp = self.folder / f"{dev}_{sid}_data.bin"
            for p in (ip, dp):
                if not p.is_file():
                    raise TwinFocusError(
                        f"{p}: missing; a capture slice needs the data and index files of all four devices"
                    )
            idx = read_index(ip)
            self.warnings.extend(idx.warnings)
            idx_files.append(idx)
            data_paths.append(dp)
            sizes.append(dp.stat().st_size)
        self._data_paths.append(data_paths)
        self._maps.append([None] * len(DEVICES))
        n = min(len(i.entries) for i in idx_files)
        counts = [len(i.entries) for i in idx_files]
        if len(set(counts)) > 1:
            self.warnings.append(f"slice {sid}: devices index {counts} frames; only the first {n} are used")
        for _dev, idx in zip(DEVICES, idx_files):
            sz = idx.entries["size"][:n]
            wrong = np.flatnonzero(sz != fb)
            if wrong.size:
                i = int(wrong[0])
                raise TwinFocusError(
                    f"{idx.path}: frame {i} is {int(sz[i])} bytes but the configuration expects {fb} "
                    f"({self.config.n_loops} loops x {self.config.n_chirps} chirps x {self.config.n_samples} "
                    f"samples x 4 RX x 4 bytes); check n_samples, n_chirps and n_loops"
                )
        for i in range(n):
            offs = tuple(int(idx_files[d].entries["offset"][i]) for d in range(len(DEVICES)))
            cut = [DEVICES[d] for d in range(len(DEVICES)) if offs[d] + fb > sizes[d]]
            if cut:
                self.warnings.append(
                    f"slice {sid}: data files of {', '.join(cut)} end inside frame {i}; "
                    f"{n - i} indexed frame(s) from there on are dropped (truncated capture)"
                )
                break
            ticks = [int(idx_files[d].entries["timestamp"][i]) for d in range(len(DEVICES))]
            if max(ticks) >= (1 << 63) // int(self.config.timestamp_unit_ns):
                raise TwinFocusError(
                    f"slice {sid} frame {i}: time stamp {max(ticks)} does not fit nanoseconds in 64 bits "
                    f"(timestamp_unit_ns = {self.config.timestamp_unit_ns}); is the index file damaged?"
                )
            frames.append((pos, i, offs, ticks))
        return frames

    def _flag_if_zero(self, ref: _FrameRef) -> _FrameRef:
        """The frame, flagged ZERO_FILLED when a device's first loop is all zeros (a real ADC
        frame always holds noise). Only the first loop is read, to keep opening a long capture cheap."""
        n = int(self.config.n_chirps) * self.config.n_samples * RX_PER_DEVICE * 4
        for d in range(len(DEVICES)):
            if not np.asarray(self._map(ref.slice_pos, d)[ref.offsets[d] : ref.offsets[d] + n]).any():
                return _FrameRef(ref.slice_pos, ref.local, ref.offsets, ref.stamp_ns, ref.flags | FrameFlag.ZERO_FILLED)
        return ref

    # -- access --------------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._refs)

    def __enter__(self) -> MmwcasCapture:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Release the memory maps of the data files."""
        for maps in self._maps:
            for d in range(len(maps)):
                maps[d] = None

    def _map(self, slice_pos: int, dev: int) -> np.ndarray:
        m = self._maps[slice_pos][dev]
        if m is None:
            m = np.memmap(self._data_paths[slice_pos][dev], dtype=np.uint8, mode="r")
            self._maps[slice_pos][dev] = m
        return m

    def read_raw(self, i: int) -> np.ndarray:
        """The four devices' raw frame ``i`` exactly as stored: int16 (4, device_frame_values)."""
        ref = self._ref(i)
        fb = self.config.device_frame_bytes
        out = np.empty((len(DEVICES), self.config.device_frame_values), dtype=np.int16)
        for d in range(len(DEVICES)):
            m = self._map(ref.slice_pos, d)
            out[d] = m[ref.offsets[d] : ref.offsets[d] + fb].view("<i2")
        return out

    def read_frame(self, i: int) -> np.ndarray:
        """Frame ``i`` with every loop: complex64 (n_loops, 12, 16, N), array order."""
        return assemble_cascade_frame(decode_device_frame(self.read_raw(i), self.config), self.config)

    def __getitem__(self, i: int) -> RadarFrame:
        """Frame ``i`` (its first loop) as a :class:`RadarFrame`."""
        return RadarFrame(
            int(self.timestamps_ns[self._index(i)]), self.read_frame(i)[0], FrameFlag(int(self.flags[self._index(i)]))
        )

    def _index(self, i: int) -> int:
        self._ref(i)
        return int(i) % len(self)

    def frames(self, loop: int | None = 0, start: int = 0, stop: int | None = None) -> Iterator[RadarFrame]:
        """Yield :class:`RadarFrame` (stamp_ns, complex64 (12, 16, N), flags) in capture order.

        loop : which loop of each frame to give; None averages the loops (coherent sum / L).
        """
        stop = len(self) if stop is None else min(int(stop), len(self))
        if loop is not None and not 0 <= int(loop) < self.config.n_loops:
            raise TwinFocusError(f"loop must be in 0..{self.config.n_loops - 1} or None, got {loop}")
        for i in range(int(start), stop):
            f = self.read_frame(i)
            data = f.mean(axis=0).astype(np.complex64) if loop is None else f[int(loop)]
            yield RadarFrame(int(self.timestamps_ns[i]), data, FrameFlag(int(self.flags[i])))

    def _ref(self, i: int) -> _FrameRef:
        if not -len(self) <= int(i) < len(self):
            raise TwinFocusError(f"frame {i} is out of range: the capture holds {len(self)} frame(s)")
        return self._refs[int(i)]
