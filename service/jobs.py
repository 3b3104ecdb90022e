"""One armed scan, from arming to its stored result: what the engine, the finisher and the
REST handlers know of it (its state, its counters, its latency, its recording)."""
from __future__ import annotations

import threading
import time
import uuid
from dataclasses import dataclass, field

from scanner_core.pipeline import PassAccumulator
from service.live_recording import LiveRecording

__all__ = ["ScanJob", "new_scan_id"]


@dataclass
class ScanJob:
    """One armed scan, from arming to its stored result."""

    scan_id: str
    part: str | None
    created: float
    accumulator: PassAccumulator | None
    state: str = "armed"
    reason: str | None = None
    end_detail: str | None = None
    note: str | None = None
    context: object = None
    frames_dropped: int = 0
    #: Frames lost before frames the trigger holds or ends the pass on: the pass's own only
    #: when a later frame of it comes (``Engine._on_frame``).
    frames_dropped_pending: int = 0
    queue_overflows: int = 0
    worker_errors: list[str] = field(default_factory=list)
    finished: float | None = None
    last_frame_monotonic: float | None = None
    end_monotonic: float | None = None
    latency_ms: dict = field(default_factory=dict)
    marker_ms: float = 0.0
    #: The longest a frame of the pass waited in the camera's buffer, ms (``Engine._acquire``).
    acquisition_lag_ms: float = 0.0
    profiles_ms: float = 0.0
    info: dict = field(default_factory=dict)
    recording: LiveRecording | None = None
    info_extra: dict = field(default_factory=dict)
    #: ^B X_T,place (4, 4) mm: the taught place pose the finished scan's correction starts from.
    taught_place: object = None
    #: The part's CAD model (``scanner_core.cad.PartModel``) the pass's pose is computed
    #: against before the pass ends; None: no pose ahead.
    part_model: object = None
    #: `part_model`'s content hash (``PartModel.version``), reported with the scan.
    part_version: str | None = None
    #: The pose computed before the pass ended (``scanner_core.pose.ahead.PoseAhead``), and
    #: the newest frame with points it was asked for.
    ahead: object = None
    ahead_asked: int = -1
    _in_flight: int = 0
    _idle: threading.Condition = field(default_factory=threading.Condition)

    def queued(self) -> None:
        with self._idle:
            self._in_flight += 1

    def processed(self, elapsed_ms: float = 0.0) -> None:
        with self._idle:
            self.profiles_ms += elapsed_ms
            self._in_flight -= 1
            if self._in_flight == 0:
                self._idle.notify_all()

    def wait_processed(self, timeout: float) -> bool:
        with self._idle:
            return self._idle.wait_for(lambda: self._in_flight == 0, timeout)


def new_scan_id() -> str:
    """Time-ordered, unique, safe as a folder name."""
    return time.strftime("%Y%m%dT%H%M%S", time.gmtime()) + "-" + uuid.uuid4().hex[:8]
