"""Backend plug-in point of the radar and VIO drivers.

A driver node (:mod:`nodes.radar_driver`, :mod:`nodes.vio_driver`) is the same for every source;
what differs is its *backend*: a small class that produces samples (simulation:
:mod:`nodes.runtime.sim_backends`; files: :mod:`nodes.runtime.file_backends`; hardware and the emulated rig:
:mod:`nodes.runtime.sensor_backends`). To add one, write the class and add one line to :data:`RADAR_BACKENDS` or
:data:`VIO_BACKENDS` (``name -> "module:Class"``, imported only when chosen), or name the class
directly in a launch file (``backend: mypackage.mymodule:MyRadar``).

Radar backend interface::

    class MyRadar:
        live = True                  # True: samples come at the device's own pace;
                                     # False: the driver paces them by stamp_ns (files, simulation)
        def __init__(self, options: dict): ...   # the driver's ``options`` parameter
        chirp: twinfocus.radar.fmcw.Chirp             # set by __init__
        channel_offsets_m: np.ndarray            # float64 (K, 3), radar body frame (VirtualArray.offsets_m)
        def samples(self) -> Iterator[RadarSample]: ...  # may block; returning ends the stream
        def close(self) -> None: ...             # called once, from the driver's thread of control

VIO backend interface: the same with ``samples() -> Iterator[PoseSample]`` and attributes
``frame_id`` (the frame poses are expressed in, ``"scene"``) and ``child_frame_id`` (``"radar"``
when poses are already the radar's, ``"camera"`` when the synchronizer must apply the
camera-to-radar calibration).

``samples()`` runs in a background thread of the driver, so a backend may simply block on its
device (socket, serial port, SDK call); raising :class:`~twinfocus.errors.TwinFocusError` stops
the driver with that message.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from twinfocus.errors import TwinFocusError


@dataclass
class RadarSample:
    """One radar position from a backend.

    stamp_ns : capture time, nanoseconds (the clock the poses use).
    data : complex64 (K, N) monostatic-equivalent IF samples (one row of a scan's ``data``;
        hardware backends apply :func:`twinfocus.sensors.frames.frame_to_virtual_channels`).
    scan_id, index, last : which scan, position in it, and whether it is the scan's last frame.
    positions_true_m : optional float64 (K, 3) true phase centres (simulation only).
    gaps : optional (frames_lost, frames_zero_filled, bytes_lost) of the capture so far.
    """

    stamp_ns: int
    data: np.ndarray
    scan_id: str = "scan"
    index: int = 0
    last: bool = False
    positions_true_m: np.ndarray | None = None
    gaps: tuple[int, int, int] | None = None


@dataclass
class PoseSample:
    """One tracked pose: body origin position_m (3,) metres, quat_xyzw (4,), confidence in [0, 1]."""

    stamp_ns: int
    position_m: np.ndarray
    quat_xyzw: np.ndarray
    confidence: float = 1.0


#: radar backend name -> "module:Class"
RADAR_BACKENDS: dict[str, str] = {
    "sim": "nodes.runtime.sim_backends:SimRadar",
    "scan_file": "nodes.runtime.file_backends:ScanFileRadar",
    "mmwcas": "nodes.runtime.sensor_backends:MmwcasRadar",  # TI MMWCAS capture folder
    "dca1000": "nodes.runtime.sensor_backends:Dca1000Radar",  # DCA1000EVM stream (+ radar CLI); the emulated rig
}

#: VIO backend name -> "module:Class"
VIO_BACKENDS: dict[str, str] = {
    "sim": "nodes.runtime.sim_backends:SimVio",
    "trajectory_file": "nodes.runtime.file_backends:TrajectoryFileVio",
    "zed": "nodes.runtime.sensor_backends:ZedVio",  # ZED 2i positional tracking (ZED SDK)
    "emulated": "nodes.runtime.sensor_backends:EmulatedRigVio",  # the emulated rig's tracker
}


def load_backend(registry: dict[str, str], name: str, kind: str) -> type:
    """The backend class registered as ``name``, or named as ``module:Class``."""
    target = registry.get(name, name)
    if ":" not in target:
        raise TwinFocusError(f"unknown {kind} backend {name!r}; known: {', '.join(registry)} (or module:Class)")
    module_name, cls_name = target.split(":", 1)
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise TwinFocusError(f"{kind} backend {name!r}: cannot import {module_name} ({exc})") from None
    cls = getattr(module, cls_name, None)
    if cls is None:
        raise TwinFocusError(f"{kind} backend {name!r}: {module_name} has no {cls_name}")
    return cls


def option(options: dict, name: str, default: Any = None, kind: type | None = None, where: str = "backend") -> Any:
    """Read one backend option with a clear error when it has the wrong type."""
    if name not in options:
        if default is None and kind is not None:
            raise TwinFocusError(f"{where}: option {name!r} is required")
        return default
    value = options[name]
    if kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if kind is not None and not isinstance(value, kind):
        raise TwinFocusError(f"{where}: option {name!r} must be {kind.__name__}, got {value!r}")
    return value


def check_unknown(options: dict, known: set[str], where: str) -> None:
    unknown = sorted(set(options) - known)
    if unknown:
        raise TwinFocusError(f"{where}: unknown option(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
