"""Edges at soft creases and on walls, end to end against the truth: a faceted dome's
drop-outs where the stripe leaves the camera's view or the light at a soft crease, set aside
as turned away; a leaning wall's steps; the report's counts per edge kind."""
import numpy as np
import pytest

from scanner_core.edges import EdgeKind
from scanner_core.pipeline import PipelineParams, camera_frames, run_pass
from scanner_core.pipeline.report import scan_report
from simulator.evaluate import DROPOUT_CAUSES, dropout_causes, edge_distances, edge_kind_accuracy
from simulator.parts import bracket_with_two_holes, faceted_dome, part_from_mesh
from simulator.session import misplacement_matrix, run_simulated_scan, simulated_cell

#: The target for edge points: RMS to the true edges (inliers, as bench pose scores)
#: and the share farther than FALSE_MM from every true edge.
TARGET_RMS_UM, TARGET_FALSE, FALSE_MM = 30.0, 0.05, 0.5


def scan_with_truth(part, cell, misplacement=None, seed=0):
    """A pass as ``run_simulated_scan`` makes it, its devices kept for the frames' truth."""
    sim = simulated_cell(part, cell, misplacement=misplacement, seed=seed)
    sim.camera.open()
    sim.robot.connect()
    try:
        scan = run_pass(camera_frames(sim.camera), cell.calibration, sim.robot, PipelineParams())
    finally:
        sim.camera.close()
        sim.robot.disconnect()
    return scan, sim


@pytest.fixture(scope="module")
def dome(cell):
    part = part_from_mesh(faceted_dome(), name="faceted dome")
    return (part, *scan_with_truth(part, cell))


@pytest.fixture(scope="module")
def dome_on_plinth(cell):
    part = part_from_mesh(faceted_dome(plinth_radius=40.0), name="faceted dome on a plinth")
    scan, report = run_simulated_scan(part, cell, seed=0, pose=False, evaluate=False)
    return part, scan, np.asarray(report["ground_truth"]["grasp"]), report


def test_a_creased_domes_false_dropouts_are_set_aside(dome, cell):
    """The dome's tiers meet at 18-20 degrees, its steepest (78 degrees) lit at 82-83 degrees
    on its sides and turned from the camera on the far one. Measured: 13 of 38 edge points
    farther than 0.5 mm from every true edge before the turned-away test (all 10 drop-outs
    among them ended where the surface went on, faint or unseen; 3 steps on that steep tier);
    with it, every one of them is set aside. The dome's rim lies on its steep tier too: the
    model-free edge cloud keeps no point on it (none to vouch for)."""
    part, scan, sim = dome
    acc = edge_kind_accuracy(scan, part.mesh, sim.true_grasp, outlier_mm=FALSE_MM)
    before = acc["without_turned_away"]
    assert before["count"] >= 30 and before["outlier_fraction"] > 0.2
    kept = acc["edges"]
    assert kept["count"] == 0 or kept["outlier_fraction"] < TARGET_FALSE
    turned = scan.edges_aside.kind == EdgeKind.TURNED_AWAY
    assert turned.sum() >= 30
    # by the truth: the false drop-outs ended where the surface went on, out of view or light
    aside = scan.edges_aside
    points = aside.points[turned & (aside.found == EdgeKind.DROPOUT)]
    frames = aside.frame_ids[turned & (aside.found == EdgeKind.DROPOUT)]
    d_xy, _, _ = edge_distances(points, part.mesh, sim.true_grasp,
                                kinds=np.full(len(points), EdgeKind.DROPOUT))
    false = d_xy > FALSE_MM
    assert false.sum() >= 8
    causes = dropout_causes(points[false], frames[false], scan.cloud, scan.frame_ids, part.mesh,
                            sim.camera.truths, cell.gripper_rotation_b, cell)
    assert set(causes) <= {"faint", "unseen"} and set(causes) <= set(DROPOUT_CAUSES)


def test_a_dome_on_a_plinth_meets_the_edge_target(dome_on_plinth):
    """Standing on a wider plinth, the dome's steepest tier meets a level face at a sharp
    crease, 0.85 mm in from the crease where its stripe is lost: drop-outs there lie within
    0.5 mm of a true edge but far off it. Measured: 151 points at 39 um RMS (inliers), 2.6 %
    false before the turned-away test; 132 at 16.5 um, none false, with it."""
    part, scan, grasp, _ = dome_on_plinth
    acc = edge_kind_accuracy(scan, part.mesh, grasp, outlier_mm=FALSE_MM)
    before, kept = acc["without_turned_away"], acc["edges"]
    assert before["rms_inliers_um"] > TARGET_RMS_UM
    assert kept["count"] >= 100  # the plinth's rim, the dome's foot
    assert kept["rms_inliers_um"] <= TARGET_RMS_UM and kept["outlier_fraction"] < TARGET_FALSE


def test_the_report_counts_edge_points_per_kind(dome_on_plinth):
    part, scan, _, report = dome_on_plinth
    counts = report["edge_kinds"]
    assert counts == scan_report(scan)["edge_kinds"]
    assert counts["dropout"] + counts["step"] == report["edge_points"] == len(scan.edges)
    aside = scan.edges_aside
    assert counts["turned_away"] == int((aside.kind == EdgeKind.TURNED_AWAY).sum()) > 0
    assert counts["occluded"] == report["edges_occluded"]
    assert counts["grazing"] == report["edges_grazing"]
    assert sum(counts.values()) == len(scan.edges) + len(aside)


def test_steps_at_a_wall_leaning_under_its_top_edge(cell):
    """The bracket turned 6 degrees about y_T: its 5 mm step's wall leans under its top edge,
    and the column beyond the near side holds both sides' stripes, measured on the far side's
    (``scanner_core.edges.DOUBLE_SHARE``). Measured: steps 24 um RMS (76 um when that
    column's share of the near side was taken as none)."""
    part = part_from_mesh(bracket_with_two_holes(), name="bracket")
    scan, report = run_simulated_scan(part, cell, seed=1, pose=False, evaluate=False,
                                      misplacement=misplacement_matrix([0, 0, 0, 0, -6, 0]))
    acc = edge_kind_accuracy(scan, part.mesh, np.asarray(report["ground_truth"]["grasp"]))
    steps = acc["edges"]["by_kind"]["step"]
    assert steps["count"] >= 25
    assert steps["rms_um"] <= TARGET_RMS_UM and steps["outlier_fraction"] == 0.0


def test_a_steps_point_keeps_its_placement_through_a_real_lens():
    """A bracket's 5 mm step scanned in a cell whose camera has a real lens's distortion: the
    step's points keep the kernel's placement (half the step back along the range) and move
    only by what the lens bends their pixel's ray; re-triangulated from the pixel outright,
    they lay 55 um off (RMS; the drop-outs 18 um). Scored against the CAD's edges."""
    from simulator.cell import cell_with_effects

    part = part_from_mesh(bracket_with_two_holes(), name="bracket")
    lens_cell = cell_with_effects(31, "lens")
    assert lens_cell.calibration.camera.distorted
    scan, sim = scan_with_truth(part, lens_cell)
    accuracy = edge_kind_accuracy(scan, part.mesh, sim.true_grasp, outlier_mm=FALSE_MM)
    by_kind = accuracy["edges"]["by_kind"]
    assert by_kind["step"]["count"] >= 25
    assert by_kind["step"]["rms_inliers_um"] < 35.0
    assert by_kind["dropout"]["rms_inliers_um"] < TARGET_RMS_UM
