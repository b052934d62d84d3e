"""Reference segmentation: which pixels of the left picture belong to the reference object.

The source paper prompts Segment Anything 2; its weights are not needed here. The default
(:class:`ClassicalSegmenter`) works from the stereo depth and the colour picture:

1. **Seed.** A click point, a pixel box, or "nearest" (the closest sizeable surface). A box is
   the natural prompt when the reference's region of interest in the radar scene is known: it is
   projected into the picture (:func:`box_from_scene_roi`).
2. **Grow on depth.** Flood fill from the seed over pixels whose depth changes by less than a
   step between neighbours (a surface, possibly tilted, without depth jumps), within a band
   around the seed depth. Depth alone already separates an object from a background 0.5 m behind.
3. **Photo-consistency.** Block matching fattens foreground edges (pixels of the background
   next to an object inherit its disparity) and a colour model cannot fix that when object and
   background look alike. So each pixel near the grown region is tested against two hypotheses:
   "on the object" (the right picture, sampled at the object's own disparity -- a plane fitted to
   the region's disparities, or the region's disparities extended outwards if it is not flat --
   matches the left one) and "elsewhere" (the best match at any disparity away from the
   object's). A clear win either way becomes a hard label.
4. **GrabCut** on a window around the region, from those labels (or, without the right picture,
   from the grown region and "far behind" depths): the colour model settles the undecided pixels
   and puts the boundary on the picture's edges.

Plug-in: any object with ``__call__(image_bgr, seed, depth_m) -> bool mask`` is a segmenter.
:class:`PredictorSegmenter` wraps a Segment-Anything-style predictor (``set_image`` +
``predict(point_coords, point_labels, box, multimask_output)``), and :func:`load_segmenter`
builds one from a checkpoint on disk through the ``sam2`` or ``segment_anything`` package.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.twins.digital_twin.camera import transform_points

# --- seeds -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Seed:
    """Where the reference is in the left picture.

    kind : ``"point"`` (``values`` = (u, v) pixel), ``"box"`` ((x0, y0, x1, y1) pixels) or
    ``"nearest"`` (no values: the closest sizeable surface).
    """

    kind: str
    values: tuple[float, ...] = ()

    @classmethod
    def point(cls, u: float, v: float) -> Seed:
        return cls("point", (float(u), float(v)))

    @classmethod
    def box(cls, x0: float, y0: float, x1: float, y1: float) -> Seed:
        return cls("box", (float(min(x0, x1)), float(min(y0, y1)), float(max(x0, x1)), float(max(y0, y1))))

    @classmethod
    def nearest(cls) -> Seed:
        return cls("nearest")

    def validate(self, shape: tuple[int, int]) -> None:
        h, w = shape[:2]
        if self.kind == "point":
            u, v = self.values
            if not (0 <= u < w and 0 <= v < h):
                raise TwinFocusError(f"seed point ({u:g}, {v:g}) lies outside the {w}x{h} picture")
        elif self.kind == "box":
            x0, y0, x1, y1 = self.values
            if x1 <= 0 or y1 <= 0 or x0 >= w or y0 >= h or x1 - x0 < 2 or y1 - y0 < 2:
                raise TwinFocusError(
                    f"seed box ({x0:g}, {y0:g}, {x1:g}, {y1:g}) holds no pixels of the {w}x{h} picture"
                )
        elif self.kind != "nearest":
            raise TwinFocusError(f"seed kind must be 'point', 'box' or 'nearest', got {self.kind!r}")

    def clipped_box(self, shape: tuple[int, int]) -> tuple[int, int, int, int]:
        """Integer (x0, y0, x1, y1) of a box seed, clipped to the picture."""
        h, w = shape[:2]
        x0, y0, x1, y1 = self.values
        return (
            max(0, int(np.floor(x0))),
            max(0, int(np.floor(y0))),
            min(w, int(np.ceil(x1))),
            min(h, int(np.ceil(y1))),
        )


def box_from_scene_roi(roi, camera, depth_margin_m: float = 0.0, margin_px: int = 10) -> Seed:
    """Project a radar region of interest (X0, X1, Y0, Y1, Z) into the left picture: a box seed.

    The rectangle's corners at depth Z (and Z +- ``depth_margin_m``) are projected with the
    camera's pose; the box bounds them, widened by ``margin_px``.
    """
    x0, x1, y0, y1, z = (float(v) for v in roi)
    corners = np.array(
        [[x, y, z + dz] for x in (x0, x1) for y in (y0, y1) for dz in (-depth_margin_m, 0.0, depth_margin_m)]
    )
    cam = transform_points(np.linalg.inv(camera.scene_from_left), corners)
    if np.any(cam[:, 2] <= 0):
        raise TwinFocusError("the reference region of interest lies behind the camera")
    uv = camera.left.project(cam)
    return Seed.box(
        uv[:, 0].min() - margin_px, uv[:, 1].min() - margin_px, uv[:, 0].max() + margin_px, uv[:, 1].max() + margin_px
    )


# --- the plug-in interface ----------------------------------------------------------------------------


class Segmenter(Protocol):
    """Anything that turns (picture, seed, depth) into the reference's mask."""

    def __call__(self, image_bgr: np.ndarray, seed: Seed, depth_m: np.ndarray | None = None) -> np.ndarray: ...


