"""A digital twin's like-with-like check (twinfocus.focus.outline_fill) and the confidence report that
reads it: closed forms for the statistics, a small simulated scene for what they tell apart, and
the report trusting or flagging a digital twin's result by them (not by the template's picture)."""

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.focus.outline_fill import SPECKLED_BELOW, outline_fill, surface_from_positions


def _outline(h=40, w=40):
    mask = np.zeros((h, w), bool)
    mask[10:30, 12:28] = True
    return mask


def test_speckle_inside_the_outline_has_contrast_two_and_all_its_energy_inside():
    # fully developed speckle: |complex Gaussian|^2 is exponential, mean(e^2) / mean(e)^2 = 2
    rng = np.random.default_rng(3)
    mask = _outline(200, 200)
    img = np.where(mask, rng.normal(size=mask.shape) + 1j * rng.normal(size=mask.shape), 0)
    fill = outline_fill(img, mask, grow_px=0)
    assert fill["energy_inside"] == 1.0
    assert fill["contrast"] == pytest.approx(2.0, abs=0.1)


def test_energy_piled_into_few_pixels_gives_the_closed_form_contrast():
    # k of the n pixels of the outline holding equal energy: contrast n / k exactly
    mask = _outline()
    img = np.zeros(mask.shape, complex)
    img[np.nonzero(mask)[0][:8], np.nonzero(mask)[1][:8]] = 2.0 - 1.0j
    assert outline_fill(img, mask, grow_px=0)["contrast"] == pytest.approx(mask.sum() / 8, rel=1e-3)


def test_energy_outside_the_grown_outline_counts_against_it():
    mask = _outline()
    img = np.zeros(mask.shape, complex)
    img[20, 20] = 1.0  # inside
    img[20, 32] = 1.0  # 5 px right of the outline: inside when grown by 5, not by 3
    assert outline_fill(img, mask, grow_px=3)["energy_inside"] == pytest.approx(0.5)
    assert outline_fill(img, mask, grow_px=5)["energy_inside"] == pytest.approx(1.0)


@pytest.mark.parametrize(
    "image, support, grow, match",
    [
        (np.ones((4, 4)), np.ones((4, 5), bool), 0, "same"),
        (np.ones((4, 4)), np.zeros((4, 4), bool), 0, "none of the region"),
        (np.ones((4, 4)), np.ones((4, 4), bool), -1, "grow_px"),
        (np.zeros((4, 4)), np.ones((4, 4), bool), 0, "no finite energy"),
    ],
)
def test_bad_input_is_refused_by_name(image, support, grow, match):
    with pytest.raises(TwinFocusError, match=match):
        outline_fill(image, support, grow)


@pytest.fixture(scope="module")
def small_scene():
    """An 'F' of rough scatterers (each its own phase) 2 mm apart, 20 mm tall at 0.3 m, scanned by a
    16-channel array on 2 x 24 positions; the tracked positions off by 1.6 mm along z (every phase
    wraps); its sub-image basis, the image on the true positions and the letter's outline."""
    from twinfocus.imaging.backprojection.numba_backend import backproject, subimage_basis
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.motion.trajectory import paper_raster, phase_centres
    from twinfocus.radar.fmcw import Chirp, uniform_virtual_array
    from twinfocus.simulation.if_simulator import simulate_if

    chirp = Chirp(n_samples=64)
    rng = np.random.default_rng(1)
    s = np.arange(-0.010, 0.0101, 0.002)
    xy = [(-0.010, y) for y in s] + [(x, 0.010) for x in s] + [(x * 0.6, 0.0) for x in s]
    points = np.array([(x - 0.025, y, 0.3) for x, y in xy])
    true = phase_centres(
        paper_raster(n_columns=2, n_rows=24, column_pitch_m=0.128, row_pitch_m=0.004), uniform_virtual_array(16, 0.002)
    )
    data = simulate_if(points, np.exp(2j * np.pi * rng.random(len(points))), true, chirp)
    tracked = true.copy()
    tracked[..., 2] += rng.normal(0, 1.6e-3, true.shape[0])[:, None]
    grid = ImageGrid.from_roi([-0.045, -0.005, -0.02, 0.02, 0.3], 24)
    pixel = grid.points().reshape(grid.shape + (3,))
    # the outline: pixels within 2 mm of a scatterer
    support = np.min(np.linalg.norm(pixel[:, :, None, :2] - points[None, None, :, :2], axis=-1), axis=-1) < 2e-3
    return subimage_basis(data, tracked, chirp, grid), backproject(data, true, chirp, grid), support


