"""Atomic file writes: a failure never leaves a partial file where a complete one is expected."""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path


def write_bytes_atomic(path, blob: bytes) -> None:
    """Write through a temporary file in the same folder, then rename it into place."""
    write_parts_atomic(path, (blob,))


def write_parts_atomic(path, parts) -> None:
    """As `write_bytes_atomic`, for buffers written in turn, none copied: an exception from
    `parts` (an iterable of bytes-like objects), as from the writing, leaves nothing."""
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            for part in parts:
                fh.write(memoryview(part).cast("B"))
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)  # mkstemp makes 0600; results are meant to be read by others
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def save_json_atomic(path, data: dict) -> None:
    """JSON (indented, NaN refused: it is not JSON) written atomically."""
    text = json.dumps(data, indent=2, allow_nan=False) + "\n"
    write_bytes_atomic(path, text.encode())
