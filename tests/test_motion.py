import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.motion.tracking_errors import apply_position_errors, drift_errors, gaussian_errors, vio_errors


def _autocorr(x, lag):
    x = x - x.mean()
    return float(np.dot(x[:-lag], x[lag:]) / np.dot(x, x))


def test_gaussian_errors_statistics_and_default_axis():
    e = gaussian_errors(200_000, (0.2e-3, 1e-3, 2e-3), rng=0)
    assert e.shape == (200_000, 3)
    # Standard error of a sample std is sigma / sqrt(2 M) ~ 0.16 %; allow 1 %.
    np.testing.assert_allclose(e.std(axis=0), [0.2e-3, 1e-3, 2e-3], rtol=0.01)
    np.testing.assert_allclose(e.mean(axis=0), 0.0, atol=3e-5)
    d = gaussian_errors(50_000, rng=1)
    np.testing.assert_array_equal(d[:, :2], 0.0)  # paper: z only
    assert d[:, 2].std() == pytest.approx(0.5e-3, rel=0.02)
    np.testing.assert_array_equal(gaussian_errors(10, 1e-3, rng=5), gaussian_errors(10, 1e-3, rng=5))
    with pytest.raises(TwinFocusError, match="sigma_m"):
        gaussian_errors(10, (1e-3, 2e-3))
    with pytest.raises(TwinFocusError, match="sigma_m"):
        gaussian_errors(10, -1e-3)
    with pytest.raises(TwinFocusError):
        gaussian_errors(0)


def test_drift_errors_variance_and_correlation_time():
    dt_s, tau = 0.1, 2.0
    ts = np.arange(200_000, dtype=np.int64) * int(dt_s * 1e9)
    e = drift_errors(ts, (1e-3, 0.0, 0.5e-3), correlation_time_s=tau, rng=0)
    # ~ M dt / (2 tau) = 5,000 independent stretches: std within 3 %.
    np.testing.assert_allclose(e[:, [0, 2]].std(axis=0), [1e-3, 0.5e-3], rtol=0.03)
    np.testing.assert_array_equal(e[:, 1], 0.0)
    for lag in (1, 20, 40):
        assert _autocorr(e[:, 0], lag) == pytest.approx(np.exp(-lag * dt_s / tau), abs=0.03)


def test_drift_errors_uneven_steps_are_exact():
    # Two stamps 1 tau apart, many realisations: correlation exp(-1), variance sigma^2 at both.
    ts = np.array([0, 500_000_000], dtype=np.int64)
    gen = np.random.default_rng(3)
    pairs = np.stack([drift_errors(ts, 1.0, 0.5, gen)[:, 0] for _ in range(8_000)])
    assert pairs.std(axis=0) == pytest.approx([1.0, 1.0], rel=0.03)
    assert np.corrcoef(pairs.T)[0, 1] == pytest.approx(np.exp(-1.0), abs=0.03)
    with pytest.raises(TwinFocusError, match="correlation_time_s"):
        drift_errors(ts, 1.0, 0.0)
    with pytest.raises(TwinFocusError, match="non-decreasing"):
        drift_errors(ts[::-1], 1.0, 1.0)


def test_vio_errors_random_walk_jitter_and_relocalisation():
    ts = np.array([0, 25, 100], dtype=np.int64) * 1_000_000_000
    gen = np.random.default_rng(7)
    q = 0.2e-3
    walks = np.stack([vio_errors(ts, 0.0, q, rng=gen) for _ in range(4000)])  # (R, 3, 3)
    np.testing.assert_array_equal(walks[:, 0], 0.0)  # aligned at the start
    # Wiener drift: std q sqrt(T).
    np.testing.assert_allclose(walks[:, 1].std(axis=0), q * 5.0, rtol=0.05)
    np.testing.assert_allclose(walks[:, 2].std(axis=0), q * 10.0, rtol=0.05)
    # Jitter only: white, std as given.
    many = np.arange(100_000, dtype=np.int64) * 100_000_000
    j = vio_errors(many, (0.1e-3, 0.2e-3, 0.5e-3), 0.0, rng=1)
    np.testing.assert_allclose(j.std(axis=0), [0.1e-3, 0.2e-3, 0.5e-3], rtol=0.02)
    assert abs(_autocorr(j[:, 2], 1)) < 0.02
    # A re-localisation at (almost) every frame replaces the drift by a fresh residual:
    # std = relocalisation_sigma and no memory, however large the drift rate.
    r = vio_errors(many, 0.0, 1.0, relocalisation_rate_hz=1e3, relocalisation_sigma_m=0.3e-3, rng=2)
    np.testing.assert_allclose(r[1:].std(axis=0), 0.3e-3, rtol=0.02)
    assert abs(_autocorr(r[1:, 0], 1)) < 0.02
    with pytest.raises(TwinFocusError, match="relocalisation_rate_hz"):
        vio_errors(ts, relocalisation_rate_hz=-1.0)


