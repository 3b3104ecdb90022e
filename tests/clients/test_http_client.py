"""FlyscanClient against an in-process fake of the REST contract (httpx.MockTransport), the PLY
reader on files built here, and the cell controller example end to end with a real PUB socket."""
import io
import json
import socket
import struct
import subprocess
import sys

import httpx
import numpy as np
import pytest
import zmq
from numpy.testing import assert_array_equal

from clients import (Conflict, FlyscanClient, FlyscanError, NotFound, PlyError, ScanFailed,
                     ServiceUnavailable, ServiceUnreachable, Unauthorized, Unprocessable,
                     parse_ply)
from clients import cell_controller

TOKEN = "s3cret"


def make_ply(columns, *, fmt="binary_little_endian 1.0", extra_header=()):
    """Binary PLY bytes from [(ply type, name, values)], written field by field with struct."""
    codes = {"char": "b", "uchar": "B", "short": "h", "ushort": "H", "int": "i", "uint": "I",
             "float": "f", "double": "d", "int8": "b", "uint8": "B", "int32": "i",
             "float32": "f", "float64": "d", "int16": "h", "uint16": "H", "uint32": "I"}
    n = len(columns[0][2]) if columns else 0
    header = ["ply", f"format {fmt}", "comment made by a test", f"element vertex {n}"]
    header += [f"property {ptype} {name}" for ptype, name, _ in columns]
    header += list(extra_header) + ["end_header"]
    record = "<" + "".join(codes[ptype] for ptype, _, _ in columns)
    body = b"".join(struct.pack(record, *(values[i] for _, _, values in columns))
                    for i in range(n))
    return ("\n".join(header) + "\n").encode("ascii") + body


def xyz_ply(xyz, **extra):
    columns = [("float", "x", xyz[:, 0]), ("float", "y", xyz[:, 1]), ("float", "z", xyz[:, 2])]
    columns += [(ptype, name, values) for name, (ptype, values) in extra.items()]
    return make_ply(columns)


class FakeService:
    """Just enough of the REST contract, recording each request."""

    def __init__(self, *, token=None, states=("armed", "scanning", "processing", "done"),
                 reason=None, cloud=None):
        self.token = token
        self.states = list(states)
        self.reason = reason
        self.cloud = np.zeros((0, 3), np.float32) if cloud is None else cloud
        self.requests: list[httpx.Request] = []
        self.on_arm = None

    def info(self, scan_id, state):
        return {"scan_id": scan_id, "state": state, "reason": self.reason if state == "failed"
                else None, "part": None, "points": len(self.cloud), "edge_points": 0,
                "frames": 10, "cross_check": {"rms_mm": 0.01234}, "pose": None}

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        method, path = request.method, request.url.path
        if method in ("POST", "PUT", "DELETE") and self.token is not None \
                and request.headers.get("authorization") != f"Bearer {self.token}":
            return httpx.Response(401, json={"detail": "missing or wrong bearer token"})
        if path == "/health":
            return httpx.Response(200, json={"status": "ok"})
        if path == "/status":
            return httpx.Response(200, json={"state": "idle", "simulated": False})
        if (method, path) == ("POST", "/scans"):
            if self.on_arm is not None:
                self.on_arm("scan-1")
            return httpx.Response(202, json={"scan_id": "scan-1", "state": "armed"})
        if (method, path) == ("GET", "/scans/scan-1"):
            state = self.states.pop(0) if len(self.states) > 1 else self.states[0]
            return httpx.Response(200, json=self.info("scan-1", state))
        if (method, path) == ("GET", "/scans/scan-1/cloud.ply"):
            return httpx.Response(200, content=xyz_ply(self.cloud))
        return httpx.Response(404, json={"detail": f"no route {method} {path}"})


def client_for(handler, **kwargs):
    return FlyscanClient("http://flyscan.test", transport=httpx.MockTransport(handler), **kwargs)


