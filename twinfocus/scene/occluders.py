"""Occluders: planar sheets (cloth, paper, plastic) that attenuate the radar returns from behind
them and hide them from the camera."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.scene.checks import checked_colour, filled, rotation_matrix, vec3_m
from twinfocus.scene.materials import MATERIALS, material


@dataclass
class Occluder:
    """A planar sheet that attenuates radar returns from behind it and hides them from the camera.

    centre_m : (3,); size_m : (width along u, height along v), metres; rotation : (3, 3) sheet
    plane -> scene (identity: facing the radar); material : key of :data:`MATERIALS`;
    attenuation_db : two-way loss, overriding the material's; colour_bgr : for the renderer.
    """

    centre_m: np.ndarray
    size_m: Sequence[float] | np.ndarray
    rotation: np.ndarray | None = None
    material: str = "polyester"
    attenuation_db: float | None = None
    colour_bgr: np.ndarray | None = None
    name: str = "occluder"

    def __post_init__(self) -> None:
        self.centre_m = vec3_m(f"occluder {self.name!r}: centre_m", self.centre_m)
        s = np.asarray(self.size_m, dtype=np.float64)
        if s.shape != (2,) or not np.isfinite(s).all() or np.any(s <= 0):
            raise TwinFocusError(
                f"occluder {self.name!r}: size_m must be 2 positive numbers (width, height), got {self.size_m!r}"
            )
        self.size_m = s
        self.rotation = rotation_matrix(f"occluder {self.name!r}: rotation", self.rotation)
        mat = material(self.material)
        if self.attenuation_db is not None:
            a = float(self.attenuation_db)
            if np.isnan(a) or a < 0:
                raise TwinFocusError(
                    f"occluder {self.name!r}: attenuation_db must be >= 0, got {self.attenuation_db!r}"
                )
            self.attenuation_db = a
        self.colour_bgr = checked_colour(self.colour_bgr, mat.colour_bgr)

    @property
    def two_way_attenuation_db(self) -> float:
        return MATERIALS[self.material].two_way_attenuation_db if self.attenuation_db is None else self.attenuation_db

    #: Raster cell of :attr:`mask` (renderers treat an occluder like a planar object).
    pixel_m: float = field(default=1e-3, init=False, repr=False)

    @property
    def mask(self) -> np.ndarray:
        """The sheet as a full mask raster, bool (rows along v, columns along u) at ``pixel_m``."""
        w, h = self.size_m
        return np.ones((max(1, round(h / self.pixel_m)), max(1, round(w / self.pixel_m))), dtype=bool)

    @property
    def amplitude_factor(self) -> float:
        """Amplitude gain of a return that crosses the sheet: 10^(-dB / 20) (0 when opaque)."""
        db = self.two_way_attenuation_db
        return 0.0 if np.isinf(db) else float(10.0 ** (-db / 20.0))

    def corners_m(self) -> np.ndarray:
        """Corners float64 (4, 3): top-left, top-right, bottom-right, bottom-left (as for masks)."""
        w, h = self.size_m
        uv = np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]])
        return self.centre_m + uv @ filled(self.rotation)[:, :2].T

    def crosses(self, origin_m, points_m: np.ndarray) -> np.ndarray:
        """Whether the segment from ``origin_m`` (3,) to each point (P, 3) passes through the sheet.

        Returns bool (P,). Points on the sheet itself or on the origin's side are not crossed.
        """
        o = vec3_m("origin_m", origin_m)
        p = np.asarray(points_m, dtype=np.float64)
        rot = filled(self.rotation)
        n = rot[:, 2]
        d = p - o
        denom = d @ n
        num = (self.centre_m - o) @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / denom
        hit_plane = (np.abs(denom) > 1e-15) & (t > 0) & (t < 1 - 1e-9)
        x = o + t[:, None] * d - self.centre_m
        u = x @ rot[:, 0]
        v = x @ rot[:, 1]
        w, h = self.size_m
        return hit_plane & (np.abs(u) <= w / 2) & (np.abs(v) <= h / 2)
