"""Triangle meshes as plain arrays: reading a mesh file and cleaning its triangles.

Binary STL, the format CAD exports most, is read with numpy alone; other formats go through
trimesh. Keeping the common path free of trimesh keeps its import (with scipy's, about half
a second) out of commands that only ray-cast a part, such as ``flyscan simulate``.

The cleaning matches what ``trimesh.Trimesh.merge_vertices``, ``nondegenerate_faces`` and
``remove_unreferenced_vertices`` do with their defaults, in a few sorts.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

__all__ = ["MERGE_TOL", "read_mesh", "read_binary_stl", "is_binary_stl", "clean_triangles",
           "check_ply_counts"]

#: Vertices closer than this (in the mesh's unit, per coordinate, after rounding) are one,
#: and a triangle thinner than this is degenerate: trimesh's ``tol.merge``.
MERGE_TOL = 1e-8

_STL_HEADER = 84
_STL_RECORD = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)),
                        ("attribute", "<u2")])


def is_binary_stl(path) -> bool:
    """True when `path` is a binary STL whose triangle count matches its size."""
    p = Path(path)
    with open(p, "rb") as fh:
        head = fh.read(_STL_HEADER)
    if len(head) < _STL_HEADER:
        return False
    count = int(np.frombuffer(head, "<u4", 1, 80)[0])
    return p.stat().st_size == _STL_HEADER + _STL_RECORD.itemsize * count


def read_binary_stl(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a binary STL's triangles.

    Parameters
    ----------
    path : str or os.PathLike
        A binary STL (`is_binary_stl`).

    Returns
    -------
    vertices : (3F, 3) float64
        Each triangle's three corners in turn, in the file's unit (not merged: see
        `clean_triangles`).
    faces : (F, 3) int64
        ``[[0, 1, 2], [3, 4, 5], ...]``.
    """
    data = Path(path).read_bytes()
    count = int(np.frombuffer(data, "<u4", 1, 80)[0])
    records = np.frombuffer(data, _STL_RECORD, count, _STL_HEADER)
    vertices = records["corners"].reshape(-1, 3).astype(np.float64)
    return vertices, np.arange(3 * count, dtype=np.int64).reshape(-1, 3)


def read_mesh(path) -> tuple[np.ndarray, np.ndarray]:
    """Read an STL, OBJ or PLY file's vertices (V, 3) float64 and faces (F, 3) int64.

    Binary STL is read by `read_binary_stl`; anything else by ``trimesh.load``.

    Raises
    ------
    ValueError
        The file holds no triangle mesh (a point cloud, a scene of several meshes that
        trimesh could not join, polygons that are not triangles).
    Exception
        Whatever trimesh raises on a file it cannot parse.
    """
    if Path(path).suffix.lower() == ".stl" and is_binary_stl(path):
        return read_binary_stl(path)
    import trimesh

    with warnings.catch_warnings():
        # trimesh's own warnings on odd files are not ours to raise; the result is checked.
        warnings.simplefilter("ignore")
        loaded = trimesh.load(str(path), force="mesh", process=False)
    if not isinstance(loaded, trimesh.Trimesh):
        raise ValueError(f"not a triangle mesh (trimesh read a {type(loaded).__name__})")
    return (np.asarray(loaded.vertices, dtype=np.float64),
            np.asarray(loaded.faces, dtype=np.int64))


