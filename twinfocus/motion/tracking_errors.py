"""Motion-error models: what a tracker gets wrong about each radar position.

Every model returns position errors float64 (M, 3) in metres (scene frame; z is range) and takes
``rng``: a ``numpy.random.Generator``, an integer seed or None (fresh entropy). The tracked
positions of a scan are the true phase centres plus one rigid offset per radar position,
shared by its K channels (:func:`apply_position_errors`, docs/architecture.md section 2).

Models
------
- :func:`gaussian_errors`: independent per position; the paper's protocol (z only, sigma 0.5 mm,
  the ZED 2i's measured jitter; sweeps to 2 mm).
- :func:`drift_errors`: temporally correlated hand drift, a first-order Gauss-Markov
  (Ornstein-Uhlenbeck) process with stationary standard deviation ``sigma_m`` and correlation
  time ``tau``: E[e(t) e(t + dt)] = sigma^2 exp(-|dt| / tau).
- :func:`vio_errors`: a VIO-like tracker: slow random-walk drift + white jitter + optional
  re-localisation jumps.
- :func:`hand_errors`: a hand-held radar tracked by a camera: Gauss-Markov drift on all three
  axes, white jitter, and small rotations of the array that drift the same way. A rotation moves
  each of the K channels differently (:func:`apply_pose_errors`), so no single phase per
  position undoes it.

:func:`draw_errors` picks a model by name (:data:`ERROR_MODELS`) for the simulator, the node
graph's sim backends and the evaluation alike.
"""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError

#: The paper's per-position range jitter of the ZED 2i (sigma, metres): x, y, z.
PAPER_SIGMA_M = (0.0, 0.0, 0.5e-3)


