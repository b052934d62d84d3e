"""Range errors from the band's halves (twinfocus.focus.band_delay) against the injected position errors,
and the transfer that uses them to find a misplaced outline's ramp once every phase has wrapped."""

import numpy as np
import pytest

from tests.test_template_match import GRID, Z, _outline, _rough_f_samples
from twinfocus.errors import TwinFocusError
from twinfocus.focus.autofocus import MIN_RANGED_RAMP_COHERENCE_SQRT_M, AutofocusConfig, transfer_phase
from twinfocus.focus.band_delay import bright_pixels, half_band_chirps, half_band_data, position_range_errors_m
from twinfocus.focus.estimators import AUTO_REFINE_BELOW_COHERENCE, estimator_settings
from twinfocus.focus.phase_ramp import fit_linear_phase
from twinfocus.focus.pipeline import Bases, Reference, upper_band_basis
from twinfocus.focus.plan import FocusPlan
from twinfocus.imaging.backprojection.numba_backend import subimage_basis
from twinfocus.imaging.metrics import oracle_phase, true_range_errors_m
from twinfocus.radar.fmcw import Chirp


def _rough_f_scan(z_sigma_m):
    """The rough 'F' of test_template_match seen from 400 positions with ``z_sigma_m`` of z
    jitter. Returns the chirp, true and tracked positions, the samples and the basis."""
    _, _, ch, true, tracked, data = _rough_f_samples(5, z_sigma_m, n_columns=4, n_rows=100, row_pitch_m=0.001)
    return ch, true, tracked, data, subimage_basis(data, tracked, ch, GRID)


@pytest.fixture(scope="module")
def wrapped():
    """1 mm of z jitter: every phase wraps."""
    return _rough_f_scan(1e-3)


def test_the_halves_of_the_band_tile_it():
    ch = Chirp()
    low, high = half_band_chirps(ch)
    assert low.n_samples + high.n_samples == ch.n_samples
    assert low.f0_hz == ch.f0_hz
    # the upper half starts one sample after the lower half's last one
    assert high.f0_hz == pytest.approx(low.frequencies_hz[-1] + ch.slope_hz_per_s / ch.fs_hz)
    assert np.allclose(np.concatenate([low.frequencies_hz, high.frequencies_hz]), ch.frequencies_hz)
    data = np.arange(2 * 3 * 256).reshape(2, 3, 256).astype(np.complex64)
    lo, hi = half_band_data(data, ch)
    assert np.array_equal(np.concatenate([lo, hi], axis=-1), data)
    # an odd count: the upper half takes the extra sample, and the two still tile the band
    odd = Chirp(n_samples=255)
    low, high = half_band_chirps(odd)
    assert (low.n_samples, high.n_samples) == (127, 128)
    assert np.allclose(np.concatenate([low.frequencies_hz, high.frequencies_hz]), odd.frequencies_hz)
    with pytest.raises(TwinFocusError, match="at least 4 samples"):
        half_band_chirps(Chirp(n_samples=3))


def test_bright_pixels_hold_the_asked_share_of_the_energy():
    rng = np.random.default_rng(0)
    image = rng.normal(size=(20, 30)) + 1j * rng.normal(size=(20, 30))
    energy = np.abs(image) ** 2
    for fraction in (0.5, 0.9, 0.99, 1.0):
        got = bright_pixels(image, fraction)
        assert energy[got].sum() >= fraction * energy.sum() - 1e-9
        # the fewest pixels that do: without the dimmest chosen one the share falls short
        assert energy[got].sum() - energy[got].min() < fraction * energy.sum()
        assert energy[got].min() >= energy[~got].max(initial=0)
    with pytest.raises(TwinFocusError, match="fraction"):
        bright_pixels(image, 0.0)
    with pytest.raises(TwinFocusError, match="no finite energy"):
        bright_pixels(np.zeros((3, 3)))


