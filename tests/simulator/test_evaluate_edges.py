"""Edge accuracy against the CAD's sharp edges: analytic cases, then the edges of a simulated
pass of the demo part (paper section II; target: 30 um RMS, under 5 % beyond 0.5 mm)."""
import numpy as np
import pytest
import trimesh
from numpy.testing import assert_allclose

import scanner_core.pipeline.accumulate as pipeline_accumulate
from scanner_core.edges import EdgeKind
from scanner_core.geometry import apply_transform, base_to_tcp
from scanner_core.pipeline import PipelineParams, process_frame
from simulator.evaluate import edge_accuracy, sharp_edges
from simulator.parts import part_from_mesh
from scanner_core.pipeline import camera_frames
from simulator.session import parse_misplacement, run_simulated_scan, simulated_cell

#: Float round-off of the distances, um.
EXACT_UM = 1e-6
#: Edge figures of the demo part's pass below (measured: drop-outs 16 um RMS, steps 27 um,
#: all 20 um, no outliers; the issue's target is 30 um). The simulator lights each pixel
#: column in proportion to the part of it the stripe covers, so a stripe ending inside a
#: column leaves it partly lit and half the relative step finds the end to about 0.1 px
#: (when each column was sampled at one point, the stripe stopped at full intensity between
#: two columns: 44 um and 49 um, the +-0.5 px of a column's uniform error). A step whose wall
#: lies in a column holding both sides' stripes (a double) is put at that column's centre,
#: within 0.27 px.
EDGE_RMS_UM, DROPOUT_RMS_UM, STEP_RMS_UM = 30.0, 30.0, 40.0
#: The issue's outlier target is 5 %; the demo part has none.
MAX_OUTLIER_FRACTION = 0.01


@pytest.fixture(scope="module")
def box():
    mesh = trimesh.creation.box(extents=(60.0, 40.0, 20.0))
    mesh.apply_translation((0.0, 0.0, 10.0))  # z in [0, 20], as a part hanging along +z_T
    return mesh


def test_sharp_edges_of_a_box_and_of_an_open_sheet(box):
    segments = sharp_edges(box)
    assert segments.shape == (12, 2, 3)  # the face diagonals are coplanar: not sharp
    lengths = np.sort(np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1))
    assert_allclose(lengths, [20.0] * 4 + [40.0] * 4 + [60.0] * 4)
    sheet = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    assert sharp_edges(sheet).shape == (4, 2, 3)  # its boundary, not its diagonal


@pytest.mark.parametrize("turned", [False, True])
def test_a_dropout_at_a_rounded_rim_is_measured_to_the_outline(turned):
    """A cylinder lying along y_T has no sharp edge along its sides: the stripe across it
    ends where the surface turns away from the sensor, at x_T = +-r. A drop-out there is on
    the outline; the same point as a step, or a point 0.2 mm outside, is measured as before
    (to the end caps' edges, 10 mm away, and 0.2 mm off the outline). Turned, the rod lies
    otherwise in {P} and the grasp turns it back: the outline is taken in {T}."""
    radius = 8.0
    rod = trimesh.creation.cylinder(radius=radius, height=20.0, sections=256)
    rod.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    grasp = np.eye(4)
    if turned:
        turn = trimesh.transformations.rotation_matrix(np.radians(70.0), [1.0, 1.0, 1.0])
        rod.apply_transform(turn)
        grasp = np.linalg.inv(turn)
    grasp[2, 3] += radius                      # the rod's top at z_T = 2 r
    # the outline runs along the vertices at x_T = +-r
    points = np.array([[radius, 0.0, radius], [radius + 0.2, 2.0, radius],
                       [-radius, 0.0, radius]])
    dropouts = edge_accuracy(points, rod, grasp, kinds=[0, 0, 1])
    assert dropouts["outline_edges"] >= 2 and dropouts["dropouts_off_sharp_edges"] == 2
    assert_allclose(dropouts["by_kind"]["dropout"]["rms_um"], np.sqrt((0 + 200.0**2) / 2),
                    atol=1e-3)
    assert_allclose(dropouts["by_kind"]["step"]["rms_um"], 10000.0, rtol=1e-6)
    sharp_only = edge_accuracy(points[:1], rod, grasp, kinds=[1])
    assert sharp_only["rms_um"] > 9000.0