# -- requests ---------------------------------------------------------------------------------
def test_requests_paths_bodies_and_bearer(tmp_path):
    seen = []

    def handler(request):
        seen.append(request)
        path = request.url.path
        if path == "/scans" and request.method == "POST":
            return httpx.Response(202, json={"scan_id": "a1", "state": "armed"})
        if path == "/scans":
            return httpx.Response(200, json={"scans": [{"scan_id": "a1"}]})
        if path == "/parts" and request.method == "GET":
            return httpx.Response(200, json={"parts": [{"name": "bracket", "units": "mm"}]})
        if path.startswith("/parts/"):
            return httpx.Response(201, json={"name": "bracket", "units": "inch", "faces": 12})
        if request.method == "DELETE":
            return httpx.Response(204)
        if path == "/calibration" and request.method == "PUT":
            return httpx.Response(200, json={"ok": True})
        return httpx.Response(200, json={"state": "idle"})

    mesh = tmp_path / "bracket.stl"
    mesh.write_bytes(b"solid x\nendsolid x\n")
    with client_for(handler, token=TOKEN) as api:
        assert api.arm(part="bracket", timeout_s=5.0) == "a1"
        assert api.arm() == "a1"
        assert api.scans() == [{"scan_id": "a1"}]
        assert api.status() == {"state": "idle"}
        assert api.parts()[0]["name"] == "bracket"
        assert api.upload_part("bracket", mesh, "inch")["faces"] == 12
        api.delete("a/b")
        assert api.put_calibration({"camera": {"f": 16.0}}) == {"ok": True}

    arm, arm_default, scans, status, parts, upload, delete, put_cal = seen
    assert (arm.method, arm.url.path) == ("POST", "/scans")
    assert json.loads(arm.content) == {"part": "bracket", "timeout_s": 5.0}
    assert json.loads(arm_default.content) == {"part": None, "timeout_s": None}
    assert (scans.method, scans.url.path, status.url.path, parts.url.path) == \
        ("GET", "/scans", "/status", "/parts")
    assert (upload.method, upload.url.path) == ("PUT", "/parts/bracket")
    assert upload.url.params["units"] == "inch"
    assert upload.headers["content-type"] == "application/octet-stream"
    assert upload.content == mesh.read_bytes()
    assert delete.method == "DELETE"
    assert delete.url.raw_path == b"/scans/a%2Fb"          # an id is one path segment
    assert (put_cal.method, json.loads(put_cal.content)) == ("PUT", {"camera": {"f": 16.0}})
    assert all(r.headers["authorization"] == f"Bearer {TOKEN}" for r in seen)


def test_arm_sends_the_taught_place_and_upload_the_grasp(tmp_path):
    seen = []

    def handler(request):
        seen.append(request)
        if request.method == "POST":
            return httpx.Response(202, json={"scan_id": "a1", "state": "armed"})
        return httpx.Response(201, json={"name": "bracket", "nominal_grasp": np.eye(4).tolist()})

    mesh = tmp_path / "bracket.ply"
    mesh.write_bytes(b"ply\n")
    ur_pose = [0.4, -0.2, 0.1, 0.0, np.pi, 0.0]
    with client_for(handler) as api:
        api.arm(part="bracket", taught_place=np.array(ur_pose))
        api.arm(taught_place=np.eye(4))
        api.upload_part("bracket", mesh, "mm", grasp="flat")
        api.upload_part("bracket", mesh, "mm")
        taught_grasp = np.eye(4)
        taught_grasp[:3, 3] = [0.1, -2.0, 12.5]
        api.upload_part("bracket", mesh, "mm", grasp=taught_grasp)
        with pytest.raises(ValueError, match="4x4"):
            api.upload_part("bracket", mesh, "mm", grasp=np.eye(3))
    vector, matrix, flat, default, taught = seen
    assert json.loads(vector.content)["taught_place"] == ur_pose
    assert json.loads(matrix.content)["taught_place"] == np.eye(4).tolist()
    assert dict(flat.url.params) == {"units": "mm", "format": "ply", "grasp": "flat"}
    assert "grasp" not in default.url.params and "grasp_matrix" not in default.url.params
    sent = [float(v) for v in taught.url.params["grasp_matrix"].split(",")]
    assert sent == taught_grasp.ravel().tolist() and "grasp" not in taught.url.params


