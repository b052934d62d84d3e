"""The reference's and the target's boxes from a wide look at the scan, so neither need be typed.

The look (:func:`look`) images the scan wide (the aperture's x/y box grown by
:data:`LOOK_MARGIN_M`, depths :data:`LOOK_DEPTHS_M`), in two passes:

- a coarse volume from the :data:`LOOK_POSITIONS` radar positions nearest the aperture's centre.
  A dense patch of the aperture, not every n-th position: positions taken n apart along a sweep
  sample it n times too coarsely, and the image's copies (grating lobes) then smear a 12 cm letter
  over the whole field (what made the reference's region 65 cm tall before). Its bright blobs are
  connected in 3-D, so that objects side by side at different depths stay apart;
- for each blob, its depth where its image is sharpest (:func:`twinfocus.imaging.depth_search.search_depth`
  on the same patch), then a plane at that depth from every position, fine enough
  (:data:`FINE_PIXEL_M`) to part objects a few cm apart.

The bright objects of the fine planes are the look's objects (:class:`LookObject`: each one's
x/y extent, depth and share of the bright energy). :func:`choose` takes the reference's object as
the one overlapping what the twin says it is (:mod:`twinfocus.focus.reference_search`: the template
scan's own look, a template file's grid, a digital twin's cloud), and the target as the brightest
other object, its extent grown into the region focused (:data:`REGION_MARGIN_M`, cut where it
would reach into the reference's region). A hand-held scan is looked at through the reference's
correction (:func:`find_target`): uncorrected, each position's tracking error scatters every
object along the sweep.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.depth_search import search_depth
from twinfocus.imaging.grid import ImageGrid, VolumeGrid
from twinfocus.outputs.plotting import _font, inferno
from twinfocus.radar.fmcw import Chirp

#: the coarse look uses this many radar positions, those nearest the aperture's centre
LOOK_POSITIONS = 120
#: the look covers the aperture's x/y box grown by this, metres, and these depths, metres ...
LOOK_MARGIN_M = 0.3
LOOK_DEPTHS_M = (0.2, 1.2)
#: ... on this many pixels per side
LOOK_SIZE = 40
#: a blob's depth is searched over its coarse depth +- this many range resolutions
DEPTH_SEARCH_RESOLUTIONS = 1.0
#: the fine plane: the blob's box grown by this (metres), pixels this size (metres), at most this many a side
FINE_MARGIN_M = 0.03
FINE_PIXEL_M = 0.004
FINE_MAX_PX = 96
#: objects are the connected pixels of the image's energy smoothed over this many pixels (a
#: Gaussian's sigma: speckle breaks a letter into islands; the smoothing joins them) within this
#: many dB of the brightest
COARSE_SMOOTHING_PX = 1.0
FINE_SMOOTHING_PX = 1.0
OBJECT_DB = -10.0
#: objects of one plane closer than this, metres, are pieces of one (a gap of less than about two
#: resolution cells at the scene's depths; the demo's letters lie 3.7 cm apart)
MERGE_GAP_M = 0.012
#: an object's edge is where its smoothed energy falls this many dB below the brightest of its
#: pixels within this many pixels (:func:`object_edges`), searched this many pixels beyond its
#: pixels, no fainter than this many dB below its peak, in pieces holding at least this share of
#: its brightest piece's energy
EDGE_DB = -6.0
EDGE_LOCAL_PX = 5
EDGE_SEARCH_PX = 3
EDGE_FLOOR_DB = -12.0
EDGE_MIN_PIECE = 0.05
#: a blob or an object with less than this share of the bright energy is ignored; at most this many blobs
MIN_SHARE = 0.02
MAX_BLOBS = 4
#: the region focused is the object's extent grown by this on every side, metres (the estimators
#: need the reference's blurred edge inside it; the typed regions of docs/architecture.md's scene
#: have 1.5-6 cm)
REGION_MARGIN_M = 0.015
#: a look object is the twin's when their x/y boxes overlap by at least this (intersection over union)
MATCH_IOU = 0.3


@dataclass
class LookObject:
    """One bright object of the look: ``extent_m`` (X0, X1, Y0, Y1) metres, the edges of its
    bright pixels; ``depth_m``; ``share`` of the look's bright energy (with the objects too faint to
    keep, below :data:`MIN_SHARE`, all sum to 1)."""

    extent_m: tuple[float, float, float, float]
    depth_m: float
    share: float

    def to_dict(self) -> dict:
        return {
            "extent_m": [round(v, 4) for v in self.extent_m],
            "depth_m": round(self.depth_m, 4),
            "share": round(self.share, 4),
        }


@dataclass
class Look:
    """What :func:`look` saw: the coarse projection (float32 (H, W) on ``plane``), the fine
    planes ((image float32 (h, w), grid) per blob) and the objects, brightest first."""

    mip: np.ndarray
    plane: ImageGrid
    fine: list[tuple[np.ndarray, ImageGrid]]
    objects: list[LookObject]
    seconds: float = 0.0


def near_centre(positions_m: np.ndarray, count: int = LOOK_POSITIONS) -> np.ndarray:
    """Indices (sorted, int) of the ``count`` radar positions whose channel centres lie nearest
    the aperture's centre in x/y. positions_m : float (M, K, 3) metres."""
    c = np.asarray(positions_m, np.float64).mean(axis=1)[:, :2]
    d = np.linalg.norm(c - c.mean(axis=0), axis=1)
    return np.sort(np.argsort(d, kind="stable")[: min(count, len(d))])


