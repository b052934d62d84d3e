"""Scene objects: a flat mask raster in its own plane (:class:`PlanarObject`, optionally with a
depth map) or point scatterers given directly (:class:`PointCloudObject`).

Geometry (docs/architecture.md section 4): a planar object's own frame has u along its mask's
columns, v along its mask's rows (downwards in the raster) and lies in the plane w = 0;
``rotation`` maps (u, v, w) to the scene, so the identity puts the mask upright as seen from the
radar (u -> +x, v -> +y: x right, y down, z forward, the camera convention) and the plane faces
the radar (normal towards -z).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.scene.checks import checked_colour, checked_roughness, filled, positive, rotation_matrix, vec3_m
from twinfocus.scene.materials import MATERIALS, material
from twinfocus.scene.scatterers import DEFAULT_SPACING_M, random_phase, rough_amplitudes


@dataclass
class PlanarObject:
    """A flat object given by a boolean mask raster in its own plane.

    Attributes
    ----------
    mask : bool (h, w); True where the object is. Row i, column j is the square pixel centred
        at (u, v) = ((j + 1/2 - w/2) p, (i + 1/2 - h/2) p) in the object plane, p = ``pixel_m``.
    pixel_m : side of one mask pixel, metres.
    centre_m : float64 (3,), scene position of the mask's centre.
    rotation : float64 (3, 3), object plane (u, v, w) -> scene; identity faces the radar.
    material : key of :data:`MATERIALS`.
    colour_bgr : uint8 (3,) for the camera renderer (default: the material's).
    texture : optional uint8 (h, w, 3) BGR picture of the surface, same raster as ``mask``.
    name : label (the scene's objects are told apart by name).
    depth_m : optional float64 (h, w), the surface's displacement along w (away from the radar
        for the identity rotation) at every mask pixel, metres: a non-planar object (see
        :func:`cylinder_section`, :func:`bent_plate`). None: flat. Camera renderers that draw
        the mask as a flat quad ignore it.
    roughness_deg : a rough surface: every scatterer gets its own reflectivity phase, uniform in
        +-roughness_deg degrees, and magnitude, reflectivity x (1 +- amplitude_spread) uniform;
        it replaces the scene-wide ``speckle`` for this object. None: ``speckle`` decides.
    amplitude_spread : fraction, see ``roughness_deg`` (used only with it).
    """

    mask: np.ndarray
    pixel_m: float
    centre_m: np.ndarray
    rotation: np.ndarray | None = None
    material: str = "metal"
    colour_bgr: np.ndarray | None = None
    texture: np.ndarray | None = None
    name: str = "object"
    depth_m: np.ndarray | None = None
    roughness_deg: float | None = None
    amplitude_spread: float = 0.0

    def __post_init__(self) -> None:
        m = np.asarray(self.mask)
        if m.ndim != 2 or m.size == 0:
            raise TwinFocusError(f"object {self.name!r}: mask must be a non-empty 2-D array, got shape {m.shape}")
        if m.dtype != bool:
            raise TwinFocusError(f"object {self.name!r}: mask must be boolean, got dtype {m.dtype}")
        if not m.any():
            raise TwinFocusError(f"object {self.name!r}: mask is empty (no pixel set)")
        self.mask = m
        self.pixel_m = positive(f"object {self.name!r}: pixel_m", self.pixel_m)
        self.centre_m = vec3_m(f"object {self.name!r}: centre_m", self.centre_m)
        self.rotation = rotation_matrix(f"object {self.name!r}: rotation", self.rotation)
        mat = material(self.material)
        self.colour_bgr = checked_colour(self.colour_bgr, mat.colour_bgr)
        if self.texture is not None:
            t = np.asarray(self.texture)
            if t.shape != (*m.shape, 3) or t.dtype != np.uint8:
                raise TwinFocusError(
                    f"object {self.name!r}: texture must be uint8 {(*m.shape, 3)} (BGR, the mask's raster), "
                    f"got {t.dtype} {t.shape}"
                )
            self.texture = t
        if self.depth_m is not None:
            d = np.asarray(self.depth_m, dtype=np.float64)
            if d.shape != m.shape or not np.isfinite(d).all():
                raise TwinFocusError(
                    f"object {self.name!r}: depth_m must be finite float {m.shape} (the mask's raster), got shape {d.shape}"
                )
            self.depth_m = d
        self.roughness_deg, self.amplitude_spread = checked_roughness(
            self.name, self.roughness_deg, self.amplitude_spread
        )

    @property
    def reflectivity(self) -> float:
        return MATERIALS[self.material].reflectivity

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the mask raster, metres."""
        h, w = self.mask.shape
        return (w * self.pixel_m, h * self.pixel_m)

    @property
    def normal_m(self) -> np.ndarray:
        """Unit normal of the face turned to the radar (scene frame); (0, 0, -1) for identity."""
        return -filled(self.rotation)[:, 2]

    def plane_to_scene(self, uv: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """Scene positions float64 (N, 3) of object-frame points ``uv`` (N, 2), metres, displaced
        by ``w`` (N,) along the object's w axis when given."""
        uv = np.asarray(uv, dtype=np.float64)
        rot = filled(self.rotation)
        out = self.centre_m + uv @ rot[:, :2].T
        if w is not None:
            out = out + np.asarray(w, dtype=np.float64)[:, None] * rot[:, 2]
        return out

    def surface_points(self, spacing_m: float = DEFAULT_SPACING_M) -> np.ndarray:
        """The object's surface sampled on a regular grid ``spacing_m`` apart (cell centres where
        the mask is set, with ``depth_m``), float64 (N, 3) scene metres: what an ideal camera
        would see of it."""
        spacing_m = positive("spacing_m", spacing_m)
        uv, rc = self._grid(spacing_m, None, 0.0)
        return self.plane_to_scene(uv, self._depth_at(rc))

    def _grid(self, spacing_m: float, gen, jitter: float) -> tuple[np.ndarray, np.ndarray]:
        w_m, h_m = self.size_m
        nu = max(1, int(np.ceil(w_m / spacing_m)))
        nv = max(1, int(np.ceil(h_m / spacing_m)))
        uu, vv = np.meshgrid((np.arange(nu) - (nu - 1) / 2) * spacing_m, (np.arange(nv) - (nv - 1) / 2) * spacing_m)
        uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
        if gen is not None:
            uv += (gen.random(uv.shape) - 0.5) * float(jitter) * spacing_m
        h, w = self.mask.shape
        col = np.floor(uv[:, 0] / self.pixel_m + w / 2).astype(np.int64)
        row = np.floor(uv[:, 1] / self.pixel_m + h / 2).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        keep = np.zeros(uv.shape[0], dtype=bool)
        keep[inside] = self.mask[row[inside], col[inside]]
        return uv[keep], np.stack([row[keep], col[keep]], axis=1)

    def _depth_at(self, rc: np.ndarray) -> np.ndarray | None:
        return None if self.depth_m is None else self.depth_m[rc[:, 0], rc[:, 1]]

    def corners_m(self) -> np.ndarray:
        """Corners of the mask raster in the scene, float64 (4, 3), in the order of the raster's
        (row, col) corners (0, 0), (0, w), (h, w), (h, 0): top-left, top-right, bottom-right,
        bottom-left as seen from the radar for the identity rotation."""
        w, h = self.size_m
        uv = np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]])
        return self.plane_to_scene(uv)

    def outline_m(self) -> list[np.ndarray]:
        """Boundaries of the mask (outer edges and holes) as scene polylines float64 (n, 3)."""
        contours, _ = cv2.findContours(self.mask.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
        h, w = self.mask.shape
        out = []
        for c in contours:
            xy = c.reshape(-1, 2).astype(np.float64)
            uv = np.stack([(xy[:, 0] + 0.5 - w / 2), (xy[:, 1] + 0.5 - h / 2)], axis=1) * self.pixel_m
            out.append(self.plane_to_scene(uv))
        return out

    def scatterers(
        self,
        spacing_m: float = DEFAULT_SPACING_M,
        rng: np.random.Generator | int | None = None,
        speckle: bool = True,
        jitter: float = 1.0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Point scatterers covering the mask.

        A grid of cells ``spacing_m`` wide over the raster; one point per cell, displaced
        uniformly by up to ``jitter`` x spacing / 2 in u and v (1.0: anywhere in its cell, which
        breaks the grid's regularity so it makes no grating lobes), kept where the mask is set.
        Amplitude: the material's reflectivity, times a uniformly random unit phase when
        ``speckle`` (a rough surface), else real; an object with ``roughness_deg`` set gets
        :func:`rough_amplitudes` instead, whatever ``speckle`` says. Points follow ``depth_m``.

        Returns (points_m float64 (P, 3), amplitudes complex128 (P,)).
        """
        spacing_m = positive("spacing_m", spacing_m)
        if not (0.0 <= float(jitter) <= 1.0):
            raise TwinFocusError(f"jitter must lie in [0, 1], got {jitter!r}")
        gen = np.random.default_rng(rng)
        uv, rc = self._grid(spacing_m, gen, jitter)
        n = uv.shape[0]
        if self.roughness_deg is not None:
            amp = rough_amplitudes(self.reflectivity, n, self.roughness_deg, self.amplitude_spread, gen)
        else:
            amp = np.full(n, self.reflectivity, dtype=np.complex128)
            if speckle:
                amp *= random_phase(gen, n)
        return self.plane_to_scene(uv, self._depth_at(rc)), amp


@dataclass
class PointCloudObject:
    """An object given directly as point scatterers (e.g. a stereo camera's point cloud).

    points_m : float64 (N, 3) scene positions; amplitudes : optional complex (N,) (default: the
    material's reflectivity, with a random phase per point when ``speckle``).
    """

    points_m: np.ndarray
    amplitudes: np.ndarray | None = None
    material: str = "metal"
    colour_bgr: np.ndarray | None = None
    name: str = "points"
    roughness_deg: float | None = None
    amplitude_spread: float = 0.0

    def __post_init__(self) -> None:
        p = np.asarray(self.points_m)
        if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0:
            raise TwinFocusError(f"object {self.name!r}: points must be a non-empty (N, 3) array, got shape {p.shape}")
        p = p.astype(np.float64)
        if not np.isfinite(p).all():
            i = int(np.argwhere(~np.isfinite(p))[0][0])
            raise TwinFocusError(f"object {self.name!r}: points hold NaN or inf (first at point {i})")
        self.points_m = p
        if self.amplitudes is not None:
            a = np.asarray(self.amplitudes)
            if a.shape != (p.shape[0],):
                raise TwinFocusError(f"object {self.name!r}: amplitudes must have shape ({p.shape[0]},), got {a.shape}")
            a = a.astype(np.complex128)
            if not np.isfinite(a).all():
                raise TwinFocusError(f"object {self.name!r}: amplitudes hold NaN or inf")
            self.amplitudes = a
        mat = material(self.material)
        self.colour_bgr = checked_colour(self.colour_bgr, mat.colour_bgr)
        self.roughness_deg, self.amplitude_spread = checked_roughness(
            self.name, self.roughness_deg, self.amplitude_spread
        )

    @property
    def reflectivity(self) -> float:
        return MATERIALS[self.material].reflectivity

    def surface_points(self, spacing_m: float | None = None) -> np.ndarray:
        """The points (thinned to one per cube of side ``spacing_m`` if given), float64 (N, 3)."""
        return self.scatterers(spacing_m, 0, speckle=False)[0]

    def scatterers(
        self,
        spacing_m: float | None = None,
        rng: np.random.Generator | int | None = None,
        speckle: bool = True,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The points (thinned to one per cube of side ``spacing_m`` if given) and amplitudes.

        Returns (points_m float64 (P, 3), amplitudes complex128 (P,)).
        """
        gen = np.random.default_rng(rng)
        pts = self.points_m
        idx = np.arange(pts.shape[0])
        if spacing_m is not None:
            spacing_m = positive("spacing_m", spacing_m)
            keys = np.floor(pts / spacing_m).astype(np.int64)
            _, idx = np.unique(keys, axis=0, return_index=True)
            idx = np.sort(idx)
        if self.amplitudes is not None:
            amp = self.amplitudes[idx].copy()
        elif self.roughness_deg is not None:
            amp = rough_amplitudes(self.reflectivity, idx.shape[0], self.roughness_deg, self.amplitude_spread, gen)
        else:
            amp = np.full(idx.shape[0], self.reflectivity, dtype=np.complex128)
            if speckle:
                amp *= random_phase(gen, idx.shape[0])
        return pts[idx].copy(), amp


SceneObject = PlanarObject | PointCloudObject


def from_points(
    points_m, amplitudes=None, material: str = "metal", name: str = "points", colour_bgr=None
) -> PointCloudObject:
    """A :class:`PointCloudObject` from arbitrary points (N, 3) and optional amplitudes (N,)."""
    return PointCloudObject(np.asarray(points_m), amplitudes, material, colour_bgr, name)
