"""The parts the service knows: meshes uploaded with their unit, and those built in (the
simulated cell's demo block, handed in by its driver).

An uploaded part is kept as ``parts/<name>/mesh.<ext>`` with ``part.json`` (its unit and
grasp), written into a temporary folder and renamed into place, and loaded again at start.
Every part is checked as ``flyscan scan`` checks it (readable, plausible size for its unit,
fits the inspection volume at its nominal grasp) before it is accepted.
"""
from __future__ import annotations

import json
import logging
import os
import re
import shutil
import tempfile
import threading
from pathlib import Path

import numpy as np

from scanner_core.cad import GRASPS, PartError, PartModel, check_fits, load_part

log = logging.getLogger("flyscan.parts")

DEMO_PART = "demo"
#: Part names become folder names: no leading dot (".", ".." and hidden folders), no separator.
PART_NAME = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}$")
MESH_SUFFIXES = (".stl", ".obj", ".ply")
#: Uploaded meshes larger than this are refused (a CAD part of a bin-picking cell is far smaller).
MAX_MESH_BYTES = 64 * 1024 * 1024


def part_info(part: PartModel) -> dict:
    return {"name": part.name, "units": part.units, "faces": int(len(part.faces)),
            "source": "built-in" if part.source.startswith("procedural") else "uploaded",
            "extents_mm": np.round(part.extents, 4).tolist(),
            "nominal_grasp": np.asarray(part.grasp).tolist()}


def _checked(load) -> PartModel:
    """Load a part (`load_part` refuses a size implausible for its unit) that fits the volume."""
    part = load()
    check_fits(part)
    return part


class PartLibrary:
    """Parts by name (``scanner_core.cad.PartModel``). Thread-safe.

    Parameters
    ----------
    root : path-like
        The data folder: uploaded parts live in its ``parts/``.
    builtin : dict of str to PartModel, optional
        Parts that come with the cell (the simulated cell's demo block); not stored, not
        replaceable by an upload.
    """

    def __init__(self, root, builtin: dict | None = None):
        self.root = Path(root) / "parts"
        self._builtin = dict(builtin or {})
        self._parts: dict[str, PartModel] = {}
        self._lock = threading.Lock()

    def open(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        self._parts.update(self._builtin)
        for folder in sorted(self.root.iterdir()):
            if folder.name.startswith(".tmp-"):
                shutil.rmtree(folder, ignore_errors=True)  # an upload that never finished
                continue
            if not (folder / "part.json").is_file():
                continue
            try:
                meta = json.loads((folder / "part.json").read_text())
                self._parts[folder.name] = load_part(folder / meta["file"], meta["units"],
                                                     name=folder.name, grasp=_grasp(meta["grasp"]))
            except (OSError, ValueError, KeyError, TypeError) as exc:  # PartError is a ValueError
                log.error("stored part %s skipped: %s", folder.name, exc)

    def names(self) -> list[str]:
        with self._lock:
            return sorted(self._parts)

    def get(self, name: str) -> PartModel:
        with self._lock:
            return self._parts[name]

    def add(self, name: str, data: bytes, units: str, *, suffix: str = ".stl",
            grasp="centred") -> PartModel:
        """Check and keep an uploaded mesh; raises PartError (or ValueError) with the reason.
        ``grasp``: a name of ``GRASPS``, or the nominal ^T X_P itself, (4, 4) mm."""
        if not PART_NAME.match(name) or name in self._builtin:
            raise ValueError(f"part name must be 1-64 letters, digits, '.', '_' or '-', not start "
                             f"with '.', and not be a built-in part's "
                             f"({', '.join(sorted(self._builtin)) or 'none'}), got {name!r}")
        if suffix not in MESH_SUFFIXES:
            raise ValueError(f"mesh format must be one of {', '.join(MESH_SUFFIXES)}, got {suffix!r}")
        if not data:
            raise PartError("the mesh file is empty")
        if len(data) > MAX_MESH_BYTES:
            raise PartError(f"the mesh file is larger than {MAX_MESH_BYTES >> 20} MiB")
        tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{name}-", dir=self.root))  # one per upload
        try:
            mesh_path = tmp / f"mesh{suffix}"
            mesh_path.write_bytes(data)
            try:
                part = _checked(lambda: load_part(mesh_path, units, name=name, grasp=_grasp(grasp)))
            except PartError as exc:  # said of the upload, not of a path on the server
                raise PartError(str(exc).replace(f" ({mesh_path})", "").replace(str(mesh_path),
                                                                                "the upload")) from None
            (tmp / "part.json").write_text(json.dumps({
                "file": mesh_path.name, "units": part.units,
                "grasp": grasp if isinstance(grasp, str) else np.asarray(part.grasp).tolist()}))
            final = self.root / name
            if final.resolve().parent != self.root.resolve():
                raise ValueError(f"part name {name!r} is not a plain folder name")
            with self._lock:
                shutil.rmtree(final, ignore_errors=True)
                os.replace(tmp, final)
                self._parts[name] = part
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        return part


def _grasp(kind):
    """A grasp name of ``GRASPS``, or a 4x4 (``load_part`` checks it is rigid)."""
    if not isinstance(kind, str):
        return np.asarray(kind, dtype=np.float64)
    if kind not in GRASPS:
        raise ValueError(f"grasp must be one of {', '.join(GRASPS)}, got {kind!r}")
    return kind


def grasp_from_query(text: str) -> np.ndarray:
    """``grasp_matrix`` of ``PUT /parts``: 16 comma-separated numbers -> (4, 4) float64 (row-
    major, mm); ValueError unless 16 finite numbers (rigidity is ``load_part``'s check)."""
    try:
        values = np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise ValueError(f"grasp_matrix must be 16 comma-separated numbers, got {text!r}") from None
    if values.shape != (16,) or not np.all(np.isfinite(values)):
        raise ValueError(f"grasp_matrix must be 16 finite numbers (a 4x4, row-major), got "
                         f"{values.size}")
    return values.reshape(4, 4)
