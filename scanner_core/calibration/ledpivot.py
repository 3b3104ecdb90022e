"""The LED's offset from the TCP, from the robot's poses: the views calibrated with the robot as
the stage.

With a stage, the LED's positions in {B} are the stage's. With the robot, they are the TCP's
reported poses times the LED's offset in {T}, ``p_j + R_j l``, and ``l`` is known only as drawn
(a real LED sits a few tenths of a millimetre off the drawing). With the tool in one
orientation ``R_0`` an error ``d`` of ``l`` only moves every position by ``R_0 d``: the views
fit as well, in a frame shifted by ``-R_0 d``, and every cloud would come out ``d`` off in {T}.
Turning the tool tells ``l`` from the frame (a pivot calibration): the views fitted on the
poses of the most common orientation triangulate the LED at every pose, ``m_j = p_j + R_j l +
s`` with ``s`` that frame's shift, linear in ``(l, s)``; then the views are fitted again on
every pose with ``l``.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from scanner_core.geometry.triangulation import triangulate_marker

__all__ = ["fit_led_offset", "led_from_robot_poses", "SAME_ORIENTATION_DEG", "MIN_TURN_DEG"]

#: Poses whose tool orientations differ by less than this are of one orientation, degrees (a
#: robot's reported orientation wanders by thousandths of a degree).
SAME_ORIENTATION_DEG = 0.5
#: The poses must turn the tool by at least this about two independent axes, degrees, for the
#: offset to be determined (a 10 degree turn moves a 100 mm offset by 17 mm).
MIN_TURN_DEG = 2.0


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two rotations, degrees (arccos of the trace: fine at these angles)."""
    c = (np.trace(a.T @ b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def fit_led_offset(marker_b, tcp_b) -> tuple[np.ndarray, np.ndarray, float]:
    """Least squares of ``m_j = p_j + R_j l + s`` over the poses.

    Parameters
    ----------
    marker_b : (N, 3) float
        The LED triangulated at each pose, mm in the views' frame (NaN rows are left out).
    tcp_b : (N, 4, 4) float
        The TCP poses ^B X_T the robot reported, mm.

    Returns
    -------
    led_t : (3,) float64
        The LED in {T}, mm.
    shift_b : (3,) float64
        The views' frame minus {B}, mm.
    rms_mm : float
        RMS residual.

    Raises
    ------
    ValueError
        Fewer than 4 poses, or orientations that do not turn about two axes by
        ``MIN_TURN_DEG``: the offset is unobservable.
    """
    marker_b = np.asarray(marker_b, dtype=np.float64).reshape(-1, 3)
    tcp_b = np.asarray(tcp_b, dtype=np.float64).reshape(-1, 4, 4)
    if len(marker_b) != len(tcp_b):
        raise ValueError(f"`marker_b` ({len(marker_b)}) and `tcp_b` ({len(tcp_b)}) must "
                         f"have one row per pose")
    ok = np.isfinite(marker_b).all(axis=1)
    if ok.sum() < 4:
        raise ValueError(f"the LED was triangulated at {ok.sum()} poses: at least 4 are needed")
    r, p, m = tcp_b[ok, :3, :3], tcp_b[ok, :3, 3], marker_b[ok]
    # Rows [R_j, I] (3 per pose); centred on the mean rotation, the columns of l show only
    # the turns, which is what determines it.
    a = np.concatenate([r, np.broadcast_to(np.eye(3), r.shape)], axis=2).reshape(-1, 6)
    b = (m - p).reshape(-1)
    turns = r - r.mean(axis=0)
    spread = np.linalg.svd(turns.reshape(-1, 3), compute_uv=False)
    if spread[1] < np.sqrt(len(r)) * np.radians(MIN_TURN_DEG) * 0.5:
        raise ValueError(f"the LED poses do not turn the tool by {MIN_TURN_DEG} degrees about "
                         f"two axes: the LED's offset from the TCP is unobservable")
    x, *_ = np.linalg.lstsq(a, b, rcond=None)
    residual = a @ x - b
    return x[:3], x[3:], float(np.sqrt(np.mean(residual.reshape(-1, 3)**2) * 3))


def led_from_robot_poses(tcp_b, led_px, led_nominal_t, views_of: Callable
                         ) -> tuple[np.ndarray, dict]:
    """The LED's positions in {B} at the robot's poses, and the report of the fit.

    Parameters
    ----------
    tcp_b : (N, 4, 4) float
        Reported TCP poses, mm.
    led_px : (N, V, 2) float
        The LED's centroid per pose and view, px (NaN where not seen).
    led_nominal_t : (3,) float
        The LED's offset as drawn, mm in {T}: the positions of the first fit.
    views_of : callable
        ``views_of(points_b, pixels) -> (camera, mirrors)``: the views fitted to LED positions
        (``scanner_core.calibration.session`` passes ``calibrate_views``).

    Returns
    -------
    positions_b : (N, 3) float64
        ``p_j + R_j l``, mm.
    report : dict
        ``led_t_mm``, ``frame_shift_mm`` (of the first fit), ``rms_mm``, ``poses``, ``turned``.
    """
    tcp_b = np.asarray(tcp_b, dtype=np.float64)
    led_px = np.asarray(led_px, dtype=np.float64)
    rotations, positions = tcp_b[:, :3, :3], tcp_b[:, :3, 3]
    # The most common orientation: the pose with the most others within SAME_ORIENTATION_DEG.
    close = np.array([[_angle_deg(a, b) < SAME_ORIENTATION_DEG for b in rotations]
                      for a in rotations])
    base = close[int(np.argmax(close.sum(axis=1)))]
    nominal = positions + rotations @ np.asarray(led_nominal_t, dtype=np.float64)
    camera, mirrors = views_of(nominal[base], led_px[base])
    marker = np.full((len(tcp_b), 3), np.nan)
    for j, px in enumerate(led_px):
        if np.isfinite(px[:, 0]).sum() >= 2:
            marker[j] = triangulate_marker(px, camera, mirrors)[0]
    led_t, shift, rms = fit_led_offset(marker, tcp_b)
    report = {"led_t_mm": led_t.tolist(), "frame_shift_mm": shift.tolist(), "rms_mm": rms,
              "poses": int(len(tcp_b)), "turned": int((~base).sum())}
    return positions + rotations @ led_t, report
