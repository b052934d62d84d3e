"""Flat plates as planar objects: rectangle, credit card, disc."""

from __future__ import annotations

import numpy as np

from twinfocus.scene.checks import positive
from twinfocus.scene.objects import PlanarObject


def rectangle(
    width_m: float,
    height_m: float,
    centre_m=(0.0, 0.0, 0.6),
    material: str = "metal",
    rotation=None,
    pixel_m: float = 0.5e-3,
    name: str = "rectangle",
    colour_bgr=None,
) -> PlanarObject:
    """A filled rectangle ``width_m`` (along u) x ``height_m`` (along v), to the nearest pixel."""
    width_m = positive("width_m", width_m)
    height_m = positive("height_m", height_m)
    pixel_m = positive("pixel_m", pixel_m)
    shape = (max(1, round(height_m / pixel_m)), max(1, round(width_m / pixel_m)))
    return PlanarObject(np.ones(shape, dtype=bool), pixel_m, centre_m, rotation, material, colour_bgr, None, name)


def card(
    centre_m=(0.0, 0.0, 0.6), material: str = "metal", width_m: float = 0.0856, height_m: float = 0.05398, **kwargs
) -> PlanarObject:
    """A credit-card-sized plate (ISO/IEC 7810 ID-1, 85.60 x 53.98 mm), like the paper's metal card."""
    kwargs.setdefault("name", "card")
    return rectangle(width_m, height_m, centre_m, material, **kwargs)


def disc(
    radius_m: float,
    centre_m=(0.0, 0.0, 0.6),
    material: str = "metal",
    rotation=None,
    pixel_m: float = 0.5e-3,
    name: str = "disc",
    colour_bgr=None,
) -> PlanarObject:
    """A filled disc of radius ``radius_m`` (the paper's circular reflector)."""
    radius_m = positive("radius_m", radius_m)
    pixel_m = positive("pixel_m", pixel_m)
    n = max(1, int(np.ceil(2 * radius_m / pixel_m)))
    c = (np.arange(n) + 0.5 - n / 2) * pixel_m
    mask = (c[None, :] ** 2 + c[:, None] ** 2) <= radius_m**2
    return PlanarObject(mask, pixel_m, centre_m, rotation, material, colour_bgr, None, name)
