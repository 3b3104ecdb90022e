"""How well a calibration pass pins the LED's offset (``led_offset_spread``, the views' error
through ``led_views_jackknife``), and how that
uncertainty reaches the calibration file and the pose."""
from __future__ import annotations

import json

import numpy as np
import pytest

from scanner_core.geometry.calibration import Calibration, CalibrationError
from scanner_core.pipeline.crosscheck import estimate_led_and_clock, led_offset_spread
from scanner_core.devices import TcpPose
from scanner_core.pose.registration import PoseParams, PoseResult
from scanner_core.pose.inputs import add_placement_error
from scanner_core.pose.confidence import judge

# {T} in {B}: z_T down, turned 30 degrees about it.
_C, _S = np.cos(np.radians(30)), np.sin(np.radians(30))
ROTATION = np.array([[_C, _S, 0.0], [_S, -_C, 0.0], [0.0, 0.0, -1.0]])
LED_T = np.array([5.0, -3.0, -40.0])
CLOCK_S = 0.0042


def position(t):
    """A pass along -y_B whose speed swings between 150 and 250 mm/s, as a real one does."""
    return np.array([10.0, 50.0 - 200.0 * t - 8.0 * np.sin(2 * np.pi * t / 0.8), 400.0])


class SwingRobot:
    connected = True

    def __init__(self, offset_b=np.zeros(3)):
        self.offset_b = np.asarray(offset_b, dtype=np.float64)

    def latest(self):
        return TcpPose(2.0, position(2.0) + self.offset_b, ROTATION)

    def pose_at(self, t):
        if not -1.0 <= t <= 2.0:
            raise LookupError(t)
        return TcpPose(t, position(t) + self.offset_b, ROTATION)


def marker_track(bias_t=lambda f: np.zeros(3), noise_mm=0.002, seed=0, offset_b=np.zeros(3)):
    """Camera times and the LED's positions in {B}: the robot's track at the robot's clock,
    plus the LED's offset, plus a bias in {T} that changes along the pass (f: 0 to 1)."""
    rng = np.random.default_rng(seed)
    times = np.arange(0.0, 0.8, 1 / 162.0)
    fraction = times / times[-1]
    marker = np.array([position(t + CLOCK_S) + offset_b + ROTATION @ (LED_T + bias_t(f))
                       for t, f in zip(times, fraction)])
    return times, marker + rng.normal(0.0, noise_mm, marker.shape)


def test_a_clean_pass_pins_the_offset_to_microns():
    times, marker = marker_track()
    led, clock, _ = estimate_led_and_clock(times, marker, SwingRobot())
    spread = led_offset_spread(times, marker, SwingRobot(), clock)
    np.testing.assert_allclose(led, LED_T, atol=0.002)
    assert np.all(spread < 0.003), spread


def test_a_bias_that_drifts_along_the_pass_shows_in_the_spread_and_bounds_the_error():
    """A marker bias growing 40 um along y_T over the pass (a blob seen from changing
    angles): the whole pass's fit is off by part of it, and the spread of its quarters' fits
    covers that error within 3 of it, where the fit's residuals alone would not."""
    drift = lambda f: np.array([0.0, 0.04 * f, 0.0])  # noqa: E731
    times, marker = marker_track(drift)
    led, clock, _ = estimate_led_and_clock(times, marker, SwingRobot())
    spread = led_offset_spread(times, marker, SwingRobot(), clock)
    error = led - LED_T
    assert abs(error[1]) > 0.005  # the case bites
    assert np.all(np.abs(error) <= 3.0 * spread + 1e-4), (error, spread)
    assert spread[2] < 0.002  # z_T is across the pass: the clock does not trade against it


def test_too_few_frames_per_stretch_give_no_spread():
    times, marker = marker_track()
    assert np.isnan(led_offset_spread(times[:30], marker[:30], SwingRobot(), CLOCK_S)).all()
    with pytest.raises(ValueError, match="segments"):
        led_offset_spread(times, marker, SwingRobot(), CLOCK_S, segments=1)


#: Moves the pass to where the reference cell's three views see the LED, mm in {B}.
IN_VIEW_B = np.array([75.0, 60.0, -350.0])


def _views_moved(calibration, shift_b):
    """The calibration's camera and mirror planes translated by `shift_b` in {B}, mm: every
    point they triangulate moves by it."""
    from dataclasses import replace

    from scanner_core.geometry import Plane

    camera = replace(calibration.camera, origin=calibration.camera.origin + shift_b)
    planes = [Plane(m.plane.normal, m.plane.offset + float(m.plane.normal @ shift_b))
              for m in calibration.mirrors]
    return camera, planes


def test_the_views_error_moves_the_led_offset_by_its_jackknife():
    """Views refitted ten times, each off by a known translation: the pass's marker moves by
    it, and the LED's offset with it, turned into {T}; the jackknife of the ten offsets gives
    ``sqrt((G - 1) / G sum (R^T s_g - mean)^2)`` per axis, the translation along the pass
    included (the clock does not take a constant shift)."""
    from simulator.cell import load_cell
    from scanner_core.calibration.session import led_views_jackknife

    calibration = load_cell().calibration
    robot = SwingRobot(IN_VIEW_B)
    times, marker = marker_track(noise_mm=0.0, offset_b=IN_VIEW_B)
    led, clock, _ = estimate_led_and_clock(times, marker, robot)
    shifts = np.random.default_rng(5).normal(0.0, [0.002, 0.008, 0.004], (10, 3))
    refits = [_views_moved(calibration, s) for s in shifts]
    std = led_views_jackknife(refits, calibration, times, marker, robot, clock)
    moved_t = shifts @ ROTATION  # rows R^T s
    expected = np.sqrt(np.sum((moved_t - moved_t.mean(axis=0))**2, axis=0) * 9 / 10)
    np.testing.assert_allclose(std, expected, rtol=0.02, atol=2e-5)
    assert np.all(std > 0.003), std  # the case bites: microns on every axis
    same = led_views_jackknife([_views_moved(calibration, np.zeros(3))] * 10, calibration,
                               times, marker, robot, clock)
    assert np.all(same < 1e-5), same
    # a pass the views do not see: no term (the calibration then writes no sigma)
    unseen = led_views_jackknife(refits, calibration, times, marker + 1000.0, robot, clock)
    assert np.isnan(unseen).all()


