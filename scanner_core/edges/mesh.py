"""Edges of a part's triangle mesh that its models are built from: the boundary of an open
mesh, and the outline seen from the sensor (pairs of adjacent faces, one turned toward it, the
other not). Used by the registration's edge model (``scanner_core.pose.models.EdgeModel``)
and by the edge kinds the registered model sets aside (``scanner_core.edges.kinds.ModelEdges``).

numpy only: the scan's edge kinds import it on every path that assembles a scan, ``flyscan
simulate``'s included, which stays free of scipy's and trimesh's import time.
"""
from __future__ import annotations

import numpy as np

__all__ = ["TOWARD_MIN", "outline_adjacency", "across_outline", "boundary_edges"]

#: A face is turned toward the sensor when its unit normal's component along the view
#: exceeds this: a wall side-on to it (0, give or take float noise: a float32 STL's walls
#: carry +-1e-7) is not.
TOWARD_MIN = 1e-6


def outline_adjacency(mesh, view) -> np.ndarray:
    """(A,) bool over ``mesh.face_adjacency`` (and its ``face_adjacency_edges``): whether the
    two faces lie on either side of the outline seen from `view`, (3,) in the mesh's frame:
    one turned toward it (beyond `TOWARD_MIN`), the other not."""
    return across_outline(mesh.face_normals, mesh.face_adjacency, view)


def across_outline(face_normals, adjacency, view) -> np.ndarray:
    """(A,) bool: whether the two faces of each pair lie on either side of the outline seen
    from `view`: one turned toward it (beyond `TOWARD_MIN`), the other not.

    Parameters
    ----------
    face_normals : (F, 3) float
        Unit face normals.
    adjacency : (A, 2) int
        Pairs of adjacent faces (``face_adjacency``).
    view : (3,) float
        Toward the sensor, in the normals' frame.
    """
    toward = np.asarray(face_normals, dtype=np.float64) @ np.asarray(
        view, dtype=np.float64) > TOWARD_MIN
    adjacency = np.asarray(adjacency)
    return toward[adjacency[:, 0]] != toward[adjacency[:, 1]]


def boundary_edges(faces: np.ndarray) -> np.ndarray:
    """(B, 2) vertex pairs used by one face only."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return unique[counts == 1]
