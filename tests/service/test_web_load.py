"""The web side bounded: the status page's pictures drawn at a bounded rate and
cached, the scan list served from the store's index, previews waiting for a render bounded.
Real HTTP against ``flyscan serve --sim`` in its own process; counts, never timings."""
import json
import os
import re
import shutil
import threading
from collections import defaultdict

import httpx
import pytest

from running import FAST_PASS, RunningService, wait_for

PNG = b"\x89PNG\r\n\x1a\n"


def _metric(url: str, name: str, **labels) -> float:
    text = httpx.get(f"{url}/metrics", timeout=30).text
    want = ",".join(f'{k}="{v}"' for k, v in labels.items())
    pattern = rf"^{name}{{{want}}} (\S+)$" if labels else rf"^{name} (\S+)$"
    return float(re.search(pattern, text, re.MULTILINE).group(1))


def _pass(client: httpx.Client) -> dict:
    scan_id = client.post("/scans", json={}).json()["scan_id"]
    return wait_for(lambda: (lambda i: i if i["state"] in ("done", "failed") else None)(
        client.get(f"/scans/{scan_id}").json()), timeout=60)


def _on_disk(data) -> list[str]:
    """Scan ids of the info.json files on disk, newest first."""
    infos = [json.loads(p.read_text()) for p in (data / "scans").glob("*/info.json")]
    return [i["scan_id"] for i in sorted(infos, key=lambda i: i["created"], reverse=True)]


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    running = RunningService(tmp_path_factory.mktemp("web") / "data", env=FAST_PASS)
    yield running
    running.stop()


def test_the_frame_is_drawn_once_per_frame_and_the_same_bytes_served_to_all(served):
    wait_for(lambda: httpx.get(f"{served.url}/frame.png").status_code == 200, timeout=30)
    before = _metric(served.url, "flyscan_picture_renders", picture="frame")
    answers, lock = [], threading.Lock()

    def client():
        with httpx.Client(base_url=served.url, timeout=30) as c:
            for _ in range(25):
                r = c.get("/frame.png")
                with lock:
                    answers.append((r.status_code, r.headers["x-frame-id"], r.content))

    threads = [threading.Thread(target=client) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    renders = _metric(served.url, "flyscan_picture_renders", picture="frame") - before
    assert len(answers) == 100 and {s for s, _, _ in answers} == {200}
    by_frame = defaultdict(set)
    for _, frame_id, png in answers:
        by_frame[frame_id].add(png)
    # one picture per frame id, whoever asked: the same bytes
    assert all(len(pngs) == 1 for pngs in by_frame.values()), {k: len(v) for k, v in by_frame.items()}
    assert all(png.startswith(PNG) for _, _, png in answers)
    # each render is a frame nobody had been served: at most one per frame id seen (the first
    # picture may have been drawn before), and far fewer than the requests
    assert renders <= len(by_frame)
    assert renders <= len(answers) // 4, (renders, len(answers))


def test_a_preview_is_drawn_once_per_scan(served):
    with httpx.Client(base_url=served.url, timeout=60) as client:
        first, second = _pass(client), _pass(client)
        assert first["state"] == second["state"] == "done"
        before = _metric(served.url, "flyscan_picture_renders", picture="preview")
        pngs = {client.get(f"/scans/{first['scan_id']}/preview.png").content for _ in range(10)}
        assert _metric(served.url, "flyscan_picture_renders", picture="preview") - before == 1
        assert len(pngs) == 1 and next(iter(pngs)).startswith(PNG)
        other = {client.get(f"/scans/{second['scan_id']}/preview.png").content for _ in range(5)}
        assert _metric(served.url, "flyscan_picture_renders", picture="preview") - before == 2
        assert other != pngs


def test_the_scan_list_is_the_stored_scans_after_a_new_scan_a_delete_and_a_restart(tmp_path):
    data = tmp_path / "data"
    running = RunningService(data, env=FAST_PASS)
    try:
        with httpx.Client(base_url=running.url, timeout=60) as client:
            ids = [_pass(client)["scan_id"] for _ in range(3)]
            listed = [s["scan_id"] for s in client.get("/scans").json()["scans"]]
            assert listed == ids[::-1] == _on_disk(data)
            assert client.delete(f"/scans/{ids[1]}").status_code == 204
            listed = [s["scan_id"] for s in client.get("/scans").json()["scans"]]
            assert listed == [ids[2], ids[0]] == _on_disk(data)
            before_restart = client.get("/scans").json()["scans"]
    finally:
        running.stop()
    # a scan folder added while the service was down is listed after its start
    shutil.copytree(data / "scans" / ids[0], data / "scans" / "copied")
    info = json.loads((data / "scans" / "copied" / "info.json").read_text())
    info.update(scan_id="copied", created=info["created"] - 100)
    (data / "scans" / "copied" / "info.json").write_text(json.dumps(info))
    running = RunningService(data, env=FAST_PASS)
    try:
        with httpx.Client(base_url=running.url, timeout=60) as client:
            after = client.get("/scans").json()["scans"]
            assert after[:2] == before_restart and after[2]["scan_id"] == "copied"
            assert [s["scan_id"] for s in after] == _on_disk(data)
            new = _pass(client)["scan_id"]
            assert [s["scan_id"] for s in client.get("/scans").json()["scans"]] == \
                [new, ids[2], ids[0], "copied"] == _on_disk(data)
    finally:
        running.stop()


#: Scans whose previews are asked for at once.
CONCURRENT = 8


def test_requests_waiting_for_a_preview_beyond_the_bound_are_503(tmp_path):
    data = tmp_path / "data"
    running = RunningService(data, env=FAST_PASS)
    try:
        with httpx.Client(base_url=running.url, timeout=60) as client:
            scan_id = _pass(client)["scan_id"]
    finally:
        running.stop()
    ids = []
    for i in range(CONCURRENT):
        ids.append(f"copy{i}")
        shutil.copytree(data / "scans" / scan_id, data / "scans" / ids[-1])
    running = RunningService(data, env={**FAST_PASS, "FLYSCAN_MAX_PENDING_PICTURES": "1"})
    try:
        refused = []
        for round_ in range(20):  # rounds until some requests found the render taken
            for i in ids:  # a cloud file changed: its preview is drawn again
                os.utime(data / "scans" / i / "cloud.ply", ns=(10**9, 10**9 * (round_ + 7)))
            barrier, answers = threading.Barrier(CONCURRENT), []

            def ask(i):
                with httpx.Client(base_url=running.url, timeout=60) as c:
                    barrier.wait()
                    answers.append(c.get(f"/scans/{i}/preview.png"))

            threads = [threading.Thread(target=ask, args=(i,)) for i in ids]
            for t in threads:
                t.start()
            for t in threads:
                t.join(120)
            assert {r.status_code for r in answers} <= {200, 503}
            assert all(r.content.startswith(PNG) for r in answers if r.status_code == 200)
            busy = [r for r in answers if r.status_code == 503]
            assert all(r.headers["retry-after"] == "1" and "previews are being drawn" in r.json()["detail"]
                       for r in busy)
            refused += busy
            if busy:
                break
        assert refused
        assert _metric(running.url, "flyscan_picture_refused") == len(refused)
        # asked one at a time, every one is served
        with httpx.Client(base_url=running.url, timeout=60) as client:
            assert all(client.get(f"/scans/{i}/preview.png").status_code == 200 for i in ids)
    finally:
        running.stop()
