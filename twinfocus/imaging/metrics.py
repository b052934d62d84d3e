"""Image-quality metrics: SSIM (Wang et al. 2004), sharpness and entropy, the oracle phase.

SSIM follows the classic definition: an 11 x 11 Gaussian window with sigma 1.5, constants
C1 = (0.01 L)^2 and C2 = (0.03 L)^2 with L the data range, local statistics with population
(not sample) covariance, averaged over the "valid" window positions (no padding), as in Wang's
reference MATLAB code and ``skimage.metrics.structural_similarity(gaussian_weights=True,
sigma=1.5, use_sample_covariance=False)``. Images smaller than 11 pixels use the largest odd
window that fits (same sigma).
"""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import C_M_PER_S, Chirp

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5


# torch is imported inside the functions that need it: the closed-form estimators and the
# metrics of ``focus`` run on numpy alone, and importing torch costs 1-3 s (docs/performance.md).


def _band_matrix_np(n: int, win: int, sigma: float) -> np.ndarray:
    """float64 (n - win + 1, n) matrix whose rows are the Gaussian window at each valid offset."""
    x = np.arange(win, dtype=np.float64) - (win - 1) / 2.0
    g = np.exp(-(x**2) / (2.0 * sigma**2))
    g /= g.sum()
    out = np.zeros((n - win + 1, n))
    for i in range(win):
        idx = np.arange(n - win + 1)
        out[idx, idx + i] = g[i]
    return out


def _band_matrix(n: int, win: int, sigma: float, dtype, device):
    import torch

    return torch.from_numpy(_band_matrix_np(n, win, sigma)).to(dtype=dtype, device=device)


def _ssim_window(h: int, w: int, window: int) -> int:
    win = min(window, h if h % 2 else h - 1, w if w % 2 else w - 1)
    if win < 1:
        raise TwinFocusError(f"image of {h} x {w} pixels is too small for SSIM")
    return win


def _ssim_map(mu_a, mu_b, e_aa, e_bb, e_ab, data_range: float):
    """SSIM map from the filtered moments (numpy arrays or torch tensors)."""
    var_a = e_aa - mu_a * mu_a
    var_b = e_bb - mu_b * mu_b
    cov = e_ab - mu_a * mu_b
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    return ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))


def ssim_torch(a, b, data_range: float = 1.0, window: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA):
    """Differentiable mean SSIM of two real images (H, W) (or batches (B, H, W)); a 0-d tensor
    (or (B,)). Separable Gaussian filtering as two small matrix products (faster than conv2d on
    CPU for these sizes, forward and backward), valid region only."""
    import torch

    if a.shape != b.shape:
        raise TwinFocusError(f"SSIM needs images of the same shape, got {tuple(a.shape)} and {tuple(b.shape)}")
    squeeze = a.dim() == 2
    if squeeze:
        a, b = a[None], b[None]
    h, w = a.shape[-2:]
    win = _ssim_window(h, w, window)
    gy = _band_matrix(h, win, sigma, a.dtype, a.device)
    gx = _band_matrix(w, win, sigma, a.dtype, a.device)
    # Five maps filtered at once: mu_a, mu_b, E[a^2], E[b^2], E[ab].
    stack = torch.stack([a, b, a * a, b * b, a * b], dim=1)  # (B, 5, H, W)
    filt = gy @ stack @ gx.T
    mu_a, mu_b, e_aa, e_bb, e_ab = filt.unbind(dim=1)
    smap = _ssim_map(mu_a, mu_b, e_aa, e_bb, e_ab, data_range)
    out = smap.mean(dim=(-2, -1))
    return out[0] if squeeze else out


