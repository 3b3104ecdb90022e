"""Triangulation: the stripe's pixels on the light plane, and the LED marker from the direct
and mirror views (paper section II), in {B}.

- :func:`triangulate_stripe`: each stripe pixel's ray meets the light plane (Eq. (2), then
  Eq. (3) back to {B}).
- :func:`triangulate_marker`: the point closest to the views' rays (each mirror view is the
  real camera reflected in its mirror, :class:`MarkerViews`), weighted so that every view
  counts in pixels; its compiled kernel (`_triangulate_views` over `_ray_solve`, numba,
  ``cache=True``) lives here with its helper and takes its constants as arguments, so that
  its cache goes stale with this file only. :func:`reproject_marker` is the way back;
  :func:`triangulate_rays` the same least squares for any bundle of rays.

The model these measure with (the camera, planes, mirrors) is in
``scanner_core.geometry.model``; ``scanner_core.geometry`` gathers both.

References
----------
.. [1] "Fast visual part inspection for bin picking", section II.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from scanner_core.geometry.model import (PARALLEL_COS, PinholeCamera, Plane, _as_points,
                                         apply_transform, unit)

__all__ = ["MAX_RAY_CONDITION", "triangulate_stripe", "triangulate_rays", "MarkerViews",
           "marker_views", "triangulate_marker", "reproject_marker"]

#: Rays this ill-conditioned (about 0.01 degrees apart at unit weight) leave the marker's
#: depth unobservable.
MAX_RAY_CONDITION = 1e8


def triangulate_stripe(pixels, camera: PinholeCamera, light_plane_c: Plane) -> np.ndarray:
    """Triangulate stripe pixels: pixel ray x light plane, returned in {B}.

    Parameters
    ----------
    pixels : (N, 2) float
        Sub-pixel stripe positions (u, v).
    camera : PinholeCamera
    light_plane_c : Plane
        The light plane in {C} (Eq. 2).

    Returns
    -------
    points_b : (N, 3) float64
        mm in {B}; NaN where the ray is parallel to the plane or meets it behind the camera.
    """
    d = camera.rays_camera(pixels)
    denom = d @ light_plane_c.normal
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(np.abs(denom) > PARALLEL_COS, light_plane_c.offset / denom, np.nan)
    s[~(s > 0)] = np.nan
    return camera.to_base(d * s[:, None])  # Eq. (2) then Eq. (3)


def triangulate_rays(origins, directions, weights=None) -> np.ndarray:
    """Least-squares point closest to a bundle of rays.

    Minimises ``sum_i w_i |(I - d_i d_i^T)(X - o_i)|^2``.

    Parameters
    ----------
    origins, directions : (V, 3) float
        V >= 2 rays; directions need not be unit.
    weights : (V,) float, optional

    Returns
    -------
    point : (3,) float64

    Raises
    ------
    ValueError
        Fewer than two rays, or rays (nearly) parallel: the depth is unobservable.
    """
    o = _as_points(origins, "origins")
    d = unit(_as_points(directions, "directions"))
    if len(o) < 2:
        raise ValueError(f"need at least two rays to triangulate, got {len(o)}")
    w = np.ones(len(o)) if weights is None else np.asarray(weights, dtype=np.float64)
    centre = o.mean(axis=0)  # centre the data before least squares
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    a = np.einsum("v,vij->ij", w, proj)
    b = np.einsum("v,vij,vj->i", w, proj, o - centre)
    if np.linalg.cond(a) > MAX_RAY_CONDITION:
        raise ValueError("rays are (nearly) parallel: the marker depth is unobservable")
    return np.linalg.solve(a, b) + centre


@dataclass(frozen=True)
class MarkerViews:
    """The direct view and each mirror view as cameras in {B}, for marker triangulation.

    Attributes
    ----------
    intrinsics : (4,) float64
        fx, fy, cx, cy of the (one) real camera, pixels.
    origins : (V, 3) float64
        Each view's centre in {B} (a mirror view's is the real camera reflected), mm.
    to_base : (V, 3, 3) float64
        Maps a pixel's ray in {C} (z = 1) to its direction in {B}.
    to_camera : (V, 3, 4) float64
        Maps a homogeneous point in {B} to the view's {C}: the reflected scene seen by the
        real camera.
    """

    intrinsics: np.ndarray
    origins: np.ndarray
    to_base: np.ndarray
    to_camera: np.ndarray


def marker_views(camera: PinholeCamera, mirrors) -> MarkerViews:
    """The views' matrices, computed once per calibration (``Calibration.marker_views``)."""
    r, o = camera.rotation, camera.origin
    reflections = [np.eye(4)] + [m.reflection for m in mirrors]
    origins = np.array([apply_transform(h, o) for h in reflections])
    to_base = np.array([h[:3, :3] @ r.T for h in reflections])
    to_camera = np.array([np.hstack([r @ h[:3, :3], (r @ (h[:3, 3] - o))[:, None]])
                          for h in reflections])
    return MarkerViews(np.array([camera.fx, camera.fy, camera.cx, camera.cy]), origins,
                       to_base, to_camera)


