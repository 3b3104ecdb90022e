"""Camera, light plane and mirror geometry: the paper's Eq. (1)-(3) and triangulation.

Conventions
-----------
- Pixel coordinates ``(u, v)`` = (column, row), pixel centres at integers.
- {C}: x along image columns, y along image rows, z the optical axis (pinhole, no distortion).
- Eq. (1): ``P_C = T (P_B - O)``; Eq. (3): ``P_B = T^-1 (P_C + T O) = T^T P_C + O``.
- A plane is ``n . x = d`` with a unit normal ``n``; Eq. (2) writes the light plane as
  ``n . (P_C - P_0) = 0``, so ``d = n . P_0``.

References
----------
.. [1] "Fast visual part inspection for bin picking", section II (../shared/paper.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Rays nearly parallel to a plane (|cos| below this) have no usable intersection.
PARALLEL_COS = 1e-9
#: Rays this ill-conditioned (about 0.01 degrees apart at unit weight) leave the marker's
#: depth unobservable.
MAX_RAY_CONDITION = 1e8


def _as_points(points, name: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == 3:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"`{name}` must be (N, 3), got {np.shape(points)}")
    return arr


def unit(vectors: np.ndarray) -> np.ndarray:
    """Normalise along the last axis (no BLAS call: see NOTES.md on OpenBLAS spinning)."""
    vectors = np.asarray(vectors, dtype=np.float64)
    return vectors / np.sqrt(np.einsum("...i,...i->...", vectors, vectors))[..., None]


def reflection_matrix(normal: np.ndarray, offset: float) -> np.ndarray:
    """4x4 homogeneous reflection in the plane ``normal . x = offset``.

    ``x' = (I - 2 n n^T) x + 2 d n``: a mirror view is the real camera looking at the
    reflected scene.
    """
    n = unit(np.asarray(normal, dtype=np.float64))
    h = np.eye(4)
    h[:3, :3] -= 2.0 * np.outer(n, n)
    h[:3, 3] = 2.0 * offset * n
    return h


def check_rigid(matrix, tol: float = 1e-6) -> np.ndarray:
    """The matrix as a (4, 4) float64 rigid transform (rotation and translation).

    `tol` (1e-6) lies well above the round-off of composed rotations and far below any real
    error. Raises ValueError naming what is wrong.
    """
    m = np.array(matrix, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ValueError(f"must be a finite (4, 4) matrix, got shape {m.shape}")
    r = m[:3, :3]
    if (not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0]) or not np.allclose(r @ r.T, np.eye(3), atol=tol)
            or np.linalg.det(r) < 0):
        raise ValueError("must be a rigid transform (a rotation and a translation)")
    return m


def apply_transform(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 homogeneous transform to (N, 3) points."""
    points = np.asarray(points, dtype=np.float64)
    return np.einsum("ij,...j->...i", matrix[:3, :3], points) + matrix[:3, 3]


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole camera posed in {B}.

    Attributes
    ----------
    fx, fy, cx, cy : float
        Intrinsics, pixels.
    width, height : int
        Image size, pixels.
    rotation : (3, 3) float64
        The paper's transfer matrix T: rows are the {C} axes expressed in {B}.
    origin : (3,) float64
        The paper's O: the camera centre in {B}, mm.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    rotation: np.ndarray
    origin: np.ndarray

    def to_camera(self, points_b) -> np.ndarray:
        """Eq. (1): {B} -> {C}. (N, 3) mm -> (N, 3) mm."""
        p = _as_points(points_b, "points_b")
        return (p - self.origin) @ self.rotation.T

    def to_base(self, points_c) -> np.ndarray:
        """Eq. (3): {C} -> {B}. (N, 3) mm -> (N, 3) mm."""
        p = _as_points(points_c, "points_c")
        return p @ self.rotation + self.origin

    def project_camera(self, points_c) -> np.ndarray:
        """(N, 3) points in {C} -> (N, 2) pixels (u, v); NaN behind the camera."""
        p = _as_points(points_c, "points_c")
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(p[:, 2] > 0, p[:, 2], np.nan)
            return np.stack([self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy], 1)

    def project(self, points_b) -> np.ndarray:
        """(N, 3) points in {B} -> (N, 2) pixels (u, v); NaN behind the camera."""
        return self.project_camera(self.to_camera(points_b))

    def rays_camera(self, pixels) -> np.ndarray:
        """(N, 2) pixels (u, v) -> (N, 3) ray directions in {C} with z = 1 (not unit)."""
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        return np.stack(
            [(px[:, 0] - self.cx) / self.fx, (px[:, 1] - self.cy) / self.fy, np.ones(len(px))], 1
        )

    def rays(self, pixels) -> np.ndarray:
        """(N, 2) pixels -> (N, 3) unit ray directions in {B}."""
        return unit(self.rays_camera(pixels) @ self.rotation)


