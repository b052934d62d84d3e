"""Scenes for the radar simulator and the digital twin's camera renderer.

A :class:`Scene` holds objects (flat masks such as metal letters, or point clouds), occluders
(sheets of cloth, paper, plastic that attenuate what lies behind them and hide it from the
camera) and optional clutter. The radar simulator asks it for point scatterers
(:meth:`Scene.scatterers`); a camera renderer uses the same objects' masks, corners, colours and
textures.

Geometry (docs/architecture.md section 4): scene frame x, y across the aperture, z from the aperture into
the scene. A planar object's own frame has u along its mask's columns, v along its mask's rows
(downwards in the raster) and lies in the plane w = 0; ``rotation`` maps (u, v, w) to the scene,
so the identity puts the mask upright as seen from the radar (u -> +x, v -> +y: x right, y down,
z forward, the camera convention) and the plane faces the radar (normal towards -z).

Scatterer density: the cross-range resolution of the paper's aperture is
lambda R / (2 D) = 3.9 mm * 0.6 m / (2 * 0.49 m) ~ 2.4 mm; scatterers a quarter to a half of that
apart make a continuous surface in the image. :data:`DEFAULT_SPACING_M` is half (1.2 mm), which
gives about 1,500-2,500 points for a 127 mm letter.
"""
from __future__ import annotations

import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from twinfocus.errors import TwinFocusError


@dataclass(frozen=True)
class Material:
    """Radar and camera properties of a material.

    reflectivity : backscatter amplitude relative to metal (metal = 1).
    two_way_attenuation_db : loss of a return that crosses a sheet of this material on the way
        in and out, in dB (inf: opaque to the radar).
    colour_bgr : default colour for the camera renderer (OpenCV order).
    """

    name: str
    reflectivity: float
    two_way_attenuation_db: float
    colour_bgr: tuple[int, int, int]


# Nominal values, not measurements. Reflectivities are of the order of the normal-incidence
# Fresnel amplitude |1 - sqrt(er)| / (1 + sqrt(er)) at W-band (plastics er ~ 2.3 -> 0.2; dry wood
# er ~ 2 - 3, raised by moisture and grain -> 0.3) and are used as contrast between materials.
# Attenuations are round two-way numbers for thin sheets (single layer of clothing, a few sheets
# of paper, a 2 - 3 mm plastic panel, corrugated board): mm-wave screening works because these
# pass most of the power; change them per experiment with Occluder(attenuation_db=...).
MATERIALS: dict[str, Material] = {
    m.name: m
    for m in (
        Material("metal", 1.0, float("inf"), (190, 190, 190)),
        Material("wood", 0.3, 10.0, (60, 120, 170)),
        Material("plastic", 0.15, 3.0, (60, 60, 200)),
        Material("polyester", 0.05, 2.0, (170, 110, 60)),
        Material("cloth", 0.05, 2.0, (150, 150, 210)),
        Material("paper", 0.05, 3.0, (235, 240, 245)),
        Material("cardboard", 0.1, 5.0, (100, 150, 190)),
    )
}

#: Cross-range resolution of the paper set-up (wavelength 3.9 mm, 0.6 m, 0.49 m aperture) / 2.
DEFAULT_SPACING_M = 1.2e-3

# OpenCV's Hershey fonts by name (cv2.putText renders printable ASCII only).
FONTS: dict[str, int] = {
    "simplex": cv2.FONT_HERSHEY_SIMPLEX,
    "plain": cv2.FONT_HERSHEY_PLAIN,
    "duplex": cv2.FONT_HERSHEY_DUPLEX,
    "complex": cv2.FONT_HERSHEY_COMPLEX,
    "triplex": cv2.FONT_HERSHEY_TRIPLEX,
    "complex_small": cv2.FONT_HERSHEY_COMPLEX_SMALL,
    "script_simplex": cv2.FONT_HERSHEY_SCRIPT_SIMPLEX,
    "script_complex": cv2.FONT_HERSHEY_SCRIPT_COMPLEX,
}


