"""Text documents: JSON and YAML files (calibrations, rigs, board descriptions, sidecars, reports).

Thin on purpose: each reader raises what the parser raises (OSError for an unreadable file,
ValueError for bad JSON, ``yaml.YAMLError`` for bad YAML), so the caller that knows what the
file should be writes the one-line error that names it (:func:`read_file` writes it from the
caller's words for any reader); the numeric modules call these instead
of opening files themselves (docs/architecture.md section 3).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from twinfocus.errors import TwinFocusError
from twinfocus.io.atomic import write_text_atomic


def read_text(path: str | os.PathLike) -> str:
    """A text file's contents (bytes that are not UTF-8 read as U+FFFD, for logs and configs)."""
    return Path(path).read_text(errors="replace")


def read_file(
    path: str | os.PathLike,
    reader: Callable[[Path], Any],
    missing: str,
    unreadable: str,
    errors: tuple[type[Exception], ...] = (OSError, ValueError),
) -> Any:
    """``reader(path)``, with one line naming the file (TwinFocusError) where there is none
    ("PATH: no such ``missing``") or ``reader`` raises one of ``errors`` ("PATH: ``unreadable`` (why)")."""
    path = Path(path)
    if not path.is_file():
        raise TwinFocusError(f"{path}: no such {missing}")
    try:
        return reader(path)
    except errors as exc:
        raise TwinFocusError(f"{path}: {unreadable} ({exc})") from None


def read_json(path: str | os.PathLike) -> Any:
    """The JSON document in ``path``; OSError or ValueError (json.JSONDecodeError) when it is not one."""
    return json.loads(Path(path).read_text())


def write_json_document(path: str | os.PathLike, doc: Any) -> Path:
    """Write ``doc`` as indented JSON (numpy scalars as floats) with a final newline, atomically."""
    return write_text_atomic(path, json.dumps(doc, indent=2, default=float) + "\n")


def read_yaml(path: str | os.PathLike) -> Any:
    """The YAML document in ``path`` (safe loader; yaml imported on first use)."""
    import yaml

    return yaml.safe_load(Path(path).read_text())