def objects_in(image: np.ndarray, plane: ImageGrid, smoothing_px: float, db: float = OBJECT_DB) -> list:
    """The bright objects of an amplitude image: [(extent (X0, X1, Y0, Y1) metres, energy)], the
    brightest first. image : float (H, W) on ``plane``. Energy is summed |image|^2 times the
    pixel's area, so that planes of different pixel sizes compare.

    Objects are found as the connected pixels within ``db`` of the image's brightest; each one's
    extent is then its edge (:func:`object_edges`): where its energy falls :data:`EDGE_DB` below
    its own bright pixels nearby, to a fraction of a pixel. The ``db`` threshold alone, relative to
    the brightest object, put the brightest's edges where its blur ends and a fainter one's inside
    it (benchmarks/results/boxes_found.json)."""
    from scipy import ndimage  # only on this path

    e = ndimage.gaussian_filter(np.asarray(image, np.float64) ** 2, smoothing_px)
    if not e.max() > 0:
        return []
    labels, n = ndimage.label(e >= e.max() * 10 ** (db / 10))
    dy, dx = plane.spacing_m
    found = []
    for k, sl in enumerate(ndimage.find_objects(labels), start=1):
        rows, cols = sl
        box = (
            float(plane.x_m[cols.start] - dx / 2),
            float(plane.x_m[cols.stop - 1] + dx / 2),
            float(plane.y_m[rows.start] - dy / 2),
            float(plane.y_m[rows.stop - 1] + dy / 2),
        )
        found.append((box, float(e[labels == k].sum()) * dx * dy, object_edges(e, plane, sl)))
    return [(edge, energy) for _, energy, edge in sorted(_merge_near(found), key=lambda f: -f[1])]


def object_edges(energy: np.ndarray, plane: ImageGrid, where: tuple[slice, slice]) -> tuple[float, float, float, float]:
    """An object's x/y edges (X0, X1, Y0, Y1) metres: where its smoothed energy falls
    :data:`EDGE_DB` below the brightest of its pixels nearby (within :data:`EDGE_LOCAL_PX`),
    interpolated between pixels.

    energy : float64 (H, W), the smoothed |image|^2 on ``plane``; where : the (rows, cols)
    slices of the object's pixels. Searched in that box grown by :data:`EDGE_SEARCH_PX` (a blurred
    edge can reach beyond the pixels the coarser threshold kept), among pixels no fainter than
    :data:`EDGE_FLOOR_DB` below the object's peak, keeping the pieces that hold at least
    :data:`EDGE_MIN_PIECE` of the brightest piece's energy (a neighbour's speckle reaching into the
    window does not count). Why -6 dB: a flat object's edge, blurred by a symmetric point response,
    sits where its amplitude is half the inside's. Why nearby, not the object's peak: an object
    whose parts differ in brightness (a glint, a letter of metal balls) would lose its fainter
    parts below a level set by its brightest."""
    from scipy import ndimage  # only on this path

    rows, cols = where
    h, w = energy.shape
    g = EDGE_SEARCH_PX
    r0, r1 = max(rows.start - g, 0), min(rows.stop + g, h)
    c0, c1 = max(cols.start - g, 0), min(cols.stop + g, w)
    win = energy[r0:r1, c0:c1]
    near = ndimage.maximum_filter(energy, size=2 * EDGE_LOCAL_PX + 1)[r0:r1, c0:c1] * 10 ** (EDGE_DB / 10)
    floor = float(energy[rows, cols].max()) * 10 ** (EDGE_FLOOR_DB / 10)
    labels, n = ndimage.label((win >= near) & (win >= floor))
    sums = np.asarray(ndimage.sum(win, labels, range(1, n + 1)), np.float64)
    mask = np.isin(labels, 1 + np.flatnonzero(sums >= EDGE_MIN_PIECE * sums.max()))
    x0, x1 = _crossings(win.T, near.T, mask.T, plane.x_m[c0:c1])
    y0, y1 = _crossings(win, near, mask, plane.y_m[r0:r1])
    return (x0, x1, y0, y1)


