"""The part's CAD model: a mesh in millimetres with its unit, its source and its nominal grasp.

What the scanner registers a scan against (``scanner_core.pose.registration``) and sets its edge points
by (``scanner_core.edges.kinds``), and what the service keeps for each part: loaded from a
mesh file with its unit (a mesh file carries no reliable unit, so every loader takes one and
converts to mm), checked (readable, a plausible size for its unit, inside the inspection
volume at its grasp). The simulator's part (``simulator.parts.Part``) adds how its surface
returns the laser and a ray-casting scene.

The part frame {P} is the CAD file's own frame. The gripper frame {T} has z_T pointing down in
the robot base: the gripper holds the part from above, so the part hangs along +z_T, and the
scanner (the laser sheet below) sees the part's max-z_T face. The nominal grasp ^T X_P maps
points of {P} to {T}: X_T = R X_P + t.
"""
from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from scanner_core.geometry import apply_transform, check_rigid
from scanner_core.io.meshfile import check_ply_counts, clean_triangles, is_binary_stl, read_mesh

if TYPE_CHECKING:  # imported where used: ray casting alone needs neither trimesh nor scipy
    from scanner_core.inspection import InspectionParams
    import trimesh

__all__ = ["UNITS_MM", "PLAUSIBLE_SIZE_MM", "INSPECTION_VOLUME_MM", "GRIPPER_TOLERANCE_MM",
           "MODEL_FACES", "simplified_for_scan",
           "PartError", "PartModel", "load_part", "part_from_mesh", "saved_part", "centred_grasp",
           "flat_grasp", "GRASPS", "named_grasp", "check_fits", "canonical_unit",
           "check_rigid_grasp"]

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


class PartError(ValueError):
    """A part cannot be used: bad unit, unreadable or empty file, bad geometry, too large."""