def clean_triangles(vertices: np.ndarray, faces: np.ndarray, *,
                    tol: float = MERGE_TOL) -> tuple[np.ndarray, np.ndarray]:
    """Merge coincident vertices, drop degenerate triangles and unused vertices.

    Parameters
    ----------
    vertices : (V, 3) float64
        Finite coordinates.
    faces : (F, 3) int64
        Indices into `vertices`.
    tol : float
        Vertices equal once rounded to this are merged (the first one's coordinates are
        kept); a triangle is degenerate when its longest edge or its height over that edge
        is at most `tol` (trimesh's ``nondegenerate`` test: the sides of its oriented box).

    Returns
    -------
    vertices : (V', 3) float64
        Each vertex used by a kept face once, in the order of first occurrence in `vertices`.
    faces : (F', 3) int64
        The kept faces, in their order, indexing the new vertices.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if len(vertices):
        vertices, faces = _merge(vertices, faces, tol)
    corners = vertices[faces]
    edges = corners[:, [1, 2, 0]] - corners
    longest = np.sqrt((edges ** 2).sum(axis=2).max(axis=1))
    twice_area = np.linalg.norm(np.cross(edges[:, 0], -edges[:, 2]), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        keep = (longest > tol) & (twice_area / longest > tol)
    faces = faces[keep]
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.ravel()] = True
    renumber = np.cumsum(used) - 1
    return vertices[used], renumber[faces]


def _merge(vertices: np.ndarray, faces: np.ndarray, tol: float):
    """Coincident vertices merged by one lexicographic sort of their rounded coordinates."""
    # Rounded as floats, not scaled to integers: any finite coordinate keeps its magnitude.
    key = np.round(vertices, max(0, round(-np.log10(tol)))) if tol > 0 else vertices
    order = np.lexsort(key.T[::-1])
    ordered = key[order]
    starts = np.ones(len(order), dtype=bool)
    np.any(ordered[1:] != ordered[:-1], axis=1, out=starts[1:])
    group = np.cumsum(starts) - 1
    # Each group is represented by its first vertex in file order (a stable sort puts it first).
    first = order[starts]
    rank = np.argsort(first, kind="stable")  # groups renumbered in order of first occurrence
    new_id = np.empty(len(first), dtype=np.int64)
    new_id[rank] = np.arange(len(first))
    index = np.empty(len(order), dtype=np.int64)
    index[order] = new_id[group]
    return vertices[np.sort(first)], index[faces]


#: Bytes of a PLY scalar type, by its names in the header.
_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2,
              "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4,
              "float32": 4, "double": 8, "float64": 8}
#: A PLY header longer than this is not one (a real one is a few hundred bytes).
_PLY_MAX_HEADER = 65536


def check_ply_counts(path) -> None:
    """ValueError when a PLY's header claims more elements than the file can hold: checked
    before a reader allocates for them (a header claiming 100 million faces with one present).
    Each element needs at least its fixed-size properties (a face at least three indices):
    bytes in a binary file, a line in an ASCII one."""
    p = Path(path)
    with open(p, "rb") as fh:
        head = fh.read(_PLY_MAX_HEADER)
    end = head.find(b"end_header")
    newline = head.find(b"\n", end)
    if not head.startswith(b"ply") or end < 0 or newline < 0:
        return  # no header to hold to its counts: the reader refuses the file ("Not a ply file")
    size = p.stat().st_size
    body_bytes = size - (newline + 1)
    fmt, elements = None, []  # [name, count, minimum bytes of one]
    for line in head[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if len(words) >= 2 and words[0] == "format":
            fmt = words[1]
        elif len(words) == 3 and words[0] == "element":
            if not words[2].isdigit():
                raise ValueError(f"PLY element {words[1]!r} has count {words[2]!r}")
            elements.append([words[1], int(words[2]), 0])
        elif len(words) >= 3 and words[0] == "property" and elements:
            one = elements[-1]
            if words[1] == "list" and len(words) >= 5:
                # a face lists at least three vertices; another list may be empty
                items = 3 if one[0] == "face" else 0
                one[2] += _PLY_SIZES.get(words[2], 1) + items * _PLY_SIZES.get(words[3], 1)
            else:
                one[2] += _PLY_SIZES.get(words[1], 1)
    if fmt is None or fmt == "ascii":
        # one line per element at least
        whole = size <= len(head)  # the file was read whole with its header
        have = head[newline + 1:].count(b"\n") if whole else _count_lines(p, newline + 1)
        need = sum(count for _, count, _ in elements)
        what = "lines"
    else:
        have, need = body_bytes, sum(count * size for _, count, size in elements)
        what = "bytes"
    if need > have + (what == "lines"):  # an ASCII file's last line may lack its newline
        claimed = ", ".join(f"{name} {count}" for name, count, _ in elements)
        raise ValueError(f"its PLY header claims {claimed}, which need at least {need} {what}; "
                         f"the file has {have}")


def _count_lines(p: Path, offset: int) -> int:
    count = 0
    with open(p, "rb") as fh:
        fh.seek(offset)
        while chunk := fh.read(1 << 20):
            count += chunk.count(b"\n")
    return count
