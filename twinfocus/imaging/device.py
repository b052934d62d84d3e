"""The torch device: the one place it is decided, for the back-projection, the fits and the solver."""

from __future__ import annotations

import os
from pathlib import Path

from twinfocus.errors import TwinFocusError


def _accelerator_present() -> bool:
    """Whether a GPU device node exists, so an unset device can be the CPU without importing
    torch (1-3 s) on the machines that have none; where it cannot tell, torch decides."""
    dev = Path("/dev")
    if os.name != "posix" or not dev.is_dir():
        return True
    return any(dev.glob("nvidia[0-9]*")) or (dev / "kfd").exists()


def resolve_device(requested: str | None) -> str:
    """The torch device to run on: None or "" -> "cuda" when torch sees one, else "cpu"; any
    other value is checked (a CUDA device must exist) and returned as given.

    The one place the device is decided: ``twinfocus focus --device``, the solver's ``device``
    and the torch back-projection's ``device=None`` all come here.
    """
    if not requested:
        if not _accelerator_present():
            return "cpu"
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"
    if requested == "cpu":
        return requested
    import torch

    try:
        dev = torch.device(requested)
    except RuntimeError:
        raise TwinFocusError(
            f"device {requested!r}: not a torch device (cpu, cuda, cuda:N; unset: cuda if present, else cpu)"
        ) from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise TwinFocusError(
                f"device {requested!r}: no CUDA device is available (torch sees none); use cpu, "
                "or leave the device unset for cuda when present, else cpu"
            )
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise TwinFocusError(f"device {requested!r}: there are only {torch.cuda.device_count()} CUDA device(s)")
    return requested
