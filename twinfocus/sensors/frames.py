"""One radar frame as the drivers hand it on, and its step to the virtual channels of a scan.

A MIMO frame holds, for one radar position, the IF samples of every TX-RX pair:
complex64 (n_tx, n_rx, N). In TDM-MIMO each TX fires its own chirp, so pair (t, r) sees the
bistatic path R_tx + R_rx; the monostatic-equivalent phase centre of the pair is the midpoint of
its two antennas (docs/architecture.md section 2). :func:`frame_to_virtual_channels` picks the pairs of a
:class:`~twinfocus.radar.fmcw.VirtualArray` and applies the multistatic-to-monostatic correction, giving
the (K, N) rows of a scan file's ``data``.
"""

from __future__ import annotations

import enum
from typing import NamedTuple

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.radar.board import Board
from twinfocus.radar.fmcw import (
    Chirp,
    VirtualArray,
    mmwcas_rx_positions_m,
    mmwcas_tx_positions_m,
    mmwcas_virtual_array,
    multistatic_to_monostatic,
)


class FrameFlag(enum.IntFlag):
    """What went wrong while a frame was captured (0 = nothing)."""

    OK = 0
    #: Some bytes of the frame never arrived; zeros stand in for them (MMWCAS: a device's
    #: samples of the frame are all zero).
    ZERO_FILLED = 1
    #: No byte of the frame arrived at all (the frame is all zeros).
    LOST = 2
    #: Packets of the frame arrived out of order (the data are complete and in place).
    REORDERED = 4
    #: The cascade devices' capture time stamps for this frame disagree by more than half a
    #: frame period (a slave skipped or repeated a frame).
    DEVICE_SKEW = 8

    @property
    def usable(self) -> bool:
        """True when the samples are all real measurements (reordering is harmless)."""
        return not (self & (FrameFlag.ZERO_FILLED | FrameFlag.LOST | FrameFlag.DEVICE_SKEW))


class RadarFrame(NamedTuple):
    """One radar frame.

    stamp_ns : int, capture time, nanoseconds (the clock is the source's: the capture card's for
        MMWCAS files, the host's receive time for DCA1000 streams).
    data : complex64 (n_tx, n_rx, N), IF samples of every TX-RX pair, TX and RX in the array
        order of :mod:`twinfocus.radar.fmcw` (MMWCAS: 12 x 16, ascending along the board).
    flags : :class:`FrameFlag`.
    """

    stamp_ns: int
    data: np.ndarray
    flags: FrameFlag


def mmwcas_antenna_positions_body_m(
    array: VirtualArray | None = None, board: Board | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """TX and RX antenna positions of the MMWCAS board (``board``: a board file's, default TI's)
    in the radar body frame; ``array`` default the board's :func:`~twinfocus.radar.fmcw.mmwcas_virtual_array`.

    The body frame is the one of :func:`twinfocus.radar.fmcw.mmwcas_virtual_array`: x along the array,
    y across it, z along boresight, origin at the middle of the virtual line (so the midpoint of
    TX t and RX r of a channel equals its ``offsets_m``).

    Returns (tx float64 (12, 3), rx float64 (16, 3)), metres, z = 0.
    """
    array = mmwcas_virtual_array(board) if array is None else array
    tx2 = mmwcas_tx_positions_m(board)
    rx2 = mmwcas_rx_positions_m(board)
    mid = (tx2[array.tx_index] + rx2[array.rx_index]) / 2.0
    centre = mid.mean(axis=0)
    tx = np.zeros((tx2.shape[0], 3))
    rx = np.zeros((rx2.shape[0], 3))
    tx[:, :2] = tx2 - centre
    rx[:, :2] = rx2 - centre
    return tx, rx


def frame_to_virtual_channels(
    frame: np.ndarray,
    chirp: Chirp,
    z0_m: float,
    array: VirtualArray | None = None,
) -> np.ndarray:
    """Monostatic-equivalent virtual channels of MIMO frames.

    Parameters
    ----------
    frame : complex (..., n_tx, n_rx, N), IF samples of every TX-RX pair (see :class:`RadarFrame`).
    chirp : the chirp the samples were taken with (``chirp.n_samples == N``).
    z0_m : range of the imaging plane, metres (the near-field correction is exact there).
    array : the virtual channels to keep; default the 86 of :func:`mmwcas_virtual_array`.

    Returns
    -------
    complex64 (..., K, N): channel k is pair (array.tx_index[k], array.rx_index[k]) times
    exp(-j k_n (dx^2 + dy^2) / (4 z0)), so that a point scatterer at range ~z0 appears as seen
    from the pair's midpoint by a co-located TX/RX (the model of :mod:`twinfocus.radar.fmcw`).
    """
    array = mmwcas_virtual_array() if array is None else array
    frame = np.asarray(frame)
    if frame.ndim < 3:
        raise TwinFocusError(f"frame must be (..., n_tx, n_rx, N), got shape {frame.shape}")
    if not np.iscomplexobj(frame):
        raise TwinFocusError(f"frame must hold complex IF samples, got dtype {frame.dtype}")
    n_tx, n_rx, n = frame.shape[-3:]
    if n != chirp.n_samples:
        raise TwinFocusError(f"frame has {n} samples per chirp but the chirp has {chirp.n_samples}")
    t_idx = np.asarray(array.tx_index)
    r_idx = np.asarray(array.rx_index)
    if t_idx.max(initial=-1) >= n_tx or r_idx.max(initial=-1) >= n_rx:
        raise TwinFocusError(
            f"the virtual array uses TX up to {t_idx.max()} and RX up to {r_idx.max()} but the frame has "
            f"{n_tx} TX x {n_rx} RX"
        )
    pairs = frame[..., t_idx, r_idx, :]
    return multistatic_to_monostatic(pairs, chirp, array.separation_m, z0_m)
