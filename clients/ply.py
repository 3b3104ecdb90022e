"""A small reader for the PLY files the service serves (``/scans/{id}/cloud.ply``, ``edges.ply``).

Only what the service writes is accepted: ``format binary_little_endian 1.0``, a single
``vertex`` element with scalar properties of the common types (``char``/``int8`` ...
``double``/``float64``). ASCII or big-endian files, other elements (faces), list properties,
truncated data and trailing bytes are refused with a :class:`PlyError` that says why.

    >>> fields = parse_ply(data)            # {"x": (N,) float32, "y": ..., "frame_id": (N,) int32}
    >>> xyz = xyz_array(fields)             # (N, 3) float32, mm in {T}

Pure standard library and numpy: nothing is evaluated or unpickled.
"""
from __future__ import annotations

import numpy as np

__all__ = ["PlyError", "parse_ply", "xyz_array"]

# PLY scalar type names (both spellings of the spec) -> little-endian numpy dtypes.
_SCALAR_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2",
    "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4",
    "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4",
    "double": "<f8", "float64": "<f8",
}
_END_HEADER = b"end_header"
# A header longer than this is not one the service wrote; stop looking for end_header there.
_MAX_HEADER_BYTES = 64 * 1024


class PlyError(ValueError):
    """The bytes are not a binary little-endian, vertex-only PLY file this reader accepts."""


def parse_ply(data: bytes) -> dict[str, np.ndarray]:
    """Parse a binary little-endian, vertex-only PLY file.

    Parameters
    ----------
    data : bytes
        The whole file.

    Returns
    -------
    fields : dict of str to (N,) ndarray
        One array per vertex property, in header order, with the property's own dtype
        (``float`` -> float32, ``int`` -> int32, ...). Each array owns its memory.

    Raises
    ------
    PlyError
        Not a PLY file, another format, another element, a list property, an unknown type,
        or a data section whose length does not match the header.
    """
    view = memoryview(data)
    count, dtype, body_start = _parse_header(bytes(view[:_MAX_HEADER_BYTES]))
    body = view[body_start:]
    expected = count * dtype.itemsize
    if len(body) < expected:
        raise PlyError(f"PLY data truncated: header announces {count} vertices "
                       f"({expected} bytes), the file holds {len(body)} bytes after the header")
    if len(body) > expected:
        raise PlyError(f"PLY data has {len(body) - expected} trailing bytes after the "
                       f"{count} vertices the header announces")
    records = np.frombuffer(body, dtype=dtype, count=count)
    return {name: np.array(records[name]) for name in dtype.names}


def xyz_array(fields: dict[str, np.ndarray]) -> np.ndarray:
    """Stack the ``x``, ``y``, ``z`` properties into an (N, 3) float32 C-order array."""
    missing = [axis for axis in ("x", "y", "z") if axis not in fields]
    if missing:
        raise PlyError(f"PLY vertices lack the properties {missing}; they have {list(fields)}")
    return np.stack([fields["x"], fields["y"], fields["z"]], axis=1).astype(np.float32, copy=False)


def _parse_header(head: bytes) -> tuple[int, np.dtype, int]:
    """Return (vertex count, structured dtype of one vertex, offset of the data section)."""
    if not (head.startswith(b"ply\n") or head.startswith(b"ply\r\n")):
        raise PlyError(f"not a PLY file: it starts with {head[:16]!r}, not the line 'ply'")
    raw_lines = []
    offset = 0
    while True:
        newline = head.find(b"\n", offset)
        if newline < 0:
            raise PlyError("PLY header has no 'end_header' line (truncated or not PLY)")
        raw = head[offset:newline].rstrip(b"\r")
        offset = newline + 1
        if raw == _END_HEADER:
            break
        raw_lines.append(raw)
    try:
        lines = [raw.decode("ascii") for raw in raw_lines[1:]]
    except UnicodeDecodeError as exc:
        raise PlyError(f"PLY header is not ASCII: {exc}") from None

    fmt = None
    count = None
    fields: list[tuple[str, str]] = []
    for line in lines:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        keyword = words[0]
        if keyword == "format":
            fmt = " ".join(words[1:])
            if fmt != "binary_little_endian 1.0":
                raise PlyError(f"PLY format {fmt!r} not supported: only "
                               "'binary_little_endian 1.0'")
        elif keyword == "element":
            if count is not None or len(words) != 3 or words[1] != "vertex":
                raise PlyError(f"PLY element {' '.join(words[1:])!r} not supported: only one "
                               "'vertex' element (a point cloud)")
            try:
                count = int(words[2])
            except ValueError:
                raise PlyError(f"PLY vertex count {words[2]!r} is not an integer") from None
            if count < 0:
                raise PlyError(f"PLY vertex count {count} is negative")
        elif keyword == "property":
            if count is None:
                raise PlyError("PLY property before any element")
            if len(words) != 3 or words[1] == "list":
                raise PlyError(f"PLY property {' '.join(words[1:])!r} not supported: only "
                               "scalar properties")
            type_name, name = words[1], words[2]
            if type_name not in _SCALAR_TYPES:
                raise PlyError(f"PLY property {name!r} has unknown type {type_name!r}; "
                               f"known: {sorted(_SCALAR_TYPES)}")
            if any(name == seen for seen, _ in fields):
                raise PlyError(f"PLY property {name!r} appears twice")
            fields.append((name, _SCALAR_TYPES[type_name]))
        else:
            raise PlyError(f"unexpected PLY header line {line!r}")
    if fmt is None:
        raise PlyError("PLY header has no 'format' line")
    if count is None:
        raise PlyError("PLY header has no 'element vertex N' line")
    if not fields:
        raise PlyError("PLY vertex element has no properties")
    return count, np.dtype(fields), offset
