"""Synthetic stereo views of a simulated scene, with the truth every later stage is tested against.

The renderer ray-casts planar surfaces (the scene's objects and occluders, background clutter
patches and a wall) from both cameras of a :class:`~twinfocus.twins.digital_twin.camera.StereoCamera`.
Each surface carries a texture fixed to its own plane, so both eyes see the same surface detail
and stereo matching has something to match (a real camera sees brushing, print or grain on
objects; a flat-shaded plate would leave the matcher nothing but its edges).

Colour pictures are ray-cast at ``supersample`` times the resolution and box-filtered down (edges
anti-aliased like a real sensor's pixel footprint), then get Gaussian sensor noise. The truth
(depth along the left camera's optical axis and the label of the visible surface) is ray-cast at
the native resolution through the pixel centres.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.io.arrays import save_npz_atomic
from twinfocus.io.images import write_image_atomic
from twinfocus.twins.digital_twin.camera import Intrinsics, StereoCamera

BACKGROUND_LABEL = -1

# Texel size of the procedural textures on objects and of the background clutter.
_OBJECT_TEXEL_M = 0.5e-3
_BACKGROUND_TEXEL_M = 2e-3


@dataclass
class Surface:
    """A planar, textured surface for the ray caster.

    Attributes
    ----------
    name : label name (objects, occluders) or "" for background clutter.
    centre_m : float64 (3,) scene point at the middle of the rasters.
    axes : float64 (3, 3) columns: the plane's u axis (raster columns grow along it), v axis
        (raster rows) and normal, in the scene frame.
    coverage : float32 (Hc, Wc) in [0, 1] or None for an unbounded plane; ``coverage_px_m`` its
        pixel size (metres).
    albedo : float32 (Ha, Wa, 3) BGR colour 0..255 on the plane; ``albedo_px_m`` its texel size.
        Both rasters are centred on ``centre_m``; albedo outside its raster repeats (wraps).
    """

    name: str
    centre_m: np.ndarray
    axes: np.ndarray
    coverage: np.ndarray | None
    coverage_px_m: float
    albedo: np.ndarray
    albedo_px_m: float
    shade: float = 1.0


@dataclass
class StereoRendering:
    """A rendered stereo pair and its truth.

    left, right : uint8 (H, W, 3) BGR pictures (an ideal rectified pair if the camera is one).
    depth_left : float32 (H, W) metres along the left optical axis of the visible surface.
    labels_left : int16 (H, W) index into ``label_names`` of the visible surface, -1 for
        background and clutter.
    """

    left: np.ndarray
    right: np.ndarray
    depth_left: np.ndarray
    labels_left: np.ndarray
    label_names: list[str]
    camera: StereoCamera

    def mask(self, name: str) -> np.ndarray:
        """Truth mask (bool (H, W)) of the visible part of the surface called ``name``."""
        if name not in self.label_names:
            raise TwinFocusError(f"no rendered surface called {name!r}; have {', '.join(self.label_names)}")
        return self.labels_left == self.label_names.index(name)

    def save(self, out_dir: str | os.PathLike) -> dict[str, Path]:
        """Write left.png, right.png, camera.json and truth.npz (depth, labels, names) to a folder."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        paths = {
            "left": write_image_atomic(out / "left.png", self.left),
            "right": write_image_atomic(out / "right.png", self.right),
            "camera": self.camera.save(out / "camera.json"),
            "truth": save_npz_atomic(
                out / "truth.npz",
                {
                    "depth_left": self.depth_left.astype(np.float32),
                    "labels_left": self.labels_left.astype(np.int16),
                    "label_names": np.array(self.label_names, dtype=str),
                },
            ),
        }
        return paths


# --- textures ----------------------------------------------------------------------------------