def _crossings(win: np.ndarray, level: np.ndarray, mask: np.ndarray, coords: np.ndarray) -> tuple[float, float]:
    """The first and last places (metres) along axis 0 of ``win`` (float (L, P) energy on
    ``coords`` (L,)) where the object (``mask``, bool (L, P)) ends: between its outermost line and
    the next one out, where the brightest of its pixels on that line falls to their ``level``
    (linear), or that line's outer half-pixel at the window's border."""
    lines = np.flatnonzero(mask.any(axis=1))
    lo, hi = int(lines[0]), int(lines[-1])
    step = float(coords[1] - coords[0]) if len(coords) > 1 else 0.0

    def cross(i: int, j: int) -> float:
        if not 0 <= j < len(coords):
            return float(coords[i] + (j - i) * step / 2)
        sel = mask[i]
        a, b, lv = float(win[i, sel].max()), float(win[j, sel].max()), float(level[i, sel].max())
        t = (a - lv) / (a - b) if a > b else 0.5
        return float(coords[i] + min(max(t, 0.0), 1.0) * (j - i) * step)

    return cross(lo, lo - 1), cross(hi, hi + 1)


def _gap(a, b) -> float:
    """How far apart two x/y boxes are, metres: the larger of the x and y gaps (<= 0: they touch)."""
    return max(max(a[0], b[0]) - min(a[1], b[1]), max(a[2], b[2]) - min(a[3], b[3]))


def _union(a, b) -> tuple[float, float, float, float]:
    return (min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3]))


def _merge_near(found: list) -> list:
    """Pieces of one object (a letter's speckle can leave a bar apart from its stem) joined: boxes
    (each found item: (box, energy, edges)) closer than :data:`MERGE_GAP_M` become one, their
    energies summed, their edges the union."""
    found = list(found)
    merged = True
    while merged:
        merged = False
        for i in range(len(found)):
            for j in range(i + 1, len(found)):
                (a, ea, ga), (b, eb, gb) = found[i], found[j]
                if _gap(a, b) < MERGE_GAP_M:
                    found[i] = (_union(a, b), ea + eb, _union(ga, gb))
                    del found[j]
                    merged = True
                    break
            if merged:
                break
    return found


def _blobs(volume: np.ndarray, grid: VolumeGrid) -> list[tuple[tuple[float, float, float, float], float, float]]:
    """The coarse volume's bright blobs, connected in 3-D (objects at different depths beside each
    other stay apart): [(x/y box (X0, X1, Y0, Y1) metres, energy, depth metres of its brightest
    voxel)], the brightest first. volume : complex (D, H, W) on ``grid``."""
    from scipy import ndimage  # only on this path

    e = ndimage.gaussian_filter(np.abs(volume).astype(np.float64) ** 2, (0.0, COARSE_SMOOTHING_PX, COARSE_SMOOTHING_PX))
    if not e.max() > 0:
        return []
    labels, _ = ndimage.label(e >= e.max() * 10 ** (OBJECT_DB / 10))
    plane = grid.plane
    dy, dx = plane.spacing_m
    found = []
    for k, (_, rows, cols) in enumerate(ndimage.find_objects(labels), start=1):
        mask = labels == k
        peak = np.unravel_index(int(np.argmax(np.where(mask, e, 0.0))), e.shape)
        box = (
            float(plane.x_m[cols.start] - dx / 2),
            float(plane.x_m[cols.stop - 1] + dx / 2),
            float(plane.y_m[rows.start] - dy / 2),
            float(plane.y_m[rows.stop - 1] + dy / 2),
        )
        found.append((box, float(e[mask].sum()), float(grid.z_m[peak[0]])))
    return sorted(found, key=lambda f: -f[1])


