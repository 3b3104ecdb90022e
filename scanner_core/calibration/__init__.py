"""Calibrating a cell: the plan a robot follows, the session of frames it records, the light
plane from a sphere (paper, section II-A), the camera and mirrors from LED views.

This is the package's public face; its modules hold the code."""
from __future__ import annotations

from scanner_core.calibration.plan import (TILT_DEG, TILTED_FRACTION, PlanGeometry, PlanStep, CalibrationPlan, make_plan, led_targets, sphere_targets, plan_to_dict, plan_from_dict, PLAN_FORMAT, TILT_AXES)
from scanner_core.calibration.session import (Session, SessionError, SessionWriter, SESSION_FORMAT, SESSION_VERSION, calibrate_session, load_session, write_session, observe_led, observe_sphere)
from scanner_core.calibration.ledpivot import (fit_led_offset, led_from_robot_poses, SAME_ORIENTATION_DEG, MIN_TURN_DEG)

__all__ = ["TILT_DEG", "TILTED_FRACTION", "PlanGeometry", "PlanStep", "CalibrationPlan", "make_plan", "led_targets", "sphere_targets", "plan_to_dict", "plan_from_dict", "PLAN_FORMAT", "TILT_AXES", "Session", "SessionError", "SessionWriter", "SESSION_FORMAT", "SESSION_VERSION", "calibrate_session", "load_session", "write_session", "observe_led", "observe_sphere", "fit_led_offset", "led_from_robot_poses", "SAME_ORIENTATION_DEG", "MIN_TURN_DEG"]
