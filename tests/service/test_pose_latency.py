"""The pose's latency as the service reports it: from the pass's last frame to the pose's
message on ZeroMQ (``latency_ms.pose_published``) and its path stage by stage
(``latency_ms.pose_path``), in a real run of ``flyscan serve --sim``. Speed is measured by
``flyscan bench service``, never asserted here: only that the figures exist and agree."""
import time

from clients import CloudSubscriber, FlyscanClient
from running import FAST_PASS, RunningService

#: The subscriber's first messages after connecting are lost (slow joiner): wait this long.
SLOW_JOINER_S = 0.5
#: Each stage is rounded to 1 us: their sum may exceed the total by that much per stage.
ROUNDING_MS = 0.001
STAGES = {"pass_end", "handoff", "wait_workers", "assemble", "cloud", "normals", "registration",
          "pose_checks", "publish"}
#: Computed before the pass ended (``latency_ms.pose_ahead``): not on the path.
AHEAD_STAGES = STAGES - {"normals", "registration"}


def test_the_pose_latency_and_its_path(tmp_path):
    """Two passes at 1 000 mm/s: the part leaves the sheet 18 frames before the marker leaves
    the view, the finisher computes the pose then (``scanner_core.pose.ahead``), and the
    pass's end keeps it; either way the path adds up."""
    service = RunningService(tmp_path / "data", env=FAST_PASS)
    infos = []
    try:
        with FlyscanClient(service.url) as client, \
                CloudSubscriber(service.zmq, topics=("pose", "edges")) as sub:
            time.sleep(SLOW_JOINER_S)
            for _ in range(2):
                scan_id = client.arm(misplace=[0.5, -0.3, 0.2, 0.4, -0.6, 1.5])
                info = client.wait(scan_id, timeout=30)
                first = sub.receive(timeout=5)
                while first.scan_id != scan_id:
                    first = sub.receive(timeout=5)
                infos.append((info, first))
    finally:
        service.stop()
    ahead = 0
    for info, first in infos:
        assert info["state"] == "done" and "matrix" in info["pose"]
        # the pose goes out before the edges: the robot waits for nothing it does not need
        assert first.topic == "pose" and first.header["pose"] == info["pose"]
        latency = info["latency_ms"]
        total, path = latency["pose_published"], latency["pose_path"]
        ahead += "pose_ahead" in latency
        expected = AHEAD_STAGES if "pose_ahead" in latency else STAGES
        assert set(path) == expected, set(path) ^ expected
        assert all(value >= 0.0 for value in path.values()), path
        assert 0.0 < sum(path.values()) <= total + ROUNDING_MS * len(path), (path, total)
        # the pose's computation is one stretch of that path, and the pass end comes before it
        assert (path.get("normals", 0.0) + path.get("registration", 0.0) + path["pose_checks"]
                <= latency["pose"] + 3 * ROUNDING_MS)
        assert latency["pass_end_to_pose"] <= total
        assert latency["pose"] > 0.0 and latency["last_frame_to_zmq"] > 0.0
        if "pose_ahead" in latency:  # the pose's own time, spent before the pass ended
            assert latency["pose_ahead"] >= info["pose"]["time_ms"] > latency["pose"]
    assert ahead >= 1, [info["latency_ms"] for info, _ in infos]
