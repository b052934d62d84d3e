"""What several test files run or build the same way: command lines for ``twinfocus`` (``cli``),
the small simulated scenes the offline commands are tested on (conftest.py's session fixtures),
the brute-force echo of point scatterers the imaging tests take as their truth, an mmWave Studio
JSON, a scan as the synchronizer's measurements, the refusal of a malformed file, and a docs page's
```sh blocks run as written."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benchmarks.docs_pages import ROOT, page_env, run_blocks
from msgs import Header, SarMeasurement
from twinfocus.cli import main
from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import C_M_PER_S, Chirp, mmwcas_virtual_array

# The simulated scene's two letters (twinfocus.simulation.scenario.Scenario): x0 x1 y0 y1 z in m.
REF_ROI = ("-0.15", "0.0", "-0.11", "0.12", "0.6")
TGT_ROI = ("0.02", "0.13", "-0.11", "0.12", "0.6")
ROIS = ("--reference-roi", *REF_ROI, "--target-roi", *TGT_ROI)
# 3 columns of 40 rows: a quarter of the paper's aperture, enough to image both letters.
SMALL_SCENE = ("--columns", "3", "--rows", "40", "--seed", "3")


def argv(*parts: object) -> list[str]:
    """The words of a command line: a ``str`` is split at white space (``"--size 48"``), anything
    else (a path, a number) is one word."""
    words: list[str] = []
    for part in parts:
        words += part.split() if isinstance(part, str) else [str(part)]
    return words


def cli(*parts: object) -> int:
    """``twinfocus`` run in this process on :func:`argv`'s words; returns its exit code."""
    return main(argv(*parts))


def simulate(folder: Path, *options: object) -> Path:
    """``simulate --quiet`` into ``folder/scan.npz`` and its template scan ``folder/tpl.npz``;
    returns ``folder``."""
    assert cli("simulate --quiet --out", folder / "scan.npz", "--template-out", folder / "tpl.npz", *options) == 0
    return folder


def metrics(out: Path) -> dict[str, Any]:
    """The ``metrics.json`` a run wrote into the folder ``out``."""
    return json.loads((Path(out) / "metrics.json").read_text())


def convert_capture(folder: Path, *options: object) -> int:
    """``convert`` of the capture ``folder/cap`` with its trajectory ``folder/traj.txt`` into
    ``folder/s.npz``; returns the exit code."""
    return cli("convert", folder / "cap", "--trajectory", folder / "traj.txt", "--out", folder / "s.npz", *options)


def assert_refuses(load: Callable[[Path], object], path: Path, text: str, message: str) -> None:
    """``load`` of a file holding ``text`` at ``path`` raises a TwinFocusError matching ``message``."""
    path.write_text(text)
    with pytest.raises(TwinFocusError, match=message):
        load(path)


def aperture(n_rows: int, pitch_m: float = 0.004, columns_m: tuple[float, ...] = (-0.02, 0.0, 0.02)) -> np.ndarray:
    """The cascade's virtual array (mmwcas_virtual_array) at ``n_rows`` rows ``pitch_m`` apart,
    centred on y = 0, in each column x of ``columns_m``, at z = 0: (columns * n_rows, 86, 3) m."""
    va = mmwcas_virtual_array()
    rows = (np.arange(n_rows) - (n_rows - 1) / 2) * pitch_m
    return np.array([va.offsets_m + np.array([cx, y, 0.0]) for cx in columns_m for y in rows])


def points_scan(chirp: Chirp, positions: np.ndarray, points: list[np.ndarray], amplitudes: list[float]) -> np.ndarray:
    """The ideal echo of point scatterers, summed by brute force (the truth the back-projections
    are checked against, independent of the simulator).

    positions: (M, C, 3) m, one phase centre per position and channel; points: (3,) m each;
    returns (M, C, chirp.n_samples) complex64.
    """
    data = np.zeros((*positions.shape[:2], chirp.n_samples), np.complex128)
    for p, a in zip(points, amplitudes):
        r = np.linalg.norm(positions - p, axis=-1)
        data += a * np.exp(1j * 2 * np.pi * chirp.frequencies_hz * 2 * r[..., None] / C_M_PER_S)
    return data.astype(np.complex64)