def test_the_calibration_file_keeps_the_offset_s_uncertainty():
    from dataclasses import replace

    from simulator.cell import load_cell

    reference_calibration = load_cell().calibration
    calibration = replace(reference_calibration, marker_offset_std_mm=np.array([0.001, 0.01, 0.002]))
    again = Calibration.from_dict(calibration.to_dict())
    np.testing.assert_array_equal(again.marker_offset_std_mm, [0.001, 0.01, 0.002])
    assert "marker_offset_std_mm" not in reference_calibration.to_dict()
    assert Calibration.from_dict(reference_calibration.to_dict()).marker_offset_std_mm is None
    for bad in ([0.0, -0.001, 0.0], [0.0, float("nan"), 0.0], [0.0, 0.0, 11.0], [0.1, 0.1]):
        data = calibration.to_dict()
        data["marker_offset_std_mm"] = bad
        with pytest.raises(CalibrationError, match="marker_offset_std_mm"):
            Calibration.from_dict(data)


def test_the_calibration_file_keeps_the_light_plane_s_uncertainty():
    from dataclasses import replace

    from scanner_core.calibration.plane import PlaneUncertainty
    from simulator.cell import load_cell

    reference_calibration = load_cell().calibration
    uncertainty = PlaneUncertainty(np.array([0.0, 1.0, -20.0]),
                                   np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
                                   np.diag([(25e-6) ** 2, (12e-6) ** 2, 0.0005**2]))
    calibration = replace(reference_calibration, light_plane_uncertainty=uncertainty)
    again = Calibration.from_dict(json.loads(json.dumps(calibration.to_dict())))
    np.testing.assert_array_equal(again.light_plane_uncertainty.covariance,
                                  uncertainty.covariance)
    np.testing.assert_array_equal(again.light_plane_uncertainty.centre_b, uncertainty.centre_b)
    assert Calibration.from_dict(reference_calibration.to_dict()).light_plane_uncertainty is None
    data = calibration.to_dict()
    data["light_plane_uncertainty_b"]["covariance"][0][0] = -1.0
    with pytest.raises(CalibrationError, match="light_plane_uncertainty_b.*semi-definite"):
        Calibration.from_dict(data)


def test_the_pose_carries_the_placement_error_whole():
    """A pose whose profiles average their own errors to 4 um along y_T is still off by the
    calibration's marker offset: 10 um of it makes y_T's sigma sqrt(4^2 + 10^2); a free axis
    stays unknown; a tolerance the sum exceeds is not acted on."""
    std = np.array([0.002, 0.004, np.nan, 0.003, 0.003, 0.003])  # mm, degrees
    covariance = np.diag(np.nan_to_num(np.r_[std[:3], np.radians(std[3:])], nan=0.0) ** 2)
    covariance[2, :] = covariance[:, 2] = np.nan
    result = PoseResult(matrix=np.eye(4), misplacement=np.eye(4), rms_mm=0.01,
                        inlier_fraction=0.99, std=std.copy(), covariance=covariance)
    add_placement_error(result, [0.0, 0.010, 0.005])
    assert result.std[0] == pytest.approx(0.002)
    assert result.std[1] == pytest.approx(np.hypot(0.004, 0.010))
    assert np.isnan(result.std[2])
    result.free_axes = []
    result.std[2] = 0.001
    judge(result, None, PoseParams(act_tolerance_mm=0.03))
    assert not result.act and any(r.startswith("ty: 3 sigma") for r in result.act_reasons)
    judge(result, None, PoseParams(act_tolerance_mm=0.1))
    assert result.act
    with pytest.raises(ValueError, match="placement_std_mm"):
        add_placement_error(result, [0.0, -1.0, 0.0])


def test_the_robot_s_orientation_report_turns_the_pose_too():
    """The robot reports its orientation 4 mdeg off (PoseParams.robot_rotation_std_deg): each
    rotation's sigma grows to sqrt(3^2 + 4^2) = 5 mdeg, no translation's does."""
    std = np.array([0.002, 0.002, 0.002, 0.003, 0.003, 0.003])
    covariance = np.diag(np.r_[std[:3], np.radians(std[3:])] ** 2)
    result = PoseResult(matrix=np.eye(4), misplacement=np.eye(4), rms_mm=0.01,
                        inlier_fraction=0.99, std=std.copy(), covariance=covariance)
    add_placement_error(result, np.zeros(3), 0.004)
    np.testing.assert_allclose(result.std, [0.002, 0.002, 0.002, 0.005, 0.005, 0.005])
    with pytest.raises(ValueError, match="robot_rotation_std_deg"):
        PoseParams(robot_rotation_std_deg=-0.001)
