"""bench abuse, quick: passes through a real ``flyscan serve --sim`` while careless and
hostile clients run; what each client was answered, and that no pass failed. (Frames dropped
are reported, not asserted: on a shared machine a pass loses frames without any client.)"""
import json

import pytest

from benchmarks.abuse import STREAMS, run

#: Timing: runs after the parallel suite, alone on the machine (`make test`).
pytestmark = pytest.mark.alone


def test_bench_abuse_quick(tmp_path):
    result = run(tmp_path, quick=True, passes=1,
                 patterns=("quiet", "target", "bodies", "slow", "streams"))
    written = json.loads((tmp_path / "abuse.json").read_text())
    assert (tmp_path / "abuse.png").stat().st_size > 10_000
    patterns = written["patterns"]
    for name, pattern in patterns.items():
        assert pattern["failed"] == 0 and pattern["passes"] >= 1, (name, pattern)
        assert pattern["rss_mb"]["max"] - pattern["rss_mb"]["start"] < 50.0, (name, pattern)
        assert pattern["latency_ms"]["pose_published"]["median"] > 0.0
        # every pass reports how long its frames waited in the camera's buffer
        assert all(lag is not None and lag >= 0.0 for lag in pattern["acquisition_lag_ms"])
    # 200 MB bodies: refused before their limit is passed: without the token (401), at the
    # limit (413), or for want of a slot (503); never read whole
    assert set(patterns["bodies"]["answers"]) <= {"body 401", "body 413", "body 503"}, patterns["bodies"]
    assert patterns["bodies"]["answers"].get("body 413", 0) >= 2
    # slow uploads: two hold the body slots, the others are refused; the passes were armed
    assert set(patterns["slow"]["answers"]) == {"slow 503"}, patterns["slow"]
    # event streams: max_event_streams (16) served, the rest refused
    streams = patterns["streams"]["answers"]
    assert streams == {"stream 200": 16, "stream 503": STREAMS - 16}, streams
    # the status pages and the picture loops were answered, paced
    target = patterns["target"]["answers"]
    assert target.get("frame.png 200", 0) > 0 and target.get("page frame 200", 0) > 0
    assert result["summary"]["target"]["failed"] == 0
