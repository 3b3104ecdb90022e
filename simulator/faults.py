"""What a gripper may hold that is not the expected part, alone and whole: faults the simulated
cell can put into it, each as a mesh in the good part's CAD frame {P} (mm), held by the good
part's grasp while the scanner registers the good part.

- ``double``: a second part hooked on the first, touching it at a side drawn at random,
  turned at random (``size`` unused: the whole part);
- ``debris``: a blob of diameter ``size`` half sunk into a face the sensor sees;
- ``chip``: a ball of radius ``size`` cut away at a corner or an edge the sensor sees
  (manifold3d's boolean difference);
- ``variant``: the part ``size`` longer along its longest axis (its features kept, its ends
  moved apart);
- ``hole``: a variant with a hole of diameter ``size`` drilled through the part, square to a
  face the sensor sees (manifold3d's boolean difference);
- ``bend``: the part bent along its longest axis, its ends ``size`` toward the sensor.

The faults are drawn from ``rng``; ``toward_p`` is the {P} direction that hangs toward the
sensor (``grasp[2, :3]``), so that the fault lies where the scan can see it.
"""
from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

__all__ = ["FAULT_KINDS", "DEFAULT_SIZES_MM", "faulty_mesh", "faulty_part", "parse_fault"]

FAULT_KINDS = ("double", "debris", "chip", "variant", "hole", "bend")
#: The size of each fault when none is given, mm (``double``: unused).
DEFAULT_SIZES_MM = {"double": 0.0, "debris": 3.0, "chip": 2.0, "variant": 2.0, "hole": 3.0,
                    "bend": 0.3}
# The second part of a double pick overlaps the first by this share of its depth: touching.
_CONTACT_OVERLAP = 0.05


def parse_fault(text: str) -> tuple[str, float]:
    """``KIND[:SIZE]`` -> (kind, size in mm); ValueError naming the kinds."""
    kind, _, size = str(text).partition(":")
    if kind not in FAULT_KINDS:
        raise ValueError(f"unknown fault {kind!r}: one of {', '.join(FAULT_KINDS)}, as "
                         f"KIND[:SIZE_MM]")
    try:
        value = float(size) if size else DEFAULT_SIZES_MM[kind]
    except ValueError:
        raise ValueError(f"the fault's size must be a number of mm, got {size!r}") from None
    if not (np.isfinite(value) and value >= 0):
        raise ValueError(f"the fault's size must be a non-negative number of mm, got {size!r}")
    return kind, value


def faulty_part(part, fault: str, rng: np.random.Generator):
    """What the gripper holds instead of ``part`` (a ``simulator.parts.Part``): the fault
    ``KIND[:SIZE]`` (``parse_fault``) built on its mesh, held by its grasp, with its surface.
    ValueError for a malformed fault, or one its mesh cannot take (a chip of an open mesh)."""
    from simulator.parts import part_from_mesh
    from simulator.surfaces import with_surface

    kind, size = parse_fault(fault)
    mesh = faulty_mesh(part.mesh, kind, size, part.grasp[2, :3], rng)
    return with_surface(part_from_mesh(mesh, name=f"{part.name} ({fault})",
                                       source=f"fault:{fault}", grasp=part.grasp),
                        part.surface)


def faulty_mesh(mesh: trimesh.Trimesh, kind: str, size_mm: float, toward_p,
                rng: np.random.Generator) -> trimesh.Trimesh:
    """The good part's mesh (mm, {P}) with the fault ``kind`` of ``size_mm`` (module docstring).

    Returns a new mesh; ValueError for an unknown kind."""
    toward = np.asarray(toward_p, dtype=np.float64)
    toward = toward / np.linalg.norm(toward)
    if kind == "double":
        return _double(mesh, toward, rng)
    if kind == "debris":
        return _debris(mesh, size_mm, toward, rng)
    if kind == "chip":
        return _chip(mesh, size_mm, toward, rng)
    if kind == "variant":
        return _stretched(mesh, size_mm)
    if kind == "hole":
        return _drilled(mesh, size_mm, toward, rng)
    if kind == "bend":
        return _bent(mesh, size_mm, toward)
    raise ValueError(f"unknown fault {kind!r}: one of {', '.join(FAULT_KINDS)}")


