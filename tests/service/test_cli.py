"""The ``flyscan`` command: a real scan to real files, and every bad input refused cleanly."""
import json
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from scanner_core.ply import read_ply
from service.cli import main
from simulator.parts import block_with_holes_and_steps

REPORT_KEYS = {"frames", "frames_dropped", "points", "edge_points", "timings_ms", "pose", "ground_truth"}


@pytest.fixture(scope="module")
def block_stl(tmp_path_factory):
    path = tmp_path_factory.mktemp("parts") / "block_inch.stl"
    mesh = block_with_holes_and_steps()
    mesh.apply_scale(1 / 25.4)  # written in inches, as CAD exports often are
    mesh.export(path)
    return path


def test_scan_writes_the_contract_files(block_stl, tmp_path):
    out = tmp_path / "scan"
    code = main(["scan", "--part", str(block_stl), "--units", "inch", "--fps", "60",
                 "--misplace", "0.5,0,0,0,0,1", "--seed", "3", "--out", str(out)])
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    assert REPORT_KEYS <= report.keys()
    assert report["pose"] is None
    assert report["points"] > 1000 and report["edge_points"] == 0
    assert report["ground_truth"]["accuracy"]["rms_um"] <= 20.0
    points, fields = read_ply(out / "cloud.ply")
    assert points.dtype == np.float32 and points.shape == (report["points"], 3)
    assert set(fields) == {"frame_id", "quality"}
    # Another tool opens the same file and finds the same points, in mm.
    other = trimesh.load(out / "cloud.ply")
    np.testing.assert_allclose(np.asarray(other.vertices), points, atol=1e-6)
    assert np.ptp(points[:, 0]) > 55.0  # the 60 mm block, not 60 inches or 2.4 mm
    edges, _ = read_ply(out / "edges.ply")
    assert edges.shape == (0, 3)


@pytest.mark.parametrize("argv, message", [
    (["--units", "furlong"], "unknown unit"),
    ([], "--units is required"),
    (["--units", "inch", "--speed", "-5"], "--speed must be positive"),
    (["--units", "inch", "--misplace", "1,2,3"], "--misplace must be six"),
    (["--units", "inch", "--method", "magic"], "--method must be one of"),
])
def test_bad_input_is_refused_and_nothing_written(block_stl, tmp_path, capsys, argv, message):
    out = tmp_path / "scan"
    code = main(["scan", "--part", str(block_stl), *argv, "--out", str(out)])
    assert code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("content, suffix, message", [
    (b"", ".stl", "empty"),
    (bytes(range(256)) * 20, ".stl", "cannot read"),
    (None, ".stl", "not found"),
])
def test_broken_files(tmp_path, capsys, content, suffix, message):
    path = tmp_path / f"part{suffix}"
    if content is not None:
        path.write_bytes(content)
    out = tmp_path / "scan"
    code = main(["scan", "--part", str(path), "--units", "mm", "--out", str(out)])
    assert code == 2
    assert message in capsys.readouterr().err.lower()
    assert not out.exists()


def test_too_large_part(tmp_path, capsys):
    path = tmp_path / "slab.stl"
    trimesh.creation.box(extents=(200.0, 50.0, 10.0)).export(path)
    code = main(["scan", "--part", str(path), "--units", "mm", "--out", str(tmp_path / "o")])
    assert code == 2
    assert "inspection volume" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_console_script_exit_code(tmp_path):
    """The installed command, as a user runs it, fails non-zero on a bad unit."""
    exe = [sys.executable, "-m", "service.cli"]
    proc = subprocess.run([*exe, "scan", "--demo", "--units", "parsec", "--out", str(tmp_path / "o")],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "--units applies only to --part" in proc.stderr


def test_wrong_calibration_is_refused(tmp_path, capsys):
    """A calibration that does not fit the (perturbed) cell: a clear error, no files."""
    from scanner_core.calibration import save_calibration
    from simulator.cell import load_cell
    cal_path = tmp_path / "nominal.json"
    save_calibration(cal_path, load_cell().calibration)
    out = tmp_path / "o"
    code = main(["scan", "--demo", "--fps", "40", "--perturb-seed", "4",
                 "--calibration", str(cal_path), "--out", str(out)])
    assert code == 2
    assert "does the calibration fit the cell?" in capsys.readouterr().err
    assert not out.exists()
    # The same cell with its own truth scans fine.
    assert main(["scan", "--demo", "--fps", "40", "--perturb-seed", "4", "--out", str(out)]) == 0


def test_malformed_calibration_file(tmp_path, capsys):
    bad = tmp_path / "cal.json"
    bad.write_text('{"camera": {"fx": 1}}')
    code = main(["scan", "--demo", "--calibration", str(bad), "--out", str(tmp_path / "o")])
    assert code == 2
    assert "calibration" in capsys.readouterr().err


def _calibration_with(tmp_path, mutate):
    from simulator.cell import load_cell
    data = load_cell().calibration.to_dict()
    mutate(data)
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(data))  # json.dumps writes NaN as the non-standard NaN token
    return path


