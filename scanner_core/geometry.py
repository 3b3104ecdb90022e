"""Camera, light plane and mirror geometry: the paper's Eq. (1)-(3) and triangulation.

Conventions
-----------
- Pixel coordinates ``(u, v)`` = (column, row), pixel centres at integers.
- {C}: x along image columns, y along image rows, z the optical axis: a pinhole, with the
  lens's radial and tangential distortion (OpenCV's k1, k2, p1, p2, k3) when it has one.
- Eq. (1): ``P_C = T (P_B - O)``; Eq. (3): ``P_B = T^-1 (P_C + T O) = T^T P_C + O``.
- A plane is ``n . x = d`` with a unit normal ``n``; Eq. (2) writes the light plane as
  ``n . (P_C - P_0) = 0``, so ``d = n . P_0``.

References
----------
.. [1] "Fast visual part inspection for bin picking", section II (../shared/paper.md).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numba import njit

#: Rays nearly parallel to a plane (|cos| below this) have no usable intersection.
PARALLEL_COS = 1e-9
#: Fixed-point iterations that invert the lens distortion, and the step (normalised image
#: units, 1e-12 is about 3e-9 px) at which they stop.
UNDISTORT_ITERATIONS = 50
UNDISTORT_TOL = 1e-12
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
