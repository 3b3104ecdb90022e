"""Model no more than the scene needs: the coarsest mesh whose predicted cloud matches the full one.

A CAD export often carries more triangles than the scanner can tell apart. The predicted
clouds of a mesh and of its quadric-decimated copies (MeshLab's quadric edge collapse,
Garland and Heckbert 1997, through pymeshlab: it keeps closed meshes closed and reaches the
face count asked for, which fast-simplification did not on these parts) are compared ray
by ray, every mesh swept with the very same rays: the distance of the simplified mesh's
point from the full mesh's tangent plane (point-to-plane, as a registration would see it),
and the rays that hit in one cloud and not the other, or another surface.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import trimesh

from simulator.parts import Part, part_from_mesh
from simulator.virtual_setup import PredictedCloud, VirtualSetup, predict_cloud, prepare

__all__ = ["cloud_deviation", "simplify_part", "SimplificationLevel", "coarsest_simplification"]

#: The study's default limits: 5 um RMS (the issue's), and at most 1 % of the points gained
#: or lost at silhouettes.
TOLERANCE_UM = 5.0
MAX_COVERAGE_CHANGE = 0.01
#: A ray's point this far off the reference surface, or its normal turned this much, hit
#: another surface (see `cloud_deviation`).
SWITCH_UM, SWITCH_DEG = 100.0, 30.0


def cloud_deviation(reference: PredictedCloud, other: PredictedCloud, *,
                    switch_um: float = SWITCH_UM, switch_deg: float = SWITCH_DEG) -> dict:
    """Compare two predicted clouds of the same sweep, ray by ray.

    A ray whose point moved by more than `switch_um` off the reference's tangent plane, or
    whose normal turned by more than `switch_deg`, landed on another surface (it grazed an
    edge that moved): it counts as a change of coverage, like a ray kept by one cloud only,
    not in the RMS, where a single one would outweigh a million good rays.

    Parameters
    ----------
    reference, other : PredictedCloud
        Same sweep: the same setup, fan and part pose (`VirtualSetup.with_fan`).
    switch_um, switch_deg : float
        Thresholds of a switched surface.

    Returns
    -------
    dict
        ``rms_um``, ``p99_um``, ``max_um``: point-to-plane distances of `other`'s points from
        `reference`'s tangent planes over the rays that both kept on the same surface
        (micrometres); ``matched``; ``switched``; ``missing`` and ``extra``: rays only
        `reference`, or only `other`, kept; ``coverage_change``: (switched + missing +
        extra) / len(reference).

    Raises
    ------
    ValueError
        When the clouds come from different sweeps.
    """
    a, b = reference.setup, other.setup
    if (a.step_mm != b.step_mm or not np.array_equal(a.laser, b.laser)
            or not np.array_equal(a.camera, b.camera) or not np.array_equal(a.motion, b.motion)
            or not np.array_equal(reference.fan, other.fan)
            or not np.array_equal(reference.pose, other.pose)):
        raise ValueError("the clouds come from different sweeps (setup, fan or pose): fix the "
                         "fan with VirtualSetup.with_fan and compare like with like")
    n_rays = len(reference.fan)
    key_a = reference.step.astype(np.int64) * n_rays + reference.ray
    key_b = other.step.astype(np.int64) * n_rays + other.ray
    _, ia, ib = np.intersect1d(key_a, key_b, assume_unique=True, return_indices=True)
    d = np.abs(np.einsum("ij,ij->i", other.points[ib] - reference.points[ia],
                         reference.normals[ia])) * 1e3
    cos = np.einsum("ij,ij->i", other.normals[ib], reference.normals[ia])
    same = (d <= switch_um) & (cos >= np.cos(np.radians(switch_deg)))
    d = d[same]
    switched = int(np.count_nonzero(~same))
    missing, extra = len(key_a) - len(ia), len(key_b) - len(ib)
    return {
        "rms_um": float(np.sqrt(np.mean(d ** 2))) if len(d) else float("nan"),
        "p99_um": float(np.percentile(d, 99)) if len(d) else float("nan"),
        "max_um": float(d.max()) if len(d) else float("nan"),
        "matched": int(len(d)), "switched": switched, "missing": int(missing),
        "extra": int(extra),
        "coverage_change": (switched + missing + extra) / max(len(key_a), 1),
    }


def simplify_part(part: Part, face_count: int) -> Part:
    """A quadric-decimated copy of the part, with about `face_count` faces and the same grasp.

    Normals are kept from flipping, the topology and the open borders are kept, and planar
    regions collapse freely (MeshLab's ``planarquadric``).

    Raises
    ------
    ImportError
        Without pymeshlab (``pip install flyscan[simplify]``).
    """
    try:
        import pymeshlab
    except ImportError as exc:
        raise ImportError("mesh simplification needs pymeshlab: pip install 'flyscan[simplify]'"
                          ) from exc
    meshes = pymeshlab.MeshSet()
    meshes.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(part.vertices, np.float64),
                                   face_matrix=np.asarray(part.faces, np.int32)))
    meshes.meshing_decimation_quadric_edge_collapse(
        targetfacenum=int(face_count), preservenormal=True, preservetopology=True,
        preserveboundary=True, planarquadric=True, optimalplacement=True)
    result = meshes.current_mesh()
    mesh = trimesh.Trimesh(result.vertex_matrix(), result.face_matrix(), process=False)
    return part_from_mesh(mesh, name=f"{part.name}-{len(mesh.faces)}", source=part.source,
                          grasp=part.grasp)


@dataclass(frozen=True)
class SimplificationLevel:
    """One decimation level of the study: its size, its error, what it costs."""

    faces: int
    simplify_s: float
    build_s: float
    sweep_s: float
    points: int
    deviation: dict

    def passes(self, tolerance_um: float, max_coverage_change: float) -> bool:
        return (self.deviation["rms_um"] <= tolerance_um
                and self.deviation["coverage_change"] <= max_coverage_change)

    def to_dict(self) -> dict:
        return {"faces": self.faces, "simplify_s": round(self.simplify_s, 4),
                "build_s": round(self.build_s, 6), "sweep_s": round(self.sweep_s, 6),
                "points": self.points,
                **{k: (round(v, 4) if isinstance(v, float) else v)
                   for k, v in self.deviation.items()}}


def coarsest_simplification(part: Part, setup: VirtualSetup, *, pose=None,
                            tolerance_um: float = TOLERANCE_UM,
                            max_coverage_change: float = MAX_COVERAGE_CHANGE,
                            min_faces: int = 100, refine: int = 4, repeats: int = 3,
                            progress=None) -> dict:
    """The coarsest decimation whose predicted cloud stays within tolerance of the full
    mesh's, and the time it saves.

    The mesh is halved down to `min_faces` (the error curve), then the face count is
    bisected `refine` times (geometrically) between the coarsest level within tolerance and
    the next, coarser one: the answer is within a factor ``2 ** (2 ** -refine)`` of the
    coarsest possible.

    Parameters
    ----------
    part : Part
    setup : VirtualSetup
        The density the comparison is made at.
    pose : (4, 4) array_like, optional
        ^T X_P for every level; default the part's grasp.
    tolerance_um : float
        RMS point-to-plane limit.
    max_coverage_change : float
        Limit on the fraction of rays gained or lost.
    min_faces : int
        Stop halving below this many faces.
    refine : int
        Bisections after the halving.
    repeats : int
        Sweeps timed per level (the fastest counts).
    progress : callable, optional
        Called with a line of text after each level.

    Returns
    -------
    dict
        ``full`` (faces, build_s: `prepare`, sweep_s, points), ``levels``
        (`SimplificationLevel.to_dict` each, finest first), ``chosen`` (the coarsest passing
        level, or None) and ``sweep_time_saved`` (1 - chosen sweep time / full sweep time).
    """
    pose = part.grasp if pose is None else np.asarray(pose, dtype=np.float64)
    full_build, full = _timed_sweep(part, setup, pose, repeats)
    setup = setup.with_fan(full.fan)  # every level swept with the full mesh's very rays
    full_faces = len(part.faces)
    levels: dict[int, SimplificationLevel] = {}

    def level(faces: int) -> SimplificationLevel:
        t0 = time.perf_counter()
        coarse = simplify_part(part, faces)
        simplify_s = time.perf_counter() - t0
        build_s, cloud = _timed_sweep(coarse, setup, pose, repeats)
        lv = SimplificationLevel(len(coarse.faces), simplify_s, build_s,
                                 cloud.elapsed_s, len(cloud), cloud_deviation(full, cloud))
        levels[lv.faces] = lv
        if progress is not None:
            progress(f"  {part.name}: {lv.faces} faces, RMS {lv.deviation['rms_um']:.2f} um, "
                     f"coverage change {100 * lv.deviation['coverage_change']:.2f} %")
        return lv

    def ok(lv: SimplificationLevel) -> bool:
        return lv.passes(tolerance_um, max_coverage_change)

    faces = full_faces // 2
    while faces >= min_faces:
        if level(faces).faces > faces * 1.5:
            break  # the decimation cannot keep the topology below this: no coarser level
        faces //= 2
    passing = [f for f, lv in levels.items() if ok(lv)]
    lo = min(passing, default=full_faces)  # coarsest within tolerance so far
    coarser = [f for f in levels if f < lo]
    if coarser:
        hi = max(coarser)  # the next coarser level, outside tolerance
        for _ in range(refine):
            mid = int(round(np.sqrt(lo * hi)))
            if not hi < mid < lo:
                break
            lv = level(mid)
            if ok(lv) and lv.faces < lo:
                lo = lv.faces
            else:
                hi = mid
    ordered = sorted(levels.values(), key=lambda lv: -lv.faces)
    chosen = levels.get(lo)
    return {
        "part": part.name, "tolerance_um": tolerance_um,
        "max_coverage_change": max_coverage_change,
        "setup": {"step_mm": setup.step_mm, "rays_per_line": setup.rays_per_line},
        "full": {"faces": full_faces, "build_s": round(full_build, 6),
                 "sweep_s": round(full.elapsed_s, 6), "points": len(full)},
        "levels": [lv.to_dict() for lv in ordered],
        "chosen": chosen.to_dict() if chosen else None,
        "sweep_time_saved": (round(1.0 - chosen.sweep_s / full.elapsed_s, 4)
                             if chosen else 0.0),
    }


def _timed_sweep(part: Part, setup: VirtualSetup, pose, repeats: int):
    build_s = prepare(part)
    clouds = [predict_cloud(part, setup, pose=pose) for _ in range(max(1, repeats))]
    return build_s, min(clouds, key=lambda c: c.elapsed_s)
