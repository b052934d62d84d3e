"""Cut-out letters: a character rasterised from OpenCV's Hershey fonts to a boolean mask with a
uniform stroke, and the planar object made of it."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.scene.checks import positive
from twinfocus.scene.objects import PlanarObject

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
    height_m = positive("height_m", height_m)
    pixel_m = positive("pixel_m", pixel_m)
    width_scale = positive("width_scale", width_scale)
    stroke_m = 0.1 * height_m if stroke_m is None else positive("stroke_m", stroke_m)
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


@dataclass(frozen=True)
class LetterStyle:
    """How :func:`letter` draws: ``font`` (a Hershey font name), ``stroke_m`` (stroke width,
    metres; None: the font's own for the height) and ``width_scale`` (width over height)."""

    font: str | int = "simplex"
    stroke_m: float | None = None
    width_scale: float = 0.65


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
    height_m = positive("height_m", height_m)
    pixel_m = height_m / 400.0 if pixel_m is None else positive("pixel_m", pixel_m)
    mask = letter_mask(char, height_m, pixel_m, font, stroke_m, width_scale)
    return PlanarObject(mask, pixel_m, centre_m, rotation, material, colour_bgr, None, name or f"letter_{char}")
