"""Scan accuracy against the ground truth the simulator knows.

Distances are to the true CAD surface (exact closest points, trimesh), after mapping the
cloud from {T} back to {P} through the true grasp. "Seen" checks that the surface point
nearest to each cloud point was visible to the camera at that point's frame: no point may
come from a surface the camera cannot see.
"""
from __future__ import annotations

import numpy as np
import trimesh

from scanner_core.geometry import apply_transform

#: Closest-point queries cost about 0.1 ms each; larger clouds are subsampled (seeded).
MAX_EVAL_POINTS = 30000


def cloud_accuracy(cloud_t, frame_ids, mesh: trimesh.Trimesh, true_grasp: np.ndarray,
                   part_poses_b: dict[int, np.ndarray] | None = None, camera_origin_b=None,
                   intersector=None, *, max_points: int = MAX_EVAL_POINTS, seed: int = 0) -> dict:
    """Distances from cloud points to the true surface, and whether each was visible.

    Parameters
    ----------
    cloud_t : (N, 3) float
        Cloud in {T}, mm.
    frame_ids : (N,) int
    mesh : trimesh.Trimesh
        The part in {P}, mm.
    true_grasp : (4, 4) float64
        True ^T X_P.
    part_poses_b : dict frame_id -> (4, 4), optional
        True ^B X_P per frame, for the visibility check (with ``camera_origin_b`` and
        ``intersector``).

    Returns
    -------
    dict
        ``points_evaluated``, ``rms_um``, ``p99_um``, ``max_um``, ``mean_um`` (signed along the
        surface normal, a bias check), and ``unseen_points`` when the visibility check ran.
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
    if part_poses_b is not None:
        ids = np.asarray(frame_ids)[pick]
        seen = np.ones(len(pick), dtype=bool)
        for fid in np.unique(ids):
            sel = ids == fid
            inv = np.linalg.inv(part_poses_b[int(fid)])
            cam_p = apply_transform(inv, np.asarray(camera_origin_b, dtype=np.float64))
            seen[sel] = intersector.visible(cam_p, closest[sel])
        out["unseen_points"] = int((~seen).sum())
    return out
