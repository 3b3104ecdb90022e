import json

import numpy as np
import pytest
from numpy.testing import assert_allclose

from scanner_core.geometry import angle_between
from simulator.cell import (REFERENCE_CELL, Cell, design_reference_cell, load_cell, marker_pixels,
                            perturb)
from simulator.motion import PassMotion

#: The marker blob must sit this far inside its strip and the image (3 sigma of 2.5 px).
MARKER_MARGIN_PX = 7.5


def test_settings_file_is_the_design():
    """The committed file holds exactly what the design code chooses."""
    on_disk = json.loads(REFERENCE_CELL.read_text())
    designed = json.loads(json.dumps(design_reference_cell().to_dict()))
    assert _close(on_disk, designed)


def _close(a, b):
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b))
    if isinstance(a, float):
        return abs(a - b) <= 1e-9 * max(1.0, abs(a))
    return a == b


def test_round_trip(cell):
    again = Cell.from_dict(json.loads(json.dumps(cell.to_dict())))
    assert _close(again.to_dict(), cell.to_dict())


def test_reference_geometry_matches_architecture(cell):
    cam = cell.calibration.camera
    assert (cam.width, cam.height) == (1920, 1200)
    # About 0.16 mm per pixel at about 450 mm.
    assert_allclose(np.linalg.norm(cam.origin), 450.0, rtol=1e-9)
    assert 0.15 < 450.0 / cam.fx < 0.17
    # The camera views the sheet at about 30 degrees.
    axis = cam.rotation[2]
    angle = np.degrees(np.arcsin(abs(axis @ cell.light_plane_b.normal)))
    assert_allclose(angle, 30.0, atol=1e-6)


@pytest.mark.parametrize("preset", ["default", "fast", "slow"])
def test_marker_in_all_three_views_through_the_pass(cell, preset):
    from simulator.cell import PASS_PRESETS
    cell = cell.with_pass(speed_mm_s=PASS_PRESETS[preset].speed_mm_s, fps=PASS_PRESETS[preset].fps)
    motion = PassMotion(cell.pass_profile)
    tcp = motion.tcp_position(np.linspace(0, motion.duration_s, 200))
    px = marker_pixels(cell, tcp)
    for view, (c0, c1) in enumerate(cell.calibration.strips):
        assert np.all(px[:, view, 0] >= c0 + MARKER_MARGIN_PX)
        assert np.all(px[:, view, 0] <= c1 - 1 - MARKER_MARGIN_PX)
        assert np.all(px[:, view, 1] >= MARKER_MARGIN_PX)
        assert np.all(px[:, view, 1] <= cell.calibration.camera.height - 1 - MARKER_MARGIN_PX)


def test_perturbation_is_repeatable_and_small(cell):
    a, b, c = perturb(cell, 7), perturb(cell, 7), perturb(cell, 8)
    assert _close(a.to_dict(), b.to_dict())
    assert not _close(a.to_dict(), c.to_dict())
    moved = np.linalg.norm(a.calibration.camera.origin - cell.calibration.camera.origin)
    assert 0.0 < moved < 6.0  # millimetres
    tilt = np.degrees(angle_between(a.light_plane_b.normal, cell.light_plane_b.normal))
    assert 0.0 < tilt < 1.5  # degrees
    assert _close(load_cell(perturb_seed=7).to_dict(), a.to_dict())


def test_a_slower_pass_keeps_the_lead_out_distance_and_the_slow_preset_ends():
    """The marker must leave the views for a pass to end: a slower pass keeps the lead-out's
    distance (the paper's slow pass, 50 mm/s at 16 fps, ended as "camera stream ended")."""
    from simulator.cell import PASS_PRESETS
    from simulator.parts import block_with_holes_and_steps, part_from_mesh
    from simulator.session import run_simulated_scan

    cell = load_cell()
    reach_mm = cell.pass_profile.lead_out_s * cell.pass_profile.speed_mm_s
    slow = PASS_PRESETS["slow"]
    slower = cell.with_pass(speed_mm_s=slow.speed_mm_s, fps=slow.fps)
    assert slower.pass_profile.lead_out_s * slower.pass_profile.speed_mm_s == pytest.approx(reach_mm)
    assert cell.with_pass(speed_mm_s=1000.0).pass_profile.lead_out_s == cell.pass_profile.lead_out_s
    assert cell.with_pass(speed_mm_s=50.0, lead_out_s=0.3).pass_profile.lead_out_s == 0.3
    block = part_from_mesh(block_with_holes_and_steps(), name="block")
    scan, report = run_simulated_scan(block, slower, seed=0, evaluate=False, pose=False)
    assert report["state"] == "done" and report["end_reason"] == "marker gone", report["reason"]
    assert len(scan.cloud) > 1000
