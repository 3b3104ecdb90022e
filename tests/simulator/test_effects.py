"""The realistic cell's effects: each does what it says, and only when switched on."""
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from simulator.cell import load_cell
from simulator.devices import SimClock, SimRobot
from simulator.effects import (BLUR_SAMPLES, EFFECTS, REAL_LENS_DISTORTION, CellEffects,
                               parse_effects, realistic_cell)
from simulator.motion import PassMotion
from simulator.render import PartScene, column_hits
from simulator.section import _column_hits_through_lens
from simulator.parts import part_from_mesh

SEGMENTS = np.array([[[-60, 0, 40], [50, 0, 80]], [[50, 0, 80], [70, 0, 60]]], float)


def test_through_an_ideal_lens_the_lens_path_is_the_pinhole_path():
    cam = load_cell().calibration.camera
    exact = column_hits(SEGMENTS, np.eye(4), cam, (384, 1536))
    pieces = _column_hits_through_lens(SEGMENTS, np.eye(4), cam, (384, 1536))
    np.testing.assert_array_equal(exact[0], pieces[0])
    np.testing.assert_allclose(exact[1], pieces[1], atol=1e-9)
    np.testing.assert_allclose(exact[2], pieces[2], atol=1e-4)
    np.testing.assert_allclose(exact[4], pieces[4], atol=1e-9)


def test_through_a_real_lens_each_sample_projects_where_it_is_drawn():
    cam = replace(load_cell().calibration.camera, distortion=REAL_LENS_DISTORTION)
    cols, rows, points, _, coverage = column_hits(SEGMENTS, np.eye(4), cam, (384, 1536))
    px = cam.project(points)
    full = coverage > 0.999  # partial columns sit at the middle of their overlap
    np.testing.assert_allclose(px[full, 0], cols[full], atol=1e-3)
    np.testing.assert_allclose(px[:, 1], rows, atol=1e-3)
    ideal = column_hits(SEGMENTS, np.eye(4), replace(cam, distortion=(0.0,) * 5), (384, 1536))
    assert np.nanmax(np.abs(np.interp(cols, ideal[0], ideal[1]) - rows)) > 0.3  # it bends (near the centre, little)


def test_the_robot_reports_on_its_own_clock_with_its_errors():
    cell = load_cell()
    motion = PassMotion(cell.pass_profile)
    effects = CellEffects(clock_offset_s=0.0125, clock_drift_ppm=50.0, tcp_rotation_error_deg=0.01)
    clock = SimClock(now=0.5)
    robot = SimRobot(motion, cell.gripper_rotation_b, clock=clock, effects=effects)
    robot.connect()
    t = 0.3
    pose = robot.pose_at(float(effects.robot_time(t)))
    np.testing.assert_allclose(pose.position, motion.tcp_position(t), atol=2e-4)
    angle = np.degrees(Rotation.from_matrix(pose.rotation @ cell.gripper_rotation_b.T).magnitude())
    assert angle == pytest.approx(0.01, rel=1e-3)
    with pytest.raises(LookupError):  # the robot's "now" is the camera's plus the offset
        robot.pose_at(float(effects.robot_time(0.5)) + 0.01)


def test_a_blurred_frame_smears_the_stripe_over_the_exposure():
    import trimesh

    cell = realistic_cell(load_cell(), ("exposure", "led"))
    box = trimesh.creation.box(extents=(40.0, 30.0, 20.0))
    box.apply_transform(trimesh.transformations.rotation_matrix(np.radians(25), [1, 0, 0]))
    part = part_from_mesh(box, name="tilted box")
    scene = PartScene(part, cell)
    # 2 mm of travel over the exposure: the stripe on the tilted faces moves by pixels.
    tcps = np.array([[0.0, y, 50.0] for y in np.linspace(-1.0, 1.0, BLUR_SAMPLES)])
    _, truth = scene.render_blurred(tcps, part.grasp, np.random.default_rng(0))
    single = scene.geometry(tcps[BLUR_SAMPLES // 2], part.grasp)
    # The light collected is the middle instant's (the faces stay in the sheet throughout).
    assert truth.stripe_gain.sum() == pytest.approx(single.stripe_gain.sum(), rel=0.05)
    # Drawn as a band: in every column, no gap between samples wider than the smear's step.
    moved = 0
    for c in np.unique(single.stripe_columns):
        rows = np.sort(truth.stripe_rows[truth.stripe_columns == c])
        if len(single.stripe_rows[single.stripe_columns == c]) == 1 and np.ptp(rows) > 2.0:
            moved += 1
            assert np.diff(rows).max() <= 0.5 + 1e-9
    assert moved > 100
    # Every point keeps its place in {T}: moved with the gripper to the middle instant.
    from scanner_core.geometry import base_to_tcp
    inside = base_to_tcp(truth.stripe_points_b, truth.tcp_b, cell.gripper_rotation_b)
    grasp_inv = np.linalg.inv(part.grasp)
    local = inside @ grasp_inv[:3, :3].T + grasp_inv[:3, 3]
    assert np.abs(trimesh.proximity.signed_distance(part.mesh, local[::50])).max() < 1e-3
    # The LED is strobed at the exposure's middle: one sharp blob per view, the middle one's.
    middle = scene.geometry(tcps[BLUR_SAMPLES // 2], part.grasp)
    np.testing.assert_array_equal(truth.marker_blobs, middle.marker_blobs)
    # The LED's blob: half its apparent radius, smaller in the (farther) mirror views.
    sigma = scene.marker_sigmas(truth.marker_b)
    distance = np.linalg.norm(truth.marker_b - cell.calibration.camera.origin)
    assert sigma[0] == pytest.approx(0.5 * cell.calibration.camera.fx * 1.5 / distance)
    assert sigma[1] < sigma[0] and sigma[2] < sigma[0]


def test_effects_are_off_in_the_reference_cell_and_named_when_unknown():
    cell = load_cell()
    assert cell.effects == CellEffects() and not cell.calibration.camera.distorted
    assert parse_effects("all") == EFFECTS and parse_effects("none") == ()
    with pytest.raises(ValueError, match="unknown cell effect"):
        parse_effects("lens,fog")
    real = realistic_cell(cell, seed=3)
    assert real.calibration.camera.distorted and real.effects.exposure_blur
    again = realistic_cell(cell, seed=3)  # repeatable
    assert again.effects == real.effects
    assert again.calibration.camera.distortion == real.calibration.camera.distortion
    assert not np.allclose(real.calibration.marker_offset_t, cell.calibration.marker_offset_t)
