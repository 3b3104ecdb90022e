"""The service in simulated mode, driven as users drive it: the real HTTP client and a real
ZeroMQ subscriber on loopback, against ``flyscan serve --sim`` in its own process."""
import time

import numpy as np
import pytest
from numpy.testing import assert_array_equal

from clients import (CloudSubscriber, Conflict, FlyscanClient, NotFound, ScanFailed, Unauthorized,
                     Unprocessable)
from running import FAST_PASS, RunningService

#: The subscriber's first messages after connecting are lost (slow joiner): wait this long.
SLOW_JOINER_S = 0.5


def test_arm_pass_and_the_same_cloud_over_rest_and_zeromq(service):
    with FlyscanClient(service.url) as client, CloudSubscriber(service.zmq, topics=("cloud", "pose")) as sub:
        time.sleep(SLOW_JOINER_S)
        assert client.health() == {"status": "ok"}
        misplace = [0.8, -0.5, 0.3, 0.5, -1.0, 2.0]
        scan_id = client.arm(misplace=misplace)
        info = client.wait(scan_id, timeout=30)
        assert info["state"] == "done" and info["end_reason"] == "marker gone"
        assert info["points"] > 1000 and info["frames"] > 20
        assert info["cross_check"]["rms_mm"] < 0.02 and not info["cross_check"]["flagged"]
        cloud_rest = client.cloud(scan_id)
        message = sub.receive(timeout=5)
        while message.topic != "cloud" or message.scan_id != scan_id:
            message = sub.receive(timeout=5)
        assert message.header["frame"] == "T" and message.header["units"] == "mm"
        assert_array_equal(message.array, cloud_rest)
        assert cloud_rest.shape == (info["points"], 3)
        # The demo block (60 x 40 x 20 mm) hangs under the TCP: its underside at z_T = 20.
        assert np.abs(cloud_rest[:, 2] - 20.0).min() < 0.05
        pose = sub.receive(timeout=5)
        assert pose.topic == "pose" and pose.scan_id == scan_id and pose.array is None
        # The misplacement the simulated pass was given, found, and the same over REST.
        assert pose.header["pose"] == info["pose"], (pose.header["pose"], info["pose"])
        # At 1 m/s profiles lie 6 mm apart: the pose says not to act on it as it stands, and
        # what it reports as known is still near the truth.
        pose_info = info["pose"]
        # (6 mm or more: a busy machine may drop a frame of the pass.)
        spacing = [float(flag.split()[1]) for flag in pose_info["flags"]
                   if flag.startswith("sparse: ")]
        assert spacing and spacing[0] >= 6.0, pose_info["flags"]
        found, std = pose_info["misplacement"], list(pose_info["std"].values())
        error = np.abs(np.subtract([*found["translation_mm"], *found["rotation_deg"]], misplace))
        known = np.array([v is not None for v in std])
        assert known[[2, 3, 4]].all()  # height and tilt: the level faces fix them
        limits = np.array([0.1, 0.1, 0.1, 0.2, 0.2, 0.2])  # mm, degrees
        assert np.all(error[known] < limits[known]), (error, std)
        assert sub.lost == 0
        assert client.scans()[0]["scan_id"] == scan_id
        fields = client.cloud_fields(scan_id)
        assert set(fields) >= {"frame_id", "quality"}


def test_a_second_arm_during_a_scan_is_refused(service):
    with FlyscanClient(service.url) as client:
        first = client.arm()
        with pytest.raises(Conflict, match="in progress"):
            client.arm()
        client.wait(first, timeout=30)


def test_a_misplacement_out_of_the_volume_is_refused(service):
    with FlyscanClient(service.url) as client:
        with pytest.raises(Unprocessable, match="into the gripper"):
            client.arm(misplace=[0, 0, 0, 180, 0, 0])
        with pytest.raises(Unprocessable, match="outside the inspection volume"):
            client.arm(misplace=[0, 0, 300, 0, 0, 0])
        assert client.status()["state"] == "idle"  # nothing was armed


