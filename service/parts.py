"""The parts the service knows: meshes uploaded with their unit, and those built in (the
simulated cell's demo block, handed in by its driver).

An uploaded part is kept as ``parts/<name>/mesh.<ext>`` with ``part.json`` (its unit and
grasp), written into a temporary folder and renamed into place, and loaded again at start.
A part's scan plan (``flyscan plan``'s ``plan.json``, read by ``scanner_core.scanplan``)
placed in its folder gives its nominal grasp at start: the plan's grasp turned by its pass
direction (it must have been made for that mesh file).
Every part is checked as ``flyscan scan`` checks it (readable, counts consistent with the
file, plausible size for its unit, fits the inspection volume at its nominal grasp) and as a
solid (`check_solid`: a thickness, a volume and a surface) before it is accepted. An upload
is streamed to disk (`staging`, then `add_staged`): its bytes are never held in memory whole.

An upload is read, checked and simplified in a process of its own, at low priority, one at a
time (`PartLibrary.add_staged`): parsing a 60 MB mesh holds an interpreter's lock for seconds,
which the camera's thread must never wait for. A mesh far finer than the scan needs is
simplified for registration (``scanner_core.cad.simplified_for_scan``): the model is kept as
``model.npz`` beside the upload, and ``part.json`` says how far it strays from the mesh.

What a scan's pose needs of a part beyond its mesh (its surface and edge models, their trees
and tables: ``PartModel.prepare``) is built when the part is uploaded, or by the finish of a
scan armed without them, never while a pass runs (`PartLibrary.prepare`), and kept within a
memory budget: past
``prepared_parts_mb``, the least recently scanned parts give theirs back
(``PartModel.release``) and build them again when next armed; a part deleted or replaced
gives them back at once.
"""
from __future__ import annotations

import ctypes
import dataclasses
import gc
import json
import logging
import mmap
import multiprocessing
import os
import re
import shutil
import signal
import tempfile
import threading
from collections import OrderedDict
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from os import PRIO_PROCESS, setpriority
from pathlib import Path

import numpy as np

from scanner_core.cad import (GRASPS, PartError, PartModel, check_fits, load_part, saved_part,
                              simplified_for_scan)
from scanner_core.inspection import InspectionParams
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
#: ``prctl``'s option: the signal a process gets when its parent ends (linux/prctl.h).
PR_SET_PDEATHSIG = 1
#: The loader process's niceness: the service's threads (the camera's) come first.
LOADER_NICE = 10
#: A stored part's scan plan, beside its part.json.
PLAN_FILE = "plan.json"


class PartQuotaExceeded(Exception):
    """The library holds ``max_parts`` uploaded parts already."""


class PartInUse(Exception):
    """A part that cannot be deleted now (built in, the default, or a pending scan's)."""


def part_info(part: PartModel, simplified: dict | None = None) -> dict:
    return {"name": part.name, "version": part.version, "units": part.units,
            "simplified": simplified,
            "faces": int(len(part.faces)),
            "source": "built-in" if part.source.startswith("procedural") else "uploaded",
            "extents_mm": np.round(part.extents, 4).tolist(),
            "nominal_grasp": np.asarray(part.grasp).tolist(),
            "inspection": part.inspection.given() if part.inspection is not None else None}


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


def read_upload(mesh_path, units: str, name: str, grasp) -> tuple[PartModel, dict | None]:
    """An uploaded mesh as the scanner's model: read and checked (`check_solid`, fits the
    volume), simplified when far finer than the scan needs (``simplified_for_scan``), its
    version computed; and the simplification's report (None: not simplified). PartError (or
    ValueError) with the reason. What the loader process runs."""
    part = _checked(lambda: load_part(mesh_path, units, name=name, grasp=_grasp(grasp)))
    part, simplified = simplified_for_scan(part)
    part.version  # noqa: B018 - computed here, not in the service's process
    part.__dict__.pop("mesh", None)  # the trimesh object is rebuilt where needed
    return part, simplified


def _lower_priority(pid) -> None:
    """Give the process `pid` (0: this one) the niceness ``LOADER_NICE``, where the system
    lets it."""
    try:
        setpriority(PRIO_PROCESS, pid, LOADER_NICE)  # None (not started yet): TypeError
    except (OSError, TypeError):  # no such process any more; not a pid yet
        pass


def _loader_start() -> None:
    """In the loader process: yield the cores to the service's (nice 10), and end with the
    service whatever ends it (Linux's parent-death signal: a worker left behind by a killed
    service would wait for uploads for ever, holding its 150 MB)."""
    _lower_priority(0)
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):  # not Linux: the service's close() ends it
        pass
    if os.getppid() == 1:  # the service ended before the signal was asked for
        os._exit(0)


