"""``flyscan simulate``: the predicted cloud as a PLY other tools open, and bad input refused."""
import json

import numpy as np
import pytest
import trimesh

from scanner_core.io.ply import read_ply
from flyscan import main
from simulator.parts import block_with_holes_and_steps


@pytest.fixture(scope="module")
def block_stl(tmp_path_factory):
    path = tmp_path_factory.mktemp("parts") / "block_cm.stl"
    mesh = block_with_holes_and_steps()
    mesh.apply_scale(0.1)  # written in centimetres
    mesh.export(path)
    return path


def test_simulate_writes_a_ply_with_steps(block_stl, tmp_path, capsys):
    out = tmp_path / "sub" / "predicted.ply"
    code = main(["simulate", "--part", str(block_stl), "--units", "cm", "--step", "0.25",
                 "--rays", "400", "--mirrors", "--out", str(out)])
    assert code == 0
    summary = json.loads(capsys.readouterr().out.splitlines()[0])
    points, fields = read_ply(out)
    assert len(points) == summary["points"] > 10_000
    assert summary["rays_cast"] == 400 * (summary["steps"][1] - summary["steps"][0] + 1)
    assert {"step", "ray", "nx", "ny", "nz", "seen_left", "seen_right"} <= set(fields)
    # In mm, in {T}: the block (60 x 40 x 20 mm) hangs centred below the TCP, seen from below.
    assert np.all(np.abs(points[:, 0]) <= 30.0 + 1e-3) and np.all(np.abs(points[:, 1]) <= 20.0 + 1e-3)
    assert points[:, 2].max() == pytest.approx(20.0, abs=1e-4)
    # y steps by 0.25 mm per step from the pass start (-130 mm).
    np.testing.assert_allclose(points[:, 1], -130.0 + 0.25 * fields["step"], atol=1e-4)
    other = trimesh.load(out)
    np.testing.assert_allclose(np.asarray(other.vertices), points)


def test_misplacement_moves_the_prediction(tmp_path, capsys):
    a, b = tmp_path / "a.ply", tmp_path / "b.ply"
    assert main(["simulate", "--demo", "--rays", "200", "--out", str(a)]) == 0
    assert main(["simulate", "--demo", "--rays", "200", "--misplace", "1.5,0,0,0,0,0",
                 "--out", str(b)]) == 0
    pa, pb = read_ply(a)[0], read_ply(b)[0]
    assert pb[:, 0].max() - pa[:, 0].max() == pytest.approx(1.5, abs=0.01)


@pytest.mark.parametrize("argv, message", [
    (["--step", "0"], "step_mm"),
    (["--step", "-1"], "step_mm"),
    (["--rays", "1"], "rays_per_line"),
    (["--laser", "0,0"], "--laser must be three"),
    (["--camera", "0,0,abc"], "--camera must be three"),
    (["--camera", "0,-130,10"], "camera passes through the part"),
    (["--laser", "0,-130,10"], "light source lies on the part's axis"),
    (["--threads", "0"], "--threads"),
    (["--misplace", "1,2"], "--misplace"),
])
def test_bad_input_is_refused_and_nothing_written(tmp_path, capsys, argv, message):
    out = tmp_path / "p.ply"
    assert main(["simulate", "--demo", "--rays", "50", *argv, "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_a_setup_given_where_it_stands_sweeps_negative_steps(tmp_path, capsys):
    """The demo block (60 x 40 x 20 mm, y in [-20, 20]) held by its CAD origin, the setup
    above it at y = 0: the sweep runs from step -40 to 40 and lights its z = 0 face."""
    out, shifted = tmp_path / "here.ply", tmp_path / "before.ply"
    assert main(["simulate", "--demo", "--grasp", "identity", "--laser", "0,0,-300",
                 "--camera", "0,-175,-300", "--rays", "200", "--out", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out.splitlines()[0])
    assert summary["steps"] == [-40, 40] and summary["rays_cast"] == 81 * 200
    points, fields = read_ply(out)
    header = out.read_bytes().split(b"end_header")[0].decode().splitlines()
    assert "property int step" in header and "comment steps -40 40" in header
    # Every line strictly inside the block lights it (the end lines graze its end faces).
    assert set(range(-39, 40)) <= set(np.unique(fields["step"]).tolist()) <= set(range(-40, 41))
    assert np.count_nonzero(fields["step"] < 0) > 0.4 * len(points)
    # The lit face z = 0, and inside the through hole (radius 4 mm at x = -15) its wall.
    on_face = np.abs(points[:, 2]) < 1e-5
    assert on_face.mean() > 0.99
    assert np.all(np.hypot(points[~on_face, 0] + 15.0, points[~on_face, 1]) <= 4.0 + 1e-4)
    np.testing.assert_allclose(points[:, 1], 0.5 * fields["step"], atol=1e-5)
    # The same planes from a setup 40 steps before: the same points, steps offset by 40.
    assert main(["simulate", "--demo", "--grasp", "identity", "--laser", "0,-20,-300",
                 "--camera", "0,-195,-300", "--rays", "200", "--out", str(shifted)]) == 0
    before, before_fields = read_ply(shifted)
    np.testing.assert_array_equal(before_fields["step"], fields["step"] + 40)
    np.testing.assert_array_equal(before_fields["ray"], fields["ray"])
    np.testing.assert_allclose(before, points, atol=1e-5)


@pytest.mark.parametrize("misplace, message", [
    ("0,0,300,0,0,0", "outside the inspection volume"),
    ("0,0,0,180,0,0", "into the gripper"),
])
def test_a_misplacement_that_takes_the_part_out_of_the_volume_is_refused(
        tmp_path, capsys, misplace, message):
    out = tmp_path / "p.ply"
    assert main(["simulate", "--demo", "--rays", "50", "--misplace", misplace,
                 "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_a_part_outside_the_volume_under_its_grasp_is_refused(tmp_path, capsys):
    box = tmp_path / "far.stl"
    mesh = trimesh.creation.box(extents=(30.0, 30.0, 30.0))
    mesh.apply_translation((0.0, 0.0, 200.0))  # its CAD origin far above it
    mesh.export(box)
    out = tmp_path / "p.ply"
    assert main(["simulate", "--part", str(box), "--units", "mm", "--grasp", "identity",
                 "--out", str(out)]) == 2
    assert "outside the inspection volume" in capsys.readouterr().err
    assert not out.exists()


def test_out_must_be_a_ply_file(tmp_path, capsys):
    assert main(["simulate", "--demo", "--out", str(tmp_path)]) == 2
    assert "--out" in capsys.readouterr().err
    assert main(["simulate", "--demo", "--out", str(tmp_path / "cloud.xyz")]) == 2


def test_part_needs_its_unit(block_stl, tmp_path, capsys):
    assert main(["simulate", "--part", str(block_stl), "--out", str(tmp_path / "p.ply")]) == 2
    assert "--units is required" in capsys.readouterr().err


def test_a_camera_that_sees_nothing_is_an_error(tmp_path, capsys):
    box = tmp_path / "box.stl"
    trimesh.creation.box(extents=(30.0, 30.0, 30.0)).export(box)
    out = tmp_path / "p.ply"
    # Above the box, behind its lit underside.
    assert main(["simulate", "--part", str(box), "--units", "mm", "--camera", "0,95,-300",
                 "--out", str(out)]) == 2
    assert "the camera sees none of the" in capsys.readouterr().err
    assert not out.exists()
