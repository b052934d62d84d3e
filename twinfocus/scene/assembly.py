"""The :class:`Scene`: objects, occluders and clutter put together, and their point scatterers
for the radar simulator (one random stream per object, occluder attenuation applied)."""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.scene.checks import vec3_m
from twinfocus.scene.clutter import Clutter
from twinfocus.scene.objects import PlanarObject, PointCloudObject, SceneObject
from twinfocus.scene.occluders import Occluder
from twinfocus.scene.scatterers import DEFAULT_SPACING_M


@dataclass
class Scene:
    """Objects, occluders and clutter.

    Each object's random draws (scatterer jitter, speckle) come from its own stream, keyed by the
    scene's seed and the object's name, so a sub-scene (:meth:`select`) gives the *same*
    scatterers for the objects it keeps: a template scan of the reference alone sees the same
    reference as the full scan, as a physical twin would.
    """

    objects: list = field(default_factory=list)
    occluders: list = field(default_factory=list)
    clutter: Clutter | None = None

    def __post_init__(self) -> None:
        self.objects = list(self.objects)
        self.occluders = list(self.occluders)
        for o in self.objects:
            if not isinstance(o, (PlanarObject, PointCloudObject)):
                raise TwinFocusError(f"scene objects must be PlanarObject or PointCloudObject, got {type(o).__name__}")
        for o in self.occluders:
            if not isinstance(o, Occluder):
                raise TwinFocusError(f"scene occluders must be Occluder, got {type(o).__name__}")
        if self.clutter is not None and not isinstance(self.clutter, Clutter):
            raise TwinFocusError(f"scene clutter must be a Clutter or None, got {type(self.clutter).__name__}")

    @property
    def names(self) -> list[str]:
        return [o.name for o in self.objects]

    def object(self, name: str) -> SceneObject:
        """The first object called ``name``."""
        for o in self.objects:
            if o.name == name:
                return o
        raise TwinFocusError(f"scene has no object named {name!r}; it has {', '.join(self.names) or 'none'}")

    def select(self, *names: str, occluders: bool = True, clutter: bool = False) -> Scene:
        """A scene with only the objects called ``names`` (same occluders unless told otherwise)."""
        for n in names:
            self.object(n)  # raises for an unknown name
        return Scene(
            [o for o in self.objects if o.name in names],
            list(self.occluders) if occluders else [],
            self.clutter if clutter else None,
        )

    def scatterers(
        self,
        spacing_m: float = DEFAULT_SPACING_M,
        rng: np.random.Generator | int | None = None,
        speckle: bool = True,
        aperture_centre_m=(0.0, 0.0, 0.0),
        return_labels: bool = False,
    ):
        """All point scatterers of the scene, with occluder attenuation applied.

        A scatterer's amplitude is multiplied by an occluder's ``amplitude_factor`` when the
        segment from ``aperture_centre_m`` to it crosses that occluder (one ray per scatterer; the
        aperture is small next to the range, so this stands for every channel). Opaque occluders
        remove the scatterers they hide.

        Returns (points_m float64 (P, 3), amplitudes complex128 (P,)), and with ``return_labels``
        also int64 (P,): index into ``objects``, or -1 for clutter.
        """
        if not self.objects and (self.clutter is None or self.clutter.n_points + self.clutter.n_strong == 0):
            raise TwinFocusError("scene is empty: it has no objects and no clutter")
        gen = np.random.default_rng(rng)
        base = int(gen.integers(0, 2**63 - 1))
        pts, amps, labels = [], [], []
        seen: dict[str, int] = {}
        for i, obj in enumerate(self.objects):
            k = seen.get(obj.name, 0)
            seen[obj.name] = k + 1
            sub = np.random.default_rng([base, zlib.crc32(f"{obj.name}#{k}".encode())])
            p, a = obj.scatterers(spacing_m, sub, speckle)
            pts.append(p)
            amps.append(a)
            labels.append(np.full(p.shape[0], i, dtype=np.int64))
        if self.clutter is not None:
            p, a = self.clutter.scatterers(np.random.default_rng([base, zlib.crc32(b"clutter")]))
            pts.append(p)
            amps.append(a)
            labels.append(np.full(p.shape[0], -1, dtype=np.int64))
        points = np.concatenate(pts, axis=0)
        amplitudes = np.concatenate(amps)
        label = np.concatenate(labels)
        origin = vec3_m("aperture_centre_m", aperture_centre_m)
        for occ in self.occluders:
            hit = occ.crosses(origin, points)
            amplitudes[hit] *= occ.amplitude_factor
        keep = amplitudes != 0
        if not keep.any():
            raise TwinFocusError("every scatterer of the scene is hidden behind an opaque occluder")
        points, amplitudes, label = points[keep], amplitudes[keep], label[keep]
        return (points, amplitudes, label) if return_labels else (points, amplitudes)
