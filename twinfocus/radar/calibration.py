"""Channel calibration from one bright point (a corner reflector): estimate, file, apply.

Every TX-RX pair of a real array carries its own complex gain and path delay. Seen through pair
k, a point at range rho_k gives (model of :mod:`twinfocus.radar.fmcw` times the channel's error)

    x_k(t_n) = G_k exp(+j 4 pi (f_n - fc) d_k / c) exp(+j 4 pi f_n rho_k / c),

G_k the complex gain at the chirp's centre frequency fc (amplitude, and phase including the
carrier part of the delay), d_k the delay as a monostatic-equivalent range offset. As TI's cascade
calibration does (``genCalibrationMatrixCascade.m``: the peak's range bin per pair,
``RangeMat``, and its complex value, ``PeakValMat``; ``calibrationCascade.m`` applies
exp(-j 2 pi dbin n / N) and PeakValMat(ref) / PeakValMat(k)), :func:`estimate_channel_errors`
measures d_k and G_k of every channel against a reference channel from a capture of a corner,
after removing each channel's own geometric range to it (the array is in the near field), and
:func:`channel_correction` undoes them:

    x_k(t_n) * exp(-j 4 pi (f_n - fc) d_k / c) / G_k.

:func:`factorise_pairs` explains the pair values as per-TX times per-RX factors (how the errors
arise); what it cannot explain (a second scatterer, a wrong antenna position) is the
factorisation residual of the quality figures. The file (:class:`ChannelCalibration`) records
the chirp and the array it was made for, and refuses to correct another.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.io.arrays import load_npz, save_npz_atomic
from twinfocus.io.checksums import file_sha256
from twinfocus.radar.fmcw import C_M_PER_S, Chirp, VirtualArray, range_compress, range_profiles_at

#: Kind tag of a calibration file.
FILE_KIND = "twinfocus-channel-calibration"
FILE_VERSION = 1
#: A bright point must stand this far above the range profile's median, dB.
MIN_PEAK_SNR_DB = 15.0
#: A second peak within this many dB of the corner, over 2.5 range bins away, is a second corner.
SECOND_PEAK_DB = 10.0


def array_fingerprint(array: VirtualArray) -> str:
    """A short hash of the channels' TX/RX pairs and phase-centre offsets (to 1 um): two arrays
    with the same fingerprint are corrected by the same calibration."""
    h = hashlib.sha256()
    h.update(np.asarray(array.tx_index, np.int64).tobytes())
    h.update(np.asarray(array.rx_index, np.int64).tobytes())
    h.update(np.round(np.asarray(array.offsets_m, np.float64) * 1e6).astype(np.int64).tobytes())
    return h.hexdigest()[:16]


def pair_array(tx_body_m: np.ndarray, rx_body_m: np.ndarray) -> VirtualArray:
    """Every TX-RX pair as a virtual channel, pair (t, r) at index t * n_rx + r.

    tx_body_m (T, 3), rx_body_m (R, 3): antenna positions in the radar body frame, metres.
    Offsets are the pairs' midpoints (not re-centred), so a point on the body z axis at range
    R is at (0, 0, R) from them.
    """
    tx = np.asarray(tx_body_m, np.float64)
    rx = np.asarray(rx_body_m, np.float64)
    t = np.repeat(np.arange(tx.shape[0]), rx.shape[0])
    r = np.tile(np.arange(rx.shape[0]), tx.shape[0])
    return VirtualArray(
        offsets_m=(tx[t] + rx[r]) / 2.0,
        tx_index=t,
        rx_index=r,
        separation_m=(tx[t] - rx[r])[:, :2],
    )


# --- finding the corner ------------------------------------------------------------------------


@dataclass
class CornerPeak:
    """The bright point found in the channel-summed range profile.

    range_m : its range, metres; snr_db : its power over the profile's median, dB.
    profile_ranges_m, profile_db : float64 (B,) the profile (dB re its peak) for pictures.
    """

    range_m: float
    snr_db: float
    profile_ranges_m: np.ndarray
    profile_db: np.ndarray


def find_corner(data: np.ndarray, chirp: Chirp, range_m: float, window_m: float = 0.25) -> CornerPeak:
    """The single bright point within ``range_m +- window_m`` of the channel-summed profile.

    data : complex (F, K, N) or (K, N). Refuses (one line) when nothing stands
    :data:`MIN_PEAK_SNR_DB` above the profile's median in the window, when the strongest return
    of the window sits on its edge (something brighter lies outside), and when a second peak
    within :data:`SECOND_PEAK_DB` of the first lies over 2.5 range bins away (two corners).
    """
    x = np.asarray(data)
    x = x.reshape(-1, x.shape[-1])
    if not range_m > 0 or not window_m > 0:
        raise TwinFocusError(f"the corner's range and search window must be positive, got {range_m} and {window_m}")
    pad = 4
    prof = range_compress(x, chirp, n_fft=pad * chirp.n_samples, window="hann")
    power = np.mean(np.abs(prof.astype(np.complex128)) ** 2, axis=0)
    ranges = chirp.range_axis_m(pad * chirp.n_samples)
    floor = float(np.median(power)) or float(np.finfo(float).tiny)
    inside = np.flatnonzero(np.abs(ranges - range_m) <= window_m)
    if inside.size < 3:
        raise TwinFocusError(
            f"the range {range_m:g} m +- {window_m:g} m lies outside the capture's range axis (0 .. {ranges[-1]:.2f} m)"
        )
    i = int(inside[np.argmax(power[inside])])
    snr = 10 * np.log10(power[i] / floor)
    db = 10 * np.log10(np.maximum(power, 1e-300) / power[i])
    if snr < MIN_PEAK_SNR_DB:
        raise TwinFocusError(
            f"no bright point near {range_m:g} m: the strongest return within +-{window_m:g} m is "
            f"{snr:.1f} dB above the floor (needs {MIN_PEAK_SNR_DB:g} dB); is the corner reflector there?"
        )
    if i in (inside[0], inside[-1]):
        j = int(np.argmax(power))
        raise TwinFocusError(
            f"no bright point near {range_m:g} m: the return rises towards the edge of the +-{window_m:g} m window "
            f"(strongest return of the capture at {ranges[j]:.3f} m); give the corner's range with --range-m"
        )
    cell = int(pad * 2.5)
    local = [
        int(b)
        for b in inside[1:-1]
        if power[b] >= power[b - 1] and power[b] >= power[b + 1] and abs(int(b) - i) > cell and db[b] > -SECOND_PEAK_DB
    ]
    if local:
        b = max(local, key=lambda q: power[q])
        raise TwinFocusError(
            f"two bright points near {range_m:g} m: at {ranges[i]:.3f} m and {ranges[b]:.3f} m ({db[b]:.1f} dB); "
            "calibrate with one corner reflector alone in the window"
        )
    return CornerPeak(float(ranges[i]), float(snr), ranges, db)


# --- estimating the channels' errors -----------------------------------------------------------


def deramp_to_range(
    data: np.ndarray, centres_m: np.ndarray, corner_m: np.ndarray, origin_m: np.ndarray, chirp: Chirp
) -> np.ndarray:
    """Move every channel's view of the corner to one range, the corner's from ``origin_m``.

    data : complex (F, K, N); centres_m : float (F, K, 3) phase centres, metres; corner_m,
    origin_m (3,). Returns complex128 (F, K, N): x * exp(-j 4 pi f_n (rho_fk - R) / c),
    rho_fk = |centre_fk - corner|, R = |origin - corner|.
    """
    c = np.asarray(centres_m, np.float64)
    rho = np.linalg.norm(c - np.asarray(corner_m, np.float64), axis=-1)
    r0 = float(np.linalg.norm(np.asarray(origin_m, np.float64) - corner_m))
    f = chirp.frequencies_hz
    return np.asarray(data) * np.exp(-1j * 4 * np.pi * f * (rho - r0)[..., None] / C_M_PER_S)


def channel_peaks(x: np.ndarray, chirp: Chirp, range_m: float, span_bins: float = 1.5, steps: int = 301):
    """Each channel's peak near ``range_m``: (range float64 (K,), complex value at fc (K,)).

    x : complex (K, N) with the point at ~range_m in every channel. The Hann-windowed profile is
    evaluated on a fine grid (span_bins range bins either side), its maximum refined by a
    parabola; the value is the profile there divided by the window's sum and referred to the
    carrier at ``range_m``: G = P(r_k) exp(-j 4 pi fc range_m / c) / sum(w).
    """
    w = np.hanning(chirp.n_samples)
    grid = range_m + np.linspace(-span_bins, span_bins, steps) * chirp.range_resolution_m
    prof = range_profiles_at((np.asarray(x) * w).astype(np.complex64), chirp, grid)
    mag = np.abs(prof)
    i = np.clip(np.argmax(mag, axis=1), 1, steps - 2)
    k = np.arange(mag.shape[0])
    a, b, c = mag[k, i - 1], mag[k, i], mag[k, i + 1]
    den = a - 2 * b + c
    frac = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    step = grid[1] - grid[0]
    r_k = grid[i] + np.clip(frac, -1, 1) * step
    # Exact value at the refined range (the profile is smooth; a second evaluation is cheap).
    kern = np.exp(-1j * 2 * np.pi * chirp.slope_hz_per_s * np.outer(chirp.t_s - chirp.t_centre_s, 2 * r_k / C_M_PER_S))
    val = np.einsum("kn,nk->k", np.asarray(x) * w, kern)
    g = val * np.exp(-1j * 4 * np.pi * chirp.fc_hz * range_m / C_M_PER_S) / w.sum()
    return r_k, g


@dataclass
class ChannelEstimate:
    """What :func:`estimate_channel_errors` measured.

    gain : complex128 (K,), each channel's gain at fc relative to the reference channel's phase
        and to the channels' rms amplitude; delay_m : float64 (K,), range offsets relative to
        the reference channel, metres; corner_range_m : the corner's range from the centres'
        mean, metres; before : complex128 (K,) the raw peak values (phase spread before).
    """

    gain: np.ndarray
    delay_m: np.ndarray
    corner_range_m: float
    reference: int
    before: np.ndarray


def estimate_channel_errors(
    data: np.ndarray,
    centres_m: np.ndarray,
    chirp: Chirp,
    range_m: float,
    reference: int,
    origin_m=None,
    axis_m=None,
) -> ChannelEstimate:
    """Per-channel gain and delay from frames of one bright point on the array's axis.

    data : complex (F, K, N), F frames of a still radar (or a scan: positions may move);
    centres_m : float (F, K, 3) or (K, 3) phase centres, metres; range_m : the corner's range
    (from :func:`find_corner`); reference : the channel whose phase and delay are zero;
    axis_m : (3,) unit vector from the centres' mean to the corner (default +z).
    """
    x = np.asarray(data)
    if x.ndim == 2:
        x = x[None]
    c = np.broadcast_to(np.asarray(centres_m, np.float64), x.shape[:2] + (3,))
    k_count = x.shape[1]
    if not 0 <= int(reference) < k_count:
        raise TwinFocusError(f"reference channel must be in 0..{k_count - 1}, got {reference}")
    axis = np.array([0.0, 0.0, 1.0]) if axis_m is None else np.asarray(axis_m, np.float64)
    origin = c.reshape(-1, 3).mean(axis=0) if origin_m is None else np.asarray(origin_m, np.float64)
    r_c = float(range_m)
    for _ in range(3):
        y = deramp_to_range(x, c, origin + r_c * axis, origin, chirp).mean(axis=0)
        r_k, g = channel_peaks(y, chirp, r_c)
        shift = float(r_k[reference] - r_c)
        r_c += shift
        if abs(shift) < 1e-7:
            break
    delay = r_k - r_k[reference]
    ref = g[reference]
    rms = float(np.sqrt(np.mean(np.abs(g) ** 2)))
    gain = g * np.exp(-1j * np.angle(ref)) / rms
    return ChannelEstimate(gain=gain, delay_m=delay, corner_range_m=r_c, reference=int(reference), before=g)


def channel_correction(chirp: Chirp, gain: np.ndarray, delay_m: np.ndarray) -> np.ndarray:
    """Per-channel, per-sample correction, complex64 (K, N): exp(-j 4 pi (f_n - fc) d_k / c) / G_k."""
    f = chirp.frequencies_hz - chirp.fc_hz
    g = np.asarray(gain, np.complex128)
    ramp = np.exp(-1j * 4 * np.pi * np.outer(np.asarray(delay_m, np.float64), f) / C_M_PER_S)
    return (ramp / g[:, None]).astype(np.complex64)


def factorise_pairs(gain: np.ndarray, delay_m: np.ndarray, tx_index, rx_index, n_tx: int, n_rx: int, iters: int = 200):
    """Per-TX and per-RX factors that best explain the channels' gains and delays.

    gain : complex (K,), delay_m : (K,), pair k = (tx_index[k], rx_index[k]).
    Returns (tx_gain complex128 (n_tx,), rx_gain (n_rx,), tx_delay_m (n_tx,), rx_delay_m (n_rx,),
    residual_phase_deg_rms, residual_delay_m_rms): gain_k ~ tx_gain[t] rx_gain[r] (alternating
    least squares), delay_k ~ tx_delay[t] + rx_delay[r] (least squares, minimum norm). TX or RX
    that no channel uses are NaN.
    """
    t = np.asarray(tx_index, int)
    r = np.asarray(rx_index, int)
    g = np.asarray(gain, np.complex128)
    tg = np.ones(n_tx, np.complex128)
    rg = np.ones(n_rx, np.complex128)
    for _ in range(iters):
        num = np.zeros(n_rx, np.complex128)
        den = np.zeros(n_rx)
        np.add.at(num, r, g * np.conj(tg[t]))
        np.add.at(den, r, np.abs(tg[t]) ** 2)
        rg = np.where(den > 0, num / np.where(den > 0, den, 1), np.nan)
        num = np.zeros(n_tx, np.complex128)
        den = np.zeros(n_tx)
        np.add.at(num, t, g * np.conj(rg[r]))
        np.add.at(den, t, np.abs(rg[r]) ** 2)
        tg = np.where(den > 0, num / np.where(den > 0, den, 1), np.nan)
    model = tg[t] * rg[r]
    res = np.angle(g * np.conj(model))
    a = np.zeros((t.size, n_tx + n_rx))
    a[np.arange(t.size), t] = 1
    a[np.arange(t.size), n_tx + r] = 1
    sol = np.linalg.lstsq(a, np.asarray(delay_m, np.float64), rcond=None)[0]
    used_t = np.isin(np.arange(n_tx), t)
    used_r = np.isin(np.arange(n_rx), r)
    td = np.where(used_t, sol[:n_tx], np.nan)
    rd = np.where(used_r, sol[n_tx:], np.nan)
    dres = np.asarray(delay_m) - (sol[:n_tx][t] + sol[n_tx:][r])
    return (
        tg,
        rg,
        td,
        rd,
        float(np.degrees(np.sqrt(np.mean(res**2)))),
        float(np.sqrt(np.mean(dres**2))),
    )


def phase_spread_deg(values: np.ndarray) -> float:
    """rms of the phases of ``values`` (K,) about their coherent mean, degrees (0: all in phase)."""
    v = np.asarray(values, np.complex128)
    mean = np.sum(v)
    return float(np.degrees(np.sqrt(np.mean(np.angle(v * np.conj(mean)) ** 2))))


def coherence(values: np.ndarray) -> float:
    """|sum v| / sum |v| of the channels' peak values (K,): 1 when they add up perfectly."""
    v = np.asarray(values, np.complex128)
    return float(np.abs(v.sum()) / max(np.abs(v).sum(), 1e-300))


