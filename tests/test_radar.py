import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import (
    C_M_PER_S,
    Chirp,
    mmwcas_rx_positions_m,
    mmwcas_tx_positions_m,
    mmwcas_virtual_array,
    multistatic_to_monostatic,
    range_compress,
    range_profiles_at,
)


def point_if(chirp, path_m):
    """IF samples of one unit scatterer at (two-way path / 2) = path_m: the model, written out."""
    return np.exp(1j * 2 * np.pi * chirp.frequencies_hz * 2 * np.asarray(path_m)[..., None] / C_M_PER_S)


def test_chirp_defaults_match_design():
    ch = Chirp()
    assert ch.f0_hz == pytest.approx(76.6e9)
    assert ch.bandwidth_hz == pytest.approx(3.84e9)
    assert ch.range_resolution_m == pytest.approx(C_M_PER_S / (2 * 3.84e9))
    assert ch.max_range_m == pytest.approx(C_M_PER_S * 8e6 / (2 * 120e12))
    assert ch.frequencies_hz[-1] == pytest.approx(76.6e9 + 120e12 * 255 / 8e6)


def test_range_compress_peaks_at_target_with_centred_phase():
    ch = Chirp()
    r = 0.6123
    prof = range_compress(point_if(ch, r), ch, n_fft=4096)
    axis = ch.range_axis_m(4096)
    b = int(np.argmax(np.abs(prof)))
    assert abs(axis[b] - r) <= axis[1] / 2 + 1e-12
    # at the exact range the zoomed profile is real-positive times exp(+j 4 pi fc R / c)
    exact = range_profiles_at(point_if(ch, r), ch, np.array([r]))[0]
    assert abs(exact) == pytest.approx(ch.n_samples, rel=1e-4)
    expected_phase = 4 * np.pi * ch.fc_hz * r / C_M_PER_S
    assert np.angle(exact * np.exp(-1j * expected_phase)) == pytest.approx(0, abs=1e-3)


def test_zoomed_profiles_equal_fft_profiles_on_bins():
    ch = Chirp()
    rng = np.random.default_rng(1)
    data = (rng.standard_normal((3, ch.n_samples)) + 1j * rng.standard_normal((3, ch.n_samples))).astype(np.complex64)
    fft = range_compress(data, ch, n_fft=1024)
    bins = np.array([5, 17, 300])
    zoom = range_profiles_at(data, ch, ch.range_axis_m(1024)[bins])
    np.testing.assert_allclose(zoom, fft[:, bins], rtol=1e-4, atol=1e-3)


def test_mmwcas_virtual_line_is_86_channels_at_quarter_wavelength():
    va = mmwcas_virtual_array()
    assert va.n_channels == 86
    steps = np.diff(va.offsets_m[:, 0])
    # lambda/4 at TI's design frequency of the board's antennas, 76.8 GHz (module_param.m)
    np.testing.assert_allclose(steps, C_M_PER_S / 76.8e9 / 4, rtol=1e-9)
    assert steps[0] == pytest.approx(0.9759e-3, abs=1e-7)
    assert np.ptp(va.offsets_m[:, 1]) == 0  # one line
    # each channel sits at the midpoint of its TX and RX
    tx, rx = mmwcas_tx_positions_m(), mmwcas_rx_positions_m()
    mid = (tx[va.tx_index] + rx[va.rx_index]) / 2
    np.testing.assert_allclose(mid[:, 0] - mid[:, 0].mean(), va.offsets_m[:, 0], atol=1e-12)
    assert len(set(zip(va.tx_index, va.rx_index))) == 86


def test_multistatic_correction_removes_bistatic_excess_phase():
    ch = Chirp()
    z0 = 0.6
    sep = np.array([[0.03, 0.067], [0.01, 0.0]])
    # TX at +sep/2, RX at -sep/2 around a midpoint on boresight of a point at z0
    paths = []
    for d in sep:
        tx = np.array([d[0] / 2, d[1] / 2, 0.0])
        rx = -tx
        p = np.array([0.0, 0.0, z0])
        paths.append((np.linalg.norm(p - tx) + np.linalg.norm(p - rx)) / 2)
    bistatic = point_if(ch, np.array(paths))
    mono = point_if(ch, np.array([z0, z0]))
    fixed = multistatic_to_monostatic(bistatic, ch, sep, z0)
    resid_before = np.abs(np.angle(bistatic * mono.conj())).max()
    resid_after = np.abs(np.angle(fixed * mono.conj())).max()
    assert resid_before > 1.0
    assert resid_after < 0.02


def test_bad_inputs_are_named():
    ch = Chirp()
    with pytest.raises(TwinFocusError, match="slope"):
        Chirp(slope_hz_per_s=-1)
    with pytest.raises(TwinFocusError, match="samples"):
        range_compress(np.zeros((2, 100), np.complex64), ch)
    with pytest.raises(TwinFocusError, match="n_fft"):
        range_compress(np.zeros((2, 256), np.complex64), ch, n_fft=100)
    with pytest.raises(TwinFocusError, match="separation"):
        multistatic_to_monostatic(np.zeros((3, 256), np.complex64), ch, np.zeros((2, 2)), 0.6)
