"""Tests of scanner_core.pipeline.crosscheck: clock offset, the learned LED correction, what is flagged."""
from __future__ import annotations

import numpy as np
import pytest

from scanner_core.pipeline.crosscheck import MAX_DRIFT_STEP_S, cross_check
from scanner_core.devices import TcpPose

SPEED = np.array([0.0, -200.0, 0.0])  # mm/s along -y_B, as the reference pass
RATE_HZ = 500.0
# {T} in {B}: z_T down, and turned 30 degrees about it, so that {T} and {B} components differ.
_C, _S = np.cos(np.radians(30)), np.sin(np.radians(30))
ROTATION = np.array([[_C, _S, 0.0], [_S, -_C, 0.0], [0.0, 0.0, -1.0]])


class TrackRobot:
    """A robot on a straight constant-speed track, sampled at 500 Hz on its own clock."""

    def __init__(self, bias_b=(0.0, 0.0, 0.0)):
        self.bias_b = np.asarray(bias_b, dtype=np.float64)
        self.connected = True

    def position(self, t_robot):
        return np.array([10.0, 50.0, 400.0]) + SPEED * t_robot + self.bias_b

    def latest(self):
        return TcpPose(2.0, self.position(2.0), ROTATION)

    def pose_at(self, t):
        if not -1.0 <= t <= 2.0:
            raise LookupError(t)
        k = np.floor(t * RATE_HZ)
        w = t * RATE_HZ - k
        p = (1 - w) * self.position(k / RATE_HZ) + w * self.position((k + 1) / RATE_HZ)
        return TcpPose(t, p, ROTATION)


def _marker_track(offset_s, led_error_t, noise_mm=0.002, seed=0):
    """Camera times and marker-derived TCP positions for a robot clock ``offset_s`` ahead."""
    rng = np.random.default_rng(seed)
    times = np.arange(0.0, 0.8, 1 / 162.0)
    truth = TrackRobot()
    positions = np.array([truth.position(t + offset_s) for t in times])
    positions += ROTATION @ np.asarray(led_error_t) + rng.normal(0, noise_mm, positions.shape)
    return times, positions


def test_clock_offset_is_found_and_a_consistent_track_passes():
    times, positions = _marker_track(0.0123, [0.0, 0.0, 0.0])
    check = cross_check(times, positions, TrackRobot(), clock_offset_s=0.0)
    assert check["offset_estimated"]
    assert check["clock_offset_s"] == pytest.approx(0.0123, abs=2e-5)
    assert check["rms_mm"] < 0.005 and not check["flagged"]


def test_led_offset_error_is_measured_in_the_gripper_frame_and_corrected():
    # Across the pass (x_B and z_B) a constant difference is not a clock offset.
    led_error_t = ROTATION.T @ np.array([0.3, 0.0, -0.2])
    times, positions = _marker_track(0.004, led_error_t)
    raw = cross_check(times, positions, TrackRobot(), clock_offset_s=0.0)
    assert raw["flagged"] and raw["max_mm"] > 0.3
    np.testing.assert_allclose(raw["mean_difference_t_mm"], led_error_t, atol=0.002)
    corrected = cross_check(times, positions, TrackRobot(), clock_offset_s=raw["clock_offset_s"],
                            led_correction_t_mm=raw["mean_difference_t_mm"])
    assert not corrected["flagged"] and corrected["max_mm"] < 0.015


@pytest.mark.parametrize("bias_b", [(0.5, 0.0, 0.0), (0.0, 0.0, 0.5), (0.0, 0.5, 0.0)],
                         ids=["across", "vertical", "along the pass"])
def test_a_half_millimetre_inconsistency_is_flagged_once_the_clock_is_known(bias_b):
    """Along the pass a shift looks like 2.5 ms of clock: the drift limit tells them apart."""
    times, positions = _marker_track(0.004, [0.0, 0.0, 0.0], seed=1)
    first = cross_check(times, positions, TrackRobot(), clock_offset_s=0.0)
    assert not first["flagged"]
    later = cross_check(times, positions, TrackRobot(bias_b=bias_b),
                        clock_offset_s=first["clock_offset_s"], max_offset_step_s=MAX_DRIFT_STEP_S)
    assert later["flagged"] and later["max_mm"] > 0.3
    assert abs(later["clock_offset_s"] - first["clock_offset_s"]) <= MAX_DRIFT_STEP_S


def test_a_disconnected_robot_flags_the_check_with_its_reason():
    times, positions = _marker_track(0.0, [0.0, 0.0, 0.0])
    robot = TrackRobot()
    robot.connected = False
    check = cross_check(times, positions, robot)
    assert check["flagged"] and check["samples"] == 0 and check["reason"] == "robot not connected"


def test_a_robot_stream_with_a_gap_on_a_turn_is_checked_only_where_it_is_known():
    """A robot turning (2000 mm/s^2 across the pass) whose reader missed 40 ms of its 500 Hz
    reports, as a loaded machine's does: interpolated across the hole, its track would lie
    up to a dt^2 / 8 = 0.4 mm off the marker's and flag a consistent pass. The frames in
    the hole are left out of the check (their positions' ``interpolation_mm`` says how far
    that chord may lie from the path), and the rest pass."""
    from scanner_core.devices import chord_deviation_mm
    from scanner_core.recording.replay import ReplayRobot

    accel = np.array([2000.0, 0.0, 0.0])

    def path(t):
        return np.array([10.0, 50.0, 400.0]) + SPEED * t + 0.5 * accel * t**2

    kept = [k for k in range(0, 400) if not 150 < k < 170]  # 0.30-0.34 s missed
    samples = np.array([np.r_[k / RATE_HZ, path(k / RATE_HZ), ROTATION.ravel()] for k in kept])
    robot = ReplayRobot(samples)
    robot.connect()
    times = np.arange(0.01, 0.75, 1 / 162.0)
    positions = np.array([path(t) for t in times])
    in_hole = (times > 0.3) & (times < 0.34)
    assert robot.pose_at(0.32).interpolation_mm == pytest.approx(
        2000.0 * 0.04 * 0.042 / 4, rel=0.1)  # a dt (dt + h) / 4, twice a dt^2 / 8 or so
    assert robot.pose_at(0.1).interpolation_mm < 0.005
    check = cross_check(times, positions, robot, clock_offset_s=0.0, estimate_offset=False)
    assert check["samples"] == len(times) - in_hole.sum() and not check["flagged"], check
    assert check["max_mm"] < 0.01
    # the bound itself: a straight chord is the path; a turn in the middle, |dv| dt / 4
    line = [(0.0, [0.0, 0.0, 0.0]), (1.0, [1.0, 0.0, 0.0]), (2.0, [2.0, 0.0, 0.0]),
            (3.0, [3.0, 0.0, 0.0])]
    assert chord_deviation_mm(*line) == 0.0
    kink = [(0.0, [0.0, 0.0, 0.0]), (1.0, [1.0, 0.0, 0.0]), (3.0, [2.0, 1.0, 0.0]),
            (4.0, [2.0, 2.0, 0.0])]  # v (1, 0) turns to (0, 1) at t = 2
    assert chord_deviation_mm(*kink) == pytest.approx(np.hypot(1.0, 1.0) * 2.0 / 4.0)
    assert chord_deviation_mm(None, *line[1:3], None) == 0.0
