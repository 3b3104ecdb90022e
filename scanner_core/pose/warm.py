"""The registration's numba kernels compiled before the first pose (`warm_up_pose`).

The normals' neighbour search and planes (``scanner_core.normals``), the fine stage's rows
and crease test, the search's agreement test (``scanner_core.pose.rows``), the lookup table's
and the grid's queries and `NearestMemo`'s bookkeeping (``scanner_core.pose.nearest_table``)
compile on their first call: some 3.7 s on a fresh install (an empty numba cache), some 150 ms loading
them from the cache, which the first pass's pose would otherwise wait for. The service warms
them up with the frame kernels (``scanner_core.pipeline.warm_up``), before it streams.
"""
from __future__ import annotations

import time

import numpy as np

__all__ = ["warm_up_pose"]


def warm_up_pose() -> float:
    """Register a small box (20 x 12 x 6 mm, its top and sides seen, its top outline as edge
    points, half of them steps) from a start 0.5 mm and 2 degrees off, and refine and score
    two candidates at once as the search does: every kernel of the registration runs, with
    the argument types a pose gives it. Returns the time it took, ms."""
    import trimesh
    from scipy.spatial.transform import Rotation

    from scanner_core.normals import estimate_normals
    from scanner_core.pose.registration import EdgeModel, PoseParams, SurfaceModel, register
    from scanner_core.pose.fine import _Terms
    from scanner_core.pose.quick import _quick_fits
    from scanner_core.pose.search import _agreements

    t0 = time.perf_counter()
    mesh = trimesh.creation.box((20.0, 12.0, 6.0))
    surface_model = SurfaceModel.from_mesh(mesh, spacing_mm=0.5)
    edge_model = EdgeModel.from_mesh(mesh)
    seen = surface_model.normals[:, 2] > -0.5
    points, normals = surface_model.points[seen], surface_model.normals[seen]
    edges = edge_model.points[edge_model.points[:, 2] > 2.9]
    steps = np.where(np.arange(len(edges)) % 2 == 0, 0.0, 1.0)
    nominal = np.eye(4)
    nominal[:3, :3] = Rotation.from_rotvec(np.radians([0.0, 0.0, 2.0])).as_matrix()
    nominal[:3, 3] = [0.5, 0.0, 0.0]
    params = PoseParams(search_points=200, max_points=800)
    estimate_normals(points, sensors=np.array([0.0, 0.0, 100.0]),
                     frame_ids=np.arange(len(points)) // 20, index=np.arange(0, len(points), 2))
    register(points, normals, surface_model, nominal, frame_ids=np.arange(len(points)) // 20,
             edges_t=edges, edge_frame_ids=np.arange(len(edges)) // 4, edge_model=edge_model,
             edge_steps_mm=steps, params=params)
    surface = _Terms(points, normals, np.arange(len(points)), surface_model, 0.5)
    edge_terms = _Terms(edges, None, np.arange(len(edges)), edge_model, steps_mm=steps)
    starts = np.stack([nominal, np.eye(4)])
    _quick_fits(surface.rough(), edge_terms.rough(), starts, params, iterations=2, gate_mm=10.0)
    _agreements(surface, edge_terms, starts, 0.1, 0.25)
    return (time.perf_counter() - t0) * 1e3
