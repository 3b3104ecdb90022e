"""One candidate scan, simulated and judged: what a Dask task of ``flyscan plan`` runs.

A candidate (``planning.candidates.Candidate``) is scanned in the simulated reference cell
as ``flyscan scan --sim`` scans it (``simulator.session.run_simulated_scan``: frames
rendered, the scanner's own pipeline, edges and pose), at the plan's fixed noise seed and
with no misplacement, and judged by its pose's information (``scanner_core.pose.registration``: which
axes it fixes, their sigmas, its flags). The fraction of the surface the pass sees comes
from the fast ray-cast path (``simulator.virtual_setup.predict_cloud`` at the pass's profile
spacing: the faces a visible point lies on).

Why the rendered pass and not the ray-cast path for the pose: the predicted cloud has no
edge points, and the edges fix a part's in-plane motions; ``flyscan bench planning``
measures how often the ray-cast path's verdict agrees (docs/planning.md).

A worker keeps the parts it has built (their ray-casting scene and registration models) in
a small per-process cache keyed by the mesh's hash, so the candidates of one part share
them; every task limits BLAS to one thread (a worker per core).
"""
from __future__ import annotations

import resource
import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from planning.candidates import Candidate

__all__ = ["PartMesh", "PLAN_SEED", "PREVIEW_POINTS", "evaluate", "score", "warm_up"]

#: The image-noise seed of every planned pass (``flyscan scan``'s default seed).
PLAN_SEED = 0
#: Points of a candidate's cloud kept for its picture (a seeded even subsample).
PREVIEW_POINTS = 2000
# Parts a worker keeps built, most recently used first: the candidates of a part come
# together, and a large part's scene and models take tens of megabytes.
_KEEP_PARTS = 4
_parts: OrderedDict = OrderedDict()


