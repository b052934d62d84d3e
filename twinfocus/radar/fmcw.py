"""FMCW chirp, the MMWCAS 12x16 MIMO layout and range compression.

Signal model used everywhere in the project (docs/architecture.md section 2): for a monostatic phase
centre at distance R_j from scatterer j the IF sample n is

    s(t_n) = sum_j a_j exp(+j 2 pi (f0 + S t_n) 2 R_j / c),   t_n = n / fs,

with f0 the frequency of the first ADC sample and S the chirp slope. Range compression and
back-projection are matched filters of exactly this model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.radar.board import C_M_PER_S as C_M_PER_S  # the speed of light, defined with the board's units
from twinfocus.radar.board import RX_ARRAY_ORDER, TX_ARRAY_ORDER, Board, default_board


@dataclass(frozen=True)
class Chirp:
    """One FMCW chirp as sampled by the ADC.

    Defaults are the TI MMWCAS set-up of the source paper: 76 GHz start, 5 us ADC start
    (first sample at 76.6 GHz), 120 MHz/us, 8 Msps, 256 complex samples (3.84 GHz sampled).
    """

    f0_hz: float = 76.6e9
    slope_hz_per_s: float = 120e12
    fs_hz: float = 8e6
    n_samples: int = 256

    def __post_init__(self) -> None:
        for name in ("f0_hz", "slope_hz_per_s", "fs_hz"):
            value = float(getattr(self, name))
            if not np.isfinite(value) or value <= 0:
                raise TwinFocusError(f"chirp {name} must be a positive finite number, got {value!r}")
        if int(self.n_samples) < 2:
            raise TwinFocusError(f"chirp n_samples must be at least 2, got {self.n_samples!r}")

    @property
    def t_s(self) -> np.ndarray:
        """Fast-time sample instants, float64 (N,), seconds."""
        return np.arange(self.n_samples) / self.fs_hz

    @property
    def t_centre_s(self) -> float:
        """Middle of the sampled part of the chirp, seconds."""
        return (self.n_samples - 1) / (2.0 * self.fs_hz)

    @property
    def frequencies_hz(self) -> np.ndarray:
        """Instantaneous frequency of each sample, float64 (N,), Hz."""
        return self.f0_hz + self.slope_hz_per_s * self.t_s

    @property
    def wavenumbers_rad_per_m(self) -> np.ndarray:
        """k_n = 2 pi f_n / c, float64 (N,), rad/m."""
        return 2.0 * np.pi * self.frequencies_hz / C_M_PER_S

    @property
    def bandwidth_hz(self) -> float:
        """Sampled bandwidth S N / fs (3.84 GHz for the defaults)."""
        return self.slope_hz_per_s * self.n_samples / self.fs_hz

    @property
    def fc_hz(self) -> float:
        """Centre frequency of the sampled band, Hz."""
        return self.f0_hz + self.slope_hz_per_s * self.t_centre_s

    @property
    def wavelength_m(self) -> float:
        """Wavelength at the centre frequency, metres."""
        return C_M_PER_S / self.fc_hz

    @property
    def range_resolution_m(self) -> float:
        """c / 2B: range bin width without zero padding (~3.9 cm for the defaults)."""
        return C_M_PER_S / (2.0 * self.bandwidth_hz)

    @property
    def max_range_m(self) -> float:
        """Unambiguous range of a complex-sampled IF: c fs / (2 S)."""
        return C_M_PER_S * self.fs_hz / (2.0 * self.slope_hz_per_s)

    def range_axis_m(self, n_fft: int | None = None) -> np.ndarray:
        """Range of each bin of :func:`range_compress`, float64 (n_fft,), metres."""
        n_fft = self.n_samples if n_fft is None else int(n_fft)
        return np.arange(n_fft) * self.max_range_m / n_fft

    def to_dict(self) -> dict:
        return {
            "f0_hz": float(self.f0_hz),
            "slope_hz_per_s": float(self.slope_hz_per_s),
            "fs_hz": float(self.fs_hz),
            "n_samples": int(self.n_samples),
        }


def range_compress(data: np.ndarray, chirp: Chirp, n_fft: int | None = None, window: str | None = None) -> np.ndarray:
    """Range profiles by a zero-padded FFT over fast time.

    Parameters
    ----------
    data : complex (..., N) IF samples of the model in this module's docstring.
    n_fft : FFT length >= N (zero padding); bin b sits at ``chirp.range_axis_m(n_fft)[b]``.
    window : None or ``"hann"`` (lower side lobes, wider main lobe).

    Returns
    -------
    complex (..., n_fft) profiles. The phase of bin b is referred to the centre of the chirp,
    so a point at range R peaks at R with phase 4 pi fc R / c (``fc`` = ``chirp.fc_hz``).
    """
    data = np.asarray(data)
    n = chirp.n_samples
    if data.shape[-1] != n:
        raise TwinFocusError(f"data has {data.shape[-1]} fast-time samples, the chirp has {n}")
    n_fft = n if n_fft is None else int(n_fft)
    if n_fft < n:
        raise TwinFocusError(f"n_fft ({n_fft}) must be at least the number of samples ({n})")
    x = data
    if window == "hann":
        x = x * np.hanning(n).astype(np.float32)
    elif window is not None:
        raise TwinFocusError(f"unknown window {window!r}; use None or 'hann'")
    spec = np.fft.fft(x, n=n_fft, axis=-1)
    # The FFT refers phase to sample 0; refer it to the chirp centre so that the profile phase
    # is that of the carrier at fc (the same convention as range_profiles_at).
    ranges = chirp.range_axis_m(n_fft)
    shift = np.exp(1j * 2.0 * np.pi * chirp.slope_hz_per_s * chirp.t_centre_s * 2.0 * ranges / C_M_PER_S)
    return (spec * shift.astype(np.complex64)).astype(np.complex64)


def range_kernel(chirp: Chirp, ranges_m: np.ndarray) -> np.ndarray:
    """Centred baseband matched-filter matrix E[n, q] = exp(-j 2 pi S (t_n - t_c) 2 r_q / c).

    ``data @ E`` evaluates the range profile at arbitrary ranges ("zoomed" range
    compression): only the range bins that reach an image are computed. The full matched filter
    of range r is ``exp(-j 4 pi fc r / c) * (data @ E)[r]``.

    Returns complex128 (N, Q).
    """
    ranges_m = np.asarray(ranges_m, dtype=np.float64)
    tau = chirp.t_s - chirp.t_centre_s
    return np.exp(-1j * 2.0 * np.pi * chirp.slope_hz_per_s * np.outer(tau, 2.0 * ranges_m / C_M_PER_S))


def range_profiles_at(data: np.ndarray, chirp: Chirp, ranges_m: np.ndarray) -> np.ndarray:
    """Baseband range profiles evaluated at ``ranges_m`` (Q,), complex64 (..., Q).

    Equal to :func:`range_compress` with infinite zero padding, sampled at ``ranges_m``.
    """
    data = np.asarray(data)
    if data.shape[-1] != chirp.n_samples:
        raise TwinFocusError(f"data has {data.shape[-1]} fast-time samples, the chirp has {chirp.n_samples}")
    kernel = range_kernel(chirp, ranges_m).astype(np.complex64)
    return (data.astype(np.complex64, copy=False) @ kernel).astype(np.complex64, copy=False)


# --- MMWCAS-RF-EVM: 4 cascaded AWR2243, 12 TX x 16 RX ---------------------------------------
# The antenna layout comes from a board file (twinfocus.radar.board; default TI's MMWCAS-RF-EVM). The
# order of this module: TX t is TI's TX 12 - t (TI's default chirp order fires TX12 first), RX a
# is the a-th RX along the board (data channel RX_ARRAY_ORDER[a]).


def mmwcas_tx_positions_m(board: Board | None = None) -> np.ndarray:
    """TX antenna positions in the board frame, float64 (12, 2): (along, across) metres."""
    board = default_board() if board is None else board
    return board.tx_positions_m()[TX_ARRAY_ORDER]


def mmwcas_rx_positions_m(board: Board | None = None) -> np.ndarray:
    """RX antenna positions in the board frame, float64 (16, 2): (along, across) metres."""
    board = default_board() if board is None else board
    return board.rx_positions_m()[RX_ARRAY_ORDER]


@dataclass(frozen=True)
class VirtualArray:
    """The virtual (monostatic-equivalent) channels a radar position contributes.

    Attributes
    ----------
    offsets_m : float64 (K, 3) phase-centre offsets in the radar body frame (x along the array,
        y across it, z along boresight), centred on the array's middle.
    tx_index, rx_index : int (K,) which TX and RX form each channel.
    separation_m : float64 (K, 2) TX minus RX position (along, across), for the
        multistatic-to-monostatic correction.
    """

    offsets_m: np.ndarray
    tx_index: np.ndarray
    rx_index: np.ndarray
    separation_m: np.ndarray

    @property
    def n_channels(self) -> int:
        return int(self.offsets_m.shape[0])


def mmwcas_virtual_array(board: Board | None = None) -> VirtualArray:
    """The virtual channels on one line at pitch lambda/4 of the board's design frequency (86 at
    0.9759 mm for the MMWCAS-RF-EVM's 76.8 GHz).

    Of the 192 TX-RX pairs, the TX on the azimuth row (the across position most TX share: nine on
    the MMWCAS) give the distinct midpoints; for each midpoint the first pair in TX order is kept.
    Offsets are centred on the line's middle.
    """
    board = default_board() if board is None else board
    tx = mmwcas_tx_positions_m(board)
    rx = mmwcas_rx_positions_m(board)
    rows, counts = np.unique(np.round(tx[:, 1], 12), return_counts=True)
    on_line = np.flatnonzero(np.round(tx[:, 1], 12) == rows[counts.argmax()])
    seen: dict[int, tuple[int, int]] = {}
    quarter = board.design_wavelength_m / 4.0
    for t in on_line:
        for r in range(rx.shape[0]):
            key = int(round((tx[t, 0] + rx[r, 0]) / 2.0 / quarter))
            seen.setdefault(key, (int(t), r))
    keys = sorted(seen)
    t_idx = np.array([seen[k][0] for k in keys])
    r_idx = np.array([seen[k][1] for k in keys])
    mid = (tx[t_idx] + rx[r_idx]) / 2.0
    offsets = np.zeros((len(keys), 3))
    offsets[:, 0] = mid[:, 0] - mid[:, 0].mean()
    offsets[:, 1] = mid[:, 1] - mid[:, 1].mean()
    return VirtualArray(
        offsets_m=offsets,
        tx_index=t_idx,
        rx_index=r_idx,
        separation_m=tx[t_idx] - rx[r_idx],
    )


def uniform_virtual_array(n_channels: int, pitch_m: float) -> VirtualArray:
    """A line of ``n_channels`` co-located TX/RX channels along x (for tests and small scenes)."""
    if n_channels < 1 or not pitch_m > 0:
        raise TwinFocusError("uniform array needs n_channels >= 1 and a positive pitch")
    offsets = np.zeros((n_channels, 3))
    offsets[:, 0] = (np.arange(n_channels) - (n_channels - 1) / 2.0) * pitch_m
    zeros = np.zeros(n_channels, dtype=int)
    return VirtualArray(offsets, zeros, zeros, np.zeros((n_channels, 2)))


def multistatic_to_monostatic(data: np.ndarray, chirp: Chirp, separation_m: np.ndarray, z0_m: float) -> np.ndarray:
    """Near-field multistatic-to-monostatic phase correction.

    Multiplies channel k's samples by exp(-j k_n (dx_k^2 + dy_k^2) / (4 z0)), with (dx, dy) its
    TX-RX separation and k_n the wavenumber of sample n.

    data : complex (..., K, N); separation_m : (K, 2) metres; z0_m : range of the image plane.
    """
    data = np.asarray(data)
    sep = np.asarray(separation_m, dtype=np.float64)
    if sep.shape != (data.shape[-2], 2):
        raise TwinFocusError(f"separation_m must be ({data.shape[-2]}, 2), got {sep.shape}")
    if not z0_m > 0:
        raise TwinFocusError(f"z0_m must be positive, got {z0_m!r}")
    d2 = (sep**2).sum(axis=1)
    phase = -np.outer(d2, chirp.wavenumbers_rad_per_m) / (4.0 * z0_m)
    return (data * np.exp(1j * phase).astype(np.complex64)).astype(np.complex64)