def test_no_token_no_authorization_header():
    service = FakeService()
    with client_for(service) as api:
        assert api.health() == {"status": "ok"}
    assert "authorization" not in service.requests[0].headers


# -- errors -----------------------------------------------------------------------------------
@pytest.mark.parametrize("status, error", [(404, NotFound), (409, Conflict),
                                           (401, Unauthorized), (422, Unprocessable),
                                           (503, ServiceUnavailable), (500, FlyscanError)])
def test_error_statuses_map_to_exceptions_with_the_reason(status, error):
    reason = f"reason for {status}"

    def handler(request):
        return httpx.Response(status, json={"detail": reason})

    with client_for(handler) as api, pytest.raises(error) as caught:
        api.scan("x")
    assert caught.value.status_code == status
    assert caught.value.detail == reason
    assert reason in str(caught.value) and str(status) in str(caught.value)


def test_fastapi_validation_detail_and_non_json_errors_are_readable(tmp_path):
    def handler(request):
        if request.url.path == "/parts/p":
            return httpx.Response(422, json={"detail": [
                {"loc": ["query", "units"], "msg": "Input should be 'mm', 'cm', 'm' or 'inch'",
                 "type": "enum"}]})
        return httpx.Response(502, text="<html>Bad Gateway</html>")

    mesh = tmp_path / "p.stl"
    mesh.write_bytes(b"")
    with client_for(handler) as api:
        with pytest.raises(Unprocessable, match=r"query\.units: Input should be 'mm'"):
            api.upload_part("p", mesh, "furlong")
        with pytest.raises(FlyscanError, match="Bad Gateway") as caught:
            api.status()
    assert caught.value.status_code == 502


def test_wrong_token_is_unauthorized():
    with client_for(FakeService(token=TOKEN), token="wrong") as api:
        assert api.health() == {"status": "ok"}              # reads need no token
        with pytest.raises(Unauthorized, match="bearer token"):
            api.arm()


def test_unreachable_service_raises_a_flyscan_error():
    with socket.socket() as s:                                # a port where nothing listens
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with FlyscanClient(f"http://127.0.0.1:{port}", timeout=2.0) as api:
        with pytest.raises(ServiceUnreachable, match=f"cannot reach .*127.0.0.1:{port}") as caught:
            api.health()
    assert isinstance(caught.value, FlyscanError) and caught.value.status_code is None


def test_request_timeout_raises_a_flyscan_error():
    def handler(request):
        raise httpx.ReadTimeout("timed out", request=request)

    with client_for(handler) as api, pytest.raises(ServiceUnreachable, match="timed out"):
        api.status()


# -- wait -------------------------------------------------------------------------------------
def test_wait_polls_until_done():
    service = FakeService()
    with client_for(service) as api:
        info = api.wait("scan-1", timeout=5.0, poll_s=0.001)
    assert info["state"] == "done"
    assert [r.url.path for r in service.requests] == ["/scans/scan-1"] * 4


def test_wait_raises_scan_failed_with_the_reason():
    service = FakeService(states=("scanning", "failed"), reason="marker gone")
    with client_for(service) as api, pytest.raises(ScanFailed, match="marker gone") as caught:
        api.wait("scan-1", timeout=5.0, poll_s=0.001)
    assert caught.value.reason == "marker gone"
    assert caught.value.info["state"] == "failed"


def test_wait_times_out():
    service = FakeService(states=("processing",))
    with client_for(service) as api, pytest.raises(TimeoutError, match="still 'processing'"):
        api.wait("scan-1", timeout=0.05, poll_s=0.01)


