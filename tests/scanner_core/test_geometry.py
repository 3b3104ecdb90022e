import numpy as np
import pytest
from numpy.testing import assert_allclose

from scanner_core.geometry import (Plane, angle_between, reflection_matrix, apply_transform, reproject_marker,
                                   marker_views, triangulate_marker, triangulate_rays,
                                   triangulate_stripe)

#: Round trips in float64 through a 450 mm standoff.
ROUND_TRIP_TOL_MM = 1e-9
ROUND_TRIP_TOL_PX = 1e-8


def test_eq1_eq3_round_trip(cell, rng):
    cam = cell.calibration.camera
    p_b = rng.uniform(-75, 75, (100, 3))
    assert_allclose(cam.to_base(cam.to_camera(p_b)), p_b, atol=ROUND_TRIP_TOL_MM)
    # Eq. (1) by hand: P_klm = T (P_xyz - O).
    assert_allclose(cam.to_camera(p_b[0])[0], cam.rotation @ (p_b[0] - cam.origin))


def test_stripe_triangulation_round_trip(cell, rng):
    """Points on the light plane -> pixels -> pixel ray x light plane -> the same points."""
    cal = cell.calibration
    plane_b = cal.light_plane_b
    pts = rng.uniform(-60, 60, (200, 3))
    pts -= np.outer(plane_b.signed_distance(pts), plane_b.normal)  # onto the plane
    px = cal.camera.project(pts)
    assert_allclose(triangulate_stripe(px, cal.camera, cal.light_plane_c), pts, atol=1e-8)


def test_stripe_triangulation_parallel_ray_is_nan(cell):
    cam = cell.calibration.camera
    # A light plane containing the camera's optical axis: the centre ray never meets it.
    plane = Plane(np.array([1.0, 0.0, 0.0]), 0.0)
    out = triangulate_stripe([[cam.cx, cam.cy]], cam, plane)
    assert np.all(np.isnan(out))


@pytest.mark.parametrize("angle", [1e-9, 1e-6, 0.3, np.pi / 2, np.pi - 1e-9])
def test_angle_between_keeps_its_precision_near_parallel(angle, rng):
    """arccos of the dot product gives 0 or 2.1e-8 rad below about 1e-8 rad; atan2 of the
    cross and dot products keeps it (here to the rounding of the vectors built)."""
    a = rng.normal(size=3)
    a /= np.linalg.norm(a)
    axis = np.cross(a, rng.normal(size=3))
    axis /= np.linalg.norm(axis)
    # b: a turned by `angle` about an axis normal to it (Rodrigues, exact for axis . a = 0)
    b = a * np.cos(angle) + np.cross(axis, a) * np.sin(angle)
    assert_allclose(angle_between(a, 3.0 * b), angle, rtol=1e-6)
    assert_allclose(angle_between(np.stack([a, a]), np.stack([b, -b]), undirected=True),
                    min(angle, np.pi - angle), rtol=1e-6)


def test_reflection_is_an_involution():
    h = reflection_matrix(np.array([0.3, -0.2, 0.9]), 12.5)
    p = np.array([[1.0, 2.0, 3.0], [-50.0, 4.0, 7.0]])
    assert_allclose(apply_transform(h, apply_transform(h, p)), p, atol=1e-12)
    n = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
    mid = (p + apply_transform(h, p)) / 2
    assert_allclose(mid @ n, 12.5, atol=1e-12)  # the midpoint lies on the mirror


def test_triangulate_rays_exact():
    target = np.array([10.0, -5.0, 30.0])
    origins = np.array([[0.0, 0, 0], [100, 0, 0], [0, 100, -20]])
    assert_allclose(triangulate_rays(origins, target - origins), target, atol=1e-10)


def test_triangulate_rays_parallel_raises():
    with pytest.raises(ValueError, match="parallel"):
        triangulate_rays([[0, 0, 0], [1, 0, 0]], [[0, 0, 1], [0, 0, 1]])
    with pytest.raises(ValueError, match="two rays"):
        triangulate_rays([[0, 0, 0]], [[0, 0, 1]])


