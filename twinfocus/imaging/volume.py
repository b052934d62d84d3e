"""Corrected images anywhere in the scene: planes at any depth and 3-D volumes.

The correction is one phase per radar position (docs/architecture.md section 1). A sub-image
B_m is linear in position m's samples, so sum_m exp(j phi_m) B_m (:func:`twinfocus.imaging.basis.form_image`)
equals the back-projection of the samples multiplied by exp(j phi_m) first: the corrected image
of any grid, a plane at another depth or a volume, costs one back-projection and no basis
(M x pixels complex64) in memory.
"""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.imaging import line_backprojection
from twinfocus.imaging.backprojection.numba_backend import backproject
from twinfocus.imaging.grid import ImageGrid, VolumeGrid
from twinfocus.imaging.line_backprojection import TABLE_BYTES
from twinfocus.radar.fmcw import Chirp

#: bytes per voxel that :func:`corrected_image` holds at its peak on a volume: the voxel positions
#: (float64, 24 B, and their float32 copies in the local frame, 12 B), the float32 accumulators and
#: the chunk's partial sums (16 B) and the complex64 result (8 B)
BYTES_PER_VOXEL = 64
#: CPU back-projection cost, seconds per voxel, radar position and channel: 1.1e-8 measured on the
#: 2-core machine under a load average of ~20 (docs/howto/find_depth_and_volume.md); an idle core
#: pair does it 2-4 times faster
SECONDS_PER_VOXEL_CHANNEL = 1.1e-8


def corrected_data(data: np.ndarray, phase_rad: np.ndarray) -> np.ndarray:
    """The scan's samples with the correction applied: complex64 (M, K, N) = data_mkn exp(j phi_m).

    data : complex (M, K, N); phase_rad : float (M,) radians, one per radar position."""
    data = np.asarray(data)
    phase_rad = np.asarray(phase_rad, dtype=np.float64)
    if data.ndim != 3 or phase_rad.shape != (data.shape[0],):
        raise TwinFocusError(
            f"phase must have one value per radar position ({data.shape[0] if data.ndim else 0}), got {phase_rad.shape}"
        )
    return (data * np.exp(1j * phase_rad).astype(np.complex64)[:, None, None]).astype(np.complex64)


def corrected_image(
    data: np.ndarray,
    positions_m: np.ndarray,
    chirp: Chirp,
    grid: ImageGrid | VolumeGrid,
    phase_rad: np.ndarray,
    **bp_options,
) -> np.ndarray:
    """sum_m exp(j phi_m) B_m on any grid: complex64 ``grid.shape`` ((H, W) or (D, H, W)).

    data : complex (M, K, N) samples; positions_m : float64 (M, K, 3) phase centres, metres;
    phase_rad : float (M,) the correction, radians. bp_options : keywords of
    :func:`twinfocus.imaging.backprojection.numba_backend.backproject_points` (oversample, precision, backend, device,
    progress). A volume on the CPU in float32 whose positions hold their channels on a line is
    formed by sub-arrays (:mod:`twinfocus.imaging.line_backprojection`) where that is at least twice
    cheaper."""
    corrected = corrected_data(data, phase_rad)
    if (
        isinstance(grid, VolumeGrid)
        and bp_options.get("backend", "numba") == "numba"
        and bp_options.get("precision", "float32") == "float32"
    ):
        line_plan = line_backprojection.plan(positions_m, chirp, grid)
        if line_plan is not None:
            opts = {k: v for k, v in bp_options.items() if k in ("oversample", "progress")}
            return line_backprojection.backproject_volume(corrected, positions_m, chirp, grid, line_plan, **opts)
    return backproject(corrected, positions_m, chirp, grid, **bp_options)


def volume_grid(plane: ImageGrid, z0: float, z1: float, dz: float) -> VolumeGrid:
    """The planes z0, z0 + dz, ... up to z1 (metres, inclusive within dz / 100) over ``plane``'s
    x/y box and pixels."""
    if not (np.isfinite([z0, z1, dz]).all() and dz > 0 and z1 >= z0 > 0):
        raise TwinFocusError(f"volume needs 0 < Z0 <= Z1 and DZ > 0 (metres), got {z0} {z1} {dz}")
    depth = int(np.floor((z1 - z0) / dz + 0.01)) + 1
    return VolumeGrid(plane, float(z0), float(z0 + (depth - 1) * dz), depth)


def volume_cost(grid: VolumeGrid, n_positions: int, n_channels: int, line_plan=None) -> dict:
    """What :func:`corrected_image` on ``grid`` will take on the CPU: {"voxels", "memory_bytes",
    "seconds_estimate"} (:data:`BYTES_PER_VOXEL` and the sub-array tables' bound,
    :data:`SECONDS_PER_VOXEL_CHANNEL` per channel evaluation: ``line_plan``'s
    (:func:`twinfocus.imaging.line_backprojection.plan`) when the volume is formed by sub-arrays, one per
    voxel, position and channel otherwise)."""
    voxels = int(np.prod(grid.shape))
    evaluations = line_plan.cost if line_plan is not None else voxels * n_positions * n_channels
    return {
        "voxels": voxels,
        "memory_bytes": BYTES_PER_VOXEL * voxels + TABLE_BYTES,
        "seconds_estimate": SECONDS_PER_VOXEL_CHANNEL * evaluations,
    }


def projections(volume: np.ndarray, grid: VolumeGrid, floor_db: float = -20.0) -> tuple[np.ndarray, np.ndarray]:
    """Maximum-intensity projection along depth and the depth map.

    volume : complex or real (D, H, W). Returns (mip float32 (H, W), the largest |volume| over
    depth; depth float32 (H, W) metres, the depth of that largest voxel, NaN where the mip is more
    than ``-floor_db`` dB below its maximum)."""
    mag = np.abs(np.asarray(volume))
    if mag.shape != grid.shape:
        raise TwinFocusError(f"volume {mag.shape} does not match its grid {grid.shape}")
    mip = mag.max(axis=0)
    depth = grid.z_m[mag.argmax(axis=0)].astype(np.float32)
    depth[mip < mip.max() * 10 ** (floor_db / 20)] = np.nan
    return mip.astype(np.float32), depth


def bright_voxels(volume: np.ndarray, grid: VolumeGrid, threshold_db: float = -12.0) -> tuple[np.ndarray, np.ndarray]:
    """The voxels within ``-threshold_db`` dB of the volume's brightest: (points float32 (P, 3)
    metres, values float32 (P,) their |volume| over the maximum, in (0, 1])."""
    mag = np.abs(np.asarray(volume)).ravel()
    if mag.size != int(np.prod(grid.shape)):
        raise TwinFocusError(f"volume {np.shape(volume)} does not match its grid {grid.shape}")
    peak = float(mag.max())
    if not peak > 0:
        return np.zeros((0, 3), np.float32), np.zeros(0, np.float32)
    keep = np.flatnonzero(mag >= peak * 10 ** (threshold_db / 20))
    d, rest = np.divmod(keep, grid.plane.height * grid.plane.width)
    i, j = np.divmod(rest, grid.plane.width)
    pts = np.stack([grid.plane.x_m[j], grid.plane.y_m[i], grid.z_m[d]], axis=1).astype(np.float32)
    return pts, (mag[keep] / peak).astype(np.float32)
