"""The engine's ``/status`` view: camera, robot, trigger, queue, counters and the cross-check's
state, read under the engine's lock (``service.engine.Engine.status``)."""
from __future__ import annotations

import numpy as np

from scanner_core.devices import Robot

__all__ = ["engine_status"]


def engine_status(engine) -> dict:
    """``Engine.status()``: a JSON-ready dict."""
    with engine._lock:
        job = engine.job
        return {
            "state": engine.trigger.state.value,
            "fault_reason": engine.trigger.fault_reason,
            "camera": {"state": engine.camera_state, "error": engine.camera_error,
                       "fps": round(engine.fps, 2), "frames": engine.frames_total,
                       "frames_dropped": engine.frames_dropped,
                       "exposure_mode": (engine.params.exposure.mode if engine.exposure.active
                                         else "fixed"),
                       "exposure_us": _finite_or_none(engine.exposure_seen[0]),
                       "gain": engine.exposure_seen[1],
                       "exposure_updates": engine.exposure.updates,
                       "clock": getattr(engine.camera, "clock_status", None)},
            "robot": _robot_status(engine.robot),
            "fps": round(engine.fps, 2),
            "frames_dropped": engine.frames_dropped,
            "queue": {"depth": engine._frames.qsize(), "capacity": engine._frames.maxsize,
                      "overflows": engine.queue_overflows},
            "current_scan_id": job.scan_id if job and job.state in ("armed", "scanning", "processing") else None,
            "last_scan_id": engine.last_scan_id,
            "scans_done": engine.scans_done,
            "scans_failed": engine.scans_failed,
            "clock_offset_s": engine.clock_offset_s,
            "led_correction_t_mm": (None if engine.cross_check_state.led_correction_t_mm is None
                                    else list(engine.cross_check_state.led_correction_t_mm)),
            "led_correction_from": engine.cross_check_state.led_correction_from,
        }


def _robot_status(robot: Robot) -> dict:
    """``connected``, and what a real robot backend tells of its link (``URRobot.status``)."""
    details = getattr(robot, "status", None)
    return {**(details() if callable(details) else {}), "connected": bool(robot.connected)}


def _finite_or_none(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None
