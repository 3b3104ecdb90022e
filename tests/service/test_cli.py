"""The ``flyscan`` command: a real scan to real files, and every bad input refused cleanly."""
import json
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from scanner_core.io.ply import read_ply
from flyscan import main
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
    code = main(["scan", "--part", str(block_stl), "--units", "inch", "--fps", "100",
                 "--misplace", "0.5,0,0,0,0,1", "--seed", "3", "--out", str(out)])
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    assert REPORT_KEYS <= report.keys()
    assert report["points"] > 1000 and report["edge_points"] > 20
    # The pose: the misplacement given, found within its reported uncertainty.
    pose = report["pose"]
    assert pose["observable"] and pose["flags"] == []
    np.testing.assert_allclose(pose["misplacement"]["translation_mm"], [0.5, 0, 0], atol=0.05)
    np.testing.assert_allclose(pose["misplacement"]["rotation_deg"], [0, 0, 1], atol=0.03)
    assert all(s <= 4 for s in report["ground_truth"]["pose_error"]["sigmas"])
    assert report["ground_truth"]["accuracy"]["rms_um"] <= 20.0
    points, fields = read_ply(out / "cloud.ply")
    assert points.dtype == np.float32 and points.shape == (report["points"], 3)
    assert set(fields) == {"nx", "ny", "nz", "sensor_x", "sensor_y", "sensor_z", "frame_id",
                           "quality", "deviation"}
    # every point's deviation from the model at the pose: a good scan's lie on it
    assert np.median(np.abs(fields["deviation"])) < 0.02 and report["inspection"]["conforms"]
    # Another tool opens the same file and finds the same points, in mm.
    other = trimesh.load(out / "cloud.ply")
    np.testing.assert_allclose(np.asarray(other.vertices), points, atol=1e-6)
    assert np.ptp(points[:, 0]) > 55.0  # the 60 mm block, not 60 inches or 2.4 mm
    edges, edge_fields = read_ply(out / "edges.ply")
    assert edges.shape == (report["edge_points"], 3)
    assert set(edge_fields) == set(fields) - {"deviation"} | {"kind", "size_mm"}
    assert set(np.unique(edge_fields["kind"])) <= {0, 1}


