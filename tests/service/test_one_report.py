"""One pass, one report: a pass the service recorded gives the same ``report.json`` through the
service's finisher, ``flyscan scan --recording`` and ``flyscan replay``, field for field but
for what only one source can know; a failed pass too (and then, from the command line, no
cloud that could pass for a scan)."""
import json
import math

import pytest

from flyscan import main
from flyscan.serve import service_for
from flyscan.simdevices import SimSettings
from service.api import create_app
from service.settings import Settings
from running import free_port, serve_in_thread, wait_for

#: Entries only one source can know: its timings and latencies, the service's part version
#: and times, a command's wall time, what it read and how fast it replayed. Within the
#: others, wall times (``*_ms``) differ from run to run and are left out.
SOURCE_ONLY = {"timings_ms", "latency_ms", "part_version", "created", "wall_s", "source",
               "replay", "_deviation_png",
               # frames a loaded machine placed before the robot's report for their time had
               # arrived, on the rotation before it: the recording has every report
               "frames_held_rotation"}

#: The live pass must keep up with the simulated camera: beside another worker's load its report
#: once counted a frame fewer than its recording's. Runs after the parallel suite, alone
#: (`make test`).
pytestmark = pytest.mark.alone


def _recorded_pass(tmp_path, **settings) -> tuple[dict, str]:
    """(the service's report.json of a recorded pass of the demo block, the recording); its
    deviation map's answer is kept in ``report["_deviation_png"]`` (status, body)."""
    data = tmp_path / "data"
    service = service_for(Settings(data=data, zmq=f"tcp://127.0.0.1:{free_port()}", **settings),
                          SimSettings(sim=True, sim_speed_mm_s=1000.0))
    with serve_in_thread(create_app(service=service)) as client:
        scan_id = client.post("/scans", json={"record": True}).json()["scan_id"]
        wait_for(lambda: client.get(f"/scans/{scan_id}").json()["state"] in ("done", "failed"),
                 timeout=60)
        recording = wait_for(lambda: client.get(f"/scans/{scan_id}").json()
                             .get("recording", {}).get("path"), timeout=30)
        picture = client.get(f"/scans/{scan_id}/deviation.png")
        info = client.get(f"/scans/{scan_id}").json()
    report = json.loads((data / "scans" / scan_id / "report.json").read_text())
    assert info.get("inspection") == report.get("inspection")  # REST says what the file says
    return {**report, "_deviation_png": (picture.status_code, picture.content)}, str(data / recording)


def _from_the_command_line(tmp_path, recording) -> dict:
    """report.json of ``scan --recording`` and of ``replay``, and their exit statuses."""
    out = {}
    for name, argv in (("scan", ["scan", "--recording", recording]),
                       ("replay", ["replay", recording])):
        folder = tmp_path / name
        code = main([*argv, "--out", str(folder)])
        out[name] = (code, json.loads((folder / "report.json").read_text()),
                     sorted(p.name for p in folder.iterdir()))
    return out


def _measured(entry):
    """The entry without its wall times (``*_ms``: how long this machine took this time)."""
    if isinstance(entry, dict):
        return {k: _measured(v) for k, v in entry.items() if not k.endswith("_ms")}
    return entry


def _same(a, b) -> bool:
    """Equal, floats but for their last bits: numpy's vectorised sums may round differently
    from one run to the next (their path depends on the arrays' alignment), and an iterative
    estimate such as the clock offset carries that into its 9th digit."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float):
        return math.isclose(a, b, rel_tol=1e-7, abs_tol=1e-15) or (a != a and b != b)
    return a == b


def _same_but_the_source(live: dict, other: dict) -> None:
    assert set(live) - SOURCE_ONLY == set(other) - SOURCE_ONLY
    differing = {k for k in set(live) - SOURCE_ONLY
                 if not _same(_measured(live[k]), _measured(other[k]))}
    assert not differing, {k: (live[k], other[k]) for k in differing}


def test_a_recorded_pass_reports_the_same_through_every_source(tmp_path):
    live, recording = _recorded_pass(tmp_path)
    assert live["state"] == "done" and "matrix" in live["pose"], live["pose"]
    assert live["inspection"]["conforms"] and live["pose"]["inspection"] == live["inspection"]
    status, png = live["_deviation_png"]  # the deviation map, as the status page shows it
    assert status == 200 and png.startswith(b"\x89PNG") and len(png) > 2000
    for name, (code, report, files) in _from_the_command_line(tmp_path, recording).items():
        assert code == 0 and files == ["cloud.ply", "edges.ply", "report.json"], (name, files)
        _same_but_the_source(live, report)


def test_a_failed_pass_fails_the_same_through_every_source(tmp_path):
    """A pass longer than the service allows ends "too long": the service, the scan of its
    recording and its replay say so in the same words, and the command line writes only the
    report."""
    live, recording = _recorded_pass(tmp_path, max_pass_s=0.05)
    assert live["state"] == "failed" and live["reason"].startswith("too long"), live["reason"]
    assert live["status"] == "failed" and live["failure"] == live["reason"]
    assert live["_deviation_png"][0] in (404, 409)  # no pose, no deviation map
    for name, (code, report, files) in _from_the_command_line(tmp_path, recording).items():
        assert code == 1 and files == ["report.json"], (name, code, files)
        _same_but_the_source(live, report)
