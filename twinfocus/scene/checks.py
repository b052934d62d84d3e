"""Checks of the scene's arguments (positions, rotations, colours, positive numbers, roughness):
each returns the checked value or raises TwinFocusError naming the argument."""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError


def vec3_m(name: str, v) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise TwinFocusError(f"{name} must be 3 numbers (x, y, z) in metres, got {v!r}") from None
    if a.shape != (3,) or not np.isfinite(a).all():
        raise TwinFocusError(f"{name} must be 3 finite numbers (x, y, z) in metres, got {v!r}")
    return a


def filled(v: np.ndarray | None) -> np.ndarray:
    """A field that ``__post_init__`` fills in when given None (never None afterwards)."""
    assert v is not None
    return v


def rotation_matrix(name: str, r) -> np.ndarray:
    if r is None:
        return np.eye(3)
    a = np.asarray(r, dtype=np.float64)
    if a.shape != (3, 3) or not np.isfinite(a).all():
        raise TwinFocusError(f"{name} must be a finite 3 x 3 rotation matrix, got shape {a.shape}")
    if not np.allclose(a @ a.T, np.eye(3), atol=1e-6) or np.linalg.det(a) < 0:
        raise TwinFocusError(f"{name} must be a proper rotation (orthonormal, det +1)")
    return a


def checked_colour(c, default: tuple[int, int, int]) -> np.ndarray:
    if c is None:
        return np.array(default, dtype=np.uint8)
    a = np.asarray(c)
    if a.shape != (3,) or not np.isfinite(a.astype(float)).all() or a.min() < 0 or a.max() > 255:
        raise TwinFocusError(f"colour_bgr must be 3 numbers in 0..255 (B, G, R), got {c!r}")
    return a.astype(np.uint8)


def positive(name: str, v) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise TwinFocusError(f"{name} must be a positive number, got {v!r}") from None
    if not (np.isfinite(f) and f > 0):
        raise TwinFocusError(f"{name} must be a positive number, got {v!r}")
    return f


def checked_roughness(name: str, roughness_deg, amplitude_spread) -> tuple[float | None, float]:
    if roughness_deg is not None:
        r = float(roughness_deg)
        if not (np.isfinite(r) and 0.0 <= r <= 180.0):
            raise TwinFocusError(f"object {name!r}: roughness_deg must lie in [0, 180] degrees, got {roughness_deg!r}")
        roughness_deg = r
    a = float(amplitude_spread)
    if not (np.isfinite(a) and 0.0 <= a < 1.0):
        raise TwinFocusError(f"object {name!r}: amplitude_spread must lie in [0, 1), got {amplitude_spread!r}")
    return roughness_deg, a
