import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import paper_raster, phase_centres
from twinfocus.radar.fmcw import C_M_PER_S, Chirp, mmwcas_virtual_array, range_compress
from twinfocus.simulation.if_simulator import add_thermal_noise, simulate_if, simulate_if_exact


def _rel_err(a, b):
    return float(np.linalg.norm(a.astype(np.complex128) - b) / np.linalg.norm(b))


@pytest.fixture(scope="module")
def small_case():
    """3 raster positions x 86 MMWCAS channels, 300 speckled points around 0.6 m."""
    rng = np.random.default_rng(0)
    pos = phase_centres(paper_raster(), mmwcas_virtual_array())[[0, 400, 779]]
    pts = np.column_stack(
        [rng.uniform(-0.1, 0.1, 300), rng.uniform(-0.07, 0.07, 300), 0.6 + rng.uniform(-0.02, 0.02, 300)]
    )
    amp = np.exp(2j * np.pi * rng.random(300)) * rng.uniform(0.2, 1.0, 300)
    return pts, amp, pos, simulate_if_exact(pts, amp, pos, Chirp())


def test_exact_sum_of_one_point_is_the_model():
    chirp = Chirp(n_samples=64)
    p = np.array([[0.01, -0.02, 0.55]])
    e = np.array([[[0.0, 0.0, 0.0], [0.3, 0.1, -0.05]]])
    out = simulate_if_exact(p, [0.5 - 0.2j], e, chirp)
    r = np.linalg.norm(p[0] - e[0], axis=1)
    f = chirp.f0_hz + chirp.slope_hz_per_s * np.arange(64) / chirp.fs_hz
    expected = (0.5 - 0.2j) * np.exp(1j * 2 * np.pi * f[None, :] * 2 * r[:, None] / C_M_PER_S)
    np.testing.assert_allclose(out[0], expected, rtol=0, atol=2e-6)


def test_fast_matches_exact_sum(small_case):
    pts, amp, pos, exact = small_case
    fast = simulate_if(pts, amp, pos, Chirp())
    assert fast.dtype == np.complex64 and fast.shape == (3, 86, 256)
    # Bound of the default step/order: 8.7e-5 per scatterer; hold the total below 1e-3.
    assert _rel_err(fast, exact) < 1e-3


def test_fast_error_is_second_order_in_the_step(small_case):
    pts, amp, pos, exact = small_case
    coarse = _rel_err(simulate_if(pts, amp, pos, Chirp(), range_step_m=4e-3, order=1), exact)
    fine = _rel_err(simulate_if(pts, amp, pos, Chirp(), range_step_m=2e-3, order=1), exact)
    # One Taylor term beyond the carrier: the remainder scales as h^2.
    assert 3.0 < coarse / fine < 5.0
    assert coarse < (80.5 * 4e-3 / 2) ** 2 / 2


def test_fast_matches_exact_at_long_range():
    """Several metres out, far from the origin: phases of ~1e5 rad that float32 could not hold."""
    rng = np.random.default_rng(1)
    pos = phase_centres(paper_raster(n_columns=2, n_rows=2, z_m=0.3), mmwcas_virtual_array()) + [2.0, -1.0, 0.0]
    pts = np.array([3.0, 0.5, 6.5]) + rng.uniform(-0.15, 0.15, (200, 3))
    amp = np.exp(2j * np.pi * rng.random(200))
    chirp = Chirp()
    exact = simulate_if_exact(pts, amp, pos, chirp)
    fast = simulate_if(pts, amp, pos, chirp)
    assert _rel_err(fast, exact) < 1e-3


