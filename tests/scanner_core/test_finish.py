"""The pass finisher: one failure rule, the cross-check's state carried, the pose, the report."""
import copy
import dataclasses

import numpy as np
import pytest

from scanner_core.pipeline.finish import CrossCheckState, finish_pass, pass_failure
from scanner_core.pipeline.trigger import EndReason
from scanner_core.types import Scan


def _empty_scan(frames: int, **changes) -> Scan:
    scan = Scan(np.zeros((0, 3), np.float32), np.zeros(0, np.int32), np.zeros(0, np.float32),
                np.zeros((0, 3), np.float32), np.zeros((frames, 3)), np.zeros(frames), frames, 0)
    for key, value in changes.items():
        setattr(scan, key, value)
    return scan


@pytest.mark.parametrize("reason, detail, expected", [
    (EndReason.TIMEOUT, None, "timeout: the marker never appeared"),
    (EndReason.CAMERA_STOPPED, "no frame for 1 s", "camera stopped: no frame for 1 s"),
    (EndReason.TOO_LONG, None, "too long: the marker did not leave the view"),
    (EndReason.RESET, "the service stopped", "reset: the service stopped"),
    (EndReason.RESET, None, "reset during the pass"),
])
def test_how_a_pass_ended_decides_first(reason, detail, expected):
    assert pass_failure(_empty_scan(35), reason, detail=detail).startswith(expected)


def test_a_pass_without_points_says_when_frames_were_lost():
    """A pass whose stripe frames were lost (a machine far behind the camera) fails with the
    count of frames lost, not only "the stripe was found on none"."""
    empty = _empty_scan(35)
    assert pass_failure(empty, EndReason.MARKER_GONE) == (
        "no points: 35 profiles were placed but the stripe was found on none")
    reason = pass_failure(empty, EndReason.MARKER_GONE, frames_lost=20, queue_overflows=3)
    assert reason.startswith("no points: 35 profiles")
    assert "20 frames of the pass never arrived" in reason and "3 overflowed" in reason


def test_no_profile_placed_says_why():
    assert pass_failure(_empty_scan(0), EndReason.MARKER_GONE).startswith(
        "no profile could be placed (the marker")
    no_robot = _empty_scan(0, frames_without_rotation=12)
    assert "the robot gave no pose" in pass_failure(no_robot, EndReason.MARKER_GONE)
    # found, but its views disagree (a second part hiding the LED in some of them, say)
    hidden = pass_failure(_empty_scan(0, frames_unplaced=1, marker_residual_px=123.8),
                          EndReason.MARKER_GONE)
    assert hidden.startswith("no profile could be placed: the marker was found in 1 frame "
                             "and never triangulated (its views disagreeing by 124 px)")
    assert "hide the gripper's LED" in hidden
    one_view = pass_failure(_empty_scan(0, frames_unplaced=3), EndReason.MARKER_GONE)
    assert "found in 3 frames" in one_view and "(in fewer than two views)" in one_view


def test_a_timeout_with_a_note():
    assert pass_failure(_empty_scan(0), EndReason.TIMEOUT, note="pass not started") == (
        "timeout: the marker never appeared (pass not started)")


def test_the_state_round_trips_through_json():
    state = CrossCheckState(clock_offset_s=0.0125, clock_offset_estimated=True,
                            led_correction_t_mm=(0.1, -0.2, 0.05), led_correction_from="s1",
                            tolerance_mm=0.2)
    assert CrossCheckState.from_dict(state.to_dict()) == state
    # unknown keys of a later format are ignored, not fatal
    assert CrossCheckState.from_dict({**state.to_dict(), "later": 1}) == state


@pytest.fixture(scope="module")
def simulated_pass():
    from scanner_core.pipeline import PipelineParams, camera_frames, run_pass, warm_up
    from simulator.cell import load_cell
    from simulator.effects import CellEffects
    from simulator.parts import block_with_holes_and_steps, part_from_mesh
    from simulator.session import simulated_cell

    cell = dataclasses.replace(load_cell(), effects=CellEffects(clock_offset_s=0.0125))
    part = part_from_mesh(block_with_holes_and_steps(), name="demo")
    sim = simulated_cell(part, cell, seed=2)
    warm_up(cell.calibration)
    sim.camera.open()
    sim.robot.connect()
    scan = run_pass(camera_frames(sim.camera), cell.calibration, sim.robot, PipelineParams())
    return scan, sim, part


def test_the_finisher_learns_the_clock_and_hands_it_on(simulated_pass):
    """The robot's clock runs 12.5 ms ahead of the camera's: the first pass estimates the
    offset (and learns the LED correction) and returns them in its state, never keeping them;
    the pose registers against the part's model, the report carries verdict and pose."""
    scan, sim, part = simulated_pass
    start = CrossCheckState()
    outcome = finish_pass(scan, EndReason.MARKER_GONE, sim.robot, start, part, scan_id="s1")
    assert outcome.state == "done" and outcome.reason == "marker gone"
    assert outcome.cross_check["samples"] > 100
    assert outcome.cross_check_state.clock_offset_estimated
    assert abs(outcome.cross_check_state.clock_offset_s - 0.0125) < 0.002
    assert outcome.cross_check_state.led_correction_from == "s1"
    assert start == CrossCheckState()  # passed in and returned, never changed in place
    assert outcome.report["state"] == "done" and outcome.report["scan_id"] == "s1"
    pose = outcome.report["pose"]
    assert pose["observable"] and np.allclose(pose["matrix"], part.grasp, atol=0.05)
    assert outcome.report["edge_kinds"]["dropout"] + outcome.report["edge_kinds"]["step"] == len(
        outcome.scan.edges)
    # no model: the pose says why there is none (the part named); not asked: none at all
    no_model = finish_pass(scan, EndReason.MARKER_GONE, sim.robot, start, part="bracket")
    assert no_model.report["pose"] == {"refused": "no CAD model for part 'bracket'"}
    assert no_model.pose_report == no_model.report["pose"] and no_model.pose is None
    assert finish_pass(scan, EndReason.MARKER_GONE, sim.robot, start,
                       register=False).report["pose"] is None
    # a failed pass: no pose either, and its reason
    failed = finish_pass(scan, EndReason.TIMEOUT, None, start, part)
    assert failed.state == "failed" and failed.report["pose"] is None
    assert failed.cross_check is None and failed.report["reason"].startswith("timeout")


