"""Point clouds to and from PLY files, with numpy only.

The scanner's clouds leave it as binary little-endian PLY: float32 ``x, y, z`` in millimetres in
the gripper frame {T}, plus optional per-vertex properties (quality, frame id, ...). This module
writes exactly that, atomically, and reads back the vertex element of any PLY with scalar vertex
properties (binary little- or big-endian, or ASCII), so a cloud from another tool loads as well.
"""
from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from scanner_core.fileio import write_bytes_atomic, write_parts_atomic

__all__ = ["write_ply", "write_ply_rows", "read_ply", "PLY_TYPES"]

#: PLY scalar type name -> numpy dtype (native byte order; the file's order is applied on use).
PLY_TYPES: dict[str, np.dtype] = {
    "char": np.dtype("i1"), "uchar": np.dtype("u1"),
    "short": np.dtype("i2"), "ushort": np.dtype("u2"),
    "int": np.dtype("i4"), "uint": np.dtype("u4"),
    "float": np.dtype("f4"), "double": np.dtype("f8"),
    # Aliases found in the wild (the PLY spec allows both spellings).
    "int8": np.dtype("i1"), "uint8": np.dtype("u1"),
    "int16": np.dtype("i2"), "uint16": np.dtype("u2"),
    "int32": np.dtype("i4"), "uint32": np.dtype("u4"),
    "float32": np.dtype("f4"), "float64": np.dtype("f8"),
}

# numpy dtype (kind, itemsize) -> the canonical PLY name written to files.
_PLY_NAME = {
    ("i", 1): "char", ("u", 1): "uchar", ("i", 2): "short", ("u", 2): "ushort",
    ("i", 4): "int", ("u", 4): "uint", ("f", 4): "float", ("f", 8): "double",
}
_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}
_COORDS = ("x", "y", "z")
# A property name: no whitespace, printable ASCII, so the header stays one token per word.
_NAME_RE = re.compile(r"^[!-~]+$")
# Bound on header size, so reading a file that is not a PLY (or a corrupt one) always ends.
_MAX_HEADER_LINES = 10_000
_MAX_HEADER_BYTES = 1 << 20


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------

def write_ply(path, points, *, fields: Mapping[str, np.ndarray] | None = None,
              comments: Iterable[str] = ()) -> Path:
    """Write a point cloud as a binary little-endian PLY file, atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Destination file. Its directory must exist. The file is written to a temporary file in
        the same directory and moved into place, so a failure never leaves a partial file.
    points : (N, 3) array_like of float, or (N,) structured ndarray
        Point coordinates, mm, normally in the gripper frame {T}. Stored as float32 ``x, y, z``.
        N may be 0 (a valid, empty PLY).
        Or the whole vertex table at once: a structured array whose first fields are
        little-endian float32 ``x, y, z``, followed by the other properties (scalar fields of
        the dtypes below, little-endian, in file order; `fields` must then be None). Its
        bytes are written as they are, without a copy: the fast path for large clouds. The
        file is the one the (N, 3) form with the same values and `fields` gives.
    fields : dict of str -> (N,) ndarray, optional
        Extra per-vertex properties, in order. Allowed dtypes: int8, uint8, int16, uint16,
        int32, uint32, float32, float64 (PLY char, uchar, short, ushort, int, uint, float,
        double); bool is stored as uchar. Names must be single printable words other than
        ``x``, ``y``, ``z``.
    comments : iterable of str, optional
        Header comment lines (no line breaks).

    Returns
    -------
    pathlib.Path
        The path written.

    Raises
    ------
    ValueError
        When `points`, `fields` or `comments` do not match the above; the message names the
        offending parameter.
    """
    path = Path(path)
    if isinstance(points, np.ndarray) and points.dtype.names is not None:
        if fields is not None:
            raise ValueError("`fields` must be None when `points` is a structured vertex table")
        return write_ply_rows(path, points, comments=comments)
    pts = _check_points(points)
    n = pts.shape[0]
    extra = _check_fields(fields, n)
    comment_lines = _check_comments(comments)

    dtype = np.dtype([(c, "<f4") for c in _COORDS]
                     + [(name, arr.dtype.newbyteorder("<")) for name, arr in extra.items()])
    data = np.empty(n, dtype=dtype)
    for i, c in enumerate(_COORDS):
        data[c] = pts[:, i]
    for name, arr in extra.items():
        data[name] = arr

    blob = _header(n, data.dtype, comment_lines) + data.tobytes()
    write_bytes_atomic(path, blob)
    return path


