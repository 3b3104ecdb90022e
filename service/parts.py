"""The parts the service knows: meshes uploaded with their unit, and those built in (the
simulated cell's demo block, handed in by its driver).

An uploaded part is kept as ``parts/<name>/mesh.<ext>`` with ``part.json`` (its unit and
grasp), written into a temporary folder and renamed into place, and loaded again at start.
A part's scan plan (``flyscan plan``'s ``plan.json``, read by ``scanner_core.scanplan``)
placed in its folder gives its nominal grasp at start: the plan's grasp turned by its pass
direction (it must have been made for that mesh file).
Every part is checked as ``flyscan scan`` checks it (readable, counts consistent with the
file, plausible size for its unit, fits the inspection volume at its nominal grasp) and as a
solid (`check_solid`: a thickness and a volume) before it is accepted. An upload is streamed
to disk (`staging`, then `add_staged`): its bytes are never held in memory whole.
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
from scanner_core.scanplan import check_plan_grasp, load_scan_plan

log = logging.getLogger("flyscan.parts")

DEMO_PART = "demo"
#: Part names become folder names: no leading dot (".", ".." and hidden folders), no separator.
PART_NAME = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}$")
MESH_SUFFIXES = (".stl", ".obj", ".ply")
#: A part thinner than this across its thinnest principal axis is no part, mm: the scanner
#: resolves about 0.02 mm, and sheet metal is 0.5 mm and up (a lone triangle has 0).
MIN_THICKNESS_MM = 0.2
#: The smallest volume of a part's box along its principal axes, mm^3.
MIN_VOLUME_MM3 = 1.0
#: The least area a part's triangles cover, as a share of its principal box's largest face:
#: any surface spanning the box covers about it or more (a plate one side of it, a solid
#: twice and up, a rod pi / 2), while slivers with no area cover none.
MIN_AREA_SHARE = 0.05
STAGING_PREFIX = ".tmp-"
#: A stored part's scan plan, beside its part.json.
PLAN_FILE = "plan.json"


class PartQuotaExceeded(Exception):
    """The library holds ``max_parts`` uploaded parts already."""


class PartInUse(Exception):
    """A part that cannot be deleted now (built in, the default, or a pending scan's)."""


def part_info(part: PartModel) -> dict:
    return {"name": part.name, "version": part.version, "units": part.units,
            "faces": int(len(part.faces)),
            "source": "built-in" if part.source.startswith("procedural") else "uploaded",
            "extents_mm": np.round(part.extents, 4).tolist(),
            "nominal_grasp": np.asarray(part.grasp).tolist()}


def check_solid(part: PartModel) -> None:
    """PartError unless the part has a thickness, a volume and a surface: its vertices' extent
    along their thinnest principal axis at least `MIN_THICKNESS_MM`, the box along its
    principal axes at least `MIN_VOLUME_MM3`, and its triangles' area at least
    `MIN_AREA_SHARE` of that box's largest face."""
    vertices = np.asarray(part.vertices, np.float64)
    centred = vertices - vertices.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    extents = np.ptp(centred @ axes.T, axis=0) if len(axes) == 3 else np.zeros(3)
    if extents.min() < MIN_THICKNESS_MM:
        raise PartError(f"the mesh has no thickness: {extents.min():.3g} mm across its thinnest "
                        f"axis (a part is at least {MIN_THICKNESS_MM} mm thick)")
    if np.prod(extents) < MIN_VOLUME_MM3:
        raise PartError(f"the mesh has no volume: its box is {np.prod(extents):.3g} mm^3 "
                        f"(a part at least {MIN_VOLUME_MM3} mm^3)")
    corners = vertices[np.asarray(part.faces)]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                         corners[:, 2] - corners[:, 0]), axis=1).sum()
    face = np.sort(extents)[-2:].prod()
    if area < MIN_AREA_SHARE * face:
        raise PartError(f"the mesh's triangles cover {area:.3g} mm^2, a surface across its "
                        f"{face:.3g} mm^2 box face covers that or more: its triangles are "
                        f"slivers with no area, nothing the scanner could register against")


