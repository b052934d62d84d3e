"""The estimate's step coherence (twinfocus.focus.drift_check): closed forms, jitter against drift, and
the digital twin's warnings in the confidence report that read it."""

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.focus.drift_check import phase_concentration, step_coherence
from twinfocus.motion.tracking_errors import drift_errors, gaussian_errors


def test_closed_forms():
    # a constant and a linear ramp along the scan: every step the same
    assert step_coherence(np.full(50, 2.0)) == pytest.approx(1.0)
    assert step_coherence(0.3 * np.arange(50)) == pytest.approx(1.0)
    # steps alternating +a and -a: |mean| = cos(a) (49 steps: 25 of one, 24 of the other)
    a = 0.7
    phi = a * (np.arange(50) % 2)
    assert step_coherence(phi) == pytest.approx(abs((25 * np.exp(1j * a) + 24 * np.exp(-1j * a)) / 49))
    with pytest.raises(TwinFocusError, match="M >= 2"):
        step_coherence(np.zeros(1))
    with pytest.raises(TwinFocusError, match="NaN"):
        step_coherence(np.array([0.0, np.nan, 1.0]))


def test_jitter_is_incoherent_and_a_drift_of_the_same_size_is_not():
    """The phase 4 pi dz / lambda of 400 positions: 0.5 mm of jitter leaves steps uncorrelated
    (|mean| near 1 / sqrt(M)); a drift of the same size, correlated over seconds, does not."""
    k = 4 * np.pi / 3.9e-3
    rng = np.random.default_rng(2)
    jitter = gaussian_errors(400, (0.0, 0.0, 0.5e-3), rng)[:, 2]
    t_ns = np.arange(400) * 20_000_000  # 50 positions a second, a hand's sweep
    drift = drift_errors(t_ns, (0.0, 0.0, 0.5e-3), 2.0, rng)[:, 2]
    assert np.std(drift) > 0.2e-3
    assert step_coherence(k * jitter) < 0.15
    assert step_coherence(k * drift) > 0.5
    # the drift spreads the phases (0.5 mm: 1.6 rad rms); 0.05 mm of it keeps them together
    assert phase_concentration(k * drift) < 0.5 < 0.9 < phase_concentration(0.1 * k * drift)
    assert phase_concentration(np.array([0.0, np.pi])) == pytest.approx(0.0, abs=1e-12)


def _report(contrast=2.5, agreement=None, step=None, digital=True, concentration=0.05):
    from twinfocus.focus.pipeline import confidence_report
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.motion.trajectory import paper_raster, phase_centres
    from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array

    pos = phase_centres(paper_raster(6, 10), mmwcas_virtual_array())
    ref = ImageGrid.from_roi([-0.15, 0.0, -0.11, 0.12, 0.6], 20)
    tgt = ImageGrid.from_roi([0.02, 0.13, -0.11, 0.12, 0.6], 20)
    m: dict = {"phase_step_coherence": step, "phase_concentration": concentration}
    if digital:
        m["reference_outline"] = {"energy_inside": 0.9, "contrast": contrast}
    if agreement is not None:
        m["estimator"] = {"outline": {"energy_inside": [0.95]}, "outline_ensemble": {"agreement": agreement}}
    return confidence_report(m, pos, Chirp(), ref, tgt, 0.5e-3)


def test_the_report_trusts_a_focused_outline_estimate_and_flags_a_drift_or_a_split_one():
    from twinfocus.focus.pipeline import MAX_STEP_COHERENCE, MIN_OUTLINE_AGREEMENT

    good = _report(2.3, MIN_OUTLINE_AGREEMENT + 0.03, 0.05)
    assert good["trusted"] and good["phase_step_coherence"] == 0.05
    drift = _report(2.3, MIN_OUTLINE_AGREEMENT + 0.03, MAX_STEP_COHERENCE + 0.1)
    (warning,) = drift["warnings"]
    assert not drift["trusted"] and "drifted" in warning and "--template-scan" in warning
    split = _report(2.3, MIN_OUTLINE_AGREEMENT - 0.03, 0.05)
    (warning,) = split["warnings"]
    assert not split["trusted"] and "not sure" in warning and "--template-scan" in warning
    # a physical twin (no outline): the drift is flagged too, with its own advice
    assert _report(step=0.05, digital=False)["trusted"]
    physical = _report(step=MAX_STEP_COHERENCE + 0.1, digital=False)
    (warning,) = physical["warnings"]
    assert "drifted" in warning and "extrapolation" in warning and "--template-scan" not in warning
    # a scan tracked well moves smoothly too, but its phases stay together: not a drift
    assert _report(step=0.99, digital=False, concentration=0.95)["trusted"]