def triangulate_marker(pixels, camera: PinholeCamera, mirrors, *,
                       views: MarkerViews | None = None) -> tuple[np.ndarray, float]:
    """Multi-view triangulation of the LED marker from the direct and mirror views.

    Least squares over the views' rays (the point closest to them), then again with each
    ray weighted by 1/range^2, so that every view counts in pixels, not millimetres.

    Parameters
    ----------
    pixels : (1 + len(mirrors), 2) float
        Marker centroid per view (u, v); NaN rows for views where it was not seen.
    camera : PinholeCamera
    mirrors : sequence of Mirror
    views : MarkerViews, optional
        ``marker_views(camera, mirrors)``, when the caller keeps it.

    Returns
    -------
    position_b : (3,) float64
        mm in {B}; NaN when fewer than two views saw the marker.
    residual_px : float
        RMS reprojection error over the views used, pixels (of the ideal pinhole, after the
        lens's distortion is undone).

    Raises
    ------
    ValueError
        The views' rays are (nearly) parallel: the depth is unobservable.
    """
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    pixels = camera.ideal_pixels(pixels)  # the views below are ideal pinholes
    views = marker_views(camera, mirrors) if views is None else views
    if len(pixels) != len(views.origins):
        raise ValueError(f"`pixels` must be ({len(views.origins)}, 2), got {pixels.shape}")
    point, residual, status = _triangulate_views(pixels, views.intrinsics, views.origins,
                                                 views.to_base, views.to_camera, MAX_RAY_CONDITION)
    if status == 1:
        return np.full(3, np.nan), float("nan")
    if status == 2:
        raise ValueError("rays are (nearly) parallel: the marker depth is unobservable")
    return point, residual


@njit(cache=True, nogil=True)
def _ray_solve(origins, dirs, weights, n, out):
    """Weighted least-squares point closest to n rays (unit directions), centred first.
    Returns the Frobenius condition number of the normal matrix (inf when singular)."""
    centre = np.zeros(3)
    for k in range(n):
        centre += origins[k]
    centre /= n
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for k in range(n):
        w = weights[k]
        for i in range(3):
            for j in range(3):
                p = (1.0 if i == j else 0.0) - dirs[k, i] * dirs[k, j]
                a[i, j] += w * p
                b[i] += w * p * (origins[k, j] - centre[j])
    det = (a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1])
           - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
           + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]))
    if det == 0.0:
        return np.inf
    inv = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            i1, i2, j1, j2 = (j + 1) % 3, (j + 2) % 3, (i + 1) % 3, (i + 2) % 3
            inv[i, j] = (a[i1, j1] * a[i2, j2] - a[i1, j2] * a[i2, j1]) / det
    for i in range(3):
        out[i] = inv[i, 0] * b[0] + inv[i, 1] * b[1] + inv[i, 2] * b[2] + centre[i]
    return np.sqrt(np.sum(a * a)) * np.sqrt(np.sum(inv * inv))


@njit(cache=True, nogil=True)
def _triangulate_views(pixels, intrinsics, view_origins, to_base, to_camera, max_cond):
    """(point, residual_px, status): status 0 ok, 1 fewer than two views, 2 ill-conditioned."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    v = pixels.shape[0]
    origins = np.empty((v, 3))
    dirs = np.empty((v, 3))
    used = np.empty(v, np.int64)
    n = 0
    for k in range(v):
        u, w = pixels[k, 0], pixels[k, 1]
        if not (np.isfinite(u) and np.isfinite(w)):
            continue
        ray = np.array([(u - cx) / fx, (w - cy) / fy, 1.0])
        d = np.zeros(3)
        for i in range(3):
            for j in range(3):
                d[i] += to_base[k, i, j] * ray[j]
        dirs[n] = d / np.sqrt(np.sum(d * d))
        origins[n] = view_origins[k]
        used[n] = k
        n += 1
    point = np.full(3, np.nan)
    if n < 2:
        return point, np.nan, 1
    weights = np.ones(n)
    cond = _ray_solve(origins, dirs, weights, n, point)
    if not cond <= max_cond:
        return np.full(3, np.nan), np.nan, 2
    for k in range(n):
        diff = point - origins[k]
        weights[k] = 1.0 / np.sum(diff * diff)
    cond = _ray_solve(origins, dirs, weights, n, point)
    if not cond <= max_cond:
        return np.full(3, np.nan), np.nan, 2
    sq = 0.0
    for k in range(n):
        m = to_camera[used[k]]
        pc = np.zeros(3)
        for i in range(3):
            pc[i] = m[i, 0] * point[0] + m[i, 1] * point[1] + m[i, 2] * point[2] + m[i, 3]
        du = fx * pc[0] / pc[2] + cx - pixels[used[k], 0]
        dv = fy * pc[1] / pc[2] + cy - pixels[used[k], 1]
        sq += du * du + dv * dv
    return point, np.sqrt(sq / n), 0


def reproject_marker(points_b, camera: PinholeCamera, mirrors) -> np.ndarray:
    """Pixels (u, v) of {B} points in the direct view and each mirror view.

    Parameters
    ----------
    points_b : (3,) or (N, 3) float
        mm in {B}.

    Returns
    -------
    (1 + M, 2) float64 for one point, (N, 1 + M, 2) for N points; NaN behind the camera.
    """
    p = _as_points(points_b, "points_b")
    views = [camera.project(p)] + [camera.project(apply_transform(m.reflection, p)) for m in mirrors]
    out = np.stack(views, axis=1)
    return out[0] if np.ndim(points_b) == 1 else out