def _header(n: int, dtype: np.dtype, comment_lines: list[str]) -> bytes:
    """The header of `n` vertices of `dtype` (float32 x, y, z first), as bytes."""
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {c}" if c else "comment" for c in comment_lines]
    header.append(f"element vertex {n}")
    header += [f"property float {c}" for c in _COORDS]
    header += [f"property {_PLY_NAME[(dtype[name].kind, dtype[name].itemsize)]} {name}"
               for name in dtype.names[3:]]
    header.append("end_header")
    return ("\n".join(header) + "\n").encode("ascii")


def write_ply_rows(path, rows, *, count: int | None = None, comments: Iterable[str] = ()) -> Path:
    """Write a vertex table as binary little-endian PLY, atomically, as it is: no copy.

    The fast path of `write_ply` for large clouds: the rows' bytes go to the file unchanged,
    from one structured array or from blocks of rows made as they are written (so the whole
    table never needs to exist at once). The file is the one `write_ply` gives for the same
    values with the (N, 3) points and the other fields as `fields`.

    Parameters
    ----------
    path : str or os.PathLike
        Destination file; its directory must exist. Written to a temporary file in the same
        directory and moved into place, so a failure never leaves a partial file.
    rows : (N,) structured ndarray, or an iterable of them
        Little-endian float32 ``x, y, z`` first, then the other vertex properties, in file
        order: packed scalar fields of the dtypes `write_ply` allows. Blocks must share one
        dtype; each is written before the next is asked for, so a producer may reuse its
        buffers.
    count : int, optional
        Number of rows in all (the header comes first). Required with blocks, checked against
        the rows written.
    comments : iterable of str, optional
        Header comment lines.

    Returns
    -------
    pathlib.Path

    Raises
    ------
    ValueError
        A dtype PLY cannot store as it is, non-finite coordinates, blocks of another dtype, or
        a `count` the rows do not match; nothing is left at `path`.
    """
    path = Path(path)
    comment_lines = _check_comments(comments)
    if isinstance(rows, np.ndarray):
        if count is not None and count != len(rows):
            raise ValueError(f"`count` {count} does not match the {len(rows)} rows given")
        count, rows = len(rows), (rows,)
    elif count is None or int(count) < 0:
        raise ValueError(f"`count` must give the number of rows when `rows` come in blocks, "
                         f"got {count!r}")
    blocks = iter(rows)
    first = next(blocks, None)
    if first is None:
        raise ValueError("`rows` must hold at least one block (an empty one for no rows)")
    dtype = first.dtype if isinstance(first, np.ndarray) else None
    _check_row_dtype(dtype)

    def checked():
        written = 0
        for block in _chain(first, blocks):
            if (not isinstance(block, np.ndarray) or block.dtype != dtype or block.ndim != 1
                    or not block.flags.c_contiguous):
                raise ValueError(f"`rows` blocks must be 1-D C-contiguous arrays of {dtype}")
            for c in _COORDS:
                if not np.all(np.isfinite(block[c])):
                    raise ValueError("`points` must be finite: a cloud with NaN or inf is "
                                     "never written")
            written += len(block)
            if written > count:
                break
            yield block
        if written != count:
            raise ValueError(f"`rows` held {written} rows, the header promised `count` {count}")

    write_parts_atomic(path, _chain(_header(int(count), dtype, comment_lines), checked()))
    return path


def _chain(first, rest):
    yield first
    yield from rest


def _check_row_dtype(dtype) -> None:
    """Raise unless `dtype` is a PLY vertex row: packed little-endian scalars, x, y, z first."""
    if dtype is None or dtype.names is None:
        raise ValueError(f"`rows` must be structured arrays, got {dtype}")
    names = dtype.names
    if names[:3] != _COORDS or any(dtype[c] != np.dtype("<f4") for c in _COORDS):
        raise ValueError(f"`rows` must start with float32 x, y, z, got "
                         f"{[(name, str(dtype[name])) for name in names[:3]]}")
    offset = 0
    for name in names:
        field_dt, at = dtype.fields[name][:2]
        if not _NAME_RE.match(name):
            raise ValueError(f"`rows` field name {name!r} must be a single printable ASCII word")
        if (field_dt.shape or (field_dt.kind, field_dt.itemsize) not in _PLY_NAME
                or field_dt.byteorder == ">" or at != offset):
            raise ValueError(f"`rows` field {name!r} ({field_dt} at byte {at}) is not a packed "
                             "little-endian scalar PLY can store")
        offset += field_dt.itemsize
    if offset != dtype.itemsize:
        raise ValueError(f"`rows` hold {dtype.itemsize - offset} bytes of padding")


