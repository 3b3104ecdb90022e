"""No state that cannot end: a finish that raises, a store that cannot take a scan, a full or
read-only disk. The service runs in this process (real HTTP, ``serve_in_thread``) so that its
writes can be made to fail (ENOSPC, EROFS: root writes through a chmod); then a
``flyscan serve`` process started on the same data folder finds no leftovers."""
import errno
import types

import pytest
import trimesh

import scanner_core.recording.writer as recording_writer
import service.daemon as daemon_module
import service.engine as engine_module
import service.parts as parts_module
import service.store as store_module
from service.api import create_app
from flyscan.serve import service_for
from flyscan.simdevices import SimSettings
from service.settings import Settings
from running import FAST_PASS, RunningService, free_port, serve_in_thread, wait_for


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    data = tmp_path_factory.mktemp("disk") / "data"
    settings = Settings(data=data, zmq=f"tcp://127.0.0.1:{free_port()}")
    service = service_for(settings, SimSettings(sim=True, sim_speed_mm_s=1000.0))
    with serve_in_thread(create_app(service=service)) as client:
        yield client, service


def _scan(client, **request) -> dict:
    response = client.post("/scans", json=request)
    assert response.status_code == 202, response.text
    scan_id = response.json()["scan_id"]
    return wait_for(lambda: (lambda i: i if i["state"] in ("done", "failed") else None)(
        client.get(f"/scans/{scan_id}").json()), timeout=60)


def _fails(code: int, strerror: str):
    def fail(*args, **kwargs):
        target = next((a for a in args if isinstance(a, (str, bytes)) or hasattr(a, "__fspath__")),
                      None)
        raise OSError(code, strerror, None if target is None else str(target))
    return fail


ENOSPC = (errno.ENOSPC, "No space left on device")
EROFS = (errno.EROFS, "Read-only file system")


def _no_absolute_path(text: str, service) -> None:
    assert str(service.settings.data.resolve()) not in text and "/tmp/" not in text, text


def test_a_finish_that_raises_fails_the_scan_which_stays_deletable(cell, monkeypatch):
    client, service = cell

    def broken(*args, **kwargs):
        raise RuntimeError("the finisher broke")

    monkeypatch.setattr(engine_module, "finish_pass", broken)
    info = _scan(client)
    monkeypatch.undo()
    assert info["state"] == "failed"
    assert "could not be finished: RuntimeError: the finisher broke" in info["reason"]
    assert client.get("/status").json()["state"] == "idle"
    assert client.delete(f"/scans/{info['scan_id']}").status_code == 204
    assert client.get(f"/scans/{info['scan_id']}").status_code == 404


def test_a_scan_the_store_cannot_take_is_served_from_memory_and_deletable(cell, monkeypatch):
    client, service = cell
    # a value JSON cannot carry: the store refuses (ValueError, not an OSError)
    monkeypatch.setattr(store_module, "save_scan", lambda *a, **k: (_ for _ in ()).throw(
        ValueError("Out of range float values are not JSON compliant")))
    info = _scan(client)
    monkeypatch.undo()
    assert info["state"] == "failed" and "could not store the scan" in info["reason"]
    assert info["frames"] > 0
    assert client.get(f"/scans/{info['scan_id']}/cloud.ply").status_code == 409
    assert client.delete(f"/scans/{info['scan_id']}").status_code == 204
    assert client.get(f"/scans/{info['scan_id']}").status_code == 404