# --- the file -----------------------------------------------------------------------------------


@dataclass
class ChannelCalibration:
    """A calibration file: the channels' gains and delays and what they were made for.

    gain : complex128 (K,), delay_m : float64 (K,) of the virtual channels (tx_index, rx_index)
    of ``array_fingerprint``; pair_gain complex128 (T, R) and pair_delay_m (T, R): every TX-RX
    pair the corner capture held (NaN where none); tx_gain, rx_gain, tx_delay_m, rx_delay_m:
    the per-TX and per-RX factors; chirp : the chirp of the corner capture; board : the board's
    name; quality : the quality figures (JSON-able dict).
    """

    gain: np.ndarray
    delay_m: np.ndarray
    tx_index: np.ndarray
    rx_index: np.ndarray
    array_fingerprint: str
    chirp: Chirp
    board: str
    pair_gain: np.ndarray
    pair_delay_m: np.ndarray
    tx_gain: np.ndarray
    rx_gain: np.ndarray
    tx_delay_m: np.ndarray
    rx_delay_m: np.ndarray
    corner_range_m: float
    reference: int
    quality: dict = field(default_factory=dict)

    @property
    def n_channels(self) -> int:
        return int(np.asarray(self.gain).shape[0])

    def correction(self) -> np.ndarray:
        """complex64 (K, N) to multiply the channels' samples with (:func:`channel_correction`)."""
        return channel_correction(self.chirp, self.gain, self.delay_m)

    def check_fits(
        self, chirp: Chirp, array: VirtualArray, board: str | None = None, source: str = "calibration"
    ) -> None:
        """Refuse (one line) data of another array, another board or another chirp."""
        if array.n_channels != self.n_channels:
            raise TwinFocusError(
                f"{source} is for {self.n_channels} channels, the data has {array.n_channels}: a calibration of another array"
            )
        fp = array_fingerprint(array)
        if fp != self.array_fingerprint:
            raise TwinFocusError(
                f"{source} was made for another array (fingerprint {self.array_fingerprint}, this one {fp}): "
                "another board or antenna layout; calibrate this one"
            )
        if board is not None and board != self.board:
            raise TwinFocusError(f"{source} was made on board {self.board!r}, the data comes from {board!r}")
        mine = self.chirp.to_dict()
        theirs = chirp.to_dict()
        diff = [k for k in mine if not np.isclose(mine[k], theirs[k], rtol=1e-6, atol=0)]
        if diff:
            k = diff[0]
            raise TwinFocusError(
                f"{source} was made with another chirp ({k} {mine[k]:g}, the data has {theirs[k]:g}); "
                "calibrate with the chirp you image with"
            )

    def save(self, path: str | os.PathLike) -> Path:
        arrays = {
            "kind": np.array(FILE_KIND),
            "version": np.int64(FILE_VERSION),
            "gain": np.asarray(self.gain, np.complex128),
            "delay_m": np.asarray(self.delay_m, np.float64),
            "tx_index": np.asarray(self.tx_index, np.int64),
            "rx_index": np.asarray(self.rx_index, np.int64),
            "array_fingerprint": np.array(self.array_fingerprint),
            "board": np.array(self.board),
            "f0_hz": np.float64(self.chirp.f0_hz),
            "slope_hz_per_s": np.float64(self.chirp.slope_hz_per_s),
            "fs_hz": np.float64(self.chirp.fs_hz),
            "n_samples": np.int64(self.chirp.n_samples),
            "pair_gain": np.asarray(self.pair_gain, np.complex128),
            "pair_delay_m": np.asarray(self.pair_delay_m, np.float64),
            "tx_gain": np.asarray(self.tx_gain, np.complex128),
            "rx_gain": np.asarray(self.rx_gain, np.complex128),
            "tx_delay_m": np.asarray(self.tx_delay_m, np.float64),
            "rx_delay_m": np.asarray(self.rx_delay_m, np.float64),
            "corner_range_m": np.float64(self.corner_range_m),
            "reference": np.int64(self.reference),
            "quality_json": np.array(json.dumps(self.quality)),
        }
        return save_npz_atomic(path, arrays)

    @classmethod
    def load(cls, path: str | os.PathLike) -> ChannelCalibration:
        z = load_npz(path)
        if "kind" not in z or str(z["kind"]) != FILE_KIND:
            raise TwinFocusError(f"{path}: not a channel calibration file (make one with `twinfocus calibrate`)")
        try:
            gain = z["gain"]
            delay = z["delay_m"]
            if gain.ndim != 1 or delay.shape != gain.shape or not np.iscomplexobj(gain):
                raise TwinFocusError(f"gain and delay_m must be (K,) (complex, real), got {gain.shape} {delay.shape}")
            if not (np.isfinite(gain).all() and np.isfinite(delay).all()) or np.any(gain == 0):
                raise TwinFocusError("gain or delay_m holds NaN, inf or a zero gain")
            chirp = Chirp(float(z["f0_hz"]), float(z["slope_hz_per_s"]), float(z["fs_hz"]), int(z["n_samples"]))
            return cls(
                gain=gain,
                delay_m=delay,
                tx_index=z["tx_index"],
                rx_index=z["rx_index"],
                array_fingerprint=str(z["array_fingerprint"]),
                chirp=chirp,
                board=str(z["board"]),
                pair_gain=z["pair_gain"],
                pair_delay_m=z["pair_delay_m"],
                tx_gain=z["tx_gain"],
                rx_gain=z["rx_gain"],
                tx_delay_m=z["tx_delay_m"],
                rx_delay_m=z["rx_delay_m"],
                corner_range_m=float(z["corner_range_m"]),
                reference=int(z["reference"]),
                quality=json.loads(str(z["quality_json"])),
            )
        except KeyError as exc:
            raise TwinFocusError(f"{path}: damaged calibration file, missing {exc}") from None
        except TwinFocusError as exc:
            raise TwinFocusError(f"{path}: {exc}") from None