def procedural_texture(
    shape: tuple[int, int], rng: np.random.Generator, contrast: float = 0.25, streak: float = 0.0
) -> np.ndarray:
    """Multiplicative surface texture, float32 (H, W) around 1: band-limited noise at three
    scales (grain, mottling, slow shading), optionally stretched along rows (brushed metal)."""
    import cv2

    h, w = int(shape[0]), int(shape[1])
    tex = np.zeros((h, w), np.float32)
    for sigma, weight in ((1.0, 0.5), (4.0, 0.35), (16.0, 0.15)):
        n = rng.standard_normal((h, w)).astype(np.float32)
        sx = sigma * (1.0 + 6.0 * streak)
        n = cv2.GaussianBlur(n, (0, 0), sigmaX=sx, sigmaY=sigma, borderType=cv2.BORDER_REFLECT)
        n /= max(float(n.std()), 1e-6)
        tex += weight * n
    tex /= max(float(tex.std()), 1e-6)
    return np.clip(1.0 + contrast * tex, 0.2, 2.0).astype(np.float32)


def clutter_texture(shape: tuple[int, int], rng: np.random.Generator, n_shapes: int = 400) -> np.ndarray:
    """A busy background (BGR float32 (H, W, 3)): random rectangles, discs and lines in random
    colours over grainy noise, like shelves and posters behind the scene."""
    import cv2

    h, w = int(shape[0]), int(shape[1])
    base = rng.uniform(60, 180, size=3)
    img = np.empty((h, w, 3), np.float32)
    img[:] = base
    canvas = img.copy()
    for _ in range(int(n_shapes)):
        colour = tuple(float(c) for c in rng.uniform(10, 245, size=3))
        kind = rng.integers(0, 3)
        cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
        size = int(rng.integers(max(2, min(h, w) // 60), max(3, min(h, w) // 8)))
        if kind == 0:
            cv2.rectangle(canvas, (cx, cy), (cx + size, cy + int(size * rng.uniform(0.3, 2.0))), colour, -1)
        elif kind == 1:
            cv2.circle(canvas, (cx, cy), size // 2, colour, -1)
        else:
            end = (cx + int(rng.integers(-size, size)), cy + int(rng.integers(-size, size)))
            cv2.line(canvas, (cx, cy), end, colour, int(rng.integers(1, 4)))
    grain = procedural_texture((h, w), rng, contrast=0.12)
    return (canvas * grain[..., None]).astype(np.float32)


# --- surfaces from the scene --------------------------------------------------------------------


def _plane_axes(rotation: np.ndarray) -> np.ndarray:
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3):
        raise TwinFocusError(f"object rotation must be 3 x 3, got {r.shape}")
    return r


def object_surface(obj, rng: np.random.Generator, name: str | None = None) -> Surface:
    """Surface of a planar scene object (``twinfocus.scene.PlanarObject`` or an ``Occluder``).

    Uses the object's ``mask`` raster (rows along its plane's v axis, columns along u, centred on
    ``centre_m``, ``pixel_m`` per cell), ``rotation`` (columns u, v, normal in the scene frame),
    ``colour_bgr`` and optional ``texture`` (uint8 BGR picture on the mask's raster). Without a
    picture the colour gets a procedural texture (brushed for metal).
    """
    import cv2

    mask = np.asarray(obj.mask, dtype=np.float32)
    pixel = float(obj.pixel_m)
    colour = np.asarray(getattr(obj, "colour_bgr", (160, 160, 160)), dtype=np.float32)
    extent = np.array(mask.shape, dtype=np.float64) * pixel
    # The albedo raster at a fixed fine texel size (the mask raster may be coarse).
    rows, cols = (int(max(8, np.ceil(e / _OBJECT_TEXEL_M))) for e in extent)
    tex_shape = (rows, cols)
    material = str(getattr(obj, "material", "")).lower()
    streak = 1.0 if "metal" in material else 0.0
    tex = procedural_texture(tex_shape, rng, contrast=0.22, streak=streak)
    given = getattr(obj, "texture", None)
    if given is not None:
        # A picture of the surface (uint8 BGR on the mask's raster): it is the colour; the fine
        # grain on top keeps stereo matchable where the picture is flat.
        pic = cv2.resize(
            np.asarray(given, dtype=np.float32), (tex_shape[1], tex_shape[0]), interpolation=cv2.INTER_LINEAR
        )
        grain = procedural_texture(tex_shape, rng, contrast=0.08)
        albedo = pic * grain[..., None]
    else:
        albedo = colour[None, None, :] * tex[..., None]
    return Surface(
        name=name if name is not None else str(getattr(obj, "name", "")),
        centre_m=np.asarray(obj.centre_m, dtype=np.float64).reshape(3),
        axes=_plane_axes(obj.rotation),
        coverage=mask,
        coverage_px_m=pixel,
        albedo=albedo.astype(np.float32),
        albedo_px_m=float(extent[0] / tex_shape[0]),
    )


def background_surfaces(
    rng: np.random.Generator,
    wall_z_m: float = 1.5,
    n_patches: int = 12,
    patch_depth_m: tuple[float, float] = (0.85, 1.3),
    width_m: float = 4.0,
    height_m: float = 2.6,
) -> list[Surface]:
    """A cluttered wall at ``wall_z_m`` plus ``n_patches`` boxes/posters at random depths."""
    wall_px = (int(height_m / _BACKGROUND_TEXEL_M), int(width_m / _BACKGROUND_TEXEL_M))
    out = [
        Surface(
            "",
            np.array([0.0, 0.0, wall_z_m]),
            np.eye(3),
            None,
            1.0,
            clutter_texture(wall_px, rng, n_shapes=900),
            _BACKGROUND_TEXEL_M,
            shade=0.85,
        )
    ]
    for _ in range(int(n_patches)):
        z = rng.uniform(*patch_depth_m)
        half = np.tan(np.deg2rad(40)) * z
        centre = np.array([rng.uniform(-half, half), rng.uniform(-0.6 * half, 0.6 * half), z])
        size = rng.uniform(0.08, 0.3, size=2)
        shape = (int(size[1] / _BACKGROUND_TEXEL_M), int(size[0] / _BACKGROUND_TEXEL_M))
        angle = rng.uniform(-0.5, 0.5)
        rot = np.array([[np.cos(angle), 0.0, np.sin(angle)], [0.0, 1.0, 0.0], [-np.sin(angle), 0.0, np.cos(angle)]])
        out.append(
            Surface(
                "",
                centre,
                rot,
                np.ones(shape, np.float32),
                _BACKGROUND_TEXEL_M,
                clutter_texture(shape, rng, n_shapes=40),
                _BACKGROUND_TEXEL_M,
                shade=rng.uniform(0.8, 1.1),
            )
        )
    return out


def scene_surfaces(scene, rng: np.random.Generator, clutter: bool = True) -> list[Surface]:
    """Surfaces of a ``twinfocus.scene.Scene``: its objects and occluders (labelled by name) and,
    with ``clutter``, a busy background."""
    objects = list(getattr(scene, "objects", []))
    occluders = list(getattr(scene, "occluders", []))
    out = (
        background_surfaces(rng)
        if clutter
        else [Surface("", np.array([0.0, 0.0, 1.5]), np.eye(3), None, 1.0, np.full((4, 4, 3), 128.0, np.float32), 1.0)]
    )
    for i, obj in enumerate(objects):
        out.append(object_surface(obj, rng, name=str(getattr(obj, "name", "") or f"object{i}")))
    for i, occ in enumerate(occluders):
        out.append(object_surface(occ, rng, name=str(getattr(occ, "name", "") or f"occluder{i}")))
    return out


# --- ray casting ----------------------------------------------------------------------------------


def _plane_to_image(
    s: Surface, raster_shape: tuple[int, int], px_m: float, intrinsics: Intrinsics, scene_from_camera: np.ndarray
) -> np.ndarray:
    """Homography (3 x 3) from a surface raster's (column, row) to image pixels (u, v)."""
    rot = np.asarray(scene_from_camera[:3, :3])
    origin = np.asarray(scene_from_camera[:3, 3])
    h, w = raster_shape
    u_ax, v_ax = s.axes[:, 0] * px_m, s.axes[:, 1] * px_m
    corner = s.centre_m - origin - (w - 1) / 2.0 * u_ax - (h - 1) / 2.0 * v_ax
    return intrinsics.K @ rot.T @ np.stack([u_ax, v_ax, corner], axis=1)


def _image_box(s: Surface, intrinsics: Intrinsics, scene_from_camera: np.ndarray) -> tuple[int, int, int, int] | None:
    """Pixel rows/columns [r0, r1) x [c0, c1) a bounded surface can cover; the whole image for an
    unbounded one or one that reaches behind the camera; None if it is out of view."""
    h, w = intrinsics.shape
    if s.coverage is None:
        return (0, h, 0, w)
    hc, wc = s.coverage.shape
    half = np.array([wc, hc], dtype=np.float64) * s.coverage_px_m / 2.0
    corners = [
        s.centre_m + sa * half[0] * s.axes[:, 0] + sb * half[1] * s.axes[:, 1] for sa in (-1, 1) for sb in (-1, 1)
    ]
    rot = np.asarray(scene_from_camera[:3, :3])
    cam = (np.array(corners) - scene_from_camera[:3, 3]) @ rot
    if np.any(cam[:, 2] <= 1e-6):
        return (0, h, 0, w)
    uv = intrinsics.project(cam)
    c0, c1 = int(np.floor(uv[:, 0].min())) - 1, int(np.ceil(uv[:, 0].max())) + 2
    r0, r1 = int(np.floor(uv[:, 1].min())) - 1, int(np.ceil(uv[:, 1].max())) + 2
    c0, c1, r0, r1 = max(c0, 0), min(c1, w), max(r0, 0), min(r1, h)
    if c0 >= c1 or r0 >= r1:
        return None
    return (r0, r1, c0, c1)


def raycast(
    surfaces: Sequence[Surface], intrinsics: Intrinsics, scene_from_camera: np.ndarray, colour: bool = True
) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """Cast one ray per pixel centre through planar surfaces (nearest hit wins).

    A plane maps to the image by a homography, and the inverse depth of its points is an affine
    function of (u, v): each surface costs one ``cv2.warpPerspective`` per raster and a few
    array operations, not a ray-plane intersection per pixel.

    Returns (bgr float32 (H, W, 3) or None, depth float32 (H, W) metres along the optical axis
    (inf where nothing is hit), surface index int16 (H, W), -1 where nothing is hit).
    """
    import cv2

    rot = np.asarray(scene_from_camera[:3, :3], dtype=np.float64)
    origin = np.asarray(scene_from_camera[:3, 3], dtype=np.float64)
    h, w = intrinsics.shape
    u = np.arange(w, dtype=np.float32)[None, :]
    v = np.arange(h, dtype=np.float32)[:, None]
    k_inv = np.linalg.inv(intrinsics.K)
    depth = np.full((h, w), np.inf, np.float32)
    index = np.full((h, w), -1, np.int16)
    bgr = np.zeros((h, w, 3), np.float32) if colour else None
    for s_idx, s in enumerate(surfaces):
        n = s.axes[:, 2]
        dist = float(n @ (s.centre_m - origin))
        if abs(dist) < 1e-9:
            continue  # the camera lies in the plane: it sees the plane edge-on
        box = _image_box(s, intrinsics, scene_from_camera)
        if box is None:
            continue
        r0, r1, c0, c1 = box
        shift = np.array([[1.0, 0.0, -c0], [0.0, 1.0, -r0], [0.0, 0.0, 1.0]])
        # 1 / t = n . (R K^-1 [u, v, 1]) / dist, with t the depth along the optical axis.
        g = (n @ rot @ k_inv) / dist
        inv_t = np.float32(g[0]) * u[:, c0:c1] + np.float32(g[1]) * v[r0:r1] + np.float32(g[2])
        with np.errstate(divide="ignore"):
            t = np.where(inv_t > 0, 1.0 / inv_t, np.inf).astype(np.float32)
        d_view = depth[r0:r1, c0:c1]
        valid = t < d_view
        if s.coverage is not None:
            hmat = shift @ _plane_to_image(s, s.coverage.shape, s.coverage_px_m, intrinsics, scene_from_camera)
            cov = cv2.warpPerspective(
                s.coverage,
                hmat,
                (c1 - c0, r1 - r0),
                flags=cv2.INTER_NEAREST,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=0,
            )
            valid &= cov >= 0.5
        if not valid.any():
            continue
        np.copyto(d_view, t, where=valid)
        index[r0:r1, c0:c1][valid] = s_idx
        if bgr is not None:  # colour
            hmat = shift @ _plane_to_image(s, s.albedo.shape[:2], s.albedo_px_m, intrinsics, scene_from_camera)
            alb = cv2.warpPerspective(
                s.albedo, hmat, (c1 - c0, r1 - r0), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
            )
            if s.shade != 1.0:
                alb *= np.float32(s.shade)
            np.copyto(bgr[r0:r1, c0:c1], alb, where=valid[..., None])
    return bgr, depth, index


def render_view(
    surfaces: Sequence[Surface],
    intrinsics: Intrinsics,
    scene_from_camera: np.ndarray,
    supersample: int,
    noise_dn: float,
    rng: np.random.Generator,
    blur_px: float = 0.5,
) -> np.ndarray:
    """One eye's uint8 BGR picture: supersampled ray cast, box filter, optics blur, sensor noise."""
    import cv2

    hi = intrinsics.scaled(supersample) if supersample > 1 else intrinsics
    bgr, _, _ = raycast(surfaces, hi, scene_from_camera, colour=True)
    assert bgr is not None  # colour=True always paints it
    if supersample > 1:
        bgr = cv2.resize(bgr, intrinsics.size, interpolation=cv2.INTER_AREA)
    if blur_px > 0:
        bgr = cv2.GaussianBlur(bgr, (0, 0), blur_px)
    if noise_dn > 0:
        bgr = bgr + rng.normal(0.0, noise_dn, size=bgr.shape).astype(np.float32)
    return np.clip(np.rint(bgr), 0, 255).astype(np.uint8)


def render_surfaces(
    surfaces: Sequence[Surface], camera: StereoCamera, *, supersample: int = 2, noise_dn: float = 2.0, seed: int = 0
) -> StereoRendering:
    """Render both eyes of ``camera`` and the left eye's truth depth and labels."""
    if not surfaces:
        raise TwinFocusError("nothing to render: the scene has no surfaces")
    rng = np.random.default_rng(seed)
    left = render_view(surfaces, camera.left, camera.scene_from_left, supersample, noise_dn, rng)
    right = render_view(surfaces, camera.right, camera.scene_from_right, supersample, noise_dn, rng)
    _, depth, index = raycast(surfaces, camera.left, camera.scene_from_left, colour=False)
    names: list[str] = []
    labels = np.full(index.shape, BACKGROUND_LABEL, np.int16)
    for s_idx, s in enumerate(surfaces):
        if not s.name:
            continue
        if s.name not in names:
            names.append(s.name)
        labels[index == s_idx] = names.index(s.name)
    return StereoRendering(left, right, depth.astype(np.float32), labels, names, camera)


def render_scene(
    scene,
    camera: StereoCamera | None = None,
    *,
    clutter: bool = True,
    supersample: int = 2,
    noise_dn: float = 2.0,
    seed: int = 0,
) -> StereoRendering:
    """Render a ``twinfocus.scene.Scene`` (objects, occluders) seen by ``camera`` (default: the
    ZED 2i-like rig of :meth:`StereoCamera.zed2i`) on a cluttered background."""
    camera = camera or StereoCamera.zed2i()
    rng = np.random.default_rng(seed)
    surfaces = scene_surfaces(scene, rng, clutter=clutter)
    return render_surfaces(surfaces, camera, supersample=supersample, noise_dn=noise_dn, seed=seed + 1)


#: peak bytes per texel of an object's texture while it is made (noise, blurs, colour channels)
BYTES_PER_TEXEL = 48
#: peak bytes per supersampled picture pixel of one view (colour, depth, hit buffers)
BYTES_PER_RENDER_PIXEL = 64


def render_memory_bytes(scene, width: int, height: int, supersample: int = 2) -> int:
    """Peak memory of :func:`render_scene` for ``scene`` and a ``width`` x ``height`` picture,
    bytes, estimated from sizes alone (nothing is made), so a command can refuse a rendering that
    cannot fit before it allocates: every planar object's texture at the fixed texel size, and
    the supersampled picture."""
    texels = 0
    for obj in scene.objects:
        if getattr(obj, "mask", None) is None:
            continue
        extent = np.array(np.shape(obj.mask), dtype=np.float64) * float(obj.pixel_m)
        rows, cols = (max(8.0, np.ceil(e / _OBJECT_TEXEL_M)) for e in extent)
        texels += int(rows * cols)
    pixels = int(width) * int(height) * int(supersample) ** 2
    return texels * BYTES_PER_TEXEL + pixels * BYTES_PER_RENDER_PIXEL
