"""The MIMO array as hardware is: per-channel errors, leakage, DC offset, IQ imbalance, beam pattern.

A real cascade's TX-RX pair (t, r) does not deliver the IF model of :mod:`twinfocus.radar.fmcw`
exactly. Its samples are (docs/calibration.md, "What the simulator's imperfect array does")

    x[t, r, n] = iq_r( T_t R_r exp(+j 2 pi f_n (tau_t + tau_r)) s[t, r, n]
                       + L[t, r] exp(+j k_n |tx_t - rx_r|) + D_r ),

with T_t, R_r the complex gains of TX t and RX r (amplitude and phase: LO routing, PCB traces,
the chips' own mismatch), tau_t, tau_r their path delays, L the direct TX-to-RX leakage (a tone at
the antennas' separation, near zero range), D_r the receiver's DC offset and iq_r its I/Q imbalance
(Q = g_r (sin(psi_r) I + cos(psi_r) Q)). The antennas' gain pattern scales each scatterer's
return by cos(theta)^(q/2) per antenna (theta off boresight), see
:func:`twinfocus.sensors.emulators.radar_scene.simulate_mimo_frames`.

Default magnitudes (:data:`TYPICAL`) and where they come from:

- channel phase: uniform over 360 degrees per TX and per RX. Raw channel phases of TI's parts
  are effectively arbitrary until calibrated (TI E2E 845205, AWR1243BOOST raw I/Q: "channel-to-
  channel phase match is approximately random"); in the cascade, PCB routing of the 80 GHz and
  20 GHz LO lines adds inter-chip imbalance (TI SPRACV2, "Cascade Coherency and Phase Shifter
  Calibration").
- channel amplitude: 1 dB standard deviation per TX and per RX (TI E2E 654592: the receivers'
  gain mismatch varies by less than 1 dB over temperature; TI SPRACV2 lists TX/RX gain
  imbalance among what the factory calibration measures).
- channel delay: 3 mm (monostatic-equivalent range) standard deviation per TX and per RX, a
  tenth of a range bin: TI's cascade calibration corrects per-channel range offsets on a grid of
  1/5 bin (``calibrationInterp = 5`` in ``calibrationCascade.m``), so offsets of that order are
  what it is built for. No published per-channel delay spread of the MMWCAS was found.
- leakage: 0 dB, the direct TX-RX coupling as strong as the scan's mean return. An assumption:
  TI notes the coupling "dominates the range bins close to the radar" (E2E 674013) and can
  saturate the ADC on antenna-on-package parts (SWRA820A), without a figure for the MMWCAS.
- DC offset: -20 dB of the mean return (an assumption; the AWR parts calibrate it at start-up,
  SPRACF4C section 3.4, and leave a residual).
- IQ imbalance: gain within +-1 dB and phase within +-2 degrees per receiver, uniform (the AWR1243
  data sheet's I/Q gain and phase mismatch, as quoted by TI in E2E 654592).
- beam pattern: each antenna's power falls to half 30 degrees off boresight (60 degree
  half-power beam width; an assumption of the order TI measures for its EVMs' patch arrays,
  SWRU613A section 3).

Everything here is a plain array function; :func:`draw_array_errors` makes one draw.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import C_M_PER_S, Chirp, VirtualArray

N_TX = 12
N_RX = 16


@dataclass(frozen=True)
class ArrayErrorLevels:
    """How large each hardware effect is (0 everywhere: the perfect array).

    channel_phase_deg : spread of the per-TX and per-RX phases; 180 or more: uniform over 360.
    channel_amplitude_db : standard deviation of the per-TX and per-RX gains, dB.
    channel_delay_mm : standard deviation of the per-TX and per-RX delays, as a
        monostatic-equivalent range offset (mm): delay tau = 2 d / c.
    leakage_db : TX-to-RX leakage relative to the mean return (dB); None: none.
    dc_offset_db : receiver DC offset relative to the mean return (dB); None: none.
    iq_gain_db, iq_phase_deg : bounds of the per-RX I/Q gain and phase mismatch (uniform).
    beamwidth_deg : each antenna's half-power beam width, degrees; None: isotropic.
    """

    channel_phase_deg: float = 0.0
    channel_amplitude_db: float = 0.0
    channel_delay_mm: float = 0.0
    leakage_db: float | None = None
    dc_offset_db: float | None = None
    iq_gain_db: float = 0.0
    iq_phase_deg: float = 0.0
    beamwidth_deg: float | None = None

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None:
                continue
            if not np.isfinite(float(v)):
                raise TwinFocusError(f"array error {f.name} must be finite, got {v!r}")
            if f.name not in ("leakage_db", "dc_offset_db") and float(v) < 0:
                raise TwinFocusError(f"array error {f.name} must be non-negative, got {v!r}")
        if self.beamwidth_deg is not None and not 0 < self.beamwidth_deg < 180:
            raise TwinFocusError(f"beamwidth_deg must lie in (0, 180), got {self.beamwidth_deg!r}")

    @property
    def pattern_exponent(self) -> float:
        """q of the per-antenna power pattern cos(theta)^q (0: isotropic)."""
        if self.beamwidth_deg is None:
            return 0.0
        return float(np.log(0.5) / np.log(np.cos(np.radians(self.beamwidth_deg) / 2.0)))

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


#: The perfect array.
NONE = ArrayErrorLevels()
#: Realistic magnitudes (sources in the module docstring).
TYPICAL = ArrayErrorLevels(
    channel_phase_deg=180.0,
    channel_amplitude_db=1.0,
    channel_delay_mm=3.0,
    leakage_db=0.0,
    dc_offset_db=-20.0,
    iq_gain_db=1.0,
    iq_phase_deg=2.0,
    beamwidth_deg=60.0,
)
LEVELS = {"none": NONE, "typical": TYPICAL}


def array_error_levels(name: str = "none", **overrides) -> ArrayErrorLevels:
    """The levels called ``name`` (``"none"`` or ``"typical"``) with some knobs replaced
    (keywords of :class:`ArrayErrorLevels`; a None value keeps the named level's)."""
    if name not in LEVELS:
        raise TwinFocusError(f"unknown array errors {name!r}; use {' or '.join(LEVELS)}")
    known = {f.name for f in fields(ArrayErrorLevels)}
    bad = sorted(set(overrides) - known)
    if bad:
        raise TwinFocusError(f"unknown array error knob(s) {', '.join(bad)}")
    return replace(LEVELS[name], **{k: v for k, v in overrides.items() if v is not None})


@dataclass(frozen=True)
class ArrayErrors:
    """One draw of the hardware effects of a 12 TX x 16 RX array.

    tx_gain complex128 (12,), rx_gain complex128 (16,): amplitude and phase of each TX and RX.
    tx_delay_m float64 (12,), rx_delay_m float64 (16,): monostatic-equivalent range offsets, m
        (a delay tau adds c tau / 2).
    leakage complex128 (12, 16): leakage tone of each pair, in units of the mean return.
    dc_offset complex128 (16,): DC offset of each RX, in units of the mean return.
    iq_gain float64 (16,) (linear, 1 = none), iq_phase_rad float64 (16,).
    pattern_exponent : q of each antenna's power pattern cos(theta)^q.
    """

    tx_gain: np.ndarray = field(default_factory=lambda: np.ones(N_TX, np.complex128))
    rx_gain: np.ndarray = field(default_factory=lambda: np.ones(N_RX, np.complex128))
    tx_delay_m: np.ndarray = field(default_factory=lambda: np.zeros(N_TX))
    rx_delay_m: np.ndarray = field(default_factory=lambda: np.zeros(N_RX))
    leakage: np.ndarray = field(default_factory=lambda: np.zeros((N_TX, N_RX), np.complex128))
    dc_offset: np.ndarray = field(default_factory=lambda: np.zeros(N_RX, np.complex128))
    iq_gain: np.ndarray = field(default_factory=lambda: np.ones(N_RX))
    iq_phase_rad: np.ndarray = field(default_factory=lambda: np.zeros(N_RX))
    pattern_exponent: float = 0.0

    def pair_gain(self, chirp: Chirp) -> np.ndarray:
        """Complex gain of every pair at the chirp's centre frequency, complex128 (12, 16):
        T_t R_r exp(j 4 pi fc (d_t + d_r) / c), what a calibration measures as its phase."""
        d = self.pair_delay_m()
        return np.outer(self.tx_gain, self.rx_gain) * np.exp(1j * 4 * np.pi * chirp.fc_hz * d / C_M_PER_S)

    def effective_pair_gain(self, chirp: Chirp) -> np.ndarray:
        """:meth:`pair_gain` times the receivers' I/Q imbalance on a positive-frequency tone,
        mu_r = (1 + g_r exp(j psi_r)) / 2: the gain a corner calibration measures, complex128 (12, 16)."""
        mu = (1 + self.iq_gain * np.exp(1j * self.iq_phase_rad)) / 2
        return self.pair_gain(chirp) * mu[None, :]

    def pair_delay_m(self) -> np.ndarray:
        """Range offset of every pair, float64 (12, 16), metres."""
        return self.tx_delay_m[:, None] + self.rx_delay_m[None, :]


def draw_array_errors(levels: ArrayErrorLevels, rng: np.random.Generator | int | None = 0) -> ArrayErrors:
    """One random draw of the effects at ``levels`` (the perfect array for :data:`NONE`)."""
    g = np.random.default_rng(rng)

    def phases(n: int) -> np.ndarray:
        s = np.radians(levels.channel_phase_deg)
        return (
            g.uniform(-np.pi, np.pi, n)
            if levels.channel_phase_deg >= 180
            else g.normal(0.0, s, n)
            if s
            else np.zeros(n)
        )

    def amps(n: int) -> np.ndarray:
        return 10 ** (g.normal(0.0, levels.channel_amplitude_db, n) / 20) if levels.channel_amplitude_db else np.ones(n)

    def delays(n: int) -> np.ndarray:
        return g.normal(0.0, levels.channel_delay_mm * 1e-3, n) if levels.channel_delay_mm else np.zeros(n)

    def tones(shape, level_db) -> np.ndarray:
        if level_db is None:
            return np.zeros(shape, np.complex128)
        return 10 ** (level_db / 20) * np.exp(1j * g.uniform(-np.pi, np.pi, shape))

    return ArrayErrors(
        tx_gain=amps(N_TX) * np.exp(1j * phases(N_TX)),
        rx_gain=amps(N_RX) * np.exp(1j * phases(N_RX)),
        tx_delay_m=delays(N_TX),
        rx_delay_m=delays(N_RX),
        leakage=tones((N_TX, N_RX), levels.leakage_db),
        dc_offset=tones(N_RX, levels.dc_offset_db),
        iq_gain=10 ** (g.uniform(-1, 1, N_RX) * levels.iq_gain_db / 20),
        iq_phase_rad=np.radians(g.uniform(-1, 1, N_RX) * levels.iq_phase_deg),
        pattern_exponent=levels.pattern_exponent,
    )


def array_errors_stream(seed: int) -> np.random.Generator:
    """The random stream of a scenario seed's array draw (independent of its other streams)."""
    return np.random.default_rng([int(seed), 38])


def iq_imbalance(x: np.ndarray, gain: np.ndarray, phase_rad: np.ndarray) -> np.ndarray:
    """I/Q imbalance of receivers: Q' = g (sin(psi) I + cos(psi) Q), I' = I.

    x : complex (..., R, N); gain, phase_rad : (R,). Returns complex64 (..., R, N).
    """
    g = np.asarray(gain, np.float64)[:, None]
    p = np.asarray(phase_rad, np.float64)[:, None]
    i, q = x.real, x.imag
    return (i + 1j * g * (np.sin(p) * i + np.cos(p) * q)).astype(np.complex64)


def apply_array_errors(
    frames: np.ndarray,
    chirp: Chirp,
    errors: ArrayErrors,
    tx_body_m: np.ndarray,
    rx_body_m: np.ndarray,
    reference_power: float | None = None,
) -> np.ndarray:
    """The pair samples of a perfect array as the imperfect one delivers them.

    frames : complex (..., 12, 16, N), every TX-RX pair (:class:`~twinfocus.sensors.frames.RadarFrame`
        order); tx_body_m (12, 3), rx_body_m (16, 3): antenna positions, metres (the leakage
        tone's path is their separation); reference_power : the "mean return" the leakage and DC
        levels refer to (default: the mean |frames|^2).
    Returns complex64 (..., 12, 16, N). The beam pattern is not applied here (it depends on each
    scatterer's direction; the scene simulator applies it).
    """
    x = np.asarray(frames)
    if x.shape[-3:-1] != (N_TX, N_RX):
        raise TwinFocusError(f"frames must be (..., {N_TX}, {N_RX}, N), got {x.shape}")
    f = chirp.frequencies_hz
    delay = errors.pair_delay_m()
    gain = np.outer(errors.tx_gain, errors.rx_gain)
    y = x * (gain[..., None] * np.exp(1j * 4 * np.pi * f * delay[..., None] / C_M_PER_S))
    ref = float(np.mean(np.abs(x) ** 2)) if reference_power is None else float(reference_power)
    amp = np.sqrt(max(ref, 0.0))
    sep = np.linalg.norm(np.asarray(tx_body_m)[:, None, :] - np.asarray(rx_body_m)[None, :, :], axis=-1)
    leak = errors.leakage[..., None] * np.exp(1j * sep[..., None] * chirp.wavenumbers_rad_per_m)
    y = y + amp * (leak + errors.dc_offset[None, :, None])
    return iq_imbalance(y, errors.iq_gain, errors.iq_phase_rad)


def apply_array_errors_to_channels(
    data: np.ndarray,
    chirp: Chirp,
    errors: ArrayErrors,
    array: VirtualArray,
    z0_m: float,
    reference_power: float | None = None,
) -> np.ndarray:
    """The same effects on a scan's monostatic-equivalent channels (M, K, N).

    The multiplicative part commutes with the multistatic-to-monostatic correction; the
    additive part (leakage, DC) and the I/Q imbalance act on the raw pair samples, so the
    correction is undone around them (``z0_m`` the range it was made for). Leakage travels the
    pair's separation. Returns complex64 (M, K, N).
    """
    x = np.asarray(data)
    t, r = np.asarray(array.tx_index), np.asarray(array.rx_index)
    if x.ndim != 3 or x.shape[1] != t.size:
        raise TwinFocusError(f"data must be (M, {t.size}, N) for this array, got {x.shape}")
    k = chirp.wavenumbers_rad_per_m
    d2 = (np.asarray(array.separation_m) ** 2).sum(axis=1)
    undo = np.exp(1j * np.outer(d2, k) / (4.0 * z0_m))  # inverse of multistatic_to_monostatic
    f = chirp.frequencies_hz
    delay = errors.pair_delay_m()[t, r]
    gain = errors.tx_gain[t] * errors.rx_gain[r]
    raw = x * undo * (gain[:, None] * np.exp(1j * 4 * np.pi * f * delay[:, None] / C_M_PER_S))
    ref = float(np.mean(np.abs(x) ** 2)) if reference_power is None else float(reference_power)
    amp = np.sqrt(max(ref, 0.0))
    sep = np.sqrt(d2)
    leak = errors.leakage[t, r][:, None] * np.exp(1j * sep[:, None] * k)
    raw = raw + amp * (leak + errors.dc_offset[r][:, None])
    # I/Q imbalance per channel's receiver.
    g = errors.iq_gain[r][:, None]
    p = errors.iq_phase_rad[r][:, None]
    raw = raw.real + 1j * g * (np.sin(p) * raw.real + np.cos(p) * raw.imag)
    return (raw / undo).astype(np.complex64)
