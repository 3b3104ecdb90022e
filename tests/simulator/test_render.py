import numpy as np
import trimesh
from numpy.testing import assert_allclose

from simulator.parts import part_from_mesh
from simulator.render import PartScene, slice_mesh

#: Geometry computed in float64 from an exact section: sub-nanometre.
EXACT_MM = 1e-6


def test_slice_box_perimeter():
    box = trimesh.creation.box(extents=(20.0, 30.0, 40.0))
    segments, faces = slice_mesh(box.vertices, box.faces, np.array([0.0, 0.0, 1.0]), 5.0)
    assert len(segments) == len(faces) == 8  # two triangles per side face
    assert_allclose(segments[:, :, 2], 5.0, atol=1e-12)
    length = np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1).sum()
    assert_allclose(length, 2 * (20.0 + 30.0), rtol=1e-12)


def test_slice_misses():
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    segments, faces = slice_mesh(box.vertices, box.faces, np.array([0.0, 0.0, 1.0]), 5.0)
    assert segments.shape == (0, 2, 3) and len(faces) == 0


def _plate(extra=()):
    plate = trimesh.creation.box(extents=(100.0, 60.0, 10.0))
    plate.apply_translation((0.0, 0.0, 5.0))  # z in [0, 10]: the underside is z_P = 10
    return part_from_mesh(trimesh.util.concatenate([plate, *extra]), name="plate")


def test_flat_plate_stripe_is_exact(cell, rng):
    scene = PartScene(_plate(), cell)
    tcp = np.array([0.0, 0.0, 50.0])
    image, truth = scene.render(tcp, scene.part.grasp, rng)
    assert image.shape == (1200, 1920) and image.dtype == np.uint8
    pts = truth.stripe_points_b
    # The underside hangs 10 mm below the TCP ({T} z points down), on the sheet y = 0.
    assert_allclose(pts[:, 2], tcp[2] - 10.0, atol=EXACT_MM)
    assert_allclose(cell.light_plane_b.signed_distance(pts), 0.0, atol=EXACT_MM)
    # One sample per column, across the whole plate, at the camera's projection.
    assert len(np.unique(truth.stripe_columns)) == len(truth.stripe_columns)
    assert pts[:, 0].min() < -49.5 and pts[:, 0].max() > 49.5
    proj = cell.calibration.camera.project(pts)
    assert_allclose(proj[:, 0], truth.stripe_columns, atol=1e-6)
    assert_allclose(proj[:, 1], truth.stripe_rows, atol=1e-6)
    # Brightness follows the laser's incidence on a face pointing down at it.
    laser = cell.laser_origin_b
    cos = (pts - laser)[:, 2] / np.linalg.norm(pts - laser, axis=1)
    assert_allclose(truth.stripe_gain, cos, atol=1e-9)
    # The marker shows in all three views.
    assert np.all(np.isfinite(truth.marker_pixels))


def test_visibility_agrees_with_independent_ray_casts(cell, rng, block_part):
    """Every rendered sample is reached by the laser and seen by the camera, checked with
    trimesh's pure-numpy triangle intersector (not Embree)."""
    scene = PartScene(block_part, cell)
    _, truth = scene.render(np.array([0.0, -5.0, 50.0]), block_part.grasp, rng)
    assert len(truth.stripe_points_b) > 100
    pose = truth.part_pose_b
    inv = np.linalg.inv(pose)
    pts_p = trimesh.transform_points(truth.stripe_points_b, inv)
    checker = trimesh.ray.ray_triangle.RayMeshIntersector(block_part.mesh)
    for source_b in (cell.laser_origin_b, cell.calibration.camera.origin):
        src = trimesh.transform_points(source_b[None], inv)[0]
        dirs = pts_p - src
        dist = np.linalg.norm(dirs, axis=1)
        locs, ray_idx, _ = checker.intersects_location(np.repeat(src[None], len(pts_p), 0),
                                                       dirs / dist[:, None], multiple_hits=True)
        first = np.full(len(pts_p), np.inf)
        np.minimum.at(first, ray_idx, np.linalg.norm(locs - src, axis=1))
        assert np.all(first >= dist - 0.02)


def test_occluding_rib_leaves_a_gap(cell, rng):
    """A rib between the sheet and the camera hides the stripe behind it."""
    rib = trimesh.creation.box(extents=(40.0, 2.0, 20.0))
    rib.apply_translation((0.0, 4.0, 20.0))  # {P}: y_P = 4 is y_B = -4 (camera side), hangs 10 mm lower
    scene_open = PartScene(_plate(), cell)
    scene_rib = PartScene(_plate([rib]), cell)
    tcp = np.array([0.0, 0.0, 50.0])
    grasp = np.eye(4)
    _, open_truth = scene_open.render(tcp, grasp, rng)
    _, rib_truth = scene_rib.render(tcp, grasp, rng)
    x_open = open_truth.stripe_points_b[:, 0]
    x_rib = rib_truth.stripe_points_b[:, 0]
    assert np.any(np.abs(x_open) < 15.0)
    assert not np.any(np.abs(x_rib) < 15.0)  # hidden behind the rib
    assert np.sum(np.abs(x_rib) > 30.0) == np.sum(np.abs(x_open) > 30.0)  # untouched beside it


def test_marker_hidden_by_the_part(cell, rng):
    """A part filling the volume's width hides the LED from the direct view (and, hanging
    this low, from the left mirror, which looks up from below); the right mirror, above the
    part, still sees it."""
    big = trimesh.creation.box(extents=(150.0, 60.0, 60.0))
    big.apply_translation((0.0, 0.0, 30.0))
    scene = PartScene(part_from_mesh(big, name="big"), cell)
    _, truth = scene.render(np.array([0.0, 0.0, 50.0]), np.eye(4), rng)
    assert np.all(np.isnan(truth.marker_pixels[0]))
    assert np.all(np.isfinite(truth.marker_pixels[2]))


def test_same_seed_same_frame(cell, block_part):
    scene = PartScene(block_part, cell)
    a, _ = scene.render(np.zeros(3) + [0, 0, 50], block_part.grasp, np.random.default_rng(5))
    b, _ = scene.render(np.zeros(3) + [0, 0, 50], block_part.grasp, np.random.default_rng(5))
    assert np.array_equal(a, b)
