"""Image grids: a region of interest on a plane at depth Z, or a 3-D volume.

Pixel [i, j] of an :class:`ImageGrid` sits at x = linspace(X0, X1, W)[j],
y = linspace(Y0, Y1, H)[i], z = Z (docs/architecture.md section 4).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from twinfocus.errors import TwinFocusError


@dataclass(frozen=True)
class ImageGrid:
    """A 2-D grid of H x W pixels on the plane z = ``z`` (metres)."""

    x0: float
    x1: float
    y0: float
    y1: float
    z: float
    height: int
    width: int

    def __post_init__(self) -> None:
        vals = (self.x0, self.x1, self.y0, self.y1, self.z)
        if not all(np.isfinite(v) for v in vals):
            raise TwinFocusError(f"region of interest must be finite numbers, got {vals}")
        if not self.x1 > self.x0 or not self.y1 > self.y0:
            raise TwinFocusError(
                f"region of interest needs X0 < X1 and Y0 < Y1, got x [{self.x0}, {self.x1}] y [{self.y0}, {self.y1}]"
            )
        if not self.z > 0:
            raise TwinFocusError(f"region of interest depth Z must be positive (into the scene), got {self.z}")
        if int(self.height) < 2 or int(self.width) < 2:
            raise TwinFocusError(f"image size must be at least 2 x 2, got {self.height} x {self.width}")

    @classmethod
    def from_roi(cls, roi: Sequence[float], size: int | tuple[int, int]) -> ImageGrid:
        """From ``(X0, X1, Y0, Y1, Z)`` and a size (``n`` for n x n, or ``(H, W)``)."""
        roi = tuple(float(v) for v in roi)
        if len(roi) != 5:
            raise TwinFocusError(f"region of interest needs 5 numbers X0 X1 Y0 Y1 Z, got {len(roi)}")
        h, w = (size, size) if np.isscalar(size) else size  # type: ignore[misc]
        return cls(*roi, height=int(h), width=int(w))  # type: ignore[arg-type]

    def every(self, rows: int, columns: int) -> ImageGrid:
        """The grid of every ``rows``-th pixel along y and every ``columns``-th along x, from the
        first: its pixels are this grid's ``[::rows, ::columns]`` (the same points, so an image
        formed on it is that slice of one formed on this grid)."""
        ky, kx = int(rows), int(columns)
        if ky < 1 or kx < 1 or (ky, kx) != (rows, columns):
            raise TwinFocusError(f"strides must be positive whole numbers, got {rows!r} x {columns!r}")
        h, w = (self.height - 1) // ky + 1, (self.width - 1) // kx + 1
        if h < 2 or w < 2:
            raise TwinFocusError(f"every {ky} x {kx} pixels of {self.height} x {self.width} leave {h} x {w}: too few")
        # the last pixel kept: this grid's own end where the stride reaches it (no round-off)
        x1 = (
            self.x1
            if (w - 1) * kx == self.width - 1
            else self.x0 + (w - 1) * kx * (self.x1 - self.x0) / (self.width - 1)
        )
        y1 = (
            self.y1
            if (h - 1) * ky == self.height - 1
            else self.y0 + (h - 1) * ky * (self.y1 - self.y0) / (self.height - 1)
        )
        return replace(self, x1=x1, y1=y1, height=h, width=w)

    @property
    def roi(self) -> tuple[float, float, float, float, float]:
        return (self.x0, self.x1, self.y0, self.y1, self.z)

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.height), int(self.width))

    @property
    def x_m(self) -> np.ndarray:
        return np.linspace(self.x0, self.x1, int(self.width))

    @property
    def y_m(self) -> np.ndarray:
        return np.linspace(self.y0, self.y1, int(self.height))

    @property
    def spacing_m(self) -> tuple[float, float]:
        """(dy, dx) pixel spacing in metres."""
        return ((self.y1 - self.y0) / (self.height - 1), (self.x1 - self.x0) / (self.width - 1))

    @property
    def centre_m(self) -> np.ndarray:
        return np.array([(self.x0 + self.x1) / 2, (self.y0 + self.y1) / 2, self.z])

    def points(self) -> np.ndarray:
        """Pixel positions, float64 (H*W, 3), row-major (i over y, j over x)."""
        yy, xx = np.meshgrid(self.y_m, self.x_m, indexing="ij")
        return np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, float(self.z))], axis=1)

    def index_of(self, x, y):
        """Fractional (row, column) of scene point(s) (x, y), metres: floats or arrays alike."""
        dy, dx = self.spacing_m
        return ((y - self.y0) / dy, (x - self.x0) / dx)


@dataclass(frozen=True)
class VolumeGrid:
    """A 3-D grid of D x H x W voxels: an :class:`ImageGrid` repeated over depths z0..z1."""

    plane: ImageGrid
    z0: float
    z1: float
    depth: int

    def __post_init__(self) -> None:
        if int(self.depth) < 1 or not (self.z1 >= self.z0 > 0):
            raise TwinFocusError(
                f"volume needs 0 < z0 <= z1 and depth >= 1, got z [{self.z0}, {self.z1}] x {self.depth}"
            )

    @property
    def shape(self) -> tuple[int, int, int]:
        return (int(self.depth), *self.plane.shape)

    @property
    def z_m(self) -> np.ndarray:
        return np.linspace(self.z0, self.z1, int(self.depth))

    def points(self) -> np.ndarray:
        """Voxel positions, float64 (D*H*W, 3), depth-major."""
        p = self.plane.points()
        out = np.repeat(p[None], int(self.depth), axis=0)
        out[:, :, 2] = self.z_m[:, None]
        return out.reshape(-1, 3)