def scatterer_spacing_m(range_m: float, aperture_m: float = 0.49, wavelength_m: float = 3.9e-3, fraction: float = 0.5) -> float:
    """``fraction`` of the cross-range resolution lambda R / (2 D), metres."""
    if not (range_m > 0 and aperture_m > 0 and wavelength_m > 0 and fraction > 0):
        raise TwinFocusError("range_m, aperture_m, wavelength_m and fraction must all be positive")
    return float(fraction * wavelength_m * range_m / (2.0 * aperture_m))


def material(name: str) -> Material:
    """The :class:`Material` called ``name`` (TwinFocusError listing the known ones otherwise)."""
    try:
        return MATERIALS[name]
    except (KeyError, TypeError):
        raise TwinFocusError(f"unknown material {name!r}; known: {', '.join(sorted(MATERIALS))}") from None


# --- validation helpers -----------------------------------------------------------------------


def _vec3(name: str, v) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise TwinFocusError(f"{name} must be 3 numbers (x, y, z) in metres, got {v!r}") from None
    if a.shape != (3,) or not np.isfinite(a).all():
        raise TwinFocusError(f"{name} must be 3 finite numbers (x, y, z) in metres, got {v!r}")
    return a


def _filled(v: np.ndarray | None) -> np.ndarray:
    """A field that ``__post_init__`` fills in when given None (never None afterwards)."""
    assert v is not None
    return v


def _rotation(name: str, r) -> np.ndarray:
    if r is None:
        return np.eye(3)
    a = np.asarray(r, dtype=np.float64)
    if a.shape != (3, 3) or not np.isfinite(a).all():
        raise TwinFocusError(f"{name} must be a finite 3 x 3 rotation matrix, got shape {a.shape}")
    if not np.allclose(a @ a.T, np.eye(3), atol=1e-6) or np.linalg.det(a) < 0:
        raise TwinFocusError(f"{name} must be a proper rotation (orthonormal, det +1)")
    return a


def _colour(c, default: tuple[int, int, int]) -> np.ndarray:
    if c is None:
        return np.array(default, dtype=np.uint8)
    a = np.asarray(c)
    if a.shape != (3,) or not np.isfinite(a.astype(float)).all() or a.min() < 0 or a.max() > 255:
        raise TwinFocusError(f"colour_bgr must be 3 numbers in 0..255 (B, G, R), got {c!r}")
    return a.astype(np.uint8)


def _positive(name: str, v) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise TwinFocusError(f"{name} must be a positive number, got {v!r}") from None
    if not (np.isfinite(f) and f > 0):
        raise TwinFocusError(f"{name} must be a positive number, got {v!r}")
    return f