def test_apply_position_errors_one_offset_per_position():
    rng = np.random.default_rng(0)
    centres = rng.standard_normal((5, 86, 3))
    err = rng.standard_normal((5, 3)) * 1e-3
    out = apply_position_errors(centres, err)
    diff = out - centres
    # Every channel of a position moves by that position's offset, exactly.
    np.testing.assert_allclose(diff, np.broadcast_to(err[:, None, :], diff.shape), atol=1e-15)
    with pytest.raises(TwinFocusError, match="errors_m"):
        apply_position_errors(centres, err[:4])
    with pytest.raises(TwinFocusError, match="centres_m"):
        apply_position_errors(centres[0], err)
    with pytest.raises(TwinFocusError, match="NaN"):
        apply_position_errors(centres, np.full((5, 3), np.nan))


def test_pose_errors_rotate_the_array_about_its_centre_like_a_rigid_body():
    from scipy.spatial.transform import Rotation

    from twinfocus.motion.tracking_errors import apply_pose_errors

    rng = np.random.default_rng(5)
    centres = rng.normal(0, 0.05, (4, 86, 3))
    shift = rng.normal(0, 1e-3, (4, 3))
    turn = rng.normal(0, np.radians(0.15), (4, 3))
    got = apply_pose_errors(centres, shift, turn)
    for m in range(4):
        c = centres[m].mean(axis=0)
        exact = Rotation.from_rotvec(turn[m]).apply(centres[m] - c) + c + shift[m]
        # first order in the angle: what is left is the second-order term, |r|^2 |arm| / 2
        arm = np.linalg.norm(centres[m] - c, axis=1).max()
        assert np.abs(got[m] - exact).max() <= 0.5 * np.dot(turn[m], turn[m]) * arm * 1.01
    with pytest.raises(TwinFocusError, match="rotation_rad"):
        apply_pose_errors(centres, shift, turn[:2])


def test_hand_errors_drift_jitter_and_rotation_sizes():
    from twinfocus.motion.tracking_errors import draw_errors, hand_errors

    stamps = np.arange(20000, dtype=np.int64) * 100_000_000
    shift, turn = hand_errors(stamps, (0.8e-3,) * 3, 2.0, (0.2e-3,) * 3, np.radians(0.15), rng=1)
    # drift and jitter are independent: variances add
    np.testing.assert_allclose(shift.std(axis=0), np.hypot(0.8e-3, 0.2e-3), rtol=0.1)
    np.testing.assert_allclose(turn.std(axis=0), np.radians(0.15), rtol=0.1)
    # the rotation drifts with the correlation time: lag-20 (2 s) correlation exp(-1)
    lag = np.mean([np.corrcoef(turn[:-20, i], turn[20:, i])[0, 1] for i in range(3)])
    assert abs(lag - np.exp(-1)) < 0.05
    s, r = draw_errors("hand", stamps[:100], (0.8e-3,) * 3, rng=4)
    s2, r2 = hand_errors(stamps[:100], (0.8e-3,) * 3, rng=4)
    np.testing.assert_array_equal(s, s2)
    np.testing.assert_array_equal(r, r2)
    with pytest.raises(TwinFocusError, match="unknown error model"):
        draw_errors("wobble", stamps[:10])
