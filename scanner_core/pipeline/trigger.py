"""The pass trigger: an explicit state machine fed one frame observation at a time.

The LED marker on the gripper triggers the scan (paper section V): once armed, the first frame
that shows the marker starts the pass, and the pass ends once the marker has been gone for
``gap_frames`` frames in a row. Frames without the marker inside the pass (a view hidden for a
moment) are held back and released when the marker comes back, so they belong to the pass (they
are processed, and counted as unplaced when their marker cannot be triangulated); those after
the end are not. A pass also ends when it runs too long (a marker that never leaves the view),
or when the camera stops; an armed trigger that never sees the marker times out.

States, as a commercial profiler reports them::

    idle --arm--> armed --marker--> scanning --end--> processing --finish--> idle
      any --fault(reason)--> fault --reset--> idle;   any --reset--> idle

The trigger holds no frames of its own type: it holds whatever items the caller feeds it
(frames, or frames with their marker observation) and hands them back in order.
"""
from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any


class TriggerState(str, Enum):
    IDLE = "idle"
    ARMED = "armed"
    SCANNING = "scanning"
    PROCESSING = "processing"
    FAULT = "fault"


class EndReason(str, Enum):
    """Why a pass (or an armed wait) ended."""

    MARKER_GONE = "marker gone"
    TIMEOUT = "timeout"
    CAMERA_STOPPED = "camera stopped"
    TOO_LONG = "too long"
    RESET = "reset"


class TriggerError(RuntimeError):
    """An operation that the trigger's current state does not allow (arming while scanning)."""


@dataclass(frozen=True)
class TriggerParams:
    """Settings of the trigger.

    Attributes
    ----------
    gap_frames : int
        The pass ends after this many consecutive frames without the marker.
    max_pass_s : float
        A pass longer than this (camera clock, s) ends as "too long": a marker that never
        leaves the view must not make a pass that never ends.
    arm_timeout_s : float
        An armed trigger that has not seen the marker for this long (camera clock, s) ends as
        "timeout". ``inf`` waits for ever (the offline command, whose stream ends by itself).
    """

    gap_frames: int = 3
    max_pass_s: float = 10.0
    arm_timeout_s: float = 30.0

    def __post_init__(self):
        if int(self.gap_frames) < 1:
            raise ValueError(f"`gap_frames` must be >= 1, got {self.gap_frames}")
        if not self.max_pass_s > 0 or not self.arm_timeout_s > 0:
            raise ValueError("`max_pass_s` and `arm_timeout_s` must be > 0, got "
                             f"{self.max_pass_s}, {self.arm_timeout_s}")


@dataclass
class TriggerStep:
    """What one fed frame decided.

    Attributes
    ----------
    emit : list
        Items to process now, in order (held items released first, then this one).
    ended : EndReason or None
        The pass (or the armed wait) ended at this frame.
    """

    emit: list = field(default_factory=list)
    ended: EndReason | None = None


class Trigger:
    """The pass trigger (module docstring). Not thread-safe: one thread feeds it."""

    def __init__(self, params: TriggerParams = TriggerParams()):
        self.params = params
        self.state = TriggerState.IDLE
        self.end_reason: EndReason | None = None
        self.fault_reason: str | None = None
        self._held: list[Any] = []
        self._armed_t: float | None = None
        self._timeout_s = params.arm_timeout_s
        self._start_t: float | None = None
        self.first_frame: Hashable | None = None
        self.last_frame: Hashable | None = None

    def arm(self, timeout_s: float | None = None) -> None:
        """Wait for the next pass, at most ``timeout_s`` (default ``params.arm_timeout_s``).
        Allowed from idle only (a pass in progress is never cut)."""
        if self.state is not TriggerState.IDLE:
            raise TriggerError(f"cannot arm while {self.state.value}")
        if timeout_s is not None and not timeout_s > 0:
            raise ValueError(f"`timeout_s` must be > 0, got {timeout_s}")
        self._timeout_s = self.params.arm_timeout_s if timeout_s is None else float(timeout_s)
        self.state = TriggerState.ARMED
        self.end_reason = None
        self._armed_t = self._start_t = None
        self.first_frame = self.last_frame = None
        self._held.clear()

    def feed(self, item: Any, t: float, present: bool, frame_id: Hashable = None) -> TriggerStep:
        """One frame: ``t`` its camera time (s), ``present`` whether it shows the marker."""
        step = TriggerStep()
        if self.state is TriggerState.ARMED:
            if self._armed_t is None:
                self._armed_t = t
            if present:
                self.state = TriggerState.SCANNING
                self._start_t = t
                self.first_frame = frame_id
                self._take(step, item, frame_id)
            elif t - self._armed_t >= self._timeout_s:
                self._end(step, EndReason.TIMEOUT)
        elif self.state is TriggerState.SCANNING:
            if t - self._start_t > self.params.max_pass_s:
                self._end(step, EndReason.TOO_LONG)
            elif present:
                step.emit.extend(self._held)
                self._held.clear()
                self._take(step, item, frame_id)
            else:
                self._held.append(item)
                if len(self._held) >= self.params.gap_frames:
                    self._end(step, EndReason.MARKER_GONE)
        return step

    def camera_stopped(self) -> TriggerStep:
        """The camera stopped delivering: an armed wait or a pass in progress ends."""
        step = TriggerStep()
        if self.state in (TriggerState.ARMED, TriggerState.SCANNING):
            self._end(step, EndReason.CAMERA_STOPPED)
        return step

    def finish(self) -> None:
        """The pass's processing is over: back to idle."""
        if self.state is TriggerState.PROCESSING:
            self.state = TriggerState.IDLE

    def fault(self, reason: str) -> None:
        """Nothing can be scanned until ``reset`` (end any pass with ``camera_stopped`` first:
        a pass still held here is dropped)."""
        self.state = TriggerState.FAULT
        self.fault_reason = reason
        self._held.clear()

    def reset(self) -> TriggerStep:
        """Back to idle from any state; a pass in progress ends as "reset"."""
        step = TriggerStep()
        if self.state in (TriggerState.ARMED, TriggerState.SCANNING):
            self._end(step, EndReason.RESET)
        self.state = TriggerState.IDLE
        self.fault_reason = None
        return step

    def _take(self, step: TriggerStep, item, frame_id) -> None:
        step.emit.append(item)
        self.last_frame = frame_id

    def _end(self, step: TriggerStep, reason: EndReason) -> None:
        # Held frames after the pass's last marker frame are not part of it.
        self._held.clear()
        step.ended = self.end_reason = reason
        scanned = self.state is TriggerState.SCANNING
        self.state = TriggerState.PROCESSING if scanned else TriggerState.IDLE