def test_a_simulated_gripper_holds_the_fault_asked_for_and_it_is_not_acted_on(service):
    """A double pick asked over HTTP (``fault``): the scan is registered against the demo
    part, the second part is extra material, and the pose is not to be acted on."""
    with FlyscanClient(service.url) as client:
        with pytest.raises(Unprocessable, match="unknown fault"):
            client.arm(fault="dent:2")
        assert client.status()["state"] == "idle"  # nothing was armed
        info = client.wait(client.arm(fault="double"), timeout=60)
        good = client.wait(client.arm(), timeout=60)
    assert good["inspection"]["conforms"], good["inspection"]["reasons"]
    # (the service's faults are drawn from a seeded generator: this draw leaves the LED seen)
    assert info["state"] == "done" and info["part"] == good["part"]
    assert not info["inspection"]["conforms"]
    assert info["inspection"]["failing"] == ["extra_material"]
    (region,) = info["inspection"]["regions"]
    assert region["area_mm2"] > 100.0 and region["max_deviation_mm"] > 5.0  # a whole part
    assert info["pose"]["act"] is False
    assert any(r.startswith("inspection: extra material") for r in info["pose"]["act_reasons"])
    assert info["points"] > 1.3 * good["points"]  # the second part's points


def test_unknown_scan_and_part(service):
    with FlyscanClient(service.url) as client:
        with pytest.raises(NotFound):
            client.scan("no-such-scan")
        with pytest.raises(NotFound, match="unknown part"):
            client.arm(part="no-such-part")


def test_scans_outlive_the_process_and_a_token_guards_changes(tmp_path):
    data = tmp_path / "data"
    first = RunningService(data, env=FAST_PASS)
    try:
        with FlyscanClient(first.url) as client:
            scan_id = client.arm()
            client.wait(scan_id, timeout=30)
            cloud = client.cloud(scan_id)
    finally:
        first.stop()
    second = RunningService(data, env={**FAST_PASS, "FLYSCAN_TOKEN": "s3cret"})
    try:
        with FlyscanClient(second.url) as anonymous:
            assert anonymous.scans()[0]["scan_id"] == scan_id  # listed and served after a restart
            assert_array_equal(anonymous.cloud(scan_id), cloud)
            with pytest.raises(Unauthorized):
                anonymous.arm()
            with pytest.raises(Unauthorized):
                anonymous.delete(scan_id)
        with FlyscanClient(second.url, token="s3cret") as client:
            client.delete(scan_id)
            with pytest.raises(NotFound):
                client.scan(scan_id)
    finally:
        second.stop()


def test_a_slow_subscriber_never_stalls_acquisition(tmp_path):
    """A subscriber that never reads, with a high-water mark of one message: scan after scan
    completes (a publisher that waited for it would hold the finisher, and the next arm would
    be refused), and a subscriber that keeps up receives every cloud."""
    running = RunningService(tmp_path / "data", env={**FAST_PASS, "FLYSCAN_ZMQ_HWM": "1"})
    try:
        with FlyscanClient(running.url) as client, \
                CloudSubscriber(running.zmq, rcvhwm=1) as stalled, \
                CloudSubscriber(running.zmq, topics=("cloud",)) as attentive:
            time.sleep(SLOW_JOINER_S)
            infos = []
            for _ in range(4):
                infos.append(client.wait(client.arm(), timeout=30))
                message = attentive.receive(timeout=5)  # read at once: never behind
                assert message.scan_id == infos[-1]["scan_id"]
            status = client.status()
        assert all(i["state"] == "done" and i["points"] > 1000 for i in infos)
        assert status["zmq"]["sent"] >= 4 * 4
        assert attentive.lost == 0 and attentive.received == 4
        assert stalled.received == 0
    finally:
        running.stop()


def test_parts_uploaded_with_their_unit_are_scanned(service, tmp_path):
    import trimesh

    mesh_path = tmp_path / "plate.stl"
    trimesh.creation.box(extents=(4.0, 3.0, 1.0)).export(mesh_path)  # cm
    with FlyscanClient(service.url) as client:
        info = client.upload_part("plate", mesh_path, "cm", inspection={"extra_mm": 0.8})
        assert info["units"] == "cm" and info["faces"] == 12
        assert info["inspection"] == {"extra_mm": 0.8}  # its own threshold, kept with it
        with pytest.raises(Unprocessable, match="inspect_deform_mm"):
            client.upload_part("plate2", mesh_path, "cm", inspection={"deform_mm": -1.0})
        assert np.allclose(sorted(info["extents_mm"]), [10.0, 30.0, 40.0])
        assert "plate" in [p["name"] for p in client.parts()]
        with pytest.raises(Unprocessable, match="unit"):
            client.upload_part("plate-in-m", mesh_path, "m")  # a 4 m plate: the wrong unit
        with pytest.raises(Unprocessable):
            client.upload_part("bad", tmp_path / "plate.stl", "furlong")
        scan = client.wait(client.arm(part="plate"), timeout=30)
        cloud = client.cloud(scan["scan_id"])
    assert scan["state"] == "done" and scan["part"] == "plate"
    assert scan["inspection"]["thresholds"]["extra_mm"] == 0.8  # the part's, over the default
    # The plate's underside (10 mm below the TCP) is flat and 40 x 30 mm. Within a millimetre
    # of its outline the stripe only partly covers the pixels, and the peak moves a little.
    inside = (np.abs(cloud[:, 0]) < 19.0) & (np.abs(cloud[:, 1]) < 14.0)
    assert inside.mean() > 0.5
    assert np.abs(cloud[inside, 2] - 10.0).max() < 0.05
    assert np.abs(cloud[:, 2] - 10.0).max() < 0.1
    assert np.ptp(cloud[:, 0]) == pytest.approx(40.0, abs=1.0)