def calibration_for(
    path: str | os.PathLike, chirp: Chirp, array: VirtualArray, board: str | None = None
) -> tuple[np.ndarray, dict]:
    """Read a calibration file for data of ``chirp`` and ``array`` (refused, one line, when it
    was made for others). Returns (correction complex64 (K, N), record): the record names the
    file and its SHA-256 and carries its quality figures, for a scan's and a focus's metrics."""
    cal = ChannelCalibration.load(path)
    cal.check_fits(chirp, array, board, source=str(path))
    record = {
        "file": Path(path).name,
        "sha256": file_sha256(path),
        "residual_phase_deg_rms": cal.quality.get("residual_phase_deg_rms"),
        "peak_sharpness": cal.quality.get("peak_sharpness"),
    }
    return cal.correction(), record


def apply_calibration(data: np.ndarray, correction: np.ndarray) -> np.ndarray:
    """data complex (..., K, N) times the correction (K, N) of :meth:`ChannelCalibration.correction`,
    complex64 (..., K, N)."""
    x = np.asarray(data)
    c = np.asarray(correction)
    if x.shape[-2:] != c.shape:
        raise TwinFocusError(f"data has channels x samples {x.shape[-2:]}, the calibration {c.shape}")
    return (x * c).astype(np.complex64)