@dataclass(frozen=True)
class PartMesh:
    """A catalogue part as it travels to the workers (scattered once per part).

    Attributes
    ----------
    name : str
    vertices : (V, 3) float64
        mm, in {P}.
    faces : (F, 3) int64
    units : str
        The unit of its file.
    source : str
        Its file.
    digest : str
        SHA-256 of the file (the cache's key for the part).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    units: str
    source: str
    digest: str


def evaluate(mesh: PartMesh, candidate: Candidate, *, preview: bool = True) -> dict:
    """Scan one candidate and judge it.

    Returns
    -------
    dict
        ``status`` ("done", or "failed" with ``reason``), ``frames``, ``points``,
        ``edge_points``, ``edge_profiles`` (profiles with an edge point: the edges crossed),
        ``surface_seen`` (area fraction of the part's faces the pass sees), ``pose``
        (``observable``, ``act``, ``act_reasons``, ``free_axes`` labels, ``std`` per axis in
        mm and degrees with None on a free axis, ``flags``), ``cost`` (``wall_s``,
        ``cpu_s``, ``rss_mb``: the worker's peak resident memory), and, with `preview`,
        ``preview`` (K, 3) float32 and ``preview_edges`` (L, 3) float32 in {T}, mm.
    """
    from threadpoolctl import threadpool_limits

    t0, c0 = time.perf_counter(), time.process_time()
    with threadpool_limits(limits=1, user_api="blas"):
        result = _evaluate(mesh, candidate, preview)
    result["cost"] = {"wall_s": round(time.perf_counter() - t0, 3),
                      "cpu_s": round(time.process_time() - c0, 3),
                      "rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                                      1)}
    return result


def warm_up() -> float:
    """Load every kernel a candidate's scan uses (numba's cache) by scanning a small box once;
    the seconds it took. A process's first scan otherwise pays it (1-2 s)."""
    import trimesh

    from planning.candidates import candidates
    from scanner_core.cad import part_from_mesh

    t0 = time.perf_counter()
    part = part_from_mesh(trimesh.creation.box((30.0, 20.0, 10.0)), name="warm-up")
    mesh = PartMesh(name=part.name, vertices=np.asarray(part.vertices),
                    faces=np.asarray(part.faces), units="mm", source="procedural:box",
                    digest="warm-up")
    evaluate(mesh, candidates(part, presets=("fast",), resting=0)[0][0], preview=False)
    _parts.pop("warm-up", None)
    return time.perf_counter() - t0


def score(result: dict, tolerance_mm: float, tolerance_deg: float) -> float:
    """A done candidate's largest sigma against the act tolerance: max over the axes of
    3 sigma / tolerance (mm for translations, degrees for rotations); inf when an axis is
    free or the pass failed. Below 1: every axis's 3 sigma within the tolerance."""
    pose = result.get("pose") or {}
    std = pose.get("std")
    if result.get("status") != "done" or not std:
        return float("inf")
    ratios = []
    for axis, value in std.items():
        if value is None:
            return float("inf")
        ratios.append(3.0 * value / (tolerance_mm if axis.endswith("_mm") else tolerance_deg))
    return float(max(ratios))


def _evaluate(mesh: PartMesh, candidate: Candidate, preview: bool) -> dict:
    from simulator.cell import PASS_PRESETS, load_cell
    from simulator.session import run_simulated_scan

    part = _part(mesh).with_grasp(candidate.nominal)
    preset = PASS_PRESETS[candidate.preset]
    cell = load_cell().with_pass(speed_mm_s=preset.speed_mm_s, fps=preset.fps)
    out = {"speed_mm_s": preset.speed_mm_s, "fps": preset.fps,
           "surface_seen": _surface_seen(part, cell)}
    scan, report = run_simulated_scan(part, cell, seed=PLAN_SEED, evaluate=False)
    out.update(frames=int(report["frames"]), points=int(report["points"]),
               edge_points=int(report["edge_points"]),
               edge_profiles=int(len(np.unique(scan.edge_frame_ids))))
    if report.get("state") == "failed":
        return {**out, "status": "failed", "reason": f"the pass failed: {report['reason']}"}
    pose = report.get("pose")
    if not pose or "refused" in pose:
        why = pose["refused"] if pose else "no pose"
        return {**out, "status": "failed", "reason": f"no pose: {why}"}
    out["status"] = "done"
    out["pose"] = {"observable": bool(pose["observable"]), "act": bool(pose["act"]),
                   "act_reasons": list(pose["act_reasons"]),
                   "free_axes": [f["label"] for f in pose["free_axes"]],
                   "std": pose["std"], "flags": list(pose["flags"])}
    if preview:
        out["preview"] = _subsample(scan.cloud, PREVIEW_POINTS)
        out["preview_edges"] = _subsample(scan.edges, PREVIEW_POINTS // 2)
    return out


def _part(mesh: PartMesh):
    """The simulator's part of `mesh`, built once per worker process (nominal grasp: the
    centred one; candidates take theirs with ``Part.with_grasp``)."""
    from simulator.parts import Part

    part = _parts.get(mesh.digest)
    if part is None:
        part = Part(name=mesh.name, vertices=mesh.vertices, faces=mesh.faces,
                    source=mesh.source, units=mesh.units, grasp=np.eye(4))
        _parts[mesh.digest] = part
        while len(_parts) > _KEEP_PARTS:
            _parts.popitem(last=False)
    _parts.move_to_end(mesh.digest)
    return part


def _surface_seen(part, cell) -> float:
    """Area fraction of the part's faces on which the pass's sheet lights a point the camera
    sees (``predict_cloud`` at the pass's profile spacing, one thread)."""
    from simulator.virtual_setup import SetupError, predict_cloud, reference_setup

    spacing = cell.pass_profile.speed_mm_s / cell.pass_profile.fps
    try:
        cloud = predict_cloud(part, reference_setup(cell, step_mm=spacing), pose=part.grasp,
                              threads=1)
    except SetupError:
        return 0.0
    v, f = part.vertices, part.faces
    areas = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]),
                                 axis=1)
    seen = np.unique(cloud.face) if len(cloud) else np.zeros(0, np.int64)
    return round(float(areas[seen].sum() / areas.sum()), 4)


def _subsample(points, count: int) -> np.ndarray:
    """(<= count, 3) float32: an even, seeded subsample of (N, 3) `points`."""
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    if len(points) <= count:
        return points
    rng = np.random.default_rng(PLAN_SEED)
    return points[np.sort(rng.choice(len(points), count, replace=False))]
