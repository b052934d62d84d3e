"""Trajectory files: TUM and EuRoC formats, read into and written from :class:`Poses`.

TUM (TUM RGB-D benchmark, ``groundtruth.txt``): one pose per line, space separated,
``timestamp tx ty tz qx qy qz qw`` with the time stamp in seconds (decimal), ``#`` comments.
EuRoC (ASL dataset format, ``state_groundtruth_estimate0/data.csv``): comma separated,
header ``#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []``
then possibly velocities and biases; time stamps integer nanoseconds, quaternion scalar first.

Pose confidence (not part of either format) travels as an extra last column: a 9th TUM column,
a ``confidence []`` EuRoC column. Readers take it when present; plain files read as before.
Times are parsed as exact decimals and numbers written with the shortest exact repr, so a
write/read round trip is bit-exact.
"""

from __future__ import annotations

import os
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.io.atomic import write_text_atomic
from twinfocus.motion.trajectory import Poses

EUROC_HEADER = "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"
EUROC_CONFIDENCE = "confidence []"


def _seconds_to_ns(text: str, where: str) -> int:
    try:
        d = Decimal(text)
    except InvalidOperation:
        raise TwinFocusError(f"{where}: time stamp {text!r} is not a number") from None
    if not d.is_finite():
        raise TwinFocusError(f"{where}: time stamp {text!r} is not finite")
    return int((d * 1_000_000_000).to_integral_value())


def _ns_to_seconds(ns: int) -> str:
    sign = "-" if ns < 0 else ""
    s, frac = divmod(abs(int(ns)), 1_000_000_000)
    return f"{sign}{s}.{frac:09d}"


def _floats(parts: list[str], where: str) -> list[float]:
    try:
        return [float(p) for p in parts]
    except ValueError:
        raise TwinFocusError(f"{where}: expected numbers, got {' '.join(parts)!r}") from None


def _finish(path: Path, ts, pos, quat, conf) -> Poses:
    if not ts:
        raise TwinFocusError(f"{path}: no poses in the file")
    try:
        return Poses(
            np.asarray(ts, dtype=np.int64),
            np.asarray(pos, dtype=np.float64),
            np.asarray(quat, dtype=np.float64),
            None if conf is None else np.asarray(conf, dtype=np.float64),
        )
    except TwinFocusError as exc:
        raise TwinFocusError(f"{path}: {exc}") from None


def read_tum(path: str | os.PathLike) -> Poses:
    """Read a TUM trajectory (8 columns, or 9 with confidence)."""
    path = Path(path)
    if not path.is_file():
        raise TwinFocusError(f"{path}: no such trajectory file")
    ts, pos, quat, conf = [], [], [], []
    n_cols = None
    for i, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        where = f"{path} line {i}"
        if len(parts) not in (8, 9):
            raise TwinFocusError(f"{where}: a TUM pose has 8 values (timestamp tx ty tz qx qy qz qw), got {len(parts)}")
        if n_cols is None:
            n_cols = len(parts)
        elif len(parts) != n_cols:
            raise TwinFocusError(f"{where}: {len(parts)} values where earlier lines have {n_cols}")
        ts.append(_seconds_to_ns(parts[0], where))
        v = _floats(parts[1:], where)
        pos.append(v[0:3])
        quat.append(v[3:7])
        if len(parts) == 9:
            conf.append(v[7])
    return _finish(path, ts, pos, quat, conf if n_cols == 9 else None)