def _checked(load) -> PartModel:
    """Load a part (`load_part` refuses a size implausible for its unit) that is a solid and
    fits the volume."""
    part = load()
    check_solid(part)
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
        replaceable by an upload, not deletable.
    max_parts : int
        Uploaded parts kept at most (an upload of a new name beyond: `PartQuotaExceeded`).
    """

    def __init__(self, root, builtin: dict | None = None, max_parts: int = 100):
        self.root = Path(root) / "parts"
        self.max_parts = int(max_parts)
        self._builtin = dict(builtin or {})
        self._parts: dict[str, PartModel] = {}
        self._lock = threading.Lock()

    def open(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        self._parts.update(self._builtin)
        for folder in sorted(self.root.iterdir()):
            if folder.name.startswith(STAGING_PREFIX):
                shutil.rmtree(folder, ignore_errors=True)  # an upload that never finished
                continue
            if not (folder / "part.json").is_file():
                continue
            try:
                meta = json.loads((folder / "part.json").read_text())
                grasp = _grasp(meta["grasp"])
                if (folder / PLAN_FILE).is_file():
                    plan = load_scan_plan(folder / PLAN_FILE)
                    plan.check_mesh(folder / meta["file"])
                    grasp = plan.nominal_grasp
                part = load_part(folder / meta["file"], meta["units"], name=folder.name,
                                 grasp=grasp)
                if (folder / PLAN_FILE).is_file():
                    check_plan_grasp(plan, part.vertices)
                    log.info("part %s: nominal grasp from its plan (%s, turned %g degrees)",
                             folder.name, plan.grasp_name, plan.pass_direction_deg)
                self._parts[folder.name] = part
            except (OSError, ValueError, KeyError, TypeError) as exc:  # PartError is a ValueError
                log.error("stored part %s skipped: %s", folder.name, exc)

    def names(self) -> list[str]:
        with self._lock:
            return sorted(self._parts)

    def get(self, name: str) -> PartModel:
        with self._lock:
            return self._parts[name]

    def check_name(self, name: str) -> None:
        """ValueError unless ``name`` can be an uploaded part's."""
        if not PART_NAME.match(name) or name in self._builtin:
            raise ValueError(f"part name must be 1-64 letters, digits, '.', '_' or '-', not start "
                             f"with '.', and not be a built-in part's "
                             f"({', '.join(sorted(self._builtin)) or 'none'}), got {name!r}")

    def check_room(self, name: str) -> None:
        """PartQuotaExceeded when a new part of this name would pass ``max_parts``."""
        with self._lock:
            uploaded = [n for n in self._parts if n not in self._builtin]
        if name not in uploaded and len(uploaded) >= self.max_parts:
            raise PartQuotaExceeded(f"{len(uploaded)} parts are stored, the most this service "
                                    f"keeps (max_parts): delete one first")

    def staging(self) -> Path:
        """A new temporary folder for one upload (removed at start if left behind)."""
        return Path(tempfile.mkdtemp(prefix=f"{STAGING_PREFIX}upload-", dir=self.root))

    def add(self, name: str, data: bytes, units: str, *, suffix: str = ".stl",
            grasp="centred") -> PartModel:
        """Check and keep an uploaded mesh given as bytes (see `add_staged`)."""
        if not data:
            raise PartError("the mesh file is empty")
        tmp = self.staging()
        try:
            (tmp / f"mesh{suffix}").write_bytes(data)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return self.add_staged(name, tmp, units, suffix=suffix, grasp=grasp)

    def add_staged(self, name: str, tmp: Path, units: str, *, suffix: str = ".stl",
                   grasp="centred") -> PartModel:
        """Check and keep the mesh ``tmp/mesh<suffix>`` (``tmp`` from `staging`, moved into
        place or removed). ``grasp``: a name of ``GRASPS``, or the nominal ^T X_P itself,
        (4, 4) mm. Raises PartError (or ValueError) with the reason, PartQuotaExceeded,
        OSError when the disk refuses."""
        try:
            self.check_name(name)
            if suffix not in MESH_SUFFIXES:
                raise ValueError(f"mesh format must be one of {', '.join(MESH_SUFFIXES)}, "
                                 f"got {suffix!r}")
            self.check_room(name)
            mesh_path = tmp / f"mesh{suffix}"
            if not mesh_path.is_file() or mesh_path.stat().st_size == 0:
                raise PartError("the mesh file is empty")
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

    def remove(self, name: str, *, in_use: dict[str, str] | None = None) -> None:
        """Delete an uploaded part: KeyError when unknown, PartInUse when built in or named
        in ``in_use`` (part name to why), OSError when the disk refuses (then it stays)."""
        with self._lock:
            if name not in self._parts:
                raise KeyError(name)
        if name in self._builtin:
            raise PartInUse(f"part {name!r} is built in")
        if in_use and name in in_use:
            raise PartInUse(f"part {name!r} is {in_use[name]}")
        folder = self.root / name
        with self._lock:
            if folder.exists():
                # renamed aside first: a removal that fails halfway leaves a leftover the next
                # start cleans, never a half part
                aside = self.root / f"{STAGING_PREFIX}deleted-{name}"
                shutil.rmtree(aside, ignore_errors=True)
                os.replace(folder, aside)
                self._parts.pop(name, None)
                shutil.rmtree(aside, ignore_errors=True)  # else gone at the next start
            else:
                self._parts.pop(name, None)


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
