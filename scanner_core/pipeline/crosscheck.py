"""The marker-derived gripper track against the robot's own: the clock offset and the deviation.

Every placed frame gives a TCP position in {B} from the LED marker at a camera time; the robot
reports its TCP on its own clock. The offset between the clocks is estimated from the pass
itself (the track must move: along the pass, one millisecond is a fifth of a millimetre at
200 mm/s), then the deviation between the two tracks at the same instants is reported and
flagged above a tolerance.

The LED's offset from the TCP (``Calibration.marker_offset_t``) is measured by hand in a real
cell; what it misses shows as a constant difference between the tracks, fixed in {T}. That
difference is estimated from a pass (``mean_difference_t_mm``) and, once learned, subtracted
(``led_correction_t_mm``): learned from every pass it would also absorb the very
inconsistencies the check is there to flag, so the service learns it once (its first
cross-checked pass) and keeps it. For the same reason the clock offset, once estimated, may
move by at most ``MAX_DRIFT_STEP_S`` from one pass to the next (real clocks drift by
microseconds per second): along a straight pass at constant speed a clock offset and a shift
along the track look alike.
"""
from __future__ import annotations

import numpy as np

from scanner_core.devices import Robot

#: Deviation above which the cross-check is flagged, mm (the marker's triangulation errs by
#: a few micrometres; a robot that reports a pose 0.1 mm off is worth a look).
DEFAULT_TOLERANCE_MM = 0.1
#: A robot position interpolated over a chord that may lie farther than this from the TCP's
#: path (``TcpPose.interpolation_mm``: samples a loaded reader missed, on a track that
#: accelerates or turns) is no position to check the marker against, mm: a quarter of the
#: default tolerance (or of the tolerance asked, if smaller).
MAX_CHORD_DEVIATION_MM = DEFAULT_TOLERANCE_MM / 4.0
#: Finite-difference step for the robot's velocity, s (a few samples at 500 Hz).
VELOCITY_STEP_S = 0.004
#: The clock offset moves at most this far from its starting value in one estimate, s: along a
#: straight stretch a clock offset and a position error along the track look alike, so a
#: larger move would hide an error the check is there to flag.
MAX_OFFSET_STEP_S = 0.05
#: How far the clock offset may move from one pass's estimate to the next, s, once estimated:
#: 100 ppm of drift over 10 s between passes. A larger jump (0.2 mm along a 200 mm/s track) is
#: an inconsistency, not a clock.
MAX_DRIFT_STEP_S = 0.001
#: Gauss-Newton iterations, and the step below which the estimate has converged, s.
OFFSET_ITERATIONS = 8
OFFSET_CONVERGED_S = 1e-6
#: At most this many frames enter the offset estimate (evenly spread over the pass).
MAX_OFFSET_SAMPLES = 120
#: Below this speed, mm/s, the track does not tell the clocks apart.
MIN_SPEED_MM_S = 1.0


def robot_positions(robot: Robot, times: np.ndarray, max_chord_mm: float = MAX_CHORD_DEVIATION_MM
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) positions and (N,) bool: which times the robot's history covers, with a
    position interpolated no farther than `max_chord_mm` from the path."""
    out = np.full((len(times), 3), np.nan)
    for i, t in enumerate(times):
        try:
            pose = robot.pose_at(float(t))
        except (LookupError, RuntimeError):
            continue
        if pose.interpolation_mm <= max_chord_mm:
            out[i] = pose.position
    return out, np.isfinite(out).all(axis=1)


def track_at(robot: Robot, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The robot's positions (N, 3) and central-difference velocities (N, 3) at robot times, and
    (N,) bool: where its history covers both."""
    p, ok = robot_positions(robot, times)
    ahead, ok_ahead = robot_positions(robot, times + VELOCITY_STEP_S)
    behind, ok_behind = robot_positions(robot, times - VELOCITY_STEP_S)
    return p, (ahead - behind) / (2 * VELOCITY_STEP_S), ok & ok_ahead & ok_behind


