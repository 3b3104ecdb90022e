"""The simulator's CAD parts: the scanner's part model, with how its surface returns the laser.

A ``Part`` is a ``scanner_core.cad.PartModel`` (the mesh in mm, its unit, its source, its
nominal grasp, and the models registration builds from it) plus what only the simulator needs:
how the surface returns the laser (``simulator.surfaces.Surface``) and a ray-casting scene
(``intersector``). Loading, units, grasps and the inspection volume's check are the scanner's
(``scanner_core.cad``); the loaders here give simulator parts.

The benchmarks' reference parts are read at run time from the folder the user points at
(`load_reference_part`: ``flyscan bench --meshes DIR`` or ``$FLYSCAN_MESHES``); the project's
tests build their parts procedurally (``simulator.procedural``).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from scanner_core import cad
from scanner_core.cad import (GRASPS, GRIPPER_TOLERANCE_MM, INSPECTION_VOLUME_MM,  # noqa: F401
                              PLAUSIBLE_SIZE_MM, UNITS_MM, PartError, PartModel, centred_grasp,
                              check_fits, flat_grasp, named_grasp)
from simulator.procedural import (block_with_holes_and_steps, bracket_with_two_holes,  # noqa: F401
                                  crowned_block, faceted_dome, fan_disk)
from simulator.raycast import Intersector
from simulator.surfaces import Surface

__all__ = [
    "UNITS_MM", "PartError", "PLAUSIBLE_SIZE_MM", "Part", "load_part", "part_from_mesh",
    "load_reference_part", "reference_meshes_dir", "centred_grasp", "flat_grasp", "GRASPS",
    "named_grasp", "check_fits", "simulated",
    "block_with_holes_and_steps", "INSPECTION_VOLUME_MM", "faceted_dome", "fan_disk",
    "bracket_with_two_holes", "crowned_block",
]

MESHES_ENV = "FLYSCAN_MESHES"


@dataclass(frozen=True, eq=False)
class Part(PartModel):
    """A CAD part as the simulator sees it: a ``scanner_core.cad.PartModel`` and

    Attributes
    ----------
    surface : simulator.surfaces.Surface
        How the surface returns the laser (default the reference matte white).
        ``simulator.surfaces.with_surface`` gives a part another.
    """

    surface: Surface = Surface()

    @cached_property
    def intersector(self) -> Intersector:
        """The part's Embree scene in {P}, built on first use and kept: most of its cost is
        copying the mesh into Embree, and every simulated pass or frame reuses it."""
        return Intersector(self.vertices, self.faces)

    def with_grasp(self, grasp) -> "Part":
        """The same part held by another nominal grasp ((4, 4) ^T X_P, mm), sharing what this
        one has built that the grasp does not change (its mesh, bounding box, ray-casting
        scene, surface model and model edges; the edge model depends on the view, so it is
        built again): a planner scans one part under many grasps."""
        grasp = np.array(grasp, dtype=np.float64)
        other = replace(self, grasp=cad.check_rigid_grasp(grasp))
        for name in _GRASP_FREE:
            if name in self.__dict__:
                other.__dict__[name] = self.__dict__[name]
        return other


# The cached properties of a part that do not depend on its grasp (all in {P}).
_GRASP_FREE = ("mesh", "bounds", "intersector", "surface_model", "model_edges")


def simulated(model: PartModel, surface: Surface | None = None) -> Part:
    """The simulator's part of a scanner's part model (the model itself when it is one already
    and no other surface is asked for)."""
    if isinstance(model, Part) and surface is None:
        return model
    return Part(name=model.name, vertices=model.vertices, faces=model.faces,
                source=model.source, units=model.units, grasp=model.grasp,
                inspection=model.inspection,
                surface=Surface() if surface is None else surface)


def load_part(path, units: str, *, name: str | None = None,
              grasp: str | np.ndarray | None = None) -> Part:
    """``scanner_core.cad.load_part``, as a simulator part."""
    return simulated(cad.load_part(path, units, name=name, grasp=grasp))


def part_from_mesh(mesh, *, name: str, units: str = "mm", source: str = "procedural",
                   grasp: str | np.ndarray | None = None) -> Part:
    """``scanner_core.cad.part_from_mesh``, as a simulator part."""
    return simulated(cad.part_from_mesh(mesh, name=name, units=units, source=source,
                                        grasp=grasp))


def reference_meshes_dir() -> Path | None:
    """The folder of the reference meshes: ``$FLYSCAN_MESHES`` (``flyscan bench --meshes DIR``
    sets it), or None when nothing says where it is: meshes are read only where the user
    points."""
    env = os.environ.get(MESHES_ENV)
    return Path(env) if env else None


def load_reference_part(name: str, grasp: str | np.ndarray | None = None) -> Part:
    """Load one of the reference parts, with the unit its manifest gives.

    Parameters
    ----------
    name : str
        File name (``"idler_riser.STL"``) or its stem, case-insensitive (``"idler_riser"``).
    grasp : (4, 4) array_like or str, optional
        As for `load_part`.

    Returns
    -------
    Part

    Raises
    ------
    PartError
        When the folder or its ``manifest.json`` is missing, or `name` is not in it (the
        message lists the names available).
    """
    folder = reference_meshes_dir()
    if folder is None:
        raise PartError(f"where are the reference meshes? Give the folder with --meshes DIR or "
                        f"the {MESHES_ENV} environment variable")
    manifest_path = folder / "manifest.json"
    if not manifest_path.is_file():
        raise PartError(f"no reference meshes at {folder} (missing manifest.json); "
                        f"give the folder with --meshes DIR or {MESHES_ENV}")
    try:
        manifest = json.loads(manifest_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise PartError(f"cannot read {manifest_path}: {exc}") from exc
    wanted = name.lower()
    for file_name, entry in manifest.items():
        if wanted in (file_name.lower(), Path(file_name).stem.lower()):
            return load_part(folder / file_name, entry["units"], name=Path(file_name).stem,
                             grasp=grasp)
    raise PartError(f"no reference part {name!r} in {folder}; available: "
                    f"{', '.join(sorted(manifest))}")
