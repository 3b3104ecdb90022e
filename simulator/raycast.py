"""Ray casting against one part with Embree (embreex), built once per part.

Most of the first call's cost is embreex copying the mesh (NOTES.md), so an ``Intersector``
is built once per part and kept; queries are batched (one call per fan of rays).
"""
from __future__ import annotations

import numpy as np
import trimesh

try:  # optional at import, required at use: a clear error where it is needed
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh
except ImportError:  # pragma: no cover - embreex is a declared dependency
    rtcore_scene = None

#: Embree works in float32: about 3e-5 mm at 500 mm. A point counts as unoccluded when
#: nothing lies more than this in front of it (a blocker closer is the same surface).
SURFACE_TOL_MM = 0.01


class Intersector:
    """First-hit and occlusion queries on a mesh, in the mesh's own frame.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Vertices in mm. Open meshes are fine.
    """

    def __init__(self, mesh: trimesh.Trimesh):
        if rtcore_scene is None:
            raise ImportError("ray casting needs embreex: pip install embreex")
        # Work relative to the mesh's centre to keep float32 precision where the part is.
        self.centre = np.asarray(mesh.bounds.mean(axis=0), dtype=np.float64)
        self._scene = rtcore_scene.EmbreeScene()
        TriangleMesh(self._scene, (mesh.vertices - self.centre).astype(np.float32),
                     np.ascontiguousarray(mesh.faces, dtype=np.int32))

    def _prepare(self, origins, directions):
        o = np.ascontiguousarray(np.asarray(origins, np.float64) - self.centre, dtype=np.float32)
        d = np.asarray(directions, np.float64)
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        return o.reshape(-1, 3), np.ascontiguousarray(d, dtype=np.float32).reshape(-1, 3)

    def first_hit(self, origins, directions) -> tuple[np.ndarray, np.ndarray]:
        """Distance along each (normalised) ray to its first hit, and the face hit.

        Returns
        -------
        distance : (N,) float64
            mm; inf where the ray misses.
        face : (N,) int64
            Face index; -1 where the ray misses.
        """
        o, d = self._prepare(origins, directions)
        if len(o) == 0:
            return np.zeros(0), np.zeros(0, dtype=np.int64)
        out = self._scene.run(o, d, output=1)
        face = out["primID"].astype(np.int64)
        dist = np.where(face >= 0, out["tfar"].astype(np.float64), np.inf)
        return dist, face

    def visible(self, origins, targets) -> np.ndarray:
        """True where nothing on the mesh blocks the segment from origin to target
        (up to SURFACE_TOL_MM before the target). (N,) bool."""
        origins = np.asarray(origins, np.float64).reshape(-1, 3)
        targets = np.asarray(targets, np.float64).reshape(-1, 3)
        if len(targets) == 0:
            return np.zeros(0, dtype=bool)
        delta = targets - origins
        length = np.linalg.norm(delta, axis=1)
        o, d = self._prepare(np.broadcast_to(origins, targets.shape), delta)
        reach = np.maximum(length - SURFACE_TOL_MM, 0.0).astype(np.float32)
        hit = self._scene.run(o, d, dists=reach, query="OCCLUDED")
        return np.asarray(hit) < 0
