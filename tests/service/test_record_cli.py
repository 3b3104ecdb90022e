"""``flyscan record`` against a running service, then ``flyscan replay`` of what it wrote."""
import json
import subprocess
import sys

import numpy as np

from clients.http_client import FlyscanClient
from clients.ply import parse_ply, xyz_array


def _flyscan(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True,
                          text=True, timeout=timeout)


def test_record_then_replay_gives_the_live_cloud(service, tmp_path):
    recorded = _flyscan("record", "--url", service.url)
    assert recorded.returncode == 0, recorded.stderr
    folder = recorded.stdout.strip().rsplit(" in ", 1)[1].split(" (on the")[0]
    scan_id = recorded.stdout.split()[1]
    replayed = _flyscan("replay", folder, "--out", str(tmp_path / "replay"))
    assert replayed.returncode == 0, replayed.stderr
    report = json.loads((tmp_path / "replay" / "report.json").read_text())
    assert report["replay"]["frames"] > 50 and report["replay"]["times_real_time"] > 0
    with FlyscanClient(service.url) as client:
        live = client.cloud(scan_id)
    replay = xyz_array(parse_ply((tmp_path / "replay" / "cloud.ply").read_bytes()))
    np.testing.assert_array_equal(replay, live)


def test_replay_of_a_folder_that_is_no_recording_is_a_usage_error(tmp_path):
    (tmp_path / "empty").mkdir()
    done = _flyscan("replay", str(tmp_path / "empty"), "--out", str(tmp_path / "out"))
    assert done.returncode == 2 and "recording.json" in done.stderr
    assert not (tmp_path / "out").exists()


def test_record_without_a_service_says_where_it_looked(tmp_path):
    done = _flyscan("record", "--url", "http://127.0.0.1:9", "--timeout", "2")
    assert done.returncode == 2 and "127.0.0.1:9" in done.stderr