@pytest.mark.parametrize("setup, message", [
    (lambda t: _calibration_with(t, lambda d: d["light_plane_c"].__setitem__("offset_mm", float("nan"))),
     "`light_plane_c.offset_mm` must be finite"),
    (lambda t: _calibration_with(t, lambda d: d.__setitem__("marker_offset_t_mm", [0, "x", 0])),
     "malformed"),
    (lambda t: (t / "one.json").write_text("1") and t / "one.json", "must hold a JSON object"),
    (lambda t: t, "cannot read calibration file"),  # a directory
])
def test_bad_calibration_files(tmp_path, capsys, setup, message):
    path = setup(tmp_path)
    out = tmp_path / "o"
    code = main(["scan", "--demo", "--calibration", str(path), "--out", str(out)])
    assert code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("argv, message", [
    (["--speed", "1e9"], "--speed must be positive and at most"),
    (["--fps", "inf"], "--fps must be positive and at most"),
    (["--speed", "nan"], "--speed must be positive and at most"),
])
def test_pass_limits(tmp_path, capsys, argv, message):
    code = main(["scan", "--demo", *argv, "--out", str(tmp_path / "o")])
    assert code == 2
    assert message in capsys.readouterr().err


def test_negative_seed_is_a_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["scan", "--demo", "--seed", "-1", "--out", str(tmp_path / "o")])
    assert exc.value.code == 2
    assert "--seed: must be >= 0" in capsys.readouterr().err


def test_out_is_a_file(tmp_path, capsys):
    target = tmp_path / "taken"
    target.write_text("keep me")
    code = main(["scan", "--demo", "--out", str(target)])
    assert code == 2
    assert "exists and is not a directory" in capsys.readouterr().err
    assert target.read_text() == "keep me"


def test_identity_grasp_of_an_offset_part(tmp_path, capsys):
    """A CAD origin far from the part: with the identity grasp it lies outside the volume."""
    mesh = trimesh.creation.box(extents=(20.0, 20.0, 10.0))
    mesh.apply_translation((200.0, 0.0, 5.0))
    path = tmp_path / "offset.stl"
    mesh.export(path)
    code = main(["scan", "--part", str(path), "--units", "mm", "--grasp", "identity",
                 "--out", str(tmp_path / "o")])
    assert code == 2
    assert "outside the inspection volume" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--port", "{busy}"], "cannot serve HTTP on 127.0.0.1:"),
    (["--zmq", "localhost:5556"], "must be a ZeroMQ endpoint"),
    (["--config", "{missing}"], "settings file not found"),
])
def test_serve_refuses_bad_settings_in_one_line(tmp_path, capsys, argv, message):
    import socket

    with socket.create_server(("127.0.0.1", 0)) as busy:
        values = {"busy": str(busy.getsockname()[1]), "missing": str(tmp_path / "none.toml")}
        argv = [a.format(**values) for a in argv]
        assert main(["serve", "--sim", "--data", str(tmp_path / "d"), *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "d").exists()  # nothing started, nothing written


def test_serve_without_devices_says_what_to_do(tmp_path, capsys):
    assert main(["serve", "--data", str(tmp_path / "d")]) == 2
    assert "run with --sim" in capsys.readouterr().err
