"""Tests of scanner_core.normals (PCA normals over a profile stack, oriented toward the sensor)
and of the normals and sensor positions that scanner_core.io.scanfiles.save_scan writes."""
from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from clients.ply import parse_ply
from scanner_core.normals import estimate_normals
from scanner_core.io.ply import read_ply
from scanner_core.io.scanfiles import point_sensors, save_scan
from scanner_core.types import Scan
from simulator.cell import load_cell
from simulator.motion import PassMotion
from simulator.parts import block_with_holes_and_steps
from simulator.session import run_simulated_scan

#: Point spacing along a profile and between profiles, mm: the reference cell's 0.16 mm per
#: pixel, and its default pass (200 mm/s at 162 fps).
ALONG_MM, ACROSS_MM = 0.16, 1.2
#: The stripe's noise, mm (the scan's RMS error is under 20 um).
NOISE_MM = 0.02
#: Where the camera sits in {T} during a pass of the reference cell: below the part.
SENSOR_T = np.array([0.0, 0.0, 440.0])
#: Exact geometry (a plane, or a cylinder along the profiles' normal): round-off only.
EXACT_TOL_DEG = 1e-3
#: Curved surfaces, inner points: the plane through neighbouring profiles ACROSS_MM apart
#: tilts by a fraction of a degree on radii of 20-30 mm.
CURVED_TOL_DEG = 0.5
#: Points at the end of a profile or in the first or last profile: a one-sided neighbourhood
#: on a curved surface (about half the neighbourhood's width over the radius, in radians).
BORDER_TOL_DEG = 3.0
#: With the stripe's noise: median and 99th percentile of the angular error.
NOISY_MEDIAN_TOL_DEG = 0.75
NOISY_P99_TOL_DEG = 3.0
#: Points per profile end counted as border (about half the own-profile neighbourhood).
BORDER_POINTS = 8


def angle_deg(a, b) -> np.ndarray:
    """Angle between rows of unit vectors, degrees (atan2: exact near 0)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1)))


def unit_rows(v) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


# ---------------------------------------------------------------------------------------------
# Synthetic profile stacks: profile i lies in the plane y = y_i, as the light sheet cuts the
# part in {T}; each returns points (N, 3), true normals toward +z (N, 3), frame ids (N,).


def _profile_planes(count):
    return (np.arange(count) - (count - 1) / 2.0) * ACROSS_MM


def tilted_plane():
    y = _profile_planes(25)
    x = np.arange(-8.0, 8.0, ALONG_MM)
    xx, yy = np.meshgrid(x, y)
    points = np.column_stack([xx.ravel(), yy.ravel(), (0.3 * xx - 0.2 * yy + 25.0).ravel()])
    normals = np.tile(unit_rows(np.array([[-0.3, 0.2, 1.0]])), (len(points), 1))
    return points, normals, np.repeat(np.arange(len(y)), len(x))


def cylinder_along_y(radius=20.0):
    """Axis along the pass: every profile is the same arc."""
    y = _profile_planes(25)
    theta = np.arange(-np.radians(60), np.radians(60), ALONG_MM / radius)
    tt, yy = np.meshgrid(theta, y)
    points = np.column_stack([radius * np.sin(tt).ravel(), yy.ravel(), radius * np.cos(tt).ravel()])
    normals = unit_rows(points * [1.0, 0.0, 1.0])
    return points, normals, np.repeat(np.arange(len(y)), len(theta))


def cylinder_along_x(radius=20.0):
    """Axis along the profiles: straight profiles, the curvature across them."""
    y = _profile_planes(25)
    x = np.arange(-8.0, 8.0, ALONG_MM)
    xx, yy = np.meshgrid(x, y)
    points = np.column_stack([xx.ravel(), yy.ravel(), np.sqrt(radius**2 - yy**2).ravel()])
    normals = unit_rows(points * [0.0, 1.0, 1.0])
    return points, normals, np.repeat(np.arange(len(y)), len(x))


def sphere(radius=28.625):
    """The calibration sphere: every profile a circle of latitude."""
    points, ids = [], []
    for i, y in enumerate(_profile_planes(25)):
        r = np.sqrt(radius**2 - y**2)
        theta = np.arange(-np.radians(60), np.radians(60), ALONG_MM / r)
        points.append(np.column_stack([r * np.sin(theta), np.full(len(theta), y), r * np.cos(theta)]))
        ids.append(np.full(len(theta), i))
    points = np.concatenate(points)
    return points, points / radius, np.concatenate(ids)


SURFACES = {"plane": (tilted_plane, EXACT_TOL_DEG), "cylinder_y": (cylinder_along_y, EXACT_TOL_DEG),
            "cylinder_x": (cylinder_along_x, CURVED_TOL_DEG), "sphere": (sphere, CURVED_TOL_DEG)}


def border(points, frame_ids) -> np.ndarray:
    """(N,) bool: the first and last profile, and BORDER_POINTS at each end of every profile."""
    out = (frame_ids == frame_ids.min()) | (frame_ids == frame_ids.max())
    for fid in np.unique(frame_ids):
        members = np.nonzero(frame_ids == fid)[0]
        ordered = members[np.argsort(points[members, 0])]
        out[ordered[:BORDER_POINTS]] = out[ordered[-BORDER_POINTS:]] = True
    return out


# ---------------------------------------------------------------------------------------------
# Against the analytic normals


@pytest.mark.parametrize("name", SURFACES)
def test_exact_profiles_match_the_analytic_normals(name):
    make, inner_tol = SURFACES[name]
    points, truth, frame_ids = make()
    normals = estimate_normals(points, sensors=SENSOR_T, frame_ids=frame_ids, fallback="nan")
    assert normals.dtype == np.float32 and normals.shape == points.shape
    assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    error = angle_deg(normals, truth)
    edge = border(points, frame_ids)
    assert error[~edge].max() < inner_tol
    assert error[edge].max() < BORDER_TOL_DEG


@pytest.mark.parametrize("name", SURFACES)
def test_noisy_profiles_match_the_analytic_normals(name):
    points, truth, frame_ids = SURFACES[name][0]()
    rng = np.random.default_rng(7)
    noisy = points + rng.normal(0.0, NOISE_MM, points.shape)
    error = angle_deg(estimate_normals(noisy, sensors=SENSOR_T, frame_ids=frame_ids), truth)
    assert np.median(error) < NOISY_MEDIAN_TOL_DEG
    assert np.percentile(error, 99) < NOISY_P99_TOL_DEG


def test_without_frame_ids_an_unstructured_cloud_works():
    """Plain k nearest neighbours (Hoppe et al.) on points spread evenly over a plane."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(-10.0, 10.0, (3000, 2))
    points = np.column_stack([xy, 0.5 * xy[:, 0] + 3.0])
    truth = unit_rows(np.array([[-0.5, 0.0, 1.0]]))
    normals = estimate_normals(points, sensors=SENSOR_T)
    assert angle_deg(normals, np.broadcast_to(truth, points.shape)).max() < EXACT_TOL_DEG


