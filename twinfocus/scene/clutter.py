"""Clutter: random weak and strong point scatterers filling a box (a cluttered room)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.scene.checks import positive, vec3_m
from twinfocus.scene.scatterers import random_phase


@dataclass
class Clutter:
    """Random weak scatterers in a box, plus optionally a few strong ones (a cluttered room).

    volume_min_m, volume_max_m : (3,) corners of the box; n_points weak scatterers of amplitude
    ``amplitude`` and n_strong of ``strong_amplitude`` (multipath-like bright spots), each with a
    random phase, uniformly placed in the box.
    """

    volume_min_m: np.ndarray
    volume_max_m: np.ndarray
    n_points: int = 300
    amplitude: float = 0.05
    n_strong: int = 0
    strong_amplitude: float = 0.5

    def __post_init__(self) -> None:
        self.volume_min_m = vec3_m("clutter volume_min_m", self.volume_min_m)
        self.volume_max_m = vec3_m("clutter volume_max_m", self.volume_max_m)
        if np.any(self.volume_max_m < self.volume_min_m):
            raise TwinFocusError("clutter volume_max_m must be >= volume_min_m on every axis")
        if int(self.n_points) < 0 or int(self.n_strong) < 0:
            raise TwinFocusError("clutter n_points and n_strong must be >= 0")
        for name in ("amplitude", "strong_amplitude"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v >= 0):
                raise TwinFocusError(f"clutter {name} must be a non-negative number, got {v!r}")

    @classmethod
    def room(cls, distance_m: float = 0.6, n_points: int = 300, n_strong: int = 4) -> Clutter:
        """Clutter behind and around a scene at ``distance_m``: a box 0.8 m x 0.6 m across, from
        5 cm to 60 cm behind it, with ``n_strong`` bright spots."""
        d = positive("distance_m", distance_m)
        return cls(
            np.array([-0.4, -0.3, d + 0.05]), np.array([0.4, 0.3, d + 0.6]), n_points=n_points, n_strong=n_strong
        )

    def scatterers(self, rng: np.random.Generator | int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(points_m float64 (P, 3), amplitudes complex128 (P,)), P = n_points + n_strong."""
        gen = np.random.default_rng(rng)
        n = int(self.n_points) + int(self.n_strong)
        pts = self.volume_min_m + gen.random((n, 3)) * (self.volume_max_m - self.volume_min_m)
        amp = np.full(n, float(self.amplitude), dtype=np.complex128)
        amp[int(self.n_points) :] = float(self.strong_amplitude)
        return pts, amp * random_phase(gen, n)
