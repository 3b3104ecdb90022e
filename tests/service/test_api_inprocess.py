"""The REST API in-process (FastAPI's TestClient, the service injected): what each of the
service's answers becomes on the wire, without devices, threads or sockets."""
from types import SimpleNamespace

import pytest
from fastapi.testclient import TestClient

from service.api import create_app
from service.api_common import get_service
from service.driver import ControllerDriven
from service.engine import EngineBusy, EngineFault
from service.settings import Settings


class _Service:
    """The daemon's face as the routes see it: arm raises what it is told to; scans are a dict."""

    def __init__(self, tmp_path):
        self.settings = Settings(data=tmp_path)
        self.driver = ControllerDriven()
        self.armed, self.raises, self.scans = [], None, {}

    def arm(self, part, timeout_s, misplace, *, record, taught_place, fault=None):
        if self.raises is not None:
            raise self.raises
        if misplace is not None:
            self.driver.misplacement(None, misplace)
        if fault is not None:
            self.driver.holding(None, fault)
        self.armed.append((part, timeout_s, misplace, record, taught_place))
        return SimpleNamespace(scan_id="s1", state="armed")

    def scan_info(self, scan_id):
        return self.scans[scan_id]  # KeyError when unknown, as the daemon's


@pytest.fixture
def api(tmp_path):
    service = _Service(tmp_path)
    app = create_app(service=service)
    app.dependency_overrides[get_service] = lambda: service
    return TestClient(app), service  # no `with`: the lifespan (the devices) never starts


@pytest.mark.parametrize("raised, status, words", [
    (KeyError("nope"), 404, "unknown part"),
    (EngineBusy("a scan is armed"), 409, "a scan is armed"),
    (EngineFault("the camera is not streaming"), 503, "not streaming"),
    (ValueError("beyond the robot's reach"), 422, "reach"),
], ids=["unknown part", "busy", "camera down", "bad value"])
def test_what_the_service_says_of_an_arm_is_the_status(api, raised, status, words):
    client, service = api
    service.raises = raised
    answer = client.post("/scans", json={"part": "p"})
    assert answer.status_code == status and words in answer.text, answer.text


def test_a_real_cell_refuses_a_misplacement_and_arms_nothing(api):
    client, service = api
    answer = client.post("/scans", json={"misplace": [1, 0, 0, 0, 0, 0]})
    assert answer.status_code == 422 and "simulated cell only" in answer.text
    assert service.armed == []
    accepted = client.post("/scans", json={"timeout_s": 2.5, "record": True})
    assert accepted.status_code == 202 and accepted.json() == {"scan_id": "s1", "state": "armed"}
    assert service.armed == [(None, 2.5, None, True, None)]


def test_a_real_cell_refuses_a_fault_and_arms_nothing(api):
    client, service = api
    answer = client.post("/scans", json={"fault": "chip:2"})
    assert answer.status_code == 422 and "simulated cell only" in answer.text
    assert service.armed == []


@pytest.mark.parametrize("body", [b"{", b'{"timeout_s": -1}', b'{"misplace": [1, 2]}',
                                  b'{"timeout_s": "soon"}', b'{"fault": "chip:two"}',
                                  b'{"fault": ""}', b'{"fault": 3}'],
                         ids=["not JSON", "negative timeout", "short misplacement", "a word",
                              "a fault's size in words", "an empty fault", "a fault's number"])
def test_a_malformed_arm_is_422_before_the_service_hears_of_it(api, body):
    client, service = api
    answer = client.post("/scans", content=body, headers={"Content-Type": "application/json"})
    assert answer.status_code == 422, answer.text
    assert service.armed == []


def test_an_unknown_scan_is_404_and_a_known_one_its_info(api):
    client, service = api
    assert client.get("/scans/missing").status_code == 404
    service.scans["s1"] = {"scan_id": "s1", "state": "done", "part": None, "created": 1.0,
                           "frames": 120, "points": 9000}
    answer = client.get("/scans/s1")
    assert answer.status_code == 200
    assert {k: answer.json()[k] for k in ("state", "frames", "points")} == {
        "state": "done", "frames": 120, "points": 9000}