def test_a_step_is_not_smoothed_over():
    """Two parallel faces 5 mm apart, each point's neighbours come from its own face only:
    the automatic radius stops at the gap."""
    points, truth, frame_ids = tilted_plane()
    step = points[:, 0] > 0
    points = points + np.where(step, 5.0, 0.0)[:, None] * [0.0, 0.0, 1.0]
    normals = estimate_normals(points, sensors=SENSOR_T, frame_ids=frame_ids)
    assert angle_deg(normals, truth).max() < EXACT_TOL_DEG


def test_a_dropped_frame_is_bridged():
    """Profiles are neighbours by rank: frame ids with gaps give the same normals."""
    points, _, frame_ids = cylinder_along_x()
    sparse = estimate_normals(points, sensors=SENSOR_T, frame_ids=3 * frame_ids + 100)
    dense = estimate_normals(points, sensors=SENSOR_T, frame_ids=frame_ids)
    assert_array_equal(sparse, dense)


# ---------------------------------------------------------------------------------------------
# Orientation


@pytest.mark.parametrize("name", SURFACES)
def test_normals_face_each_points_own_sensor(name):
    """Sensors on either side of the surface, chosen per point: each normal points to its own."""
    points, truth, frame_ids = SURFACES[name][0]()
    rng = np.random.default_rng(11)
    side = rng.choice([-1.0, 1.0], len(points))
    sensors = points + side[:, None] * 300.0 * truth + rng.normal(0.0, 50.0, points.shape)
    normals = estimate_normals(points, sensors=sensors, frame_ids=frame_ids)
    assert np.all(np.einsum("ij,ij->i", normals, sensors - points) > 0)
    assert_array_equal(np.sign(np.einsum("ij,ij->i", normals, truth)), side)


