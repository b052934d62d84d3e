"""Non-planar reference shapes: a planar object wrapped onto a cylinder or folded along its
centre line (a depth map over its mask), and :func:`shaped` choosing one by name."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.scene.checks import positive
from twinfocus.scene.objects import PlanarObject


def _object_u(obj: PlanarObject) -> np.ndarray:
    """u coordinate (metres) of every mask column's centre, float64 (w,)."""
    w = obj.mask.shape[1]
    return (np.arange(w) + 0.5 - w / 2) * obj.pixel_m


def cylinder_section(obj: PlanarObject, radius_m: float) -> PlanarObject:
    """``obj`` wrapped onto a cylinder of radius ``radius_m`` whose axis runs along v (the mask's
    rows), convex towards the radar: the centre column stays at w = 0 and a column at u recedes by
    R - sqrt(R^2 - u^2). The mask is kept as the object's projection on its plane. Returns a new
    :class:`PlanarObject` with ``depth_m`` set (same name, material, roughness)."""
    r = positive("radius_m", radius_m)
    u = _object_u(obj)
    if np.abs(u).max() >= r:
        raise TwinFocusError(f"cylinder radius {r} m is smaller than half the object's width ({np.abs(u).max():.4f} m)")
    w = r - np.sqrt(r * r - u * u)
    return replace(obj, depth_m=np.broadcast_to(w[None, :], obj.mask.shape).copy())


def bent_plate(obj: PlanarObject, bend_deg: float) -> PlanarObject:
    """``obj`` folded along its centre line u = 0 (a crease along v) by ``bend_deg`` degrees in
    all: each half turns away from the radar by bend/2, so a column at u recedes by
    |u| tan(bend / 2) (a V with its crease towards the radar). Returns a new :class:`PlanarObject`
    with ``depth_m`` set."""
    b = float(bend_deg)
    if not (np.isfinite(b) and 0.0 <= b < 180.0):
        raise TwinFocusError(f"bend_deg must lie in [0, 180), got {bend_deg!r}")
    w = np.abs(_object_u(obj)) * np.tan(np.deg2rad(b) / 2.0)
    return replace(obj, depth_m=np.broadcast_to(w[None, :], obj.mask.shape).copy())


#: Reference shapes :func:`shaped` knows, with the meaning of their parameter.
SHAPES = {"plane": "none", "cylinder": "radius, metres", "bent": "bend angle, degrees"}


def shaped(obj: PlanarObject, shape: str, parameter: float | None = None) -> PlanarObject:
    """``obj`` as a ``shape`` of :data:`SHAPES`: 'plane' (unchanged), 'cylinder'
    (:func:`cylinder_section`, ``parameter`` the radius, default 0.15 m) or 'bent'
    (:func:`bent_plate`, ``parameter`` the bend, default 30 degrees)."""
    if shape == "plane":
        return obj
    if shape == "cylinder":
        return cylinder_section(obj, 0.15 if parameter is None else parameter)
    if shape == "bent":
        return bent_plate(obj, 30.0 if parameter is None else parameter)
    raise TwinFocusError(f"unknown shape {shape!r}; use one of {', '.join(SHAPES)}")