def _random_phase(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.exp(2j * np.pi * rng.random(n))


def _check_roughness(name: str, roughness_deg, amplitude_spread) -> tuple[float | None, float]:
    if roughness_deg is not None:
        r = float(roughness_deg)
        if not (np.isfinite(r) and 0.0 <= r <= 180.0):
            raise TwinFocusError(f"object {name!r}: roughness_deg must lie in [0, 180] degrees, got {roughness_deg!r}")
        roughness_deg = r
    a = float(amplitude_spread)
    if not (np.isfinite(a) and 0.0 <= a < 1.0):
        raise TwinFocusError(f"object {name!r}: amplitude_spread must lie in [0, 1), got {amplitude_spread!r}")
    return roughness_deg, a


def rough_amplitudes(
    reflectivity: float, n: int, roughness_deg: float, amplitude_spread: float, rng: np.random.Generator
) -> np.ndarray:
    """Amplitudes of ``n`` scatterers of a rough surface, complex128 (n,).

    Each scatterer has its own reflectivity phase, uniform in [-roughness_deg, +roughness_deg]
    degrees, and its own magnitude, uniform in reflectivity x [1 - amplitude_spread,
    1 + amplitude_spread]. 180 degrees is full speckle (as ``speckle=True``), 0 a smooth surface.
    """
    phase = np.deg2rad(float(roughness_deg)) * (2.0 * rng.random(n) - 1.0)
    mag = float(reflectivity) * (1.0 + float(amplitude_spread) * (2.0 * rng.random(n) - 1.0))
    return mag * np.exp(1j * phase)


# --- objects ----------------------------------------------------------------------------------


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
        self.pixel_m = _positive(f"object {self.name!r}: pixel_m", self.pixel_m)
        self.centre_m = _vec3(f"object {self.name!r}: centre_m", self.centre_m)
        self.rotation = _rotation(f"object {self.name!r}: rotation", self.rotation)
        mat = material(self.material)
        self.colour_bgr = _colour(self.colour_bgr, mat.colour_bgr)
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
        self.roughness_deg, self.amplitude_spread = _check_roughness(self.name, self.roughness_deg, self.amplitude_spread)

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
        return -_filled(self.rotation)[:, 2]

    def plane_to_scene(self, uv: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """Scene positions float64 (N, 3) of object-frame points ``uv`` (N, 2), metres, displaced
        by ``w`` (N,) along the object's w axis when given."""
        uv = np.asarray(uv, dtype=np.float64)
        rot = _filled(self.rotation)
        out = self.centre_m + uv @ rot[:, :2].T
        if w is not None:
            out = out + np.asarray(w, dtype=np.float64)[:, None] * rot[:, 2]
        return out

    def surface_points(self, spacing_m: float = DEFAULT_SPACING_M) -> np.ndarray:
        """The object's surface sampled on a regular grid ``spacing_m`` apart (cell centres where
        the mask is set, with ``depth_m``), float64 (N, 3) scene metres: what an ideal camera
        would see of it."""
        spacing_m = _positive("spacing_m", spacing_m)
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
        spacing_m = _positive("spacing_m", spacing_m)
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
                amp *= _random_phase(gen, n)
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
        self.colour_bgr = _colour(self.colour_bgr, mat.colour_bgr)
        self.roughness_deg, self.amplitude_spread = _check_roughness(self.name, self.roughness_deg, self.amplitude_spread)

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
            spacing_m = _positive("spacing_m", spacing_m)
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
                amp *= _random_phase(gen, idx.shape[0])
        return pts[idx].copy(), amp


SceneObject = PlanarObject | PointCloudObject


def from_points(points_m, amplitudes=None, material: str = "metal", name: str = "points", colour_bgr=None) -> PointCloudObject:
    """A :class:`PointCloudObject` from arbitrary points (N, 3) and optional amplitudes (N,)."""
    return PointCloudObject(np.asarray(points_m), amplitudes, material, colour_bgr, name)


def _font(font) -> int:
    if isinstance(font, str):
        try:
            return FONTS[font]
        except KeyError:
            raise TwinFocusError(f"unknown font {font!r}; known: {', '.join(FONTS)}") from None
    if isinstance(font, (int, np.integer)) and int(font) in FONTS.values():
        return int(font)
    raise TwinFocusError(f"unknown font {font!r}; use one of {', '.join(FONTS)}")


def letter_mask(
    char: str,
    height_m: float,
    pixel_m: float,
    font="simplex",
    stroke_m: float | None = None,
    width_scale: float = 0.65,
) -> np.ndarray:
    """Boolean raster of one character, ``height_m`` tall (ink extent), at ``pixel_m`` per pixel.

    The character's centre line is drawn by OpenCV's Hershey font (cv2.putText), scaled to
    height ``height_m - stroke_m`` and by ``width_scale`` across (Hershey capitals are about as
    wide as tall; 0.65 gives the condensed shape a pair of 127 mm letters 10 degrees apart at
    60 cm needs to leave a gap), and thickened to a uniform ``stroke_m`` (default 0.1 x height, 12.7 mm for 127 mm)
    with round ends. Returns bool (rows, cols) cropped to the ink.
    """
    if not isinstance(char, str) or len(char) != 1 or not (33 <= ord(char) <= 126):
        raise TwinFocusError(
            f"letter must be one printable ASCII character other than space (Hershey fonts), got {char!r}"
        )
    height_m = _positive("height_m", height_m)
    pixel_m = _positive("pixel_m", pixel_m)
    width_scale = _positive("width_scale", width_scale)
    stroke_m = 0.1 * height_m if stroke_m is None else _positive("stroke_m", stroke_m)
    if stroke_m >= height_m:
        raise TwinFocusError(f"stroke_m ({stroke_m}) must be smaller than height_m ({height_m})")
    if height_m / pixel_m < 8:
        raise TwinFocusError(f"pixel_m ({pixel_m}) is too coarse for a {height_m} m letter (need >= 8 pixels)")
    if height_m / pixel_m > 4000:
        raise TwinFocusError(f"pixel_m ({pixel_m}) is too fine for a {height_m} m letter (at most 4000 pixels)")
    face = _font(font)
    # Render the glyph at least 1.5x finer than the output raster (so that mapping its centre
    # line onto the output leaves no gaps) and thin it to a one-pixel centre line: OpenCV 4 draws
    # Hershey glyphs as 1-pixel strokes, OpenCV 5 as filled outlines whose weight grows with the
    # scale; thinning gives the same centre line from either.
    (_, th1), _ = cv2.getTextSize(char, face, 1.0, 1)
    scale = max(1.0, 1.5 * (height_m / pixel_m) / max(th1, 1))
    (tw, th), base = cv2.getTextSize(char, face, scale, 1)
    pad = 8
    canvas = np.zeros((th + base + 2 * pad, tw + 2 * pad), np.uint8)
    cv2.putText(canvas, char, (pad, pad + th), face, scale, 255, 1, cv2.LINE_8)
    canvas = np.where(canvas > 127, 255, 0).astype(np.uint8)
    canvas = cv2.ximgproc.thinning(canvas, thinningType=cv2.ximgproc.THINNING_ZHANGSUEN)
    ys, xs = np.nonzero(canvas)
    if ys.size == 0:
        raise TwinFocusError(f"character {char!r} renders nothing in this font")
    hs = ys.max() - ys.min()
    if hs < 3:
        raise TwinFocusError(f"character {char!r} is too flat to be scaled to a height")
    sy = (height_m - stroke_m) / hs
    sx = sy * width_scale
    v = (ys - ys.min()) * sy + stroke_m / 2
    u = (xs - xs.min()) * sx + stroke_m / 2
    rows = int(np.ceil(height_m / pixel_m)) + 2
    cols = int(np.ceil(((xs.max() - xs.min()) * sx + stroke_m) / pixel_m)) + 2
    skel = np.full((rows, cols), 255, np.uint8)
    skel[np.clip((v / pixel_m).astype(int) + 1, 0, rows - 1), np.clip((u / pixel_m).astype(int) + 1, 0, cols - 1)] = 0
    dist = cv2.distanceTransform(skel, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    mask = dist <= stroke_m / (2 * pixel_m)
    r = np.flatnonzero(mask.any(axis=1))
    c = np.flatnonzero(mask.any(axis=0))
    return mask[r[0] : r[-1] + 1, c[0] : c[-1] + 1].copy()


def letter(
    char: str,
    height_m: float = 0.127,
    centre_m=(0.0, 0.0, 0.6),
    material: str = "metal",
    font="simplex",
    stroke_m: float | None = None,
    width_scale: float = 0.65,
    rotation=None,
    pixel_m: float | None = None,
    name: str | None = None,
    colour_bgr=None,
) -> PlanarObject:
    """A flat cut-out letter (e.g. the paper's 5-inch metal letters), see :func:`letter_mask`.

    pixel_m : mask resolution (default height / 400, 0.32 mm for 127 mm).
    """
    height_m = _positive("height_m", height_m)
    pixel_m = height_m / 400.0 if pixel_m is None else _positive("pixel_m", pixel_m)
    mask = letter_mask(char, height_m, pixel_m, font, stroke_m, width_scale)
    return PlanarObject(mask, pixel_m, centre_m, rotation, material, colour_bgr, None, name or f"letter_{char}")


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
    width_m = _positive("width_m", width_m)
    height_m = _positive("height_m", height_m)
    pixel_m = _positive("pixel_m", pixel_m)
    shape = (max(1, round(height_m / pixel_m)), max(1, round(width_m / pixel_m)))
    return PlanarObject(np.ones(shape, dtype=bool), pixel_m, centre_m, rotation, material, colour_bgr, None, name)


def card(centre_m=(0.0, 0.0, 0.6), material: str = "metal", width_m: float = 0.0856, height_m: float = 0.05398, **kwargs) -> PlanarObject:
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
    radius_m = _positive("radius_m", radius_m)
    pixel_m = _positive("pixel_m", pixel_m)
    n = max(1, int(np.ceil(2 * radius_m / pixel_m)))
    c = (np.arange(n) + 0.5 - n / 2) * pixel_m
    mask = (c[None, :] ** 2 + c[:, None] ** 2) <= radius_m**2
    return PlanarObject(mask, pixel_m, centre_m, rotation, material, colour_bgr, None, name)


def _object_u(obj: PlanarObject) -> np.ndarray:
    """u coordinate (metres) of every mask column's centre, float64 (w,)."""
    w = obj.mask.shape[1]
    return (np.arange(w) + 0.5 - w / 2) * obj.pixel_m


def cylinder_section(obj: PlanarObject, radius_m: float) -> PlanarObject:
    """``obj`` wrapped onto a cylinder of radius ``radius_m`` whose axis runs along v (the mask's
    rows), convex towards the radar: the centre column stays at w = 0 and a column at u recedes by
    R - sqrt(R^2 - u^2). The mask is kept as the object's projection on its plane. Returns a new
    :class:`PlanarObject` with ``depth_m`` set (same name, material, roughness)."""
    r = _positive("radius_m", radius_m)
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


# --- occluders and clutter --------------------------------------------------------------------


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
        self.centre_m = _vec3(f"occluder {self.name!r}: centre_m", self.centre_m)
        s = np.asarray(self.size_m, dtype=np.float64)
        if s.shape != (2,) or not np.isfinite(s).all() or np.any(s <= 0):
            raise TwinFocusError(f"occluder {self.name!r}: size_m must be 2 positive numbers (width, height), got {self.size_m!r}")
        self.size_m = s
        self.rotation = _rotation(f"occluder {self.name!r}: rotation", self.rotation)
        mat = material(self.material)
        if self.attenuation_db is not None:
            a = float(self.attenuation_db)
            if np.isnan(a) or a < 0:
                raise TwinFocusError(f"occluder {self.name!r}: attenuation_db must be >= 0, got {self.attenuation_db!r}")
            self.attenuation_db = a
        self.colour_bgr = _colour(self.colour_bgr, mat.colour_bgr)

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
        return self.centre_m + uv @ _filled(self.rotation)[:, :2].T

    def crosses(self, origin_m, points_m: np.ndarray) -> np.ndarray:
        """Whether the segment from ``origin_m`` (3,) to each point (P, 3) passes through the sheet.

        Returns bool (P,). Points on the sheet itself or on the origin's side are not crossed.
        """
        o = _vec3("origin_m", origin_m)
        p = np.asarray(points_m, dtype=np.float64)
        rot = _filled(self.rotation)
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
        self.volume_min_m = _vec3("clutter volume_min_m", self.volume_min_m)
        self.volume_max_m = _vec3("clutter volume_max_m", self.volume_max_m)
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
        d = _positive("distance_m", distance_m)
        return cls(np.array([-0.4, -0.3, d + 0.05]), np.array([0.4, 0.3, d + 0.6]), n_points=n_points, n_strong=n_strong)

    def scatterers(self, rng: np.random.Generator | int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(points_m float64 (P, 3), amplitudes complex128 (P,)), P = n_points + n_strong."""
        gen = np.random.default_rng(rng)
        n = int(self.n_points) + int(self.n_strong)
        pts = self.volume_min_m + gen.random((n, 3)) * (self.volume_max_m - self.volume_min_m)
        amp = np.full(n, float(self.amplitude), dtype=np.complex128)
        amp[int(self.n_points) :] = float(self.strong_amplitude)
        return pts, amp * _random_phase(gen, n)


# --- scene ------------------------------------------------------------------------------------


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
        origin = _vec3("aperture_centre_m", aperture_centre_m)
        for occ in self.occluders:
            hit = occ.crosses(origin, points)
            amplitudes[hit] *= occ.amplitude_factor
        keep = amplitudes != 0
        if not keep.any():
            raise TwinFocusError("every scatterer of the scene is hidden behind an opaque occluder")
        points, amplitudes, label = points[keep], amplitudes[keep], label[keep]
        return (points, amplitudes, label) if return_labels else (points, amplitudes)


def paper_scene(
    reference: str = "A",
    target: str = "F",
    distance_m: float = 0.6,
    separation_deg: float = 10.0,
    height_m: float = 0.127,
    reference_distance_m: float | None = None,
    reference_material: str = "metal",
    target_material: str = "metal",
    occluder: str | Occluder | None = None,
    occluder_distance_m: float | None = None,
    clutter: bool | Clutter = False,
    font="simplex",
    stroke_m: float | None = None,
    width_scale: float = 0.65,
) -> Scene:
    """The paper's two-letter scene: a reference letter on the -x side, the target on +x.

    Both letters face the radar, centred at y = 0 on the planes z = ``reference_distance_m``
    (default ``distance_m``) and z = ``distance_m``; seen from the aperture centre (the origin)
    their centres lie at -separation/2 and +separation/2 from boresight, so they are
    ``separation_deg`` apart. For the defaults (A and F, 127 mm, 0.6 m, 10 degrees) the reference
    lies inside x [-0.15, 0], the target inside x [0.02, 0.13], both inside y [-0.11, 0.12] (the
    regions of interest of docs/architecture.md section 2).

    occluder : None, a material name (a sheet of it is put ``occluder_distance_m`` from the
        aperture, default 10 cm in front of the target, covering the target with a 2 cm margin
        as seen from the aperture centre) or an :class:`Occluder`.
    clutter : False, True (:meth:`Clutter.room`) or a :class:`Clutter`.

    Objects are named ``"reference"`` and ``"target"``.
    """
    distance_m = _positive("distance_m", distance_m)
    ref_z = distance_m if reference_distance_m is None else _positive("reference_distance_m", reference_distance_m)
    sep = float(separation_deg)
    if not (np.isfinite(sep) and 0 <= sep < 170):
        raise TwinFocusError(f"separation_deg must lie in [0, 170), got {separation_deg!r}")
    half = np.deg2rad(sep / 2.0)
    ref = letter(reference, height_m, (-ref_z * np.tan(half), 0.0, ref_z), reference_material, font, stroke_m, width_scale, name="reference")
    tgt = letter(target, height_m, (distance_m * np.tan(half), 0.0, distance_m), target_material, font, stroke_m, width_scale, name="target")
    occluders = []
    if isinstance(occluder, Occluder):
        occluders.append(occluder)
    elif occluder is not None:
        z_occ = distance_m - 0.1 if occluder_distance_m is None else _positive("occluder_distance_m", occluder_distance_m)
        if not z_occ < distance_m:
            raise TwinFocusError(f"occluder_distance_m ({z_occ}) must be less than the target's distance ({distance_m})")
        corners = tgt.corners_m()
        scaled = corners * (z_occ / corners[:, 2:3])  # project the target's outline onto the sheet's plane
        lo, hi = scaled[:, :2].min(axis=0), scaled[:, :2].max(axis=0)
        margin = 0.02
        centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, z_occ])
        occluders.append(Occluder(centre, (hi[0] - lo[0] + 2 * margin, hi[1] - lo[1] + 2 * margin), material=occluder))
    room: Clutter | None
    if clutter is True:
        room = Clutter.room(max(distance_m, ref_z))
    elif clutter is False or clutter is None:
        room = None
    elif isinstance(clutter, Clutter):
        room = clutter
    else:
        raise TwinFocusError(f"clutter must be True, False or a Clutter, got {clutter!r}")
    return Scene([ref, tgt], occluders, room)