def look(
    data: np.ndarray,
    positions_m: np.ndarray,
    chirp: Chirp,
    *,
    phase_rad: np.ndarray | None = None,
    bp_options: dict | None = None,
    progress_factory=None,
) -> Look:
    """The wide uncorrected look at a scan and its bright objects (module docstring).

    data : complex (M, K, N); positions_m : float64 (M, K, 3) metres; phase_rad : float (M,) a
    correction to look through (None: none); bp_options : keywords of
    :func:`twinfocus.imaging.backprojection.numba_backend.backproject_points`."""
    import time

    from twinfocus.imaging.volume import corrected_image, projections  # lazy: numba, scipy (+1.5 s at import)

    t = time.perf_counter()
    prog = progress_factory or (lambda label: None)
    bp = dict(bp_options or {})
    phase = np.zeros(data.shape[0]) if phase_rad is None else np.asarray(phase_rad, np.float64)
    sub = near_centre(positions_m)
    d, p, ph = data[sub], positions_m[sub], phase[sub]
    centres = positions_m.reshape(-1, 3)
    lo = centres[:, :2].min(axis=0) - LOOK_MARGIN_M
    hi = centres[:, :2].max(axis=0) + LOOK_MARGIN_M
    z0, z1 = LOOK_DEPTHS_M
    plane = ImageGrid(float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]), z0, LOOK_SIZE, LOOK_SIZE)
    n_planes = int(np.ceil((z1 - z0) / (0.5 * chirp.range_resolution_m))) + 1
    grid = VolumeGrid(plane, z0, z1, n_planes)
    vol = corrected_image(d, p, chirp, grid, ph, progress=prog("look"), **bp)
    mip, _ = projections(vol, grid)
    blobs = _blobs(vol, grid)
    total = sum(b[1] for b in blobs) or 1.0
    fine, objects = [], []
    for box, energy, z_blob in blobs[:MAX_BLOBS]:
        if energy / total < MIN_SHARE:
            continue
        half = DEPTH_SEARCH_RESOLUTIONS * chirp.range_resolution_m
        found = search_depth(d, p, chirp, box, (max(0.05, z_blob - half), z_blob + half), ph, bp_options=bp)
        g = FINE_MARGIN_M
        w, h = box[1] - box[0] + 2 * g, box[3] - box[2] + 2 * g
        size = (min(FINE_MAX_PX, max(8, round(h / FINE_PIXEL_M))), min(FINE_MAX_PX, max(8, round(w / FINE_PIXEL_M))))
        fgrid = ImageGrid.from_roi((box[0] - g, box[1] + g, box[2] - g, box[3] + g, found.depth_m), size)
        img = np.abs(corrected_image(data, positions_m, chirp, fgrid, phase, progress=prog("look, fine"), **bp))
        fine.append((img.astype(np.float32), fgrid))
        objects += [(ext, float(found.depth_m), e) for ext, e in objects_in(img, fgrid, FINE_SMOOTHING_PX)]
    if not objects:
        raise TwinFocusError("the look at the scan found no bright object; type --reference-roi and --target-roi")
    total = sum(o[2] for o in objects)
    kept = [
        LookObject(ext, z, e / total) for ext, z, e in sorted(objects, key=lambda o: -o[2]) if e / total >= MIN_SHARE
    ]
    return Look(mip, plane, fine, kept, time.perf_counter() - t)