@dataclass(frozen=True)
class Plane:
    """A plane ``normal . x = offset`` (unit normal)."""

    normal: np.ndarray
    offset: float

    @classmethod
    def from_point_normal(cls, point, normal) -> "Plane":
        n = unit(np.asarray(normal, dtype=np.float64))
        return cls(n, float(n @ np.asarray(point, dtype=np.float64)))

    def signed_distance(self, points) -> np.ndarray:
        return _as_points(points, "points") @ self.normal - self.offset

    def intersect(self, origins, directions) -> np.ndarray:
        """Ray-plane intersections, (N, 3); NaN rows for rays parallel to the plane or
        meeting it behind their origin."""
        o = _as_points(origins, "origins")
        d = _as_points(directions, "directions")
        denom = d @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(np.abs(denom) > PARALLEL_COS, (self.offset - o @ self.normal) / denom, np.nan)
        s[s < 0] = np.nan
        return o + s[:, None] * d

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> "Plane":
        """The plane after ``x -> R x + t``."""
        n = rotation @ self.normal
        return Plane(n, float(self.offset + n @ translation))


@dataclass(frozen=True)
class Mirror:
    """A plane mirror in {B} whose view is clipped to a strip of image columns.

    Attributes
    ----------
    plane : Plane
        Mirror plane in {B}, mm.
    columns : (int, int)
        Image columns [c0, c1) where this mirror's view lies.
    """

    plane: Plane
    columns: tuple[int, int]

    @property
    def reflection(self) -> np.ndarray:
        return reflection_matrix(self.plane.normal, self.plane.offset)


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


def view_rays(pixels: np.ndarray, camera: PinholeCamera, mirrors) -> tuple[np.ndarray, np.ndarray]:
    """Rays in {B} of the marker seen in the direct view and in each mirror view.

    Parameters
    ----------
    pixels : (1 + len(mirrors), 2) float
        Marker pixel in the direct view, then in each mirror view.

    Returns
    -------
    origins, directions : (V, 3) float64
        A mirror view's ray is the real camera's ray reflected in the mirror: it starts at
        the virtual camera (the real one reflected) and points into the scene.
    """
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    dirs = camera.rays(pixels)
    origins = np.repeat(camera.origin[None, :], len(pixels), axis=0)
    for k, mirror in enumerate(mirrors, start=1):
        h = mirror.reflection
        origins[k] = apply_transform(h, camera.origin)
        dirs[k] = h[:3, :3] @ dirs[k]
    return origins, dirs


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


def triangulate_marker(pixels, camera: PinholeCamera, mirrors) -> tuple[np.ndarray, float]:
    """Multi-view triangulation of the LED marker from the direct and mirror views.

    Parameters
    ----------
    pixels : (1 + len(mirrors), 2) float
        Marker centroid per view (u, v); NaN rows for views where it was not seen.

    Returns
    -------
    position_b : (3,) float64
        mm in {B}; NaN when fewer than two views saw the marker.
    residual_px : float
        RMS reprojection error over the views used, pixels.
    """
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    seen = np.isfinite(pixels).all(axis=1)
    if seen.sum() < 2:
        return np.full(3, np.nan), float("nan")
    origins, dirs = view_rays(pixels, camera, mirrors)
    origins, dirs = origins[seen], dirs[seen]
    point = triangulate_rays(origins, dirs)
    # Weight each ray by 1/range^2 so that every view counts in pixels, not millimetres.
    ranges = np.linalg.norm(point - origins, axis=1)
    point = triangulate_rays(origins, dirs, weights=1.0 / ranges**2)
    reproj = reproject_marker(point, camera, mirrors)[seen]
    residual = float(np.sqrt(np.mean(np.sum((reproj - pixels[seen]) ** 2, axis=1))))
    return point, residual


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


def base_to_tcp(points_b, tcp_b, rotation_b) -> np.ndarray:
    """{B} -> {T}: ``X_T = R^T (X_B - p)`` for a TCP at ``p`` with rotation ``R`` in {B}.

    Parameters
    ----------
    points_b : (N, 3) float, mm
    tcp_b : (3,) float, mm
    rotation_b : (3, 3) float

    Returns
    -------
    (N, 3) float64, mm in {T}.
    """
    return (_as_points(points_b, "points_b") - tcp_b) @ np.asarray(rotation_b, dtype=np.float64)
