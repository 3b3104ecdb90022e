"""The service's edge against ``flyscan serve --sim`` in its own process: the token before the
body, bodies stopped at their limit while they stream, strict and bounded request models.

Large bodies are sent as users' programs would send them (httpx, from a generator: chunked,
and with a Content-Length), while a pass runs; the service's peak memory is read from
``/proc`` (``VmHWM``, reset before through ``clear_refs``)."""
import json
import select
import socket
import threading
from pathlib import Path

import httpx
import numpy as np
import pytest

from running import TOKEN, wait_for

#: A body far past every limit, bytes (200 MB), sent in chunks of 1 MiB.
BIG = 200 * 10**6
CHUNK = 1 << 20
#: The service's peak memory may grow by less than this while it refuses BIG bodies, bytes.
MAX_GROWTH = 50 * 2**20


def _auth(token=TOKEN):
    return {"Authorization": f"Bearer {token}"}


def _body(total=BIG, first=b"{\"part\": \""):
    """``total`` bytes: the start of a JSON object, then a string that never ends."""
    yield first
    sent = len(first)
    chunk = b"x" * CHUNK
    while sent < total:
        piece = chunk[:min(CHUNK, total - sent)]
        sent += len(piece)
        yield piece


def _wait(client, scan_id) -> dict:
    return wait_for(lambda: (lambda i: i if i["state"] in ("done", "failed") else None)(
        client.get(f"/scans/{scan_id}").json()), timeout=60)