def studio_json(path: Path, profile: dict[str, Any], tx_numbers: list[int], n_loops: int, period_ms: float) -> None:
    """An mmWave Studio JSON written field by field (TI's rlProfileCfg_t / rlChirpCfg_t /
    rlFrameCfg_t names): every device with profile 0 (``profile``, its fields past profileId), one
    chirp per entry of ``tx_numbers`` (TI numbering 1..12, device d's TX b as 3 d + b + 1)."""
    devices = []
    for d in range(4):
        chirps = []
        for c, n in enumerate(tx_numbers):
            mask = 1 << ((n - 1) % 3) if (n - 1) // 3 == d else 0
            chirps.append(
                {"rlChirpCfg_t": {"chirpStartIdx": c, "chirpEndIdx": c, "profileId": 0, "txEnable": f"0x{mask:X}"}}
            )
        frame = {
            "chirpStartIdx": 0,
            "chirpEndIdx": len(tx_numbers) - 1,
            "numLoops": n_loops,
            "numFrames": 0,
            "framePeriodicity_msec": period_ms,
        }
        rf = {
            "rlProfiles": [{"rlProfileCfg_t": {"profileId": 0, **profile}}],
            "rlChirps": chirps,
            "rlFrameCfg_t": frame,
        }
        data_format = {"rlDevDataFmtCfg_t": {"iqSwapSel": 0, "chInterleave": 0}}
        devices.append({"mmWaveDeviceId": d, "rfConfig": rf, "rawDataCaptureConfig": data_format})
    path.write_text(json.dumps({"mmWaveDevices": devices}))


def sar_measurements(data, positions, chirp: Chirp, scan_id: str, stamps_ns=None, positions_true=None) -> list:
    """A scan as the synchronizer publishes it: one SarMeasurement per position, the last one
    marked. data: complex64 (M, K, N); positions (and positions_true): (M, K, 3) m; stamps_ns:
    int (M,), default 1, 2, ... ns."""
    n = data.shape[0]
    stamps = np.arange(1, n + 1) if stamps_ns is None else stamps_ns
    chirp_fields = {"f0_hz": chirp.f0_hz, "slope_hz_per_s": chirp.slope_hz_per_s, "fs_hz": chirp.fs_hz}
    return [
        SarMeasurement(
            header=Header(stamp_ns=int(stamps[i])),
            data=data[i],
            positions_m=positions[i],
            positions_true_m=None if positions_true is None else positions_true[i],
            **chirp_fields,
            scan_id=scan_id,
            index=i,
            last=i == n - 1,
        )
        for i in range(n)
    ]


def page_folder(tmp_path: Path, name: str = "work") -> tuple[Path, dict[str, str]]:
    """An empty folder ``tmp_path/name`` to run a docs page's blocks in, and the reader's
    environment for them (:func:`benchmarks.docs_pages.page_env`, its cache in ``tmp_path/cache``)."""
    work = tmp_path / name
    work.mkdir()
    return work, page_env(tmp_path / "cache")


def run_page_blocks(page: Path, work: Path, env: dict[str, str]) -> list[dict]:
    """Every ```sh block of ``page`` run in ``work`` as a reader would
    (:func:`benchmarks.docs_pages.run_blocks`'s records); fails the test at the first block that
    fails, with its text and the end of what it printed."""
    runs = run_blocks(page, work, env)
    failed = [r for r in runs if r["returncode"] != 0]
    assert not failed, f"{page.relative_to(ROOT)}: step failed:\n{failed[0]['block']}\n{failed[0]['printed'][-3000:]}"
    return runs