def test_a_part_replaced_while_its_scan_is_pending_changes_nothing_in_that_scan(service,
                                                                                tmp_path):
    import trimesh

    first, second = tmp_path / "first.stl", tmp_path / "second.stl"
    trimesh.creation.box(extents=(40.0, 30.0, 10.0)).export(first)
    trimesh.creation.cylinder(radius=9.0, height=25.0).export(second)
    with FlyscanClient(service.url) as client:
        armed = client.upload_part("swapped", first, "mm")
        armed_version = armed["version"]
        scan_id = client.arm(part="swapped", misplace=[1.0, -0.5, 0.3, 0.0, 0.0, 4.0])
        replaced = client.upload_part("swapped", second, "mm")  # 201 while the scan is pending
        pending = client.scan(scan_id)["state"]
        scan = client.wait(scan_id, timeout=30)
        cloud = client.cloud(scan_id)
        listed = {p["name"]: p for p in client.parts()}["swapped"]
    assert pending in ("armed", "acquiring", "processing")  # else the test proves nothing
    assert replaced["version"] != armed_version and listed["version"] == replaced["version"]
    # The pass held, and the pose registered, the box the scan was armed with.
    assert scan["state"] == "done" and scan["part_version"] == armed_version
    assert np.ptp(cloud[:, 0]) > 35.0  # the box turned 4 degrees: 42 mm; the cylinder: 18
    pose = scan["pose"]  # the fast pass's profiles lie too far apart to act on; it fits well
    assert not any("poor fit" in reason for reason in pose["act_reasons"])
    moved = np.array(pose["matrix"]) @ np.linalg.inv(np.array(armed["nominal_grasp"]))
    turn = np.degrees(np.arccos(np.clip((np.trace(moved[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    assert turn == pytest.approx(4.0, abs=0.3)  # the box's turn nearest its nominal grasp


def test_a_late_pass_of_a_timed_out_scan_is_never_the_next_scan_s(service, tmp_path):
    import trimesh

    bar = tmp_path / "bar.stl"
    trimesh.creation.box(extents=(110.0, 8.0, 8.0)).export(bar)
    with FlyscanClient(service.url) as client:
        client.upload_part("late-bar", bar, "mm")
        # its first pass is prepared (ray-cast) for longer than the scan waits
        with pytest.raises(ScanFailed, match="timeout") as failed:
            client.wait(client.arm(part="late-bar", timeout_s=0.05), timeout=30)
        scan = client.wait(client.arm(), timeout=30)  # the default part, the demo block
        cloud = client.cloud(scan["scan_id"])
        demo = {p["name"]: p for p in client.parts()}[scan["part"]]
    assert failed.value.info["part"] == "late-bar"
    assert scan["state"] == "done" and scan["part"] != "late-bar"
    assert np.ptp(cloud[:, 0]) < max(demo["extents_mm"]) + 5.0  # not the 110 mm bar


def test_calibration_round_trip_and_a_bad_one_refused(service):
    with FlyscanClient(service.url) as client:
        calibration = client.calibration()
        assert client.put_calibration(calibration)["camera"] == calibration["camera"]
        # within the edge's bounds (each entry -1 to 1), refused by the calibration's own check
        broken = {**calibration, "light_plane_c": {"normal": [0.0, 0.6, 0.6], "offset_mm": 1.0}}
        with pytest.raises(Unprocessable, match="unit 3-vector"):
            client.put_calibration(broken)
        with pytest.raises(Unprocessable, match="version: Input should be 1 or 2"):
            client.put_calibration({**calibration, "version": 3})
        # A calibration file (a lens, a clock offset, its provenance) goes through.
        lens = {**calibration, "camera": {**calibration["camera"],
                                          "distortion": [-0.08, 0.12, 2e-4, -1e-4, 0.0]},
                "clock_offset_s": 0.0125, "provenance": {"cell": "test"}}
        back = client.put_calibration(lens)
        assert back["camera"]["distortion"] == lens["camera"]["distortion"]
        assert back["clock_offset_s"] == 0.0125 and back["provenance"] == {"cell": "test"}
        # ... and one that says how well its marker offset is known keeps it.
        measured = client.put_calibration({**calibration, "marker_offset_std_mm": [0.001, 0.01, 0.002]})
        assert measured["marker_offset_std_mm"] == [0.001, 0.01, 0.002]
        assert client.calibration()["marker_offset_std_mm"] == [0.001, 0.01, 0.002]
        with pytest.raises(Unprocessable, match="marker_offset_std_mm"):
            client.put_calibration({**calibration, "marker_offset_std_mm": [0.0, -1.0, 0.0]})
        # ... and how well its light plane is known, which every pose then carries.
        plane_std = {"centre_mm": [0.0, 1.0, -20.0], "axes": [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]],
                     "covariance": [[6.25e-10, 0.0, 0.0], [0.0, 1.44e-10, 0.0],
                                    [0.0, 0.0, 2.5e-7]]}
        measured = client.put_calibration({**calibration, "light_plane_uncertainty_b": plane_std})
        assert measured["light_plane_uncertainty_b"] == plane_std
        with pytest.raises(Unprocessable, match="light_plane_uncertainty_b"):
            client.put_calibration({**calibration, "light_plane_uncertainty_b": {
                **plane_std, "axes": [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]}})
        client.put_calibration(calibration)
        assert client.calibration() == calibration


def test_metrics_count_what_happened(service):
    import httpx

    with FlyscanClient(service.url) as client:
        client.wait(client.arm(), timeout=30)
    text = httpx.get(f"{service.url}/metrics").text
    done = [line for line in text.splitlines() if line.startswith('flyscan_scans_total{state="done"}')]
    assert done and float(done[0].split()[-1]) >= 1
    assert 'flyscan_state{state="idle"} 1.0' in text
    assert "flyscan_cloud_latency_seconds_count" in text


@pytest.mark.parametrize("name", ["..", ".", ".hidden", "a/b"])
def test_a_part_name_never_reaches_outside_its_folder(service, tmp_path, name):
    import httpx
    import trimesh

    stl = trimesh.creation.box(extents=(20.0, 20.0, 5.0)).export(file_type="stl")
    before = sorted(p.name for p in service.data.iterdir())
    quoted = name.replace(".", "%2E").replace("/", "%2F")  # as sent: no client resolves it away
    response = httpx.put(f"{service.url}/parts/{quoted}", params={"units": "mm"},
                         content=stl, headers={"Content-Type": "application/octet-stream"})
    assert response.status_code in (404, 422), response.text
    assert response.status_code == 404 or "part name" in response.json()["detail"]
    assert sorted(p.name for p in service.data.iterdir()) == before  # the data folder intact
    assert (service.data / "scans").is_dir()


def test_the_documentation_pages_need_no_network(service):
    import httpx

    page = httpx.get(f"{service.url}/docs").text
    assert "cdn." not in page and "/static-offline-docs/swagger-ui-bundle.js" in page
    script = httpx.get(f"{service.url}/static-offline-docs/swagger-ui-bundle.js")
    assert script.status_code == 200 and len(script.content) > 100_000


def test_a_simulated_misplacement_moves_the_cloud(service):
    import httpx


    with FlyscanClient(service.url) as client:
        plain = client.cloud(client.wait(client.arm(), timeout=30)["scan_id"])
        response = httpx.post(f"{service.url}/scans", json={"misplace": [4.0, 0, 0, 0, 0, 0]})
        assert response.status_code == 202
        moved = client.cloud(client.wait(response.json()["scan_id"], timeout=30)["scan_id"])
        bad = httpx.post(f"{service.url}/scans", content=b'{"misplace": [NaN, 0, 0, 0, 0, 0]}',
                         headers={"Content-Type": "application/json"})
        assert bad.status_code == 422
    # The block's x extent is exact at its ends: both ends move by the misplacement.
    assert moved[:, 0].min() - plain[:, 0].min() == pytest.approx(4.0, abs=0.2)
    assert moved[:, 0].max() - plain[:, 0].max() == pytest.approx(4.0, abs=0.2)
