"""The robot's track through the live simulated cell's passes, on the camera clock.

A :class:`TrackSegment` is the robot's motion through one pass (``simulator.motion.PassMotion``
placed on the camera clock), pure and picklable; :func:`tcp_on_track` gives the TCP at any time
from a schedule of them; :func:`pass_frame_count` is how many camera frames a pass spans. The
live simulated robot (``simulator.live``) and the RTDE emulator (``simulator.rtde_emulator``,
in another process) both compute the TCP from these, so that the two agree to the bit.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from simulator.cell import PassProfile
from simulator.motion import PassMotion

__all__ = ["TrackSegment", "tcp_on_track", "pass_frame_count"]


def pass_frame_count(profile: PassProfile) -> int:
    """Frames a pass spans from lead-in to lead-out (as ``SimCamera.frame_count``)."""
    duration = PassMotion(profile).duration_s
    return int(np.floor((profile.lead_in_s + duration + profile.lead_out_s) * profile.fps)) + 1


@dataclass(frozen=True)
class TrackSegment:
    """The robot's motion through one pass, on the camera clock: pure and picklable.

    The simulated robot of the cell and the RTDE emulator (``simulator.rtde_emulator``, in
    another process) both compute the TCP from these, so that the two agree to the bit.

    Attributes
    ----------
    robot_start_t : float
        Camera clock, s, from which the robot follows this segment.
    t_zero : float
        Camera clock, s, of the pass's t = 0 (the end of its lead-in).
    t_last : float
        Camera clock, s, at which the robot stops (held there afterwards).
    profile : PassProfile
    """

    robot_start_t: float
    t_zero: float
    t_last: float
    profile: PassProfile
    # Built once: tcp_position runs for every robot sample.
    _motion: PassMotion = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "_motion", PassMotion(self.profile))

    def __getstate__(self):
        return (self.robot_start_t, self.t_zero, self.t_last, self.profile)

    def __setstate__(self, state):
        for name, value in zip(("robot_start_t", "t_zero", "t_last", "profile"), state):
            object.__setattr__(self, name, value)
        self.__post_init__()

    def tcp_position(self, t_cam: float) -> np.ndarray:
        """(3,) float64, mm in {B}: the TCP at camera clock ``t_cam``, s, held after ``t_last``."""
        return self._motion.tcp_position(min(t_cam, self.t_last) - self.t_zero)


def tcp_on_track(segments, idle_tcp_b: np.ndarray, t_cam: float) -> np.ndarray:
    """The TCP at camera clock ``t_cam`` given a schedule of segments.

    Parameters
    ----------
    segments : sequence of TrackSegment
        In time order (increasing ``robot_start_t``).
    idle_tcp_b : (3,) float64
        Where the robot waits before the first segment, mm in {B}.
    t_cam : float
        Camera clock, s.

    Returns
    -------
    (3,) float64
        TCP position in {B}, mm: that of the last segment started at ``t_cam``, else idle.
    """
    for seg in reversed(segments):
        if t_cam >= seg.robot_start_t:
            return seg.tcp_position(t_cam)
    return idle_tcp_b
