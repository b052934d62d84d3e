"""One SAR scan ready to image, and its ``.npz`` file (docs/architecture.md section 4).

Keys of the scan file:
    data            complex64 (M, K, N)  monostatic-equivalent IF samples
    positions       float64   (M, K, 3)  phase-centre positions as tracked (carry the error)
    f0_hz, slope_hz_per_s, fs_hz         scalars (N is data.shape[-1])
    positions_true  float64   (M, K, 3)  optional ground truth
    timestamps_ns   int64     (M,)       optional capture times
    calibration     str                  optional JSON: the channel calibration applied (file, sha256)
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.io.arrays import load_npz, save_npz_atomic
from twinfocus.radar.fmcw import Chirp


@dataclass
class Scan:
    """IF samples, tracked phase-centre positions and the chirp that made them.

    Attributes
    ----------
    data : complex64 (M, K, N), radar position m, virtual channel k, fast-time sample n.
    positions : float64 (M, K, 3) metres, scene frame (z from the aperture into the scene).
    chirp : the :class:`~twinfocus.radar.fmcw.Chirp`; ``chirp.n_samples == N``.
    positions_true : optional float64 (M, K, 3), the positions the data were really taken at.
    timestamps_ns : optional int64 (M,).
    calibration : optional JSON text naming the channel calibration the data went through
        (``twinfocus convert --calibration``: file name, SHA-256, quality figures).
    """

    data: np.ndarray
    positions: np.ndarray
    chirp: Chirp
    positions_true: np.ndarray | None = None
    timestamps_ns: np.ndarray | None = None
    calibration: str | None = None

    def __post_init__(self) -> None:
        self.data = np.asarray(self.data)
        self.positions = np.asarray(self.positions)
        self.validate()

    @property
    def n_positions(self) -> int:
        return int(self.data.shape[0])

    @property
    def n_channels(self) -> int:
        return int(self.data.shape[1])

    def validate(self) -> None:
        """Raise :class:`TwinFocusError` naming the first thing wrong with this scan."""
        d, p = self.data, self.positions
        if d.ndim != 3:
            raise TwinFocusError(f"scan data must be 3-D (positions, channels, samples), got shape {d.shape}")
        if not np.iscomplexobj(d):
            raise TwinFocusError(f"scan data must be complex (complex64), got dtype {d.dtype}")
        if d.shape[0] == 0 or d.shape[1] == 0:
            raise TwinFocusError(f"scan data is empty: shape {d.shape}")
        if d.shape[2] != self.chirp.n_samples:
            raise TwinFocusError(
                f"scan data has {d.shape[2]} fast-time samples but the chirp has {self.chirp.n_samples}"
            )
        _check_positions("positions", p, d.shape[:2])
        if self.positions_true is not None:
            self.positions_true = np.asarray(self.positions_true)
            _check_positions("positions_true", self.positions_true, d.shape[:2])
        if self.timestamps_ns is not None:
            self.timestamps_ns = np.asarray(self.timestamps_ns)
            if self.timestamps_ns.shape != (d.shape[0],) or not np.issubdtype(self.timestamps_ns.dtype, np.integer):
                raise TwinFocusError(
                    f"timestamps_ns must be integer with shape ({d.shape[0]},), got "
                    f"{self.timestamps_ns.dtype} {self.timestamps_ns.shape}"
                )
        if not np.isfinite(d).all():
            bad = np.argwhere(~np.isfinite(d))[0]
            raise TwinFocusError(f"scan data holds NaN or inf (first at position {bad[0]}, channel {bad[1]})")
        if not np.any(d):
            raise TwinFocusError("scan data is all zeros: nothing was captured")

    def with_data(self, data: np.ndarray) -> Scan:
        return replace(self, data=data)

    def save(self, path: str | os.PathLike) -> Path:
        """Write the scan file atomically (a crash never leaves a half-written file)."""
        arrays = {
            "data": self.data.astype(np.complex64, copy=False),
            "positions": self.positions.astype(np.float64, copy=False),
            "f0_hz": np.float64(self.chirp.f0_hz),
            "slope_hz_per_s": np.float64(self.chirp.slope_hz_per_s),
            "fs_hz": np.float64(self.chirp.fs_hz),
        }
        if self.positions_true is not None:
            arrays["positions_true"] = self.positions_true.astype(np.float64, copy=False)
        if self.timestamps_ns is not None:
            arrays["timestamps_ns"] = self.timestamps_ns.astype(np.int64, copy=False)
        if self.calibration is not None:
            arrays["calibration"] = np.array(self.calibration)
        return save_npz_atomic(path, arrays)

    @classmethod
    def load(cls, path: str | os.PathLike) -> Scan:
        """Read and validate a scan file; errors name the file and the bad key."""
        z = load_npz(path)
        missing = [k for k in ("data", "positions", "f0_hz", "slope_hz_per_s", "fs_hz") if k not in z]
        if missing:
            raise TwinFocusError(f"{path}: not a scan file, missing key(s) {', '.join(missing)}")
        data = z["data"]
        if data.ndim != 3:
            raise TwinFocusError(f"{path}: 'data' must be 3-D (positions, channels, samples), got shape {data.shape}")
        try:
            chirp = Chirp(float(z["f0_hz"]), float(z["slope_hz_per_s"]), float(z["fs_hz"]), int(data.shape[2]))
            return cls(
                data=data,
                positions=z["positions"],
                chirp=chirp,
                positions_true=z.get("positions_true"),
                timestamps_ns=z.get("timestamps_ns"),
                calibration=str(z["calibration"]) if "calibration" in z else None,
            )
        except TwinFocusError as exc:
            raise TwinFocusError(f"{path}: {exc}") from None


def _check_positions(name: str, p: np.ndarray, mk: tuple[int, int]) -> None:
    if p.shape != (*mk, 3):
        raise TwinFocusError(f"{name} must have shape ({mk[0]}, {mk[1]}, 3) to match the data, got {p.shape}")
    if not np.issubdtype(p.dtype, np.floating):
        raise TwinFocusError(f"{name} must be floating point (float64 metres), got dtype {p.dtype}")
    if not np.isfinite(p).all():
        bad = np.argwhere(~np.isfinite(p))[0]
        raise TwinFocusError(f"{name} holds NaN or inf (first at position {bad[0]}, channel {bad[1]})")
