"""Reasons the service gives, without the server's absolute paths.

A reason goes to a client (a REST error, a scan's ``reason``, a recording's ``path``): a path
on the server is named relative to the data folder (``scans/.tmp-...``), never absolutely (it
tells a client nothing it can use, and tells anyone on the cell network how the server is laid
out).
"""
from __future__ import annotations

import errno
import os
from pathlib import Path

__all__ = ["disk_reason", "relative_text", "relative_path", "DISK_FULL"]

#: errno values that mean "no room", as opposed to a disk that refuses writes.
DISK_FULL = frozenset({errno.ENOSPC, errno.EDQUOT})


def relative_path(path, root: Path) -> str:
    """``path`` relative to ``root`` when it lies inside it, else its last component."""
    path = Path(path)
    for base in (root, root.resolve()):
        try:
            return path.relative_to(base).as_posix() or "."
        except ValueError:
            pass
    try:
        return path.resolve().relative_to(root.resolve()).as_posix() or "."
    except (ValueError, OSError):
        return path.name


def relative_text(text: str, root: Path) -> str:
    """``text`` with the data folder's absolute path (as given and resolved) taken out."""
    for base in sorted({str(root.resolve()), os.path.abspath(root), str(root)}, key=len,
                       reverse=True):
        if base not in (".", ""):
            text = text.replace(base + os.sep, "").replace(base, ".")
    return text


def disk_reason(exc: OSError, root: Path) -> str:
    """What the disk said (``No space left on device``) and of which file, relative to
    ``root``."""
    what = exc.strerror or type(exc).__name__
    if exc.filename is not None:
        return f"{what} ({relative_path(exc.filename, root)})"
    return relative_text(str(exc), root) if not exc.strerror else what
