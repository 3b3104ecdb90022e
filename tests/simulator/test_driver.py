"""The simulated robot program (``simulator.driver.SimPassDriver``): a calibration session's
pass, announced by ``park(calibration_pass=True)``, speeds up to its middle and down again;
the passes of scans keep the cell's own shape."""
from types import SimpleNamespace

import numpy as np

from simulator.driver import SimPassDriver
from simulator.live import PassInProgress


class _Cell:
    """What the driver asks of the live cell: its pass, the pose it parks at, the passes."""

    def __init__(self, cell):
        self.cell, self.idle_tcp_b, self.profiles, self.holds = cell, np.zeros(3), [], []

    busy_calls = 0  # how many more calls find the previous pass's lead-out under way

    def _busy(self):
        if self.busy_calls > 0:
            self.busy_calls -= 1
            raise PassInProgress("the simulated robot is in a pass")

    def hold(self, pose, truth):
        self._busy()
        self.holds.append(pose)

    def prepare_pass(self, part, misplacement, *, profile=None):
        return None

    def start_pass(self, part, misplacement, *, profile=None):
        self._busy()
        self.profiles.append(profile)
        return SimpleNamespace(segment=None)


def test_only_the_announced_calibration_pass_is_peaked(cell):
    live = _Cell(cell)
    driver = SimPassDriver(live)
    driver._simulated = lambda part: part  # the part itself does not matter here
    driver.start_pass("demo", None)
    driver.park(calibration_pass=True)
    driver.start_pass("demo", None)
    driver.start_pass("demo", None)
    driver.park()
    driver.start_pass("demo", None)
    shapes = [None if p is None else p.speed_shape for p in live.profiles]
    assert shapes == [None, "peak", None, None]  # None: the cell's own pass ("ramp")
    peaked = live.profiles[1]
    assert peaked.speed_mm_s == cell.pass_profile.speed_mm_s and len(live.holds) == 2


def test_a_pass_no_longer_wanted_is_not_started(cell):
    live = _Cell(cell)
    driver = SimPassDriver(live)
    driver._simulated = lambda part: part
    driver.start_pass("demo", None, wanted=lambda: False)  # its scan timed out meanwhile
    driver.start_pass("demo", None)
    assert len(live.profiles) == 1


def test_the_robot_finishes_a_pass_s_lead_out_before_it_parks_or_holds(cell):
    """A scan is done when the marker has left; the robot's lead-out goes on a little longer,
    and a calibration step asked for then must wait for it, not fail."""
    live = _Cell(cell)
    driver = SimPassDriver(live)
    driver._scenes = SimpleNamespace(truth=lambda kind, tcp_b: None)
    live.busy_calls = 3
    driver.hold("led", np.eye(4))
    live.busy_calls = 2
    driver.park()
    assert len(live.holds) == 2 and live.busy_calls == 0
