"""Content-addressed cache of reference templates: a reference is paid for once.

A template scan's image (or a digital twin's template) depends only on the input files' contents,
the reference grid and the back-projection options, so it is stored under a SHA-256 of exactly
those and reused by every later ``focus`` (and solver) run with the same reference. A changed file
changes its hash, so a stale entry is never found; entries are never overwritten in place.

Where: ``$TWINFOCUS_CACHE_DIR``, else ``$XDG_CACHE_HOME/twinfocus``, else ``~/.cache/twinfocus``;
one ``templates/<key>.npz`` per entry (``image`` as computed, ``roi``, ``shape``, and for a digital
twin ``info_json``, what its conditioning chose and why, for metrics.json), and under ``digests/``
the input files' digests, found by their stat (:func:`remembered_sha256`). ``twinfocus
focus --no-cache`` bypasses it. Delete the folder to empty it. Reading and writing fail soft: a
cache that cannot be written or an unreadable entry is a miss, never an error.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.grid import ImageGrid
from twinfocus.io.arrays import load_npz, save_npz_atomic
from twinfocus.io.atomic import write_text_atomic
from twinfocus.io.checksums import file_sha256
from twinfocus.io.documents import read_text
from twinfocus.sensors.rosbag2_files import bag_source_sha256, split_bag_source

#: environment variable that relocates the cache
ENV_DIR = "TWINFOCUS_CACHE_DIR"
#: a file changed less than this many seconds ago is hashed but not remembered: a second change
#: within the file system's clock tick could leave its stat as it was (git's "racily clean")
RACY_S = 2.0
#: part of every key: bump when the back-projection or the template builders change their output
FORMAT_VERSION = 2  # 2: digital twins with the seeded RANSAC plane and GrabCut


def cache_dir() -> Path:
    """The cache folder (not created here)."""
    if os.environ.get(ENV_DIR):
        return Path(os.environ[ENV_DIR]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "twinfocus"


def remembered_sha256(path: str | os.PathLike, root: str | os.PathLike | None = None) -> str:
    """:func:`file_sha256` of ``path``, remembered under ``root`` (default :func:`cache_dir`) by the
    file's identity and stat: the real path, device, inode, size, and modification and change
    times in ns. A field user focuses many scans against one template scan of ~140 MB, and hashing
    it again each time was 0.2-0.5 s of every ``focus`` on the 2-core machine. Any write to the
    file changes its change time (which no program can set back), so a changed file is hashed
    anew, as ``git`` trusts its index; a file changed in the last ``RACY_S`` is not remembered.
    Fails soft: a memo that cannot be read or written means hashing the file."""
    import time

    try:
        st = os.stat(path)
        ident = f"{os.path.realpath(path)}|{st.st_dev}|{st.st_ino}|{st.st_size}|{st.st_mtime_ns}|{st.st_ctime_ns}"
        memo = Path(root if root is not None else cache_dir()) / "digests" / hashlib.sha256(ident.encode()).hexdigest()
        known = read_text(memo).strip() if memo.is_file() else ""
    except OSError:
        return file_sha256(path)
    if len(known) == 64:
        return known
    digest = file_sha256(path)
    if time.time() - max(st.st_mtime, st.st_ctime) < RACY_S:
        return digest
    try:
        write_text_atomic(memo, digest)
    except OSError:
        pass
    return digest


def array_sha256(*arrays: np.ndarray) -> str:
    """SHA-256 over arrays' dtypes, shapes and bytes, hex."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.data)
    return h.hexdigest()


