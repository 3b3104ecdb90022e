"""Numba kernels of the virtual setup's sweep (`simulator.virtual_setup`).

They turn Embree's answers into points and visibility rays without Python loops or
temporary arrays, and release the GIL, so two threads keep both cores busy. All coordinates
are relative to the intersector's centre (float32 for Embree, float64 for the points).
"""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(nogil=True, cache=True)
def fan_rays(laser0, shift, steps, fan, origins, directions):
    """Fill the rays of consecutive fans: step ``s`` fires from ``laser0 + steps[s] * shift``.

    Parameters
    ----------
    laser0, shift : (3,) float64
        Light source at step 0, and its move per step, mm.
    steps : (S,) int64
    fan : (R, 3) float32
        Unit ray directions of one fan.
    origins, directions : (S * R, 3) float32
        Output, ray ``s * R + r``.
    """
    n_rays = fan.shape[0]
    for s in range(steps.shape[0]):
        ox = laser0[0] + steps[s] * shift[0]
        oy = laser0[1] + steps[s] * shift[1]
        oz = laser0[2] + steps[s] * shift[2]
        for r in range(n_rays):
            i = s * n_rays + r
            origins[i, 0] = ox
            origins[i, 1] = oy
            origins[i, 2] = oz
            directions[i, 0] = fan[r, 0]
            directions[i, 1] = fan[r, 1]
            directions[i, 2] = fan[r, 2]


@numba.njit(nogil=True, cache=True)
def lit_points(laser0, shift, steps, fan, face, normals, offsets, index, points, point_normals,
               point_faces, point_steps):
    """The points the light source lights: each first hit, placed exactly on its face's plane.

    Embree answers in float32; intersecting the same ray with the plane of the face it hit,
    in float64, puts the point on the surface to far below a micrometre.

    Parameters
    ----------
    laser0, shift : (3,) float64
    steps : (S,) int64
    fan : (R, 3) float64
        Unit ray directions.
    face : (S * R,) int32
        Face hit by each ray, -1 for a miss.
    normals : (F, 3) float64
    offsets : (F,) float64
        Face planes ``normals[f] @ x == offsets[f]``.
    index : (S * R,) int64
        Output: the ray of each point.
    points : (S * R, 3) float64
        Output.
    point_normals : (S * R, 3) float64
        Output: unit normals turned towards the light (the lit side).
    point_faces, point_steps : (S * R,) int64
        Output.

    Returns
    -------
    int
        Number of points written.
    """
    n_rays = fan.shape[0]
    k = 0
    for i in range(face.shape[0]):
        f = face[i]
        if f < 0:
            continue
        s = i // n_rays
        r = i - s * n_rays
        lx = laser0[0] + steps[s] * shift[0]
        ly = laser0[1] + steps[s] * shift[1]
        lz = laser0[2] + steps[s] * shift[2]
        nx, ny, nz = normals[f, 0], normals[f, 1], normals[f, 2]
        dn = nx * fan[r, 0] + ny * fan[r, 1] + nz * fan[r, 2]
        if dn == 0.0:  # a degenerate face, or a ray in the face's plane: lights nothing
            continue
        t = (offsets[f] - (nx * lx + ny * ly + nz * lz)) / dn
        if t <= 0.0:
            continue
        sign = -1.0 if dn > 0.0 else 1.0
        index[k] = i
        points[k, 0] = lx + t * fan[r, 0]
        points[k, 1] = ly + t * fan[r, 1]
        points[k, 2] = lz + t * fan[r, 2]
        point_normals[k, 0] = sign * nx
        point_normals[k, 1] = sign * ny
        point_normals[k, 2] = sign * nz
        point_faces[k] = f
        point_steps[k] = steps[s]
        k += 1
    return k


@numba.njit(nogil=True, cache=True)
def sight_rays(view0, shift, point_steps, points, normals, tol, origins, directions, reach,
               chosen):
    """Rays from a viewpoint to the points that face it, for Embree's occlusion query.

    A point faces the viewpoint when the viewpoint is on the lit side of its surface; the
    others are hidden without a ray. The ray stops `tol` before the point, so the surface
    the point lies on does not hide it.

    Parameters
    ----------
    view0, shift : (3,) float64
        Viewpoint at step 0 and its move per step, mm.
    point_steps : (K,) int64
    points : (K, 3) float64
    normals : (K, 3) float64
        Unit normals pointing to the lit side.
    tol : float
        mm.
    origins, directions : (K, 3) float32
        Output.
    reach : (K,) float32
        Output, mm.
    chosen : (K,) int64
        Output: the point of each ray.

    Returns
    -------
    int
        Number of rays written.
    """
    m = 0
    for j in range(points.shape[0]):
        vx = view0[0] + point_steps[j] * shift[0]
        vy = view0[1] + point_steps[j] * shift[1]
        vz = view0[2] + point_steps[j] * shift[2]
        dx = points[j, 0] - vx
        dy = points[j, 1] - vy
        dz = points[j, 2] - vz
        if normals[j, 0] * dx + normals[j, 1] * dy + normals[j, 2] * dz >= 0.0:
            continue  # the viewpoint is behind the lit surface
        length = np.sqrt(dx * dx + dy * dy + dz * dz)
        origins[m, 0] = vx
        origins[m, 1] = vy
        origins[m, 2] = vz
        directions[m, 0] = dx / length
        directions[m, 1] = dy / length
        directions[m, 2] = dz / length
        reach[m] = max(length - tol, 0.0)
        chosen[m] = j
        m += 1
    return m


@numba.njit(nogil=True, cache=True)
def keep_rows(mask, index, points, point_normals, point_faces, point_steps):
    """Compact the point arrays in place to the rows where `mask` holds; returns the count."""
    w = 0
    for j in range(mask.shape[0]):
        if not mask[j]:
            continue
        if w != j:
            index[w] = index[j]
            point_faces[w] = point_faces[j]
            point_steps[w] = point_steps[j]
            for c in range(3):
                points[w, c] = points[j, c]
                point_normals[w, c] = point_normals[j, c]
        w += 1
    return w