def _memory(pid: int, key: str) -> int:
    """``VmRSS`` or ``VmHWM`` (peak) of a process, bytes."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
    raise KeyError(key)


def _reset_peak(pid: int) -> None:
    Path(f"/proc/{pid}/clear_refs").write_text("5")  # VmHWM := VmRSS (Linux 4.0 and up)


#: Bodies sent during a pass: (method, path, token, with Content-Length, expected status).
BIG_CASES = [
    ("POST", "/scans", None, False, 401), ("POST", "/scans", None, True, 401),
    ("PUT", "/calibration", None, False, 401), ("PUT", "/parts/big?units=mm", None, True, 401),
    ("POST", "/scans", TOKEN, False, 413), ("POST", "/scans", TOKEN, True, 413),
    ("PUT", "/calibration", TOKEN, False, 413),
    ("PUT", "/parts/big?units=mm", TOKEN, False, 413),
    ("PUT", "/parts/big?units=mm", TOKEN, True, 413),
]
#: Passes tried: the machine's other load (four engineers on two cores) may cost a live pass
#: frames whatever the bodies do; one pass of these must lose none.
PASSES = 3


def _bodies_during_a_pass(url: str) -> tuple[dict, list]:
    """Arm a pass and send BIG_CASES, over and over (each at least once), until it has ended:
    (the scan's info, [(case, status, detail)])."""
    answers, ended = [], threading.Event()

    def send():
        with httpx.Client(base_url=url, timeout=120) as client:
            while not ended.is_set() or len(answers) < len(BIG_CASES):
                case = BIG_CASES[len(answers) % len(BIG_CASES)]
                method, path, token, sized, _ = case
                headers = {"Content-Type": "application/json", **(_auth(token) if token else {})}
                if sized:
                    headers["Content-Length"] = str(BIG)
                response = client.request(method, path, content=_body(), headers=headers)
                answers.append((case, response.status_code, response.json()["detail"]))

    with httpx.Client(base_url=url, timeout=30, headers=_auth()) as client:
        scan_id = client.post("/scans", json={}).json()["scan_id"]
        sender = threading.Thread(target=send)
        sender.start()
        try:
            info = _wait(client, scan_id)
        finally:
            ended.set()
            sender.join(600)
    return info, answers


@pytest.mark.alone  # timing: after the parallel suite, alone (`make test`)
def test_big_bodies_are_refused_before_they_are_read_while_a_pass_runs(guarded):
    pid = guarded.process.pid
    # warm: the first pass of a process and the first requests of each route build what
    # they keep (about 34 MB for the first pass)
    with httpx.Client(base_url=guarded.url, timeout=30, headers=_auth()) as client:
        _wait(client, client.post("/scans", json={}).json()["scan_id"])
        client.put("/parts/warm", params={"units": "mm"}, content=b"x")
    baseline = _memory(pid, "VmRSS")
    _reset_peak(pid)
    passes = []
    for _ in range(PASSES):
        info, answers = _bodies_during_a_pass(guarded.url)
        growth = _memory(pid, "VmHWM") - baseline
        print(f"peak RSS growth {growth / 2**20:.1f} MiB after {len(answers)} bodies of "
              f"{BIG / 1e6:g} MB; the pass {info['state']}, {info['frames']} frames, "
              f"{info['frames_dropped']} dropped, {info['queue_overflows']} overflows")
        assert [status for _, status, _ in answers] == [case[-1] for case, _, _ in answers]
        assert all("bearer token" in detail for _, status, detail in answers if status == 401)
        assert all("larger than" in detail for _, status, detail in answers if status == 413)
        assert growth < MAX_GROWTH, growth
        assert info["state"] == "done", info["reason"]
        passes.append(info)
        if info["frames_dropped"] == 0 and info["queue_overflows"] == 0:
            break
    assert passes[-1]["frames_dropped"] == 0 and passes[-1]["queue_overflows"] == 0, [
        (i["frames_dropped"], i["queue_overflows"]) for i in passes]
    parts = [p["name"] for p in httpx.get(f"{guarded.url}/parts", headers=_auth()).json()["parts"]]
    assert "big" not in parts
    leftovers = [p.name for p in (guarded.data / "parts").iterdir() if p.name.startswith(".")]
    assert leftovers == []


def test_the_token_comes_before_the_body_and_reads_are_protected(guarded):
    url = guarded.url
    malformed = httpx.post(f"{url}/scans", content=b"{not json",
                           headers={"Content-Type": "application/json"})
    assert malformed.status_code == 401 and malformed.headers["www-authenticate"] == "Bearer"
    wrong = httpx.post(f"{url}/scans", json={}, headers=_auth("wrong"))
    assert wrong.status_code == 401
    for path in ("/scans", "/status", "/parts", "/calibration", "/metrics", "/frame.png"):
        assert httpx.get(f"{url}{path}").status_code == 401, path
        assert httpx.get(f"{url}{path}", headers=_auth()).status_code in (200, 404), path
    for path in ("/health", "/", "/openapi.json", "/docs"):
        assert httpx.get(f"{url}{path}").status_code == 200, path


@pytest.mark.parametrize("body, problem", [
    (b"\xff\xfe{\"part\": 1}", "body"),
    (b"[" * 100_000 + b"]" * 100_000, "body"),
    (b'{"timeout_s": "5"}', "timeout_s"),
    (b'{"record": "yes"}', "record"),
    (b'{"misplace": [true, 0, 0, 0, 0, 0]}', "misplace"),
    (b'{"part": 7}', "part"),
], ids=["invalid UTF-8", "nested deep", "a string for a number", "a string for a boolean",
        "a boolean for a number", "a number for a string"])
def test_malformed_requests_are_422_naming_the_field(service, body, problem):
    response = httpx.post(f"{service.url}/scans", content=body,
                          headers={"Content-Type": "application/json"})
    assert response.status_code == 422, response.text
    assert problem in json.dumps(response.json()["detail"])


def _absurd(calibration: dict) -> list:
    """(name, calibration, the field the 422 must name): the issue's list."""
    camera = calibration["camera"]
    mirror = calibration["mirrors"][0]
    return [
        ("cx = 1e308", {**calibration, "camera": {**camera, "cx": 1e308}}, "cx"),
        ("0 mirrors", {**calibration, "mirrors": []}, "mirrors"),
        ("2000 mirrors", {**calibration, "mirrors": [mirror] * 2000}, "mirrors"),
        ("marker offset 1e308", {**calibration, "marker_offset_t_mm": [1e308, 0.0, 0.0]},
         "marker_offset_t_mm"),
        ("clock offset 1e308", {**calibration, "clock_offset_s": 1e308}, "clock_offset_s"),
        ("distortion 1e10", {**calibration, "camera": {**camera,
                                                      "distortion": [1e10, 0, 0, 0, 0]}},
         "distortion"),
        ("an unknown field", {**calibration, "lens_model": "fisheye"}, "lens_model"),
        ("a string for a focal length", {**calibration, "camera": {**camera, "fx": "2730"}},
         "fx"),
        ("cx outside the image", {**calibration, "camera": {**camera, "cx": 5000.0}}, "camera"),
    ]


def test_each_absurd_calibration_is_refused_naming_the_field(service):
    calibration = httpx.get(f"{service.url}/calibration").json()
    for name, absurd, field in _absurd(calibration):
        response = httpx.put(f"{service.url}/calibration", json=absurd)
        assert response.status_code == 422, (name, response.text)
        locations = [".".join(map(str, e["loc"])) for e in response.json()["detail"]]
        assert any(field in loc for loc in locations), (name, locations)
    assert httpx.get(f"{service.url}/calibration").json() == calibration  # none was taken


def _changed(calibration: dict, path: str, value) -> dict:
    out = json.loads(json.dumps(calibration))
    *parents, leaf = path.split(".")
    node = out
    for key in parents:
        node = node[key]
    node[leaf] = value
    return out


@pytest.mark.parametrize("path, value, message", [
    ("camera.fx", 10.0, "square"),
    ("camera.rotation", [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "triangulated"),
    ("camera.origin_mm", [0.0, -225.0, 610.0], "triangulated"),
    ("camera.distortion", [10.0, 0.0, 0.0, 0.0, 0.0], "corners"),
    ("clock_offset_s", 1e10, "clocks"),
    ("marker_offset_t_mm", [1000.0, 0.0, 0.0], "LED is within"),
])
def test_a_calibration_no_cell_could_have_is_never_activated(service, path, value, message):
    calibration = httpx.get(f"{service.url}/calibration").json()
    response = httpx.put(f"{service.url}/calibration", json=_changed(calibration, path, value))
    assert response.status_code == 422 and message in response.text, response.text
    assert httpx.get(f"{service.url}/calibration").json() == calibration


def test_meshes_that_are_no_part_are_refused(service, tmp_path):
    import trimesh

    triangle = trimesh.Trimesh([[0, 0, 0], [30, 0, 0], [0, 30, 0]], [[0, 1, 2]], process=False)
    ply = triangle.export(file_type="ply", encoding="binary")
    claims = ply.replace(b"element face 1\n", b"element face 100000000\n")
    # slivers spanning a 20 mm cube: thick and voluminous by their vertices, no area
    rng = np.random.default_rng(5)
    a, b = rng.uniform(0.0, 20.0, (2, 60, 3))
    corners = np.stack([a, b, (a + b) / 2 + 1e-5], axis=1).reshape(-1, 3)
    slivers = trimesh.Trimesh(corners, np.arange(len(corners)).reshape(-1, 3), process=False)
    cases = [(triangle.export(file_type="stl"), "stl", "no thickness"),
             (claims, "ply", "face 100000000"), (ply, "ply", "no thickness"),
             (slivers.export(file_type="ply", encoding="binary"), "ply", "slivers")]
    for content, fmt, problem in cases:
        response = httpx.put(f"{service.url}/parts/flat", params={"units": "mm", "format": fmt},
                             content=content)
        assert response.status_code == 422 and problem in response.json()["detail"], response.text
        assert str(service.data.parent) not in response.json()["detail"]  # no server path


def test_parts_are_deleted_unless_built_in_or_in_use(service):
    import trimesh

    stl = trimesh.creation.box(extents=(30.0, 20.0, 10.0)).export(file_type="stl")
    url = service.url
    assert httpx.put(f"{url}/parts/spare", params={"units": "mm"}, content=stl).status_code == 201
    assert httpx.delete(f"{url}/parts/demo").status_code == 409  # built in
    assert httpx.delete(f"{url}/parts/nothing").status_code == 404
    scan_id = httpx.post(f"{url}/scans", json={"part": "spare"}).json()["scan_id"]
    busy = httpx.delete(f"{url}/parts/spare")
    with httpx.Client(base_url=url) as client:
        info = _wait(client, scan_id)
    assert busy.status_code == 409 and scan_id in busy.json()["detail"], busy.text
    assert info["state"] == "done" and info["part"] == "spare"
    assert httpx.delete(f"{url}/parts/spare").status_code == 204
    assert "spare" not in [p["name"] for p in httpx.get(f"{url}/parts").json()["parts"]]
    assert not (service.data / "parts" / "spare").exists()


def test_the_number_of_parts_is_bounded(tmp_path):
    import trimesh

    from service.parts import PartLibrary, PartQuotaExceeded

    stl = trimesh.creation.box(extents=(30.0, 20.0, 10.0)).export(file_type="stl")
    library = PartLibrary(tmp_path, max_parts=2)
    library.open()
    library.add("a", stl, "mm")
    library.add("b", stl, "mm")
    library.add("a", stl, "mm")  # a replacement takes no more room
    with pytest.raises(PartQuotaExceeded, match="2 parts"):
        library.add("c", stl, "mm")
    library.remove("a")
    library.add("c", stl, "mm")
    assert library.names() == ["b", "c"]
    assert sorted(p.name for p in (tmp_path / "parts").iterdir()) == ["b", "c"]


def _held_upload(url: str) -> socket.socket:
    """A chunked ``PUT /parts/held`` whose body has begun and does not end (raw HTTP: the test
    decides when it ends)."""
    host, port = url.removeprefix("http://").split(":")
    sock = socket.create_connection((host, int(port)))
    chunk = b"solid held open\n"
    sock.sendall(f"PUT /parts/held?units=mm HTTP/1.1\r\nHost: {host}\r\n"
                 f"Authorization: Bearer {TOKEN}\r\nTransfer-Encoding: chunked\r\n\r\n"
                 f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n")
    return sock


def _answered(sock: socket.socket) -> bool:
    """Whether the service has answered on ``sock`` already (without waiting)."""
    return bool(select.select([sock], [], [], 0)[0])


def _status(sock: socket.socket) -> int:
    sock.settimeout(30)
    return int(sock.recv(4096).split(b" ", 2)[1])


def test_bodies_read_at_once_are_bounded(guarded):
    """Two uploads held open take both body slots (``max_concurrent_bodies``, 2): one more
    upload is refused with 503 and Retry-After; an arm's few bytes (a body declared small)
    and requests without a body pass; the held uploads, left without a next piece for
    ``body_idle_s`` (3 s here), are answered 408 and free their slots."""
    uploads = [_held_upload(guarded.url), _held_upload(guarded.url)]

    def probe():
        for k, upload in enumerate(uploads):
            if _answered(upload):  # refused while a probe held a slot: open it again
                upload.close()
                uploads[k] = _held_upload(guarded.url)
        response = httpx.put(f"{guarded.url}/parts/third?units=mm", headers=_auth(),
                             content=iter([b"solid third\n"]))  # chunked: no length
        return response if response.status_code == 503 else None

    try:
        refused = wait_for(probe, timeout=30)
        assert refused.headers["retry-after"] == "1" and "bodies" in refused.json()["detail"]
        assert not any(_answered(upload) for upload in uploads)  # both still held
        arm = httpx.post(f"{guarded.url}/scans", content=b"{}",
                         headers={**_auth(), "Content-Type": "application/json"})
        assert arm.status_code in (202, 409), arm.text
        if arm.status_code == 202:
            with httpx.Client(base_url=guarded.url, headers=_auth()) as client:
                _wait(client, arm.json()["scan_id"])
        assert httpx.get(f"{guarded.url}/status", headers=_auth()).status_code == 200
        # the uploads stall: 408, and their slots are free again
        assert [_status(upload) for upload in uploads] == [408, 408]
        freed = httpx.put(f"{guarded.url}/parts/third?units=mm", headers=_auth(),
                          content=iter([b"solid third\n"]))
        assert freed.status_code == 422  # read whole: not a mesh
    finally:
        for upload in uploads:
            upload.close()


@pytest.mark.parametrize("headers, status", [
    ({"origin": "http://evil.example"}, 403),
    ({"referer": "http://evil.example/page.html"}, 403),
    ({"origin": "null"}, 403),
    ({"origin": "http://127.0.0.1:9", "referer": "http://127.0.0.1:8000/"}, 403),  # Origin wins
    ({"content-type": "application/x-www-form-urlencoded"}, 415),
    ({"content-type": "text/plain;charset=UTF-8"}, 415),
    ({"content-type": "multipart/form-data; boundary=x"}, 415),
    ({"content-type": "application/octet-stream"}, 415),
])
def test_a_write_a_page_of_another_site_could_send_is_refused(headers, status):
    from service.edge import foreign_write

    got = foreign_write({"host": "127.0.0.1:8000", **headers}, "POST", "/scans")
    assert got is not None and got[0] == status


@pytest.mark.parametrize("headers, method, path", [
    ({"origin": "http://127.0.0.1:8000", "content-type": "application/json"}, "POST", "/scans"),
    ({"referer": "http://127.0.0.1:8000/#scans"}, "POST", "/calibration/rollback"),
    ({"origin": "https://cell-hmi.local:8443"}, "DELETE", "/scans/x"),  # trusted below
    ({"content-type": "application/octet-stream"}, "PUT", "/parts/bracket"),
    ({"content-type": "model/stl"}, "PUT", "/parts/bracket"),
    ({}, "POST", "/scans"),  # a script's request without a type: read as JSON
])
def test_writes_of_the_service_own_pages_and_scripts_go_on(headers, method, path):
    from service.edge import foreign_write

    assert foreign_write({"host": "127.0.0.1:8000", **headers}, method, path,
                         ["https://cell-hmi.local:8443/"]) is None


def _form_post(url, path, **headers):
    return httpx.post(f"{url}{path}", content=b"part=demo",
                      headers={"content-type": "application/x-www-form-urlencoded", **headers})


def test_cross_site_form_posts_change_nothing_with_or_without_a_token(service, guarded):
    for running in (service, guarded):
        before = httpx.get(f"{running.url}/scans", headers=_auth()).json()["scans"]
        for path in ("/scans", "/calibration/rollback"):
            refused = _form_post(running.url, path, origin="http://evil.example")
            assert refused.status_code == 403, refused.text
            assert "another site" in refused.json()["detail"]
        # a form the browser posts without an Origin (an old browser, a stripped header)
        bare = _form_post(running.url, "/scans")
        assert bare.status_code == 415 and "application/json" in bare.json()["detail"]
        assert httpx.get(f"{running.url}/scans", headers=_auth()).json()["scans"] == before
    # the service's own status page arms as before
    own = httpx.post(f"{service.url}/scans", content=b"{}",
                     headers={"content-type": "application/json", "origin": service.url})
    assert own.status_code == 202, own.text
    from clients import FlyscanClient

    with FlyscanClient(service.url) as client:
        assert client.wait(own.json()["scan_id"], timeout=30)["state"] == "done"


def test_options_says_what_may_be_done_at_a_path(service):
    for path, methods in (("/scans", {"GET", "POST"}), ("/scans/x", {"GET", "DELETE"}),
                          ("/parts/demo", {"PUT", "DELETE"}), ("/calibration", {"GET", "PUT"})):
        response = httpx.options(f"{service.url}{path}")
        allowed = {m.strip() for m in response.headers["allow"].split(",")}
        assert response.status_code == 204 and methods | {"OPTIONS"} <= allowed, (path, allowed)
    patch = httpx.patch(f"{service.url}/scans", json={})
    assert patch.status_code == 405 and "POST" in patch.headers["allow"]