@pytest.mark.slow  # 8 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_range_errors_follow_the_injected_ones_and_ignore_the_images_place(wrapped):
    ch, true, tracked, data, basis = wrapped
    high = upper_band_basis(data, tracked, ch, GRID)(np.ones(GRID.shape, bool)).reshape(basis.shape)
    # the halves' bases add up to the whole band's (one back-projection saved)
    low = subimage_basis(half_band_data(data, ch)[0], tracked, half_band_chirps(ch)[0], GRID)
    assert np.linalg.norm(basis - high - low) < 0.01 * np.linalg.norm(basis)
    centre = np.array([0.0, 0.0, Z])
    truth = true_range_errors_m(true, tracked, centre)
    oracle = oracle_phase(true, tracked, centre, ch)
    assert np.abs(np.exp(1j * oracle).mean()) * np.sqrt(oracle.size) < 2.5  # every phase wrapped
    rng = np.random.default_rng(1)
    phase = oracle + rng.normal(0, 0.3, oracle.size)  # an estimate good to 0.3 rad
    ap = tracked.mean(axis=1)[:, :2]
    ramp = 16.0 * ap[:, 1]  # what an outline 2 mm off across y pulls in (4 pi dy / (lambda R))
    got = position_range_errors_m(basis - high, high, phase, ch)
    moved = position_range_errors_m(basis - high, high, phase + ramp, ch)
    assert np.corrcoef(got, truth)[0, 1] > 0.8
    slope = np.polyfit(truth, got, 1)[0]
    assert 0.4 < slope < 1.1  # pulled toward 0 by each position's own share of the image
    # the image's place hardly enters (the ramp is the same in both halves; each half's image
    # moves by its own k_c / k, a few percent apart)
    assert np.std((moved - got) - (moved - got).mean()) < 0.15 * np.std(truth)
    with pytest.raises(TwinFocusError, match="one shape"):
        position_range_errors_m(basis, high[:, :5], phase, ch)
    with pytest.raises(TwinFocusError, match="mask"):
        upper_band_basis(data, tracked, ch, GRID)(np.ones((3, 3), bool))
    with pytest.raises(TwinFocusError, match="one value per radar position"):
        position_range_errors_m(basis - high, high, phase[:-1], ch)


def test_the_transfer_finds_a_wrapped_estimates_ramp_with_the_range_errors():
    """Synthetic: 1 mm of range error (wrapped phases) plus a misplacement's ramp; the fit sees
    the ramp only with the range errors taken out."""
    rng = np.random.default_rng(2)
    lam, m = 3.9e-3, 800
    ap = np.column_stack([rng.uniform(-0.1, 0.1, m), rng.uniform(-0.1, 0.1, m)])
    dr = rng.normal(0, 1e-3, m)
    slope = np.array([-6.0, 20.0])  # rad/m: the image moved by (-0.5, +1.9) mm at 0.25 m
    phase = np.angle(np.exp(1j * (-4 * np.pi / lam * dr + ap @ slope + 0.7)))
    measured = 0.7 * dr + rng.normal(0, 0.3e-3, m)  # what the halves give: scaled down, noisy
    kept, info = transfer_phase(phase, ap, 0.25, lam, "auto")
    assert not info["from_range_errors"] and np.allclose(info["slope_rad_per_m"], 0)  # the ramp is out of sight
    out, info = transfer_phase(phase, ap, 0.25, lam, "auto", range_errors_m=measured)
    assert (
        info["removed"]
        and info["from_range_errors"]
        and info["ramp_coherence_sqrt_m"] > MIN_RANGED_RAMP_COHERENCE_SQRT_M
    )
    assert np.allclose(info["slope_rad_per_m"], slope, atol=2.0)
    # what was taken is the ramp alone: the rest of the estimate is untouched
    left = np.angle(np.exp(1j * (phase - out)))
    assert fit_linear_phase(left, ap, min_coherence_sqrt_m=0)[1][1:] == pytest.approx(slope, abs=2.0)
    assert np.std(np.angle(np.exp(1j * (left - ap @ np.asarray(info["slope_rad_per_m"]))))) < 1e-6
    # range errors that explain nothing leave the ramp out of sight: nothing is moved
    _, info = transfer_phase(phase, ap, 0.25, lam, "auto", range_errors_m=rng.normal(0, 1e-3, m))
    assert info["ramp_coherence_sqrt_m"] < MIN_RANGED_RAMP_COHERENCE_SQRT_M and np.allclose(info["slope_rad_per_m"], 0)
    # a registered template's estimate keeps its ramp whatever the range errors say
    _, info = transfer_phase(phase, ap, 0.25, lam, "auto", registered=True, range_errors_m=measured)
    assert not info["removed"]
    with pytest.raises(TwinFocusError, match="range_errors_m"):
        transfer_phase(phase, ap, 0.25, lam, "auto", range_errors_m=measured[:-1])


