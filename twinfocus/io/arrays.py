"""Array files: ``.npz`` archives (the scan file, the template cache, a render's truth), ``.npy``
point clouds, PLY point clouds (what MeshLab, CloudCompare and Open3D open).

Readers give plain arrays with one :class:`~twinfocus.errors.TwinFocusError` line naming the file
for a missing, truncated or damaged one; writers go through a temporary file and a rename
(:mod:`twinfocus.io.atomic`), so a crash never leaves half a file.
"""

from __future__ import annotations

import io
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.io.atomic import atomic_writer, write_bytes_atomic


def load_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Load every array of an ``.npz`` file into a dict, with a clear error for a bad file."""
    path = Path(path)
    if not path.is_file():
        raise TwinFocusError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    # A truncated or damaged archive fails inside zipfile/zlib, not with an OSError.
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise TwinFocusError(f"{path}: not a readable .npz file, truncated or damaged? ({exc})") from None


def peek_npz_shapes(path: str | os.PathLike) -> dict[str, tuple[int, ...]]:
    """Shapes of the arrays of an ``.npz`` file from their headers alone (milliseconds, whatever
    the file's size): lets a command check sizes and memory before loading anything. A truncated
    file (its zip directory sits at the end) fails here with one line."""
    path = Path(path)
    if not path.is_file():
        raise TwinFocusError(f"{path}: no such file")
    try:
        shapes = {}
        with zipfile.ZipFile(path) as zf:
            for name in zf.namelist():
                if not name.endswith(".npy"):
                    continue
                with zf.open(name) as f:
                    version = np.lib.format.read_magic(f)
                    read = (
                        np.lib.format.read_array_header_1_0
                        if version == (1, 0)
                        else np.lib.format.read_array_header_2_0
                    )
                    shape, _, _ = read(f)
                shapes[name[:-4]] = tuple(shape)
        return shapes
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise TwinFocusError(f"{path}: not a readable .npz file, truncated or damaged? ({exc})") from None


def save_npz_atomic(path: str | os.PathLike, arrays: dict[str, np.ndarray]) -> Path:
    """Write ``arrays`` to ``path`` through a temporary file and a rename."""
    with atomic_writer(path) as f:
        np.savez(f, **arrays)  # type: ignore[arg-type]  # numpy stubs type **kwds as the flag
    return Path(path)


def save_npy_atomic(path: str | os.PathLike, array: np.ndarray) -> Path:
    """Write one array as ``.npy`` through a temporary file and a rename."""
    buf = io.BytesIO()
    np.save(buf, np.asarray(array))
    return write_bytes_atomic(path, buf.getvalue())


def load_npy(path: str | os.PathLike) -> np.ndarray:
    """Read one ``.npy`` array (no pickles). Raises OSError or ValueError as :func:`numpy.load`
    does, for the caller to name what the file should have been."""
    return np.load(path, allow_pickle=False)


def ply_bytes(points_m: np.ndarray, values: np.ndarray) -> bytes:
    """A binary little-endian PLY point cloud (what MeshLab, CloudCompare and Open3D open): float
    x y z (metres) and an ``intensity`` per point, with grey-level red/green/blue from it.

    points_m : float (P, 3); values : float (P,) in [0, 1]."""
    pts = np.asarray(points_m, np.float32).reshape(-1, 3)
    vals = np.asarray(values, np.float32).reshape(-1)
    if vals.shape[0] != pts.shape[0]:
        raise TwinFocusError(f"{pts.shape[0]} points but {vals.shape[0]} values")
    grey = np.clip(np.round(255 * vals), 0, 255).astype(np.uint8)
    rec = np.empty(
        pts.shape[0],
        dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")],
    )
    rec["x"], rec["y"], rec["z"], rec["intensity"] = pts[:, 0], pts[:, 1], pts[:, 2], vals
    rec["r"] = rec["g"] = rec["b"] = grey
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {pts.shape[0]}\n"
        "property float x\nproperty float y\nproperty float z\nproperty float intensity\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    return header.encode("ascii") + rec.tobytes()


def read_ply_points(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read back what :func:`ply_bytes` writes: (points float32 (P, 3), intensity float32 (P,))."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    n = int(next(ln for ln in raw[:end].decode("ascii").splitlines() if ln.startswith("element vertex")).split()[2])
    rec = np.frombuffer(
        raw[end:],
        dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")],
        count=n,
    )
    return np.stack([rec["x"], rec["y"], rec["z"]], axis=1), rec["intensity"].copy()
