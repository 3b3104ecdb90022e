"""CAD parts: a mesh in millimetres with its unit, its source and its nominal grasp.

A mesh file carries no reliable unit, so every loader takes one and converts to mm. The part
frame {P} is the CAD file's own frame. The gripper frame {T} has z_T pointing down in the robot
base: the gripper holds the part from above, so the part hangs along +z_T, and the scanner (the
laser sheet below) sees the part's max-z_T face. The nominal grasp ^T X_P maps points of {P} to
{T}: X_T = R X_P + t.

The four reference parts of ``shared/data/meshes`` are read from there at run time
(`load_reference_part`); the project's tests build their parts procedurally
(`block_with_holes_and_steps`).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

from typing import TYPE_CHECKING

import numpy as np

from scanner_core.geometry import apply_transform, check_rigid
from simulator.meshfile import clean_triangles, is_binary_stl, read_mesh
from simulator.raycast import Intersector
from simulator.surfaces import Surface

if TYPE_CHECKING:  # imported where used: ray casting alone needs neither trimesh nor scipy
    import trimesh

__all__ = [
    "UNITS_MM", "PartError", "PLAUSIBLE_SIZE_MM", "Part", "load_part", "part_from_mesh",
    "load_reference_part", "reference_meshes_dir", "centred_grasp", "flat_grasp", "GRASPS",
    "named_grasp", "check_fits",
    "block_with_holes_and_steps", "INSPECTION_VOLUME_MM", "faceted_dome", "fan_disk",
    "bracket_with_two_holes", "crowned_block",
]

#: Length of one unit in millimetres.
UNITS_MM: dict[str, float] = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "inch": 25.4}
# Other spellings accepted for the same units (CAD exports and manifests use them).
_UNIT_ALIASES = {
    "millimetre": "mm", "millimeter": "mm", "millimetres": "mm", "millimeters": "mm",
    "centimetre": "cm", "centimeter": "cm", "metre": "m", "meter": "m", "metres": "m",
    "meters": "m", "in": "inch", "inches": "inch",
}
#: The reference cell's inspection volume (x, y, z in {T}), mm.
INSPECTION_VOLUME_MM = (150.0, 150.0, 100.0)
#: A mesh file whose largest extent falls outside this range (mm) is refused: it probably has
#: the wrong unit. Below 6 mm the default pass (1.2 mm between profiles) gives fewer than five
#: profiles, and every part that fits the inspection volume, read in inches or cm as if in mm,
#: falls below it; above 2 m no gripper holds it.
PLAUSIBLE_SIZE_MM = (6.0, 2000.0)
#: How far (mm) a misplaced part may reach above z_T = 0. A tilt about the TCP lifts one edge
#: of the gripped face (2 degrees over 60 mm: 1 mm); the simulated cell has no gripper body, so
#: that is harmless. Beyond it the part would be inside the gripper.
GRIPPER_TOLERANCE_MM = 5.0
# Slack when comparing a part's size with the volume, mm: float noise of unit conversion.
_FIT_TOL_MM = 1e-6
_FORMATS = (".stl", ".obj", ".ply")
MESHES_ENV = "FLYSCAN_MESHES"


class PartError(ValueError):
    """A part cannot be used: bad unit, unreadable or empty file, bad geometry, too large."""


@dataclass(frozen=True, eq=False)
class Part:
    """A CAD part, in millimetres.

    Attributes
    ----------
    name : str
        Name of the part (by default the file's stem).
    vertices : (V, 3) float64
        The mesh's vertices in mm in the part's CAD frame {P}. Read-only.
    faces : (F, 3) int64
        Its triangles, indices into `vertices`; not necessarily watertight. Read-only.
    source : str
        The file it came from, or ``"procedural:..."``.
    units : str
        The unit of the source file, one of `UNITS_MM`.
    grasp : (4, 4) float64
        Nominal ^T X_P, mm: X_T = R X_P + t. Read-only.
    surface : simulator.surfaces.Surface
        How the surface returns the laser (the simulator's only; default the reference matte
        white). ``simulator.surfaces.with_surface`` gives a part another.
    """

    name: str
    vertices: np.ndarray = field(repr=False)
    faces: np.ndarray = field(repr=False)
    source: str
    units: str
    grasp: np.ndarray = field(repr=False)
    surface: Surface = Surface()

    @cached_property
    def mesh(self) -> trimesh.Trimesh:
        """The part as a ``trimesh.Trimesh`` (built on first use: ray casting alone does not
        need trimesh, whose import costs half a second). Treat as read-only."""
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)

    @cached_property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64, mm: the bounding box's corners in {P}, min then max."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    @property
    def extents(self) -> np.ndarray:
        """(3,) float64, mm: bounding-box size in {P}."""
        return self.bounds[1] - self.bounds[0]

    @property
    def extents_t(self) -> np.ndarray:
        """(3,) float64, mm: bounding-box size in {T} after the nominal grasp."""
        lo, hi = _bounds_t(self, self.grasp)
        return hi - lo

    @cached_property
    def intersector(self) -> Intersector:
        """The part's Embree scene in {P}, built on first use and kept: most of its cost is
        copying the mesh (NOTES.md), and every simulated pass or frame reuses it."""
        return Intersector(self.vertices, self.faces)

    @cached_property
    def surface_model(self):
        """The CAD surface sampled for registration (``scanner_core.pose.SurfaceModel``),
        built on first use and kept: every scan of the part reuses it."""
        from scanner_core.pose import SurfaceModel
        return SurfaceModel.from_mesh(self.mesh)

    @cached_property
    def edge_model(self):
        """The CAD's sharp edges for registration (``scanner_core.pose.EdgeModel``), a
        narrow chamfer's on the outline seen from the sensor under the nominal grasp."""
        from scanner_core.pose import EdgeModel
        return EdgeModel.from_mesh(self.mesh, view=self.grasp[2, :3])

    @cached_property
    def model_edges(self):
        """The CAD's sharp edges and what its outline needs
        (``scanner_core.edge_kinds.ModelEdges``), for edge kinds after registration."""
        from scanner_core.edge_kinds import ModelEdges
        return ModelEdges.from_mesh(self.mesh)

    def vertices_t(self) -> np.ndarray:
        """(V, 3) float64, mm: the mesh vertices in {T} under the nominal grasp."""
        return apply_transform(self.grasp, self.vertices)


# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------

def load_part(path, units: str, *, name: str | None = None,
              grasp: str | np.ndarray | None = None) -> Part:
    """Load a CAD part from an STL, OBJ or PLY file.

    Parameters
    ----------
    path : str or os.PathLike
        The mesh file. Open (non-watertight) meshes are accepted.
    units : str
        Unit of the file's coordinates: one of ``mm``, ``cm``, ``m``, ``inch`` (``metre``,
        ``in`` and similar spellings are accepted).
    name : str, optional
        Part name; default the file's stem.
    grasp : (4, 4) array_like or str, optional
        Nominal ^T X_P in mm, or one of `GRASPS` by name (`named_grasp`); default
        `centred_grasp` of the mesh (real CAD origins are arbitrary).

    Returns
    -------
    Part
        The mesh in mm, with degenerate faces and unreferenced vertices removed.

    Raises
    ------
    PartError
        Unknown unit, missing, empty or unparseable file, no triangles, non-finite vertices.
        A size implausible for the unit (largest extent outside `PLAUSIBLE_SIZE_MM`), with
        the unit that would make it plausible.
    """
    unit = _canonical_unit(units)
    p = Path(path)
    if not p.exists():
        raise PartError(f"part file not found: {p}")
    if not p.is_file():
        raise PartError(f"part path is not a file: {p}")
    if p.suffix.lower() not in _FORMATS:
        raise PartError(f"part file {p} has an unsupported format {p.suffix!r}; "
                        f"supported: {', '.join(_FORMATS)}")
    if p.stat().st_size == 0:
        raise PartError(f"part file is empty: {p}")
    _check_content(p)
    try:
        vertices, faces = read_mesh(p)
    except Exception as exc:  # trimesh raises many types on a bad file; re-raised with the path
        raise PartError(f"cannot read part file {p}: {type(exc).__name__}: {exc}") from exc
    name = p.stem if name is None else name
    part = _make_part(vertices, faces, name=name, unit=unit, source=str(p), grasp=grasp)
    _check_plausible_size(part, unit)
    return part


def _check_content(p: Path) -> None:
    """Reject binary garbage in formats trimesh would otherwise try to decode as text.

    (Without this, trimesh's text fallback fails with an unrelated error, such as a missing
    optional charset-detection module.)
    """
    suffix = p.suffix.lower()
    if suffix == ".stl" and not is_binary_stl(p):
        with open(p, "rb") as fh:
            head = fh.read(84)
        size = p.stat().st_size
        if len(head) == 84:
            n = int(np.frombuffer(head[80:84], "<u4")[0])
        if not _is_text(p):
            expected = f"{84 + 50 * n} bytes for its {n} triangles" if len(head) == 84 else "84"
            raise PartError(f"cannot read part file {p}: neither a binary STL (its header needs "
                            f"{expected}, the file has {size}) nor an ASCII STL")
    elif suffix == ".obj" and not _is_text(p):
        raise PartError(f"cannot read part file {p}: an OBJ file must be text, this one is binary")


def _is_text(p: Path) -> bool:
    data = p.read_bytes()
    if b"\x00" in data:
        return False
    try:
        data.decode("utf-8")
    except UnicodeDecodeError:
        return False
    return True


def part_from_mesh(mesh: trimesh.Trimesh, *, name: str, units: str = "mm",
                   source: str = "procedural", grasp: str | np.ndarray | None = None) -> Part:
    """Make a Part from a mesh in memory (copied, converted to mm and cleaned).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Triangle mesh in `units`, in the part frame {P}.
    name : str
        Part name.
    units : str
        Unit of `mesh`, as for `load_part`.
    source : str
        Where it came from, e.g. ``"procedural:block"``.
    grasp : (4, 4) array_like or str, optional
        Nominal ^T X_P in mm, or one of `GRASPS` by name; default `centred_grasp`.

    Returns
    -------
    Part

    Raises
    ------
    PartError
        As `load_part`, for the mesh content.
    """
    unit = _canonical_unit(units)
    if not hasattr(mesh, "vertices") or not hasattr(mesh, "faces"):
        raise PartError(f"part {name!r} ({source}) is not a triangle mesh "
                        f"(got {type(mesh).__name__})")
    return _make_part(mesh.vertices, mesh.faces, name=name, unit=unit, source=source,
                      grasp=grasp)


def reference_meshes_dir() -> Path | None:
    """The folder of the reference meshes, or None when nothing says where it is.

    ``$FLYSCAN_MESHES`` (``flyscan bench --meshes DIR`` sets it) first; in a source checkout,
    ``../shared/data/meshes`` beside the repository. An installed package has no such
    neighbour: there the folder must be given.
    """
    env = os.environ.get(MESHES_ENV)
    if env:
        return Path(env)
    checkout = Path(__file__).resolve().parents[1]
    if (checkout / "pyproject.toml").is_file():
        return checkout.parent / "shared" / "data" / "meshes"
    return None


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


def _canonical_unit(units) -> str:
    key = str(units).strip().lower() if isinstance(units, str) else None
    key = _UNIT_ALIASES.get(key, key)
    if key not in UNITS_MM:
        raise PartError(f"unknown unit {units!r}; allowed: {', '.join(UNITS_MM)}")
    return key


def _make_part(vertices, faces, *, name: str, unit: str, source: str, grasp) -> Part:
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if faces.ndim != 2 or len(faces) == 0:
        raise PartError(f"part {name!r} ({source}) has no triangles")
    if faces.shape[1] != 3:
        raise PartError(f"part {name!r} ({source}) faces must be triangles, got {faces.shape}")
    faces = faces.astype(np.int64, copy=False)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise PartError(f"part {name!r} ({source}) vertices must be (V, 3), got "
                        f"{vertices.shape}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise PartError(f"part {name!r} ({source}) has face indices outside its "
                        f"{len(vertices)} vertices")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise PartError(f"part {name!r} ({source}) has {int(bad.sum())} vertices with NaN or "
                        "infinite coordinates")
    vertices, faces = clean_triangles(vertices * UNITS_MM[unit], faces)
    if len(faces) == 0:
        raise PartError(f"part {name!r} ({source}) has no non-degenerate triangles")
    if grasp is None or isinstance(grasp, str):
        grasp = named_grasp(grasp or "centred", vertices)
    else:
        grasp = _check_grasp(grasp)
    for array in (vertices, faces, grasp):
        array.setflags(write=False)
    return Part(name=name, vertices=vertices, faces=faces, source=source, units=unit,
                grasp=grasp)


def _check_plausible_size(part: Part, unit: str) -> None:
    size = float(np.max(part.extents))
    lo, hi = PLAUSIBLE_SIZE_MM
    if lo <= size <= hi:
        return
    raw = size / UNITS_MM[unit]
    fits = [u for u, f in UNITS_MM.items() if u != unit and lo <= raw * f <= hi]
    # Prefer the unit that makes the part closest to a typical 100 mm part (log scale).
    fits.sort(key=lambda u: abs(np.log10(raw * UNITS_MM[u] / 100.0)))
    hint = f": did you mean units={fits[0]!r}?" if fits else ""
    raise PartError(f"part {part.name!r} is {size:.6g} mm across read in {unit}, "
                    f"{'smaller' if size < lo else 'larger'} than a part the scanner can take "
                    f"({lo:g} to {hi:g} mm){hint}")


# --------------------------------------------------------------------------------------------
# Grasp and fit
# --------------------------------------------------------------------------------------------

def centred_grasp(mesh) -> np.ndarray:
    """The nominal grasp that centres the part under the TCP and hangs it along +z_T.

    Parameters
    ----------
    mesh : trimesh.Trimesh or (V, 3) array_like
        Part mesh in {P}, mm, or its vertices.

    Returns
    -------
    (4, 4) float64
        ^T X_P, a pure translation: the centre of the bounding box in x, y goes to the TCP and
        the minimum z to z_T = 0, so the part occupies z_T in [0, height].
    """
    vertices = np.asarray(getattr(mesh, "vertices", mesh), dtype=np.float64)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    x = np.eye(4)
    x[:2, 3] = -(lo[:2] + hi[:2]) / 2.0
    x[2, 3] = -lo[2]
    return x


#: The nominal grasps that have a name: `centred_grasp`, `flat_grasp`, the CAD origin at the TCP.
GRASPS = ("centred", "flat", "identity")


def flat_grasp(mesh) -> np.ndarray:
    """The nominal grasp of a part held by its broadest side, as a suction cup holds it.

    The part turns a quarter about x or y (never more) so that its smallest bounding-box
    extent lies along z_T, and is then centred as by `centred_grasp`. A part already flat
    (smallest extent along z of {P}) keeps the centred grasp. The scanner then sees a broad
    face: a part standing on a narrow one shows the sheet a strip, whose position along the
    pass only the profiles' spacing fixes.

    Parameters
    ----------
    mesh : trimesh.Trimesh or (V, 3) array_like
        Part mesh in {P}, mm, or its vertices.

    Returns
    -------
    (4, 4) float64
        ^T X_P.
    """
    vertices = np.asarray(getattr(mesh, "vertices", mesh), dtype=np.float64)
    turn = np.eye(4)
    smallest = int(np.argmin(np.ptp(vertices, axis=0)))
    if smallest == 1:    # a quarter turn about x takes y to z
        turn[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    elif smallest == 0:  # a quarter turn about y takes x to z
        turn[:3, :3] = [[0, 0, -1], [0, 1, 0], [1, 0, 0]]
    return centred_grasp(vertices @ turn[:3, :3].T) @ turn


def named_grasp(kind: str, mesh) -> np.ndarray:
    """The nominal grasp ^T X_P (4, 4) named `kind`, one of `GRASPS`, for `mesh` (mm)."""
    if kind == "centred":
        return centred_grasp(mesh)
    if kind == "flat":
        return flat_grasp(mesh)
    if kind == "identity":
        return np.eye(4)
    raise PartError(f"grasp must be one of {', '.join(GRASPS)}, got {kind!r}")


def check_fits(part: Part, volume_mm=INSPECTION_VOLUME_MM, *, pose=None) -> None:
    """Raise when the part, under its nominal grasp or `pose`, does not fit the inspection volume.

    The volume hangs below the TCP: x_T and y_T within half its size either side, z_T from 0
    (the gripper) to its height. A part may be small enough and still sit outside it, when
    its grasp (the identity, say, for a CAD origin far from the part) or a misplacement puts
    it elsewhere; a part reaching above z_T = 0 would be inside the gripper.

    Parameters
    ----------
    part : Part
    volume_mm : (3,) sequence of float
        Size of the inspection volume along x_T, y_T, z_T, mm.
    pose : (4, 4) array_like, optional
        ^T X_P actually held (a misplacement composed with the nominal grasp); default the
        nominal grasp.

    Raises
    ------
    PartError
        Naming the part's size and the volume's, or where the part lies.
    """
    vol = np.asarray(volume_mm, dtype=np.float64)
    if vol.shape != (3,) or not np.all(vol > 0):
        raise ValueError(f"`volume_mm` must be 3 positive sizes, got {volume_mm!r}")
    misplaced = pose is not None
    pose = part.grasp if pose is None else _check_grasp(pose)
    lo, hi = _bounds_t(part, pose)
    ext = hi - lo
    if np.any(ext > vol + _FIT_TOL_MM):
        raise PartError(f"part {part.name!r} is {ext[0]:.1f} x {ext[1]:.1f} x {ext[2]:.1f} mm "
                        f"in {{T}}; the inspection volume is {vol[0]:g} x {vol[1]:g} x "
                        f"{vol[2]:g} mm")
    box_lo = np.array([-vol[0] / 2, -vol[1] / 2, 0.0]) - _FIT_TOL_MM
    box_hi = np.array([vol[0] / 2, vol[1] / 2, vol[2]]) + _FIT_TOL_MM
    if misplaced:
        box_lo[2] -= GRIPPER_TOLERANCE_MM
    if np.all(lo >= box_lo) and np.all(hi <= box_hi):
        return
    held = "with the misplacement" if misplaced else "under its grasp"
    spans = (f"part {part.name!r} {held} spans {np.round(lo, 1).tolist()} to "
             f"{np.round(hi, 1).tolist()} mm in {{T}}")
    hint = ("a misplacement must leave the part in the volume" if misplaced
            else "use the centred grasp")
    if lo[2] < box_lo[2] and np.all(hi <= box_hi):
        raise PartError(f"{spans}, reaching {-lo[2]:.1f} mm into the gripper (z_T < 0): {hint}")
    raise PartError(f"{spans}, outside the inspection volume below the TCP ({vol[0]:g} x "
                    f"{vol[1]:g} x {vol[2]:g} mm, z_T from 0): {hint}")


def _check_grasp(grasp) -> np.ndarray:
    try:
        return check_rigid(grasp)
    except ValueError as exc:
        raise PartError(f"`grasp` {exc}") from None


def _bounds_t(part: "Part", pose: np.ndarray) -> np.ndarray:
    """(2, 3) float64, mm: the part's bounding box in {T} under ^T X_P = `pose`."""
    if np.allclose(pose[:3, :3], np.eye(3)):
        return part.bounds + pose[:3, 3]
    v = apply_transform(pose, part.vertices)
    return np.stack([v.min(axis=0), v.max(axis=0)])


# --------------------------------------------------------------------------------------------
# Procedural test part
# --------------------------------------------------------------------------------------------

# Facets of the hole cylinders: round enough for the stripe and edge tests, few triangles.
_HOLE_SECTIONS = 48
# Cutting tools overshoot the faces they cut by this much (mm), so no coplanar faces remain
# for the boolean engine to resolve.
_CUT_OVERSHOOT = 1.0


def block_with_holes_and_steps(size=(60.0, 40.0, 20.0), *, hole_radius: float = 4.0,
                               blind_depth: float | None = None,
                               step_length: float | None = None,
                               step_depth: float | None = None) -> trimesh.Trimesh:
    """A watertight test block (mm) with a through hole, a blind hole and a step.

    The block is ``size = (L, W, H)`` in {P} with x in [-L/2, L/2], y in [-W/2, W/2] and z in
    [0, H], so `centred_grasp` of it is the identity. The features are on the max-z face, the
    underside that the scanner sees when the part hangs along +z_T:

    - a through hole along z at (-L/4, 0), radius `hole_radius`;
    - a blind hole from the max-z face at (0, 0), radius `hole_radius`, depth `blind_depth`
      (default H/2);
    - a step: the region x > L/2 - `step_length` (default L/4) is lowered from z = H to
      z = H - `step_depth` (default H/4).

    Hole cylinders have ``_HOLE_SECTIONS`` facets (a regular polygon inscribed in the circle).
    The features are described in ``mesh.metadata["features"]``.

    Returns
    -------
    trimesh.Trimesh
        Watertight mesh, mm.

    Raises
    ------
    ValueError
        When the features do not fit in the block.
    ImportError
        When no boolean engine (manifold3d) is installed.
    """
    length, width, height = (float(s) for s in size)
    if min(length, width, height) <= 0:
        raise ValueError(f"`size` must be 3 positive lengths, got {size!r}")
    blind_depth = height / 2.0 if blind_depth is None else float(blind_depth)
    step_length = length / 4.0 if step_length is None else float(step_length)
    step_depth = height / 4.0 if step_depth is None else float(step_depth)
    r = float(hole_radius)
    through_xy = (-length / 4.0, 0.0)
    blind_xy = (0.0, 0.0)
    step_x = length / 2.0 - step_length
    if not (0 < r and r < width / 2 and through_xy[0] - r > -length / 2
            and blind_xy[0] + r < step_x and through_xy[0] + r < blind_xy[0] - r):
        raise ValueError(f"`hole_radius` {r} does not fit the block {size!r}")
    if not 0 < blind_depth < height:
        raise ValueError(f"`blind_depth` must be in (0, {height}), got {blind_depth}")
    if not (0 < step_length < length / 2 and 0 < step_depth < height):
        raise ValueError(f"step {step_length} x {step_depth} mm does not fit the block {size!r}")
    _require_boolean_engine()
    import trimesh

    block = trimesh.creation.box(extents=(length, width, height))
    block.apply_translation((0.0, 0.0, height / 2.0))
    o = _CUT_OVERSHOOT
    through = trimesh.creation.cylinder(radius=r, height=height + 2 * o, sections=_HOLE_SECTIONS)
    through.apply_translation((*through_xy, height / 2.0))
    blind = trimesh.creation.cylinder(radius=r, height=blind_depth + o, sections=_HOLE_SECTIONS)
    blind.apply_translation((*blind_xy, height - blind_depth + (blind_depth + o) / 2.0))
    step = trimesh.creation.box(extents=(step_length + o, width + 2 * o, step_depth + o))
    step.apply_translation((step_x + (step_length + o) / 2.0, 0.0,
                            height - step_depth + (step_depth + o) / 2.0))
    mesh = trimesh.boolean.difference([block, through, blind, step], engine="manifold")
    if not mesh.is_watertight:
        raise RuntimeError("boolean difference gave a mesh that is not watertight")
    mesh.metadata["features"] = {
        "size": (length, width, height),
        "through_holes": [{"xy": through_xy, "radius": r}],
        "blind_holes": [{"xy": blind_xy, "radius": r, "depth": blind_depth}],
        "steps": [{"x_min": step_x, "depth": step_depth}],
        "hole_sections": _HOLE_SECTIONS,
    }
    return mesh


def _require_boolean_engine() -> None:
    try:
        import manifold3d  # noqa: F401  (trimesh's boolean engine)
    except ImportError as exc:
        raise ImportError("block_with_holes_and_steps needs the boolean engine manifold3d: "
                          "pip install manifold3d") from exc


# --------------------------------------------------------------------------------------------
# Procedural parts with soft creases, curved surfaces and holes (issue 25)
# --------------------------------------------------------------------------------------------

#: Default slopes (degrees from level) of a faceted dome's tiers, from its flat top outward:
#: creases of 18 to 20 degrees between tiers, soft (under the 30-degree feature angle of the
#: edge evaluation and the edge model). In the reference cell the camera looks up at about
#: 30 degrees from z_T, so a tier sloping more than about 60 degrees away from it (the 78 one,
#: on the side turned from the camera) is lit by the sheet and unseen: the stripe drops out
#: at a soft crease.
DOME_SLOPES_DEG = (0.0, 18.0, 38.0, 58.0, 78.0)
#: Facets around a dome's axis: 12 put 18 to 29 degrees between neighbouring facets of the
#: steeper tiers (2 asin(sin(slope) sin(180 / 12))), soft creases as well.
DOME_SECTORS = 12


def _dome_rings(radius: float, base_z: float, slopes_deg, sectors: int, phase: float,
                tier_drop: float):
    """Vertex rings of a faceted dome: its flat top, then one ring per tier outward, each
    tier falling `tier_drop` toward ``base_z`` at its slope (so spanning ``tier_drop /
    tan(slope)`` of the radius); the flat top takes the rest of `radius`. (K, sectors, 3)."""
    slopes = np.radians(np.asarray(slopes_deg, dtype=np.float64))
    if slopes.ndim != 1 or len(slopes) < 2 or np.any(np.diff(slopes) <= 0) \
            or slopes[0] < 0 or slopes[-1] >= np.pi / 2 or not tier_drop > 0:
        raise ValueError(f"`slopes_deg` must rise from >= 0 to < 90 degrees over at least two "
                         f"tiers and `tier_drop` be > 0, got {slopes_deg!r}, {tier_drop!r}")
    widths = tier_drop / np.tan(slopes[1:])
    top = radius - widths.sum()
    if not top > 0:
        raise ValueError(f"tiers of {tier_drop} mm at {slopes_deg!r} degrees need more than "
                         f"the radius {radius} mm")
    radii = top + np.concatenate([[0.0], np.cumsum(widths)])
    heights = base_z + tier_drop * np.arange(len(slopes) - 1, -1, -1)
    theta = phase + 2.0 * np.pi * np.arange(sectors) / sectors
    ring = np.stack([np.cos(theta), np.sin(theta), np.zeros(sectors)], axis=1)
    return np.stack([ring * r + (0.0, 0.0, z) for r, z in zip(radii, heights)])


def faceted_dome(radius: float = 30.0, base_height: float = 8.0, *,
                 slopes_deg=DOME_SLOPES_DEG, sectors: int = DOME_SECTORS,
                 tier_drop: float = 4.0, plinth_radius: float | None = None) -> trimesh.Trimesh:
    """A faceted dome on a prism: a creased surface the scanner sees (mm).

    A regular ``sectors``-gon prism of circumradius `radius`, z in [0, `base_height`], topped
    (toward +z, the underside the scanner sees when the part hangs along +z_T) by a convex
    faceted dome: a flat polygonal top, then tiers of rising slope (`slopes_deg`, degrees
    from level), each falling `tier_drop` toward the prism. Neighbouring tiers meet at creases
    of their slope difference; neighbouring facets of one tier at about
    ``2 asin(sin(slope) sin(180 / sectors))``. The steepest tier meets the prism's wall at
    ``90 - slopes_deg[-1]``: the part's outline seen along z. With `plinth_radius` (larger
    than `radius`) the prism is that wide and the dome stands on its face: its steepest tier
    meets a level face at a sharp (concave) crease, and the plinth's rim is the outline.

    Returns
    -------
    trimesh.Trimesh
        Watertight, convex; ``metadata["features"]`` gives the slopes, the tiers' radii and
        heights, and the crease angles.
    """
    import trimesh

    if not (radius > 0 and base_height > 0) or int(sectors) != sectors or sectors < 6:
        raise ValueError(f"`radius` and `base_height` must be > 0 and `sectors` an integer >= 6, "
                         f"got {radius!r}, {base_height!r}, {sectors!r}")
    rings = _dome_rings(float(radius), float(base_height), slopes_deg, int(sectors), 0.0,
                        float(tier_drop))
    base = rings[-1].copy()
    base[:, 2] = 0.0
    mesh = trimesh.convex.convex_hull(np.concatenate([rings.reshape(-1, 3), base]))
    if plinth_radius is not None:
        if not plinth_radius > radius:
            raise ValueError(f"`plinth_radius` must exceed `radius` {radius}, got "
                             f"{plinth_radius!r}")
        _require_boolean_engine()
        plinth = trimesh.creation.cylinder(radius=float(plinth_radius), height=base_height,
                                           sections=int(sectors))
        plinth.apply_translation((0.0, 0.0, base_height / 2.0))
        mesh = trimesh.boolean.union([mesh, plinth], engine="manifold")
    slopes = np.asarray(slopes_deg, dtype=np.float64)
    mesh.metadata["features"] = {
        "radius": float(radius), "base_height": float(base_height),
        "height": float(rings[0, 0, 2]), "slopes_deg": slopes.tolist(), "sectors": int(sectors),
        "tier_radii": np.linalg.norm(rings[:, 0, :2], axis=1).tolist(),
        "tier_heights": rings[:, 0, 2].tolist(),
        "crease_deg": np.diff(slopes).tolist(), "plinth_radius": plinth_radius,
    }
    return mesh


def fan_disk(radius: float = 45.0, thickness: float = 6.0, *, hub_radius: float = 20.0,
             hub_slopes_deg=(0.0, 20.0, 40.0, 62.0, 80.0), hub_sectors: int = 12,
             hub_tier_drop: float = 3.0,
             blades: int = 8, blade_height: float = 7.0, blade_thickness: float = 2.5,
             blade_pitch_deg: float = 30.0, blade_sections: int = 4,
             blade_twist_deg: float = 20.0) -> trimesh.Trimesh:
    """A fan-disk-like part (mm): a disc, a faceted hub and pitched, twisted blades.

    Toward +z (the underside the scanner sees when the part hangs along +z_T), on a regular
    48-gon disc of `radius` and `thickness` (z in [0, thickness]):

    - a faceted hub (:func:`faceted_dome`'s surface) of `hub_radius`, tiers at
      `hub_slopes_deg` each falling `hub_tier_drop`: soft creases of 18 to 22 degrees
      between tiers, and between the facets of a tier;
    - `blades` radial blades between the hub and the rim, `blade_height` tall, each a plate
      `blade_thickness` thick leaning `blade_pitch_deg` about its radial axis, twisted along
      its length: it is made of `blade_sections` straight pieces whose pitch grows by
      ``blade_twist_deg / (blade_sections - 1)`` from one to the next, each piece the hull
      of its two end sections, so neighbouring pieces meet at soft creases (a twisted blade's
      facets).

    Returns
    -------
    trimesh.Trimesh
        Watertight; ``metadata["features"]`` lists the dimensions.

    Raises
    ------
    ValueError
        When the hub and the blades do not fit the disc.
    """
    _require_boolean_engine()
    import trimesh

    r, t = float(radius), float(thickness)
    if not (0 < hub_radius < r - 4.0 and t > 0 and blade_height > 0 and blade_thickness > 0
            and int(blades) == blades and blades >= 0 and int(blade_sections) == blade_sections
            and blade_sections >= 2):
        raise ValueError(f"the hub ({hub_radius} mm) and blades must fit a disc of radius {r}")
    o = _CUT_OVERSHOOT
    disc = trimesh.creation.cylinder(radius=r, height=t, sections=48)
    disc.apply_translation((0.0, 0.0, t / 2.0))
    rings = _dome_rings(float(hub_radius), t, hub_slopes_deg, int(hub_sectors),
                        np.pi / hub_sectors, float(hub_tier_drop))
    foot = rings[-1].copy()
    foot[:, 2] = t - o
    hub = trimesh.convex.convex_hull(np.concatenate([rings.reshape(-1, 3), foot]))
    pieces = [disc, hub]
    r0, r1 = hub_radius - 1.0, r - 3.0  # into the hub's steep tier; short of the rim
    cuts = np.linspace(r0, r1, int(blade_sections))
    pitches = np.radians(blade_pitch_deg + np.linspace(0.0, blade_twist_deg, len(cuts)))
    for k in range(int(blades)):
        phi = 2.0 * np.pi * k / blades
        radial = np.array([np.cos(phi), np.sin(phi), 0.0])
        side = np.array([-np.sin(phi), np.cos(phi), 0.0])
        sections = []
        for rad, pitch in zip(cuts, pitches):
            lean = np.cos(pitch) * np.array([0.0, 0.0, 1.0]) + np.sin(pitch) * side
            across = np.cos(pitch) * side - np.sin(pitch) * np.array([0.0, 0.0, 1.0])
            centre = rad * radial + (0.0, 0.0, t - o)
            half = 0.5 * blade_thickness * across
            up = (blade_height + o) * lean
            sections.append(np.array([centre - half, centre + half,
                                      centre - half + up, centre + half + up]))
        for a, b in zip(sections[:-1], sections[1:]):
            pieces.append(trimesh.convex.convex_hull(np.concatenate([a, b])))
    mesh = trimesh.boolean.union(pieces, engine="manifold")
    if not mesh.is_watertight:
        raise RuntimeError("boolean union gave a mesh that is not watertight")
    mesh.metadata["features"] = {
        "radius": r, "thickness": t, "hub_radius": float(hub_radius),
        "hub_slopes_deg": list(map(float, hub_slopes_deg)), "hub_sectors": int(hub_sectors),
        "hub_height": float(rings[0, 0, 2] - t), "blades": int(blades),
        "blade_height": float(blade_height), "blade_pitch_deg": float(blade_pitch_deg),
        "blade_twist_deg": float(blade_twist_deg), "blade_sections": int(blade_sections),
    }
    return mesh


def bracket_with_two_holes(size=(70.0, 40.0, 6.0), *, step_height: float = 5.0,
                           step_x: float = 10.0, hole_radii=(4.0, 3.0),
                           rib_height: float = 0.0) -> trimesh.Trimesh:
    """A bracket (mm): a plate with two through holes and a step.

    The plate is ``size = (L, W, T)``, x in [-L/2, L/2], y in [-W/2, W/2]; toward +z (the
    underside the scanner sees), its part x > `step_x` is `step_height` thicker (z up to
    T + step_height), the rest z up to T. One through hole of ``hole_radii[0]`` in the thin
    part at x = (step_x - L/2) / 2, one of ``hole_radii[1]`` in the thick part at
    x = (step_x + L/2) / 2, both at y = 0 (``_HOLE_SECTIONS`` facets). With `rib_height`,
    a rib runs along x on the thin part's face at y = W/4 (2 mm wide): a lower step.

    Returns
    -------
    trimesh.Trimesh
        Watertight; ``metadata["features"]`` gives the holes' centres and radii and the step.
    """
    _require_boolean_engine()
    import trimesh

    length, width, t = (float(s) for s in size)
    h = float(step_height)
    x_thin = (step_x - length / 2.0) / 2.0
    x_thick = (step_x + length / 2.0) / 2.0
    r_thin, r_thick = (float(v) for v in hole_radii)
    if not (min(length, width, t, h, r_thin, r_thick) > 0 and -length / 2 < step_x < length / 2
            and x_thin - r_thin > -length / 2 and x_thin + r_thin < step_x
            and x_thick - r_thick > step_x and x_thick + r_thick < length / 2
            and max(r_thin, r_thick) < width / 4 - 1.5):
        raise ValueError(f"the holes {hole_radii!r} and the step at x = {step_x} do not fit "
                         f"the plate {size!r}")
    o = _CUT_OVERSHOOT
    plate = trimesh.creation.box(extents=(length, width, t))
    plate.apply_translation((0.0, 0.0, t / 2.0))
    thick = trimesh.creation.box(extents=(length / 2.0 - step_x, width, h + o))
    thick.apply_translation(((step_x + length / 2.0) / 2.0, 0.0, t + (h - o) / 2.0))
    pieces = [plate, thick]
    if rib_height > 0:
        rib = trimesh.creation.box(extents=(step_x + length / 2.0 - 4.0, 2.0, rib_height + o))
        rib.apply_translation(((step_x - length / 2.0) / 2.0, width / 4.0,
                               t + (rib_height - o) / 2.0))
        pieces.append(rib)
    body = trimesh.boolean.union(pieces, engine="manifold")
    holes = []
    for (x, rad) in ((x_thin, r_thin), (x_thick, r_thick)):
        hole = trimesh.creation.cylinder(radius=rad, height=t + h + 2 * o,
                                         sections=_HOLE_SECTIONS)
        hole.apply_translation((x, 0.0, (t + h) / 2.0))
        holes.append(hole)
    mesh = trimesh.boolean.difference([body, *holes], engine="manifold")
    if not mesh.is_watertight:
        raise RuntimeError("boolean difference gave a mesh that is not watertight")
    mesh.metadata["features"] = {
        "size": (length, width, t), "step": {"x_min": float(step_x), "height": h},
        "through_holes": [{"xy": (x_thin, 0.0), "radius": r_thin},
                          {"xy": (x_thick, 0.0), "radius": r_thick}],
        "rib_height": float(rib_height), "hole_sections": _HOLE_SECTIONS,
    }
    return mesh


def crowned_block(size=(60.0, 40.0, 10.0), *, crown_radius: float = 25.0,
                  crown_height: float = 8.0, axis_deg: float = 45.0,
                  sections: int = 96) -> trimesh.Trimesh:
    """A block with a cylindrical crown: a curved surface turning away from the camera (mm).

    A box ``size = (L, W, H)`` (z in [0, H]) topped, toward +z, by the part of a cylinder of
    `crown_radius` that rises `crown_height` above the box's face, its axis level and turned
    `axis_deg` from x about z, clipped to the box's outline. Where the crown turns more than
    about 60 degrees from level away from the camera (the cell's camera looks up at 30
    degrees from z_T), the sheet lights it and the camera does not see it: the stripe fades
    out on a smooth surface. The cylinder has `sections` facets around (creases of
    360 / sections degrees).

    Returns
    -------
    trimesh.Trimesh
        Watertight.
    """
    _require_boolean_engine()
    import trimesh

    length, width, height = (float(s) for s in size)
    rc, hc = float(crown_radius), float(crown_height)
    if not (min(length, width, height) > 0 and 0 < hc < rc):
        raise ValueError(f"crown {rc} x {hc} mm does not fit the block {size!r}")
    o = _CUT_OVERSHOOT
    block = trimesh.creation.box(extents=(length, width, height))
    block.apply_translation((0.0, 0.0, height / 2.0))
    span = 2.0 * float(np.hypot(length, width))
    cylinder = trimesh.creation.cylinder(radius=rc, height=span, sections=int(sections))
    cylinder.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    cylinder.apply_transform(trimesh.transformations.rotation_matrix(np.radians(axis_deg),
                                                                     [0, 0, 1]))
    cylinder.apply_translation((0.0, 0.0, height + hc - rc))
    clip = trimesh.creation.box(extents=(length, width, hc + o))
    clip.apply_translation((0.0, 0.0, height + (hc - o) / 2.0))
    crown = trimesh.boolean.intersection([cylinder, clip], engine="manifold")
    mesh = trimesh.boolean.union([block, crown], engine="manifold")
    if not mesh.is_watertight:
        raise RuntimeError("boolean union gave a mesh that is not watertight")
    mesh.metadata["features"] = {"size": (length, width, height), "crown_radius": rc,
                                 "crown_height": hc, "axis_deg": float(axis_deg),
                                 "sections": int(sections)}
    return mesh