@pytest.mark.slow  # 72 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_focus_places_a_misplaced_outline_by_the_band_halves(wrapped):
    """An outline 2 px off across y (a camera's offset): the outline estimator keeps it there once
    the phases wrap; with the upper band's basis the transfer moves the image back, and the
    report no longer warns that nothing placed it."""
    from twinfocus.focus.template_match import _shift_mask

    ch, true, tracked, data, basis = wrapped
    support = _shift_mask(_outline(GRID), 2, 0)
    oracle = oracle_phase(true, tracked, np.array([0.0, 0.0, Z]), ch)
    ap = tracked.mean(axis=1)[:, :2]
    cfg = AutofocusConfig(**estimator_settings("auto", False, has_support=True))
    reference = Reference(template=support.astype(np.float32), support=support)
    calls = []

    def upper(pixels):
        calls.append(pixels.mean())
        return upper_band_basis(data, tracked, ch, GRID)(pixels)

    runs = {}
    for name, band in (("without", None), ("with", upper)):
        out = FocusPlan.make(config=cfg).focus_bases(
            Bases(basis, basis, tracked, ch, GRID, GRID, upper_band=band),
            reference,
        )
        _, coeffs = fit_linear_phase(np.angle(np.exp(1j * (out.phase_rad - oracle))), ap, min_coherence_sqrt_m=0)
        runs[name] = (abs(coeffs[2]) * (Z - tracked[..., 2].mean()) * ch.wavelength_m / (4 * np.pi), out.metrics)
    assert len(calls) == 1 and 0.05 < calls[0] < 0.8  # once, on the reference's bright pixels
    off_without, m_without = runs["without"]
    off_with, m_with = runs["with"]
    assert off_without > 1.5e-3  # the outline's 2 px (3.9 mm) off across y, most of it kept
    assert off_with < 0.5 * off_without
    assert m_with["phase_ramp"]["from_range_errors"] and m_with["phase_ramp"]["removed"]
    placed = m_with["confidence"]["placement_by_band_halves"]
    assert placed["removed"] and placed["ramp_coherence_sqrt_m"] >= MIN_RANGED_RAMP_COHERENCE_SQRT_M
    # wrapped either way, so flagged either way: placed by the halves, the report says the place
    # may still be a few mm off; not placed, that nothing checked where the outline put it
    for m, says, not_says in (
        (m_with, "placed the reference", "cannot check"),
        (m_without, "cannot check", "placed the reference"),
    ):
        conf = m["confidence"]
        assert conf["phase_coherence_sqrt_m"] < AUTO_REFINE_BELOW_COHERENCE and not conf["trusted"]
        wrapped = [w for w in conf["warnings"] if "phases have wrapped" in w]
        assert len(wrapped) == 1 and says in wrapped[0] and not_says not in wrapped[0]


@pytest.mark.slow  # 11 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_focus_asks_the_band_halves_when_a_coherent_estimates_ramp_is_too_large():
    """0.2 mm of jitter (the phases hold together) and an amplitude template 3 px (5.8 mm) off
    across y: the plain ramp fit sees the shift but keeps it (more than the 3 mm a misplacement is
    allowed: it could be tracking error); the range errors show it is not, and it is removed."""
    from twinfocus.focus.template_match import shift_image
    from twinfocus.imaging.backprojection.numba_backend import backproject

    ch, true, tracked, data, basis = _rough_f_scan(0.2e-3)
    template = np.abs(shift_image(backproject(data, true, ch, GRID), 3, 0))
    oracle = oracle_phase(true, tracked, np.array([0.0, 0.0, Z]), ch)
    ap = tracked.mean(axis=1)[:, :2]
    cfg = AutofocusConfig(**estimator_settings("projection", False))
    off = {}
    for name, band in (("without", None), ("with", upper_band_basis(data, tracked, ch, GRID))):
        out = FocusPlan.make(config=cfg).focus_bases(
            Bases(basis, basis, tracked, ch, GRID, GRID, upper_band=band),
            Reference(template=template),
        )
        _, coeffs = fit_linear_phase(np.angle(np.exp(1j * (out.phase_rad - oracle))), ap, min_coherence_sqrt_m=0)
        off[name] = (
            abs(coeffs[2]) * (Z - tracked[..., 2].mean()) * ch.wavelength_m / (4 * np.pi),
            out.metrics["phase_ramp"],
        )
    assert off["without"][0] > 4e-3 and not off["without"][1]["removed"]  # kept as if it were tracking error
    assert off["with"][0] < 1e-3 and off["with"][1]["removed"]
    assert off["with"][1]["asked_range_errors_because"] == "its ramp is larger than a misplacement explains"


