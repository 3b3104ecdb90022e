import numpy as np
import trimesh
from numpy.testing import assert_allclose

from simulator.parts import part_from_mesh
from scanner_core.geometry import PinholeCamera
from simulator.render import PartScene, column_hits, slice_mesh

#: Geometry computed in float64 from an exact section: sub-nanometre.
EXACT_MM = 1e-6
#: Pixel coverage from float64 projections of columns near 100: round-off only.
EXACT_COVERAGE = 1e-9


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
    assert pts[:, 0].min() < -49.5 and pts[:, 0].max() > 49.5
    # Each sample lies at the camera's projection of its point, inside its pixel column.
    proj = cell.calibration.camera.project(pts)
    assert_allclose(proj[:, 1], truth.stripe_rows, atol=1e-6)
    assert np.all(np.abs(proj[:, 0] - truth.stripe_columns) <= 0.5 + 1e-9)
    # Brightness follows the laser's incidence on a face pointing down at it, times the share
    # of the pixel column covered: the columns inside the plate are covered once in full,
    # the two at its ends in part, as far as the plate's sides reach into them.
    laser = cell.laser_origin_b
    cos = (pts - laser)[:, 2] / np.linalg.norm(pts - laser, axis=1)
    cols = truth.stripe_columns
    coverage = np.bincount(cols - cols.min(), truth.stripe_gain / cos)
    assert_allclose(coverage[1:-1], 1.0, atol=EXACT_COVERAGE)
    ends_b = np.array([[-50.0, 0.0, tcp[2] - 10.0], [50.0, 0.0, tcp[2] - 10.0]])
    u_ends = np.sort(cell.calibration.camera.project(ends_b)[:, 0])
    expected_ends = [cols.min() + 0.5 - u_ends[0], u_ends[1] - (cols.max() - 0.5)]
    assert_allclose(coverage[[0, -1]], expected_ends, atol=EXACT_COVERAGE)
    # The marker shows in all three views.
    assert np.all(np.isfinite(truth.marker_pixels))


def _camera():
    """A camera at the origin of {B} looking along +z_B: u = 10 x / z * 100 + 100."""
    return PinholeCamera(fx=1000.0, fy=1000.0, cx=100.0, cy=50.0, width=200, height=100,
                         rotation=np.eye(3), origin=np.zeros(3))


def _segment_at(camera, u, row_slope=0.3, depth=(100.0, 140.0)):
    """A straight 3-D segment whose ends project to columns ``u`` (its depth varying
    linearly from ``depth[0]`` at u = 0 to ``depth[1]`` at u = 200, its row as
    50 + row_slope * (u - 100) ): (2, 3)."""
    u = np.asarray(u, dtype=np.float64)
    z = depth[0] + (depth[1] - depth[0]) * u / 200.0
    x = (u - camera.cx) / camera.fx * z
    y = row_slope * (u - camera.cx) / camera.fy * z
    return np.stack([x, y, z], axis=1)


def test_coverage_of_the_last_column_of_a_segment():
    """A segment ending at u = c + 0.3 lights column c at 0.8 of a full one; each sample sits
    at the middle of the part of its pixel column it covers."""
    cam = _camera()
    seg = _segment_at(cam, [37.6, 50.3])
    cols, rows, points, segment, coverage = column_hits(seg[None], np.eye(4), cam, (0, 200))
    assert_allclose(cols, np.arange(38, 51))
    assert np.all(segment == 0)
    assert_allclose(coverage, [0.9] + [1.0] * 11 + [0.8], atol=EXACT_COVERAGE)
    middle = np.where(cols == 38, (37.6 + 38.5) / 2, np.where(cols == 50, (49.5 + 50.3) / 2, cols))
    assert_allclose(cam.project(points), np.column_stack([middle, rows]), atol=1e-9)
    assert_allclose(rows, 50.0 + 0.3 * (middle - 100.0), atol=1e-9)
    # the direct view's border cuts the segment like a pixel boundary
    cols, _, _, _, coverage = column_hits(seg[None], np.eye(4), cam, (40, 45))
    assert_allclose(cols, np.arange(40, 45))
    assert_allclose(coverage, 1.0, atol=EXACT_COVERAGE)


def test_segments_sharing_a_column_add_up_to_a_full_stripe():
    """Two pieces of one straight section meeting at u = 45.3: column 45 gets two samples
    whose coverages sum to 1 and whose coverage-weighted row is the row at its centre. A
    segment along a line of sight (no extent in u) and one ending on a pixel boundary add
    nothing."""
    cam = _camera()
    line = _segment_at(cam, [37.6, 45.3, 50.5])
    edge_on = np.array([[0.0, 0.0, 100.0], [0.0, 1.0, 120.0]])  # both ends at u = 100
    segments = np.stack([line[[0, 1]], line[[1, 2]], edge_on])
    cols, rows, points, segment, coverage = column_hits(segments, np.eye(4), cam, (0, 200))
    assert not np.any(segment == 2)
    assert np.bincount(cols)[45] == 2 and np.bincount(cols)[50] == 1  # u = 50.5: no column 51
    full = np.bincount(cols, coverage, minlength=52)[38:51]
    assert_allclose(full, [0.9] + [1.0] * 12, atol=EXACT_COVERAGE)
    shared = cols == 45
    assert_allclose(coverage[shared], [0.8, 0.2], atol=EXACT_COVERAGE)
    weighted_row = np.sum(coverage[shared] * rows[shared]) / np.sum(coverage[shared])
    assert_allclose(weighted_row, 50.0 + 0.3 * (45.0 - 100.0), atol=1e-9)


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
