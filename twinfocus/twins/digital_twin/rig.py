"""A calibrated rig: the camera's offset from the radar, measured once from one scan on accurate
positions (a motion-stage scan, or any scan whose positions are trusted) of a scene holding an
object the camera's cloud shows, and applied to every later cloud of that camera on that board.

What one scan shows: a translation across x and y, where the cloud's conditioned template is
registered against the radar image of the reference (normalised cross-correlation, sub-pixel
parabola, on pixels of 2 mm: :func:`twinfocus.twins.digital_twin.align.register_translation`). Along z
the radar's depth (where the reference's image is sharpest, :func:`twinfocus.imaging.depth_search.search_depth`)
against the cloud's median depth is recorded but not applied: it missed injected offsets of 1-2 mm
by 2-4 mm (the focus resolves centimetres along z). A rotation is *not* measured: a tilt of a flat object moves its radar
image by less than the registration resolves over a few centimetres (a 1 deg tilt of a 5 cm letter
moves its edge by 0.9 mm in depth, far below the range resolution), and an in-plane rotation of one
object is confounded with the outline's own errors; a rig file says ``"rotation": "not measured"``.

How sure (:func:`rig_spread`): three measured spreads, each of what moves the registration that
the others do not see, and a floor for the template's model, added in quadrature into the rig
file's ``sd_m`` (``source.sd`` keeps each and ``method``, how they were made):

* ``positions``: a bootstrap over the scan's positions (each draw sums the per-position sub-images
  with multinomial weights and registers again): the receiver's noise. It alone was the stated sd
  once, and it was 2-8 times too small: resampling positions keeps the scene's speckle and the
  template's shape, so it never sees the two errors that dominate.
* ``cells``: a leave-one-block-out jackknife over the radar image in blocks of
  :data:`JACKKNIFE_CELLS` resolution cells a side (pixels within a cell are one measurement, so
  blocks, not pixels, are the units): the speckle of the object's surface and where the image and
  the template disagree locally (a glint, an edge the camera missed).
* ``cloud``: template perturbations: the camera's cloud with another :data:`CLOUD_DROP` of its
  points removed in patches (as a camera loses them), conditioned and registered again
  (:data:`CLOUD_DRAWS` draws): the outline's dependence on which parts of the object the camera
  happened to see, a bias no resampling of the radar's data shows.
* ``model``: :data:`MODEL_CELLS` of a resolution cell, what no resampling of one scan shows.

On the rig bench's calibrations (``python -m benchmarks.bench_rig --calibrations N``) the error
falls within 2 of this sd where it fell outside 2 of the bootstrap's for about half of them.

Applied (``--rig``): the cloud is moved by the offset (:func:`rig_reference`), and the focus then
places the reference on the calibrated outline (:func:`rig_placed`, :func:`place_on_rig`: the
estimate's ramp that holds the reference's energy most inside it, taken out when that is clear);
the confidence report reads that placement (:func:`rig_trust`).

Refusals (one line, :class:`TwinFocusError`): an object too small to register (its outline covers
fewer than :data:`MIN_SUPPORT_PIXELS` pixels, or spans fewer than :data:`MIN_EXTENT_CELLS`
resolution cells), a cloud and image that disagree in shape (correlation below
:data:`MIN_MATCH`), a measurement whose combined spread exceeds :data:`MAX_SD_PX` pixels.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.subpixel import shift_image
from twinfocus.io.documents import read_json, write_json_document
from twinfocus.radar.board import default_board
from twinfocus.twins.digital_twin.template import load_points

#: the reference's outline must cover at least this many pixels of the region to be registered
MIN_SUPPORT_PIXELS = 30
#: ... and span at least this many of the radar's cross-range resolution cells on each axis
MIN_EXTENT_CELLS = 3.0
#: the template's correlation with the radar image below which cloud and image disagree in shape
MIN_MATCH = 0.3
#: the measured spread (the sd less the model's floor, :func:`rig_spread`; pixels, either axis) above
#: which the offset is not measured: 2 mm at the measuring pixel, the least a camera is off on the
#: benches (2-3 mm), so a rig less sure than that cannot be told from none. Half a pixel, the rule
#: while the sd was the positions' bootstrap alone, refused 7 of the 16 build calibrations once
#: the sd was honest (benchmarks/results/rig_calibration.json ``summary.refused_half_pixel``)
MAX_SD_PX = 1.0
#: bootstrap draws over the positions
BOOTSTRAP = 24
#: the jackknife's blocks over the radar image, resolution cells a side
JACKKNIFE_CELLS = 2.0
#: template perturbations: draws, and the share of the cloud's points each removes in patches
CLOUD_DRAWS = 8
CLOUD_DROP = 0.2
#: the template's shape model, resolution cells: what the radar image and the template built from
#: the cloud disagree by however well both were measured (each scatterer's own strength and phase
#: move the image's brightness inside the outline; the template has none of it). No resampling of
#: one scan shows it; a tenth of a cell is what the first ten of the rig bench's build
#: calibrations needed to fall within 2 sd (one was 0.8 px off across y where the three measured
#: spreads said 0.3 px; benchmarks/results/rig_calibration.json)
MODEL_CELLS = 0.1
#: how the rig file's sd was made (``source.sd.method``; the draws and blocks filled in)
SD_METHOD = (
    "the root sum of squares of four parts (each *_px: pixels, dy then dx): positions, a bootstrap over the scan's "
    "positions ({positions} draws); "
    "cells, a leave-one-block-out jackknife over the radar image in blocks of {cells:g} x {cells:g} resolution "
    "cells ({blocks} blocks of {block_px[0]} x {block_px[1]} pixels); cloud, the spread of the offset over the "
    "camera's cloud with another {drop:.0%} of its points removed in patches and conditioned again ({cloud} draws); "
    "model, {model:g} of a resolution cell (the template's shape model); the rule that refuses a calibration reads "
    "the three measured spreads, not the model's"
)

#: the depths searched for the radar's reference, metres either side of the region's plane
DEPTH_HALF_RANGE_M = 0.03

RIG_KIND = "twinfocus-rig"
#: registration rounds (each on the residual)
REGISTRATION_ROUNDS = 3
#: the measuring grid's pixel, metres (the registration's sub-pixel part is good to ~0.2 px)
MEASURE_PIXEL_M = 2e-3
#: ... and its most pixels per side
MEASURE_MAX_PIXELS = 200


def measuring_grid(grid: ImageGrid) -> ImageGrid:
    """The reference region on pixels of about :data:`MEASURE_PIXEL_M` (at most
    :data:`MEASURE_MAX_PIXELS` per side, at least the given grid's): where the rig is measured."""
    x0, x1, y0, y1, z = grid.roi
    h = int(np.clip(round((y1 - y0) / MEASURE_PIXEL_M) + 1, grid.shape[0], MEASURE_MAX_PIXELS))
    w = int(np.clip(round((x1 - x0) / MEASURE_PIXEL_M) + 1, grid.shape[1], MEASURE_MAX_PIXELS))
    return ImageGrid.from_roi(grid.roi, (h, w))


def camera_identity(cloud_path: str | os.PathLike) -> str | None:
    """The camera that made the cloud in ``cloud_path``, from a sidecar ``CLOUD.json`` (key
    ``camera``) next to it, else None (a bare .npy carries no metadata)."""
    side = Path(cloud_path).with_suffix(".json")
    if not side.is_file():
        return None
    try:
        v = read_json(side).get("camera")
    except (OSError, ValueError, AttributeError):
        return None
    return None if v is None else str(v)


@dataclass
class Rig:
    """The camera's offset from the radar (metres, scene frame: added to the camera's points) and
    the identities of the radar board and camera it was measured on."""

    offset_m: np.ndarray
    sd_m: np.ndarray
    board: str
    camera: str | None
    created_ns: int = 0
    source: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("offset_m", "sd_m"):
            v = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            if v.shape != (3,) or not np.isfinite(v).all():
                raise TwinFocusError(f"a rig's {name} must be 3 finite numbers (metres), got {getattr(self, name)!r}")
            setattr(self, name, v)

    def to_dict(self) -> dict:
        return {
            "kind": RIG_KIND,
            "offset_m": self.offset_m.tolist(),
            "sd_m": self.sd_m.tolist(),
            "rotation": "not measured",
            "board": self.board,
            "camera": self.camera,
            "created_ns": int(self.created_ns),
            "source": self.source,
        }

    def save(self, path: str | os.PathLike) -> Path:
        return write_json_document(path, self.to_dict())

    @classmethod
    def load(cls, path: str | os.PathLike) -> Rig:
        p = Path(path)
        if not p.is_file():
            raise TwinFocusError(f"--rig {p}: no such rig file (make one with twinfocus rig)")
        try:
            d = read_json(p)
            if d.get("kind") != RIG_KIND:
                raise ValueError(f"kind is {d.get('kind')!r}, not {RIG_KIND!r}")
            return cls(d["offset_m"], d["sd_m"], str(d["board"]), d.get("camera"), int(d.get("created_ns", 0)),
                       dict(d.get("source", {})))  # fmt: skip
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            raise TwinFocusError(f"--rig {p}: not a rig file ({exc})") from None
        except TwinFocusError as exc:
            raise TwinFocusError(f"--rig {p}: {exc}") from None

    def check(self, board: str, camera: str | None, path: str | os.PathLike = "") -> None:
        """Refuse the rig for another radar board or camera (a camera unknown on either side
        is not checked: a bare cloud names none)."""
        if board != self.board:
            raise TwinFocusError(f"--rig {path}: measured on the {self.board} board, this scan is from the {board}")
        if camera is not None and self.camera is not None and camera != self.camera:
            raise TwinFocusError(f"--rig {path}: measured with camera {self.camera!r}, this cloud is from {camera!r}")


def scan_board(scan) -> str:
    """The radar board a scan comes from: the board named in its channel calibration's record
    (``twinfocus convert``), else the default board's name."""
    if scan.calibration:
        try:
            b = json.loads(scan.calibration).get("board")
            if isinstance(b, dict) and b.get("name"):
                return str(b["name"])
            if isinstance(b, str) and b:
                return b
        except (ValueError, AttributeError):
            pass
    return default_board().name


def load_rig_for(path: str | os.PathLike, scan, cloud_path: str | os.PathLike | None) -> tuple[Rig, dict]:
    """``--rig PATH`` for a scan and its cloud: the rig, checked against the scan's board and the
    cloud's camera, and what metrics.json records of it (path, SHA-256, offset, sd)."""
    from twinfocus.io.checksums import file_sha256  # lazy: twinfocus.io.checksums (+0.03 s on twinfocus rig --help)

    rig = Rig.load(path)
    rig.check(scan_board(scan), camera_identity(cloud_path) if cloud_path else None, path)
    record = {"path": str(path), "sha256": file_sha256(path), "offset_m": rig.offset_m.tolist(),
              "sd_m": rig.sd_m.tolist(), "board": rig.board, "camera": rig.camera}  # fmt: skip
    return rig, record


@dataclass
class RigMeasurement:
    """What :func:`measure_rig` found: the rig, the shift in pixels (dy, dx) and its bootstrap sd,
    the match score, and the pictures' inputs (radar image, outline before and after)."""

    rig: Rig
    shift_px: tuple[float, float]
    sd_px: tuple[float, float]
    match: float
    image: np.ndarray
    outline_before: np.ndarray
    outline_after: np.ndarray


def _extent_cells(support: np.ndarray, grid: ImageGrid, resolution_m: float) -> float:
    ys, xs = np.nonzero(support)
    sy, sx = grid.spacing_m
    return float(min((ys.max() - ys.min() + 1) * sy, (xs.max() - xs.min() + 1) * sx) / resolution_m)


def _resolution_px(scan, grid: ImageGrid) -> tuple[np.ndarray, float]:
    """The radar's cross-range resolution at the region: float (2,) pixels (y, x), lambda R / (2 L)
    with L the aperture's extent on that axis, and the finer of the two in metres (the extent
    check's unit: lambda R / (2 L), L the aperture's larger extent)."""
    centres = scan.positions.reshape(-1, 3)
    extent = np.maximum(np.ptp(centres[:, :2], axis=0), 1e-6)  # (x, y)
    range_m = float(np.linalg.norm(grid.centre_m - centres.mean(axis=0)))
    cell_m = scan.chirp.wavelength_m * range_m / (2.0 * extent)
    return cell_m[::-1] / np.asarray(grid.spacing_m), float(scan.chirp.wavelength_m * range_m / (2.0 * extent.max()))


def _cells_jackknife(shifted: np.ndarray, image: np.ndarray, block_px: tuple[int, int]) -> tuple[np.ndarray, int]:
    """Leave-one-block-out jackknife sd (float (2,), pixels, (dy, dx)) of the registration of
    ``shifted`` (the template where the registration put it, float (H, W)) onto ``image`` (H, W),
    over blocks of ``block_px`` pixels: each block in turn is set to the image's mean (it then adds
    nothing to the mean-removed correlation), and the number of blocks."""
    from twinfocus.twins.digital_twin.align import (
        register_translation,  # lazy: twinfocus.twins.digital_twin.align (+0.03 s on twinfocus rig --help)
    )

    by, bx = block_px
    fill = float(image.mean())
    draws = []
    for i in range(0, image.shape[0], by):
        for j in range(0, image.shape[1], bx):
            cut = image.copy()
            cut[i : i + by, j : j + bx] = fill
            draws.append(register_translation(shifted, cut)[:2])
    d = np.asarray(draws)
    n = d.shape[0]
    return np.sqrt((n - 1) / n * ((d - d.mean(axis=0)) ** 2).sum(axis=0)), n


def _cloud_spread(points: np.ndarray, scan, grid: ImageGrid, image: np.ndarray, shift: tuple[float, float],
                  draws: int, rng: int, **bp_options) -> np.ndarray:  # fmt: skip
    """sd (float (2,), pixels, (dy, dx)) of the registration over ``draws`` templates of the cloud
    ``points`` (float (N, 3), metres) with another :data:`CLOUD_DROP` of its points removed in
    patches (:func:`twinfocus.twins.digital_twin.camera_cloud.camera_cloud`'s holes) and
    conditioned again, each registered from ``shift`` (dy, dx) onto ``image`` (H, W)."""
    from twinfocus.twins.digital_twin.align import (
        register_translation,  # lazy: twinfocus.twins.digital_twin.align (+0.03 s on twinfocus rig --help)
    )
    from twinfocus.twins.digital_twin.camera_cloud import (
        camera_cloud,  # lazy: scipy.spatial (the calibration study's cloud draws only)
    )
    from twinfocus.twins.digital_twin.condition import (
        digital_twin_reference,  # lazy: open3d, scipy.ndimage (+4.3 s at import)
    )

    gen = np.random.default_rng([rng, 1])
    out = []
    for _ in range(int(draws)):
        cut = camera_cloud(points, 0.0, CLOUD_DROP, 0.0, 0.0, rng=gen)
        try:
            t = digital_twin_reference(cut, scan.positions, scan.chirp, grid, **bp_options).template
        except TwinFocusError:  # too little left to condition: that draw says nothing
            continue
        out.append(register_translation(shift_image(np.asarray(t, np.float64), *shift), image)[:2])
    return np.asarray(out).std(axis=0, ddof=1) if len(out) > 1 else np.zeros(2)


def rig_spread(scan, points: np.ndarray, grid: ImageGrid, basis: np.ndarray, template: np.ndarray,
               shift: tuple[float, float], *, bootstrap: int = BOOTSTRAP, cloud_draws: int = CLOUD_DRAWS,
               rng: int = 0, **bp_options) -> dict:  # fmt: skip
    """How surely the registration ``shift`` (dy, dx, pixels) of ``template`` (float (H, W), the
    cloud's) onto the radar image (the sum of ``basis``, complex (M, H, W), the scan's sub-images
    on ``grid``) was measured: the module docstring's three spreads and their root sum of squares,
    pixels (dy, dx) each: ``positions_px``, ``cells_px``, ``cloud_px``, their root sum of squares
    ``measured_px``, ``model_px`` (:data:`MODEL_CELLS` of ``cell_px``, the resolution cell) and
    ``sd_px`` (all four), and ``method`` (:data:`SD_METHOD`, the draws and blocks filled in)."""
    from twinfocus.twins.digital_twin.align import (
        register_translation,  # lazy: twinfocus.twins.digital_twin.align (+0.03 s on twinfocus rig --help)
    )

    dy, dx = shift
    image = np.abs(basis.sum(axis=0))
    shifted = shift_image(template, dy, dx)
    gen = np.random.default_rng(rng)
    m = basis.shape[0]
    draws = []
    for _ in range(int(bootstrap)):
        w = gen.multinomial(m, np.full(m, 1.0 / m)).astype(np.float32)
        bdy, bdx, _ = register_translation(shifted, np.abs(np.tensordot(w, basis, axes=1)))
        draws.append((dy + bdy, dx + bdx))
    positions = np.asarray(draws).std(axis=0, ddof=1) if len(draws) > 1 else np.zeros(2)
    cell_px, _ = _resolution_px(scan, grid)
    block = tuple(int(max(1, round(JACKKNIFE_CELLS * c))) for c in cell_px)
    cells, blocks = _cells_jackknife(shifted, image, block)  # type: ignore[arg-type]
    cloud = _cloud_spread(points, scan, grid, image, shift, cloud_draws, rng, **bp_options)
    measured = np.sqrt(positions**2 + cells**2 + cloud**2)
    model = MODEL_CELLS * cell_px
    method = SD_METHOD.format(positions=int(bootstrap), cells=JACKKNIFE_CELLS, blocks=blocks, block_px=block,
                              drop=CLOUD_DROP, cloud=int(cloud_draws), model=MODEL_CELLS)  # fmt: skip
    return {"method": method, "sd_px": np.sqrt(measured**2 + model**2).tolist(), "measured_px": measured.tolist(),
            "positions_px": positions.tolist(), "cells_px": cells.tolist(), "cloud_px": cloud.tolist(),
            "model_px": model.tolist(), "cell_px": cell_px.tolist()}  # fmt: skip


def measure_rig(
    scan,
    points_m: np.ndarray,
    grid: ImageGrid,
    *,
    board: str,
    camera: str | None,
    bootstrap: int = BOOTSTRAP,
    cloud_draws: int = CLOUD_DRAWS,
    rng: int = 0,
    max_sd_px: float = MAX_SD_PX,
    depth: bool = True,
    **bp_options,
) -> RigMeasurement:
    """Measure the camera's offset from the radar on ``scan`` (positions trusted).

    scan : :class:`~twinfocus.radar.scan.Scan`; points_m : float (N, 3) the camera's cloud of the
    reference, scene frame, metres, as it comes (no offset applied); grid : the reference region.
    bootstrap, cloud_draws : draws of the spreads (:func:`rig_spread`); max_sd_px : the spread
    (pixels) above which it refuses (:data:`MAX_SD_PX`; the bench's calibration study passes inf to
    see every spread); depth : search the radar's depth (recorded, never applied; the study skips it).
    Returns :class:`RigMeasurement`; raises :class:`TwinFocusError` when the offset cannot be
    measured (module docstring)."""
    from twinfocus.imaging.backprojection.numba_backend import subimage_basis  # lazy: numba (+2.1 s at import)
    from twinfocus.twins.digital_twin.align import (
        register_translation,  # lazy: twinfocus.twins.digital_twin.align (+0.03 s on twinfocus rig --help)
    )
    from twinfocus.twins.digital_twin.condition import (
        digital_twin_reference,  # lazy: open3d, scipy.ndimage (+4.3 s at import)
    )

    points = np.asarray(points_m, dtype=np.float64)
    grid = measuring_grid(grid)
    ref = digital_twin_reference(points, scan.positions, scan.chirp, grid, **bp_options)
    support = ref.support
    _, resolution = _resolution_px(scan, grid)
    if support.sum() < MIN_SUPPORT_PIXELS or _extent_cells(support, grid, resolution) < MIN_EXTENT_CELLS:
        raise TwinFocusError(
            f"the object is too small to measure the rig on: its outline covers {int(support.sum())} pixels and "
            f"{_extent_cells(support, grid, resolution):.1f} resolution cells ({resolution * 1e3:.1f} mm) across "
            f"(at least {MIN_SUPPORT_PIXELS} and {MIN_EXTENT_CELLS} needed); use a larger object"
        )
    basis = subimage_basis(scan.data, scan.positions, scan.chirp, grid, **bp_options)
    image = np.abs(basis.sum(axis=0))
    template = np.asarray(ref.template, np.float64)
    # a few rounds: each registers the residual once the template sits where the last put it (the
    # parabola's sub-pixel part is biased towards whole pixels; this takes most of it out)
    dy = dx = 0.0
    for _ in range(REGISTRATION_ROUNDS):
        ry, rx, match = register_translation(shift_image(template, dy, dx), image)
        dy, dx = dy + ry, dx + rx
    if match < MIN_MATCH:
        raise TwinFocusError(
            f"the cloud and the radar image disagree in shape (match {match:.2f} < {MIN_MATCH}): check that the cloud "
            "shows the object in --reference-roi and that the scan's positions are accurate"
        )
    spread = rig_spread(scan, points, grid, basis, template, (dy, dx), bootstrap=bootstrap, cloud_draws=cloud_draws,
                        rng=rng, **bp_options)  # fmt: skip
    sd_px, measured = np.asarray(spread["sd_px"]), np.asarray(spread["measured_px"])
    # the model's part is the same on every scan of this aperture: refusing for it would refuse all
    if np.any(measured > max_sd_px):
        raise TwinFocusError(
            f"the offset is not measured surely enough: its spread is {measured[0]:.2f}, {measured[1]:.2f} px "
            f"(> {max_sd_px}; "
            f"of it the positions' {spread['positions_px'][0]:.2f}, {spread['positions_px'][1]:.2f}, the image's cells' "
            f"{spread['cells_px'][0]:.2f}, {spread['cells_px'][1]:.2f}, the cloud's {spread['cloud_px'][0]:.2f}, "
            f"{spread['cloud_px'][1]:.2f}); {_advice(spread)}"
        )
    source = _depth_record(scan, grid, ref, bp_options) if depth else {"z": "not measured"}
    sy, sx = grid.spacing_m
    offset = np.array([dx * sx, dy * sy, 0.0])
    sd = np.array([sd_px[1] * sx, sd_px[0] * sy, 0.0])
    source.update({"shift_px": [dy, dx], "sd_px": sd_px.tolist(), "sd": spread, "match": match,
                   "grid_roi": list(grid.roi), "grid_shape": list(grid.shape), "bootstrap": int(bootstrap),
                   "support_pixels": int(support.sum())})  # fmt: skip
    rig = Rig(offset, sd, board, camera, time.time_ns(), source)
    after = shift_image(support.astype(np.float32), dy, dx) > 0.5
    return RigMeasurement(rig, (dy, dx), (float(sd_px[0]), float(sd_px[1])), match, image, support, after)


def _advice(spread: dict) -> str:
    """What to change when the spread is too large: the largest of its three parts says."""
    parts = {k: max(spread[k]) for k in ("positions_px", "cells_px", "cloud_px")}
    return {
        "positions_px": "scan with more positions or a brighter object",
        "cells_px": "use an object with a smoother surface and sharper corners (a letter cut from sheet metal)",
        "cloud_px": "record the camera's cloud so that it shows the whole object (closer, better lit, from more views)",
    }[max(parts, key=parts.get)]  # type: ignore[arg-type]


def _depth_record(scan, grid: ImageGrid, ref, bp_options: dict) -> dict:
    """The radar's depth of the reference (where its image is sharpest,
    :func:`twinfocus.imaging.depth_search.search_depth`) against the cloud's median depth: the rig
    file's ``source`` keys for z, which is recorded but not applied."""
    from twinfocus.imaging.depth_search import (
        search_depth,  # lazy: twinfocus.imaging.depth_search (+0.03 s on twinfocus twin --help)
    )

    z0 = grid.z
    search = search_depth(scan.data, scan.positions, scan.chirp, tuple(grid.roi[:4]),
                          (z0 - DEPTH_HALF_RANGE_M, z0 + DEPTH_HALF_RANGE_M), np.zeros(scan.n_positions),
                          size=min(48, *grid.shape), bp_options=bp_options)  # fmt: skip
    fine_step = float(search.fine_z_m[1] - search.fine_z_m[0]) if search.fine_z_m.size > 1 else 0.0
    # z is not applied: the sharpest plane's depth missed injected mm offsets by 2-4 mm on the rig
    # bench (the radar's focus resolves centimetres along z, not millimetres), and a wrong z costs
    # more than the camera's own; it is recorded (source.depth_offset_m) for the user to judge
    return {"radar_depth_m": search.depth_m, "depth_offset_m": float(search.depth_m - np.median(ref.cloud.points_m[:, 2])),
            "depth_step_m": fine_step, "z": "not measured (depth_offset_m: the radar's focus)"}  # fmt: skip


def overlay_picture(image: np.ndarray, before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """uint8 (H, 2W+4, 3) BGR: the radar image (grey, dB over 30 dB) with the outline's edge in
    red before and in green after the offset, side by side."""
    from scipy.ndimage import binary_erosion

    a = np.abs(image).astype(np.float64)
    db = 20 * np.log10(np.maximum(a / max(a.max(), 1e-30), 1e-12))
    grey = (np.clip((db + 30.0) / 30.0, 0, 1) * 255).astype(np.uint8)

    def panel(mask: np.ndarray, colour: tuple[int, int, int]) -> np.ndarray:
        p = np.repeat(grey[:, :, None], 3, axis=2)
        edge = mask & ~binary_erosion(mask)
        p[edge] = colour
        return p[::-1]  # y up

    gap = np.zeros((grey.shape[0], 4, 3), np.uint8)
    return np.concatenate([panel(before, (0, 0, 255)), gap, panel(after, (0, 255, 0))], axis=1)


def rig_reference(points_m: np.ndarray, scan, grid: ImageGrid, rig: Rig, **bp_options):
    """The camera's cloud ``points_m`` (float (N, 3), scene frame, metres, as it comes) moved by
    the rig's offset, then conditioned as without one
    (:func:`twinfocus.twins.digital_twin.condition.digital_twin_reference`); its info's ``rig`` records
    the offset applied and its sd (metres), and tells the focus to place the reference on the
    calibrated outline (:func:`rig_placed`)."""
    from twinfocus.twins.digital_twin.condition import (
        digital_twin_reference,  # lazy: open3d, scipy.ndimage (+4.3 s at import)
    )

    ref = digital_twin_reference(points_m, scan.positions, scan.chirp, grid, offset_m=rig.offset_m, **bp_options)
    ref.info["rig"] = {"reference_moved_m": rig.offset_m.tolist(), "sd_m": rig.sd_m.tolist()}
    return ref


def rig_reference_from_file(cloud_path: str | os.PathLike, scan, grid: ImageGrid, rig: Rig, **bp_options):
    """``focus --digital-twin CLOUD --rig RIG``: :func:`rig_reference` of the cloud in the file."""
    points = load_points(cloud_path, allow_non_finite=True)
    try:
        return rig_reference(points, scan, grid, rig, **bp_options)
    except TwinFocusError as exc:
        raise TwinFocusError(f"{cloud_path}: {exc}") from None