def read_euroc(path: str | os.PathLike) -> Poses:
    """Read an EuRoC ground-truth / estimate CSV (columns found by header when there is one)."""
    path = Path(path)
    if not path.is_file():
        raise TwinFocusError(f"{path}: no such trajectory file")
    cols = {"t": 0, "px": 1, "py": 2, "pz": 3, "qw": 4, "qx": 5, "qy": 6, "qz": 7}
    conf_col = None
    ts, pos, quat, conf = [], [], [], []
    for i, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        where = f"{path} line {i}"
        if s.startswith("#") or s[0].isalpha():
            names = [c.strip().lstrip("#").strip() for c in s.split(",")]
            for key, prefix in (
                ("t", "timestamp"),
                ("px", "p_RS_R_x"),
                ("py", "p_RS_R_y"),
                ("pz", "p_RS_R_z"),
                ("qw", "q_RS_w"),
                ("qx", "q_RS_x"),
                ("qy", "q_RS_y"),
                ("qz", "q_RS_z"),
            ):
                hit = [j for j, n in enumerate(names) if n.split(" ")[0] == prefix]
                if hit:
                    cols[key] = hit[0]
            hit = [j for j, n in enumerate(names) if n.split(" ")[0] == "confidence"]
            conf_col = hit[0] if hit else None
            continue
        parts = [p.strip() for p in s.split(",")]
        need = max(max(cols.values()), conf_col or 0) + 1
        if len(parts) < need:
            raise TwinFocusError(f"{where}: expected at least {need} comma-separated values, got {len(parts)}")
        try:
            ts.append(int(parts[cols["t"]]))
        except ValueError:
            raise TwinFocusError(
                f"{where}: EuRoC time stamps are integer nanoseconds, got {parts[cols['t']]!r}"
            ) from None
        v = _floats([parts[cols[k]] for k in ("px", "py", "pz", "qx", "qy", "qz", "qw")], where)
        pos.append(v[0:3])
        quat.append(v[3:7])
        if conf_col is not None:
            conf.append(_floats([parts[conf_col]], where)[0])
    return _finish(path, ts, pos, quat, conf if conf_col is not None else None)


def read_trajectory(path: str | os.PathLike, fmt: str = "auto") -> Poses:
    """Read a TUM or EuRoC file; ``fmt="auto"`` decides by extension and content."""
    path = Path(path)
    if fmt == "auto":
        if not path.is_file():
            raise TwinFocusError(f"{path}: no such trajectory file")
        head = ""
        with open(path, errors="replace") as f:
            for line in f:
                if line.strip():
                    head = line.strip()
                    break
        fmt = (
            "euroc"
            if ("," in head and ("timestamp" in head or path.suffix == ".csv")) or path.suffix == ".csv"
            else "tum"
        )
    if fmt == "tum":
        return read_tum(path)
    if fmt == "euroc":
        return read_euroc(path)
    raise TwinFocusError(f"unknown trajectory format {fmt!r}; use 'tum', 'euroc' or 'auto'")


def write_tum(path: str | os.PathLike, poses: Poses, confidence: bool = True) -> Path:
    """Write a TUM file (a 9th confidence column when the poses have one and ``confidence``)."""
    with_conf = confidence and poses.confidence is not None
    lines = ["# timestamp tx ty tz qx qy qz qw" + (" confidence" if with_conf else "")]
    for m in range(len(poses)):
        vals = list(poses.position_m[m]) + list(poses.quat_xyzw[m])
        if with_conf:
            vals.append(poses.confidence[m])  # type: ignore[index]  # with_conf
        lines.append(" ".join([_ns_to_seconds(poses.timestamps_ns[m])] + [repr(float(v)) for v in vals]))
    return write_text_atomic(path, "\n".join(lines) + "\n")


def write_euroc(path: str | os.PathLike, poses: Poses, confidence: bool = True) -> Path:
    """Write a EuRoC CSV (a ``confidence []`` column when the poses have one and ``confidence``)."""
    with_conf = confidence and poses.confidence is not None
    lines = [EUROC_HEADER + ("," + EUROC_CONFIDENCE if with_conf else "")]
    for m in range(len(poses)):
        x, y, z = poses.position_m[m]
        qx, qy, qz, qw = poses.quat_xyzw[m]
        vals = [x, y, z, qw, qx, qy, qz] + ([poses.confidence[m]] if with_conf else [])  # type: ignore[index]
        lines.append(",".join([str(int(poses.timestamps_ns[m]))] + [repr(float(v)) for v in vals]))
    return write_text_atomic(path, "\n".join(lines) + "\n")