def test_place_estimate_moves_back_a_known_misplacement_of_the_exact_phase(wrapped):
    """The true phase moved by the ramp of a 2.5 mm misplacement across y (what an outline the
    camera put there does to an exact estimate), every phase wrapped: the plain fit alone cannot
    see the ramp and keeps it; with the band's halves most of it is taken out, and the true phase
    itself is moved by less than that."""
    from twinfocus.focus.plan import place_estimate

    ch, true, tracked, data, basis = wrapped
    oracle = oracle_phase(true, tracked, np.array([0.0, 0.0, Z]), ch)
    ap = tracked.mean(axis=1)[:, :2]
    depth = Z - tracked[..., 2].mean()
    k = 4 * np.pi / ch.wavelength_m
    moved = oracle + k / depth * (ap[:, 1] - ap[:, 1].mean()) * 2.5e-3
    band = upper_band_basis(data, tracked, ch, GRID)

    def left_off_m(phase):
        _, coeffs = fit_linear_phase(np.angle(np.exp(1j * (phase - oracle))), ap, min_coherence_sqrt_m=0)
        return np.abs(coeffs[1:]) * depth / k

    kept, info, seconds = place_estimate(moved, basis, tracked, ch, GRID)
    assert seconds is None and not info["from_range_errors"] and not any(info["slope_rad_per_m"])
    assert left_off_m(kept)[1] == pytest.approx(2.5e-3, abs=0.1e-3)
    placed, info, seconds = place_estimate(moved, basis, tracked, ch, GRID, upper_band=band)
    assert seconds is not None and info["from_range_errors"] and info["removed"]
    assert info["asked_range_errors_because"] == "the estimate's phases have wrapped"
    assert left_off_m(placed).max() < 0.5 * 2.5e-3  # the halves read the range errors to ~0.5 mm here
    same, _, _ = place_estimate(oracle, basis, tracked, ch, GRID, upper_band=band)
    # not untouched: the halves' own floor (the reference's delay texture) moves it, by less than
    # the misplacement it takes out
    assert left_off_m(same).max() < 0.5 * 2.5e-3


def test_the_placement_check_flags_every_wrapped_estimate_and_says_whether_the_halves_placed_it():
    """At and above the wrapping line nothing is said; below it the report warns whether or not
    the band's halves placed the reference (their ramp must reach the fit's coherence and have
    been taken out), and names what to do next only for a digital twin's outline."""
    from twinfocus.focus.pipeline import DIGITAL_TWIN_NEXT, placement_warnings

    line, least = AUTO_REFINE_BELOW_COHERENCE, MIN_RANGED_RAMP_COHERENCE_SQRT_M
    assert placement_warnings(line, least, True) == [] and placement_warnings(9.0, None, False) == []
    cases = {  # (ranged, removed): placed
        (least, True): True,
        (least + 4.0, True): True,
        (least - 0.01, True): False,  # too faint to count, whatever was done with it
        (least + 4.0, False): False,
        (None, False): False,
    }
    for (ranged, removed), placed in cases.items():
        (w,) = placement_warnings(line - 0.01, ranged, removed)
        assert "phases have wrapped" in w and DIGITAL_TWIN_NEXT in w
        assert ("placed the reference" in w) == placed and ("cannot check" in w) == (not placed)
        assert ("did not place it either" in w) == (not placed and ranged is not None)
    (w,) = placement_warnings(0.5, least + 1.0, True, outline=False)
    assert DIGITAL_TWIN_NEXT not in w