def _double(mesh, toward, rng):
    other = mesh.copy()
    centre = mesh.bounds.mean(axis=0)
    turn = np.eye(4)
    turn[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    other.apply_transform(trimesh.transformations.translation_matrix(-centre))
    other.apply_transform(turn)
    # beside the first part, off to a side at random and touching it there (their extents
    # along that side overlap a little), at a height anywhere along the first one's depth
    side = rng.normal(size=3)
    side -= (side @ toward) * toward
    side /= np.linalg.norm(side)
    reach = float(np.max((mesh.vertices - centre) @ side))
    other_reach = float(-np.min(other.vertices @ side))
    depth = float(np.ptp(mesh.vertices @ toward))
    shift = (centre + side * (reach + other_reach) * (1.0 - _CONTACT_OVERLAP)
             + toward * rng.uniform(-0.25, 0.25) * depth)
    other.apply_transform(trimesh.transformations.translation_matrix(shift))
    return trimesh.util.concatenate([mesh, other])


def _visible_point(mesh, toward, rng):
    """A point on a face the sensor sees (its normal within 45 degrees of ``toward``), drawn
    by area, and that face's normal."""
    normals = mesh.face_normals
    facing = np.nonzero(normals @ toward > np.cos(np.radians(45.0)))[0]
    if not len(facing):
        facing = np.arange(len(mesh.faces))
    weights = mesh.area_faces[facing] / mesh.area_faces[facing].sum()
    face = rng.choice(facing, p=weights)
    a, b, c = mesh.vertices[mesh.faces[face]]
    u, v = rng.uniform(size=2)
    if u + v > 1:
        u, v = 1 - u, 1 - v
    return a + u * (b - a) + v * (c - a), normals[face]


def _debris(mesh, size, toward, rng):
    point, normal = _visible_point(mesh, toward, rng)
    radius = 0.5 * max(size, 1e-3)
    blob = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    blob.apply_translation(point + normal * 0.5 * radius)
    return trimesh.util.concatenate([mesh, blob])


def _chip(mesh, size, toward, rng):
    # a corner or an edge the sensor sees: among the hull's vertices, those farthest toward it
    hull = mesh.convex_hull.vertices
    height = hull @ toward
    near = hull[height >= height.max() - 0.25 * np.ptp(height)]
    corner = near[rng.integers(len(near))]
    ball = trimesh.creation.icosphere(subdivisions=3, radius=max(size, 1e-3))
    ball.apply_translation(corner)
    if not mesh.is_volume:
        raise ValueError("a chip is cut from a closed mesh (a volume): this one is open")
    return trimesh.boolean.difference([mesh, ball], engine="manifold")


def _drilled(mesh, size, toward, rng):
    if not mesh.is_volume:
        raise ValueError("a hole is drilled through a closed mesh (a volume): this one is open")
    point, normal = _visible_point(mesh, toward, rng)
    through = 2.0 * float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    drill = trimesh.creation.cylinder(radius=0.5 * max(size, 1e-3), height=through,
                                      sections=48)
    turn = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], normal)
    turn[:3, 3] = point
    drill.apply_transform(turn)
    return trimesh.boolean.difference([mesh, drill], engine="manifold")


def _longest_axis(mesh):
    return int(np.argmax(np.ptp(mesh.vertices, axis=0)))


def _stretched(mesh, size):
    out = mesh.copy()
    axis = _longest_axis(mesh)
    centre = mesh.bounds.mean(axis=0)[axis]
    v = out.vertices.copy()
    v[:, axis] += np.sign(v[:, axis] - centre) * 0.5 * size
    out.vertices = v
    return out


def _bent(mesh, size, toward):
    out = mesh.copy()
    axis = _longest_axis(mesh)
    lo, hi = mesh.bounds[:, axis]
    half = 0.5 * (hi - lo)
    x = (out.vertices[:, axis] - 0.5 * (lo + hi)) / half
    out.vertices = out.vertices + np.outer(size * x**2, toward)
    return out