def ssim(a: np.ndarray, b: np.ndarray, data_range: float = 1.0) -> float:
    """Mean SSIM of two real images (H, W), computed in float64 with numpy (the same arithmetic
    as :func:`ssim_torch`, which the optimiser differentiates)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.ndim != 2:
        raise TwinFocusError(f"SSIM needs 2-D images, got shape {a.shape}")
    if a.shape != b.shape:
        raise TwinFocusError(f"SSIM needs images of the same shape, got {a.shape} and {b.shape}")
    h, w = a.shape
    win = _ssim_window(h, w, SSIM_WINDOW)
    gy = _band_matrix_np(h, win, SSIM_SIGMA)
    gx = _band_matrix_np(w, win, SSIM_SIGMA)
    mu_a, mu_b, e_aa, e_bb, e_ab = (gy @ m @ gx.T for m in (a, b, a * a, b * b, a * b))
    return float(_ssim_map(mu_a, mu_b, e_aa, e_bb, e_ab, data_range).mean())


def normalise(amplitude, eps: float = 1e-30):
    """Divide by the maximum (works on numpy arrays and torch tensors)."""
    return amplitude / (amplitude.max() + eps)


def soft_threshold(normalised_amplitude, centre: float = 0.4, steepness: float = 1.0):
    """The paper's soft threshold sigmoid(steepness * (a - centre)) of a max-normalised amplitude.

    The defaults are the paper's sigmoid(a - 0.4). Works on numpy arrays and torch tensors.
    """
    if type(normalised_amplitude).__module__.startswith("torch"):
        import torch

        return torch.sigmoid(steepness * (normalised_amplitude - centre))
    return 1.0 / (1.0 + np.exp(-steepness * (np.asarray(normalised_amplitude) - centre)))


def display_image(image: np.ndarray, centre: float = 0.4, steepness: float = 1.0) -> np.ndarray:
    """Amplitude image -> max-normalised, soft-thresholded float64 image in which SSIM is taken."""
    amp = np.abs(np.asarray(image))
    if not np.isfinite(amp).all():
        raise TwinFocusError("image holds NaN or inf")
    return soft_threshold(normalise(amp.astype(np.float64)), centre, steepness)


def image_ssim(image: np.ndarray, truth: np.ndarray, centre: float = 0.4, steepness: float = 1.0) -> float:
    """The paper's metric: SSIM of the soft-thresholded image against the soft-thresholded image
    formed with the true positions (both max-normalised)."""
    return ssim(display_image(image, centre, steepness), display_image(truth, centre, steepness))


def sharpness(intensity: np.ndarray) -> float:
    """sum(I^2) / sum(I)^2 of an intensity image: larger is sharper."""
    i = np.asarray(intensity, dtype=np.float64)
    return float((i**2).sum() / max(i.sum() ** 2, 1e-300))


def image_sharpness(image: np.ndarray) -> float:
    """:func:`sharpness` of a complex image's intensity |image|^2 (any shape): 1 / the number of
    pixels its energy spreads over, larger when sharper. Scale-free: taken at unit peak in float64,
    since a capture's ADC counts put |I|^4 past float32's range (0.0 for an all-zero image)."""
    a = np.abs(np.asarray(image)).astype(np.float64)
    return sharpness((a / max(float(a.max()), 1e-300)) ** 2)


def entropy(intensity: np.ndarray) -> float:
    """Shannon entropy (nats) of the normalised intensity: smaller is sharper."""
    i = np.asarray(intensity, dtype=np.float64).ravel()
    p = i / max(i.sum(), 1e-300)
    p = p[p > 0]
    return float(-(p * np.log(p)).sum())


def oracle_phase(
    positions_true_m: np.ndarray, positions_m: np.ndarray, point_m: np.ndarray, chirp: Chirp
) -> np.ndarray:
    """The per-position phase correction that is exact at ``point_m``: float64 (M,) radians.

    phi_m = angle( sum_k exp(-j 4 pi fc (R_true_mk - R_tracked_mk) / c) ), the correction that
    undoes the motion error of position m as seen from the point (positions (M, K, 3)).
    """
    p = np.asarray(point_m, dtype=np.float64).reshape(1, 1, 3)
    r_true = np.linalg.norm(np.asarray(positions_true_m) - p, axis=-1)
    r_trk = np.linalg.norm(np.asarray(positions_m) - p, axis=-1)
    ph = -4.0 * np.pi * chirp.fc_hz * (r_true - r_trk) / C_M_PER_S
    return np.angle(np.exp(1j * ph).sum(axis=1))


def true_range_errors_m(positions_true_m: np.ndarray, positions_m: np.ndarray, point_m: np.ndarray) -> np.ndarray:
    """Each radar position's true range error as seen from ``point_m``: float64 (M,) metres, the
    mean over its channels of R_true - R_tracked (positions (M, K, 3), point (3,)). Unwrapped: the
    delay :func:`oracle_phase` takes the phase of, and what
    :func:`twinfocus.focus.band_delay.position_range_errors_m` reads from the scan."""
    p = np.asarray(point_m, dtype=np.float64).reshape(1, 1, 3)
    r_true = np.linalg.norm(np.asarray(positions_true_m, dtype=np.float64) - p, axis=-1)
    r_trk = np.linalg.norm(np.asarray(positions_m, dtype=np.float64) - p, axis=-1)
    return (r_true - r_trk).mean(axis=1)


def phase_error_rms(estimate_rad: np.ndarray, truth_rad: np.ndarray) -> float:
    """RMS of the wrapped difference after removing the best constant (phases are known only up
    to a constant): radians."""
    d = np.asarray(estimate_rad, dtype=np.float64) - np.asarray(truth_rad, dtype=np.float64)
    d = d - np.angle(np.exp(1j * d).mean())
    d = np.angle(np.exp(1j * d))
    return float(np.sqrt((d**2).mean()))


def transfer_bound_rad(
    positions_m: np.ndarray, reference_m: np.ndarray, target_m: np.ndarray, wavelength_m: float, tracking_error_m: float
) -> np.ndarray:
    """First-order bound on the phase-error difference between reference and target (paper eq. 7).

    |dphi_ref - dphi_tgt| <= (4 pi / lambda) |u_ref - u_tgt| |dp| per radar position, with u the
    unit line-of-sight vectors from the position's phase centre (channel mean) to the two points
    and |dp| the tracking error. positions_m (M, K, 3); returns float64 (M,) radians.
    """
    c = np.asarray(positions_m, dtype=np.float64).mean(axis=1)
    u_r = np.asarray(reference_m, float) - c
    u_t = np.asarray(target_m, float) - c
    u_r /= np.linalg.norm(u_r, axis=1, keepdims=True)
    u_t /= np.linalg.norm(u_t, axis=1, keepdims=True)
    return 4.0 * np.pi / wavelength_m * np.linalg.norm(u_r - u_t, axis=1) * float(tracking_error_m)