@pytest.mark.parametrize("error", [ENOSPC, EROFS], ids=["full", "read-only"])
def test_disk_errors_are_507_with_a_relative_reason_and_leave_nothing(cell, monkeypatch,
                                                                      tmp_path, error):
    client, service = cell
    data = service.settings.data
    stl = tmp_path / "block.stl"
    trimesh.creation.box(extents=(30.0, 20.0, 10.0)).export(stl)
    kept = _scan(client)  # a scan stored before the disk fills
    assert kept["state"] == "done"
    calibration = client.get("/calibration").json()
    assert client.put("/parts/block", params={"units": "mm"},
                      content=stl.read_bytes()).status_code == 201

    fail = _fails(*error)
    # the store's writes (after it has written part of the scan), the parts', the
    # calibration's, a recording's frames and its files' closing
    real_save_scan = store_module.save_scan

    def save_scan_then_fail(folder, *args, **kwargs):
        real_save_scan(folder, *args, **kwargs)
        fail(folder / "info.json")

    monkeypatch.setattr(store_module, "save_scan", save_scan_then_fail)
    monkeypatch.setattr(store_module, "shutil", types.SimpleNamespace(rmtree=_rmtree_or(fail)))
    monkeypatch.setattr(parts_module, "os", types.SimpleNamespace(replace=fail))
    monkeypatch.setattr(daemon_module, "save_calibration", fail)
    monkeypatch.setattr(recording_writer.PassRecorder, "add_frame", lambda self, frame: fail(
        self._tmp / "frames.bin"))
    real_close = recording_writer.PassRecorder._close_files

    def close_then_fail(self):
        real_close(self)
        fail(self._tmp / "frames.bin")

    monkeypatch.setattr(recording_writer.PassRecorder, "_close_files", close_then_fail)

    answers = {
        "PUT /calibration": client.put("/calibration", json=calibration),
        "PUT /parts": client.put("/parts/other", params={"units": "mm"},
                                 content=stl.read_bytes()),
        "DELETE /scans": client.delete(f"/scans/{kept['scan_id']}"),
    }
    failed = _scan(client, record=True)
    recording = wait_for(lambda: client.get(f"/scans/{failed['scan_id']}").json()
                         .get("recording", {}).get("state") in ("done", "failed")
                         and client.get(f"/scans/{failed['scan_id']}").json()["recording"])
    status = client.get("/status").json()
    monkeypatch.undo()

    for what, response in answers.items():
        assert response.status_code == 507, (what, response.text)
        assert error[1] in response.json()["detail"], (what, response.text)
        _no_absolute_path(response.json()["detail"], service)
    assert failed["state"] == "failed" and error[1] in failed["reason"], failed["reason"]
    _no_absolute_path(failed["reason"], service)
    assert recording["state"] == "failed" and error[1] in recording["error"]
    _no_absolute_path(recording["error"], service)
    assert status["camera"]["state"] == "streaming"
    # what the disk refused left nothing behind, and what it kept is whole
    hidden = [p.relative_to(data).as_posix() for p in data.rglob(".*")]
    assert hidden == [], hidden
    assert client.get(f"/scans/{kept['scan_id']}").json()["state"] == "done"
    assert client.get("/calibration").json() == calibration
    assert "other" not in [p["name"] for p in client.get("/parts").json()["parts"]]
    # the failed scan is deletable; the disk back, the service scans and stores again
    assert client.delete(f"/scans/{failed['scan_id']}").status_code == 204
    assert _scan(client)["state"] == "done"
    assert client.delete("/parts/block").status_code == 204


def test_a_recording_never_costs_the_scan_its_room(cell, monkeypatch):
    import service.live_recording as live_recording

    client, service = cell
    recordings = service.settings.data / "recordings"
    before = sorted(recordings.iterdir()) if recordings.is_dir() else []
    reserve = int(service.settings.disk_reserve_mb * 2**20)
    # 228 KB free: no recording is started (the docs' 507), and no scan is armed
    monkeypatch.setattr(daemon_module, "free_bytes", lambda path: 228 << 10)
    refused = client.post("/scans", json={"record": True})
    assert refused.status_code == 507 and "no room to record" in refused.json()["detail"]
    assert client.get("/status").json()["current_scan_id"] is None
    monkeypatch.undo()
    # room for the scan and a few frames: the recording stops at the reserve and is removed,
    # the scan is done and stored
    left = iter(range(10, -1000, -1))
    monkeypatch.setattr(live_recording, "free_bytes",
                        lambda path: reserve + next(left) * 2_400_000)
    info = _scan(client, record=True)
    recording = wait_for(lambda: client.get(f"/scans/{info['scan_id']}").json()
                         .get("recording", {}).get("state") in ("done", "failed")
                         and client.get(f"/scans/{info['scan_id']}").json()["recording"])
    monkeypatch.undo()
    assert info["state"] == "done" and info["points"] > 0
    assert recording["state"] == "failed" and "disk_reserve_mb" in recording["error"]
    assert client.get(f"/scans/{info['scan_id']}/cloud.ply").status_code == 200
    assert (sorted(recordings.iterdir()) if recordings.is_dir() else []) == before


def test_a_pose_whose_scan_cannot_be_stored_is_not_acted_on(cell, monkeypatch):
    client, service = cell
    monkeypatch.setattr(daemon_module, "free_bytes", lambda path: 300 << 10)
    monkeypatch.setattr(service.settings, "taught_place", [0.4, -0.2, 0.1, 3.14159, 0.0, 0.0])
    info = _scan(client)
    monkeypatch.undo()
    pose = info["pose"]
    assert pose["act"] is False and any("cannot be stored" in r for r in pose["act_reasons"])
    assert info["correction"]["act"] is False  # what the robot reads says the same


def _rmtree_or(fail):
    """``shutil.rmtree`` that fails unless told to ignore errors (the store's cleanup of its
    temporary folder ignores them; its deletion of a scan does not)."""
    import shutil

    def rmtree(path, ignore_errors=False, **kwargs):
        if ignore_errors:
            return shutil.rmtree(path, ignore_errors=True)
        fail(path)
    return rmtree


def test_leftovers_are_gone_after_a_restart(tmp_path):
    data = tmp_path / "data"
    # what a process killed mid-write leaves: a scan's, an upload's, a recording's
    for leftover in ("scans/.tmp-20260101T000000-abcdef01", "parts/.tmp-upload-x1y2",
                     "recordings/.20260101T000000-abcdef01.k3j4.partial"):
        (data / leftover).mkdir(parents=True)
        (data / leftover / "frames.bin").write_bytes(b"\0" * 1024)
    running = RunningService(data, env=FAST_PASS)
    try:
        hidden = [p.relative_to(data).as_posix() for p in data.rglob(".*")]
    finally:
        running.stop()
    assert hidden == []
