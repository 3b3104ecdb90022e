"""Faults the simulated gripper can hold (``simulator.faults``): each mesh is what it says, and
a scan of one is caught by the inspection and not acted on, where the good part's is."""
import numpy as np
import pytest
import trimesh

from clients.ply import parse_ply
from flyscan import main
from scanner_core.pipeline.finish import inspect_pass
from simulator.cell import load_cell
from simulator.faults import FAULT_KINDS, faulty_mesh, parse_fault
from simulator.parts import part_from_mesh
from simulator.procedural import block_with_holes_and_steps
from simulator.session import misplacement_matrix, run_simulated_scan

TOWARD = np.array([0.0, 0.0, 1.0])  # the demo block's face toward the sensor: max z


@pytest.fixture(scope="module")
def block():
    return block_with_holes_and_steps()


def test_each_fault_is_what_it_says(block):
    rng = np.random.default_rng(3)
    double = faulty_mesh(block, "double", 0.0, TOWARD, rng)
    assert len(double.faces) == 2 * len(block.faces)
    assert np.ptp(double.vertices, axis=0).max() > 1.5 * np.ptp(block.vertices, axis=0).max()
    debris = faulty_mesh(block, "debris", 3.0, TOWARD, rng)
    extra = debris.vertices[len(block.vertices):]
    assert np.ptp(extra, axis=0) == pytest.approx([3.0, 3.0, 3.0], rel=0.1)
    chip = faulty_mesh(block, "chip", 2.0, TOWARD, rng)
    assert chip.is_watertight and 0.0 < block.volume - chip.volume < 4 / 3 * np.pi * 2.0**3
    variant = faulty_mesh(block, "variant", 2.0, TOWARD, rng)
    assert np.ptp(variant.vertices[:, 0]) == pytest.approx(np.ptp(block.vertices[:, 0]) + 2.0)
    hole = faulty_mesh(block, "hole", 4.0, TOWARD, rng)
    assert hole.is_watertight
    # through the part, square to a face the sensor sees: the cylinder's volume taken away
    assert block.volume - hole.volume == pytest.approx(
        np.pi * 2.0**2 * np.ptp(block.vertices @ TOWARD), rel=0.6)
    bend = faulty_mesh(block, "bend", 0.3, TOWARD, rng)
    moved = (bend.vertices - block.vertices) @ TOWARD
    assert moved.max() == pytest.approx(0.3) and moved.min() == pytest.approx(0.0, abs=1e-9)
    assert parse_fault("chip:1.5") == ("chip", 1.5) and parse_fault("double")[0] == "double"
    for bad in ("dent:2", "chip:big", "bend:-1"):
        with pytest.raises(ValueError):
            parse_fault(bad)
    assert set(FAULT_KINDS) == {"double", "debris", "chip", "variant", "hole", "bend"}


@pytest.mark.parametrize("kind, size", [("double", 0.0), ("variant", 2.0), ("hole", 5.0),
                                        ("bend", 0.3)])
def test_a_faulty_pick_is_caught_and_not_acted_on(block, kind, size):
    part = part_from_mesh(block, name="block")
    cell = load_cell()
    misplace = misplacement_matrix([0.8, -0.5, 0.3, 1.0, -0.5, 2.0])
    _, good = run_simulated_scan(part, cell, misplacement=misplace, seed=1, evaluate=False)
    assert good["inspection"]["conforms"] and good["pose"]["act"], good["inspection"]
    held = part_from_mesh(faulty_mesh(block, kind, size, TOWARD, np.random.default_rng(1)),
                          name="held", grasp=part.grasp)
    scan, bad = run_simulated_scan(part, cell, misplacement=misplace, seed=1, evaluate=False,
                                   held=held)
    assert not bad["inspection"]["conforms"], bad["inspection"]
    # the check asked again of the pass's scan (as ``bench inspect --timing`` does) answers
    # as the pass did
    again = inspect_pass(scan, part, np.asarray(bad["pose"]["matrix"]))
    np.testing.assert_array_equal(again.deviations_mm, scan.deviations_mm)
    assert again.to_dict()["failing"] == bad["inspection"]["failing"]
    assert bad["pose"]["act"] is False
    assert any(r.startswith("inspection: ") for r in bad["pose"]["act_reasons"])
    if kind == "hole":  # a hole through the part: no point where the scan should see one
        assert any(r["evidence"] == "no points" for r in bad["inspection"]["regions"])


def test_the_command_line_puts_a_fault_or_a_mesh_into_the_gripper(tmp_path, block, capsys):
    out = tmp_path / "debris"
    assert main(["scan", "--demo", "--fault", "double", "--no-eval", "--out", str(out)]) == 0
    cloud = parse_ply((out / "cloud.ply").read_bytes())
    deviation = np.asarray(cloud["deviation"])
    assert len(deviation) == len(cloud["x"]) and np.nanmax(deviation) > 5.0  # the second part
    held = tmp_path / "held.stl"
    faulty_mesh(block, "variant", 3.0, TOWARD, np.random.default_rng(0)).export(held)
    out = tmp_path / "held"
    assert main(["scan", "--demo", "--held", str(held), "--no-eval", "--out", str(out)]) == 0
    import json

    report = json.loads((out / "report.json").read_text())
    assert report["inspection"]["conforms"] is False and report["pose"]["act"] is False
    assert report["ground_truth"]["held"]["source"] == str(held)
    capsys.readouterr()
    assert main(["scan", "--demo", "--fault", "dent", "--out", str(tmp_path / "x")]) == 2
    assert "unknown fault 'dent'" in capsys.readouterr().err
    assert main(["scan", "--demo", "--fault", "double", "--held", str(held),
                 "--out", str(tmp_path / "y")]) == 2


def test_a_good_part_tilted_out_of_the_scanners_volume_is_no_fault():
    """A fan disk (radius 45 mm) held tilted 15 degrees about x_T and 7 about y_T lifts its
    rim more than 10 mm above the gripper's plane, beyond the inspection volume and its
    margin, where the geometric window does not look for the stripe: the rim is cut from
    the scan there, and the check does not call it missing material (it did before the scan
    carried its measured box)."""
    import dataclasses

    from simulator.procedural import fan_disk

    disk = fan_disk()
    part = part_from_mesh(disk, name="fan_disk")
    misplace = misplacement_matrix([3.2, 1.7, -0.8, -14.7, -7.3, 5.4])
    scan, report = run_simulated_scan(part, load_cell(), misplacement=misplace, seed=2,
                                      evaluate=False)
    box = scan.measured_box_t
    truth = misplace @ part.grasp
    lifted = (disk.vertices @ truth[:3, :3].T + truth[:3, 3])[:, 2].min()
    assert box is not None and lifted < box[0, 2] - 5.0
    # the rim is cut near the box (the window's rows reach a little past it)
    assert scan.cloud[:, 2].min() > lifted + 3.0
    assert report["inspection"]["conforms"], report["inspection"]
    unbounded = dataclasses.replace(scan, measured_box_t=None)
    again = inspect_pass(unbounded, part, np.asarray(report["pose"]["matrix"]))
    assert "missing_material" in again.failing
