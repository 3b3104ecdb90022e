"""The cell's geometric model: vectors and rigid transforms, the camera with its lens, planes
and mirrors (the paper's Eq. (1)-(3)).

Conventions
-----------
- Pixel coordinates ``(u, v)`` = (column, row), pixel centres at integers.
- {C}: x along image columns, y along image rows, z the optical axis: a pinhole, with the
  lens's radial and tangential distortion (OpenCV's k1, k2, p1, p2, k3) when it has one.
- Eq. (1): ``P_C = T (P_B - O)``; Eq. (3): ``P_B = T^-1 (P_C + T O) = T^T P_C + O``.
- A plane is ``n . x = d`` with a unit normal ``n``; Eq. (2) writes the light plane as
  ``n . (P_C - P_0) = 0``, so ``d = n . P_0``.

What is measured with this model (the stripe and the marker triangulated) is in
``scanner_core.geometry.triangulation``; ``scanner_core.geometry`` gathers both.

``PARALLEL_COS`` is compiled into the edge kernel (``scanner_core.edges.kernel``, numba,
``cache=True``), whose cache is invalidated only when that kernel's own file changes: after a
change to it here, clear numba's caches (``*.nbi``, ``*.nbc``).

References
----------
.. [1] "Fast visual part inspection for bin picking", section II.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

__all__ = ["PARALLEL_COS", "UNDISTORT_ITERATIONS", "UNDISTORT_TOL", "NO_DISTORTION", "unit",
           "angle_between", "reflection_matrix", "check_rigid", "apply_transform", "base_to_tcp",
           "distort_normalized", "undistort_normalized", "PinholeCamera", "Plane", "Mirror"]

#: Rays nearly parallel to a plane (|cos| below this) have no usable intersection.
PARALLEL_COS = 1e-9
#: Fixed-point iterations that invert the lens distortion, and the step (normalised image
#: units, 1e-12 is about 3e-9 px) at which they stop.
UNDISTORT_ITERATIONS = 50
UNDISTORT_TOL = 1e-12


def _as_points(points, name: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == 3:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"`{name}` must be (N, 3), got {np.shape(points)}")
    return arr


def unit(vectors: np.ndarray) -> np.ndarray:
    """Normalise along the last axis (no BLAS call: see docs/design.md on OpenBLAS spinning)."""
    vectors = np.asarray(vectors, dtype=np.float64)
    return vectors / np.sqrt(np.einsum("...i,...i->...", vectors, vectors))[..., None]


def angle_between(a, b, *, undirected: bool = False) -> np.ndarray:
    """Angle between vectors, radians, exact near 0 and near pi.

    ``atan2(|a x b|, a . b)``: ``arccos`` of the dot product of nearly parallel unit vectors
    has no precision left (a dot product of 0.9999999999999998, one unit in the last place,
    gives 2.1e-8 rad whatever the true angle, and the last bits differ between CPUs and BLAS
    kernels); the cross product keeps it. The vectors need not be unit length.

    Parameters
    ----------
    a, b : (..., 3) float
        Broadcast against each other.
    undirected : bool
        Lines rather than vectors (plane normals of either sign): the angle folded into
        ``[0, pi / 2]``.

    Returns
    -------
    (...) float64
        Radians in ``[0, pi]`` (``[0, pi / 2]`` when ``undirected``).
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    cross = np.cross(a, b)
    sin = np.sqrt(np.einsum("...i,...i->...", cross, cross))
    cos = np.einsum("...i,...i->...", a, b)
    if undirected:
        cos = np.abs(cos)
    return np.arctan2(sin, cos)


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


def planes_moved(planes: np.ndarray, rotation: np.ndarray, translation: np.ndarray
                 ) -> np.ndarray:
    """Planes ``n . x = offset`` after ``x -> R x + t``: ``(R n, offset + (R n) . t)``.

    Parameters
    ----------
    planes : (K, 4) or (4,) float
        ``(n_x, n_y, n_z, offset)``, unit n.
    rotation : (3, 3) or (K, 3, 3) float
        One R for all, or one per plane.
    translation : (3,) or (K, 3) float, mm

    Returns
    -------
    (K, 4) float64
    """
    planes = np.asarray(planes, dtype=np.float64).reshape(-1, 4)
    rotation = np.asarray(rotation, dtype=np.float64)
    normals = (np.einsum("kij,kj->ki", rotation, planes[:, :3]) if rotation.ndim == 3
               else planes[:, :3] @ rotation.T)
    translation = np.broadcast_to(np.asarray(translation, dtype=np.float64), normals.shape)
    return np.column_stack([normals, planes[:, 3] + np.einsum("ki,ki->k", normals, translation)])