def estimate_clock_offset(times, positions_b, robot: Robot, *, initial_s: float = 0.0,
                          max_step_s: float = MAX_OFFSET_STEP_S,
                          difference_b=None) -> float | None:
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
    max_step_s : float
        The estimate may move at most this far from ``initial_s``.
    difference_b : (N, 3) float64, optional
        Known constant differences marker minus robot, {B}, mm (the learned LED correction),
        taken off the marker's positions first.

    Returns
    -------
    float or None
        None when the track is too short or too slow to tell, the robot has no history, the
        estimate does not converge, or it would move more than ``max_step_s`` from
        ``initial_s``.
    """
    times = np.asarray(times, dtype=np.float64)
    positions = np.asarray(positions_b, dtype=np.float64).reshape(-1, 3)
    if difference_b is not None:
        positions = positions - np.asarray(difference_b, dtype=np.float64).reshape(-1, 3)
    if len(times) < 3:
        return None
    pick = np.unique(np.linspace(0, len(times) - 1, min(len(times), MAX_OFFSET_SAMPLES)).astype(int))
    times, positions = times[pick], positions[pick]
    offset = float(initial_s)
    for _ in range(OFFSET_ITERATIONS):
        p, velocity, ok = track_at(robot, times + offset)
        if ok.sum() < 3:
            return None
        velocity = velocity[ok]
        speed2 = np.einsum("ij,ij->i", velocity, velocity)
        if np.sqrt(speed2.mean()) < MIN_SPEED_MM_S:
            return None
        # Minimise sum |m_i - r(t_i + d)|^2: linearise r around the current d.
        step = np.einsum("ij,ij->", positions[ok] - p[ok], velocity) / speed2.sum()
        offset += float(step)
        if abs(offset - initial_s) > max_step_s:
            return None  # not a clock offset: the check measures the deviation instead
        if abs(step) < OFFSET_CONVERGED_S:
            return offset
    return None  # did not converge


def cross_check(times, positions_b, robot: Robot, *, clock_offset_s: float = 0.0,
                estimate_offset: bool = True, max_offset_step_s: float = MAX_OFFSET_STEP_S,
                led_correction_t_mm=None, tolerance_mm: float = DEFAULT_TOLERANCE_MM) -> dict:
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
    max_offset_step_s : float
        How far the estimate may move from ``clock_offset_s`` (``MAX_DRIFT_STEP_S`` once a
        previous pass has estimated it).
    led_correction_t_mm : (3,) array_like, optional
        The learned constant difference marker minus robot in {T}, mm (a correction of the
        calibration's LED offset), taken off before the deviation is measured.
    tolerance_mm : float
        Deviations above this flag the check.

    Returns
    -------
    dict
        ``samples``, ``rms_mm``, ``max_mm``, ``clock_offset_s``, ``offset_estimated``,
        ``mean_difference_t_mm`` (the mean difference marker minus robot in {T} before any
        correction: what the LED offset misses, plus any inconsistency), ``led_correction_t_mm``,
        ``tolerance_mm``, ``flagged`` and ``robot_connected``; ``samples`` 0 (and a ``reason``)
        when the robot had no pose for any frame.
    """
    times = np.asarray(times, dtype=np.float64)
    positions = np.asarray(positions_b, dtype=np.float64).reshape(-1, 3)
    correction = (np.zeros(3) if led_correction_t_mm is None
                  else np.asarray(led_correction_t_mm, dtype=np.float64).reshape(3))
    connected = bool(robot.connected)
    offset, estimated = float(clock_offset_s), False
    result = {"samples": 0, "clock_offset_s": offset, "offset_estimated": False,
              "tolerance_mm": tolerance_mm, "robot_connected": connected,
              "led_correction_t_mm": correction.tolist(), "mean_difference_t_mm": None}
    rotations = robot_rotations(robot, times + offset) if connected and len(times) else None
    if rotations is not None and estimate_offset:
        found = estimate_clock_offset(times, positions, robot, initial_s=offset,
                                      max_step_s=max_offset_step_s,
                                      difference_b=rotations @ correction)
        if found is not None:
            offset, estimated = found, True
    robot_p, ok = (robot_positions(robot, times + offset,
                                    min(MAX_CHORD_DEVIATION_MM, tolerance_mm / 4.0))
                   if len(times) else (np.zeros((0, 3)), np.zeros(0, bool)))
    result |= {"samples": int(ok.sum()), "clock_offset_s": offset, "offset_estimated": estimated}
    if not ok.any() or rotations is None:
        reason = "robot not connected" if not connected else "no robot pose for the pass's times"
        return result | {"samples": 0, "rms_mm": None, "max_mm": None, "flagged": True,
                         "reason": reason}
    difference_b = positions[ok] - robot_p[ok]
    difference_t = np.einsum("nji,nj->ni", rotations[ok], difference_b)  # R^T d
    d = np.linalg.norm(difference_t - correction, axis=1)
    rms, worst = float(np.sqrt(np.mean(d**2))), float(d.max())
    return result | {"rms_mm": rms, "max_mm": worst, "flagged": bool(worst > tolerance_mm),
                     "mean_difference_t_mm": difference_t.mean(axis=0).tolist()}


def robot_rotations(robot: Robot, times: np.ndarray) -> np.ndarray | None:
    """(N, 3, 3) rotations of {T} in {B} at the robot times (the newest known where the history
    has none); None when the robot has given none."""
    out = np.full((len(times), 3, 3), np.nan)
    last = None
    for i, t in enumerate(times):
        try:
            last = np.asarray(robot.pose_at(float(t)).rotation, dtype=np.float64)
        except (LookupError, RuntimeError):
            pass
        if last is not None:
            out[i] = last
    if last is None:
        try:
            last = np.asarray(robot.latest().rotation, dtype=np.float64)
        except RuntimeError:
            return None
    out[~np.isfinite(out).all(axis=(1, 2))] = last
    return out