def test_distances_are_measured_across_z_t(box):
    """Points beside the outline, on a wall at half height, and in the middle of a face."""
    grasp = np.eye(4)
    points = np.array([
        [30.03, 5.0, 20.0],  # 30 um outside the wall x = 30, at the underside
        [-30.0, -20.04, 20.0],  # 40 um beside a corner's vertical edge
        [10.0, -19.95, 15.0],  # 50 um inside, 5 mm up the wall: a step's half-height point
        [30.0, 0.0, 10.0],  # on the wall at half height: on its top and bottom edges' line
        [0.0, 0.0, 20.0],  # the middle of the underside: 20 mm from any edge, an outlier
    ])
    acc = edge_accuracy(points, box, grasp, kinds=[0, 0, 1, 1, 0])
    xy_um = np.array([30.0, 40.0, 50.0, 0.0, 20000.0])
    assert acc["count"] == 5 and acc["sharp_edges"] == 12
    assert_allclose(acc["rms_um"], np.sqrt(np.mean(xy_um**2)), rtol=1e-9)
    assert_allclose(acc["outlier_fraction"], 0.2)
    assert_allclose(acc["rms_inliers_um"], np.sqrt(np.mean(xy_um[:4] ** 2)), rtol=1e-9)
    d3_um = np.array([30.0, 40.0, np.hypot(50.0, 5000.0), 10000.0, 20000.0])
    assert_allclose(acc["rms_3d_um"], np.sqrt(np.mean(d3_um**2)), rtol=1e-9)
    assert acc["by_kind"]["dropout"]["count"] == 3 and acc["by_kind"]["step"]["count"] == 2
    assert_allclose(acc["by_kind"]["step"]["rms_um"], np.sqrt(np.mean([50.0**2, 0.0])), rtol=1e-9)
    # the same part and points moved by a grasp give the same figures
    grasp = parse_misplacement("3,-2,1,0,0,25")
    moved = edge_accuracy(apply_transform(grasp, points), box, grasp)
    for key in ("rms_um", "p99_um", "outlier_fraction", "rms_3d_um"):
        assert_allclose(moved[key], acc[key], rtol=1e-6, atol=EXACT_UM)


def test_a_step_on_a_leaning_wall_is_measured_across_the_wall(box):
    """Turned 10 degrees about y_T, the wall x = 30 leans: its half-height point lies
    10 tan(10 deg) = 1.76 mm off the (x_T, y_T) line of its top and bottom edges, by design
    (paper section II places a step there); across the wall it is off by its own error."""
    grasp = parse_misplacement("0,0,0,0,10,0")
    wall_point_p = np.array([[30.0 + 0.04, 5.0, 10.0]])  # 40 um out of the wall, half way up
    point_t = apply_transform(grasp, wall_point_p)
    as_dropout = edge_accuracy(point_t, box, grasp, kinds=[EdgeKind.DROPOUT])
    as_step = edge_accuracy(point_t, box, grasp, kinds=[EdgeKind.STEP])
    assert as_dropout["rms_um"] > 1000.0 * 10.0 * np.tan(np.radians(10.0)) - 100.0
    assert_allclose(as_step["rms_um"], 40.0, rtol=1e-6)
    # a point beyond the wall's reach (30 mm below its edge, in its plane) is no step of it
    far_p = np.array([[30.0, 5.0, -30.0]])
    far = edge_accuracy(apply_transform(grasp, far_p), box, grasp, kinds=[EdgeKind.STEP])
    assert far["rms_um"] > 1000.0


def test_no_points_and_bad_kinds(box):
    assert edge_accuracy(np.zeros((0, 3)), box, np.eye(4))["count"] == 0
    with pytest.raises(ValueError, match="`kinds`"):
        edge_accuracy(np.zeros((2, 3)), box, np.eye(4), kinds=[0])


# ---------------------------------------------------------------------------------------------
# End to end: the edges of real simulated frames


@pytest.fixture(scope="module")
def demo_pass_edges(block_part, cell):
    """Edge points of one pass of the demo part (misplaced and turned), placed in {T} by the
    marker and the robot's rotation as the accumulator places profiles."""
    misplacement = parse_misplacement("1.5,-2,0.5,2,-3,5")
    sim = simulated_cell(block_part, cell, misplacement=misplacement, seed=3)
    sim.camera.open()
    cal, params, rotation = cell.calibration, PipelineParams(), cell.gripper_rotation_b
    points, kinds = [], []
    for frame in camera_frames(sim.camera):
        profile = process_frame(frame, cal, params)  # the pipeline's own edges
        edges, marker = profile.edges, profile.marker
        if len(edges) and marker.valid:
            tcp = marker.position_b - rotation @ cal.marker_offset_t
            points.append(base_to_tcp(edges.point_b, tcp, rotation))
            kinds.append(edges.kind)
    sim.camera.close()
    return np.concatenate(points), np.concatenate(kinds), sim.true_grasp