def overlap(a, b) -> float:
    """Intersection over union of two x/y boxes (X0, X1, Y0, Y1): 0 apart, 1 the same."""
    w = min(a[1], b[1]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[2], b[2])
    if w <= 0 or h <= 0:
        return 0.0
    inter = w * h
    return float(inter / ((a[1] - a[0]) * (a[3] - a[2]) + (b[1] - b[0]) * (b[3] - b[2]) - inter))


def grow(extent, margin_m: float = REGION_MARGIN_M) -> list[float]:
    """An x/y extent grown by ``margin_m`` on every side: [X0, X1, Y0, Y1]."""
    return [extent[0] - margin_m, extent[1] + margin_m, extent[2] - margin_m, extent[3] + margin_m]


def cut_away(region: list[float], keep, extent, other_extent) -> list[float]:
    """``region`` (X0, X1, Y0, Y1) shortened so that it does not reach into the region ``keep``:
    cut at ``keep``'s edge along the axis on which the objects (``extent``, ``other_extent``) lie
    furthest apart. Unchanged when they do not overlap or the objects themselves overlap."""
    r = list(region)
    if overlap(r, keep) == 0.0:
        return r
    e, o = extent, other_extent
    gaps = [max(o[0] - e[1], e[0] - o[1]), max(o[2] - e[3], e[2] - o[3])]
    axis = int(np.argmax(gaps))
    if gaps[axis] <= 0:
        return r
    lo, hi = 2 * axis, 2 * axis + 1
    if e[hi] <= o[lo]:  # this object lies before the other along the axis
        r[hi] = min(r[hi], keep[lo])
    else:
        r[lo] = max(r[lo], keep[hi])
    return r


@dataclass
class Boxes:
    """What :func:`choose` took: ``target_roi`` (X0, X1, Y0, Y1, Z metres, the region focused)
    and ``info`` (for metrics.json ``boxes``: the look's objects, why each box, how surely)."""

    reference_roi: tuple
    target_roi: tuple
    info: dict = field(default_factory=dict)

    def line(self) -> str:
        """The one line ``focus`` prints: which boxes it took and how surely."""
        r, t = self.info["reference"], self.info["target"]
        fmt = lambda roi: " ".join(f"{v:.3f}" for v in roi)  # noqa: E731
        return (
            f"[boxes] reference {fmt(self.reference_roi)} ({r['why']}); target {fmt(self.target_roi)} "
            f"({t['why']}); sure: {self.info['sure']}"
        )


def choose(
    seen: Look,
    reference_roi,
    reference_extent,
    reference_source: str,
    margin_m: float = REGION_MARGIN_M,
) -> Boxes:
    """The target's region from the look's objects, beside the reference's (typed or found).

    reference_roi : the reference's region (X0, X1, Y0, Y1, Z), kept as it is; reference_extent :
    the reference object's extent (X0, X1, Y0, Y1, Z) as its source knows it (the region itself
    when typed); reference_source : its name ("typed", "physical twin scan", ...).

    The reference is the look object overlapping its extent most; the target the brightest of the
    others that lie apart from the reference's region, its extent grown by ``margin_m`` and cut
    where it would reach into the reference's region (:func:`cut_away`), at its depth. How sure:
    the reference's overlap with a look object (intersection over union), the target's share of
    the energy of the objects other than the reference and the next brightest's energy over its."""
    objs = seen.objects
    scores = [overlap(o.extent_m, reference_extent[:4]) for o in objs]
    k = int(np.argmax(scores))
    ref_index = k if scores[k] >= MATCH_IOU else None
    ref_why = (
        f"{reference_source}, the look's object {k + 1} of {len(objs)} (overlap {scores[k]:.2f})"
        if ref_index is not None
        else f"{reference_source}; no object of the look matches it (best overlap {scores[k]:.2f})"
    )
    # an object the reference's region mostly holds is the reference's (or a piece of it)
    others = [i for i, o in enumerate(objs) if i != ref_index and _inside(o.extent_m, reference_roi) < 0.5]
    if not others:
        raise TwinFocusError("the look found no bright object besides the reference; type --target-roi")
    rest = sum(objs[i].share for i in others)
    o = objs[others[0]]
    share = o.share / rest
    runner_up = objs[others[1]].share / o.share if len(others) > 1 else 0.0
    region = cut_away(grow(o.extent_m, margin_m), reference_roi[:4], o.extent_m, reference_extent[:4])
    target_roi = (*region, float(o.depth_m))
    sure = "yes" if ref_index is not None and share >= 0.5 and runner_up < 0.5 else "no"
    info = {
        "objects": [ob.to_dict() for ob in objs],
        "reference": {
            "roi": list(reference_roi),
            "extent_m": [float(v) for v in reference_extent],
            "source": reference_source,
            "look_object": None if ref_index is None else ref_index + 1,
            "overlap": round(scores[k], 3),
            "why": ref_why,
        },
        "target": {
            "roi": list(target_roi),
            "extent_m": [float(v) for v in o.extent_m],
            "look_object": others[0] + 1,
            "share": round(share, 3),
            "next_over_chosen": round(runner_up, 3),
            "why": f"the look's brightest other object, {others[0] + 1} of {len(objs)}, {share:.2f} of their energy",
        },
        "sure": sure,
        "margin_m": margin_m,
        "look_seconds": round(seen.seconds, 2),
    }
    return Boxes(tuple(reference_roi), target_roi, info)


