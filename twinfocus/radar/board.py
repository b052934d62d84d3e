"""A radar board's antennas from a board description file (YAML) a user can replace.

The file gives, in half wavelengths at the board's design frequency, where each TX and RX antenna
lies, numbered as TI numbers them (TX n, RX data channel c), and where the TX group lies relative
to the RX group, in wavelengths. The default is ``twinfocus/radar/boards/mmwcas_rf_evm.yaml`` (TI's
MMWCAS-RF-EVM, from TI's ``module_param.m``). Keys::

    name: MMWCAS-RF-EVM
    design_frequency_hz: 76.8e9
    tx_along_half_wavelengths: [...]      # 12 values, TX1..TX12
    tx_across_half_wavelengths: [...]     # 12
    rx_along_half_wavelengths: [...]      # 16 values, data channels 1..16
    rx_across_half_wavelengths: [...]     # 16
    tx_offset_wavelengths: [8, 17]        # TX position 0 relative to RX position 0 (along, across)

The board frame is (along the array, across it), metres; :mod:`twinfocus.radar.fmcw` builds the
virtual array from it.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.io.documents import read_yaml

C_M_PER_S = 299_792_458.0

#: The board file used when none is named.
DEFAULT_BOARD_FILE = Path(__file__).parent / "boards" / "mmwcas_rf_evm.yaml"

#: Antennas the cascade readers (:mod:`twinfocus.sensors.ti_mmwcas`) place: 12 TX, 16 RX.
N_TX = 12
N_RX = 16

#: Board-file index of TX t in the order of :mod:`twinfocus.radar.fmcw`: TX t is TI's TX 12 - t.
TX_ARRAY_ORDER = np.arange(N_TX)[::-1].copy()
#: Data channel (0-based; 4 x device + device RX) of RX a, the a-th RX along the MMWCAS board:
#: TI's ``TI_Cascade_RX_ID`` - 1.
RX_ARRAY_ORDER = np.array([13, 14, 15, 16, 1, 2, 3, 4, 9, 10, 11, 12, 5, 6, 7, 8]) - 1

_LISTS = {
    "tx_along_half_wavelengths": N_TX,
    "tx_across_half_wavelengths": N_TX,
    "rx_along_half_wavelengths": N_RX,
    "rx_across_half_wavelengths": N_RX,
    "tx_offset_wavelengths": 2,
}
_KEYS = {"name", "design_frequency_hz", *_LISTS}


@dataclass(frozen=True)
class Board:
    """A board's antenna layout (values as the file gives them; tuples so a board is hashable).

    tx_* : (12,) half wavelengths, TX1..TX12; rx_* : (16,) half wavelengths, data channels 1..16;
    tx_offset_wavelengths : (along, across) of TX position 0 relative to RX position 0.
    """

    name: str
    design_frequency_hz: float
    tx_along_half_wavelengths: tuple[float, ...]
    tx_across_half_wavelengths: tuple[float, ...]
    rx_along_half_wavelengths: tuple[float, ...]
    rx_across_half_wavelengths: tuple[float, ...]
    tx_offset_wavelengths: tuple[float, float]
    source: str = ""

    @property
    def design_wavelength_m(self) -> float:
        """c / design frequency, metres (3.9035 mm for the MMWCAS-RF-EVM's 76.8 GHz)."""
        return C_M_PER_S / self.design_frequency_hz

    def tx_positions_m(self) -> np.ndarray:
        """TX positions in the board frame, float64 (12, 2) (along, across), TI's order TX1..TX12."""
        half = self.design_wavelength_m / 2.0
        off = np.asarray(self.tx_offset_wavelengths) * self.design_wavelength_m
        return (
            np.stack([np.asarray(self.tx_along_half_wavelengths), np.asarray(self.tx_across_half_wavelengths)], 1)
            * half
            + off
        )

    def rx_positions_m(self) -> np.ndarray:
        """RX positions in the board frame, float64 (16, 2) (along, across), data channels 1..16."""
        half = self.design_wavelength_m / 2.0
        return (
            np.stack([np.asarray(self.rx_along_half_wavelengths), np.asarray(self.rx_across_half_wavelengths)], 1)
            * half
        )

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "file": self.source,
            "design_frequency_hz": self.design_frequency_hz,
            "tx_offset_wavelengths": list(self.tx_offset_wavelengths),
        }


def load_board(path: str | os.PathLike | None = None) -> Board:
    """Read and check a board file (None: the default board). Any problem is one
    :class:`TwinFocusError` line naming the file and the key."""
    return default_board() if path is None else _load(str(path))


@functools.lru_cache(maxsize=1)
def default_board() -> Board:
    """The board used when none is named (``twinfocus/radar/boards/mmwcas_rf_evm.yaml``), read once."""
    return _load(str(DEFAULT_BOARD_FILE))


def _load(path: str) -> Board:
    import yaml

    p = Path(path)
    try:
        doc = read_yaml(p)
    except OSError as exc:
        raise TwinFocusError(f"{p}: cannot read the board file ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        line = f" (line {where.line + 1})" if where is not None else ""
        raise TwinFocusError(f"{p}: not a YAML board file{line}") from None
    if not isinstance(doc, dict):
        raise TwinFocusError(f"{p}: a board file is a mapping of keys {sorted(_KEYS)}")
    unknown = sorted(set(doc) - _KEYS)
    missing = sorted(_KEYS - set(doc))
    if unknown:
        raise TwinFocusError(f"{p}: unknown board key(s) {', '.join(unknown)}; the keys are {', '.join(sorted(_KEYS))}")
    if missing:
        raise TwinFocusError(f"{p}: board file lacks {', '.join(missing)}")
    try:
        freq = float(doc["design_frequency_hz"])
    except (TypeError, ValueError):
        freq = float("nan")
    if not 1e9 <= freq <= 1e12:
        raise TwinFocusError(
            f"{p}: design_frequency_hz must be a frequency in Hz (e.g. 76.8e9), got {doc['design_frequency_hz']!r}"
        )
    lists = {}
    for key, n in _LISTS.items():
        v = doc[key]
        try:
            arr = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            arr = np.array([np.nan])
        if arr.shape != (n,) or not np.all(np.isfinite(arr)):
            raise TwinFocusError(f"{p}: {key} must be a list of {n} numbers, got {v!r}")
        lists[key] = tuple(float(x) for x in arr)
    board = Board(str(doc["name"]), freq, **lists, source=str(p))  # type: ignore[arg-type]
    tx, rx = board.tx_positions_m(), board.rx_positions_m()
    for what, pos in (("TX", tx), ("RX", rx)):
        if len({(round(a, 12), round(b, 12)) for a, b in pos}) != len(pos):
            raise TwinFocusError(f"{p}: two {what} antennas share a position")
    return board