def test_single_point_range_profile_peaks_at_its_range():
    chirp = Chirp()
    pos = np.zeros((1, 1, 3))
    r_true = 0.6537
    data = simulate_if(np.array([[0.0, 0.0, r_true]]), None, pos, chirp)
    n_fft = 8192
    prof = range_compress(data, chirp, n_fft=n_fft)[0, 0]
    axis = chirp.range_axis_m(n_fft)
    peak = int(np.argmax(np.abs(prof)))
    assert abs(axis[peak] - r_true) <= axis[1] / 2 + 1e-12
    # Across the main lobe its phase is the carrier at the band centre, 4 pi fc R / c
    # (radar.range_compress refers phases to the chirp centre).
    expected = np.exp(1j * 4 * np.pi * chirp.fc_hz * r_true / C_M_PER_S)
    assert abs(np.angle(prof[peak] * np.conj(expected))) < 1e-3


def test_chunks_and_progress_do_not_change_the_result(small_case):
    pts, amp, pos, _ = small_case
    calls = []
    one = simulate_if(pts, amp, pos, Chirp(), chunk_positions=1, progress=lambda d, t: calls.append((d, t)))
    whole = simulate_if(pts, amp, pos, Chirp())
    assert calls == [(1, 3), (2, 3), (3, 3)]
    # Range nodes sit on one global lattice, so chunking changes nothing beyond rounding.
    assert _rel_err(one, whole.astype(np.complex128)) < 1e-6


def test_bad_inputs_raise():
    chirp = Chirp(n_samples=16)
    pos = np.zeros((2, 3, 3))
    pts = np.array([[0.0, 0.0, 1.0]])
    with pytest.raises(TwinFocusError, match="NaN"):
        simulate_if([[0.0, np.nan, 1.0]], None, pos, chirp)
    with pytest.raises(TwinFocusError, match=r"\(P, 3\)"):
        simulate_if(np.zeros((4, 2)), None, pos, chirp)
    with pytest.raises(TwinFocusError, match="empty"):
        simulate_if(np.zeros((0, 3)), None, pos, chirp)
    with pytest.raises(TwinFocusError, match="amplitudes"):
        simulate_if(pts, np.ones(2), pos, chirp)
    with pytest.raises(TwinFocusError, match="positions_m"):
        simulate_if(pts, None, np.zeros((2, 3)), chirp)
    with pytest.raises(TwinFocusError, match="positions_m holds NaN"):
        simulate_if(pts, None, np.full((2, 3, 3), np.inf), chirp)
    with pytest.raises(TwinFocusError, match="range_step_m"):
        simulate_if(pts, None, pos, chirp, range_step_m=0.0)
    with pytest.raises(TwinFocusError, match="order"):
        simulate_if(pts, None, pos, chirp, order=9)
    with pytest.raises(TwinFocusError, match="Chirp"):
        simulate_if(pts, None, pos, "chirp")
    with pytest.raises(TwinFocusError, match="NaN"):
        simulate_if_exact(pts, [np.nan], pos, chirp)


def test_thermal_noise_snr_definition():
    rng = np.random.default_rng(0)
    data = (rng.standard_normal((40, 20, 256)) * 3 + 1j).astype(np.complex64)
    noisy = add_thermal_noise(data, 10.0, rng=1)
    assert noisy.dtype == np.complex64 and noisy.shape == data.shape
    noise = noisy.astype(np.complex128) - data
    p_signal = np.mean(np.abs(data.astype(np.complex128)) ** 2)
    assert np.mean(np.abs(noise) ** 2) == pytest.approx(p_signal / 10.0, rel=0.01)
    assert noise.real.var() == pytest.approx(noise.imag.var(), rel=0.02)
    assert abs(noise.mean()) < 0.01 * np.sqrt(p_signal)
    np.testing.assert_array_equal(add_thermal_noise(data, 3.0, rng=5), add_thermal_noise(data, 3.0, rng=5))
    with pytest.raises(TwinFocusError, match="zeros"):
        add_thermal_noise(np.zeros((2, 2), np.complex64), 10.0)
    with pytest.raises(TwinFocusError, match="snr_db"):
        add_thermal_noise(data, float("nan"))
    with pytest.raises(TwinFocusError, match="complex"):
        add_thermal_noise(np.ones(4), 10.0)