def _inside(box, region) -> float:
    """The share of ``box``'s area (X0, X1, Y0, Y1) inside ``region``'s."""
    w = min(box[1], region[1]) - max(box[0], region[0])
    h = min(box[3], region[3]) - max(box[2], region[2])
    return float(max(w, 0.0) * max(h, 0.0) / ((box[1] - box[0]) * (box[3] - box[2])))


def find_target(
    focus, scan, reference_roi, reference_extent, reference_source: str, bp_options: dict, progress_factory=None
):
    """The target's box when none is typed: the reference's phase first (its estimate with a 2 x 2
    target region on the reference's own: the target is not needed for it), then the look at the
    scan corrected by it (uncorrected, the tracking error's phase scatters every object along the
    sweep), then :func:`choose`. focus : as :func:`twinfocus.imaging.depth_search.find_target_depth`'s.
    Returns (:class:`Boxes`, :class:`Look`)."""
    import dataclasses

    probe = ImageGrid.from_roi(tuple(reference_roi), 2)
    blind = dataclasses.replace(scan, positions_true=None)  # no truth images for the probe
    phase = focus(blind, target_grid=probe, space_variant="off").phase_rad
    seen = look(
        scan.data, scan.positions, scan.chirp, phase_rad=phase, bp_options=bp_options, progress_factory=progress_factory
    )
    return choose(seen, reference_roi, reference_extent, reference_source), seen


def look_picture(path, seen: Look, boxes: Boxes) -> None:
    """``look.png``: the wide look's projection and its fine planes, the reference's region drawn
    in cyan and the target's in lime (Pillow, beside summary.png)."""
    from PIL import Image, ImageDraw

    panels = [(seen.mip, seen.plane, "look, wide (projection over depth)")]
    panels += [(img, g, f"look, z {g.z * 1e3:.0f} mm") for img, g in seen.fine]
    px, pad, head = 320, 12, 24
    canvas = Image.new("RGB", (len(panels) * (px + 2 * pad), px + head + 2 * pad), "white")
    draw = ImageDraw.Draw(canvas)
    for n, (img, g, title) in enumerate(panels):
        amp = np.asarray(img, np.float64) / max(float(np.max(img)), 1e-30)
        scale = px / max(g.x1 - g.x0, g.y1 - g.y0)
        size = (max(1, round((g.x1 - g.x0) * scale)), max(1, round((g.y1 - g.y0) * scale)))
        tile = Image.fromarray((inferno(amp) * 255 + 0.5).astype(np.uint8), "RGB").resize(size)
        x0, y0 = n * (px + 2 * pad) + pad, head
        canvas.paste(tile, (x0, y0))
        draw.text((x0, 4), title, fill="black", font=_font(13))
        for roi, colour in ((boxes.reference_roi, "cyan"), (boxes.target_roi, "lime")):
            a = (x0 + (roi[0] - g.x0) * scale, y0 + (roi[2] - g.y0) * scale)
            b = (x0 + (roi[1] - g.x0) * scale, y0 + (roi[3] - g.y0) * scale)
            draw.rectangle((a, b), outline=colour, width=2)
    canvas.save(path, format="PNG")