@pytest.mark.parametrize("argv, message", [
    (["--units", "furlong"], "unknown unit"),
    ([], "--units is required"),
    (["--units", "inch", "--speed", "-5"], "--speed must be positive"),
    (["--units", "inch", "--misplace", "1,2,3"], "--misplace must be six"),
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
    exe = [sys.executable, "-m", "flyscan"]
    proc = subprocess.run([*exe, "scan", "--demo", "--units", "parsec", "--out", str(tmp_path / "o")],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "--units applies only to --part" in proc.stderr


def test_wrong_calibration_is_refused(tmp_path, capsys):
    """A calibration that does not fit the (perturbed) cell: a clear error, no files."""
    from scanner_core.geometry.calibration import save_calibration
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
     "calibration field `marker_offset_t_mm` must be 3 numbers"),
    (lambda t: _calibration_with(t, lambda d: d.__setitem__("camera", 1)),
     "calibration field `camera` must be a JSON object, got 1"),
    (lambda t: _calibration_with(t, lambda d: d["camera"].pop("fx")),
     "calibration field `camera.fx` is missing"),
    (lambda t: _calibration_with(t, lambda d: d["mirrors"][1].__setitem__("columns", [1.5, 9])),
     "calibration field `mirrors[1].columns` must be two whole column numbers"),
    (lambda t: _calibration_with(t, lambda d: d["camera"].__setitem__("width", "wide")),
     "calibration field `camera.width` must be a number"),
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


# --------------------------------------------------------------------------------------------
# What a new user trips on
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("option", ["--misplace", "--laser", "--camera"])
def test_number_lists_may_start_with_a_minus(option):
    from flyscan.common import join_number_lists as _join_number_lists
    assert _join_number_lists(["simulate", option, "-1,0,-2", "--out", "x"]) == \
        ["simulate", f"{option}=-1,0,-2", "--out", "x"]
    # Another option after it is left alone, as is a value without a minus.
    assert _join_number_lists([option, "--out", "x"]) == [option, "--out", "x"]
    assert _join_number_lists([option, "1,2,3"]) == [option, "1,2,3"]


def test_negative_misplacement_scans(tmp_path):
    out = tmp_path / "o"
    assert main(["scan", "--demo", "--fps", "60", "--no-eval", "--misplace", "-1.5,0,0,0,0,-2",
                 "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    misplacement = np.asarray(report["ground_truth"]["misplacement"])
    np.testing.assert_allclose(misplacement[:3, 3], [-1.5, 0.0, 0.0])
    np.testing.assert_allclose(np.degrees(np.arctan2(misplacement[1, 0], misplacement[0, 0])), -2.0)
    assert report["points"] > 1000


def _inch_box(tmp_path, extents, name="part.stl"):
    path = tmp_path / name
    trimesh.creation.box(extents=extents).export(path)
    return path


@pytest.mark.parametrize("extents, units, hint", [
    ((2.0, 1.0, 0.5), "mm", "did you mean units='inch'"),      # a 2-inch part read in mm
    ((0.06, 0.04, 0.02), "mm", "did you mean units='m'"),      # a part in metres read in mm
    ((60.0, 40.0, 20.0), "m", "did you mean units='mm'"),      # mm read in metres
])
def test_implausible_size_is_refused_with_the_unit_hint(tmp_path, capsys, extents, units, hint):
    out = tmp_path / "o"
    code = main(["scan", "--part", str(_inch_box(tmp_path, extents)), "--units", units,
                 "--out", str(out)])
    assert code == 2
    err = capsys.readouterr().err
    assert hint in err and "Warning" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def _emptied(run, frames_too: bool):
    """``run_pass`` whose scan has no point (and, with ``frames_too``, no profile): what the
    pass finisher then makes of it."""
    import dataclasses

    def wrapped(*args, **kwargs):
        scan = run(*args, **kwargs)
        empty = dict(cloud=scan.cloud[:0], frame_ids=scan.frame_ids[:0],
                     quality=scan.quality[:0])
        if frames_too:
            empty.update(frames=0)
        return dataclasses.replace(scan, **empty)
    return wrapped


@pytest.mark.parametrize("frames_too, message", [
    (False, "no points: "),
    (True, "no profile could be placed"),
])
def test_a_scan_without_points_fails(tmp_path, capsys, monkeypatch, frames_too, message):
    import scanner_core.pipeline.session as pass_session
    monkeypatch.setattr(pass_session, "run_pass",
                        _emptied(pass_session.run_pass, frames_too=frames_too))
    out = tmp_path / "o"
    code = main(["scan", "--demo", "--fps", "60", "--no-eval", "--out", str(out)])
    assert code == 1
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    # The pass's record is kept; no cloud claims to be a scan.
    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "failed" and message in report["failure"]
    assert not (out / "cloud.ply").exists()


@pytest.mark.parametrize("out, message", [
    ("/proc/flyscan-out/scan", "cannot be written"),       # procfs takes no new files, even from root
    ("{file}/scan", "is a file, not a directory"),
])
def test_unwritable_out_is_refused_before_the_pass(tmp_path, capsys, monkeypatch, out, message):
    import simulator.session

    def never(*args, **kwargs):
        raise AssertionError("the pass ran before --out was checked")
    monkeypatch.setattr(simulator.session, "run_simulated_scan", never)
    blocker = tmp_path / "file"
    blocker.write_text("keep")
    code = main(["scan", "--demo", "--out", out.format(file=blocker)])
    assert code == 2
    assert message in capsys.readouterr().err
    assert blocker.read_text() == "keep"


@pytest.mark.parametrize("misplace, message", [
    ("0,0,300,0,0,0", "outside the inspection volume"),
    ("0,0,0,180,0,0", "mm into the gripper"),
    ("-100,0,0,0,0,0", "outside the inspection volume"),
])
def test_misplacement_out_of_the_volume_is_refused(tmp_path, capsys, misplace, message):
    out = tmp_path / "o"
    assert main(["scan", "--demo", "--misplace", misplace, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and "misplacement" in err
    assert not out.exists()


def test_a_small_tilt_is_a_misplacement_not_an_error():
    from simulator.parts import check_fits, part_from_mesh
    from simulator.session import parse_misplacement
    part = part_from_mesh(block_with_holes_and_steps(), name="block")
    check_fits(part, pose=parse_misplacement("0.5,-1,0,2,-3,5") @ part.grasp)


def test_too_low_a_frame_rate_names_the_frame_rate(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["scan", "--demo", "--fps", "0.5", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    # 200 mm/s over 0.5 fps: 400 mm between frames on a 40 mm part; 5 profiles need 25 fps.
    assert "frames are 400 mm apart" in err and "raise --fps to 25" in err
    assert "marker never triggered" not in err
    assert not out.exists()


def test_help_and_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    top = capsys.readouterr().out
    assert "``" not in top and "flyscan command line" in top
    with pytest.raises(SystemExit):
        main(["--version"])
    from importlib.metadata import version
    assert capsys.readouterr().out.strip() == f"flyscan {version('flyscan')}"
    with pytest.raises(SystemExit):
        main(["scan", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "{cog,gaussian3,parabola,blais_rioux,lsq_gauss}" in text
    assert "(default: cog)" in text and "(default: 0)" in text  # defaults shown, 0 included
    assert "(default: None)" not in text


def test_unknown_method_lists_the_choices(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["scan", "--demo", "--method", "magic", "--out", str(tmp_path / "o")])
    assert exc.value.code == 2
    assert "invalid choice: 'magic'" in capsys.readouterr().err


def test_the_act_tolerance_decides_the_verdict_not_the_pose(tmp_path, capsys):
    """The demo part's pose is acted on at the default tolerance (0.1 mm, 0.1 degrees); held
    to 1 um, the same pose is not, and the report and the terminal say which axes failed."""
    loose, tight = tmp_path / "loose", tmp_path / "tight"
    assert main(["scan", "--demo", "--no-eval", "--out", str(loose)]) == 0
    assert "pose: act: misplacement" in capsys.readouterr().out
    assert main(["scan", "--demo", "--no-eval", "--act-tolerance-mm", "0.001",
                 "--out", str(tight)]) == 0
    out = capsys.readouterr().out
    assert "pose: do not act: tx: 3 sigma" in out
    first = json.loads((loose / "report.json").read_text())["pose"]
    second = json.loads((tight / "report.json").read_text())["pose"]
    assert first["act"] is True and first["act_reasons"] == [] and first["observable"] is True
    assert second["act"] is False and second["observable"] is False
    assert any("beyond the act tolerance 0.001 mm" in r for r in second["act_reasons"])
    assert np.allclose(first["matrix"], second["matrix"], atol=1e-12)


@pytest.mark.parametrize("value", ["0", "-0.1", "nan", "inf"])
def test_a_tolerance_that_is_no_tolerance_is_a_usage_error(tmp_path, capsys, value):
    code = main(["scan", "--demo", "--act-tolerance-deg", value, "--out", str(tmp_path / "o")])
    assert code == 2
    assert "--act-tolerance-deg must be finite and > 0" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("argv, message", [
    (["place", "--cells", "1,x"], "--cells must be comma-separated whole numbers"),
    (["place", "--parts", "block,teapot"], "unknown part(s) ['teapot']"),
    (["place", "--picks", "0"], "--picks must be at least 1"),
    (["stripe", "--cells", "1"], "--cells is for bench place only"),
])
def test_bench_place_options_are_checked(argv, message, tmp_path, capsys):
    code = main(["bench", *argv, "--out", str(tmp_path / "o")])
    assert code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
