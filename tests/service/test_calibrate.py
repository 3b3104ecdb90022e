"""flyscan calibrate: a simulated session in a cell the scanner does not know."""
import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from scanner_core.geometry import angle_between
from scanner_core.calibration.session import SessionError, load_session, write_session
from flyscan import main
from simulator.calsession import simulate_session
from simulator.cell import load_cell
from simulator.effects import EFFECTS, realistic_cell


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    out = tmp_path_factory.mktemp("cal") / "cal.json"
    assert main(["calibrate", "--sim", "--perturb-seed", "5", "--led-positions", "120",
                 "--sphere-positions", "20", "--out", str(out)]) == 0
    return out


def test_calibration_finds_the_unknown_cell(calibrated):
    report = json.loads(calibrated.with_suffix(".report.json").read_text())
    truth = report["against_truth"]
    assert truth["plane_normal_deg"] < 0.005
    assert truth["plane_offset_um"] < 10
    assert truth["led_offset_um"] < 50
    assert abs(truth["clock_offset_ms"]) < 0.2
    assert report["residuals"]["sphere_centre_rms_mm"] < 0.020
    for view in report["models"]["ladder"]:
        assert view["chosen"] == "pinhole+distortion"
        assert view["heldout_rms_px"]["pinhole+distortion"] < 0.05
    data = json.loads(calibrated.read_text())
    assert data["version"] == 2 and data["provenance"]["observations"]["led_positions"] == 120


def test_scan_on_the_calibration_is_as_good_as_on_the_truth(calibrated, tmp_path):
    rms = {}
    for name, extra in (("truth", []), ("calibrated", ["--calibration", str(calibrated)])):
        out = tmp_path / name
        assert main(["scan", "--demo", "--perturb-seed", "5", "--effects", "all",
                     "--out", str(out)] + extra) == 0
        rms[name] = json.loads((out / "report.json").read_text())["ground_truth"]["accuracy"]["rms_um"]
    assert rms["calibrated"] <= 30.0
    assert rms["calibrated"] <= 1.5 * rms["truth"]


def test_scan_takes_the_cell_the_calibration_was_made_in(calibrated, tmp_path, capsys):
    """The issue's command as written: `flyscan scan --perturb-seed M --calibration FILE` with
    FILE from `flyscan calibrate --sim --perturb-seed M` scans in the cell FILE was made in
    (its provenance says which), and is as good as the truth there."""
    data = json.loads(calibrated.read_text())
    assert data["provenance"]["simulated_cell"] == {"perturb_seed": 5, "effects": list(EFFECTS)}
    out = tmp_path / "literal"
    assert main(["scan", "--demo", "--perturb-seed", "5", "--calibration", str(calibrated),
                 "--out", str(out)]) == 0
    assert "effects: lens,exposure,clocks,robot,led" in capsys.readouterr().err
    report = json.loads((out / "report.json").read_text())
    assert report["ground_truth"]["cell"]["calibration"]["camera"]["distortion"] != [0.0] * 5
    assert report["ground_truth"]["accuracy"]["rms_um"] <= 30.0


def test_the_ideal_calibration_is_far_off_in_the_real_cell(tmp_path):
    """The lens alone, not calibrated, throws the cloud off by more than a millimetre: the
    calibration above is doing the work."""
    out = tmp_path / "ideal"
    ideal = tmp_path / "ideal.json"
    from scanner_core.geometry.calibration import save_calibration
    save_calibration(ideal, load_cell(perturb_seed=5).calibration)
    code = main(["scan", "--demo", "--perturb-seed", "5", "--effects", "lens", "--out", str(out),
                 "--calibration", str(ideal)])
    if code == 0:
        rms = json.loads((out / "report.json").read_text())["ground_truth"]["accuracy"]["rms_um"]
        assert rms > 200.0
    else:
        assert code != 0  # or the scan refuses: the marker's residuals give it away