def test_a_focused_reference_fills_its_outline_and_one_with_wrapped_errors_does_not(small_scene):
    basis, truth, support = small_scene
    focused, unfocused = outline_fill(truth, support), outline_fill(basis.sum(axis=0), support)
    # the image on the true positions keeps 0.84 of its energy within 3 px of the letter; the scan
    # as tracked (1.6 mm along z: every phase wrapped) spreads it outside
    assert focused["energy_inside"] > 0.8
    assert unfocused["energy_inside"] < focused["energy_inside"] - 0.1


def _report(fill, match=0.68):
    from twinfocus.focus.pipeline import confidence_report
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.motion.trajectory import paper_raster, phase_centres
    from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array

    pos = phase_centres(paper_raster(6, 10), mmwcas_virtual_array())
    ref = ImageGrid.from_roi([-0.15, 0.0, -0.11, 0.12, 0.6], 20)
    tgt = ImageGrid.from_roi([0.02, 0.13, -0.11, 0.12, 0.6], 20)
    m = {"reference_ssim_vs_template_corrected": match, "reference_outline": fill}
    return confidence_report(m, pos, Chirp(), ref, tgt, 0.5e-3)


def test_the_report_reads_a_digital_twin_against_its_outline_not_its_template_picture():
    from twinfocus.focus.pipeline import MAX_OUTLINE_CONTRAST

    good = {"energy_inside": 0.9, "contrast": MAX_OUTLINE_CONTRAST - 0.2}
    # a speckled reference matches an outline's picture at 0.68: no longer a reason to flag it
    report = _report(good)
    assert report["trusted"] and report["reference_outline"] == good
    report = _report({**good, "contrast": MAX_OUTLINE_CONTRAST + 0.2})
    assert not report["trusted"]
    (warning,) = report["warnings"]
    assert "does not fill its outline" in warning and "--template-scan" in warning


def test_the_contrast_is_not_held_against_a_reference_the_scan_reads_as_speckled():
    from twinfocus.focus.pipeline import MAX_OUTLINE_CONTRAST, outline_warnings

    piled = {"energy_inside": 0.9, "contrast": MAX_OUTLINE_CONTRAST + 0.3}
    # speckle in focus reaches the contrast of a coherent reference's piled energy: no reason to flag
    assert _report({**piled, "position_energy_contrast": 1.3, "surface": "speckled"})["trusted"]
    for surface in ({"surface": "coherent"}, {}):  # a coherent part, or a record that did not read the surface
        (warning,) = outline_warnings({**piled, **surface}, None)
        assert "does not fill its outline" in warning and "--template-scan" in warning
    # the other checks still hold for a speckled reference
    (warning,) = outline_warnings({**piled, "surface": "speckled"}, 0.8)
    assert "not sure of the reference's phase" in warning


def test_a_reference_that_sends_its_return_to_a_few_positions_is_flagged():
    from twinfocus.focus.pipeline import MAX_POSITION_ENERGY_CONTRAST, outline_warnings

    filled = {"energy_inside": 0.95, "contrast": 1.7, "surface": "coherent"}
    assert outline_warnings({**filled, "position_energy_contrast": MAX_POSITION_ENERGY_CONTRAST - 0.5}, None) == []
    (warning,) = outline_warnings({**filled, "position_energy_contrast": MAX_POSITION_ENERGY_CONTRAST + 0.4}, None)
    assert "to a few radar positions" in warning and "--template-scan" in warning
    assert not _report({**filled, "position_energy_contrast": MAX_POSITION_ENERGY_CONTRAST + 0.4})["trusted"]


