"""Plates and hand tools as flat references of a letter's size: a plate, a disc, a washer (a
ring), an open-ended wrench and a key, each fitting a box ``height_m`` tall like a letter.

Each is a mask drawn on a pixel raster in the object's own plane (u across, v down, origin at the
mask's centre); the scene builds it by name (:data:`OBJECT_SHAPES`) wherever it takes a letter.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.scene.checks import positive
from twinfocus.scene.objects import PlanarObject


def _plate(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    # a plate as wide as a letter (0.65 of its height), its corners rounded by a tenth of it
    a, b, r = 0.325, 0.5, 0.1
    du, dv = np.maximum(np.abs(u) - (a - r), 0), np.maximum(np.abs(v) - (b - r), 0)
    return (np.abs(u) <= a) & (np.abs(v) <= b) & (du**2 + dv**2 <= r**2)


def _disc(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u**2 + v**2 <= 0.4**2


def _washer(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    r2 = u**2 + v**2
    return (r2 <= 0.45**2) & (r2 >= 0.2**2)


def _wrench(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    # a handle down the middle and an open jaw at the top: a disc with a slot cut into it
    handle = (np.abs(u) <= 0.07) & (v >= -0.2) & (v <= 0.5)
    head = u**2 + (v + 0.3) ** 2 <= 0.2**2
    jaw = (np.abs(u) <= 0.075) & (v <= -0.3)
    return (handle | head) & ~jaw


def _key(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    # a ring-shaped bow at the top, a blade below it with three bits on its right
    r2 = u**2 + (v + 0.32) ** 2
    bow = (r2 <= 0.18**2) & (r2 >= 0.08**2)
    blade = (np.abs(u) <= 0.05) & (v >= -0.16) & (v <= 0.5)
    bits = (
        (u > 0.05) & (u <= 0.15) & (((v >= 0.2) & (v <= 0.27)) | ((v >= 0.33) & (v <= 0.38)) | (v >= 0.43)) & (v <= 0.5)
    )
    return bow | blade | bits


#: the shapes by name: each a function of (u, v) in units of the height (the box u in
#: [-0.5, 0.5], v in [-0.5, 0.5]) that is True on the object
OBJECT_SHAPES: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "plate": _plate,
    "disc": _disc,
    "washer": _washer,
    "wrench": _wrench,
    "key": _key,
}


def shape_mask(shape: str, height_m: float = 0.127, pixel_m: float | None = None) -> np.ndarray:
    """bool (h, w): the mask of :data:`OBJECT_SHAPES` ``shape``, ``height_m`` tall, on pixels of
    ``pixel_m`` (default height / 400), trimmed to the object's rows and columns."""
    if shape not in OBJECT_SHAPES:
        raise TwinFocusError(f"unknown object shape {shape!r}; use a letter or one of {', '.join(OBJECT_SHAPES)}")
    height_m = positive("height_m", height_m)
    pixel_m = height_m / 400.0 if pixel_m is None else positive("pixel_m", pixel_m)
    n = max(3, round(height_m / pixel_m))
    c = (np.arange(n) + 0.5 - n / 2) * pixel_m / height_m
    mask = OBJECT_SHAPES[shape](c[None, :], c[:, None])
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    return mask[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]


def shaped_object(
    shape: str,
    height_m: float = 0.127,
    centre_m=(0.0, 0.0, 0.6),
    material: str = "metal",
    rotation=None,
    pixel_m: float | None = None,
    name: str | None = None,
    colour_bgr=None,
) -> PlanarObject:
    """A flat plate or tool of :data:`OBJECT_SHAPES` as a :class:`PlanarObject` centred at
    ``centre_m`` (metres), like :func:`twinfocus.scene.letters.letter` for a letter."""
    mask = shape_mask(shape, height_m, pixel_m)
    pixel_m = height_m / 400.0 if pixel_m is None else pixel_m
    return PlanarObject(mask, pixel_m, centre_m, rotation, material, colour_bgr, None, name or shape)