# --- from a corner capture to a calibration ---------------------------------------------------


@dataclass
class CalibrationReport:
    """The numbers behind a calibration's picture, per imaging channel (K,): the corner's peak
    value before (geometry removed) and after calibration (held-out frames when there are two or
    more), and the corner's range profile."""

    before: np.ndarray
    after: np.ndarray
    peak: CornerPeak


def _pair_lookup(pairs: VirtualArray, array: VirtualArray) -> np.ndarray:
    """Index into ``pairs`` of each channel of ``array`` (-1 where the pair was not measured)."""
    where = {(int(t), int(r)): i for i, (t, r) in enumerate(zip(pairs.tx_index, pairs.rx_index))}
    return np.array([where.get((int(t), int(r)), -1) for t, r in zip(array.tx_index, array.rx_index)])


def make_calibration(
    data: np.ndarray,
    centres_m: np.ndarray,
    chirp: Chirp,
    peak: CornerPeak,
    pairs: VirtualArray,
    array: VirtualArray,
    board: str,
    reference: int | None = None,
    origin_m=None,
    n_tx: int = 12,
    n_rx: int = 16,
) -> tuple[ChannelCalibration, CalibrationReport]:
    """A calibration of ``array``'s channels from frames of one corner seen through ``pairs``.

    data : complex (F, P, N), the monostatic-equivalent samples of the P measured pairs
    (every TX-RX pair of a capture, or a scan's own channels); centres_m : (F, P, 3) or (P, 3);
    peak : :func:`find_corner`'s; array : the imaging channels the file corrects (a channel whose
    pair was not measured gets its per-TX times per-RX factor); reference : index into
    ``array`` of the channel whose phase and delay are zero (default its middle one).
    """
    x = np.asarray(data)
    if x.ndim == 2:
        x = x[None]
    look = _pair_lookup(pairs, array)
    ref_k = array.n_channels // 2 if reference is None else int(reference)
    if not 0 <= ref_k < array.n_channels:
        raise TwinFocusError(f"reference channel must be in 0..{array.n_channels - 1}, got {reference}")
    if look[ref_k] < 0:
        raise TwinFocusError(f"reference channel {ref_k} was not measured by the corner capture")
    est = estimate_channel_errors(x, centres_m, chirp, peak.range_m, int(look[ref_k]), origin_m)
    tg, rg, td, rd, fact_deg, fact_delay = factorise_pairs(
        est.gain, est.delay_m, pairs.tx_index, pairs.rx_index, n_tx, n_rx
    )
    pair_gain = np.full((n_tx, n_rx), np.nan + 0j)
    pair_delay = np.full((n_tx, n_rx), np.nan)
    pair_gain[pairs.tx_index, pairs.rx_index] = est.gain
    pair_delay[pairs.tx_index, pairs.rx_index] = est.delay_m
    t, r = np.asarray(array.tx_index), np.asarray(array.rx_index)
    gain = np.where(look >= 0, est.gain[look], tg[t] * rg[r])
    delay = np.where(look >= 0, est.delay_m[look], td[t] + rd[r])
    if not (np.isfinite(gain).all() and np.isfinite(delay).all()):
        raise TwinFocusError("the corner capture does not measure every TX and RX the imaging array uses")
    gain = gain * np.exp(-1j * np.angle(gain[ref_k])) / np.sqrt(np.mean(np.abs(gain) ** 2))
    before = np.where(look >= 0, est.before[look], np.nan)
    quality = {
        "corner_range_m": round(est.corner_range_m, 5),
        "peak_snr_db": round(peak.snr_db, 1),
        "frames": int(x.shape[0]),
        "channels_measured": int(pairs.n_channels),
        "phase_spread_before_deg": round(phase_spread_deg(before[look >= 0]), 2),
        "amplitude_spread_db": round(float(np.std(20 * np.log10(np.abs(gain)))), 3),
        "delay_spread_mm": round(float(np.std(delay)) * 1e3, 3),
        "factorisation_residual_deg_rms": round(fact_deg, 2),
        "factorisation_residual_delay_mm_rms": round(fact_delay * 1e3, 4),
        "peak_sharpness_before": round(coherence(before[look >= 0]), 4),
    }
    if x.shape[0] >= 2:
        # Held out: calibrate on the even frames, look at the odd ones through it.
        half = estimate_channel_errors(
            x[0::2], _frames(centres_m, x)[0::2], chirp, peak.range_m, int(look[ref_k]), origin_m
        )
        corr = channel_correction(chirp, half.gain, half.delay_m)
        odd = apply_calibration(x[1::2], corr)
        origin = (
            _frames(centres_m, x).reshape(-1, 3).mean(axis=0) if origin_m is None else np.asarray(origin_m, np.float64)
        )
        y = deramp_to_range(
            odd, _frames(centres_m, x)[1::2], origin + est.corner_range_m * np.array([0, 0, 1.0]), origin, chirp
        )
        _, after_pairs = channel_peaks(y.mean(axis=0), chirp, est.corner_range_m)
        quality["residual_from"] = "held-out frames"
    else:
        after_pairs = est.gain / (tg[pairs.tx_index] * rg[pairs.rx_index])
        quality["residual_from"] = "per-TX x per-RX model (one frame)"
    after = np.where(look >= 0, after_pairs[np.maximum(look, 0)], np.nan)
    quality["residual_phase_deg_rms"] = round(phase_spread_deg(after_pairs), 2)
    quality["peak_sharpness"] = round(coherence(after_pairs), 4)
    cal = ChannelCalibration(
        gain=gain,
        delay_m=delay,
        tx_index=t,
        rx_index=r,
        array_fingerprint=array_fingerprint(array),
        chirp=chirp,
        board=board,
        pair_gain=pair_gain,
        pair_delay_m=pair_delay,
        tx_gain=tg,
        rx_gain=rg,
        tx_delay_m=td,
        rx_delay_m=rd,
        corner_range_m=est.corner_range_m,
        reference=ref_k,
        quality=quality,
    )
    return cal, CalibrationReport(before=before, after=after, peak=peak)


def _frames(centres_m, x: np.ndarray) -> np.ndarray:
    return np.broadcast_to(np.asarray(centres_m, np.float64), x.shape[:2] + (3,))