def test_the_glint_threshold_grows_with_the_scans_aperture():
    """Measured on the same bench references scanned over 390 and 780 positions (0.0635 and
    0.128 m^2): a rough letter reads 4.5-5.4 at the longer scan, a smooth washer 8.0-8.2."""
    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.ladder import Problem
    from twinfocus.focus.pipeline import (
        GLINT_APERTURE_M2,
        MAX_POSITION_ENERGY_CONTRAST,
        glint_threshold,
        outline_warnings,
    )
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.radar.fmcw import Chirp

    assert glint_threshold(None) == glint_threshold(GLINT_APERTURE_M2) == MAX_POSITION_ENERGY_CONTRAST
    assert glint_threshold(GLINT_APERTURE_M2 / 4) == MAX_POSITION_ENERGY_CONTRAST  # never below the bench's
    assert glint_threshold(2 * GLINT_APERTURE_M2) == pytest.approx(MAX_POSITION_ENERGY_CONTRAST * 2**0.8)
    filled = {"energy_inside": 0.95, "contrast": 1.7, "surface": "coherent"}
    for contrast, aperture, glint in (
        (5.0, 0.128, False),
        (5.4, 0.128, False),
        (8.0, 0.128, True),
        (5.0, 0.0635, True),
    ):
        warnings = outline_warnings({**filled, "position_energy_contrast": contrast, "aperture_m2": aperture}, None)
        assert any("to a few radar positions" in w for w in warnings) == glint, (contrast, aperture)
    # the scan's aperture, as the report reads it: the phase centres' extent across x times across y
    rng = np.random.default_rng(0)
    positions = np.zeros((20, 2, 3))
    positions[:, :, 0] = rng.uniform(-0.2, 0.3, (20, 1)) + np.array([0.0, 0.01])
    positions[:, :, 1] = rng.uniform(0.0, 0.1, (20, 1))
    grid = ImageGrid(-0.05, 0.05, -0.05, 0.05, 0.5, 8, 8)
    basis = (rng.standard_normal((20, 8, 8)) + 1j * rng.standard_normal((20, 8, 8))).astype(np.complex64)
    support = np.zeros((8, 8), bool)
    support[2:6, 2:6] = True
    problem = Problem(basis, basis, positions, Chirp(), grid, grid, AutofocusConfig(), support=support)
    p = positions.reshape(-1, 3)
    assert problem.surface["aperture_m2"] == pytest.approx(np.ptp(p[:, 0]) * np.ptp(p[:, 1]), abs=1e-5)


def test_surface_from_positions_is_the_contrast_of_each_positions_energy_in_the_grown_outline():
    """Against a loop over positions and pixels, and unchanged at any scale of the scan."""
    rng = np.random.default_rng(3)
    m, h, w = 7, 12, 10
    basis = (rng.normal(size=(m, h, w)) + 1j * rng.normal(size=(m, h, w))).astype(np.complex64)
    basis *= rng.uniform(0.2, 3.0, m)[:, None, None].astype(np.float32)  # positions of unequal energy
    support = np.zeros((h, w), bool)
    support[5, 4] = True
    grown = np.array([[abs(r - 5) + abs(c - 4) <= 1 for c in range(w)] for r in range(h)])  # one step of dilation
    energy = np.array(
        [sum(abs(complex(basis[k, r, c])) ** 2 for r in range(h) for c in range(w) if grown[r, c]) for k in range(m)]
    )
    expected = (energy**2).mean() / energy.mean() ** 2
    got = surface_from_positions(basis, support, grow_px=1)
    assert got["position_energy_contrast"] == pytest.approx(expected, abs=1e-3)
    assert got["surface"] == ("speckled" if expected < SPECKLED_BELOW else "coherent")
    for scale in (1e-20, 1e20):
        assert surface_from_positions(basis * np.float32(scale), support, grow_px=1) == got
    # one position holding all the energy: contrast M; all equal: 1
    lone = np.zeros_like(basis)
    lone[2] = 1.0
    assert surface_from_positions(lone, support)["position_energy_contrast"] == pytest.approx(m, rel=1e-3)
    assert surface_from_positions(np.ones_like(basis), support) == {
        "position_energy_contrast": 1.0,
        "surface": "speckled",
    }


