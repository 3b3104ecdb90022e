"""``flyscan record`` against a running service, then ``flyscan replay`` of what it wrote."""
import json
import subprocess
import sys

import numpy as np
import pytest

from clients.http_client import FlyscanClient
from clients.ply import parse_ply, xyz_array

#: The live pass must keep up with the simulated camera: beside another worker's load it lost
#: frames (26 of a pass's 45: 18 profiles where the check wants more than 20). Runs after the
#: parallel suite, alone (`make test`).
pytestmark = pytest.mark.alone


def _flyscan(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "flyscan", *args], capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture(scope="module")
def recorded(service):
    """A pass recorded through the running service: (its folder, its scan id)."""
    done = _flyscan("record", "--url", service.url)
    assert done.returncode == 0, done.stderr
    relative = done.stdout.strip().rsplit(" in ", 1)[1].split(" (in the")[0]
    assert not relative.startswith("/")  # no server path: relative to the data folder
    folder = str(service.data / relative)
    return folder, done.stdout.split()[1]


def _same_report(report, live):
    """The replay's report is the live pass's: verdict, cross-check, pose, edges."""
    assert report["state"] == live["state"] == "done"
    assert report["points"] == live["points"] and report["edge_points"] == live["edge_points"]
    assert report["edge_kinds"] == live["edge_kinds"]
    for key in ("samples", "rms_mm", "max_mm", "clock_offset_s", "flagged",
                "mean_difference_t_mm", "led_correction_t_mm", "reports_until_s"):
        np.testing.assert_allclose(report["cross_check"][key], live["cross_check"][key],
                                   rtol=1e-9, atol=1e-12, err_msg=key)
    np.testing.assert_allclose(report["pose"]["matrix"], live["pose"]["matrix"], atol=1e-9)
    assert report["pose"]["flags"] == live["pose"]["flags"]
    assert report["pose"]["observable"] == live["pose"]["observable"]


def test_record_then_replay_gives_the_live_report(service, recorded, tmp_path):
    """the recording keeps the part and the cross-check's state the pass started
    from, so that the replay gives the live report, pose and cross-check included."""
    folder, scan_id = recorded
    replayed = _flyscan("replay", folder, "--out", str(tmp_path / "replay"))
    assert replayed.returncode == 0, replayed.stderr
    report = json.loads((tmp_path / "replay" / "report.json").read_text())
    assert report["replay"]["frames"] > 50 and report["replay"]["times_real_time"] > 0
    with FlyscanClient(service.url) as client:
        live_cloud = client.cloud(scan_id)
        live = client.scan(scan_id)
    replay = xyz_array(parse_ply((tmp_path / "replay" / "cloud.ply").read_bytes()))
    np.testing.assert_array_equal(replay, live_cloud)
    assert live["cross_check"]["samples"] > 20  # one per profile of the pass
    # the robot's reports the live check had: the replay reads those, not all recorded
    from scanner_core.recording import load_recording
    settings = load_recording(folder).settings
    assert settings["cross_check_reports_until_s"] == live["cross_check"]["reports_until_s"]
    _same_report(report, live)


def test_scan_of_a_recording_and_of_its_devices_give_the_live_report(service, recorded,
                                                                    tmp_path):
    """``flyscan scan --recording`` gives the replay's report; ``--camera replay:R --robot
    replay:R`` runs the real cell's path (armed on a camera's stream, the robot looked up, the
    calibration given) on the same frames and samples, and gives it too; ``--part`` replaces
    the recording's own part."""
    from scanner_core.recording import load_recording
    from scanner_core.geometry.calibration import save_calibration

    folder, scan_id = recorded
    with FlyscanClient(service.url) as client:
        live = client.scan(scan_id)
    done = _flyscan("scan", "--recording", folder, "--out", str(tmp_path / "rec"))
    assert done.returncode == 0, done.stderr
    _same_report(json.loads((tmp_path / "rec" / "report.json").read_text()), live)
    recording = load_recording(folder)
    calibration = tmp_path / "cell.json"
    save_calibration(calibration, recording.calibration)
    part = tmp_path / "part.stl"
    _write_stl(part, recording.part())
    done = _flyscan("scan", "--camera", f"replay:{folder}", "--robot", f"replay:{folder}",
                    "--calibration", str(calibration), "--part", str(part), "--units", "mm",
                    "--out", str(tmp_path / "cell"))
    assert done.returncode == 0, done.stderr
    report = json.loads((tmp_path / "cell" / "report.json").read_text())
    assert report["state"] == "done" and report["points"] == live["points"]
    # its own cross-check from the calibration's clock offset (no state learned before it)
    assert report["cross_check"]["samples"] == live["cross_check"]["samples"]
    # the part came back through an STL file (float32 vertices: a model sampled a little
    # differently, whose fit differs by a few hundredths of its sigma): the pose agrees to a
    # micron and a thousandth of a degree, or to a tenth of its sigma, and on no axis it leaves
    # free
    _same_pose(report["pose"], live["pose"])
    # simulated-cell options are refused with another source, and a part needs its unit
    refused = _flyscan("scan", "--recording", folder, "--seed", "3", "--out", str(tmp_path / "x"))
    assert refused.returncode == 2 and "--seed" in refused.stderr
    refused = _flyscan("scan", "--recording", folder, "--part", str(part), "--out",
                       str(tmp_path / "x"))
    assert refused.returncode == 2 and "--units" in refused.stderr
    assert not (tmp_path / "x").exists()


def _same_pose(pose, live):
    from scipy.spatial.transform import Rotation

    a, b = np.asarray(pose["matrix"]), np.asarray(live["matrix"])
    turn = Rotation.from_matrix(a[:3, :3] @ b[:3, :3].T).as_rotvec(degrees=True)
    for axis, difference in zip(("tx_mm", "ty_mm", "tz_mm", "rx_deg", "ry_deg", "rz_deg"),
                                np.concatenate([a[:3, 3] - b[:3, 3], turn])):
        sigma = live["std"][axis]
        if sigma is not None:  # None: a free axis
            assert abs(difference) <= max(1e-3, 0.1 * sigma), (axis, difference, sigma)


def _write_stl(path, part):
    """The part model's mesh as an STL (mm), as a user's CAD file."""
    import trimesh

    trimesh.Trimesh(part.vertices, part.faces, process=False).export(path)


def test_replay_of_a_folder_that_is_no_recording_is_a_usage_error(tmp_path):
    (tmp_path / "empty").mkdir()
    done = _flyscan("replay", str(tmp_path / "empty"), "--out", str(tmp_path / "out"))
    assert done.returncode == 2 and "recording.json" in done.stderr
    assert not (tmp_path / "out").exists()


def test_record_without_a_service_says_where_it_looked(tmp_path):
    done = _flyscan("record", "--url", "http://127.0.0.1:9", "--timeout", "2")
    assert done.returncode == 2 and "127.0.0.1:9" in done.stderr
