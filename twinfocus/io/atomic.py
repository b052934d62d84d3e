"""Atomic file writes: a result appears whole under its name or not at all.

Every writer goes through a temporary file in the target's folder (same file system, so the
final :func:`os.replace` is atomic) that is removed when writing fails; an earlier file of the
same name survives a failed run. The temporary file gets the mode a plain ``open()`` would give
(``mkstemp`` makes it 0600).

A command's output (``--out``) is never replaced by surprise: :func:`refuse_existing` refuses an
existing one without ``--overwrite``; :func:`output_lock` holds a lock beside it for the whole run,
so a second run on the same output refuses in one line instead of mixing its files in; and
:func:`output_folder` builds a folder in a temporary folder beside it and moves it into place whole.
A folder written so lists the files it wrote (:data:`WRITTEN`); a later run removes only those,
never a file that it did not write.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import IO, Any

import numpy as np

from twinfocus.errors import TwinFocusError

#: inside a folder that a run wrote: the JSON list of the names it wrote there
WRITTEN = ".twinfocus-written.json"
#: errors of a file system that is full or cannot take the write: one line, not a traceback
DISK_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS})


@contextmanager
def atomic_writer(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path`` for writing (``mode`` "wb" or "w"); on a clean exit
    it replaces ``path``, on an exception it is removed and ``path`` is left as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns ``path``."""
    with atomic_writer(path, "wb") as f:
        f.write(data)
    return Path(path)


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns ``path``."""
    return write_bytes_atomic(path, text.encode("utf-8"))


def json_default(v: Any) -> Any:
    """``json.dumps`` fallback for numpy scalars and arrays and for tuples."""
    if isinstance(v, (np.floating, np.integer, np.bool_)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, tuple):
        return list(v)
    raise TypeError(f"not JSON serialisable: {type(v).__name__}")


def write_json_atomic(path: str | os.PathLike, doc: Any) -> Path:
    """Write ``doc`` as compact JSON (numpy values as plain numbers and lists) atomically."""
    return write_text_atomic(path, json.dumps(doc, separators=(",", ":"), default=json_default))


def disk_error_message(exc: OSError, what: str | os.PathLike | None = None) -> str | None:
    """The one line for a full (or read-only) disk, naming the file; None for other errors."""
    if exc.errno not in DISK_ERRNOS:
        return None
    where = exc.filename or what
    reason = {
        errno.ENOSPC: "no space left on the device",
        errno.EDQUOT: "the disk quota is used up",
        errno.EFBIG: "the file is larger than the file system allows",
        errno.EROFS: "the file system is read-only",
    }[exc.errno]
    return f"cannot write {where}: {reason}" if where else f"cannot write: {reason}"


def refuse_existing(path: str | os.PathLike, overwrite: bool, option: str = "--out") -> None:
    """Refuse (TwinFocusError) an existing output without ``overwrite``; an empty folder is no
    result and is taken."""
    p = Path(path)
    if p.is_dir() and not any(p.iterdir()):
        return
    if (p.exists() or p.is_symlink()) and not overwrite:
        raise TwinFocusError(f"{option} {path}: already exists; choose another name or pass --overwrite")


def _lock_path(path: Path) -> Path:
    return path.parent / f".{path.name}.lock"


@contextmanager
def output_lock(path: str | os.PathLike, option: str = "--out") -> Iterator[None]:
    """Hold an exclusive lock on ``path``'s output for the block: ``.NAME.lock`` beside it
    (``fcntl.flock``; removed when the block ends). Another run holding it: refused at once."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    lock = _lock_path(p)
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise TwinFocusError(
                f"{option} {path}: another twinfocus run is writing it now; wait for it to end or choose another {option}"
            ) from None
        try:  # the lock file that the last holder removed is not the lock: take the new one
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        yield
    finally:
        Path(lock).unlink(missing_ok=True)  # while still held: the next run makes a fresh one
        os.close(fd)


@contextmanager
def output_file(path: str | os.PathLike, overwrite: bool, option: str = "--out") -> Iterator[Path]:
    """Lock ``path`` and refuse it when it exists without ``overwrite``; the block writes it with
    :func:`atomic_writer` (or a writer built on it), so it appears whole."""
    with output_lock(path, option):
        refuse_existing(path, overwrite, option)
        yield Path(path)


@contextmanager
def output_files(outputs: dict[str, str | os.PathLike | None], overwrite: bool) -> Iterator[None]:
    """:func:`output_file` for every ``option -> path`` of a command (None: not asked for), all
    held for the block: every output is refused or locked before any work starts."""
    with ExitStack() as stack:
        for option, path in outputs.items():
            if path is not None:
                stack.enter_context(output_file(path, overwrite, option))
        yield


def written_files(folder: str | os.PathLike) -> set[str]:
    """The plain names that a run listed in ``folder``'s :data:`WRITTEN` (none: an empty set)."""
    try:
        names = json.loads((Path(folder) / WRITTEN).read_text())
    except (OSError, ValueError):
        return set()
    if not isinstance(names, list):
        return set()
    return {n for n in names if isinstance(n, str) and n not in ("", ".", "..") and "/" not in n and "\\" not in n}


def record_written(folder: str | os.PathLike, names) -> None:
    """List ``names`` as written by this run in ``folder``'s :data:`WRITTEN`."""
    write_json_atomic(Path(folder) / WRITTEN, sorted(set(names) - {WRITTEN}))


def remove_earlier(folder: str | os.PathLike, keep) -> None:
    """Remove the files an earlier run listed in ``folder`` and this one did not write (``keep``)."""
    for name in written_files(folder) - set(keep):
        f = Path(folder) / name
        if f.is_file() and not f.is_symlink():
            f.unlink()


@contextmanager
def output_folder(path: str | os.PathLike, overwrite: bool, option: str = "--out") -> Iterator[Path]:
    """A folder output made whole: locked (:func:`output_lock`), refused when it exists without
    ``overwrite``; the block writes into the yielded temporary folder beside it, which then takes
    its place. An earlier folder's files that its run wrote are replaced or removed; any other file
    in it (one the user put there) is kept. A failed block leaves the earlier folder as it was."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise TwinFocusError(f"{option} {path}: is an existing file, not a folder")
    with output_lock(out, option):
        refuse_existing(out, overwrite, option)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
        try:
            yield tmp
            _publish(tmp, out)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


def _publish(tmp: Path, out: Path) -> None:
    record_written(tmp, (p.name for p in tmp.iterdir()))
    os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes it 0700
    if not out.exists():
        os.rename(tmp, out)
        return
    if not any(out.iterdir()):
        os.rmdir(out)
        os.rename(tmp, out)
        return
    earlier = written_files(out) | {WRITTEN}
    aside = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
    os.rename(out, aside)  # onto the empty folder mkdtemp made
    try:
        os.rename(tmp, out)
    except BaseException:
        os.rename(aside, out)
        raise
    for entry in aside.iterdir():  # the user's own files stay
        if entry.name not in earlier and not (out / entry.name).exists():
            os.rename(entry, out / entry.name)
    shutil.rmtree(aside, ignore_errors=True)


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask
