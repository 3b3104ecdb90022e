"""A catalogue: a folder of CAD files, their units, and the parts read from them.

The folder holds mesh files (STL, OBJ, PLY) and optionally ``manifest.json`` mapping a file's
name to its unit (``{"bracket.stl": {"units": "mm"}}``, the format of the reference meshes'
manifest); ``--units`` gives the unit of every file the manifest does not name. A file that
cannot be read as a part (``scanner_core.cad.load_part``: unreadable, empty, implausible size
for its unit) is a broken entry: reported with its reason, the others planned.

`procedural_catalogue` writes a catalogue of procedural parts of varied shapes (the
simulator's blocks, brackets, domes, fan discs and crowned blocks, and plain prisms and
cylinders, at random sizes) for measuring the planner.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from planning.evaluate import PartMesh
from scanner_core.cad import PartError, canonical_unit, load_part
from scanner_core.scanplan import file_sha256

__all__ = ["CatalogueError", "Entry", "read_catalogue", "procedural_catalogue",
           "MESH_SUFFIXES"]

MESH_SUFFIXES = (".stl", ".obj", ".ply")
MANIFEST = "manifest.json"


class CatalogueError(ValueError):
    """The catalogue folder itself cannot be used: missing, empty, a bad manifest, no unit."""


@dataclass
class Entry:
    """One file of the catalogue: its part, or why it has none.

    Attributes
    ----------
    name : str
        The file's stem (unique in the catalogue).
    path : Path
    units : str or None
    part : scanner_core.cad.PartModel or None
        None when broken.
    mesh : PartMesh or None
        What the workers receive.
    error : str or None
        Why the file is no part.
    """

    name: str
    path: Path
    units: str | None
    part: object = None
    mesh: PartMesh | None = None
    error: str | None = None


def read_catalogue(folder, units: str | None = None) -> list[Entry]:
    """Every mesh file of `folder`, sorted by name, read as a part or marked broken.

    Raises
    ------
    CatalogueError
        Missing folder, no mesh file in it, an unreadable manifest, a file with no unit (not
        in the manifest and no `units`), two files of one stem, or a bad `units`.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise CatalogueError(f"catalogue folder not found: {folder}")
    if units is not None:
        try:
            units = canonical_unit(units)
        except PartError as exc:
            raise CatalogueError(f"--units: {exc}") from None
    manifest = _manifest(folder)
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES and p.is_file())
    if not files:
        raise CatalogueError(f"no mesh file ({', '.join(MESH_SUFFIXES)}) in {folder}")
    stems = [p.stem for p in files]
    twice = sorted({s for s in stems if stems.count(s) > 1})
    if twice:
        raise CatalogueError(f"two files of one name in {folder}: {', '.join(twice)} (a part "
                             f"is named by its file's stem)")
    missing = [p.name for p in files if p.name not in manifest and units is None]
    if missing:
        raise CatalogueError(f"no unit for {', '.join(missing[:5])}"
                             f"{' ...' if len(missing) > 5 else ''}: give --units or list them "
                             f"in {folder / MANIFEST}")
    return [_entry(p, manifest.get(p.name, units)) for p in files]


def _manifest(folder: Path) -> dict:
    path = folder / MANIFEST
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text())
        return {name: entry["units"] for name, entry in data.items()}
    except (OSError, json.JSONDecodeError, AttributeError, KeyError, TypeError) as exc:
        raise CatalogueError(f"{path} must map file names to {{\"units\": U}}: "
                             f"{type(exc).__name__}: {exc}") from None


def _entry(path: Path, units: str) -> Entry:
    entry = Entry(name=path.stem, path=path, units=units)
    try:
        part = load_part(path, units, name=path.stem)
    except PartError as exc:
        entry.error = str(exc)
        return entry
    entry.part = part
    entry.mesh = PartMesh(name=part.name, vertices=np.asarray(part.vertices),
                          faces=np.asarray(part.faces), units=part.units, source=str(path),
                          digest=file_sha256(path))
    return entry


# --------------------------------------------------------------------------------------------
# A procedural catalogue
# --------------------------------------------------------------------------------------------

#: The shapes `procedural_catalogue` draws from, in turn.
SHAPES = ("block", "bracket", "dome", "fan_disk", "crowned", "prism", "cylinder", "plate")


def procedural_catalogue(folder, count: int, *, seed: int = 0, extra_broken: bool = False,
                         progress=None) -> list[Path]:
    """Write `count` procedural parts of varied shapes and sizes as binary STL files (mm) into
    `folder`, with their ``manifest.json``.

    Parameters
    ----------
    folder : path-like
        Created when missing.
    count : int
        Parts; shape ``i`` is ``SHAPES[i % len(SHAPES)]``, its sizes drawn from
        ``default_rng([seed, i])`` so any one part is repeatable alone.
    extra_broken : bool
        Also write ``broken.stl``, a file that is no mesh (a test's broken entry).
    progress : callable, optional
        ``progress(i, count)`` after each part.

    Returns
    -------
    list of Path
        The files written.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths, manifest = [], {}
    for i in range(int(count)):
        rng = np.random.default_rng([seed, i])
        shape = SHAPES[i % len(SHAPES)]
        mesh = _shape(shape, rng)
        path = folder / f"p{i:04d}_{shape}.stl"
        mesh.export(path)
        paths.append(path)
        manifest[path.name] = {"units": "mm"}
        if progress is not None:
            progress(i + 1, count)
    if extra_broken:
        path = folder / "broken.stl"
        path.write_bytes(b"solid nothing\nthis is not a mesh\n")
        manifest[path.name] = {"units": "mm"}
        paths.append(path)
    (folder / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    return paths


def _shape(shape: str, rng: np.random.Generator):
    """One procedural mesh (trimesh.Trimesh, mm) of kind `shape` at sizes from `rng`."""
    import trimesh

    from simulator import procedural

    u = rng.uniform
    if shape == "block":
        size = (u(30, 80), u(25, 60), u(10, 30))
        return procedural.block_with_holes_and_steps(
            size, hole_radius=u(2.5, min(size[:2]) / 8))
    if shape == "bracket":
        return procedural.bracket_with_two_holes((u(40, 90), u(25, 50), u(4, 10)),
                                                 step_height=u(3, 8))
    if shape == "dome":
        return procedural.faceted_dome(u(25, 45), u(4, 12))
    if shape == "fan_disk":
        radius = u(40, 60)
        return procedural.fan_disk(radius, u(4, 10), hub_radius=radius * u(0.4, 0.5))
    if shape == "crowned":
        size = (u(40, 80), u(30, 50), u(8, 16))
        return procedural.crowned_block(size, crown_radius=u(0.6, 0.9) * size[1])
    if shape == "prism":
        sides = int(rng.integers(3, 9))
        poly = trimesh.creation.cylinder(radius=u(15, 40), height=u(8, 40), sections=sides)
        return poly
    if shape == "cylinder":
        return trimesh.creation.cylinder(radius=u(10, 30), height=u(15, 60), sections=64)
    return trimesh.creation.box((u(30, 100), u(20, 80), u(2, 8)))  # plate