@pytest.mark.parametrize("views", [(0, 1, 2), (0, 1), (0, 2), (1, 2)])
def test_marker_triangulation_against_truth(cell, rng, views):
    """The marker from any two or three views, exact pixels and noisy ones."""
    cal = cell.calibration
    marker = np.array([88.0, 40.0, 80.0])
    px = reproject_marker(marker, cal.camera, cal.mirrors)
    masked = np.full_like(px, np.nan)
    masked[list(views)] = px[list(views)]
    pos, residual = triangulate_marker(masked, cal.camera, cal.mirrors)
    assert_allclose(pos, marker, atol=1e-6)
    assert residual < ROUND_TRIP_TOL_PX * 1e3
    # 0.02 px of centroid noise moves the triangulated marker by micrometres, not more.
    errors = []
    for _ in range(200):
        noisy = masked + rng.normal(0, 0.02, masked.shape)
        errors.append(triangulate_marker(noisy, cal.camera, cal.mirrors)[0] - marker)
    rms = np.sqrt(np.mean(np.sum(np.square(errors), axis=1)))
    assert rms < (0.010 if len(views) == 3 else 0.050)


def test_marker_triangulation_needs_two_views(cell):
    cal = cell.calibration
    px = reproject_marker([88.0, 0.0, 80.0], cal.camera, cal.mirrors)
    px[1:] = np.nan
    pos, residual = triangulate_marker(px, cal.camera, cal.mirrors)
    assert np.all(np.isnan(pos)) and np.isnan(residual)


def _reference_marker(pixels, camera, mirrors):
    """The triangulation written plainly: each view's ray in {B}, two weighted solves."""
    rays, origins = [], []
    for k, px in enumerate(pixels):
        if not np.all(np.isfinite(px)):
            continue
        h = np.eye(4) if k == 0 else mirrors[k - 1].reflection
        rays.append(h[:3, :3] @ camera.rays(px[None])[0])
        origins.append(apply_transform(h, camera.origin))
    origins, rays = np.array(origins), np.array(rays)
    point = triangulate_rays(origins, rays)
    point = triangulate_rays(origins, rays, weights=1.0 / np.sum((point - origins) ** 2, axis=1))
    return point


def test_marker_kernel_equals_the_plain_triangulation(cell, rng):
    cal = cell.calibration
    for _ in range(20):
        marker = rng.uniform([-60, -60, 30], [60, 60, 120])
        px = reproject_marker(marker, cal.camera, cal.mirrors) + rng.normal(0, 0.05, (3, 2))
        pos, _ = triangulate_marker(px, cal.camera, cal.mirrors, views=cal.marker_views)
        assert_allclose(pos, _reference_marker(px, cal.camera, cal.mirrors), atol=1e-9)


def test_marker_from_parallel_views_is_refused(cell):
    cal = cell.calibration
    px = reproject_marker(np.array([0.0, 0.0, 60.0]), cal.camera, cal.mirrors)
    same = np.array([px[0], px[0], [np.nan, np.nan]])
    views = marker_views(cal.camera, (cal.mirrors[0], cal.mirrors[0]))
    views = type(views)(views.intrinsics, np.repeat(views.origins[:1], 3, 0),
                        np.repeat(views.to_base[:1], 3, 0), np.repeat(views.to_camera[:1], 3, 0))
    with pytest.raises(ValueError, match="parallel"):
        triangulate_marker(same, cal.camera, cal.mirrors[:2], views=views)


def test_planes_moved_carry_their_points():
    """A point on a plane, moved by (R, t), lies on the moved plane; one R for all and one
    per plane agree."""
    from scipy.spatial.transform import Rotation

    from scanner_core.geometry import planes_moved

    rng = np.random.default_rng(4)
    normals = rng.normal(size=(5, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = rng.normal(size=(5, 3)) * 50.0
    planes = np.c_[normals, np.einsum("ki,ki->k", normals, points)]
    rotations = Rotation.random(5, random_state=rng).as_matrix()
    shifts = rng.normal(size=(5, 3)) * 20.0
    moved = planes_moved(planes, rotations, shifts)
    carried = np.einsum("kij,kj->ki", rotations, points) + shifts
    np.testing.assert_allclose(np.einsum("ki,ki->k", moved[:, :3], carried), moved[:, 3],
                               atol=1e-9)
    one = planes_moved(planes, rotations[0], shifts[0])
    np.testing.assert_allclose(one, planes_moved(planes, np.repeat(rotations[:1], 5, axis=0),
                                                 np.repeat(shifts[:1], 5, axis=0)), atol=1e-12)
