"""A live pass's recording keeps the robot's reports its cross-check read, up to the newest."""
from types import SimpleNamespace

import numpy as np
import pytest

from scanner_core.devices import RobotConnection, TcpPose
from scanner_core.recording import load_recording
from scanner_core.recording.replay import REPORTS_UNTIL_SETTING, ReplayRobot
from scanner_core.types import Frame
from service.live_recording import REPORTS_AFTER_PASS_S, LiveRecording

#: A real controller's reports: 500 Hz, but not on the recording's sample grid (k / 500 s).
REPORT_PERIOD_S, REPORT_PHASE_S = 0.002, 0.00073


class _Reporting(RobotConnection):
    """A robot moving along x at 100 mm/s whose reports so far end at ``newest``."""

    def __init__(self, newest: float):
        self.newest = newest
        self.looked_up = 0

    def _pose(self, t: float) -> TcpPose:
        return TcpPose(t, np.array([100.0 * t, 0.0, 0.0]), np.eye(3))

    def latest(self) -> TcpPose:
        return self._pose(REPORT_PHASE_S + np.floor((self.newest - REPORT_PHASE_S)
                                                    / REPORT_PERIOD_S) * REPORT_PERIOD_S)

    def pose_at(self, t: float) -> TcpPose:
        self.looked_up += 1
        if not 0.0 <= t <= self.newest:
            raise LookupError(t)
        return self._pose(t)


def _recorded(tmp_path, cell, robot, until):
    calibration = cell.calibration
    camera = SimpleNamespace(width=calibration.camera.width,
                             height=calibration.camera.height, fps=100.0)
    recording = LiveRecording(tmp_path / "pass", camera=camera, calibration=calibration,
                              settings={})
    image = np.zeros((camera.height, camera.width), np.uint8)
    for i in range(5):
        recording.add(Frame(image, i, 0.5 + 0.01 * i))
    recording.keep(REPORTS_UNTIL_SETTING, until)
    info = recording.finish(robot, clock_offset_s=0.0)
    assert info["path"], info
    return load_recording(info["path"])


def test_the_replay_ends_at_the_report_the_check_read(tmp_path, cell):
    """The check ran when the robot's newest report was off the sample grid and before the
    pass's last frame: the recording holds that report, and its replay's newest is it."""
    robot = _Reporting(newest=10.0)
    robot.connect()
    # a report two frames before the pass's last
    until = REPORT_PHASE_S + np.floor((0.52 - REPORT_PHASE_S) / REPORT_PERIOD_S) * REPORT_PERIOD_S
    assert until * 500 % 1 != 0  # off the grid
    replay = ReplayRobot.of(_recorded(tmp_path, cell, robot, float(until)))
    replay.connect()
    newest = replay.latest()
    assert newest.t == pytest.approx(until, abs=1e-12)
    np.testing.assert_allclose(newest.position, [100.0 * until, 0.0, 0.0], atol=1e-9)
    assert replay.pose_at(0.54).t == 0.54  # the pass's later samples are there all the same


def test_a_cut_off_past_the_pass_is_recorded_to_it_and_a_far_one_is_not_followed(tmp_path,
                                                                                  cell):
    robot = _Reporting(newest=10.0)
    robot.connect()
    until = 0.6 + REPORT_PHASE_S  # 0.06 s after the pass: reports the check waited for
    replay = ReplayRobot.of(_recorded(tmp_path / "near", cell, robot, until))
    replay.connect()
    assert replay.latest().t == pytest.approx(until, abs=1e-12)
    # A cut-off hours after the pass (a clock offset gone wrong): the recording is not held
    # up looking up hours of samples, and the replay's newest is its last sample.
    robot.looked_up = 0
    far = _recorded(tmp_path / "far", cell, robot, 0.5 + REPORTS_AFTER_PASS_S + 3600.0)
    assert robot.looked_up < 1000  # the pass's 0.05 s at 500 Hz and its margins
    replay = ReplayRobot.of(far)
    replay.connect()
    assert replay.latest().t == far.robot_samples[-1, 0] < 1.0


def test_a_check_without_reports_replays_without_any(tmp_path, cell):
    robot = _Reporting(newest=10.0)
    robot.connect()
    replay = ReplayRobot.of(_recorded(tmp_path, cell, robot, None))
    replay.connect()
    with pytest.raises(RuntimeError, match="no robot report"):
        replay.latest()