def apply_transform(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 homogeneous transform to (N, 3) points."""
    points = np.asarray(points, dtype=np.float64)
    return np.einsum("ij,...j->...i", matrix[:3, :3], points) + matrix[:3, 3]


def distort_normalized(xy, distortion) -> np.ndarray:
    """Brown-Conrady lens distortion of normalised image points, as OpenCV models it.

    Parameters
    ----------
    xy : (N, 2) float
        Ideal normalised coordinates ``(X/Z, Y/Z)``.
    distortion : (5,) float
        ``(k1, k2, p1, p2, k3)``.

    Returns
    -------
    (N, 2) float64
        Distorted normalised coordinates.

    References
    ----------
    .. [1] OpenCV, "Camera Calibration and 3D Reconstruction" (calib3d), the distortion model.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    k1, k2, p1, p2, k3 = (float(v) for v in distortion)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return np.stack([x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                     y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y], axis=1)


def undistort_normalized(xy, distortion) -> np.ndarray:
    """The inverse of :func:`distort_normalized`, by fixed-point iteration.

    Converges for the distortion of machine-vision lenses (a few percent at the corners);
    points that have not converged after ``UNDISTORT_ITERATIONS`` come back NaN rather than
    wrong.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    k1, k2, p1, p2, k3 = (float(v) for v in distortion)
    xd, yd = xy[:, 0], xy[:, 1]
    x, y = xd.copy(), yd.copy()
    with np.errstate(invalid="ignore", over="ignore"):
        for _ in range(UNDISTORT_ITERATIONS):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            nx = (xd - 2.0 * p1 * x * y - p2 * (r2 + 2.0 * x * x)) / radial
            ny = (yd - p1 * (r2 + 2.0 * y * y) - 2.0 * p2 * x * y) / radial
            step = np.nanmax(np.abs(nx - x) + np.abs(ny - y), initial=0.0)
            x, y = nx, ny
            if step < UNDISTORT_TOL:
                break
        # A point whose iteration has not settled is not trusted.
        back = distort_normalized(np.stack([x, y], 1), distortion)
        bad = ~(np.abs(back - xy).max(axis=1) < 1e3 * UNDISTORT_TOL)
    out = np.stack([x, y], axis=1)
    out[bad & np.isfinite(xy).all(axis=1)] = np.nan
    return out


NO_DISTORTION = (0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole camera posed in {B}, with its lens's distortion.

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
    distortion : (5,) tuple of float
        ``(k1, k2, p1, p2, k3)`` (OpenCV's order); all zero for an ideal pinhole.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    rotation: np.ndarray
    origin: np.ndarray
    distortion: tuple = NO_DISTORTION

    @property
    def distorted(self) -> bool:
        return any(v != 0.0 for v in self.distortion)

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 intrinsic matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def to_camera(self, points_b) -> np.ndarray:
        """Eq. (1): {B} -> {C}. (N, 3) mm -> (N, 3) mm."""
        p = _as_points(points_b, "points_b")
        return (p - self.origin) @ self.rotation.T

    def to_base(self, points_c) -> np.ndarray:
        """Eq. (3): {C} -> {B}. (N, 3) mm -> (N, 3) mm."""
        p = _as_points(points_c, "points_c")
        return p @ self.rotation + self.origin

    def project_camera(self, points_c) -> np.ndarray:
        """(N, 3) points in {C} -> (N, 2) pixels (u, v), through the lens; NaN behind the
        camera."""
        p = _as_points(points_c, "points_c")
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(p[:, 2] > 0, p[:, 2], np.nan)
            xy = np.stack([p[:, 0] / z, p[:, 1] / z], 1)
        if self.distorted:
            xy = distort_normalized(xy, self.distortion)
        return np.stack([self.fx * xy[:, 0] + self.cx, self.fy * xy[:, 1] + self.cy], 1)

    def project(self, points_b) -> np.ndarray:
        """(N, 3) points in {B} -> (N, 2) pixels (u, v); NaN behind the camera."""
        return self.project_camera(self.to_camera(points_b))

    def rays_camera(self, pixels) -> np.ndarray:
        """(N, 2) pixels (u, v) -> (N, 3) ray directions in {C} with z = 1 (not unit), the
        lens's distortion undone."""
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        xy = np.stack([(px[:, 0] - self.cx) / self.fx, (px[:, 1] - self.cy) / self.fy], 1)
        if self.distorted:
            xy = undistort_normalized(xy, self.distortion)
        return np.concatenate([xy, np.ones((len(px), 1))], axis=1)

    def ideal_pixels(self, pixels) -> np.ndarray:
        """(N, 2) measured pixels -> where an ideal pinhole with the same intrinsics would
        have seen them (the pixels themselves when the lens has no distortion)."""
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        if not self.distorted:
            return px
        xy = self.rays_camera(px)
        return np.stack([self.fx * xy[:, 0] + self.cx, self.fy * xy[:, 1] + self.cy], 1)

    def without_distortion(self) -> "PinholeCamera":
        return replace(self, distortion=NO_DISTORTION)

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