# -- PLY --------------------------------------------------------------------------------------
def test_ply_round_trip_with_several_property_types(rng):
    n = 7
    xyz = rng.normal(scale=50.0, size=(n, 3)).astype(np.float32)
    frame_id = rng.integers(-1000, 100000, n).astype(np.int32)
    quality = rng.random(n)
    flags = rng.integers(0, 255, n).astype(np.uint8)
    short = rng.integers(-3000, 3000, n).astype(np.int16)
    data = xyz_ply(xyz, frame_id=("int", frame_id), quality=("double", quality),
                   flags=("uchar", flags), short=("short", short), tiny=("char", -short % 100),
                   big=("uint", frame_id.astype(np.uint32)))
    fields = parse_ply(data)
    assert list(fields) == ["x", "y", "z", "frame_id", "quality", "flags", "short", "tiny", "big"]
    assert fields["x"].dtype == np.float32 and fields["frame_id"].dtype == np.int32
    assert fields["quality"].dtype == np.float64 and fields["flags"].dtype == np.uint8
    assert fields["short"].dtype == np.int16 and fields["tiny"].dtype == np.int8
    assert_array_equal(fields["frame_id"], frame_id)
    assert_array_equal(fields["quality"], quality)
    assert_array_equal(fields["flags"], flags)
    assert_array_equal(fields["short"], short)
    assert_array_equal(np.stack([fields["x"], fields["y"], fields["z"]], axis=1), xyz)
    fields["x"][0] = 1.0                                      # the arrays own their memory


def test_client_cloud_is_n_by_3_float32(rng):
    xyz = rng.normal(size=(5, 3)).astype(np.float32)
    with client_for(FakeService(cloud=xyz)) as api:
        cloud = api.cloud("scan-1")
    assert cloud.shape == (5, 3) and cloud.dtype == np.float32 and cloud.flags.c_contiguous
    assert_array_equal(cloud, xyz)


def test_empty_cloud():
    with client_for(FakeService()) as api:
        cloud = api.cloud("scan-1")
    assert cloud.shape == (0, 3) and cloud.dtype == np.float32
    assert parse_ply(make_ply([("float", "x", []), ("int", "frame_id", [])]))["frame_id"].shape \
        == (0,)


def test_crlf_header_is_accepted():
    data = xyz_ply(np.ones((2, 3), np.float32))
    head, body = data.split(b"end_header\n")
    fields = parse_ply(head.replace(b"\n", b"\r\n") + b"end_header\r\n" + body)
    assert_array_equal(fields["z"], [1.0, 1.0])


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d[:-5], "truncated: header announces 3 vertices"),
    (lambda d: d + b"\0", "1 trailing bytes"),
    (lambda d: d[:d.index(b"end_header")], "no 'end_header'"),
    (lambda d: b"PK\x03\x04" + d, "not a PLY file"),
    (lambda d: d.replace(b"binary_little_endian", b"binary_big_endian"), "binary_big_endian"),
    (lambda d: d.replace(b"binary_little_endian 1.0", b"ascii 1.0"), "'ascii 1.0' not supported"),
    (lambda d: d.replace(b"property float z", b"property float z\nelement face 0\n"
                                              b"property list uchar int vertex_indices"),
     "element 'face 0' not supported"),
    (lambda d: d.replace(b"property float z", b"property list uchar int z"), "only scalar"),
    (lambda d: d.replace(b"property float z", b"property half z"), "unknown type 'half'"),
    (lambda d: d.replace(b"property float z", b"property float x"), "'x' appears twice"),
    (lambda d: d.replace(b"element vertex 3", b"element vertex -3"), "negative"),
])
def test_bad_ply_is_refused_with_a_reason(mutate, message):
    data = xyz_ply(np.arange(9, dtype=np.float32).reshape(3, 3))
    with pytest.raises(PlyError, match=message.replace("(", r"\(").replace(")", r"\)")):
        parse_ply(mutate(data))


def test_cloud_without_xyz_is_refused():
    def handler(request):
        return httpx.Response(200, content=make_ply([("float", "u", [1.0])]))

    with client_for(handler) as api, pytest.raises(PlyError, match=r"lack the properties"):
        api.edges("e")