class _LostAfter:
    """The simulated robot, lost after robot time ``t``: no pose for later times."""

    def __init__(self, robot, t: float):
        self._robot, self._t = robot, t
        self.connected = True

    def pose_at(self, t: float):
        if t > self._t:
            raise LookupError(f"no pose at {t}")
        return self._robot.pose_at(t)

    def latest(self):
        return self._robot.pose_at(self._t)


def test_frames_on_a_held_rotation_flag_the_check_with_their_fraction(simulated_pass):
    """A robot lost for part of a pass (81 of 225 frames on a held rotation, and a
    check over the other frames' samples that passed): the check is flagged and says how many
    frames and what fraction. Frames held only because
    the robot's reports came late, all checked since, flag nothing."""
    scan, sim, part = simulated_pass
    held = copy.copy(scan)
    held.frames_held_rotation = round(scan.frames * 81 / 225)
    late = finish_pass(held, EndReason.MARKER_GONE, sim.robot, CrossCheckState()).cross_check
    assert late["samples"] == scan.frames and not late["flagged"]
    assert "held_rotation_fraction" not in late
    # the robot lost for the last frames held (its clock: the camera's + 12.5 ms)
    lost_from = scan.tcp_times[scan.frames - held.frames_held_rotation] + 0.0125
    outcome = finish_pass(held, EndReason.MARKER_GONE, _LostAfter(sim.robot, lost_from),
                          CrossCheckState(clock_offset_s=0.0125, clock_offset_estimated=True))
    check = outcome.cross_check
    assert 0 < check["samples"] < scan.frames
    assert check["flagged"] and check["frames_held_rotation"] == held.frames_held_rotation
    assert check["held_rotation_fraction"] == round(held.frames_held_rotation / scan.frames, 4)
    assert f"{held.frames_held_rotation} of {scan.frames} frames" in check["reason"]
    assert outcome.report["cross_check"]["held_rotation_fraction"] == check["held_rotation_fraction"]
    # a frame held while its report was late, and another the check leaves out for its own
    # reason (its pose interpolated too far from the path): the robot gives every frame a
    # pose, and nothing is flagged
    held.frames_held_rotation = 1
    far = _ChordFarAt(sim.robot, scan.tcp_times[scan.frames // 2] + 0.0125)  # robot's clock
    check = finish_pass(held, EndReason.MARKER_GONE, far, CrossCheckState()).cross_check
    assert check["samples"] == scan.frames - 1 and not check["flagged"], check
    assert "held_rotation_fraction" not in check


class _ChordFarAt:
    """The simulated robot, its pose within 1 ms of robot time ``t`` interpolated 1 mm from
    its path."""

    def __init__(self, robot, t: float):
        self._robot, self._t = robot, t
        self.connected = True

    def pose_at(self, t: float):
        import dataclasses

        pose = self._robot.pose_at(t)
        if abs(t - self._t) < 1e-3:
            return dataclasses.replace(pose, interpolation_mm=1.0)
        return pose

    def latest(self):
        return self._robot.latest()


class _ReportsLate:
    """The simulated robot whose reports after robot time ``t`` arrive `delay_s` late: until
    then it has no pose for later times, and its newest is at ``t``."""

    def __init__(self, robot, t: float, delay_s: float):
        import time

        self._robot, self._t = robot, t
        self._arrived = time.monotonic() + delay_s
        self.connected = True

    def _late(self) -> bool:
        import time

        return time.monotonic() < self._arrived

    def pose_at(self, t: float):
        if t > self._t and self._late():
            raise LookupError(f"no pose at {t} yet")
        return self._robot.pose_at(t)

    def latest(self):
        return self._robot.pose_at(self._t) if self._late() else self._robot.latest()


def test_the_check_waits_for_the_robot_s_reports_on_the_last_frames(simulated_pass):
    """Reports of the pass's last tenth that arrive 50 ms after the pass is finished (a robot
    on a loaded network, a pose that came out quickly): the check waits for them and checks
    every frame, unflagged; a robot lost for those frames still flags it (after the wait)."""
    import time

    scan, sim, part = simulated_pass
    held = copy.copy(scan)
    held.frames_held_rotation = scan.frames // 10
    state = CrossCheckState(clock_offset_s=0.0125, clock_offset_estimated=True)
    last_reported = scan.tcp_times[scan.frames - held.frames_held_rotation] + 0.0125
    t0 = time.monotonic()
    check = finish_pass(held, EndReason.MARKER_GONE, _ReportsLate(sim.robot, last_reported, 0.05),
                        state).cross_check
    assert time.monotonic() - t0 >= 0.05
    assert check["samples"] == scan.frames and not check["flagged"], check
    lost = finish_pass(held, EndReason.MARKER_GONE, _LostAfter(sim.robot, last_reported),
                       state).cross_check
    assert lost["flagged"] and lost["samples"] < scan.frames