def estimate_led_and_clock(times, marker_b, robot: Robot, *, initial_offset_s: float = 0.0,
                           iterations: int = OFFSET_ITERATIONS) -> tuple[np.ndarray, float, float]:
    """The LED's offset from the TCP in {T} and the clock offset, from one pass.

    Solves ``M_i = p(t_i + d) + R(t_i + d) m`` for ``m`` (the LED in {T}, mm) and ``d`` (robot
    minus camera clock, s) by Gauss-Newton: ``M_i`` the marker's triangulated positions, ``p``
    and ``R`` the robot's reports. A clock offset moves the robot's track along its velocity and
    the LED offset by a constant: a pass whose speed changes (every real one) tells them apart.

    Parameters
    ----------
    times : (N,) float64
        Camera times, s.
    marker_b : (N, 3) float64
        The LED's positions in {B}, mm.
    robot : Robot
        Reports ``pose_at`` on its own clock.
    initial_offset_s : float

    Returns
    -------
    led_t_mm : (3,) float64
    clock_offset_s : float
    rms_mm : float
        RMS residual of the fit.

    Raises
    ------
    ValueError
        Fewer than 10 frames with a robot pose, or a pass too slow or too uniform to tell
        the clock from the offset.
    """
    times = np.asarray(times, dtype=np.float64)
    marker = np.asarray(marker_b, dtype=np.float64).reshape(-1, 3)
    offset = float(initial_offset_s)
    led = np.zeros(3)
    for _ in range(iterations):
        p, velocity, ok = track_at(robot, times + offset)
        if ok.sum() < 10:
            raise ValueError(f"only {int(ok.sum())} frames have a robot pose: no LED offset")
        a = clock_and_offset_rows(velocity[ok], robot_rotations(robot, times[ok] + offset))
        r = (marker[ok] - p[ok]).ravel()
        sol, *_ = np.linalg.lstsq(a, r, rcond=None)
        if np.linalg.cond(a) > 1e6:
            raise ValueError("the pass does not tell the clock offset from the LED offset "
                             "(too slow, or too uniform a speed)")
        step, led = float(sol[0]), sol[1:]
        offset += step
        if abs(step) < OFFSET_CONVERGED_S:
            break
    res = (r - a @ sol).reshape(-1, 3)
    return led, offset, float(np.sqrt(np.mean(np.sum(res**2, axis=1))))


def clock_and_offset_rows(velocity, rotations) -> np.ndarray:
    """(3N, 4) rows of the LED-and-clock fit's unknowns (d_step, m): the residual
    ``M - p - R m`` is about ``v d_step + R dm``, for (N, 3) `velocity` and (N, 3, 3)
    `rotations`."""
    rows = np.zeros((3 * len(velocity), 4))
    rows[:, 0] = np.asarray(velocity).ravel()
    rows[:, 1:] = np.asarray(rotations).reshape(-1, 3)
    return rows


#: Consecutive stretches of a calibration pass the LED offset is fitted on apart.
LED_SEGMENTS = 4


def led_offset_spread(times, marker_b, robot: Robot, clock_offset_s: float, *,
                      segments: int = LED_SEGMENTS) -> np.ndarray:
    """How well one pass pins the LED's offset in {T}: its standard deviation per {T} axis,
    mm, from the spread of the offsets fitted on `segments` consecutive stretches of the
    pass apart: on each, ``M_i - p(t_i + d) = v_i d_k + R_i m_k`` linearised about
    `clock_offset_s` and solved for its own clock step ``d_k`` and offset ``m_k``; the
    result is the standard error of their mean, ``std_k(m_k) / sqrt(segments)`` (ddof 1).

    Not the fit's own standard error, which takes the frames as independent: the clock and
    the offset along the pass trade against each other through the pass's speed, and what
    biases the marker (the LED's blob seen from each view, the robot's report) changes
    slowly along the pass; its stretches, each with its own clock, disagree by that. Every
    profile of a scan shares that error. Across the pass it misses a bias of the LED's blob
    (docs/calibration.md: both measured against the truth of realistic simulated cells).

    Parameters
    ----------
    times : (N,) float64
        Camera times, s.
    marker_b : (N, 3) float64
        The LED's positions in {B}, mm.
    robot : Robot
    clock_offset_s : float
        Robot minus camera clock, s (`estimate_led_and_clock`'s).
    segments : int
        At least 2.

    Returns
    -------
    (3,) float64
        mm along x_T, y_T, z_T; NaN where fewer than 2 stretches have 10 frames with a pose.
    """
    if segments < 2:
        raise ValueError(f"segments must be at least 2, got {segments}")
    times = np.asarray(times, dtype=np.float64)
    marker = np.asarray(marker_b, dtype=np.float64).reshape(-1, 3)
    p, velocity, ok = track_at(robot, times + clock_offset_s)
    fits = []
    for part in np.array_split(np.nonzero(ok)[0], segments):
        if len(part) < 10:
            continue
        a = clock_and_offset_rows(velocity[part],
                                   robot_rotations(robot, times[part] + clock_offset_s))
        sol, *_ = np.linalg.lstsq(a, (marker[part] - p[part]).ravel(), rcond=None)
        fits.append(sol[1:])
    if len(fits) < 2:
        return np.full(3, np.nan)
    return np.std(np.array(fits), axis=0, ddof=1) / np.sqrt(len(fits))
