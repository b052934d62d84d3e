"""Checksums of files: the SHA-256 that cache keys and a calibration's provenance record."""

from __future__ import annotations

import hashlib
import os


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes, hex (~0.1 s for a 140 MB scan)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:  # hashlib.file_digest is 3.11+; the project supports 3.10
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