def test_moving_the_sensor_across_flips_every_sign():
    points, truth, frame_ids = sphere()
    inside = estimate_normals(points, sensors=np.zeros(3), frame_ids=frame_ids)
    outside = estimate_normals(points, sensors=SENSOR_T, frame_ids=frame_ids)
    assert_array_equal(inside, -outside)
    assert np.all(np.einsum("ij,ij->i", outside, truth) > 0)  # the sphere seen from outside


# ---------------------------------------------------------------------------------------------
# Points without a plane, unknown sensors, bad input


@pytest.mark.parametrize("curved", [False, True])
def test_a_lone_profile_gets_the_view_direction_or_nan(curved):
    """One profile fixes no surface plane: straight, it is a line; curved, its plane is the
    light sheet's. "view" gives the unit vector to the sensor."""
    if curved:  # round a 1.5 mm fillet: no line, but a plane only through the sheet
        theta = np.arange(-np.radians(80), np.radians(80), ALONG_MM / 1.5)
        points = np.column_stack([1.5 * np.sin(theta), np.zeros_like(theta), 1.5 * np.cos(theta)])
    else:
        x = np.arange(-5.0, 5.0, ALONG_MM)
        points = np.column_stack([x, np.zeros_like(x), 0.1 * x])
    frame_ids = np.full(len(points), 7, np.int64)
    sensor = np.array([3.0, -50.0, 400.0])
    view = estimate_normals(points, sensors=sensor, frame_ids=frame_ids)
    assert_allclose(view, unit_rows(sensor - points), atol=1e-6)
    assert np.isnan(estimate_normals(points, sensors=sensor, frame_ids=frame_ids,
                                     fallback="nan")).all()


def test_a_feature_one_profile_saw_gets_the_fallback():
    """A hole's floor seen by one profile through its mouth: the profiles either side are
    beyond the radius, so that profile alone fixes no plane."""
    points, truth, frame_ids = tilted_plane()
    floor = frame_ids == 12
    points[floor] -= [0.0, 0.0, 10.0]
    normals = estimate_normals(points, sensors=SENSOR_T, frame_ids=frame_ids, fallback="nan")
    assert np.isnan(normals[floor]).all()
    assert angle_deg(normals[~floor], truth[~floor]).max() < EXACT_TOL_DEG


def test_isolated_points_get_the_fallback_the_rest_a_plane():
    points, truth, frame_ids = tilted_plane()
    far = np.array([[500.0, 0.0, 0.0], [0.0, 500.0, 0.0]])
    points = np.vstack([points, far])
    frame_ids = np.concatenate([frame_ids, [3, 7]])
    normals = estimate_normals(points, sensors=SENSOR_T, frame_ids=frame_ids, fallback="nan")
    assert np.isnan(normals[-2:]).all()
    assert angle_deg(normals[:-2], truth).max() < EXACT_TOL_DEG
    fallback = estimate_normals(points, sensors=SENSOR_T, frame_ids=frame_ids)
    assert_allclose(fallback[-2:], unit_rows(SENSOR_T - far), atol=1e-6)


def test_an_unknown_sensor_gives_nan():
    points, _, frame_ids = tilted_plane()
    sensors = np.tile(SENSOR_T, (len(points), 1))
    sensors[:10] = np.nan
    normals = estimate_normals(points, sensors=sensors, frame_ids=frame_ids)
    assert np.isnan(normals[:10]).all() and np.isfinite(normals[10:]).all()


def test_empty_and_tiny_clouds():
    assert estimate_normals(np.zeros((0, 3)), sensors=SENSOR_T).shape == (0, 3)
    three = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert_allclose(estimate_normals(three, sensors=SENSOR_T), unit_rows(SENSOR_T - three),
                    atol=1e-6)  # fewer than min_neighbours: the fallback


@pytest.mark.parametrize("kwargs, match", [
    ({"points": np.zeros((4, 2))}, "`points` must be"),
    ({"points": np.array([[0.0, np.nan, 0.0]] * 4)}, "`points` must be finite"),
    ({"sensors": np.zeros((3, 3))}, "`sensors` must be"),
    ({"frame_ids": np.zeros(4)}, "`frame_ids` must be"),
    ({"frame_ids": np.zeros(5, np.int32)}, "`frame_ids` must be"),
    ({"k": 2}, "`k` must be"),
    ({"min_neighbours": 2.5}, "`min_neighbours` must be"),
    ({"radius": -1.0}, "`radius` must be"),
    ({"radius": "wide"}, "`radius` must be"),
    ({"fallback": "zero"}, "`fallback` must be"),
    ({"workers": 0}, "`workers` must be"),
])
def test_bad_input_is_named(kwargs, match):
    args = {"points": np.zeros((4, 3)), "sensors": SENSOR_T} | kwargs
    with pytest.raises(ValueError, match=match):
        estimate_normals(args.pop("points"), **args)


