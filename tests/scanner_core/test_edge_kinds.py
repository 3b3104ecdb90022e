"""Edge kinds: the near side's view and light margins on analytic surfaces, the
model's edges and the edge points off them, the counts per kind."""
import numpy as np
import pytest
import trimesh
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation

from scanner_core.edges.kinds import (MODEL_EDGE_TOL_MM, SOFT_CREASE_DEG, STRIPE_LOSS_DEG,
                                      AsideEdges, ModelEdges, kind_counts, model_distances,
                                      reclassify_with_model, sheet_range_b, turned_away)
from scanner_core.edges import EdgeKind
from scanner_core.types import Scan

#: Noise-free planes: the normals' PCA in float32, degrees.
ANGLE_TOL_DEG = 0.01
#: The camera's centre in {T} in the reference cell (450 mm away, 30 degrees from z_T toward
#: +y_T), and the sheet's range axis there (away from the camera: -z_T).
SENSOR_T = np.array([0.0, 225.0, 389.71])
RANGE_T = np.array([0.0, 0.0, -1.0])
#: Profiles 1.2 mm apart (200 mm/s at 162 fps), points 0.16 mm apart along them.
SPACING_MM, PITCH_MM = 1.2, 0.16
#: Float round-off of the distances, mm.
EXACT_MM = 1e-9


def tilted_plane_scan(tilt_deg: float, about: str = "x"):
    """Profiles along x_T (y_T = k * SPACING_MM) on a plane through the origin turned
    `tilt_deg` from level about x_T (positive: its normal toward -y_T, away from the camera)
    or about y_T, ending at x_T = 0: the cloud, its frame ids, and the end of profile 0."""
    normal = Rotation.from_euler(about, tilt_deg if about == "x" else -tilt_deg,
                                 degrees=True).apply([0.0, 0.0, 1.0])
    points, frames = [], []
    for k in range(-3, 4):
        x = np.arange(-40, 1) * PITCH_MM
        y = np.full_like(x, k * SPACING_MM)
        z = -(normal[0] * x + normal[1] * y) / normal[2]
        points.append(np.stack([x, y, z], axis=1))
        frames.append(np.full(len(x), k + 10))
    cloud = np.concatenate(points)
    return cloud, np.concatenate(frames), np.array([[0.0, 0.0, 0.0]])


def judge(cloud, frames, ends, kinds=(EdgeKind.DROPOUT,), sizes=(np.nan,)):
    m = len(ends)
    return turned_away(ends, np.array(kinds, np.uint8), np.array(sizes), np.tile(RANGE_T, (m, 1)),
                       np.tile(SENSOR_T, (m, 1)), cloud, frames, np.full(m, 10),
                       np.tile(SENSOR_T, (len(cloud), 1)))


@pytest.mark.parametrize("tilt, about, view, light, turned", [
    (0.0, "x", 60.0, STRIPE_LOSS_DEG, False),          # level: seen at 30 degrees off its normal
    (35.0, "x", 25.0, STRIPE_LOSS_DEG - 35.0, True),   # turned from the camera: view margin
    (-40.0, "x", 80.0, STRIPE_LOSS_DEG - 40.0, False),  # toward the camera, lit at 40
    (-60.0, "x", 60.0, STRIPE_LOSS_DEG - 60.0, True),  # toward the camera, lit at 60: light
    (45.0, "y", None, STRIPE_LOSS_DEG - 45.0, False),
])
def test_the_near_sides_margins(tilt, about, view, light, turned):
    """A drop-out at the end of a profile on a plane: the angle between the camera's line of
    sight and the plane, and the sheet's incidence on it taken from the stripe's loss: under
    a soft crease (30 degrees) either one, and the surface may go on unseen beyond."""
    cloud, frames, end = tilted_plane_scan(tilt, about)
    flags, view_margin, light_margin = judge(cloud, frames, end)
    if view is None:  # about y_T: the camera sees it at acos(cos 30 cos 45) from its normal
        view = 90.0 - np.degrees(np.arccos(np.cos(np.radians(30.0)) * np.cos(np.radians(tilt))))
    assert_allclose(view_margin, [view], atol=ANGLE_TOL_DEG)
    assert_allclose(light_margin, [light], atol=ANGLE_TOL_DEG)
    assert flags.tolist() == [turned]
    assert (min(view, light) < SOFT_CREASE_DEG) == turned


def test_a_step_is_judged_at_its_near_side():
    """A step's point lies half its height beyond its near side's end, along the range axis:
    found there, its surface is judged as a drop-out's; taken where the point lies, no point of
    its profile is near enough to say anything (kept)."""
    cloud, frames, end = tilted_plane_scan(35.0)
    step = end + 2.5 * RANGE_T  # a 5 mm step's half-height point, off the surface
    flags, view, _ = judge(cloud, frames, step, kinds=(EdgeKind.STEP,), sizes=(5.0,))
    assert flags.tolist() == [True]
    assert_allclose(view, [25.0], atol=ANGLE_TOL_DEG)
    flags, view, light = judge(cloud, frames, step, kinds=(EdgeKind.DROPOUT,), sizes=(5.0,))
    assert flags.tolist() == [False] and np.isnan(view[0]) and np.isnan(light[0])


def test_turned_away_checks_its_arguments():
    cloud, frames, end = tilted_plane_scan(0.0)
    with pytest.raises(ValueError, match="range_t"):
        turned_away(end, [0], [np.nan], RANGE_T[None, :2], SENSOR_T[None], cloud, frames, [10],
                    np.tile(SENSOR_T, (len(cloud), 1)))
    empty = turned_away(np.zeros((0, 3)), [], [], np.zeros((0, 3)), np.zeros((0, 3)), cloud,
                        frames, [], np.tile(SENSOR_T, (len(cloud), 1)))
    assert empty[0].shape == (0,)