# --- classical default --------------------------------------------------------------------------------


@dataclass(frozen=True)
class ClassicalConfig:
    """Settings of :class:`ClassicalSegmenter` (lengths in metres, sizes in pixels).

    step_m : largest depth change between neighbouring pixels of one surface (grows with
        depth^2 like the stereo depth step; the value is at 1 m).
    band_m : largest depth difference from the seed depth inside the object.
    ring_px : width of the undecided band GrabCut may move the boundary in.
    photo_ring_px : how far from the grown region the photo-consistency test looks.
    photo_window : side of the window the matching cost is averaged over (pixels).
    photo_margin_dn : cost difference (8-bit grey levels) that makes a hypothesis a sure win.
    """

    step_m: float = 0.012
    band_m: float = 0.08
    ring_px: int = 6
    grabcut_iterations: int = 4
    refine: str = "grabcut"  # or "none"
    min_area_px: int = 60
    max_area_fraction: float = 0.35
    nearest_bin_m: float = 0.02
    photo_ring_px: int = 8
    photo_window: int = 3
    photo_margin_dn: float = 10.0


class ClassicalSegmenter:
    """Seeded depth region growing refined by GrabCut (see the module docstring)."""

    def __init__(self, config: ClassicalConfig | None = None):
        self.config = config or ClassicalConfig()
        if self.config.refine not in ("grabcut", "none"):
            raise TwinFocusError(f"segmentation refine must be 'grabcut' or 'none', got {self.config.refine!r}")

    def __call__(
        self,
        image_bgr: np.ndarray,
        seed: Seed,
        depth_m: np.ndarray | None = None,
        *,
        right_bgr: np.ndarray | None = None,
        disparity_px: np.ndarray | None = None,
    ) -> np.ndarray:
        """Bool (H, W) mask of the reference.

        image_bgr : (rectified) left picture; depth_m : float (H, W) its depth, NaN where unknown.
        right_bgr, disparity_px : the rectified right picture and the disparity map (pixels); with
        both, boundaries are decided by photo-consistency (module docstring, step 3).
        """
        image_bgr = np.asarray(image_bgr)
        if depth_m is None:
            raise TwinFocusError("the classical segmenter needs the stereo depth map")
        depth = np.asarray(depth_m, dtype=np.float32)
        if depth.shape != image_bgr.shape[:2]:
            raise TwinFocusError(f"depth map is {depth.shape} but the picture is {image_bgr.shape[:2]}")
        seed.validate(depth.shape)
        region, z0 = self.grow(depth, seed)
        if self.config.refine == "grabcut":
            hints = None
            if right_bgr is not None and disparity_px is not None:
                hints = self.photo_hints(image_bgr, np.asarray(right_bgr), np.asarray(disparity_px, np.float32), region)
            region = self.refine(image_bgr, depth, region, z0, hints)
        return region

    # -- stage 2: depth region growing
    def grow(self, depth: np.ndarray, seed: Seed) -> tuple[np.ndarray, float]:
        """Bool mask of the surface at the seed and its median depth (metres)."""
        cfg = self.config
        h, w = depth.shape
        valid = np.isfinite(depth) & (depth > 0)
        if not valid.any():
            raise TwinFocusError("no object at the seed: the depth map holds no valid pixel")
        starts, z0 = self._starts(depth, valid, seed)
        step = np.float32(cfg.step_m * max(z0, 0.1) ** 2)
        band = cfg.band_m
        # Invalid pixels get a depth no surface has, so the fill cannot cross them.
        img = np.where(valid & (np.abs(depth - z0) <= band), depth, np.float32(-1e3)).astype(np.float32)
        region = np.zeros((h, w), bool)
        import cv2

        for v, u in starts:
            if region[v, u] or img[v, u] < 0:
                continue
            ff = np.zeros((h + 2, w + 2), np.uint8)
            cv2.floodFill(
                img,
                ff,
                (int(u), int(v)),
                0,
                loDiff=float(step),
                upDiff=float(step),
                flags=4 | cv2.FLOODFILL_MASK_ONLY | (1 << 8),
            )
            region |= ff[1:-1, 1:-1] > 0
        area = int(region.sum())
        if area < cfg.min_area_px:
            raise TwinFocusError(f"no object at the seed: the surface found there has only {area} pixels")
        if area > cfg.max_area_fraction * h * w:
            raise TwinFocusError(
                f"no object at the seed: the surface there covers {100.0 * area / (h * w):.0f} % of the picture "
                "(a wall or table, not an object); give a point or box on the reference"
            )
        return region, float(np.median(depth[region]))

    def _starts(self, depth: np.ndarray, valid: np.ndarray, seed: Seed) -> tuple[list[tuple[int, int]], float]:
        """Fill start pixels (row, col) and the seed depth."""
        import cv2

        cfg = self.config
        h, w = depth.shape
        if seed.kind == "point":
            u, v = (int(round(x)) for x in seed.values)
            u, v = min(max(u, 0), w - 1), min(max(v, 0), h - 1)
            win = depth[max(0, v - 3) : v + 4, max(0, u - 3) : u + 4]
            wv = win[np.isfinite(win) & (win > 0)]
            if wv.size == 0:
                raise TwinFocusError(f"no object at the seed ({u}, {v}): the stereo depth has no value there")
            z0 = float(np.median(wv))
            rows, cols = np.nonzero(np.isfinite(win) & (np.abs(win - z0) < cfg.step_m * z0 * z0 + 1e-4))
            return [(int(r + max(0, v - 3)), int(c + max(0, u - 3))) for r, c in zip(rows, cols)][:5], z0
        if seed.kind == "box":
            x0, y0, x1, y1 = seed.clipped_box(depth.shape)
            sub = depth[y0:y1, x0:x1]
            sub_valid = valid[y0:y1, x0:x1]
            if sub_valid.sum() < cfg.min_area_px:
                raise TwinFocusError(
                    f"no object in the seed box ({x0}, {y0}, {x1}, {y1}): too few pixels with stereo depth"
                )
            z0 = self._nearest_mode(sub[sub_valid], min_count=max(cfg.min_area_px, int(0.03 * sub_valid.sum())))
            near = sub_valid & (np.abs(sub - z0) <= cfg.band_m)
            n, lab, stats, _ = cv2.connectedComponentsWithStats(near.astype(np.uint8), connectivity=4)
            starts = []
            for i in range(1, n):
                if stats[i, cv2.CC_STAT_AREA] < max(10, cfg.min_area_px // 4):
                    continue
                rr, cc = np.nonzero(lab == i)
                k = len(rr) // 2
                starts.append((int(rr[k] + y0), int(cc[k] + x0)))
            if not starts:
                raise TwinFocusError(f"no object in the seed box ({x0}, {y0}, {x1}, {y1})")
            return starts, z0
        # nearest: the closest depth with a connected surface of sizeable area
        z = depth[valid]
        lo, hi = float(z.min()), float(z.max())
        bins = np.arange(lo, hi + 2 * cfg.nearest_bin_m, cfg.nearest_bin_m)
        hist, edges = np.histogram(z, bins=bins)
        min_area = max(cfg.min_area_px * 10, int(0.002 * depth.size))
        for b in np.flatnonzero(hist >= cfg.min_area_px):
            band = valid & (depth >= edges[b]) & (depth < edges[b + 1] + cfg.nearest_bin_m)
            n, lab, stats, _ = cv2.connectedComponentsWithStats(band.astype(np.uint8), connectivity=4)
            if n < 2:
                continue
            best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
            if stats[best, cv2.CC_STAT_AREA] >= min_area:
                rr, cc = np.nonzero(lab == best)
                zz = depth[rr, cc]
                k = int(np.argmin(np.abs(zz - np.median(zz))))
                return [(int(rr[k]), int(cc[k]))], float(np.median(zz))
        raise TwinFocusError("no object found nearest to the camera: no surface of sizeable area in the depth map")

    def _nearest_mode(self, z: np.ndarray, min_count: int) -> float:
        """Median depth of the closest depth cluster holding at least ``min_count`` pixels."""
        cfg = self.config
        bins = np.arange(float(z.min()), float(z.max()) + 2 * cfg.nearest_bin_m, cfg.nearest_bin_m)
        hist, edges = np.histogram(z, bins=bins)
        # Two neighbouring bins together, so a surface on a bin edge still counts once.
        pair = hist[:-1] + hist[1:] if hist.size > 1 else hist
        idx = np.flatnonzero(pair >= min_count)
        b = int(idx[0]) if idx.size else int(np.argmax(hist))
        sel = z[(z >= edges[b]) & (z < edges[min(b + 2, edges.size - 1)])]
        return float(np.median(sel))

    # -- stage 3: photo-consistency
    def photo_hints(
        self, left_bgr: np.ndarray, right_bgr: np.ndarray, disparity: np.ndarray, region: np.ndarray
    ) -> np.ndarray | None:
        """int8 (H, W): +1 sure object, -1 sure not, 0 undecided (module docstring, step 3);
        None when the region has too few disparities to model."""
        import cv2

        cfg = self.config
        if right_bgr.shape[:2] != left_bgr.shape[:2] or disparity.shape != left_bgr.shape[:2]:
            raise TwinFocusError("right picture and disparity map must match the left picture's size")
        h, w = region.shape
        ring = cv2.dilate(region.astype(np.uint8), np.ones((2 * cfg.photo_ring_px + 1,) * 2, np.uint8)) > 0
        ys, xs = np.nonzero(ring)
        r0, r1, c0, c1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
        valid = np.isfinite(disparity) & (disparity > 0)
        v, u = np.nonzero(region & valid)
        if v.size < cfg.min_area_px:
            return None
        d_obj = self._object_disparity(u, v, disparity[v, u], region, r0, r1, c0, c1)
        gl = _grey_f32(left_bgr)[r0:r1, c0:c1]
        gr = _grey_f32(right_bgr)
        uu, vv = np.meshgrid(np.arange(c0, c1, dtype=np.float32), np.arange(r0, r1, dtype=np.float32))
        win = (int(cfg.photo_window),) * 2

        def cost(d):
            warped = cv2.remap(gr, uu - d, vv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            return cv2.blur(np.abs(gl - warped), win)

        c_obj = cost(d_obj)
        c_else = np.full_like(c_obj, np.inf)
        d_all = disparity[valid]
        for d in np.arange(np.floor(d_all.min()) - 2, np.ceil(d_all.max()) + 3, 1.0, dtype=np.float32):
            away = np.abs(d - d_obj) > 3.0
            if away.any():
                c_else = np.where(away, np.minimum(c_else, cost(d)), c_else)
        hints = np.zeros((h, w), np.int8)
        sub = np.zeros(c_obj.shape, np.int8)
        m = float(cfg.photo_margin_dn)
        sub[c_obj + m < c_else] = 1
        sub[c_else + m < c_obj] = -1
        sub[~ring[r0:r1, c0:c1]] = 0
        hints[r0:r1, c0:c1] = sub
        return hints

    def _object_disparity(self, u, v, d, region, r0, r1, c0, c1) -> np.ndarray:
        """The object's disparity over the window: a robust plane d = a u + b v + c when it fits
        (rms < 0.5 px), else the region's own disparities extended to each pixel's nearest."""
        a = np.stack([u, v, np.ones_like(u)], axis=1).astype(np.float64)
        keep = np.ones(u.size, bool)
        for _ in range(3):
            coef, *_ = np.linalg.lstsq(a[keep], d[keep], rcond=None)
            res = d - a @ coef
            s = max(1.4826 * float(np.median(np.abs(res[keep]))), 0.1)
            keep = np.abs(res) < 3.0 * s
        uu, vv = np.meshgrid(np.arange(c0, c1), np.arange(r0, r1))
        if float(np.sqrt(np.mean(res[keep] ** 2))) < 0.5:
            return (coef[0] * uu + coef[1] * vv + coef[2]).astype(np.float32)
        from scipy.ndimage import distance_transform_edt

        known = np.full((r1 - r0, c1 - c0), np.nan, np.float32)
        inside = (v >= r0) & (v < r1) & (u >= c0) & (u < c1)
        known[v[inside] - r0, u[inside] - c0] = d[inside]
        _, (iy, ix) = distance_transform_edt(~np.isfinite(known), return_indices=True)
        return known[iy, ix]

    # -- stage 4: GrabCut refinement
    def refine(
        self, image_bgr: np.ndarray, depth: np.ndarray, region: np.ndarray, z0: float, hints: np.ndarray | None = None
    ) -> np.ndarray:
        import cv2

        cfg = self.config
        h, w = region.shape
        ring = int(max(cfg.ring_px, cfg.photo_ring_px if hints is not None else 0))
        ys, xs = np.nonzero(region)
        pad = 4 * ring + 10
        r0, r1 = max(0, ys.min() - pad), min(h, ys.max() + pad + 1)
        c0, c1 = max(0, xs.min() - pad), min(w, xs.max() + pad + 1)
        reg = region[r0:r1, c0:c1].astype(np.uint8)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * ring + 1, 2 * ring + 1))
        outer = cv2.dilate(reg, kernel) > 0
        gc = np.full(reg.shape, cv2.GC_BGD, np.uint8)
        gc[outer] = cv2.GC_PR_BGD
        gc[reg > 0] = cv2.GC_PR_FGD
        if hints is None:
            core = cv2.erode(reg, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))) > 0
            gc[core] = cv2.GC_FGD
            sub_depth = depth[r0:r1, c0:c1]
            # Depth far behind the object is background whatever its colour.
            behind = np.isfinite(sub_depth) & (sub_depth > z0 + cfg.band_m)
            gc[behind & ~core] = cv2.GC_BGD
        else:
            hs = hints[r0:r1, c0:c1]
            gc[outer & (hs > 0)] = cv2.GC_FGD
            gc[outer & (hs < 0)] = cv2.GC_BGD
        if not (gc == cv2.GC_FGD).any() or not ((gc == cv2.GC_BGD) | (gc == cv2.GC_PR_BGD)).any():
            return region
        bgd = np.zeros((1, 65), np.float64)
        fgd = np.zeros((1, 65), np.float64)
        img = np.ascontiguousarray(image_bgr[r0:r1, c0:c1])
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        # GrabCut seeds its colour models with k-means on OpenCV's per-thread random generator:
        # reset, so the mask does not depend on what this thread ran before (a Dask worker's
        # thread and a serial run's main thread gave different twins of one scene).
        cv2.setRNGSeed(0)
        cv2.grabCut(img, gc, None, bgd, fgd, int(cfg.grabcut_iterations), cv2.GC_INIT_WITH_MASK)
        fg = ((gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)) & outer
        # Keep the parts connected to the depth region (drop specks GrabCut found elsewhere).
        n, lab = cv2.connectedComponents(fg.astype(np.uint8), connectivity=4)
        keep = np.unique(lab[fg & (reg > 0)])
        fg = np.isin(lab, keep[keep > 0])
        out = np.zeros((h, w), bool)
        out[r0:r1, c0:c1] = fg
        if out.sum() < cfg.min_area_px:
            return region
        return out


