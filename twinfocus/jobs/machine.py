"""Where the numbers were measured: written beside every benchmark and evaluation result."""

from __future__ import annotations

import os
import platform

from twinfocus.errors import TwinFocusError


def machine_info() -> dict:
    """Platform, Python, CPU (count, model, load average), numpy/torch versions and threads, CUDA."""
    import numba
    import numpy
    import torch

    info = {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "numpy": numpy.__version__,
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "numba_threads": numba.get_num_threads(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }
    try:
        with open("/proc/cpuinfo") as f:
            info["cpu_model"] = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), None)
    except OSError:
        pass
    return info


def available_memory_bytes() -> int | None:
    """Memory the OS can give a process now (Linux MemAvailable), bytes; None when unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def require_memory(need: int, what: str, advice: str, available: int | None = None) -> int:
    """Refuse, in one line, work that needs ``need`` bytes when less is available (``available``
    None: ask the OS, :func:`available_memory_bytes`); returns ``need``. ``what`` names the work,
    ``advice`` what to change."""
    available = available_memory_bytes() if available is None else available
    if available is not None and need > available:
        raise TwinFocusError(
            f"{what} needs about {need / 2**30:.1f} GiB, {available / 2**30:.1f} GiB is available; {advice}"
        )
    return need
