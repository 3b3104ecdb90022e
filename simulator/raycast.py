"""Ray casting against one part with Embree, built once per part.

An ``Intersector`` holds the part's Embree scene (`simulator.embree.PacketScene`, queried
in packets of 16 rays) relative to the mesh's centre, so float32 keeps its precision where
the part is. Build one per part and keep it (`Part.intersector` does); batch the queries.
"""
from __future__ import annotations

from functools import cached_property
import numpy as np

from simulator.embree import PacketScene

#: Embree works in float32: about 3e-5 mm at 500 mm. A point counts as unoccluded when
#: nothing lies more than this in front of it (a blocker closer is the same surface).
SURFACE_TOL_MM = 0.01


class Intersector:
    """First-hit and occlusion queries on a mesh, in the mesh's own frame.

    Parameters
    ----------
    vertices : (V, 3) array_like of float
        The mesh's vertices, mm.
    faces : (F, 3) array_like of int
        Its triangles. Open meshes are fine; degenerate faces are never hit.
    """

    def __init__(self, vertices, faces):
        vertices = np.asarray(vertices, dtype=np.float64)
        self.centre = (vertices.min(axis=0) + vertices.max(axis=0)) / 2.0
        self._vertices = vertices - self.centre
        self._faces = np.asarray(faces, dtype=np.int64)
        self._scene = PacketScene(self._vertices, self._faces)

    @cached_property
    def face_planes(self) -> tuple[np.ndarray, np.ndarray]:
        """Each face's unit normal (F, 3) and offset (F,), float64, relative to `centre`.

        A point x on face f satisfies ``normal[f] @ x == offset[f]``. Degenerate faces get a
        zero normal and offset.
        """
        v, f = self._vertices, self._faces
        n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        length = np.linalg.norm(n, axis=1)
        n = np.divide(n, length[:, None], out=np.zeros_like(n), where=length[:, None] > 0)
        return n, np.einsum("ij,ij->i", n, v[f[:, 0]])

    def cast_faces(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """The face each prepared ray hits first: the fast path, without copies.

        Parameters
        ----------
        origins, directions : (N, 3) float32, C-contiguous
            Relative to `centre`; directions of unit length.

        Returns
        -------
        (N,) int32
            Face hit, -1 where the ray misses. (Recompute the hit point in float64 from the
            face's plane, `face_planes`.)

        Notes
        -----
        The rays are traced as coherent packets (`PacketScene.intersect`): give them in runs
        of neighbours, as a fan's are, or they are traced more slowly (with the same hits).
        """
        return self._scene.intersect(origins, directions, coherent=True)[1]

    def occluded(self, origins: np.ndarray, directions: np.ndarray,
                 reach: np.ndarray) -> np.ndarray:
        """True where something lies within `reach` along a prepared ray (the fast path).

        Parameters
        ----------
        origins, directions : (N, 3) float32, C-contiguous
            Relative to `centre`; directions of unit length.
        reach : (N,) float32
            mm.

        Returns
        -------
        (N,) bool

        Notes
        -----
        Traced as coherent packets, as `cast_faces`.
        """
        return self._scene.occluded(origins, directions, reach, coherent=True)

    def _prepare(self, origins, directions):
        o = np.ascontiguousarray(np.asarray(origins, np.float64) - self.centre, dtype=np.float32)
        d = np.asarray(directions, np.float64)
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        return o.reshape(-1, 3), np.ascontiguousarray(d, dtype=np.float32).reshape(-1, 3)

    def first_hit(self, origins, directions) -> tuple[np.ndarray, np.ndarray]:
        """Distance along each (normalised) ray to its first hit, and the face hit.

        Parameters
        ----------
        origins, directions : (N, 3) array_like
            mm, in the mesh's frame.

        Returns
        -------
        distance : (N,) float64
            mm; inf where the ray misses.
        face : (N,) int64
            Face index; -1 where the ray misses.
        """
        o, d = self._prepare(origins, directions)
        o, d = np.broadcast_arrays(o, d)
        o, d = np.ascontiguousarray(o), np.ascontiguousarray(d)
        distance, face = self._scene.intersect(o, d)
        return distance.astype(np.float64), face.astype(np.int64)

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
        return ~self._scene.occluded(o, d, reach)