def _check_points(points) -> np.ndarray:
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] != 3 or not (
            np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"`points` must be (N, 3) float, got {arr.shape} {arr.dtype}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("`points` must be finite: a cloud with NaN or inf is never written")
    return arr


def _check_fields(fields, n: int) -> dict[str, np.ndarray]:
    if fields is None:
        return {}
    if not isinstance(fields, Mapping):
        raise ValueError(f"`fields` must be a dict of name -> (N,) array, got {type(fields).__name__}")
    out: dict[str, np.ndarray] = {}
    for name, value in fields.items():
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise ValueError(f"`fields` name {name!r} must be a single printable ASCII word")
        if name in _COORDS:
            raise ValueError(f"`fields` name {name!r} clashes with the coordinates x, y, z")
        arr = np.asarray(value)
        if arr.dtype == np.bool_:
            arr = arr.astype(np.uint8)
        if arr.shape != (n,):
            raise ValueError(f"`fields[{name!r}]` must have shape ({n},) like `points`, "
                             f"got {arr.shape}")
        if (arr.dtype.kind, arr.dtype.itemsize) not in _PLY_NAME:
            raise ValueError(
                f"`fields[{name!r}]` has dtype {arr.dtype}, which PLY cannot store; use one of "
                "int8, uint8, int16, uint16, int32, uint32, float32, float64")
        out[name] = arr
    return out


def _check_comments(comments) -> list[str]:
    if isinstance(comments, str):
        comments = [comments]
    out = []
    for c in comments:
        c = str(c)
        if "\n" in c or "\r" in c:
            raise ValueError(f"`comments` entries must be single lines, got {c!r}")
        if not c.isascii():
            raise ValueError(f"`comments` entries must be ASCII, got {c!r}")
        out.append(c)
    return out


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------

class _Element:
    def __init__(self, name: str, count: int):
        self.name = name
        self.count = count
        self.props: list[tuple[str, np.dtype | None]] = []  # dtype None for a list property

    @property
    def scalar(self) -> bool:
        return all(dt is not None for _, dt in self.props)


def read_ply(path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read the vertices of a PLY file.

    Reads binary (little- or big-endian) and ASCII PLY. Only the ``vertex`` element is
    returned; elements after it (faces, ...) are ignored, and elements before it are skipped
    when their size is fixed (scalar properties only, or any ASCII file).

    Parameters
    ----------
    path : str or os.PathLike
        The PLY file.

    Returns
    -------
    points : (N, 3) float32
        ``x, y, z`` as stored in the file (mm in {T} for the scanner's clouds); coordinates
        stored as double are cast to float32.
    fields : dict of str -> (N,) ndarray
        The other vertex properties, in file order, with their stored dtype (native byte
        order).

    Raises
    ------
    ValueError
        On a malformed header, a vertex element that is missing, lacks ``x, y, z`` or has list
        properties, an unskippable element before the vertices, or truncated data. The message
        names the file.
    FileNotFoundError
        When `path` does not exist.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        fmt, elements = _read_header(fh, path)
        vertex, skip = _find_vertex(elements, fmt, path)
        if fmt is None:
            table = _read_ascii(fh, vertex, skip, path)
        else:
            table = _read_binary(fh, vertex, skip, fmt, path)
    points = np.stack([table[c] for c in _COORDS], axis=1).astype(np.float32, copy=False)
    fields = {name: np.ascontiguousarray(table[name]) for name, _ in vertex.props
              if name not in _COORDS}
    return np.ascontiguousarray(points), fields


def _read_header(fh, path: Path) -> tuple[str | None, list[_Element]]:
    first = fh.readline(64)
    if first.rstrip(b"\r\n") != b"ply":
        raise ValueError(f"{path}: not a PLY file (first line {first[:20]!r}, expected b'ply')")
    fmt_order: str | None = None
    have_format = False
    elements: list[_Element] = []
    total = len(first)
    for _ in range(_MAX_HEADER_LINES):
        raw = fh.readline(_MAX_HEADER_BYTES)
        total += len(raw)
        if not raw:
            raise ValueError(f"{path}: PLY header ends without 'end_header'")
        if total > _MAX_HEADER_BYTES:
            raise ValueError(f"{path}: PLY header longer than {_MAX_HEADER_BYTES} bytes")
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise ValueError(f"{path}: PLY header has non-ASCII bytes: {raw[:40]!r}") from None
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        key = words[0]
        if key == "end_header":
            break
        if key == "format":
            if len(words) != 3 or words[1] not in _FORMATS:
                raise ValueError(f"{path}: bad PLY format line {line!r}; expected one of "
                                 f"{sorted(_FORMATS)}")
            fmt_order, have_format = _FORMATS[words[1]], True
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise ValueError(f"{path}: bad PLY element line {line!r}")
            elements.append(_Element(words[1], int(words[2])))
        elif key == "property":
            if not elements:
                raise ValueError(f"{path}: PLY property before any element: {line!r}")
            elements[-1].props.append(_parse_property(words, line, path))
        else:
            raise ValueError(f"{path}: unknown PLY header line {line!r}")
    else:
        raise ValueError(f"{path}: PLY header has more than {_MAX_HEADER_LINES} lines")
    if not have_format:
        raise ValueError(f"{path}: PLY header has no format line")
    return fmt_order, elements


def _parse_property(words: list[str], line: str, path: Path) -> tuple[str, np.dtype | None]:
    if len(words) == 3 and words[1] in PLY_TYPES:
        return words[2], PLY_TYPES[words[1]]
    if (len(words) == 5 and words[1] == "list" and words[2] in PLY_TYPES
            and words[3] in PLY_TYPES):
        return words[4], None
    raise ValueError(f"{path}: bad PLY property line {line!r}")


def _find_vertex(elements: list[_Element], fmt: str | None, path: Path):
    skip_bytes = 0
    skip_rows = 0
    for el in elements:
        if el.name == "vertex":
            if not el.scalar:
                raise ValueError(f"{path}: PLY vertex element has list properties; only scalar "
                                 "vertex properties are supported")
            names = [n for n, _ in el.props]
            missing = [c for c in _COORDS if c not in names]
            if missing:
                raise ValueError(f"{path}: PLY vertex element lacks properties {missing}")
            if len(set(names)) != len(names):
                raise ValueError(f"{path}: PLY vertex element repeats a property name: {names}")
            return el, (skip_rows if fmt is None else skip_bytes)
        if fmt is not None and not el.scalar:
            raise ValueError(f"{path}: PLY element {el.name!r} with list properties comes before "
                             "the vertex element; cannot skip it in a binary file")
        skip_rows += el.count
        if fmt is not None:
            skip_bytes += el.count * _row_dtype(el, fmt).itemsize
    raise ValueError(f"{path}: PLY file has no vertex element")


def _row_dtype(el: _Element, order: str) -> np.dtype:
    return np.dtype([(name, dt.newbyteorder(order)) for name, dt in el.props])


def _read_binary(fh, vertex: _Element, skip: int, order: str, path: Path) -> np.ndarray:
    dtype = _row_dtype(vertex, order)
    if skip:
        got = len(fh.read(skip))
        if got != skip:
            raise ValueError(f"{path}: PLY data truncated before the vertex element")
    need = vertex.count * dtype.itemsize
    blob = fh.read(need)
    if len(blob) != need:
        raise ValueError(f"{path}: PLY data truncated: {vertex.count} vertices need {need} bytes, "
                         f"the file has {len(blob)}")
    table = np.frombuffer(blob, dtype=dtype, count=vertex.count)
    native = np.dtype([(name, dt) for name, dt in vertex.props])
    return table.astype(native)


def _read_ascii(fh, vertex: _Element, skip_rows: int, path: Path) -> np.ndarray:
    lines: list[list[bytes]] = []
    n_props = len(vertex.props)
    skipped = 0
    for raw in fh:
        words = raw.split()
        if not words:
            continue  # blank lines are not rows
        if skipped < skip_rows:
            skipped += 1
            continue
        if len(words) != n_props:
            raise ValueError(f"{path}: PLY vertex row {len(lines)} has {len(words)} values, "
                             f"expected {n_props}")
        lines.append(words)
        if len(lines) == vertex.count:
            break
    if len(lines) != vertex.count:
        raise ValueError(f"{path}: PLY data truncated: expected {vertex.count} vertex rows, "
                         f"found {len(lines)}")
    native = np.dtype([(name, dt) for name, dt in vertex.props])
    table = np.empty(vertex.count, dtype=native)
    if vertex.count:
        cols = np.array(lines, dtype=object).T
        for i, (name, dt) in enumerate(vertex.props):
            try:
                if dt.kind == "f":
                    table[name] = np.array(cols[i], dtype=np.float64)
                else:
                    table[name] = np.array([int(v) for v in cols[i]], dtype=dt)
            except (ValueError, OverflowError) as exc:
                raise ValueError(f"{path}: PLY property {name!r} has a bad value: {exc}") from None
    return table
