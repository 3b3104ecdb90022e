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
from simulator.rtde_emulator import EmulatorError, RtdeEmulator, free_loopback_host
from service.ur_robot import (MAX_GAP_S, RtdeProbeError, URRobot, parse_robot_url,
                              probe_rtde)
from simulator.live import TrackSegment, pass_frame_count, tcp_on_track
from simulator.motion import PassMotion

CLOCK_OFFSET_S = 123.25  # robot clock - camera clock
#: Interpolating 2 ms apart on the reference pass errs by < 0.05 um, except across the track's
#: corners (see ``_track_corners``); a sample is exact.
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


def _track_corners(segment) -> list[float]:
    """Camera times at which the emulated track's velocity jumps: there linear interpolation
    between exact samples 2 ms apart is off the track by up to |jump| * 2 ms / 4.

    The robot leaves idle at the lead-in speed (0 -> 150 mm/s in y on the reference pass: up to
    75 um), the bow (x) and rise (z) begin and end with the pass (a few mm/s: 1 to 3 um), and
    the robot halts at ``t_last`` at full speed (250 mm/s: up to 125 um).
    """
    return [segment.robot_start_t, segment.t_zero,
            segment.t_zero + PassMotion(segment.profile).duration_s, segment.t_last]


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

    # The samples: on the robot's 500 Hz grid, each exactly the track. About 1000 are sent; a
    # loaded machine misses many (ur-rtde keeps only the newest package for the poller).
    times, positions = robot.history()
    assert len(times) > 250
    assert_allclose(times * 500.0, np.round(times * 500.0), atol=1e-6)
    for t, p in zip(times, positions):
        assert_allclose(p, truth(t), atol=1e-9)
    # The robot's clock is the camera's plus the offset (the newest sample may be some 0.1 s
    # old on a loaded machine).
    assert abs(robot.latest().t - (_camera_now(track) + CLOCK_OFFSET_S)) < 0.25
    # Between samples: interpolated, before, during and after the pass. Every interval is
    # the straight line between its two (exact) samples; off the track's corners, and 2 ms
    # long (under load samples are missed), it is also the track itself within 1 um.
    corners = np.array(_track_corners(segment)) + CLOCK_OFFSET_S
    steps = np.diff(times)
    rng = np.random.default_rng(7)
    checked = on_track = 0
    for i in rng.permutation(np.flatnonzero(steps <= MAX_GAP_S))[:200]:
        t = times[i] + rng.uniform(0.0, steps[i])
        pose = robot.pose_at(t)
        assert pose.t == t
        w = (t - times[i]) / steps[i]
        assert_allclose(pose.position, (1 - w) * truth(times[i]) + w * truth(times[i + 1]),
                        atol=1e-9)
        # how far the chord may lie from the track, across missed samples too, holds
        assert np.linalg.norm(pose.position - truth(t)) <= pose.interpolation_mm + POSITION_TOL_MM
        if abs(steps[i] - 0.002) < 1e-9 and not np.any((corners > times[i])
                                                       & (corners < times[i + 1])):
            assert_allclose(pose.position, truth(t), atol=POSITION_TOL_MM)
            on_track += 1
        assert_allclose(pose.rotation, track["rotation"], atol=1e-12)
        checked += 1
    assert checked >= 100 and on_track >= 20
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


class _TearingClient:
    """ur-rtde's receive interface as its reader meets it under load: a new data package
    (applied whole, as ur-rtde does under its state mutex) may land between any two getter
    calls, so a timestamp and a pose read one after the other are often of different packages.

    Package ``k``: robot time ``100 + k / 500`` s; the TCP moves at 200 mm/s along y (a pose
    one package off is 0.4 mm off) up to package ``moving``, then stands still, reporting the
    same pose bit for bit. Whether a package lands before a call is drawn from a seeded
    generator, so a run does not depend on timing.
    """

    def __init__(self, packages: int = 400, moving: int = 200, seed: int = 3):
        self.packages, self.moving = packages, moving
        self.k = 0
        self._rng = np.random.default_rng(seed)
        self.calls: list[tuple[str, int]] = []  # (getter, package it answered from)

    @staticmethod
    def time_of(k: int) -> float:
        return 100.0 + k / 500.0

    def pose_of(self, k: int) -> list:
        y_m = 0.2 * min(k, self.moving) / 500.0  # 200 mm/s
        return [0.25, -0.1 + y_m, 0.3, 0.0, 3.0, 0.1]

    def _call(self, getter: str) -> int:
        if self.k < self.packages - 1 and self._rng.random() < 0.35:
            self.k += 1
        self.calls.append((getter, self.k))
        return self.k

    def getTimestamp(self):
        return self.time_of(self._call("t"))

    def getActualTCPPose(self):
        return self.pose_of(self._call("pose"))

    def isConnected(self):
        return True

    def reconnect(self):
        return True

    def disconnect(self):
        pass

    def whole_reads(self) -> tuple[set, int]:
        """Packages read whole (timestamp, pose, timestamp of one package in a row), and how
        many timestamp-pose pairs read in a row were torn (of two packages)."""
        whole, torn = set(), 0
        for (g0, k0), (g1, k1), (g2, k2) in zip(self.calls, self.calls[1:], self.calls[2:]):
            if (g0, g1, g2) == ("t", "pose", "t"):
                if k0 == k1 == k2:
                    whole.add(k0)
                torn += k0 != k1
        return whole, torn


def test_torn_reads_are_never_kept(monkeypatch):
    """A timestamp and a pose of two different packages are never kept as a sample, and no
    package read whole is lost, moving or standing still."""
    monkeypatch.setattr("service.ur_robot.probe_rtde", lambda *args, **kwargs: None)
    client = _TearingClient()
    robot = URRobot("fake-robot", client_factory=lambda *args: client)
    robot.connect()
    try:
        last = client.time_of(client.packages - 1)
        _wait_for(lambda: robot.latest().t == last, 10.0)
        times, positions = robot.history()
    finally:
        robot.disconnect()
    whole, torn = client.whole_reads()
    assert torn >= 50  # the reader was offered many torn pairs
    ks = np.round((times - 100.0) * 500.0).astype(int)
    assert_allclose(times, [client.time_of(k) for k in ks], rtol=0, atol=1e-12)
    # Every sample kept is its package's pose, to the bit (torn: 0.4 mm off).
    for k, p in zip(ks, positions):
        assert_allclose(p, np.array(client.pose_of(k)[:3]) * 1000.0, rtol=0, atol=1e-9)
    # Nothing read whole was dropped, the repeated poses of the robot at rest included.
    assert set(ks) == whole
    assert sum(k > client.moving for k in ks) >= 50


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
        # an address whose port binds: one that only refuses connections may still hold the
        # port in TIME_WAIT from this test's last run
        host = free_loopback_host(first=200, count=50)
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