def template_key(kind: str, inputs: dict, grid: ImageGrid, bp_options: dict) -> str:
    """The key of one template: ``kind`` ("template_scan", "digital_twin"), the input digests
    (``inputs``: JSON-serialisable), the grid (region and pixels) and the back-projection options.
    The torch device is left out: every back-end computes the same image."""
    bp = {k: v for k, v in sorted(bp_options.items()) if k != "device"}
    doc = {
        "version": FORMAT_VERSION,
        "kind": kind,
        "inputs": inputs,
        "roi": [float(v) for v in grid.roi],
        "shape": list(grid.shape),
        "bp": bp,
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()


def template_scan_key(
    path: str | os.PathLike, grid: ImageGrid, bp_options: dict, root: str | os.PathLike | None = None
) -> str:
    """Key of a template scan's complex image (:func:`twinfocus.twins.templates.template_from_scan`
    with ``keep_phase=True``) on ``grid``; the file's digest remembered under ``root``
    (:func:`remembered_sha256`)."""
    digest = remembered_sha256(path, root)
    return template_key("template_scan", {"file_sha256": digest, "keep_phase": True}, grid, bp_options)


def digital_twin_key(
    cloud_path: str | os.PathLike,
    positions_m: np.ndarray,
    chirp,
    grid: ImageGrid,
    bp_options: dict,
    method: str = "psf",
    root: str | os.PathLike | None = None,
) -> str:
    """Key of a digital twin's template: the cloud file (its digest remembered under ``root``,
    :func:`remembered_sha256`), the scan's aperture (positions (M, K, 3) and chirp) it is
    simulated for, ``grid`` and the options."""
    inputs = {
        "cloud_sha256": _cloud_sha256(cloud_path, root),
        "positions_sha256": array_sha256(np.asarray(positions_m)),
        "chirp": [chirp.f0_hz, chirp.slope_hz_per_s, chirp.fs_hz, chirp.n_samples],
        "method": method,
    }
    return template_key("digital_twin", inputs, grid, bp_options)


def _cloud_sha256(cloud: str | os.PathLike, root) -> str:
    """A cloud file's digest, or for a rosbag2 source ``BAG:TOPIC@STAMP`` that of the message's points."""
    source = split_bag_source(str(cloud))
    return remembered_sha256(cloud, root) if source is None else bag_source_sha256(source)


class TemplateCache:
    """Templates stored by key under ``root`` (default :func:`cache_dir`); ``enabled=False``
    makes every lookup a miss and every store a no-op."""

    def __init__(self, root: str | os.PathLike | None = None, enabled: bool = True):
        self.root = Path(root) if root is not None else cache_dir()
        self.enabled = enabled
        self.warning: str | None = None  # why the last store failed, for the caller to show

    def path(self, key: str) -> Path:
        return self.root / "templates" / f"{key}.npz"

    def get(self, key: str, grid: ImageGrid) -> np.ndarray | None:
        """The stored image for ``key`` on ``grid`` (dtype as stored), or None."""
        entry = self._load(key, grid)
        return None if entry is None else entry[0]

    def _load(self, key: str, grid: ImageGrid) -> tuple[np.ndarray, dict | None] | None:
        """(image, info or None when stored without), or None for a miss."""
        if not self.enabled:
            return None

        path = self.path(key)
        if not path.is_file():
            return None
        try:
            z = load_npz(path)
            image = z["image"]
            ok = tuple(z["shape"]) == grid.shape and np.allclose(z["roi"], grid.roi) and np.isfinite(image).all()
            info = json.loads(str(z["info_json"])) if "info_json" in z else None
        except (TwinFocusError, KeyError, ValueError):
            ok = False
        if not ok:  # a damaged entry is a miss; the next store replaces it
            return None
        return image, info

    def get_or_compute(self, key: str | None, grid: ImageGrid, compute, with_info: bool = False) -> tuple:
        """(image, status): the stored image ("hit"), or ``compute()`` stored for next time
        ("miss"), or computed alone when the cache is disabled or ``key`` is None ("off").

        with_info : ``compute()`` returns (image, info dict) and this returns (image, info,
        status); an entry stored without info is a miss."""
        if not self.enabled or key is None:
            return (*compute(), "off") if with_info else (compute(), "off")
        hit = self._load(key, grid)
        if hit is not None and (hit[1] is not None or not with_info):
            return (*hit, "hit") if with_info else (hit[0], "hit")
        image, info = compute() if with_info else (compute(), None)
        self.put(key, np.asarray(image), grid, info)
        return (image, info, "miss") if with_info else (image, "miss")

    def put(self, key: str, image: np.ndarray, grid: ImageGrid, info: dict | None = None) -> Path | None:
        """Store ``image`` (as is) and ``info`` (JSON) for ``key``; returns the file, or None when
        it could not be written (``warning`` says why)."""
        if not self.enabled:
            return None

        arrays = {"image": np.asarray(image), "roi": np.asarray(grid.roi, float), "shape": np.asarray(grid.shape)}
        if info is not None:
            arrays["info_json"] = np.asarray(json.dumps(info, default=float))
        try:
            return save_npz_atomic(self.path(key), arrays)
        except OSError as exc:
            self.warning = f"could not write the template cache {self.root} ({exc.strerror or exc})"
            return None
