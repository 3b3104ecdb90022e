"""The robot an emulated UR controller reports (``simulator.rtde_emulator``): its clocks, its
TCP on the simulated track, and the values of every output variable at each sample.

It lives in the emulator's process (``simulator.rtde_server``). The TCP follows the same track
as the live simulated cell (``simulator.track.TrackSegment`` and ``tcp_on_track``), so what a
client reads can be checked against ground truth. Sample ``k`` is the robot's state at robot
time ``k / 500`` s; the robot clock is the camera clock plus ``clock_offset_s``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from scanner_core.io.rtde import MAX_FREQUENCY_HZ, TYPE_FORMATS, output_type, ur_pose
from simulator.track import tcp_on_track

#: The controller's cycle (e-Series): samples are sent on this grid of the robot clock.
ROBOT_RATE_HZ = MAX_FREQUENCY_HZ
#: Constant values of an idle, healthy robot (others are zero): RUNNING, NORMAL, PLAYING.
_CONSTANTS = {"robot_mode": (7,), "safety_mode": (1,), "safety_status": (1,),
              "runtime_state": (2,), "speed_scaling": (1.0,), "target_speed_fraction": (1.0,),
              "actual_main_voltage": (48.0,), "actual_robot_voltage": (48.0,)}


@dataclass
class _Track:
    """What the emulated robot does: its clocks and the TCP's track in {B}."""

    epoch: float
    clock_offset_s: float = 0.0
    rotvec: tuple = (0.0, 0.0, 0.0)
    idle_tcp_b: np.ndarray = field(default_factory=lambda: np.zeros(3))
    segments: list = field(default_factory=list)
    bias_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def robot_now(self) -> float:
        """Robot clock now, s."""
        return time.monotonic() - self.epoch + self.clock_offset_s

    def monotonic_of(self, t_robot: float) -> float:
        """``time.monotonic()`` at which the robot clock reads ``t_robot``."""
        return t_robot - self.clock_offset_s + self.epoch

    def tcp_b_mm(self, t_robot: float) -> np.ndarray:
        """(3,) float64: TCP in {B}, mm, at robot time ``t_robot`` (bias included)."""
        return tcp_on_track(self.segments, self.idle_tcp_b,
                            t_robot - self.clock_offset_s) + self.bias_mm

    def prune(self, keep_s: float = 60.0) -> None:
        """Forget segments replaced by a later one more than ``keep_s`` ago."""
        t_cam = self.robot_now() - self.clock_offset_s
        while len(self.segments) > 1 and self.segments[1].robot_start_t < t_cam - keep_s:
            self.segments.pop(0)


class _Sample:
    """The values of sample ``k``, computed on first use (shared by every client)."""

    def __init__(self, track: _Track, k: int):
        self.track, self.t = track, k / ROBOT_RATE_HZ
        self._cache: dict = {}

    def _pose(self, t: float) -> tuple:
        return tuple(float(x) for x in ur_pose(self.track.tcp_b_mm(t), self.track.rotvec))

    def value(self, name: str) -> tuple:
        if name in self._cache:
            return self._cache[name]
        if name == "timestamp":
            v = (self.t,)
        elif name in ("actual_TCP_pose", "target_TCP_pose"):
            v = self._pose(self.t)
        elif name in ("actual_TCP_speed", "target_TCP_speed"):
            dt = 0.5e-3  # a central difference: the track is smooth at this scale
            a, b = self._pose(self.t - dt), self._pose(self.t + dt)
            v = (*((y - x) / (2 * dt) for x, y in zip(a[:3], b[:3])), 0.0, 0.0, 0.0)
        else:
            v = _CONSTANTS.get(name) or _zeros(output_type(name))
        self._cache[name] = v
        return v


def _zeros(rtde_type: str) -> tuple:
    fmt = TYPE_FORMATS[rtde_type]
    n = int(fmt[:-1]) if len(fmt) > 1 else 1
    zero = False if fmt == "?" else (0.0 if fmt[-1] == "d" else 0)
    return (zero,) * n
