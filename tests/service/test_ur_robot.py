"""URRobot against the RTDE emulator: the real ur-rtde client, the emulator in its own process.

Every emulator listens on its own loopback address (ur-rtde only uses port 30004): the first
free one from 127.0.0.2 on, so that concurrent sessions on one machine do not collide.
"""
import socket
import struct
import time

import numpy as np
import pytest
from numpy.testing import assert_allclose

from scanner_core.devices import Robot
from service.rtde_emulator import EmulatorError, RtdeEmulator
from service.ur_robot import RtdeProbeError, URRobot, parse_robot_url, probe_rtde
from simulator.live import TrackSegment, pass_frame_count, tcp_on_track
from simulator.motion import PassMotion

CLOCK_OFFSET_S = 123.25  # robot clock - camera clock
#: Interpolating 2 ms apart on the reference pass errs by < 0.05 um; a sample is exact.
POSITION_TOL_MM = 1e-3
LOSS_DETECTED_S = 3.0
RECOVERED_S = 5.0


def _start_emulator(first: int = 2) -> RtdeEmulator:
    for last_octet in range(first, 250):
        try:
            return RtdeEmulator(f"127.0.0.{last_octet}").start()
        except EmulatorError as exc:
            if "in use" not in str(exc):
                raise
    raise RuntimeError("no free loopback address for an RTDE emulator")


def _wait_for(predicate, timeout_s: float, step_s: float = 0.005) -> float:
    """Seconds until ``predicate()`` held; fails the test after ``timeout_s``."""
    t0 = time.monotonic()
    while not predicate():
        if time.monotonic() - t0 > timeout_s:
            pytest.fail(f"condition not met within {timeout_s} s")
        time.sleep(step_s)
    return time.monotonic() - t0


@pytest.fixture(scope="module")
def track(cell):
    profile = cell.pass_profile
    return {"epoch": time.monotonic(), "rotation": np.array(cell.gripper_rotation_b, float),
            "idle": PassMotion(profile).tcp_position(-profile.lead_in_s), "profile": profile}


@pytest.fixture(scope="module")
def emulator(track):
    emulator = _start_emulator()
    emulator.set_track(track["epoch"], CLOCK_OFFSET_S, track["rotation"], track["idle"])
    yield emulator
    emulator.stop()


@pytest.fixture
def robot(emulator):
    robot = URRobot(emulator.host)
    yield robot
    robot.disconnect()


def _camera_now(track) -> float:
    return time.monotonic() - track["epoch"]


# --------------------------------------------------------------------------------------------

def test_parse_robot_url():
    assert parse_robot_url("ur://192.168.1.10") == "192.168.1.10"
    assert parse_robot_url("ur://robot-1.cell.local:30004") == "robot-1.cell.local"
    assert parse_robot_url("ur://[fe80::1]") == "fe80::1"
    with pytest.raises(ValueError, match="30004"):
        parse_robot_url("ur://10.0.0.2:30002")
    for bad in ("10.0.0.2", "http://10.0.0.2", "ur://", "ur://a b"):
        with pytest.raises(ValueError, match="ur://HOST"):
            parse_robot_url(bad)


def test_follows_a_simulated_pass(emulator, robot, track):
    """The real client's poses against the track's ground truth, through one pass."""
    assert isinstance(robot, Robot)
    robot.connect()
    assert robot.connected
    profile = track["profile"]
    start = _camera_now(track) + 0.05
    segment = TrackSegment(start, start + profile.lead_in_s,
                           start + (pass_frame_count(profile) - 1) / profile.fps, profile)
    emulator.add_segment(segment)
    _wait_for(lambda: robot.latest().t - CLOCK_OFFSET_S > segment.t_last + 0.05, 5.0)

    def truth(t_robot):
        return tcp_on_track([segment], track["idle"], t_robot - CLOCK_OFFSET_S)

    # The samples: on the robot's 500 Hz grid, each exactly the track.
    times, positions = robot.history()
    assert len(times) > 500
    assert_allclose(times * 500.0, np.round(times * 500.0), atol=1e-6)
    for t, p in zip(times, positions):
        assert_allclose(p, truth(t), atol=1e-9)
    # The robot's clock is the camera's plus the offset.
    assert abs(robot.latest().t - (_camera_now(track) + CLOCK_OFFSET_S)) < 0.05
    # Between samples: interpolated, before, during and after the pass.
    steps = np.diff(times)
    rng = np.random.default_rng(7)
    checked = 0
    for i in rng.permutation(np.flatnonzero(np.abs(steps - 0.002) < 1e-9))[:200]:
        t = times[i] + rng.uniform(0.0, 0.002)
        pose = robot.pose_at(t)
        assert pose.t == t
        assert_allclose(pose.position, truth(t), atol=POSITION_TOL_MM)
        assert_allclose(pose.rotation, track["rotation"], atol=1e-12)
        checked += 1
    assert checked >= 100
    moving = [t for t in times if segment.robot_start_t < t - CLOCK_OFFSET_S < segment.t_last]
    assert np.ptp(np.array([truth(t) for t in moving])[:, 1]) > 200.0  # it did move
    with pytest.raises(LookupError):
        robot.pose_at(robot.latest().t + 0.05)
    with pytest.raises(LookupError):
        robot.pose_at(times[0] - 0.01)
    status = robot.status()
    assert status["connected"] and status["samples"] >= len(times)
    assert status["last_error"] is None and status["last_sample_age_s"] < 0.1