# ---------------------------------------------------------------------------------------------
# save_scan end to end: the simulated cell's demo block


#: The flat underside's normals against the true face normal, inner points.
FACE_TOL_DEG = 2.0
FACE_MEDIAN_TOL_DEG = 0.5
#: The marker-derived TCP errs by about 10 um against the true one (the simulated robot's
#: rotation is exact), and the sensor position inherits that error.
SENSOR_TRUTH_TOL_MM = 0.05
#: Points this close to a face's outline or a hole's rim are left out of the face check.
FACE_MARGIN_MM = 2.0


@pytest.fixture(scope="module")
def saved_block(block_part, tmp_path_factory):
    cell = load_cell().with_pass(fps=60.0)  # a cheap pass: about 4000 points
    scan, report = run_simulated_scan(block_part, cell, seed=3, evaluate=False)
    out = tmp_path_factory.mktemp("scan")
    save_scan(out, scan, report)
    return cell, scan, out


def test_cloud_ply_fields(saved_block):
    _, scan, out = saved_block
    points, fields = read_ply(out / "cloud.ply")
    assert list(fields) == ["nx", "ny", "nz", "sensor_x", "sensor_y", "sensor_z", "frame_id",
                            "quality", "deviation"]
    assert all(fields[f].dtype == np.float32 for f in ("nx", "ny", "nz", "sensor_x", "sensor_y",
                                                       "sensor_z", "quality", "deviation"))
    assert fields["frame_id"].dtype == np.int32
    assert_array_equal(points, scan.cloud)
    normals = np.column_stack([fields["nx"], fields["ny"], fields["nz"]])
    assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    # The clients' reader takes the same file, field for field.
    served = parse_ply((out / "cloud.ply").read_bytes())
    assert list(served) == ["x", "y", "z", *fields]
    for name, values in fields.items():
        assert_array_equal(served[name], values)
    edges, edge_fields = read_ply(out / "edges.ply")
    assert edges.shape == (len(scan.edges), 3) and len(scan.edges) > 0
    assert list(edge_fields) == [*(f for f in fields if f != "deviation"), "kind", "size_mm"]


def test_normals_of_the_underside_are_its_face_normal_toward_the_camera(saved_block):
    """The block hangs along +z_T with its underside at z_T = 20 facing the camera below it,
    which sits at large +z_T: the face normal toward the camera is +z_T."""
    _, scan, out = saved_block
    points, fields = read_ply(out / "cloud.ply")
    normals = np.column_stack([fields["nx"], fields["ny"], fields["nz"]]).astype(np.float64)
    sensors = np.column_stack([fields["sensor_x"], fields["sensor_y"], fields["sensor_z"]])
    assert np.all(sensors[:, 2] > points[:, 2].max() + 300.0)  # the camera is below the part
    assert np.all(np.einsum("ij,ij->i", normals, sensors - points) > 0)
    feats = block_with_holes_and_steps().metadata["features"]
    step_x = feats["steps"][0]["x_min"]
    inner = ((np.abs(points[:, 2] - 20.0) < 0.1)
             & (points[:, 0] > -30.0 + FACE_MARGIN_MM) & (points[:, 0] < step_x - FACE_MARGIN_MM)
             & (np.abs(points[:, 1]) < 20.0 - FACE_MARGIN_MM))
    for hole in feats["through_holes"] + feats["blind_holes"]:
        rim = np.hypot(points[:, 0] - hole["xy"][0], points[:, 1] - hole["xy"][1])
        inner &= rim > hole["radius"] + FACE_MARGIN_MM
    assert inner.sum() > 1000
    error = angle_deg(normals[inner], np.broadcast_to([0.0, 0.0, 1.0], (inner.sum(), 3)))
    assert error.max() < FACE_TOL_DEG
    assert np.median(error) < FACE_MEDIAN_TOL_DEG


