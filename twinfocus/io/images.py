"""Picture files through OpenCV (imported on first use): any format its suffix names."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.io.atomic import write_bytes_atomic


def write_image_atomic(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Encode an image (format from the suffix) and write it through a temp file and a rename."""
    import cv2

    path = Path(path)
    ok, buf = cv2.imencode(path.suffix or ".png", np.asarray(image))
    if not ok:
        raise TwinFocusError(f"{path}: could not encode the image")
    return write_bytes_atomic(path, buf.tobytes())


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read a colour picture as uint8 BGR (H, W, 3), with an error naming the file."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise TwinFocusError(f"{path}: no such image file")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise TwinFocusError(f"{path}: not a readable image")
    return img
