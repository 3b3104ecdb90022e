"""The marker-derived gripper track against the robot's own: the clock offset and the deviation.

Every placed frame gives a TCP position in {B} from the LED marker at a camera time; the robot
reports its TCP on its own clock. The offset between the clocks is estimated from the pass
itself (the track must move: along the pass, one millisecond is a fifth of a millimetre at
200 mm/s), then the deviation between the two tracks at the same instants is reported and
flagged above a tolerance.
"""
from __future__ import annotations

import numpy as np

from scanner_core.devices import Robot

#: Deviation above which the cross-check is flagged, mm (the marker's triangulation errs by
#: a few micrometres; a robot that reports a pose 0.1 mm off is worth a look).
DEFAULT_TOLERANCE_MM = 0.1
#: Finite-difference step for the robot's velocity, s (a few samples at 500 Hz).
VELOCITY_STEP_S = 0.004
#: The clock offset moves at most this far from its starting value in one estimate, s: along a
#: straight stretch a clock offset and a position error along the track look alike, so a
#: larger move would hide an error the check is there to flag.
MAX_OFFSET_STEP_S = 0.05
#: Gauss-Newton iterations, and the step below which the estimate has converged, s.
OFFSET_ITERATIONS = 8
OFFSET_CONVERGED_S = 1e-6
#: At most this many frames enter the offset estimate (evenly spread over the pass).
MAX_OFFSET_SAMPLES = 120
#: Below this speed, mm/s, the track does not tell the clocks apart.
MIN_SPEED_MM_S = 1.0


def _robot_positions(robot: Robot, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) positions and (N,) bool: which times the robot's history covers."""
    out = np.full((len(times), 3), np.nan)
    for i, t in enumerate(times):
        try:
            out[i] = robot.pose_at(float(t)).position
        except (LookupError, RuntimeError):
            pass
    return out, np.isfinite(out).all(axis=1)


def estimate_clock_offset(times, positions_b, robot: Robot, *, initial_s: float = 0.0) -> float | None:
    """Robot clock minus camera clock, s, from one pass's track (Gauss-Newton on the offset).

    Parameters
    ----------
    times : (N,) float64
        Camera times of the marker-derived positions, s.
    positions_b : (N, 3) float64
        Marker-derived TCP positions in {B}, mm.
    robot : Robot
    initial_s : float
        Start of the search (the previous pass's estimate).

    Returns
    -------
    float or None
        None when the track is too short or too slow to tell, the robot has no history, the
        estimate does not converge, or it would move more than ``MAX_OFFSET_STEP_S`` from
        ``initial_s``.
    """
    times = np.asarray(times, dtype=np.float64)
    positions = np.asarray(positions_b, dtype=np.float64).reshape(-1, 3)
    if len(times) < 3:
        return None
    pick = np.unique(np.linspace(0, len(times) - 1, min(len(times), MAX_OFFSET_SAMPLES)).astype(int))
    times, positions = times[pick], positions[pick]
    offset = float(initial_s)
    for _ in range(OFFSET_ITERATIONS):
        p, ok = _robot_positions(robot, times + offset)
        ahead, ok_ahead = _robot_positions(robot, times + offset + VELOCITY_STEP_S)
        behind, ok_behind = _robot_positions(robot, times + offset - VELOCITY_STEP_S)
        ok &= ok_ahead & ok_behind
        if ok.sum() < 3:
            return None
        velocity = (ahead[ok] - behind[ok]) / (2 * VELOCITY_STEP_S)
        speed2 = np.einsum("ij,ij->i", velocity, velocity)
        if np.sqrt(speed2.mean()) < MIN_SPEED_MM_S:
            return None
        # Minimise sum |m_i - r(t_i + d)|^2: linearise r around the current d.
        step = np.einsum("ij,ij->", positions[ok] - p[ok], velocity) / speed2.sum()
        offset += float(step)
        if abs(offset - initial_s) > MAX_OFFSET_STEP_S:
            return None  # not a clock offset: the check measures the deviation instead
        if abs(step) < OFFSET_CONVERGED_S:
            return offset
    return None  # did not converge


def cross_check(times, positions_b, robot: Robot, *, clock_offset_s: float = 0.0,
                estimate_offset: bool = True, tolerance_mm: float = DEFAULT_TOLERANCE_MM) -> dict:
    """Marker-derived TCP positions against the robot's at the same instants.

    Parameters
    ----------
    times : (N,) float64
        Camera times, s.
    positions_b : (N, 3) float64
        Marker-derived TCP positions, {B}, mm.
    robot : Robot
    clock_offset_s : float
        Robot minus camera clock, s: used as is, or as the start of the estimate.
    estimate_offset : bool
    tolerance_mm : float
        Deviations above this flag the check.

    Returns
    -------
    dict
        ``samples``, ``rms_mm``, ``max_mm``, ``clock_offset_s``, ``offset_estimated``,
        ``tolerance_mm``, ``flagged`` and ``robot_connected``; ``samples`` 0 (and a
        ``reason``) when the robot had no pose for any frame.
    """
    times = np.asarray(times, dtype=np.float64)
    positions = np.asarray(positions_b, dtype=np.float64).reshape(-1, 3)
    connected = bool(robot.connected)
    offset, estimated = float(clock_offset_s), False
    if estimate_offset and connected:
        found = estimate_clock_offset(times, positions, robot, initial_s=offset)
        if found is not None:
            offset, estimated = found, True
    robot_p, ok = _robot_positions(robot, times + offset) if len(times) else (np.zeros((0, 3)), np.zeros(0, bool))
    result = {"samples": int(ok.sum()), "clock_offset_s": offset, "offset_estimated": estimated,
              "tolerance_mm": tolerance_mm, "robot_connected": connected}
    if not ok.any():
        reason = "robot not connected" if not connected else "no robot pose for the pass's times"
        return result | {"rms_mm": None, "max_mm": None, "flagged": True, "reason": reason}
    d = np.linalg.norm(positions[ok] - robot_p[ok], axis=1)
    rms, worst = float(np.sqrt(np.mean(d**2))), float(d.max())
    return result | {"rms_mm": rms, "max_mm": worst, "flagged": bool(worst > tolerance_mm)}