def test_sensor_positions_are_the_camera_centre_in_the_gripper_frame(saved_block):
    cell, scan, out = saved_block
    _, fields = read_ply(out / "cloud.ply")
    sensors = np.column_stack([fields["sensor_x"], fields["sensor_y"], fields["sensor_z"]])
    # From the scan's own per-frame pose and the calibration: R_f^T (C_B - t_f), per point.
    frame = np.searchsorted(scan.tcp_frame_ids, fields["frame_id"])
    assert_array_equal(scan.tcp_frame_ids[frame], fields["frame_id"])
    centre_b = cell.calibration.camera.origin
    expected = np.einsum("nji,nj->ni", scan.tcp_rotations_b[frame],
                         centre_b - scan.tcp_positions_b[frame])
    assert_allclose(sensors, expected, atol=1e-4)  # float32 of ~440 mm
    # And against the simulator's truth: the robot's true rotation and TCP at each frame.
    assert_allclose(scan.tcp_rotations_b, np.broadcast_to(cell.gripper_rotation_b,
                                                          scan.tcp_rotations_b.shape))
    true_tcp = PassMotion(cell.pass_profile).tcp_position(scan.tcp_times)
    truth = (centre_b - true_tcp) @ cell.gripper_rotation_b
    assert_allclose(scan.sensor_positions_t, truth, atol=SENSOR_TRUTH_TOL_MM)


def test_a_scan_without_sensor_positions_is_written_with_nan(tmp_path):
    """A Scan built by hand (no per-frame poses): no viewpoint, so NaN normals and sensors."""
    scan = Scan(np.ones((5, 3), np.float32), np.zeros(5, np.int32), np.ones(5, np.float32),
                np.zeros((0, 3), np.float32), np.zeros((1, 3)), np.zeros(1), 1, 0)
    save_scan(tmp_path, scan, {})
    points, fields = read_ply(tmp_path / "cloud.ply")
    assert points.shape == (5, 3)
    assert all(np.isnan(fields[f]).all() for f in ("nx", "ny", "nz", "sensor_x", "sensor_y",
                                                   "sensor_z"))


def test_point_sensors_refuses_mismatched_frames():
    scan = Scan(np.ones((2, 3), np.float32), np.array([4, 5], np.int32), np.ones(2, np.float32),
                np.zeros((0, 3), np.float32), np.zeros((2, 3)), np.zeros(2), 2, 0)
    scan.tcp_frame_ids = np.array([5, 4])
    scan.sensor_positions_t = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 4.0]])
    assert_array_equal(point_sensors(scan), [[0.0, 0.0, 4.0], [0.0, 0.0, 5.0]])
    scan.sensor_positions_t = np.zeros((3, 3))
    with pytest.raises(ValueError, match="same frames"):
        point_sensors(scan)


@pytest.mark.parametrize("radius", [None, 0.5])
def test_the_profile_search_finds_what_a_kd_tree_finds(radius):
    """The neighbours searched profile by profile along their main direction
    (``normals._profile_neighbours``) are those a KD-tree over the points, each profile kept
    apart from the others, answers: the same distances in the same order, and the same points
    (duplicated points, at the same distance, may come in another order), on curved, noisy
    profiles with duplicates, a one-point profile and a rank with no neighbour on one side."""
    from scipy.spatial import cKDTree

    from scanner_core.normals import _profile_neighbours

    rng = np.random.default_rng(4)
    rows = []
    for rank in range(12):
        n = 1 if rank == 5 else int(rng.integers(20, 60))
        s = np.sort(rng.uniform(-4.0, 4.0, n))
        rows.append(np.column_stack([s, np.full(n, rank * ACROSS_MM),
                                     0.3 * s**2 + rng.normal(0.0, NOISE_MM, n), np.full(n, rank)]))
    cloud = np.concatenate(rows)
    cloud = np.concatenate([cloud, cloud[::7]])  # duplicates: ties broken the same way
    points, ranks = cloud[:, :3] - cloud[:, :3].mean(axis=0), cloud[:, 3].astype(np.int64)
    query = rng.choice(len(points), 150, replace=False)
    bound = np.inf if radius is None else radius
    index, distance = _profile_neighbours(points, ranks, 9, bound, query)
    separation = 4.0 * float(np.linalg.norm(np.ptp(points, axis=0))) + 4.0
    tree = cKDTree(np.column_stack([points, ranks * separation]))
    for i, offset in enumerate((0, -1, 1)):
        at = np.column_stack([points[query], (ranks[query] + offset) * separation])
        d, j = tree.query(at, k=9, distance_upper_bound=min(bound, separation / 2))
        assert_array_equal(distance[i], d)
        found = np.isfinite(d)
        assert_array_equal(points[index[i][found]], points[j[found]])
        assert np.all(index[i][~np.isfinite(d)] == len(points))
