"""The drivers of the streaming core: frames in, the scan of a pass out.

:func:`run_pass` is the single-threaded driver (``flyscan scan``, the benchmarks): each frame
goes through :func:`feed_frame` (the tracked marker, the trigger, and the profiles of the
frames the trigger releases, :func:`measure_frame`). The service runs the same pieces with the
marker and trigger on its acquisition thread and :func:`measure_frame` (or
``scanner_core.pipeline.frame.process_frame`` + ``PassAccumulator.add``) on worker threads.
:func:`camera_frames` turns a camera into a stream of frames.
"""
from __future__ import annotations

import time
from collections.abc import Iterable, Iterator

from scanner_core.geometry.calibration import Calibration
from scanner_core.devices import Camera, CameraClosed, CameraTimeout, Robot
from scanner_core.pipeline.exposure import ExposureController
from scanner_core.pipeline.accumulate import PassAccumulator
from scanner_core.pipeline.frame import (MarkerTracker, PipelineParams, marker_in_view,
                                         process_frame)
from scanner_core.pipeline.trigger import Trigger, TriggerStep
from scanner_core.types import Frame, MarkerObservation, Scan

__all__ = ["camera_frames", "measure_frame", "feed_frame", "run_pass"]


def camera_frames(camera: Camera, timeout: float = 1.0) -> Iterator[Frame]:
    """The camera's frames until its stream ends (``CameraClosed``); ``CameraTimeout``
    propagates (the camera stopped)."""
    while True:
        try:
            yield camera.grab(timeout)
        except CameraClosed:
            return


def measure_frame(frame: Frame, marker: MarkerObservation, accumulator: PassAccumulator,
                  params: PipelineParams, exposure: ExposureController | None = None) -> bool:
    """One triggered frame: its profile (in the geometric window of the robot's rotation at
    its time), placed; exposure control learns from its stripe. Returns whether it was
    placed. Thread-safe (the service's workers)."""
    looked_up = accumulator.rotation_at(frame.t) if marker.valid else None
    profile = process_frame(frame, accumulator.calibration, params, marker,
                            None if looked_up is None else looked_up[0],
                            accumulator.expected_rows(frame.frame_id))
    if exposure is not None:
        exposure.profile_measured(profile.exposure_us, profile.gain, profile.stripe_peaks,
                                  profile.background_dn)
    return accumulator.add(profile, looked_up)


def feed_frame(frame: Frame, tracker: MarkerTracker, trigger: Trigger,
               accumulator: PassAccumulator, params: PipelineParams,
               timings: dict | None = None,
               exposure: ExposureController | None = None) -> TriggerStep:
    """One frame through the single-threaded core: the tracked marker, the trigger, and the
    profiles of the frames it releases, placed. Adds seconds to ``timings["marker"]`` and
    ``timings["profiles"]`` when given. (The service runs the same steps on two threads.)"""
    if exposure is not None:
        exposure.frame_grabbed(frame.exposure_us, frame.gain)
    t0 = time.perf_counter()
    marker = tracker.observe(frame)
    t1 = time.perf_counter()
    step = trigger.feed((frame, marker), frame.t, marker_in_view(marker), frame.frame_id)
    for held_frame, held_marker in step.emit:
        measure_frame(held_frame, held_marker, accumulator, params, exposure)
    if timings is not None:
        timings["marker"] += t1 - t0
        timings["profiles"] += time.perf_counter() - t1
    return step


def run_pass(frames: Iterable[Frame], calibration: Calibration, robot: Robot,
             params: PipelineParams = PipelineParams(), *, clock_offset_s: float = 0.0,
             exposure: ExposureController | None = None) -> Scan:
    """A stream of frames -> the scan of the first pass it contains, on one thread.

    The trigger is armed at the first frame. Wall time per stage lands in
    ``Scan.timings_ms``: ``acquire`` (waiting for / producing frames), ``marker`` (the tracked
    search, which is also the trigger's presence test), ``profiles`` (stripe, triangulation,
    placement) and ``scan`` (assembling the sorted cloud). A camera that stops mid-pass (it
    raises ``CameraTimeout``, or its stream ends) ends the pass: what was acquired is kept and
    ``Scan.end_reason`` says why. ``exposure`` drives the camera's exposure during the pass
    (``scanner_core.pipeline.exposure``).
    """
    timings = dict.fromkeys(("acquire", "marker", "profiles", "scan"), 0.0)
    trigger = Trigger(params.trigger)
    trigger.arm()
    tracker = MarkerTracker(calibration, params)
    accumulator = PassAccumulator(calibration, robot, clock_offset_s,
                                  merge_exposure_pairs=params.exposure.mode == "multiple",
                                  partly_lit_ratio=params.partly_lit_ratio,
                                  measured_box_t=params.measured_box_t)
    source = iter(frames)
    camera_error = None
    while trigger.state.value in ("armed", "scanning"):
        t0 = time.perf_counter()
        try:
            frame = next(source)
        except StopIteration:
            trigger.camera_stopped()
            break
        except CameraTimeout as exc:
            camera_error = f"camera timeout: {exc}"
            trigger.camera_stopped()
            break
        timings["acquire"] += time.perf_counter() - t0
        feed_frame(frame, tracker, trigger, accumulator, params, timings, exposure)
    t0 = time.perf_counter()
    scan = accumulator.scan(end_reason=trigger.end_reason,
                            stopped_because=camera_error or "camera stream ended")
    timings["scan"] = time.perf_counter() - t0
    scan.timings_ms = {k: round(v * 1e3, 3) for k, v in timings.items()}
    return scan
