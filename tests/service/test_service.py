"""The service in simulated mode, driven as users drive it: the real HTTP client and a real
ZeroMQ subscriber on loopback, against ``flyscan serve --sim`` in its own process."""
import time

import numpy as np
import pytest
from numpy.testing import assert_array_equal

from clients import CloudSubscriber, Conflict, FlyscanClient, NotFound, Unauthorized
from running import FAST_PASS, RunningService

#: The subscriber's first messages after connecting are lost (slow joiner): wait this long.
SLOW_JOINER_S = 0.5


def test_arm_pass_and_the_same_cloud_over_rest_and_zeromq(service):
    with FlyscanClient(service.url) as client, CloudSubscriber(service.zmq, topics=("cloud", "pose")) as sub:
        time.sleep(SLOW_JOINER_S)
        assert client.health() == {"status": "ok"}
        scan_id = client.arm()
        info = client.wait(scan_id, timeout=30)
        assert info["state"] == "done" and info["end_reason"] == "marker gone"
        assert info["points"] > 1000 and info["frames"] > 20
        assert info["frames_dropped"] == 0 and info["queue_overflows"] == 0
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
    """A subscriber that never reads, with a high-water mark of one message: the publisher
    drops (and counts) what it cannot send; passes keep their every frame."""
    running = RunningService(tmp_path / "data", env={**FAST_PASS, "FLYSCAN_ZMQ_HWM": "1"})
    try:
        with FlyscanClient(running.url) as client, \
                CloudSubscriber(running.zmq, rcvhwm=1) as stalled:
            time.sleep(SLOW_JOINER_S)
            infos = [client.wait(client.arm(), timeout=30) for _ in range(4)]
            status = client.status()
        assert all(i["state"] == "done" and i["frames_dropped"] == 0 for i in infos)
        assert status["frames_dropped"] == 0
        assert status["zmq"]["sent"] + status["zmq"]["dropped"] >= 4 * 4
        assert stalled.received == 0
    finally:
        running.stop()
