"""Write MMWCAS capture folders the way the MMWCAS-DSP-EVM (TDA2) capture card lays them out.

For tests and for replaying simulated scenes through the real reader: one ``<device>_NNNN_data.bin``
and ``<device>_NNNN_idx.bin`` per device, index header and entries as in
:mod:`twinfocus.sensors.ti_mmwcas`, frames back to back. Like the real card, the first frame can
be garbage (``bad_first_frame=True``); the reader drops it by default.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.sensors.ti_mmwcas import (
    BUFF_IDX_TAG,
    DEVICES,
    IDX_ENTRY_DTYPE,
    IDX_HEADER_DTYPE,
    INFO_TAG,
    MmwcasConfig,
    cascade_frame_to_device_iq,
)

#: Version number written into generated index files.
IDX_VERSION = 1


def write_mmwcas_capture(
    folder: str | os.PathLike,
    frames_iq: np.ndarray,
    timestamps_ns: np.ndarray,
    config: MmwcasConfig | None = None,
    slice_index: int = 0,
    bad_first_frame: bool = True,
    device_skew_ns: np.ndarray | None = None,
    rng: np.random.Generator | int | None = 0,
) -> list[Path]:
    """Write one capture slice.

    frames_iq : int16 (F, n_loops, 12, 16, N, 2), (I, Q) per [frame, loop, TX, RX (array order),
        sample]; or (F, 12, 16, N, 2) when n_loops == 1.
    timestamps_ns : int (F,), capture times; stored in ticks of ``config.timestamp_unit_ns``
        (floored), so give multiples of it for an exact round trip.
    bad_first_frame : write a garbage frame (random samples, one period earlier) before the
        others, as the TDA2 card does.
    device_skew_ns : optional int (F, 4) added to each device's time stamps.
    Returns the eight paths written.
    """
    config = config or MmwcasConfig()
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    x = np.asarray(frames_iq)
    if x.ndim == 5 and config.n_loops == 1:
        x = x[:, None]
    ts = np.asarray(timestamps_ns, dtype=np.int64)
    if x.ndim != 6 or ts.shape != (x.shape[0],):
        raise TwinFocusError(
            f"frames_iq must be (F, loops, 12, 16, N, 2) with F time stamps, got {x.shape} and {ts.shape}"
        )
    skew = (
        np.zeros((x.shape[0], len(DEVICES)), np.int64)
        if device_skew_ns is None
        else np.asarray(device_skew_ns, np.int64)
    )
    if bad_first_frame:
        gen = np.random.default_rng(rng)
        junk = gen.integers(-32768, 32767, size=x.shape[1:], dtype=np.int16, endpoint=True)
        period = int(round((config.frame_period_s or 0.1) * 1e9))
        x = np.concatenate([junk[None], x], axis=0)
        ts = np.concatenate([[max(int(ts[0]) - period, 0) if ts.size else 0], ts])
        skew = np.concatenate([np.zeros((1, len(DEVICES)), np.int64), skew], axis=0)
    n = x.shape[0]
    per_device = (
        np.stack([cascade_frame_to_device_iq(f, config) for f in x], axis=1)
        if n
        else np.zeros((len(DEVICES), 0, config.device_frame_values), np.int16)
    )
    fb = config.device_frame_bytes
    written = []
    for d, dev in enumerate(DEVICES):
        data_path = folder / f"{dev}_{slice_index:04d}_data.bin"
        idx_path = folder / f"{dev}_{slice_index:04d}_idx.bin"
        data_path.write_bytes(per_device[d].astype("<i2").tobytes())
        header = np.zeros(1, IDX_HEADER_DTYPE)
        header["tag"] = INFO_TAG
        header["version"] = IDX_VERSION
        header["num_idx"] = n
        header["data_file_size"] = n * fb
        entries = np.zeros(n, IDX_ENTRY_DTYPE)
        entries["tag"] = BUFF_IDX_TAG
        entries["version"] = IDX_VERSION
        entries["width"] = config.n_samples
        entries["height"] = config.n_chirps * config.n_loops
        entries["size"] = fb
        entries["timestamp"] = (ts + skew[:, d]) // int(config.timestamp_unit_ns)
        entries["offset"] = np.arange(n, dtype=np.uint64) * fb
        idx_path.write_bytes(header.tobytes() + entries.tobytes())
        written += [data_path, idx_path]
    return written