def settle_objects() -> None:
    """After a part's models are built: collect, then move every object that lives on into
    the collector's permanent generation (``gc.freeze``), as the service does at start. A
    prepared part brings tens of thousands of objects; left to the collector, a full
    collection over them comes at some allocation during a pass and holds the interpreter's
    lock for a hundred milliseconds and more (a pass under uploads lost 23 frames so)."""
    gc.collect()
    gc.freeze()


def return_memory() -> None:
    """Give what Python's objects freed back to the system: collect their cycles (a tree's,
    a table's; the frozen objects too, then frozen again: `settle_objects`), then ask glibc
    to return its free heap (``malloc_trim``; without it a service that deleted three 170 MB
    parts kept 500 MB resident)."""
    gc.unfreeze()
    settle_objects()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: its allocator keeps its own counsel
        pass


def prepared_bytes(part: PartModel) -> int:
    """What a part's prepared models hold (the arrays of its surface and edge models, their
    trees and tables, its model edges), bytes: walked through their attributes."""
    seen, total = set(), 0
    stack = [part.__dict__.get(k) for k in ("surface_model", "edge_model", "model_edges",
                                            "mesh")]
    while stack:
        item = stack.pop()
        if item is None or id(item) in seen or isinstance(item, (str, bytes, int, float)):
            continue
        seen.add(id(item))
        if isinstance(item, np.ndarray):
            total += item.nbytes
        elif hasattr(item, "data") and hasattr(item, "n") and hasattr(item, "m"):  # cKDTree
            total += 3 * np.asarray(item.data).nbytes  # its data, indices and nodes
        elif isinstance(item, dict):
            stack.extend(item.values())
        elif isinstance(item, (list, tuple)):
            stack.extend(item)
        elif hasattr(item, "__dict__"):
            stack.extend(vars(item).values())
    return total


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

    def __init__(self, root, builtin: dict | None = None, max_parts: int = 100,
                 prepared_budget_bytes: int = 1 << 30, load_in_process: bool = True):
        self.root = Path(root) / "parts"
        self.max_parts = int(max_parts)
        self.prepared_budget_bytes = int(prepared_budget_bytes)
        self.load_in_process = bool(load_in_process)
        self._builtin = dict(builtin or {})
        self._parts: dict[str, PartModel] = {}
        self._simplified: dict[str, dict] = {}
        self._lock = threading.Lock()
        self._loader: ProcessPoolExecutor | None = None
        self._loader_lock = threading.Lock()  # one upload read at a time
        # name -> (model, bytes) of the prepared parts, least recently scanned first
        self._prepared: OrderedDict[str, tuple[PartModel, int]] = OrderedDict()
        self.released = 0  # parts that gave their prepared models back (the budget)

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
                inspection = (InspectionParams.from_dict(meta["inspection"])
                              if meta.get("inspection") else None)
                if (folder / PLAN_FILE).is_file():
                    plan = load_scan_plan(folder / PLAN_FILE)
                    plan.check_mesh(folder / meta["file"])
                    grasp = plan.nominal_grasp
                    if plan.inspection is not None:  # the plan's over the upload's
                        inspection = (plan.inspection if inspection is None
                                      else plan.inspection.over(inspection))
                if meta.get("model"):  # the simplified model, as it was made
                    with np.load(folder / meta["model"]) as model:
                        part = saved_part(model["vertices"], model["faces"], grasp,
                                          name=folder.name, units=meta["units"],
                                          source=str(folder / meta["file"]))
                    self._simplified[folder.name] = meta.get("simplified")
                else:
                    part = load_part(folder / meta["file"], meta["units"], name=folder.name,
                                     grasp=grasp)
                if inspection is not None:
                    part = dataclasses.replace(part, inspection=inspection)
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
            grasp="centred", inspection: InspectionParams | None = None) -> PartModel:
        """Check and keep an uploaded mesh given as bytes (see `add_staged`)."""
        if not data:
            raise PartError("the mesh file is empty")
        tmp = self.staging()
        try:
            (tmp / f"mesh{suffix}").write_bytes(data)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return self.add_staged(name, tmp, units, suffix=suffix, grasp=grasp,
                               inspection=inspection)

    def add_staged(self, name: str, tmp: Path, units: str, *, suffix: str = ".stl",
                   grasp="centred", inspection: InspectionParams | None = None) -> PartModel:
        """Check and keep the mesh ``tmp/mesh<suffix>`` (``tmp`` from `staging`, moved into
        place or removed). ``grasp``: a name of ``GRASPS``, or the nominal ^T X_P itself,
        (4, 4) mm. ``inspection``: the part's own inspection thresholds, kept with it.
        Raises PartError (or ValueError) with the reason, PartQuotaExceeded,
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
                part, simplified = self._read(mesh_path, units, name, grasp)
            except PartError as exc:  # said of the upload, not of a path on the server
                raise PartError(str(exc).replace(f" ({mesh_path})", "").replace(str(mesh_path),
                                                                                "the upload")) from None
            meta = {"file": mesh_path.name, "units": part.units,
                    "grasp": grasp if isinstance(grasp, str) else np.asarray(part.grasp).tolist()}
            if simplified is not None and simplified["kept"]:
                np.savez(tmp / "model.npz", vertices=part.vertices, faces=part.faces)
                # the grasp of the mesh as uploaded, not one of the simplified mesh's
                meta.update(model="model.npz", grasp=np.asarray(part.grasp).tolist())
            if simplified is not None:
                meta["simplified"] = simplified
            if inspection is not None and inspection.given():
                meta["inspection"] = inspection.given()
                part = dataclasses.replace(part, inspection=inspection)
            (tmp / "part.json").write_text(json.dumps(meta))
            final = self.root / name
            if final.resolve().parent != self.root.resolve():
                raise ValueError(f"part name {name!r} is not a plain folder name")
            with self._lock:
                shutil.rmtree(final, ignore_errors=True)
                os.replace(tmp, final)
                self._parts[name] = part
                self._simplified[name] = simplified
                replaced = self._forget_prepared(name)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        if replaced:
            return_memory()
        return part

    def _read(self, mesh_path: Path, units: str, name: str, grasp):
        """`read_upload`, in the loader process (one upload at a time) unless
        ``load_in_process``."""
        if self.load_in_process:
            return read_upload(mesh_path, units, name, grasp)
        with self._loader_lock:
            for attempt in range(2):
                if self._loader is None:
                    self._loader = ProcessPoolExecutor(
                        max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                        initializer=_loader_start)
                try:
                    future = self._loader.submit(read_upload, str(mesh_path), units, name,
                                                 grasp)
                    # at once: a process just spawned imports the libraries for a second or
                    # more before its initializer runs, and that took a pass's frames
                    for worker in list(getattr(self._loader, "_processes", {}).values()):
                        _lower_priority(worker.pid)
                    return future.result()
                except BrokenProcessPool:  # the loader died (killed, out of memory): anew
                    self._loader = None
                    if attempt:
                        raise PartError("the mesh could not be read: its reader process "
                                        "ended (out of memory?)") from None

    def simplified(self, name: str) -> dict | None:
        """How the part's model was simplified (``simplified_for_scan``'s report), or None."""
        with self._lock:
            return self._simplified.get(name)

    def close(self) -> None:
        """End the loader process (an upload being read is dropped)."""
        with self._loader_lock:
            if self._loader is not None:
                workers = list(getattr(self._loader, "_processes", {}).values())
                self._loader.shutdown(wait=False, cancel_futures=True)
                for worker in workers:  # not left waiting for work that never comes
                    worker.terminate()
                self._loader = None

    # -- prepared models within a budget -----------------------------------------------------
    def prepare(self, name: str, model: PartModel | None = None) -> float:
        """Build (``PartModel.prepare``) the models a scan of `name` needs, mark it the most
        recently used, and release the least recently used others' past the budget; the
        preparation's time, ms (0 when it was prepared). `model`: the part's model a scan
        holds (default the library's)."""
        model = self.get(name) if model is None else model
        resident = _resident_bytes()
        took = 0.0 if model.prepared else model.prepare()
        # what it holds: its arrays, or what the process grew by building them (the trees'
        # and the meshes' own objects), whichever is more
        size = max(prepared_bytes(model), _resident_bytes() - resident) if took else None
        released = False
        with self._lock:
            previous = self._prepared.pop(name, None)
            if size is None:
                size = previous[1] if previous is not None else prepared_bytes(model)
            self._prepared[name] = (model, size)
            used = sum(b for _, b in self._prepared.values())
            for other in list(self._prepared):
                if used <= self.prepared_budget_bytes or other == name:
                    continue
                old, freed = self._prepared.pop(other)
                old.release()
                used -= freed
                self.released += 1
                released = True
                log.info("part %s: its prepared models released (budget %.0f MB)", other,
                         self.prepared_budget_bytes / 2**20)
        if released:
            return_memory()
        return took

    def prepared_mb(self) -> float:
        with self._lock:
            return sum(b for _, b in self._prepared.values()) / 2**20

    def _forget_prepared(self, name: str) -> bool:
        """Under the lock: the part `name` is replaced or gone; its prepared models with it
        (`return_memory` gives them back to the system, after the lock)."""
        entry = self._prepared.pop(name, None)
        if entry is not None:
            entry[0].release()
        return entry is not None

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
                shutil.rmtree(aside, ignore_errors=True)  # else gone at the next start
            self._parts.pop(name, None)
            self._forget_prepared(name)


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


def _resident_bytes() -> int:
    """This process's resident memory, bytes (0 where ``/proc`` does not say)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * mmap.PAGESIZE
    except (OSError, ValueError, IndexError):
        return 0
