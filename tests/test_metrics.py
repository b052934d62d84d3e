import numpy as np
import pytest
from skimage.metrics import structural_similarity

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.metrics import (
    image_ssim,
    oracle_phase,
    phase_error_rms,
    soft_threshold,
    ssim,
    true_range_errors_m,
)
from twinfocus.radar.fmcw import C_M_PER_S, Chirp


def _reference_ssim(a, b):
    # Wang et al.: Gaussian window sigma 1.5 (11 x 11), population covariance, data range 1
    return structural_similarity(a, b, data_range=1.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ssim_matches_skimage(seed):
    rng = np.random.default_rng(seed)
    a = rng.random((100, 100))
    yy, xx = np.mgrid[:100, :100]
    b = np.clip(0.5 * a + 0.5 * np.exp(-((xx - 40) ** 2 + (yy - 60) ** 2) / 300.0), 0, 1)
    assert ssim(a, b) == pytest.approx(_reference_ssim(a, b), abs=1e-6)
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    assert ssim(a, b) == pytest.approx(ssim(b, a), abs=1e-12)


def _bruteforce_ssim(a, b, win, sigma=1.5):
    """Wang et al.'s formula evaluated window by window (skimage fixes the window at 11 for sigma 1.5)."""
    g = np.exp(-((np.arange(win) - (win - 1) / 2) ** 2) / (2 * sigma**2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for i in range(a.shape[0] - win + 1):
        for j in range(a.shape[1] - win + 1):
            pa, pb = a[i : i + win, j : j + win], b[i : i + win, j : j + win]
            ma, mb = (w * pa).sum(), (w * pb).sum()
            va, vb = (w * (pa - ma) ** 2).sum(), (w * (pb - mb) ** 2).sum()
            cov = (w * (pa - ma) * (pb - mb)).sum()
            vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


def test_ssim_small_images_use_the_largest_window_that_fits():
    rng = np.random.default_rng(5)
    a, b = rng.random((8, 8)), rng.random((8, 8))
    assert ssim(a, b) == pytest.approx(_bruteforce_ssim(a, b, 7), abs=1e-9)
    big_a, big_b = rng.random((30, 30)), rng.random((30, 30))
    assert ssim(big_a, big_b) == pytest.approx(_bruteforce_ssim(big_a, big_b, 11), abs=1e-9)


def test_image_ssim_is_scale_invariant_and_rejects_nan():
    rng = np.random.default_rng(0)
    img = rng.random((20, 20)) + 1j * rng.random((20, 20))
    truth = img + 0.3 * rng.random((20, 20))
    assert image_ssim(img, truth) == pytest.approx(image_ssim(5 * img, 0.2 * truth), abs=1e-9)
    bad = img.copy()
    bad[0, 0] = np.nan
    with pytest.raises(TwinFocusError, match="NaN"):
        image_ssim(bad, truth)
    with pytest.raises(TwinFocusError, match="same shape"):
        ssim(np.zeros((4, 4)), np.zeros((5, 5)))


def test_soft_threshold_is_design_sigmoid():
    a = np.array([0.0, 0.4, 1.0])
    np.testing.assert_allclose(soft_threshold(a), 1 / (1 + np.exp(-(a - 0.4))))


def test_oracle_phase_closed_form_for_range_error():
    ch = Chirp()
    m, k = 50, 4
    true = np.zeros((m, k, 3))
    true[..., 0] = np.linspace(-1e-3, 1e-3, k)  # tiny array: all channels see the same range change
    dz = np.random.default_rng(0).normal(0, 0.5e-3, m)
    tracked = true.copy()
    tracked[..., 2] += dz[:, None]
    point = np.array([0.0, 0.0, 0.6])
    # tracked closer by dz -> true range is longer by dz -> correction -4 pi fc dz / c
    expected = np.angle(np.exp(-1j * 4 * np.pi * ch.fc_hz * dz / C_M_PER_S))
    got = oracle_phase(true, tracked, point, ch)
    assert phase_error_rms(got, expected) < 1e-3


def test_true_range_errors_are_the_injected_ones_and_the_oracle_phases_delay():
    ch = Chirp()
    m, k = 50, 4
    true = np.zeros((m, k, 3))
    true[..., 0] = np.linspace(-1e-3, 1e-3, k)
    dz = np.random.default_rng(2).normal(0, 2e-3, m)  # several wavelengths' worth: no wrapping here
    tracked = true.copy()
    tracked[..., 2] += dz[:, None]
    point = np.array([0.0, 0.0, 0.6])
    got = true_range_errors_m(true, tracked, point)
    np.testing.assert_allclose(got, dz, atol=1e-8)
    assert phase_error_rms(oracle_phase(true, tracked, point, ch), -4 * np.pi * ch.fc_hz * got / C_M_PER_S) < 1e-3


def test_phase_error_rms_ignores_constant_and_wrapping():
    rng = np.random.default_rng(1)
    truth = rng.uniform(-np.pi, np.pi, 100)
    assert phase_error_rms(truth + 2.0 + 2 * np.pi * rng.integers(-3, 3, 100), truth) < 1e-9
    assert phase_error_rms(truth + rng.normal(0, 0.1, 100), truth) == pytest.approx(0.1, rel=0.25)


def test_transfer_bound_closed_form():
    from twinfocus.imaging.metrics import transfer_bound_rad

    pos = np.zeros((1, 2, 3))  # one position at the origin
    z = 0.6
    half = np.deg2rad(10) / 2
    ref = np.array([-z * np.tan(half), 0, z])
    tgt = np.array([z * np.tan(half), 0, z])
    lam, dp = 3.9e-3, 0.5e-3
    # |u1 - u2| = 2 sin(theta / 2) for two unit vectors theta apart
    expected = 4 * np.pi / lam * 2 * np.sin(np.deg2rad(10) / 2) * dp
    assert transfer_bound_rad(pos, ref, tgt, lam, dp)[0] == pytest.approx(expected, rel=1e-9)
    # the paper's figure: 20 degrees and 0.5 mm stay below ~0.17 pi
    tgt20 = np.array([z * np.tan(np.deg2rad(20) - half), 0, z])
    assert transfer_bound_rad(pos, ref, tgt20, 4e-3, dp)[0] < 0.18 * np.pi
