"""The robot a spec names: a UR robot through ur-rtde, a recording's samples, or none.

``ur://HOST`` is a UR controller (``service.ur_robot.URRobot``); ``replay:FOLDER`` answers
from a recorded pass's robot samples (``scanner_core.recording.replay.ReplayRobot``), as ``replay:FOLDER``
cameras give its frames; no spec is a cell without a robot (:class:`NoRobot`).
"""
from __future__ import annotations

__all__ = ["ROBOT_SPEC_FORMS", "NoRobot", "open_robot"]

#: What a robot spec may be.
ROBOT_SPEC_FORMS = ("ur://HOST                  a UR controller (ur-rtde, RTDE port 30004)",
                    "replay:FOLDER              a recorded pass's robot samples")


class NoRobot:
    """The robot of a cell without one: never connected (scans hold the last rotation they
    were given; without one they cannot be placed, and say so)."""

    connected = False

    def connect(self) -> None:
        pass

    def disconnect(self) -> None:
        pass

    def latest(self):
        raise RuntimeError("no robot is configured (--robot ur://HOST)")

    def pose_at(self, t: float):
        raise RuntimeError("no robot is configured (--robot ur://HOST)")


def open_robot(spec: str | None):
    """The robot of ``spec`` (not connected yet); ValueError naming the forms accepted."""
    if spec is None:
        return NoRobot()
    spec = str(spec)
    if spec.startswith("ur://"):
        from service.ur_robot import URRobot, parse_robot_url

        return URRobot(parse_robot_url(spec))
    if spec.startswith("replay:"):
        from scanner_core.recording import load_recording
        from scanner_core.recording.replay import ReplayRobot

        return ReplayRobot.of(load_recording(spec[len("replay:"):]))
    forms = "\n  ".join(ROBOT_SPEC_FORMS)
    raise ValueError(f"unknown robot {spec!r}; accepted forms:\n  {forms}")
