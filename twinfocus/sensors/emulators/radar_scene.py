"""What a TDM-MIMO radar would record from point scatterers: per TX-RX pair, the bistatic path.

Used by the emulated devices (the fake capture board, the capture-folder generator) so that a
live graph on loopback images a real scene. Model (docs/architecture.md section 2 with the bistatic
range R = (R_tx + R_rx) / 2):

    s[t, r, n] = sum_j a_j exp(+j k_n (|p_j - tx_t| + |p_j - rx_r|)),   k_n = 2 pi (f0 + S n / fs) / c
"""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import Poses
from twinfocus.radar.array_errors import apply_array_errors
from twinfocus.radar.fmcw import C_M_PER_S, Chirp
from twinfocus.sensors.frames import mmwcas_antenna_positions_body_m


def simulate_mimo_frames(
    chirp: Chirp,
    poses: Poses,
    scatterers_m: np.ndarray,
    amplitudes: np.ndarray | None = None,
    tx_body_m: np.ndarray | None = None,
    rx_body_m: np.ndarray | None = None,
    chunk: int = 8,
    pattern_exponent: float = 0.0,
) -> np.ndarray:
    """IF samples of every TX-RX pair at every radar pose.

    chirp : the chirp; poses : radar body poses (M) in the scene frame;
    scatterers_m : float (J, 3) scene-frame points; amplitudes : complex (J,), default 1;
    tx_body_m, rx_body_m : antenna positions in the body frame (default the MMWCAS board);
    pattern_exponent : q of each antenna's power pattern cos(theta)^q, theta off the body's z
        axis (0, the default: isotropic antennas; see :mod:`twinfocus.radar.array_errors`).
    Returns complex64 (M, n_tx, n_rx, N).
    """
    pts = np.asarray(scatterers_m, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise TwinFocusError(f"scatterers_m must be (J, 3) with J >= 1, got {pts.shape}")
    amp = np.ones(pts.shape[0], np.complex128) if amplitudes is None else np.asarray(amplitudes, np.complex128)
    if amp.shape != (pts.shape[0],):
        raise TwinFocusError(f"amplitudes must be ({pts.shape[0]},), got {amp.shape}")
    if tx_body_m is None or rx_body_m is None:
        tx_default, rx_default = mmwcas_antenna_positions_body_m()
        tx_body_m = tx_default if tx_body_m is None else tx_body_m
        rx_body_m = rx_default if rx_body_m is None else rx_body_m
    tx_b = np.asarray(tx_body_m, np.float64)
    rx_b = np.asarray(rx_body_m, np.float64)
    rot = poses.rotation_matrices()
    k = chirp.wavenumbers_rad_per_m
    m_total = len(poses)
    out = np.zeros((m_total, tx_b.shape[0], rx_b.shape[0], chirp.n_samples), dtype=np.complex64)
    for m0 in range(0, m_total, max(1, int(chunk))):
        sl = slice(m0, min(m_total, m0 + max(1, int(chunk))))
        tx = np.einsum("mij,tj->mti", rot[sl], tx_b) + poses.position_m[sl, None, :]
        rx = np.einsum("mij,rj->mri", rot[sl], rx_b) + poses.position_m[sl, None, :]
        acc = np.zeros(out[sl].shape, dtype=np.complex128)
        for j in range(pts.shape[0]):
            r_tx = np.linalg.norm(tx - pts[j], axis=-1)  # (m, T)
            r_rx = np.linalg.norm(rx - pts[j], axis=-1)  # (m, R)
            path = r_tx[:, :, None] + r_rx[:, None, :]
            term = amp[j] * np.exp(1j * path[..., None] * k)
            if pattern_exponent:
                # Amplitude cos(theta)^(q/2) per antenna, theta between boresight and the ray.
                bore = rot[sl][:, :, 2]  # (m, 3) body z in the scene frame
                cos_t = np.einsum("mti,mi->mt", pts[j] - tx, bore) / r_tx
                cos_r = np.einsum("mri,mi->mr", pts[j] - rx, bore) / r_rx
                g = np.clip(cos_t, 0, 1)[:, :, None] * np.clip(cos_r, 0, 1)[:, None, :]
                term = term * (g ** (pattern_exponent / 2))[..., None]
            acc += term
        out[sl] = acc
    return out


def quantize_iq(samples: np.ndarray, full_scale: float | None = None, headroom: float = 0.5) -> np.ndarray:
    """Complex samples as the ADC's int16 (I, Q) pairs.

    samples : complex (...); full_scale : the magnitude mapped to ``headroom * 32767``
    (default the largest |I| or |Q| present). Returns int16 (..., 2).
    """
    x = np.asarray(samples)
    peak = (
        float(max(np.abs(x.real).max(initial=0.0), np.abs(x.imag).max(initial=0.0)))
        if full_scale is None
        else float(full_scale)
    )
    scale = headroom * 32767.0 / peak if peak > 0 else 1.0
    iq = np.stack([x.real, x.imag], axis=-1) * scale
    return np.clip(np.round(iq), -32768, 32767).astype(np.int16)


def monostatic_if(chirp: Chirp, centres_m: np.ndarray, scatterers_m: np.ndarray, amplitudes=None) -> np.ndarray:
    """The project's monostatic IF model at phase centres (..., 3): complex128 (..., N).

    s_n = sum_j a_j exp(+j 2 pi (f0 + S t_n) 2 R_j / c): what :func:`frame_to_virtual_channels`
    should reproduce from the bistatic pairs.
    """
    c = np.asarray(centres_m, np.float64)
    pts = np.asarray(scatterers_m, np.float64)
    amp = np.ones(pts.shape[0]) if amplitudes is None else np.asarray(amplitudes)
    f = chirp.frequencies_hz
    out = np.zeros(c.shape[:-1] + (chirp.n_samples,), np.complex128)
    for j in range(pts.shape[0]):
        r = np.linalg.norm(c - pts[j], axis=-1)
        out += amp[j] * np.exp(1j * 2 * np.pi * f * 2 * r[..., None] / C_M_PER_S)
    return out


def imperfect_mimo_frames(
    chirp: Chirp,
    poses: Poses,
    scatterers_m: np.ndarray,
    errors,
    amplitudes: np.ndarray | None = None,
    snr_db: float | None = None,
    rng: np.random.Generator | int | None = 0,
) -> np.ndarray:
    """:func:`simulate_mimo_frames` through the MMWCAS board as hardware is.

    errors : a :class:`twinfocus.radar.array_errors.ArrayErrors` (its beam pattern, channel errors,
    leakage, DC offset and I/Q imbalance; leakage and DC refer to the scene's mean return);
    snr_db : per-sample SNR of thermal noise added before the receivers' imperfections (None:
    none). Returns complex64 (M, 12, 16, N).
    """
    tx, rx = mmwcas_antenna_positions_body_m()
    clean = simulate_mimo_frames(
        chirp, poses, scatterers_m, amplitudes, tx, rx, pattern_exponent=errors.pattern_exponent
    )
    power = float(np.mean(np.abs(clean) ** 2))
    x = clean
    if snr_db is not None:
        g = np.random.default_rng(rng)
        sd = np.sqrt(power / 10 ** (snr_db / 10) / 2)
        x = clean + (sd * (g.standard_normal(clean.shape) + 1j * g.standard_normal(clean.shape))).astype(np.complex64)
    return apply_array_errors(x, chirp, errors, tx, rx, reference_power=power)