@dataclass(frozen=True, eq=False)
class PartModel:
    """A CAD part, in millimetres: what the scanner registers its scans against.

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
    inspection : scanner_core.inspection.InspectionParams or None
        The part's own thresholds for the inspection (from its plan or its upload), over
        those of the service or the command; None: none of its own.

    The models built from the mesh for registration (``surface_model``, ``edge_model``,
    ``model_edges``) are built on first use and kept (``prepare`` builds them, with their
    KD-trees, before a scan needs them). The simulator's part
    (``simulator.parts.Part``) is one of these with how its surface returns the laser and a
    ray-casting scene.
    """

    name: str
    vertices: np.ndarray = field(repr=False)
    faces: np.ndarray = field(repr=False)
    source: str
    units: str
    grasp: np.ndarray = field(repr=False)
    inspection: InspectionParams | None = field(default=None, repr=False)

    @cached_property
    def mesh(self) -> "trimesh.Trimesh":
        """The part as a ``trimesh.Trimesh`` (built on first use: ray casting alone does not
        need trimesh, whose import costs half a second). Treat as read-only."""
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)

    @cached_property
    def version(self) -> str:
        """The part's content hash: 16 hex digits of the SHA-256 of its triangles (vertices in
        mm, float64; faces, int64), its unit and its nominal grasp. Two models with the same
        name and another mesh, unit or grasp differ in it; the same content read again (from
        any file format) keeps it."""
        digest = hashlib.sha256()
        digest.update(self.units.encode())
        for array, dtype in ((self.vertices, np.float64), (self.faces, np.int64),
                             (self.grasp, np.float64)):
            digest.update(np.ascontiguousarray(array, dtype=dtype).tobytes())
        return digest.hexdigest()[:16]

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
    def surface_model(self):
        """The CAD surface sampled for registration (``scanner_core.pose.registration.SurfaceModel``),
        built on first use and kept: every scan of the part reuses it."""
        from scanner_core.pose.registration import SurfaceModel
        return SurfaceModel.from_mesh(self.mesh)

    @cached_property
    def coverage_model(self):
        """The CAD surface sampled more coarsely, what the inspection judges the scan's
        coverage on (``scanner_core.inspection.coverage``), with its KD-tree."""
        from scanner_core.inspection.coverage import COVERAGE_SPACING_MM
        from scanner_core.pose.registration import SurfaceModel
        sampled = SurfaceModel.from_mesh(self.mesh, spacing_mm=COVERAGE_SPACING_MM,
                                         max_points=100_000, seed=1)
        # in its KD-tree's leaf order, neighbours side by side in memory: the check's loops
        # over the samples then read the cloud's points near each in turn, not at random
        order = sampled.tree.indices
        return replace(sampled, points=sampled.points[order], normals=sampled.normals[order],
                       faces=sampled.faces[order])

    def occluded(self, origins, directions) -> np.ndarray:
        """Whether rays (origins (R, 3), directions (R, 3), {P} mm) meet the part: (R,) bool.
        Embree's any-hit query where embreex is installed (it stops at the first face it
        meets, where trimesh's ``intersects_any`` finds the nearest), trimesh's own tests
        otherwise."""
        origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        if not len(origins):
            return np.zeros(0, bool)
        directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        if self._occlusion_scene is None:
            return np.asarray(self.mesh.ray.intersects_any(origins, directions), bool)
        scene, origin = self._occlusion_scene
        return scene.run((origins - origin).astype(np.float32), directions.astype(np.float32),
                         query="OCCLUDED") != -1

    @cached_property
    def _occlusion_scene(self):
        """Embree's scene of the mesh and the origin its float32 vertices are taken from (the
        mesh's lower corner: the part's own extent keeps their precision), or None without
        embreex."""
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
        except ImportError:
            return None
        origin = np.asarray(self.mesh.vertices, dtype=np.float64).min(axis=0)
        scene = rtcore_scene.EmbreeScene()
        TriangleMesh(scene=scene, vertices=(self.mesh.vertices - origin).astype(np.float32),
                     indices=np.asarray(self.mesh.faces, dtype=np.int32))
        return scene, origin

    @cached_property
    def edge_model(self):
        """The CAD's sharp edges for registration (``scanner_core.pose.registration.EdgeModel``), a
        narrow chamfer's on the outline seen from the sensor under the nominal grasp."""
        from scanner_core.pose.registration import EdgeModel
        return EdgeModel.from_mesh(self.mesh, view=self.grasp[2, :3])

    @cached_property
    def model_edges(self):
        """The CAD's sharp edges and what its outline needs
        (``scanner_core.edges.kinds.ModelEdges``), for edge kinds after registration."""
        from scanner_core.edges.kinds import ModelEdges
        return ModelEdges.from_mesh(self.mesh)

    def prepare(self) -> float:
        """Build now, and keep, everything a scan's pose uses that does not depend on the
        scan: the surface and edge models with their KD-trees, grids and lookup tables, the
        part's exact symmetries, the surface's crease planes, the edge model's curves, and the
        model edges of the edge kinds; the wall time it took, ms (0 when all was built).
        Otherwise the first pose of the part builds them (about 0.5-1.5 s for the reference
        parts, and 0.2-1.9 s more for the crease planes) while the robot waits."""
        t0 = time.perf_counter()
        for model in (self.surface_model, self.edge_model):
            model.tree  # noqa: B018 - cached_property: built here, kept
            model.grid  # noqa: B018
            model.lookup  # noqa: B018
        self.surface_model.symmetries  # noqa: B018
        self.surface_model.crease_planes  # noqa: B018
        self.edge_model.curves  # noqa: B018
        self.model_edges  # noqa: B018
        self.coverage_model.tree  # noqa: B018
        self.occluded(np.zeros((1, 3)), np.ones((1, 3)))  # the ray scene
        self.__dict__["_prepared"] = True
        return (time.perf_counter() - t0) * 1e3

    @property
    def prepared(self) -> bool:
        """Whether `prepare` has built everything a scan's pose needs (and nothing released
        it since)."""
        return self.__dict__.get("_prepared", False)

    def release(self) -> None:
        """Drop what `prepare` built (and the trimesh object): its memory goes back, and the
        next scan of the part builds it again. A scan holding one of them keeps it."""
        for name in ("surface_model", "edge_model", "model_edges", "coverage_model",
                     "_occlusion_scene", "mesh", "_prepared"):
            self.__dict__.pop(name, None)

    def vertices_t(self) -> np.ndarray:
        """(V, 3) float64, mm: the mesh vertices in {T} under the nominal grasp."""
        return apply_transform(self.grasp, self.vertices)


# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------

def load_part(path, units: str, *, name: str | None = None,
              grasp: str | np.ndarray | None = None) -> PartModel:
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
    PartModel
        The mesh in mm, with degenerate faces and unreferenced vertices removed.

    Raises
    ------
    PartError
        Unknown unit, missing, empty or unparseable file, no triangles, non-finite vertices.
        A size implausible for the unit (largest extent outside `PLAUSIBLE_SIZE_MM`), with
        the unit that would make it plausible.
    """
    unit = canonical_unit(units)
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
    elif suffix == ".ply":
        try:
            check_ply_counts(p)
        except ValueError as exc:
            raise PartError(f"cannot read part file {p}: {exc}") from None


def _is_text(p: Path) -> bool:
    data = p.read_bytes()
    if b"\x00" in data:
        return False
    try:
        data.decode("utf-8")
    except UnicodeDecodeError:
        return False
    return True


def saved_part(vertices, faces, grasp, *, name: str, units: str, source: str) -> PartModel:
    """A part model from the arrays a part model holds, as they are (not cleaned again): what
    a recording keeps of the part its pass scanned, read back identical.

    Parameters
    ----------
    vertices : (V, 3) float64
        mm, in {P}.
    faces : (F, 3) int64
    grasp : (4, 4) float64
        The nominal ^T X_P.
    name, units, source : str
        As the part had them (``units``: the unit of its original file).

    Raises
    ------
    PartError
        Arrays of the wrong shape, indices outside the vertices, non-finite values.
    """
    vertices = np.array(vertices, dtype=np.float64)
    faces = np.array(faces, dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3 \
            or len(faces) == 0:
        raise PartError(f"part {name!r} ({source}): vertices must be (V, 3) and faces (F, 3), "
                        f"got {vertices.shape} and {faces.shape}")
    if faces.min() < 0 or faces.max() >= len(vertices) or not np.all(np.isfinite(vertices)):
        raise PartError(f"part {name!r} ({source}) has face indices outside its vertices or "
                        "non-finite vertices")
    grasp = _check_grasp(grasp)
    for array in (vertices, faces, grasp):
        array.setflags(write=False)
    return PartModel(name=name, vertices=vertices, faces=faces, source=source,
                     units=canonical_unit(units), grasp=grasp)


def part_from_mesh(mesh: "trimesh.Trimesh", *, name: str, units: str = "mm",
                   source: str = "procedural", grasp: str | np.ndarray | None = None) -> PartModel:
    """Make a part from a mesh in memory (copied, converted to mm and cleaned).

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
    PartModel

    Raises
    ------
    PartError
        As `load_part`, for the mesh content.
    """
    unit = canonical_unit(units)
    if not hasattr(mesh, "vertices") or not hasattr(mesh, "faces"):
        raise PartError(f"part {name!r} ({source}) is not a triangle mesh "
                        f"(got {type(mesh).__name__})")
    return _make_part(mesh.vertices, mesh.faces, name=name, unit=unit, source=source,
                      grasp=grasp)


#: A mesh with more triangles than this is simplified for the scanner (`simplified_for_scan`):
#: the registration samples surfaces every 0.25 mm (``SurfaceModel``) and the scan resolves
#: about 20 um, so a CAD export of millions of triangles holds nothing more for it, only
#: memory (about 1 GB for 1.3 M triangles) and preparation time.
MODEL_FACES = 150_000
#: ... unless the simplified surface strays this far from the mesh's (99th percentile of
#: either's samples' distances to the other), mm: then the mesh is kept whole.
MODEL_DEVIATION_MM = 0.005
#: Surface samples each way that measure how far the simplified mesh strays.
DEVIATION_SAMPLES = 3000


def simplified_for_scan(part: PartModel, max_faces: int = MODEL_FACES,
                        tolerance_mm: float = MODEL_DEVIATION_MM) -> tuple[PartModel, dict | None]:
    """The part as the scanner needs it: its mesh decimated to `max_faces` triangles by
    quadric error (Garland and Heckbert 1997, ``trimesh``'s ``simplify_quadric_decimation``
    through ``fast_simplification``) when it has more than twice as many, and kept so when the
    two surfaces lie within `tolerance_mm` of each other (99th percentile of
    ``DEVIATION_SAMPLES`` samples of each, measured to the other). The nominal grasp is the
    part's.

    Returns
    -------
    part : PartModel
        Simplified, or `part` itself.
    report : dict or None
        ``faces_from``, ``faces_to``, ``deviation_p99_um``, ``deviation_max_um``,
        ``kept`` (whether the simplified mesh was kept); None when the mesh was small enough.
    """
    import fast_simplification
    import trimesh

    if len(part.faces) <= 2 * max_faces:
        return part, None
    points, triangles = fast_simplification.simplify(  # writable copies: it takes no views
        np.array(part.vertices, dtype=np.float64), np.array(part.faces, dtype=np.int64),
        target_count=int(max_faces))
    simple = trimesh.Trimesh(points, triangles, process=False)
    deviations = []
    rng = np.random.default_rng(0)
    for source, target in ((part.mesh, simple), (simple, part.mesh)):
        samples, _ = trimesh.sample.sample_surface(source, DEVIATION_SAMPLES,
                                                   seed=int(rng.integers(2**31)))
        _, distance, _ = trimesh.proximity.closest_point(target, samples)
        deviations.append(distance)
    distance = np.concatenate(deviations)
    report = {"faces_from": int(len(part.faces)), "faces_to": int(len(simple.faces)),
              "deviation_p99_um": round(float(np.percentile(distance, 99)) * 1e3, 3),
              "deviation_max_um": round(float(distance.max()) * 1e3, 3)}
    report["kept"] = bool(report["deviation_p99_um"] <= tolerance_mm * 1e3)
    if not report["kept"]:
        return part, report
    vertices = np.asarray(simple.vertices, dtype=np.float64)
    faces = np.asarray(simple.faces, dtype=np.int64)
    for array in (vertices, faces):
        array.setflags(write=False)
    return PartModel(name=part.name, vertices=vertices, faces=faces,
                     source=f"{part.source} (simplified to {len(faces)} triangles)",
                     units=part.units, grasp=part.grasp), report


def canonical_unit(units) -> str:
    """`units` as one of `UNITS_MM` (other spellings accepted), or PartError."""
    key = str(units).strip().lower() if isinstance(units, str) else None
    key = _UNIT_ALIASES.get(key, key)
    if key not in UNITS_MM:
        raise PartError(f"unknown unit {units!r}; allowed: {', '.join(UNITS_MM)}")
    return key


def _make_part(vertices, faces, *, name: str, unit: str, source: str, grasp) -> PartModel:
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
    return PartModel(name=name, vertices=vertices, faces=faces, source=source, units=unit,
                     grasp=grasp)


def _check_plausible_size(part: PartModel, unit: str) -> None:
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


def check_fits(part: PartModel, volume_mm=INSPECTION_VOLUME_MM, *, pose=None) -> None:
    """Raise when the part, under its nominal grasp or `pose`, does not fit the inspection volume.

    The volume hangs below the TCP: x_T and y_T within half its size either side, z_T from 0
    (the gripper) to its height. A part may be small enough and still sit outside it, when
    its grasp (the identity, say, for a CAD origin far from the part) or a misplacement puts
    it elsewhere; a part reaching above z_T = 0 would be inside the gripper.

    Parameters
    ----------
    part : PartModel
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


def check_rigid_grasp(grasp) -> np.ndarray:
    """`grasp` as a read-only (4, 4) float64 rigid ^T X_P; PartError naming what is wrong."""
    checked = _check_grasp(grasp)
    checked.setflags(write=False)
    return checked


def _check_grasp(grasp) -> np.ndarray:
    try:
        return check_rigid(grasp)
    except ValueError as exc:
        raise PartError(f"`grasp` {exc}") from None


def _bounds_t(part: "PartModel", pose: np.ndarray) -> np.ndarray:
    """(2, 3) float64, mm: the part's bounding box in {T} under ^T X_P = `pose`."""
    if np.allclose(pose[:3, :3], np.eye(3)):
        return part.bounds + pose[:3, 3]
    v = apply_transform(pose, part.vertices)
    return np.stack([v.min(axis=0), v.max(axis=0)])