def test_bias_shows_in_positions(emulator, robot, track):
    emulator.set_track(track["epoch"], CLOCK_OFFSET_S, track["rotation"], track["idle"])
    robot.connect()
    assert_allclose(robot.latest().position, track["idle"], atol=1e-9)
    bias = np.array([0.5, 0.0, -0.5])
    emulator.set_bias(bias)
    try:
        t_set = robot.latest().t
        _wait_for(lambda: robot.latest().t > t_set + 0.02, 2.0)
        assert_allclose(robot.latest().position - track["idle"], bias, atol=1e-9)
    finally:
        emulator.set_bias([0.0, 0.0, 0.0])


def test_default_client_reads_every_variable(emulator):
    """ur-rtde's default recipe (about 60 variables) decodes with the emulator's types."""
    import rtde_receive

    client = rtde_receive.RTDEReceiveInterface(emulator.host)
    try:
        assert client.isConnected()
        assert client.getRobotMode() == 7 and client.getSafetyMode() == 1
        assert len(client.getActualQ()) == 6
        assert len(client.getActualTCPPose()) == 6
    finally:
        client.disconnect()


def test_link_loss_and_recovery(track):
    """drop: refused and closed; stall: open but silent (the stale-data path)."""
    emulator = _start_emulator(first=20)
    robot = URRobot(emulator.host)
    try:
        emulator.set_track(track["epoch"], CLOCK_OFFSET_S, track["rotation"], track["idle"])
        robot.connect()
        assert robot.connected
        for fault, seconds_down in ((emulator.drop, 2.5), (emulator.stall, 1.0)):
            fault()
            lost_s = _wait_for(lambda: not robot.connected, LOSS_DETECTED_S)
            before = robot.latest().t
            time.sleep(max(seconds_down - lost_s, 0.0))  # long enough for the backoff to grow
            assert not robot.connected and robot.status()["last_error"]
            emulator.restore()
            back_s = _wait_for(lambda: robot.connected, RECOVERED_S)
            _wait_for(lambda: robot.latest().t > before + 0.1, 1.0)
            print(f"{fault.__name__}: lost after {lost_s:.3f} s, back {back_s:.3f} s after restore")
            assert abs(robot.latest().t - (_camera_now(track) + CLOCK_OFFSET_S)) < 0.05
            with pytest.raises(LookupError, match="gap"):
                robot.pose_at(before + 0.05)  # no interpolation across the outage
        status = robot.status()
        assert status["reconnects"] == 2 and status["last_error"] is None
    finally:
        robot.disconnect()
        emulator.stop()


def test_nothing_listening_stays_disconnected():
    host = next(f"127.0.0.{n}" for n in range(200, 250) if _refused(f"127.0.0.{n}"))
    robot = URRobot(host, first_sample_s=0.3)
    t0 = time.monotonic()
    robot.connect()
    assert time.monotonic() - t0 < 1.0
    try:
        time.sleep(0.1)
        assert not robot.connected
        assert "connection refused" in robot.status()["last_error"]
        with pytest.raises(RuntimeError, match="no pose"):
            robot.latest()
        with pytest.raises(LookupError):
            robot.pose_at(1.0)
    finally:
        robot.disconnect()
    with pytest.raises(RuntimeError, match="not connected"):
        robot.pose_at(1.0)


def test_silent_server_is_probed_not_constructed():
    """A server that accepts but never answers would block ur-rtde's constructor for ever,
    holding the GIL: the probe keeps the client from being made."""
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)
        host, port = silent.getsockname()
        with pytest.raises(RtdeProbeError, match="handshake"):
            probe_rtde(host, port=port, timeout_s=0.2)

    made = []
    with socket.socket() as silent:
        host = next(f"127.0.0.{n}" for n in range(200, 250) if _refused(f"127.0.0.{n}"))
        silent.bind((host, 30004))
        silent.listen(8)
        robot = URRobot(host, probe_timeout_s=0.2, first_sample_s=0.5,
                        client_factory=lambda *args: made.append(args))
        robot.connect()
        try:
            assert not robot.connected
            assert "handshake" in robot.status()["last_error"]
            assert made == []
        finally:
            robot.disconnect()


def test_emulator_survives_malformed_packets(emulator):
    before = emulator.stats()["malformed"]
    for junk in (b"\x00\x01V",  # size below the header's
                 struct.pack(">HB", 3, ord("Z")),  # unknown type
                 struct.pack(">HB", 11, ord("O")) + struct.pack(">d", 500.0)):  # before 'V'
        with socket.create_connection((emulator.host, 30004), timeout=2.0) as sock:
            sock.sendall(junk)
            assert sock.recv(100) == b""  # closed by the server
    assert emulator.stats()["malformed"] == before + 3
    probe_rtde(emulator.host, timeout_s=2.0)  # still serving


def test_emulator_refuses_a_taken_address(emulator):
    with pytest.raises(EmulatorError, match="in use"):
        RtdeEmulator(emulator.host).start()


def _refused(host: str) -> bool:
    try:
        probe_rtde(host, timeout_s=0.2)
    except RtdeProbeError as exc:
        return "connection refused" in str(exc)
    return False
