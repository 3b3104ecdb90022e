"""Scan accuracy against the ground truth the simulator knows.

Distances are to the true CAD surface (exact closest points, trimesh), after mapping the
cloud from {T} back to {P} through the true grasp. Provenance: every cloud point must lie
near a stripe sample that the renderer found lit by the laser and seen by the camera in the
same frame; a point that does not came from a surface the camera cannot see (or from
nothing at all).
"""
from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from scanner_core.geometry import apply_transform, base_to_tcp

#: Closest-point queries cost about 0.1 ms each; larger clouds are subsampled (seeded).
MAX_EVAL_POINTS = 30000
#: A cloud point farther than this from every visible stripe sample of its frame has no
#: visible source (the stripe error is tens of micrometres).
PROVENANCE_TOL_MM = 0.2
#: Separates frames in the provenance search (far larger than any part).
FRAME_SPACING_MM = 1.0e5


def cloud_accuracy(cloud_t, frame_ids, mesh: trimesh.Trimesh, true_grasp: np.ndarray,
                   truths: dict | None = None, gripper_rotation_b=None, *,
                   max_points: int = MAX_EVAL_POINTS, seed: int = 0) -> dict:
    """Distances from cloud points to the true surface, and each point's provenance.

    Parameters
    ----------
    cloud_t : (N, 3) float
        Cloud in {T}, mm.
    frame_ids : (N,) int
    mesh : trimesh.Trimesh
        The part in {P}, mm.
    true_grasp : (4, 4) float64
        True ^T X_P.
    truths : dict frame_id -> simulator.render.FrameTruth, optional
        With ``gripper_rotation_b``: enables the provenance check.

    Returns
    -------
    dict
        ``points_evaluated``, ``rms_um``, ``p99_um``, ``max_um``, ``mean_signed_um`` (along
        the surface normal: a bias check), and with truths ``unmatched_points``.
    """
    cloud_t = np.asarray(cloud_t, dtype=np.float64)
    n = len(cloud_t)
    if n == 0:
        return {"points_evaluated": 0}
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(n, max_points, replace=False)) if n > max_points else np.arange(n)
    points_p = apply_transform(np.linalg.inv(true_grasp), cloud_t[pick])
    closest, distance, face = trimesh.proximity.closest_point(mesh, points_p)
    signed = np.einsum("ij,ij->i", points_p - closest, mesh.face_normals[face])
    out = {
        "points_evaluated": int(len(pick)),
        "rms_um": float(np.sqrt(np.mean(distance**2)) * 1e3),
        "p99_um": float(np.percentile(distance, 99) * 1e3),
        "max_um": float(distance.max() * 1e3),
        "mean_signed_um": float(signed.mean() * 1e3),
    }
    if truths is not None:
        out["unmatched_points"] = int(unmatched(cloud_t, frame_ids, truths, gripper_rotation_b).sum())
    return out


def unmatched(cloud_t, frame_ids, truths: dict, gripper_rotation_b) -> np.ndarray:
    """(N,) bool: points with no lit-and-seen stripe sample within PROVENANCE_TOL_MM in
    their own frame."""
    r = np.asarray(gripper_rotation_b, dtype=np.float64)
    ref, ref_ids = [], []
    for fid in np.unique(frame_ids):
        truth = truths[int(fid)]
        ref.append(base_to_tcp(truth.stripe_points_b, truth.tcp_b, r))
        ref_ids.append(np.full(len(truth.stripe_points_b), fid))
    ref = np.concatenate(ref) if ref else np.zeros((0, 3))
    if len(ref) == 0:
        return np.ones(len(cloud_t), dtype=bool)
    ref_ids = np.concatenate(ref_ids).astype(np.float64)
    tree = cKDTree(np.column_stack([ref, ref_ids * FRAME_SPACING_MM]))
    query = np.column_stack([cloud_t, np.asarray(frame_ids, np.float64) * FRAME_SPACING_MM])
    dist, _ = tree.query(query, distance_upper_bound=PROVENANCE_TOL_MM)
    return ~np.isfinite(dist)