def test_demo_part_edges_lie_on_the_cad_edges(demo_pass_edges, block_part):
    points, kinds, true_grasp = demo_pass_edges
    acc = edge_accuracy(points, block_part.mesh, true_grasp, kinds=kinds)
    dropout, step = acc["by_kind"]["dropout"], acc["by_kind"]["step"]
    # the outline, both holes' rims and the blind hole's and the step's walls
    assert dropout["count"] >= 60 and step["count"] >= 20
    assert acc["outlier_fraction"] <= MAX_OUTLIER_FRACTION
    assert acc["rms_um"] < EDGE_RMS_UM
    assert dropout["rms_um"] < DROPOUT_RMS_UM
    assert step["rms_um"] < STEP_RMS_UM
    # a step's point lies half way up its wall: 2.5 mm (the step) or 5 mm (the blind hole)
    # from the wall's edges in 3-D
    assert step["rms_3d_um"] > 2000.0
    assert np.all(np.isin(kinds, [EdgeKind.DROPOUT, EdgeKind.STEP]))


@pytest.mark.parametrize("misplacement", ["1.5,-2,0.5,2,-3,5", "-1,1,0,-1,2,-4"])
def test_steps_lie_on_their_walls_where_the_sheet_leans_from_them(block_part, misplacement):
    """In a cell whose light sheet leans from the part's walls (``--perturb-seed 1``), a step
    whose wall the camera does not see is moved up its wall along z_T, not along the sheet's
    range axis, which leans off the wall: the demo part's steps 12-14 um RMS there (as in
    the reference cell), against 24-26 um moved along the range axis."""
    from simulator.cell import load_cell

    truth = parse_misplacement(misplacement)
    scan, _ = run_simulated_scan(block_part, load_cell(perturb_seed=1), misplacement=truth,
                                 seed=3, pose=False, evaluate=False)
    acc = edge_accuracy(scan.edges, block_part.mesh, truth @ block_part.grasp,
                        kinds=scan.edge_kind)
    step = acc["by_kind"]["step"]
    assert step["count"] >= 30 and step["outlier_fraction"] == 0.0
    assert step["rms_um"] < 18.0


def chamfered_box(extents=(40.0, 30.0, 12.0), chamfer_mm=0.2) -> trimesh.Trimesh:
    """A box whose every edge is chamfered at 45 degrees, ``chamfer_mm`` on each face (the
    hull of three boxes, each short of the full size by twice that along two axes):
    ADIS16480's outline, narrower than a pixel's footprint in the reference cell."""
    ext = np.asarray(extents, dtype=np.float64)
    corners = []
    for axis in range(3):
        size = ext - 2.0 * chamfer_mm
        size[axis] = ext[axis]
        corners.append(trimesh.creation.box(extents=size).vertices)
    mesh = trimesh.convex.convex_hull(np.concatenate(corners))
    mesh.apply_translation((0.0, 0.0, ext[2] / 2.0))
    return mesh


def scan_chamfered_box(cell):
    """One pass of the chamfered box, misplaced and turned: its part, scan and true grasp."""
    part = part_from_mesh(chamfered_box(), name="chamfered box")
    scan, report = run_simulated_scan(part, cell, misplacement=parse_misplacement(
        "1,-1.5,0.5,1,-2,7"), seed=5, evaluate=False, pose=False)
    return part, scan, np.asarray(report["ground_truth"]["grasp"])


def dropout_accuracy(part, scan, grasp) -> dict:
    return edge_accuracy(scan.edges[scan.edge_kind == EdgeKind.DROPOUT], part.mesh, grasp)


def test_a_chamfered_outline_is_placed_at_the_outline(cell, monkeypatch):
    """A 0.2 mm chamfer (1.25 px) along the underside's outline: its drop-outs lie on the
    outline within the edge target (``scanner_core.edges.chamfered_dropouts``); placed by
    half the face's level alone, they fall on the chamfer, about 0.4 px (65 um) inside."""
    acc = dropout_accuracy(*scan_chamfered_box(cell))
    assert acc["count"] >= 20
    assert acc["outlier_fraction"] == 0.0
    assert acc["rms_um"] < EDGE_RMS_UM
    monkeypatch.setattr(pipeline_accumulate, "chamfered_dropouts", lambda points, *args: (
        np.asarray(points, np.float64), np.full(len(points), np.nan)))
    unmoved = dropout_accuracy(*scan_chamfered_box(cell))
    assert unmoved["count"] == acc["count"]
    assert unmoved["rms_um"] > 1.5 * acc["rms_um"]