def _sigma3(name: str, sigma_m) -> np.ndarray:
    try:
        a = np.asarray(sigma_m, dtype=np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or a.ndim > 1 or a.size not in (1, 3):
        raise TwinFocusError(f"{name} must be a number or 3 numbers (x, y, z) in metres, got {sigma_m!r}")
    s = np.broadcast_to(a.reshape(-1), (3,)).copy()
    if not np.isfinite(s).all() or np.any(s < 0):
        raise TwinFocusError(f"{name} must be finite and non-negative, got {sigma_m!r}")
    return s


def _times_s(timestamps_ns) -> np.ndarray:
    ts = np.asarray(timestamps_ns)
    if ts.ndim != 1 or ts.shape[0] == 0 or not np.issubdtype(ts.dtype, np.integer):
        raise TwinFocusError(f"timestamps_ns must be a non-empty 1-D integer array, got {ts.dtype} {ts.shape}")
    if np.any(np.diff(ts) < 0):
        raise TwinFocusError("timestamps_ns must be non-decreasing")
    # Relative to the first stamp so that float64 keeps nanosecond resolution.
    return (ts - ts[0]).astype(np.float64) * 1e-9


def gaussian_errors(m: int, sigma_m=PAPER_SIGMA_M, rng: np.random.Generator | int | None = None) -> np.ndarray:
    """Independent zero-mean Gaussian error per radar position.

    m : number of radar positions; sigma_m : standard deviation, a number (all axes) or
    (sx, sy, sz) metres. Default (0, 0, 0.5 mm): the paper's z-only jitter.
    Returns float64 (m, 3), metres.
    """
    m = int(m)
    if m < 1:
        raise TwinFocusError(f"number of positions must be at least 1, got {m}")
    s = _sigma3("sigma_m", sigma_m)
    gen = np.random.default_rng(rng)
    return gen.standard_normal((m, 3)) * s


def drift_errors(
    timestamps_ns,
    sigma_m=(0.5e-3, 0.5e-3, 0.5e-3),
    correlation_time_s: float = 2.0,
    rng: np.random.Generator | int | None = None,
) -> np.ndarray:
    """Temporally correlated drift: a stationary first-order Gauss-Markov process per axis.

    Exact discrete update for arbitrary (uneven) time steps dt_i:

        e_0 ~ N(0, sigma^2),  e_i = rho_i e_{i-1} + sigma sqrt(1 - rho_i^2) w_i,
        rho_i = exp(-dt_i / tau),  w_i ~ N(0, 1),

    so every e_i has variance sigma^2 and corr(e_i, e_j) = exp(-|t_i - t_j| / tau).

    timestamps_ns : int (M,), non-decreasing; sigma_m : stationary standard deviation, a number
    or (sx, sy, sz) metres; correlation_time_s : tau > 0.
    Returns float64 (M, 3), metres.
    """
    t = _times_s(timestamps_ns)
    s = _sigma3("sigma_m", sigma_m)
    tau = float(correlation_time_s)
    if not (np.isfinite(tau) and tau > 0):
        raise TwinFocusError(f"correlation_time_s must be a positive number, got {correlation_time_s!r}")
    gen = np.random.default_rng(rng)
    w = gen.standard_normal((t.shape[0], 3))
    rho = np.exp(-np.diff(t) / tau)
    innov = np.sqrt(1.0 - rho**2)
    out = np.empty((t.shape[0], 3))
    out[0] = w[0]
    for i in range(1, t.shape[0]):
        out[i] = rho[i - 1] * out[i - 1] + innov[i - 1] * w[i]
    return out * s


def vio_errors(
    timestamps_ns,
    jitter_sigma_m=(0.2e-3, 0.2e-3, 0.5e-3),
    drift_m_per_sqrt_s=(0.1e-3, 0.1e-3, 0.2e-3),
    relocalisation_rate_hz: float = 0.0,
    relocalisation_sigma_m=(0.3e-3, 0.3e-3, 0.3e-3),
    rng: np.random.Generator | int | None = None,
) -> np.ndarray:
    """A VIO-like tracking error: random-walk drift + white jitter + re-localisation jumps.

    e(t_i) = d(t_i) + j_i with

    - jitter j_i ~ N(0, jitter_sigma^2), independent per pose (feature noise, per-frame solve);
    - drift d: a Wiener process starting at 0 (the tracker is aligned at the start),
      d(t_i) = d(t_{i-1}) + q sqrt(dt_i) w_i, so its standard deviation after T seconds is
      q sqrt(T) (``drift_m_per_sqrt_s`` = q; defaults give ~1.8 mm in z after the paper's 78 s);
    - re-localisation (loop closure): events of a Poisson process with rate
      ``relocalisation_rate_hz``; at an event the accumulated drift is replaced by a fresh
      residual ~ N(0, relocalisation_sigma^2), i.e. the pose jumps and drift restarts from there.

    The defaults are nominal values of the order a consumer stereo-inertial tracker reaches over a
    short hand sweep (sub-millimetre jitter, millimetre drift over a minute), not a fit to a
    specific device. Returns float64 (M, 3), metres.
    """
    t = _times_s(timestamps_ns)
    jit = _sigma3("jitter_sigma_m", jitter_sigma_m)
    q = _sigma3("drift_m_per_sqrt_s", drift_m_per_sqrt_s)
    reloc = _sigma3("relocalisation_sigma_m", relocalisation_sigma_m)
    rate = float(relocalisation_rate_hz)
    if not (np.isfinite(rate) and rate >= 0):
        raise TwinFocusError(f"relocalisation_rate_hz must be a non-negative number, got {relocalisation_rate_hz!r}")
    gen = np.random.default_rng(rng)
    m = t.shape[0]
    dt = np.diff(t)
    steps = gen.standard_normal((m - 1, 3)) * np.sqrt(dt)[:, None] * q
    jumps = gen.random(m - 1) < -np.expm1(-rate * dt)  # P(at least one event in dt)
    residual = gen.standard_normal((m - 1, 3)) * reloc
    drift = np.zeros((m, 3))
    for i in range(1, m):
        drift[i] = residual[i - 1] if jumps[i - 1] else drift[i - 1] + steps[i - 1]
    return drift + gen.standard_normal((m, 3)) * jit


#: per-axis array rotation of :func:`hand_errors`, radians (0.15 degrees)
HAND_ROTATION_SIGMA_RAD = float(np.radians(0.15))


def hand_errors(
    timestamps_ns,
    drift_sigma_m=(0.8e-3, 0.8e-3, 0.8e-3),
    correlation_time_s: float = 2.0,
    jitter_sigma_m=(0.2e-3, 0.2e-3, 0.2e-3),
    rotation_sigma_rad=HAND_ROTATION_SIGMA_RAD,
    rng: np.random.Generator | int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Tracking error of a hand-held radar: translation drift + jitter, and array rotation drift.

    - translation: :func:`drift_errors` (stationary Gauss-Markov, ``drift_sigma_m`` per axis,
      correlation time ``correlation_time_s``) plus white jitter ``jitter_sigma_m``;
    - rotation: a small rotation vector (rx, ry, rz) per position, radians, also Gauss-Markov with
      the same correlation time (a wrist turns as slowly as it moves), ``rotation_sigma_rad`` per
      axis. About the array's centre; 0.15 degrees tilts the ends of the 83 mm virtual line by
      0.11 mm (0.35 rad of phase at 77 GHz).

    The defaults are the held-out handheld scene of docs/results.md: 0.8 mm drift over ~20
    positions at 10 Hz, 0.2 mm jitter, 0.15 degree rotations.
    Returns (translation float64 (M, 3) metres, rotation float64 (M, 3) radians).
    """
    gen = np.random.default_rng(rng)
    drift = drift_errors(timestamps_ns, drift_sigma_m, correlation_time_s, gen)
    jitter = gaussian_errors(drift.shape[0], jitter_sigma_m, gen)
    rotation = drift_errors(timestamps_ns, rotation_sigma_rad, correlation_time_s, gen)
    return drift + jitter, rotation


#: the names :func:`draw_errors` takes
ERROR_MODELS = ("gaussian", "drift", "vio", "hand", "none")


def draw_errors(
    model: str,
    timestamps_ns,
    sigma_m=PAPER_SIGMA_M,
    rng: np.random.Generator | int | None = None,
    correlation_time_s: float = 2.0,
    rotation_sigma_rad: float = HAND_ROTATION_SIGMA_RAD,
) -> tuple[np.ndarray, np.ndarray]:
    """One draw of a named error model: (translation float64 (M, 3) metres, rotation float64 (M, 3)
    radians; zeros for the models without rotation).

    sigma_m : per-axis size, metres: the jitter of "gaussian", the stationary sigma of "drift", the
    drift sigma of "hand" (its jitter and rotation keep :func:`hand_errors`'s defaults unless
    given); "vio" uses :func:`vio_errors`'s defaults; "none" is the truth.
    """
    stamps = np.asarray(timestamps_ns)
    m = int(stamps.shape[0])
    gen = np.random.default_rng(rng)
    zeros = np.zeros((m, 3))
    if model == "gaussian":
        return gaussian_errors(m, sigma_m, gen), zeros
    if model == "drift":
        return drift_errors(stamps, sigma_m, correlation_time_s, gen), zeros
    if model == "vio":
        return vio_errors(stamps, rng=gen), zeros
    if model == "hand":
        return hand_errors(stamps, sigma_m, correlation_time_s, rotation_sigma_rad=rotation_sigma_rad, rng=gen)
    if model == "none":
        return zeros, zeros.copy()
    raise TwinFocusError(f"unknown error model {model!r}; use one of {', '.join(ERROR_MODELS)}")


def apply_pose_errors(
    centres_m: np.ndarray, translation_m: np.ndarray, rotation_rad: np.ndarray | None = None
) -> np.ndarray:
    """Tracked phase centres of a rigid array moved by a small pose error per radar position.

    Channel k of position m moves by t_m + r_m x (c_mk - cbar_m): a translation shared by the K
    channels and a small rotation r_m (rotation vector, radians, first order) about the
    position's channel centre cbar_m, so the channels at the array's ends move most.

    centres_m : float (M, K, 3) true phase centres; translation_m : (M, 3) metres;
    rotation_rad : (M, 3) radians or None. Returns float64 (M, K, 3).
    """
    out = apply_position_errors(centres_m, translation_m)
    if rotation_rad is None:
        return out
    r = np.asarray(rotation_rad, dtype=np.float64)
    c = np.asarray(centres_m, dtype=np.float64)
    if r.shape != (c.shape[0], 3) or not np.isfinite(r).all():
        raise TwinFocusError(f"rotation_rad must be finite ({c.shape[0]}, 3) radians, got {r.shape}")
    arm = c - c.mean(axis=1, keepdims=True)
    return out + np.cross(np.broadcast_to(r[:, None, :], arm.shape), arm)


def apply_position_errors(centres_m: np.ndarray, errors_m: np.ndarray) -> np.ndarray:
    """Tracked phase centres: one rigid offset per radar position, shared by its K channels.

    centres_m : float (M, K, 3) true phase centres; errors_m : float (M, 3) metres.
    Returns float64 (M, K, 3) = centres + errors[:, None, :].
    """
    c = np.asarray(centres_m, dtype=np.float64)
    e = np.asarray(errors_m, dtype=np.float64)
    if c.ndim != 3 or c.shape[2] != 3:
        raise TwinFocusError(f"centres_m must be (M, K, 3), got shape {c.shape}")
    if e.shape != (c.shape[0], 3):
        raise TwinFocusError(f"errors_m must be ({c.shape[0]}, 3) to match centres_m {c.shape}, got {e.shape}")
    if not np.isfinite(e).all():
        raise TwinFocusError("errors_m holds NaN or inf")
    return c + e[:, None, :]
