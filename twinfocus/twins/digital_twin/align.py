"""Radar-camera alignment of the digital twin's template (source paper, section 4.3, step 3).

The template is simulated where the camera put the reference; the radar sees it where it really
is. The difference -- mounting (extrinsic) error, stereo depth bias, the phase-centre model -- is
a nearly constant translation, so:

* **One-time calibration** (:func:`calibrate_offset`): register the simulated template against a
  *focused* radar image of the same reference (a scan on accurate positions, e.g. a motion-stage
  capture) and store the translation, in metres in the scene frame, as a
  :class:`RadarCameraCalibration` JSON file. Later templates add it to the points.
* **Per-scan refinement** (:func:`refine_template_shift`): register the template against the
  scan's own (defocused) reference image, with a bounded shift, and move the template by the
  sub-pixel result, so a residual offset does not bias SSIM.

Registration (:func:`register_translation`) is normalised cross-correlation of the two amplitude
images with a sub-pixel parabolic peak.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.subpixel import parabola_vertex, shift_image
from twinfocus.io.documents import read_json, write_json_document


def register_translation(moving: np.ndarray, fixed: np.ndarray) -> tuple[float, float, float]:
    """Sub-pixel shift (dy, dx) that moves ``moving`` onto ``fixed``, and the normalised
    correlation at that shift (-1..1, how much to trust it).

    ``shift_image(moving, dy, dx)`` then lines up with ``fixed``. Both are real (H, W) images of
    one size (complex inputs are taken in magnitude). Plain (not phase-whitened) cross-correlation
    of the mean-removed, max-normalised amplitudes, zero-padded so nothing wraps, with a parabola
    through the peak and its neighbours on each axis for the sub-pixel part: it stays robust when
    ``fixed`` is speckled or defocused.
    """
    a = np.abs(np.asarray(moving)).astype(np.float64)
    b = np.abs(np.asarray(fixed)).astype(np.float64)
    if a.shape != b.shape or a.ndim != 2:
        raise TwinFocusError(f"images to register must be 2-D and of one size, got {a.shape} and {b.shape}")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise TwinFocusError("images to register hold NaN or inf")
    if a.max() <= 0 or b.max() <= 0:
        raise TwinFocusError("cannot register an empty (all-zero) image")
    a = a / a.max() - (a / a.max()).mean()
    b = b / b.max() - (b / b.max()).mean()
    h, w = a.shape
    shape = (2 * h, 2 * w)
    xc = np.fft.irfft2(np.fft.rfft2(b, shape) * np.conj(np.fft.rfft2(a, shape)), shape)
    i, j = np.unravel_index(int(np.argmax(xc)), xc.shape)

    fy = parabola_vertex(xc[(i - 1) % shape[0], j], xc[i, j], xc[(i + 1) % shape[0], j])
    fx = parabola_vertex(xc[i, (j - 1) % shape[1]], xc[i, j], xc[i, (j + 1) % shape[1]])
    dy = (i if i < h else i - shape[0]) + fy
    dx = (j if j < w else j - shape[1]) + fx
    norm = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float(dy), float(dx), float(xc[i, j] / norm) if norm > 0 else 0.0


def pixels_to_metres(grid: ImageGrid, dy: float, dx: float) -> np.ndarray:
    """A pixel shift on ``grid`` as a scene-frame translation (x, y, 0) in metres."""
    sy, sx = grid.spacing_m
    return np.array([dx * sx, dy * sy, 0.0])


@dataclass
class RadarCameraCalibration:
    """Translation (metres, scene frame) to add to camera-derived points so their simulated
    image lands where the radar sees the object."""

    offset_m: np.ndarray
    created_ns: int = 0
    source: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        off = np.asarray(self.offset_m, dtype=np.float64).reshape(-1)
        if off.shape != (3,) or not np.isfinite(off).all():
            raise TwinFocusError(f"calibration offset must be 3 finite numbers (metres), got {self.offset_m!r}")
        self.offset_m = off

    def to_dict(self) -> dict:
        return {
            "kind": "twinfocus-radar-camera-offset",
            "offset_m": self.offset_m.tolist(),
            "created_ns": int(self.created_ns),
            "source": self.source,
        }

    def save(self, path: str | os.PathLike) -> Path:
        return write_json_document(path, self.to_dict())

    @classmethod
    def load(cls, path: str | os.PathLike) -> RadarCameraCalibration:
        path = Path(path)
        if not path.is_file():
            raise TwinFocusError(
                f"{path}: no such radar-camera calibration file (make one with twinfocus twin --calibrate-scan)"
            )
        try:
            d = read_json(path)
            return cls(
                np.asarray(d["offset_m"], dtype=np.float64), int(d.get("created_ns", 0)), dict(d.get("source", {}))
            )
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise TwinFocusError(f"{path}: not a radar-camera calibration file ({exc})") from None
        except TwinFocusError as exc:
            raise TwinFocusError(f"{path}: {exc}") from None


def calibrate_offset(
    template: np.ndarray, focused_reference: np.ndarray, grid: ImageGrid, min_response: float = 0.05
) -> RadarCameraCalibration:
    """One-time calibration: the translation that moves the simulated ``template`` onto the
    ``focused_reference`` radar image (both on ``grid``).

    Raises :class:`TwinFocusError` if the two images do not correlate (wrong region, no object).
    """
    dy, dx, resp = register_translation(template, focused_reference)
    if resp < min_response:
        raise TwinFocusError(
            f"the simulated template and the radar image do not correlate (peak response {resp:.3f}); "
            "check that both show the reference in the same region"
        )
    return RadarCameraCalibration(
        pixels_to_metres(grid, dy, dx),
        time.time_ns(),
        {"shift_px": [dy, dx], "response": resp, "grid_roi": list(grid.roi), "grid_shape": list(grid.shape)},
    )


def refine_template_shift(
    template: np.ndarray, measured_reference: np.ndarray, max_shift_px: float = 3.0, min_response: float = 0.05
) -> tuple[np.ndarray, tuple[float, float]]:
    """Per-scan refinement: move ``template`` onto the scan's own reference image.

    The measured image is defocused, so only a small residual shift is trusted: a shift longer
    than ``max_shift_px`` or a weak correlation leaves the template unchanged.
    Returns (template float32 (H, W), (dy, dx) applied).
    """
    dy, dx, resp = register_translation(template, measured_reference)
    if resp < min_response or np.hypot(dy, dx) > max_shift_px:
        return np.asarray(template, np.float32), (0.0, 0.0)
    return shift_image(np.asarray(template, np.float32), dy, dx), (dy, dx)


def _parabola_vertex(lm: float, l0: float, lp: float, step: float) -> float:
    """Abscissa of the minimum of the parabola through (-step, lm), (0, l0), (step, lp), kept
    within +-step (the stencil says nothing beyond it)."""
    den = lm - 2.0 * l0 + lp
    if den <= 0:  # no interior minimum: go to the lower side
        return -step if lm < lp else (step if lp < lm else 0.0)
    return step * parabola_vertex(lm, l0, lp, limit=1.0)


def refine_template_shift_by_loss(
    basis: np.ndarray, template: np.ndarray, config=None, step_px: float = 1.0, iterations: int = 60, progress=None
) -> tuple[np.ndarray, tuple[float, float], dict]:
    """Per-scan sub-pixel registration of the template, measured with the autofocus's own loss.

    Registering the template against the scan's defocused reference image is biased (motion
    errors displace the blurred image, measured ~1 px on the paper scene), and after autofocus the
    optimiser has already pulled the image onto the template. The loss reached by a short
    autofocus run, however, is lowest when the template sits where the object is (a 1 px offset
    raised the 80-iteration loss by 0.001-0.007 and cost 0.04-0.08 target SSIM). So: short runs
    (``iterations``) with the template shifted by 0 and +-``step_px`` along each axis, a parabola
    per axis through the three final losses, and the template moved to the vertex.

    basis : complex (M, H, W) reference sub-image basis; template : float (H, W).
    Returns (shifted template float32 (H, W), (dy, dx) pixels, {"losses": ...}).
    """
    from dataclasses import replace

    from twinfocus.focus.autofocus import AutofocusConfig, twin_autofocus  # lazy: scipy.fft (+0.8 s at import)

    cfg = replace(config or AutofocusConfig(), iterations=int(iterations))
    tpl = np.asarray(template, np.float32)
    cache: dict[tuple[float, float], float] = {}

    def loss(dy: float, dx: float) -> float:
        key = (round(dy, 6), round(dx, 6))
        if key not in cache:
            res = twin_autofocus(basis, shift_image(tpl, dy, dx), cfg)
            cache[key] = float(res.loss_history[-5:].mean())
            if progress is not None:
                progress(len(cache), 5)
        return cache[key]

    s = float(step_px)
    l0 = loss(0.0, 0.0)
    dy = _parabola_vertex(loss(-s, 0.0), l0, loss(s, 0.0), s)
    dx = _parabola_vertex(loss(0.0, -s), l0, loss(0.0, s), s)
    info = {"losses": {f"{k[0]:+g},{k[1]:+g}": v for k, v in cache.items()}, "shift_px": [dy, dx]}
    if dy == 0.0 and dx == 0.0:
        return tpl, (0.0, 0.0), info
    return shift_image(tpl, dy, dx), (dy, dx), info