def test_the_scanner_never_reads_the_truth(tmp_path):
    """From a session folder, with the simulator unimportable, the calibration still comes out
    (and is not the truth exactly: it was measured)."""
    cell = realistic_cell(load_cell(perturb_seed=6), ("lens", "clocks", "led"), seed=6)
    # A short pass at 60 fps keeps the recording small (30 frames, 70 MB).
    short = cell.with_pass(start_y_mm=-40.0, end_y_mm=40.0, lead_in_s=0.05, lead_out_s=0.05,
                           fps=60.0)
    session = simulate_session(short, seed=1, led_count=60, sphere_count=8)
    write_session(tmp_path / "session", session)
    assert (tmp_path / "session" / "pass" / "recording.json").is_file()
    script = textwrap.dedent(f"""
        import sys, json
        sys.modules["simulator"] = None  # any import of the simulator now fails
        from scanner_core.calibration.session import calibrate_session, load_session
        cal, report = calibrate_session(load_session({str(tmp_path / 'session')!r}))
        print(json.dumps(cal.to_dict()))
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    from scanner_core.geometry.calibration import Calibration
    cal = Calibration.from_dict(json.loads(done.stdout.strip().splitlines()[-1]))
    true = cell.calibration
    angle = np.degrees(angle_between(cal.light_plane_b.normal, true.light_plane_b.normal, undirected=True))
    assert 0.0 < angle < 0.02
    assert 0.0 < np.linalg.norm(cal.camera.origin - true.camera.origin) < 1.0
    # The lens as it bends pixels (its k2 and k3 trade off against each other over a session
    # this short): across the direct view, within a fifth of a pixel.
    u, v = np.meshgrid(np.linspace(400, 1500, 12), np.linspace(50, 1150, 12))
    grid = np.column_stack([u.ravel(), v.ravel()])
    bend = cal.camera.ideal_pixels(grid) - grid
    true_bend = true.camera.ideal_pixels(grid) - grid
    assert np.abs(true_bend).max() > 2.0
    assert np.abs(bend - true_bend).max() < 0.2
    # The pass in the folder gave the LED's offset and the clocks.
    assert np.linalg.norm(cal.marker_offset_t - true.marker_offset_t) < 0.05
    assert np.linalg.norm(cal.marker_offset_t - load_cell().calibration.marker_offset_t) > 0.05
    assert abs(cal.clock_offset_s - cell.effects.robot_time(0.0)) < 2e-4


def test_a_broken_session_folder_is_named(tmp_path):
    with pytest.raises(SessionError, match="session.json not found"):
        load_session(tmp_path)
    (tmp_path / "session.json").write_text(json.dumps({"format": "flyscan-calibration-session",
                                                       "version": 9}))
    with pytest.raises(SessionError, match="version 9"):
        load_session(tmp_path)


def test_calibrate_refuses_too_few_positions(tmp_path, capsys):
    assert main(["calibrate", "--sim", "--led-positions", "2", "--out",
                 str(tmp_path / "c.json")]) == 2
    assert "--led-positions must be at least 3" in capsys.readouterr().err


def test_a_session_whose_sphere_the_sheet_never_cuts_is_refused(tmp_path, capsys):
    """The stage log puts the sphere 40 mm off the sheet: no stripe pixel meets it there, and
    the calibration says so (exit 2, nothing written)."""
    import csv

    cell = load_cell()
    session = simulate_session(cell, seed=2, led_count=60, sphere_count=5, with_pass=False)
    folder = tmp_path / "session"
    write_session(folder, session)
    with open(folder / "sphere.csv", newline="") as f:
        rows = list(csv.reader(f))
    for row in rows[1:]:
        row[2] = repr(float(row[2]) + 40.0)  # y: along the pass, off the sheet
    with open(folder / "sphere.csv", "w", newline="") as f:
        csv.writer(f).writerows(rows)
    out = tmp_path / "c.json"
    assert main(["calibrate", "--session", str(folder), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert ("does the sheet cut the sphere" in err or "do not lie on one plane" in err), err
    assert not out.exists()


def test_the_service_runs_on_what_calibrate_learned(tmp_path):
    """The service in the realistic simulated cell (a lens, an LED off its drawing) with the
    calibration `flyscan calibrate --sim` made there: a plate's flat underside comes out flat
    and where it is; with the ideal cell's calibration it does not."""
    import trimesh
    from clients import FlyscanClient
    from running import FAST_PASS, RunningService
    from scanner_core.geometry.calibration import save_calibration

    learned, ideal = tmp_path / "learned.json", tmp_path / "ideal.json"
    assert main(["calibrate", "--sim", "--perturb-seed", "7", "--effects", "lens,led",
                 "--led-positions", "120", "--sphere-positions", "20", "--out", str(learned)]) == 0
    save_calibration(ideal, load_cell(perturb_seed=7).calibration)
    plate = tmp_path / "plate.stl"
    trimesh.creation.box(extents=(40.0, 30.0, 10.0)).export(plate)
    flatness = {}
    for name, calibration in (("learned", learned), ("ideal", ideal)):
        env = {**FAST_PASS, "FLYSCAN_SIM_PERTURB_SEED": "7", "FLYSCAN_SIM_EFFECTS": "lens,led",
               "FLYSCAN_CALIBRATION": str(calibration)}
        running = RunningService(tmp_path / f"data-{name}", env=env)
        try:
            with FlyscanClient(running.url) as client:
                client.upload_part("plate", plate, "mm")
                scan = client.wait(client.arm(part="plate"), timeout=60)
                cloud = client.cloud(scan["scan_id"])
        finally:
            running.stop()
        inside = (np.abs(cloud[:, 0]) < 19.0) & (np.abs(cloud[:, 1]) < 14.0)
        flatness[name] = (np.abs(cloud[inside, 2] - 10.0).max(), inside.mean())
    assert flatness["learned"][0] < 0.05 and flatness["learned"][1] > 0.5
    assert flatness["ideal"][0] > 0.2


def test_a_figure_that_could_not_be_measured_is_null_not_nan():
    from scanner_core.calibration.session import _json_safe

    assert _json_safe({"a": [np.float64("nan"), np.int64(3), 1.5], "b": float("inf")}) == \
        {"a": [None, 3, 1.5], "b": None}
    json.dumps(_json_safe({"x": np.float32(2.0)}), allow_nan=False)