# -- the example cell controller --------------------------------------------------------------
@pytest.fixture
def publisher():
    sock = zmq.Context.instance().socket(zmq.PUB)
    sock.setsockopt(zmq.LINGER, 0)
    port = sock.bind_to_random_port("tcp://127.0.0.1")
    yield sock, f"tcp://127.0.0.1:{port}"
    sock.close(linger=0)


def cloud_frames(scan_id, seq, xyz):
    header = {"scan_id": scan_id, "seq": seq, "frame": "T", "units": "mm", "t": 0.0,
              "dtype": "<f4", "shape": list(xyz.shape), "fields": ["x", "y", "z"]}
    return [b"cloud", json.dumps(header).encode(), xyz.astype("<f4").tobytes()]


def test_cell_controller_scans_and_compares_the_two_clouds(publisher, rng, monkeypatch):
    pub, endpoint = publisher
    xyz = rng.normal(size=(4, 3)).astype(np.float32)
    service = FakeService(cloud=xyz)
    seq = iter(range(1, 10_000))
    out = io.StringIO()
    monkeypatch.setattr(cell_controller, "SUBSCRIBE_SETTLE_S", 0.0)
    with client_for(service) as api, cell_controller.CloudCollector(endpoint) as clouds:
        # Slow joiner: publish a warm-up cloud until the collector has one.
        for _ in range(500):
            pub.send_multipart(cloud_frames("warm-up", next(seq), xyz))
            if clouds.pop("warm-up", timeout=0.01) is not None:
                break
        else:
            pytest.fail("the subscriber never joined")
        service.on_arm = lambda scan_id: pub.send_multipart(cloud_frames(scan_id, next(seq), xyz))
        done = cell_controller.run(api, clouds, count=2, part=None, timeout=5.0, out=out)
    assert done == 2
    lines = out.getvalue().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("#1 scan-1 done: 4 points")
    assert "no pose," in lines[0] and '{"rms_mm":0.012}' in lines[0]
    assert lines[0].endswith("zmq cloud == rest cloud; do not place: no part, so no nominal grasp")


def test_cell_controller_exits_non_zero_with_the_reason(capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    assert cell_controller.main(["--url", f"http://127.0.0.1:{port}",
                                 "--zmq", f"tcp://127.0.0.1:{port}"]) == 1
    assert "cannot reach the flyscan service" in capsys.readouterr().err


def test_scan_line_reports_pose_and_mismatch():
    info = {"scan_id": "s", "state": "done", "points": 2, "edge_points": 1, "cross_check": None,
            "pose": {"misplacement": {"translation_mm": [1.23456, 0.0, 0.0]}}}
    rest = np.zeros((2, 3), np.float32)
    line = cell_controller.scan_line(3, info, rest, rest + 1)
    assert '{"translation_mm":[1.235,0.0,0.0]}' in line and line.endswith("DIFFERS from rest cloud")
    assert cell_controller.scan_line(3, info, rest, None, lost=2).endswith(
        "no cloud received (lost 2)")


@pytest.mark.parametrize("pose, expected", [
    (None, "no pose"),
    ({"refused": "a pose needs at least 50 points, the scan has 3"}, "no pose (a pose needs"),
    ({"misplacement": {"translation_mm": [1.0, 0, 0]}, "flags": ["not observable: about z_T"]},
     'NOT TO ACT ON: not observable: about z_T'),
])
def test_the_controller_says_when_not_to_act_on_a_pose(pose, expected):
    assert expected in cell_controller.describe_pose(pose)
    assert cell_controller.describe_pose({"misplacement": {"x": 1}, "flags": []}) == '{"x":1}'


def test_clients_import_nothing_of_the_service():
    code = ("import sys, clients, clients.cell_controller; "
            "print(sorted({m.split('.')[0] for m in sys.modules} "
            "& {'scanner_core', 'simulator', 'service', 'fastapi', 'numba', 'trimesh'}))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=60, check=True)
    assert result.stdout.strip() == "[]"