def _grey_f32(img: np.ndarray) -> np.ndarray:
    import cv2

    img = np.asarray(img)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return img.astype(np.float32)


# --- SAM-family plug-in -------------------------------------------------------------------------------


class PredictorSegmenter:
    """A Segment-Anything-style predictor as a segmenter.

    ``predictor`` must offer ``set_image(rgb uint8 (H, W, 3))`` and
    ``predict(point_coords=(P, 2) | None, point_labels=(P,) | None, box=(4,) | None,
    multimask_output=bool) -> (masks (K, H, W), scores (K,), logits)`` — the interface of
    ``sam2.sam2_image_predictor.SAM2ImagePredictor`` and ``segment_anything.SamPredictor``.
    The highest-scoring mask is returned. A "nearest" seed is turned into a point by the
    classical segmenter's depth analysis (SAM needs a prompt).
    """

    def __init__(self, predictor):
        for name in ("set_image", "predict"):
            if not callable(getattr(predictor, name, None)):
                raise TwinFocusError(f"segmentation model has no {name}() method: not a SAM-style predictor")
        self.predictor = predictor

    def __call__(self, image_bgr: np.ndarray, seed: Seed, depth_m: np.ndarray | None = None) -> np.ndarray:
        image_bgr = np.asarray(image_bgr)
        seed.validate(image_bgr.shape[:2])
        if seed.kind == "nearest":
            if depth_m is None:
                raise TwinFocusError("a 'nearest' seed needs the depth map to find the nearest object")
            starts, _ = ClassicalSegmenter()._starts(
                np.asarray(depth_m, np.float32), np.isfinite(depth_m) & (np.asarray(depth_m) > 0), seed
            )
            seed = Seed.point(starts[0][1], starts[0][0])
        rgb = (
            np.ascontiguousarray(image_bgr[..., ::-1])
            if image_bgr.ndim == 3
            else np.repeat(image_bgr[..., None], 3, axis=2)
        )
        self.predictor.set_image(rgb)
        kwargs: dict[str, object] = {"point_coords": None, "point_labels": None, "box": None, "multimask_output": True}
        if seed.kind == "point":
            kwargs["point_coords"] = np.array([seed.values], dtype=np.float32)
            kwargs["point_labels"] = np.array([1], dtype=np.int64)
        else:
            kwargs["box"] = np.array(seed.values, dtype=np.float32)
        masks, scores, _ = self.predictor.predict(**kwargs)
        masks = _to_numpy(masks)
        scores = _to_numpy(scores).reshape(-1)
        if masks.ndim == 2:
            masks = masks[None]
        if masks.ndim != 3 or masks.shape[1:] != image_bgr.shape[:2] or masks.shape[0] != scores.size:
            raise TwinFocusError(
                f"segmentation model returned masks {masks.shape} and scores {scores.shape} for a "
                f"{image_bgr.shape[1]}x{image_bgr.shape[0]} picture"
            )
        best = masks[int(np.argmax(scores))]
        # SAM returns booleans (or logits with return_logits): both threshold at 0 / False.
        mask = best > 0 if best.dtype != bool else best
        if not mask.any():
            raise TwinFocusError("no object at the seed: the segmentation model returned an empty mask")
        return mask


