"""A name that comes from data becomes a path only through :func:`child_path`.

A scan id on the bus, a manifest column, a topic field: none of them is the user's own choice of
where to write, so none may point outside the folder it belongs in (``../../x``, ``/etc/x``), hide
a NUL that the operating system would cut the name at, or (where one name is due) name a
subfolder. :func:`child_path` refuses such a name with one :class:`TwinFocusError` line and
returns the path inside the folder otherwise.
"""

from __future__ import annotations

import os
from pathlib import Path, PurePosixPath

from twinfocus.errors import TwinFocusError


def child_path(folder: str | os.PathLike, name: str, *, what: str, subfolders: bool = False) -> Path:
    """``folder / name``, refused (TwinFocusError naming ``what``) unless it stays inside ``folder``.

    name : a name from data. Refused: empty, ".", "..", a NUL or other control character, an
        absolute path, a ``..`` part, a backslash, and (unless ``subfolders``) any ``/``. Also
        refused when a symbolic link already inside ``folder`` leads the path out of it.
    what : the name's role in the message ("scan id", "manifest item 3 save_template").
    """
    text = str(name)
    bad = None
    if not text.strip():
        bad = "is empty"
    elif any(ord(c) < 32 or ord(c) == 127 for c in text):
        bad = "holds a control character (NUL, newline, ...)"
    elif "\\" in text:
        bad = "holds a backslash"
    elif text.startswith("/") or PurePosixPath(text).is_absolute():
        bad = "is an absolute path"
    elif ".." in PurePosixPath(text).parts:
        bad = "climbs out of its folder with '..'"
    elif not subfolders and "/" in text:
        bad = "holds a '/' (one file or folder name is due)"
    elif text.strip("/") in ("", "."):
        bad = "names the folder itself"
    if bad is None:
        root = Path(folder).resolve()
        path = Path(folder) / text
        if not path.resolve().is_relative_to(root):
            bad = "leads out of the folder through a symbolic link"
    if bad is not None:
        raise TwinFocusError(f"{what} {text!r} {bad}; it must name a file inside {folder}")
    return path
