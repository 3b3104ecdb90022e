"""Numba kernels of the virtual setup's sweep (`simulator.virtual_setup`).

They turn Embree's answers into points and visibility rays without Python loops or
temporary arrays, and release the GIL, so two threads keep both cores busy. All coordinates
are relative to the intersector's centre (float32 for Embree, float64 for the points).

A sweep keeps only each point's ray and face while it runs (8 bytes a point); the point, its
normal and its PLY row are computed from them, exactly as the sweep computed them, when they
are asked for (`emit_points`, `emit_rows`): a sweep of millions of points never holds its
float64 arrays unless someone reads them.
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
def _on_face(laser0, shift, step, fan, r, normals, offsets, f):
    """Ray ``r`` of step `step` meets face `f`'s plane: (x, y, z, dn, t); ``dn = normal . ray``.

    Embree answers in float32; intersecting the same ray with the plane of the face it hit,
    in float64, puts the point on the surface to far below a micrometre. The one place this
    is computed, so a point recomputed later is the very point the sweep tested.
    """
    lx = laser0[0] + step * shift[0]
    ly = laser0[1] + step * shift[1]
    lz = laser0[2] + step * shift[2]
    dn = normals[f, 0] * fan[r, 0] + normals[f, 1] * fan[r, 1] + normals[f, 2] * fan[r, 2]
    if dn == 0.0:
        return lx, ly, lz, dn, 0.0
    t = (offsets[f] - (normals[f, 0] * lx + normals[f, 1] * ly + normals[f, 2] * lz)) / dn
    return lx + t * fan[r, 0], ly + t * fan[r, 1], lz + t * fan[r, 2], dn, t


@numba.njit(nogil=True, cache=True)
def lit_points(laser0, shift, steps, fan, face, normals, offsets, index, points, point_normals,
               point_faces, point_steps):
    """The points the light source lights: each first hit, placed exactly on its face's plane.

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
        x, y, z, dn, t = _on_face(laser0, shift, steps[s], fan, r, normals, offsets, f)
        # A degenerate face, or a ray in the face's plane, lights nothing.
        if dn == 0.0 or t <= 0.0:
            continue
        sign = -1.0 if dn > 0.0 else 1.0
        index[k] = i
        points[k, 0] = x
        points[k, 1] = y
        points[k, 2] = z
        point_normals[k, 0] = sign * normals[f, 0]
        point_normals[k, 1] = sign * normals[f, 1]
        point_normals[k, 2] = sign * normals[f, 2]
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


@numba.njit(nogil=True, cache=True)
def _kept_point(laser0, shift, first_step, fan, ray_index, f, normals, offsets, rot, trans):
    """One kept point from its ray number and face, in the setup frame: its step and ray in
    the fan, the point, and the face normal turned toward the light source."""
    n_rays = fan.shape[0]
    s = ray_index // n_rays
    r = ray_index - s * n_rays
    x, y, z, dn, _ = _on_face(laser0, shift, first_step + s, fan, r, normals, offsets, f)
    sign = -1.0 if dn > 0.0 else 1.0
    px = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z + trans[0]
    py = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z + trans[1]
    pz = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z + trans[2]
    nx = sign * (rot[0, 0] * normals[f, 0] + rot[0, 1] * normals[f, 1] + rot[0, 2] * normals[f, 2])
    ny = sign * (rot[1, 0] * normals[f, 0] + rot[1, 1] * normals[f, 1] + rot[1, 2] * normals[f, 2])
    nz = sign * (rot[2, 0] * normals[f, 0] + rot[2, 1] * normals[f, 1] + rot[2, 2] * normals[f, 2])
    return first_step + s, r, px, py, pz, nx, ny, nz


@numba.njit(nogil=True, cache=True)
def emit_points(laser0, shift, first_step, fan, ray, face, normals, offsets, rot, trans,
                out_points, out_normals, out_step, out_ray, out_face, start):
    """Write kept points, from their rays and faces, into the cloud's arrays, in the setup frame.

    Parameters
    ----------
    laser0, shift : (3,) float64
    first_step : int
        Step of ray 0 of `ray`'s numbering.
    fan : (R, 3) float64
    ray : (K,) int32
        ``(step - first_step) * R + r`` of each point.
    face : (K,) int32
    normals, offsets : (F, 3), (F,) float64
        Face planes.
    rot : (3, 3) float64
    trans : (3,) float64
        The part's frame, relative to the intersector's centre, to the setup frame:
        ``x_setup = rot @ x + trans``.
    out_points, out_normals : (N, 3) float64
    out_step, out_ray : (N,) int32
    out_face : (N,) int64
        Output, rows ``start`` to ``start + K``.
    """
    for j in range(ray.shape[0]):
        step, r, px, py, pz, nx, ny, nz = _kept_point(laser0, shift, first_step, fan, ray[j],
                                                      face[j], normals, offsets, rot, trans)
        k = start + j
        out_points[k, 0], out_points[k, 1], out_points[k, 2] = px, py, pz
        out_normals[k, 0], out_normals[k, 1], out_normals[k, 2] = nx, ny, nz
        out_step[k] = step
        out_ray[k] = r
        out_face[k] = face[j]


@numba.njit(nogil=True, cache=True)
def emit_rows(laser0, shift, first_step, fan, ray, face, normals, offsets, rot, trans, rows,
              start):
    """As `emit_points`, into PLY rows: float32 x, y, z, int32 step and ray, float32 normal.

    `rows` is a record array with the fields ``x, y, z, step, ray, nx, ny, nz`` (a view of
    the file's vertex table, which may hold further fields); rows ``start`` to
    ``start + K`` are written.
    """
    for j in range(ray.shape[0]):
        step, r, px, py, pz, nx, ny, nz = _kept_point(laser0, shift, first_step, fan, ray[j],
                                                      face[j], normals, offsets, rot, trans)
        row = rows[start + j]
        row.x, row.y, row.z = px, py, pz
        row.step = step
        row.ray = r
        row.nx, row.ny, row.nz = nx, ny, nz