def _to_numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def load_segmenter(spec: str | None, device: str = "cpu") -> Segmenter:
    """A segmenter from a command-line spec.

    ``"classical"`` (or None): :class:`ClassicalSegmenter`.
    ``"sam2:CHECKPOINT[:CONFIG]"``: SAM 2 through the ``sam2`` package
    (``build_sam2(CONFIG, CHECKPOINT, device)``; CONFIG defaults from the checkpoint's name, e.g.
    ``sam2.1_hiera_tiny.pt`` -> ``configs/sam2.1/sam2.1_hiera_t.yaml``).
    ``"sam:CHECKPOINT[:MODEL_TYPE]"``: Segment Anything through ``segment_anything``
    (``sam_model_registry[MODEL_TYPE](checkpoint=...)``, type from the name when omitted).
    """
    if spec is None or spec == "classical":
        return ClassicalSegmenter()
    kind, _, rest = spec.partition(":")
    if kind not in ("sam2", "sam") or not rest:
        raise TwinFocusError(
            f"unknown segmenter {spec!r}; use 'classical', 'sam2:CHECKPOINT[:CONFIG]' or 'sam:CHECKPOINT[:TYPE]'"
        )
    ckpt, _, extra = rest.partition(":")
    path = Path(ckpt)
    if not path.is_file():
        raise TwinFocusError(f"{path}: segmentation checkpoint not found")
    if kind == "sam2":
        build = _import_attr(
            "sam2.build_sam", "build_sam2", "pip install 'git+https://github.com/facebookresearch/sam2'"
        )
        predictor_cls = _import_attr("sam2.sam2_image_predictor", "SAM2ImagePredictor", "the sam2 package")
        config = extra or _sam2_config_for(path.name)
        try:
            model = build(config, str(path), device=device)
        except Exception as exc:  # the package raises hydra/torch errors of many kinds
            raise TwinFocusError(f"{path}: could not build SAM 2 with config {config!r} ({exc})") from None
        return PredictorSegmenter(predictor_cls(model))
    registry = _import_attr("segment_anything", "sam_model_registry", "pip install segment-anything")
    predictor_cls = _import_attr("segment_anything", "SamPredictor", "the segment_anything package")
    model_type = extra or _sam_type_for(path.name)
    if model_type not in registry:
        raise TwinFocusError(f"unknown SAM model type {model_type!r}; have {', '.join(sorted(registry))}")
    try:
        model = registry[model_type](checkpoint=str(path))
        model.to(device=device)
    except Exception as exc:
        raise TwinFocusError(f"{path}: could not load SAM ({model_type}) ({exc})") from None
    return PredictorSegmenter(predictor_cls(model))


def _import_attr(module: str, attr: str, hint: str):
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError):
        raise TwinFocusError(
            f"the {module.split('.')[0]} package is not installed ({hint}); use --segmenter classical"
        ) from None


def _sam2_config_for(name: str) -> str:
    size = {"tiny": "t", "small": "s", "base_plus": "b+", "large": "l"}
    for key, short in size.items():
        if key in name:
            ver = "sam2.1" if "2.1" in name else "sam2"
            return f"configs/{ver}/{ver}_hiera_{short}.yaml"
    raise TwinFocusError(f"cannot tell the SAM 2 config from the checkpoint name {name!r}; pass sam2:CHECKPOINT:CONFIG")


def _sam_type_for(name: str) -> str:
    for t in ("vit_h", "vit_l", "vit_b"):
        if t in name:
            return t
    raise TwinFocusError(f"cannot tell the SAM model type from the checkpoint name {name!r}; pass sam:CHECKPOINT:TYPE")


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two bool masks (1.0 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)