@pytest.mark.parametrize(
    ("basis_shape", "support_shape", "grow", "why"),
    [
        ((4, 5, 6), (5, 5), 0, "must be"),
        ((5, 6), (5, 6), 0, "must be"),
        ((4, 5, 6), (5, 6), -1, "grow_px"),
        ((4, 5, 6), (5, 6), 0, "no finite energy"),
    ],
)
def test_surface_from_positions_refuses_what_it_cannot_read(basis_shape, support_shape, grow, why):
    support = np.ones(support_shape, bool)
    with pytest.raises(TwinFocusError, match=why):
        surface_from_positions(np.zeros(basis_shape, np.complex64), support, grow)
    with pytest.raises(TwinFocusError, match="covers none"):
        surface_from_positions(np.ones((4, 5, 6), np.complex64), np.zeros((5, 6), bool))


@pytest.mark.slow  # 12 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_the_scan_tells_a_speckled_reference_from_a_smooth_or_rough_one_whatever_the_tracking_error():
    """Field geometry (the MMWCAS array at 0.6 m, an 'H'), 120 positions: a smooth sheet-metal
    letter (every scatterer in phase) and a rough one (phases within +-90 degrees) send back a lobe
    that changes across the scan; a speckled one (phases anywhere) does not. Under 1.6 mm of
    jitter and under a hand's drift alike."""
    from scipy.spatial import cKDTree

    from twinfocus.imaging.backprojection.numba_backend import subimage_basis
    from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario

    for errors in (
        {"error_sigma_m": (0.3e-3, 0.3e-3, 1.6e-3)},
        {"error_model": "hand", "error_sigma_m": (0.8e-3,) * 3},
    ):
        for roughness_deg, surface in ((0.0, "coherent"), (90.0, "coherent"), (None, "speckled")):
            sc = Scenario(reference="H", reference_roughness_deg=roughness_deg, n_rows=20, snr_db=15, seed=4, **errors)
            scan, _ = simulate_scenario(sc)
            grid, _ = scenario_grids(sc, 32)
            # the outline: pixels within 2 mm of the letter's surface
            distance, _ = cKDTree(sc.scene().object("reference").surface_points(1e-3)[:, :2]).query(
                grid.points()[:, :2]
            )
            support = (distance < 2e-3).reshape(grid.shape)
            got = surface_from_positions(subimage_basis(scan.data, scan.positions, scan.chirp, grid), support)
            assert got["surface"] == surface, (errors, roughness_deg, got)


@pytest.mark.slow  # 7 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_focus_reads_a_digital_twin_against_its_outline(small_scene):
    """focus_bases with an outline (what --digital-twin runs) writes the corrected reference's
    outline statistics, and its confidence report judges them, not the picture match."""
    from twinfocus.focus.autofocus import AutofocusConfig
    from twinfocus.focus.estimators import estimator_settings
    from twinfocus.focus.pipeline import MAX_OUTLINE_CONTRAST, Bases, Reference, outline_warnings
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.motion.trajectory import paper_raster, phase_centres
    from twinfocus.radar.fmcw import Chirp, uniform_virtual_array

    basis, _, support = small_scene
    grid = ImageGrid.from_roi([-0.045, -0.005, -0.02, 0.02, 0.3], 24)
    positions = phase_centres(
        paper_raster(n_columns=2, n_rows=24, column_pitch_m=0.128, row_pitch_m=0.004), uniform_virtual_array(16, 0.002)
    )
    cfg = AutofocusConfig(**estimator_settings("auto", False, has_support=True))
    out = FocusPlan.make(config=cfg).focus_bases(
        Bases(basis, basis, positions, Chirp(n_samples=64), grid, grid),
        Reference(template=support.astype(np.float32), support=support),
    )
    fill = out.metrics["reference_outline"]
    extent = positions.reshape(-1, 3)
    aperture = round(float(np.ptp(extent[:, 0]) * np.ptp(extent[:, 1])), 5)
    assert fill == {**outline_fill(out.reference, support), **surface_from_positions(basis, support),
                    "aperture_m2": aperture}  # fmt: skip
    report = out.metrics["confidence"]
    assert report["reference_outline"] == fill
    assert not any("matches its template poorly" in w for w in report["warnings"])
    own = outline_warnings(fill, report.get("outline_agreement"))
    assert [w for w in report["warnings"] if w in own] == own
    judged = fill["surface"] != "speckled"
    assert any("does not fill its outline" in w for w in report["warnings"]) == (
        judged and fill["contrast"] > MAX_OUTLINE_CONTRAST
    )
