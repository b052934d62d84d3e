"""The depth of a target from the scan itself: the plane where its corrected image is sharpest.

A region typed as an x/y box without its depth (or with a range of depths) is imaged with the
correction at a ladder of depths (:func:`twinfocus.imaging.volume.corrected_image`: the twin's phase
applies at every depth). Each plane is scored by sum |I|^4 over its pixels, which grows both with
the energy the target returns there and with how tightly the image gathers it (a defocused image
spreads the same energy over more pixels, and the fourth power prefers the concentrated one).

Coarse to fine: planes half a range resolution apart over the range, then planes a fifth of that
apart around the best, and a parabola through the best fine plane and its two neighbours.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.grid import ImageGrid, VolumeGrid
from twinfocus.radar.fmcw import Chirp

#: a search without a typed depth covers the reference's depth +- this, metres
DEFAULT_HALF_RANGE_M = 0.25
#: coarse planes this many range resolutions apart (the depth response of a focused point is about
#: one range resolution wide, so two samples per width cannot step over it)
COARSE_STEP_RESOLUTIONS = 0.5
#: fine planes: this many per coarse step, over +- one coarse step around the best coarse plane
FINE_PER_COARSE = 5


@dataclass
class DepthSearch:
    """What :func:`search_depth` found: ``depth_m`` and the curves behind it (metres, scores
    normalised to the best plane's)."""

    depth_m: float
    coarse_z_m: np.ndarray
    coarse_score: np.ndarray
    fine_z_m: np.ndarray
    fine_score: np.ndarray
    #: the best coarse plane's score over the coarse curve's median: how clearly the target stands out
    contrast: float
    at_edge: bool
    seconds: float

    def to_dict(self) -> dict:
        return {
            "depth_m": float(self.depth_m),
            "searched_m": [float(self.coarse_z_m[0]), float(self.coarse_z_m[-1])],
            "contrast": float(self.contrast),
            "at_edge_of_range": bool(self.at_edge),
            "coarse": {"z_m": self.coarse_z_m.tolist(), "score": self.coarse_score.tolist()},
            "fine": {"z_m": self.fine_z_m.tolist(), "score": self.fine_score.tolist()},
            "seconds": float(self.seconds),
        }


def sharpness_score(images: np.ndarray) -> np.ndarray:
    """sum |I|^4 over each plane: float64 (D,) from complex (D, H, W) (or (H, W) -> shape ())."""
    mag2 = np.abs(np.asarray(images)).astype(np.float64) ** 2
    return (mag2**2).sum(axis=(-2, -1))


def parse_depth(text: str) -> tuple[float, float] | float:
    """The depth field of a region typed on the command line: ``"Z"`` -> Z, ``"Z0:Z1"`` -> (Z0, Z1)
    (metres; Z0 < Z1, both positive)."""
    try:
        if ":" in text:
            a, b = (float(v) for v in text.split(":"))
            if not (np.isfinite([a, b]).all() and 0 < a < b):
                raise ValueError
            return (a, b)
        z = float(text)
    except ValueError:
        raise TwinFocusError(f"a depth must be Z or a range Z0:Z1 with 0 < Z0 < Z1 (metres), got {text!r}") from None
    if not (np.isfinite(z) and z > 0):
        raise TwinFocusError(f"a depth must be positive (metres), got {text!r}")
    return z


def _planes(box: Sequence[float], zs: np.ndarray, size: int) -> VolumeGrid:
    plane = ImageGrid.from_roi((*box, float(zs[0])), size)
    return VolumeGrid(plane, float(zs[0]), float(zs[-1]), len(zs))


def search_depth(
    data: np.ndarray,
    positions_m: np.ndarray,
    chirp: Chirp,
    box: Sequence[float],
    z_range_m: tuple[float, float],
    phase_rad: np.ndarray,
    *,
    size: int = 32,
    bp_options: dict | None = None,
    progress_factory=None,
) -> DepthSearch:
    """Search ``z_range_m`` for the depth at which the corrected image of the x/y ``box`` is
    sharpest (module docstring).

    data : complex (M, K, N) samples; positions_m : float64 (M, K, 3) phase centres, metres;
    box : (X0, X1, Y0, Y1) metres; z_range_m : (Z0, Z1) metres; phase_rad : float (M,) the
    correction (zeros for none); size : pixels per side of the planes searched; bp_options :
    keywords of :func:`twinfocus.imaging.backprojection.numba_backend.backproject_points`."""
    import time

    from twinfocus.imaging.volume import corrected_image  # lazy: numba (+2.1 s at import), only when a search runs

    t = time.perf_counter()
    z0, z1 = (float(v) for v in z_range_m)
    if not (np.isfinite([z0, z1]).all() and 0 < z0 < z1):
        raise TwinFocusError(f"depth range needs 0 < Z0 < Z1 (metres), got {z0}:{z1}")
    if len(box) != 4:
        raise TwinFocusError(f"a depth search needs an x/y box X0 X1 Y0 Y1, got {len(box)} numbers")
    bp = dict(bp_options or {})
    prog = progress_factory or (lambda label: None)
    step = COARSE_STEP_RESOLUTIONS * chirp.range_resolution_m
    coarse_z = np.linspace(z0, z1, max(3, int(np.ceil((z1 - z0) / step)) + 1))
    coarse = sharpness_score(
        corrected_image(
            data, positions_m, chirp, _planes(box, coarse_z, size), phase_rad, progress=prog("depth search"), **bp
        )
    )
    k = int(np.argmax(coarse))
    dz = coarse_z[1] - coarse_z[0]
    fine_z = np.linspace(coarse_z[k] - dz, coarse_z[k] + dz, 2 * FINE_PER_COARSE + 1)
    fine_z = fine_z[(fine_z >= z0 - 1e-12) & (fine_z <= z1 + 1e-12)]
    fine = sharpness_score(
        corrected_image(
            data, positions_m, chirp, _planes(box, fine_z, size), phase_rad, progress=prog("depth refine"), **bp
        )
    )
    f = int(np.argmax(fine))
    depth = float(fine_z[f])
    if 0 < f < len(fine) - 1:
        # vertex of the parabola through the best plane and its neighbours (equal spacing h)
        a, b, c = fine[f - 1], fine[f], fine[f + 1]
        denom = a - 2 * b + c
        if denom < 0:
            depth += float(0.5 * (a - c) / denom * (fine_z[1] - fine_z[0]))
    peak = max(float(coarse.max()), float(fine.max()), 1e-300)
    return DepthSearch(
        depth_m=depth,
        coarse_z_m=coarse_z,
        coarse_score=coarse / peak,
        fine_z_m=fine_z,
        fine_score=fine / peak,
        contrast=float(coarse[k] / max(float(np.median(coarse)), 1e-300)),
        at_edge=k in (0, len(coarse_z) - 1),
        seconds=time.perf_counter() - t,
    )


def default_range(reference_depth_m: float) -> tuple[float, float]:
    """The depths searched when none is typed: the reference's +- :data:`DEFAULT_HALF_RANGE_M`
    (kept in front of the aperture)."""
    return (max(0.05, reference_depth_m - DEFAULT_HALF_RANGE_M), reference_depth_m + DEFAULT_HALF_RANGE_M)


def range_to_search(
    typed: float | tuple[float, float] | None, refine_m: float | None, reference_depth_m: float
) -> tuple[float, float] | None:
    """The depths to search for the target (metres): the typed range, Z +- ``refine_m``, the
    default range around the reference (:func:`default_range`) when no depth was typed; None for
    a typed Z to be trusted."""
    if typed is None:
        return default_range(reference_depth_m)
    if isinstance(typed, tuple):
        return typed
    if refine_m is not None:
        return (max(0.01, typed - refine_m), typed + refine_m)
    return None


def find_target_depth(
    focus: Callable,
    scan,
    box: Sequence[float],
    depth_range: tuple[float, float],
    method: str,
    bp_options: dict,
    progress_factory=None,
) -> tuple[DepthSearch, dict]:
    """The target's depth from the scan: the phase from the reference first (its scalar estimate,
    on a 2 x 2 target region at the range's middle: the target's own images are not needed yet),
    then :func:`search_depth` with it. What ``twinfocus focus`` and the solver node both run.

    focus : ``focus(scan, target_grid=, space_variant=)`` returning outputs with ``phase_rad``
    (:meth:`twinfocus.focus.plan.FocusPlan.focus_scan` with the reference bound); scan :
    :class:`twinfocus.radar.scan.Scan`; box : (X0, X1, Y0, Y1) metres; method : ``twin`` or a
    reference-free one (then the uncorrected scan is searched). Returns (the search, {"range_m",
    "phase": what phase it used})."""
    if method == "twin":
        probe = ImageGrid.from_roi((*box, float(np.mean(depth_range))), 2)
        blind = dataclasses.replace(scan, positions_true=None)  # no truth images for the probe
        phase = focus(blind, target_grid=probe, space_variant="off").phase_rad
        used = "the twin's estimate (one phase per position, before any space-variant step)"
    else:
        # the sharpness estimate needs the target's own region; search the uncorrected scan
        phase = np.zeros(scan.n_positions)
        used = "none (uncorrected)"
    search = search_depth(
        scan.data,
        scan.positions,
        scan.chirp,
        box,
        depth_range,
        phase,
        bp_options=bp_options,
        progress_factory=progress_factory,
    )
    return search, {"range_m": list(depth_range), "phase": used}