def test_the_sheets_range_axis_in_the_reference_cell(cell):
    """Across the stripe, away from the camera: up, z_B, in the reference cell."""
    assert_allclose(sheet_range_b(cell.calibration), [0.0, 0.0, 1.0], atol=1e-12)


# ---------------------------------------------------------------------------------------------
# The model's edges


@pytest.fixture(scope="module")
def box_model():
    box = trimesh.creation.box(extents=(60.0, 40.0, 20.0))
    box.apply_translation((0.0, 0.0, 10.0))
    return ModelEdges.from_mesh(box)


def test_model_edges_of_a_box(box_model):
    segments = box_model.segments_t(np.eye(4))
    assert segments.shape == (12, 2, 3)  # its sharp edges; a face diagonal is none
    points = np.array([[30.05, 5.0, 20.0], [25.0, 5.0, 20.0], [30.0, 0.0, 17.5]])
    kinds = [EdgeKind.DROPOUT, EdgeKind.DROPOUT, EdgeKind.STEP]
    assert_allclose(model_distances(points, kinds, box_model, np.eye(4)), [0.05, 5.0, 0.0],
                    atol=EXACT_MM)
    with pytest.raises(ValueError, match="kinds"):
        model_distances(points, kinds[:2], box_model, np.eye(4))


def test_a_rounded_rim_is_on_the_models_outline():
    """A rod lying along y_T has no sharp edge along its sides: its outline seen from the
    sensor (x_T = +-r) is an edge of the model all the same; turned, it is taken in {T}."""
    radius = 8.0
    rod = trimesh.creation.cylinder(radius=radius, height=20.0, sections=256)
    rod.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    model = ModelEdges.from_mesh(rod)
    pose = np.eye(4)
    pose[2, 3] = radius
    points = np.array([[radius, 0.0, radius], [radius - 0.5, 0.0, 2 * radius - 0.02]])
    dropouts = [EdgeKind.DROPOUT] * 2
    assert_allclose(model_distances(points, dropouts, model, pose), [0.0, 0.5], atol=1e-3)
    # a step is measured to the sharp edges only: the end caps' rims, 10 mm away
    assert model_distances(points[:1], [EdgeKind.STEP], model, pose)[0] > 9.0
    turn = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    turned = trimesh.Trimesh(rod.vertices @ turn.T, rod.faces)
    back = pose.copy()
    back[:3, :3] = turn.T
    assert_allclose(model_distances(points, dropouts, ModelEdges.from_mesh(turned), back),
                    [0.0, 0.5], atol=1e-3)


def edge_scan(points, kinds) -> Scan:
    m = len(points)
    scan = Scan(cloud=np.zeros((0, 3), np.float32), frame_ids=np.zeros(0, np.int32),
                quality=np.zeros(0, np.float32), edges=np.asarray(points, np.float32),
                tcp_positions_b=np.zeros((m, 3)), tcp_times=np.arange(m, dtype=float),
                frames=m, frames_dropped=0)
    scan.edge_frame_ids = np.arange(m, dtype=np.int32)
    scan.edge_kind = np.asarray(kinds, np.uint8)
    scan.edge_size_mm = np.where(scan.edge_kind == EdgeKind.STEP, 5.0, np.nan).astype(np.float32)
    scan.edge_quality = np.full(m, 200.0, np.float32)
    scan.edges_aside = AsideEdges(np.array([[0.0, 0.0, 20.0]], np.float32), np.array([7], np.int32),
                                  np.array([EdgeKind.TURNED_AWAY], np.uint8),
                                  np.array([EdgeKind.DROPOUT], np.uint8),
                                  np.array([np.nan], np.float32), np.array([90.0], np.float32))
    return scan


def test_points_off_the_models_edges_go_aside(box_model):
    """Under the registered pose, an edge point farther than MODEL_EDGE_TOL_MM from every
    model edge is set aside as off the model; the others stay, in order; what was set aside
    before stays aside (the point at the box's centre: far from any edge, but not counted
    twice)."""
    pose = np.eye(4)
    pose[:3, 3] = [0.3, -0.2, 0.0]  # the part where the registration put it
    points = np.array([[30.3, 5.0, 20.0],                                  # on an edge
                       [30.3 + 2.0 * MODEL_EDGE_TOL_MM, -5.0, 20.0],       # off it
                       [-29.7 + 0.5 * MODEL_EDGE_TOL_MM, 0.0, 17.5]])      # a step by a wall
    scan = edge_scan(points, [EdgeKind.DROPOUT, EdgeKind.DROPOUT, EdgeKind.STEP])
    assert reclassify_with_model(scan, box_model, pose) == 1
    assert_allclose(scan.edges, points[[0, 2]].astype(np.float32))
    assert scan.edge_kind.tolist() == [EdgeKind.DROPOUT, EdgeKind.STEP]
    assert scan.edge_frame_ids.tolist() == [0, 2] and len(scan.edge_size_mm) == 2
    aside = scan.edges_aside
    assert aside.kind.tolist() == [EdgeKind.TURNED_AWAY, EdgeKind.OFF_MODEL]
    assert aside.found.tolist() == [EdgeKind.DROPOUT, EdgeKind.DROPOUT]
    assert_allclose(aside.points[1], points[1].astype(np.float32))
    counts = kind_counts(scan)
    assert counts == {"dropout": 1, "step": 1, "occluded": 0, "grazing": 0, "turned_away": 1,
                      "off_model": 1}
