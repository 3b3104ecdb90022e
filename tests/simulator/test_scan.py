"""End to end: the simulated cell through the full image pipeline, against the truth."""
import numpy as np
import pytest
from numpy.testing import assert_allclose

from scanner_core.pipeline import PipelineParams
from simulator.cell import PASS_PRESETS, load_cell
from simulator.parts import block_with_holes_and_steps
from simulator.session import parse_misplacement, run_simulated_scan

#: The issue's accuracy targets for the cloud (true calibration, default pass).
RMS_TARGET_UM = 20.0
P99_TARGET_UM = 60.0
#: Marker-derived TCP against the robot's reported TCP.
CROSS_CHECK_TOL_MM = 0.02


@pytest.fixture(scope="module")
def block_scan(block_part):
    cell = load_cell()
    return run_simulated_scan(block_part, cell, seed=11)


def test_block_cloud_on_the_surface(block_scan):
    scan, report = block_scan
    acc = report["ground_truth"]["accuracy"]
    assert acc["points_evaluated"] > 5000
    assert acc["rms_um"] <= RMS_TARGET_UM
    assert acc["p99_um"] <= P99_TARGET_UM
    assert abs(acc["mean_signed_um"]) < 5.0
    assert acc["unmatched_points"] == 0


def test_block_cloud_shows_its_features(block_scan):
    """The underside (z_T = 20), the step (z_T = 15) and the holes where there is no floor."""
    scan, _ = block_scan
    feats = block_with_holes_and_steps().metadata["features"]
    cloud = scan.cloud.astype(np.float64)
    underside = np.abs(cloud[:, 2] - 20.0) < 0.1
    step = np.abs(cloud[:, 2] - 15.0) < 0.1
    assert underside.sum() > 1000 and step.sum() > 200
    assert cloud[step, 0].min() > feats["steps"][0]["x_min"] - 0.1
    for hole in feats["through_holes"] + feats["blind_holes"]:
        r = np.hypot(cloud[:, 0] - hole["xy"][0], cloud[:, 1] - hole["xy"][1])
        assert not np.any(underside & (r < hole["radius"] - 0.2))
    # The blind hole's floor (z_T = 10) is seen through its mouth.
    floor = np.abs(cloud[:, 2] - 10.0) < 0.1
    assert floor.sum() > 10
    assert_allclose(cloud[:, 0].min(), -30.0, atol=0.5)
    assert_allclose(cloud[:, 0].max(), 30.0, atol=0.5)


def test_stitching_follows_the_curved_accelerating_pass(block_scan):
    scan, report = block_scan
    # The robot's newest 500 Hz sample may precede the last frame: at most one is missed.
    assert report["cross_check"]["samples"] >= scan.frames - 1
    assert report["cross_check"]["rms_mm"] < CROSS_CHECK_TOL_MM
    speeds = np.diff(scan.tcp_positions_b[:, 1]) / np.diff(scan.tcp_times)
    assert speeds[-10:].mean() > 1.4 * speeds[:10].mean()  # it did accelerate
    assert np.ptp(scan.tcp_positions_b[:, 0]) > 2.0  # and curved


def test_misplacement_moves_the_cloud(block_part):
    cell = load_cell()
    misplace = parse_misplacement("1.5,-2,0.5,0,0,3")
    scan, report = run_simulated_scan(block_part, cell.with_pass(fps=60.0), misplacement=misplace, seed=2)
    acc = report["ground_truth"]["accuracy"]
    assert acc["rms_um"] <= RMS_TARGET_UM  # scored against the true (misplaced) grasp
    assert_allclose(report["ground_truth"]["grasp"], misplace @ block_part.grasp)
    # The cloud sits where the misplacement says: back through the nominal grasp it is off.
    from simulator.evaluate import cloud_accuracy
    nominal = cloud_accuracy(scan.cloud, scan.frame_ids, block_part.mesh, block_part.grasp)
    assert nominal["rms_um"] > 300.0


def test_perturbed_cell_needs_its_calibration(block_part):
    """With the cell's true geometry the cloud is accurate; with the nominal (unperturbed)
    calibration on a perturbed cell the marker's views disagree and no profile is placed:
    an explicit failure, never a quietly wrong cloud."""
    reference = load_cell()
    perturbed = load_cell(perturb_seed=4).with_pass(fps=60.0)
    _, good = run_simulated_scan(block_part, perturbed, seed=1)
    _, bad = run_simulated_scan(block_part, perturbed, calibration=reference.calibration, seed=1)
    assert good["ground_truth"]["accuracy"]["rms_um"] <= RMS_TARGET_UM
    assert good["marker_residual_px"] < 0.1
    # Frames with two views only (the marker entering or leaving the image) can agree by
    # chance; the rest are refused.
    assert bad["frames"] <= 0.05 * good["frames"]
    assert bad["frames_unplaced"] > 0.9 * good["frames"] and bad["marker_residual_px"] > 1.0


def test_dropped_frames_are_counted(block_part):
    scan, report = run_simulated_scan(block_part, load_cell().with_pass(fps=60.0), seed=5,
                                      drop_rate=0.15)
    assert report["frames_dropped"] > 0
    assert report["frames_dropped"] == scan.frames_dropped
    assert report["ground_truth"]["accuracy"]["rms_um"] <= RMS_TARGET_UM


@pytest.mark.parametrize("method", ["cog", "lsq_gauss", "blais_rioux"])
def test_methods_through_the_pipeline(block_part, method):
    cell = load_cell().with_pass(fps=50.0)
    _, report = run_simulated_scan(block_part, cell, params=PipelineParams(stripe_method=method))
    assert report["ground_truth"]["accuracy"]["rms_um"] <= RMS_TARGET_UM


def test_paper_presets(block_part):
    """1 m/s at 162 fps: a profile every ~6 mm; 50 mm/s at 16 fps: every ~3 mm (paper II, V)."""
    for name, spacing in (("fast", 1000 / 162), ("slow", 50 / 16)):
        p = PASS_PRESETS[name]
        scan, report = run_simulated_scan(block_part, load_cell().with_pass(speed_mm_s=p.speed_mm_s, fps=p.fps))
        steps = np.diff(scan.tcp_positions_b[:, 1])
        assert_allclose(np.median(steps), spacing, rtol=0.3)
        assert report["ground_truth"]["accuracy"]["rms_um"] <= RMS_TARGET_UM


def test_a_part_its_turns_map_onto_itself_is_scored_against_its_nearest_turn():
    """An octagonal prism misplaced 32 degrees about z_T sits as it would 13 degrees the
    other way: the pose is that turn (the nearest the grasp) and the ground truth's error is
    against it, within a few of the pose's sigmas, not 45 degrees off."""
    import trimesh

    from simulator.parts import part_from_mesh

    octagon = part_from_mesh(trimesh.creation.cylinder(radius=18.0, height=10.0, sections=8),
                             name="octagon")
    _, report = run_simulated_scan(octagon, load_cell(),
                                   misplacement=parse_misplacement("1,-0.5,0.3,1,-0.5,32"),
                                   seed=3, evaluate=False)
    pose = report["pose"]
    assert pose["part_symmetry"]["order"] == 16
    assert pose["misplacement"]["rotation_deg"][2] == pytest.approx(32.0 - 45.0, abs=0.1)
    error = report["ground_truth"]["pose_error"]
    assert max(abs(v) for v in error["rotation_mdeg"]) < 100.0
    assert max(error["sigmas"]) < 3.0
