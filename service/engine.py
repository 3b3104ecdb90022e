"""The daemon's acquisition engine: one thread owns the camera, workers process the pass.

The acquisition thread grabs every frame, counts gaps in the frame ids (dropped frames), and,
while a scan is armed or in progress, finds the marker (tracked from frame to frame) and feeds
the trigger. The frames of a pass go through a bounded queue to worker threads, which extract
and triangulate the stripe and place the profile (``scanner_core.pipeline``: the numba kernels
release the GIL) while the pass is still running; a full queue drops the frame and counts it,
so acquisition never waits. Once the part has left the sheet the finisher thread assembles the
scan so far and computes its pose (``scanner_core.pose.ahead``); when the trigger ends the
pass, it waits for the last profiles, assembles the scan (taking what the pass did not change)
and hands it on (``on_scan``: the service publishes the cloud, then ends the pass as every pass
ends, ``scanner_core.pipeline.finish``, and stores it). ``flyscan scan`` and ``flyscan replay`` run the
same ``scanner_core`` functions offline.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import queue
import threading
import time
from pathlib import Path

import numpy as np

from scanner_core.geometry.calibration import Calibration
from scanner_core.devices import Camera, CameraClosed, CameraTimeout, Robot
from scanner_core.pipeline.exposure import ExposureController
from scanner_core.inspection import InspectionParams
from scanner_core.pipeline.finish import CrossCheckState, PassOutcome, finish_pass, pass_failure
from scanner_core.pipeline import (MarkerTracker, PassAccumulator, PipelineParams, marker_in_view,
                                   measure_frame, warm_up)
from scanner_core.pose.ahead import pose_ahead
from scanner_core.inspection.check import warm_up_inspection
from scanner_core.pose.warm import warm_up_pose
from scanner_core.pipeline.trigger import EndReason, Trigger, TriggerError, TriggerState
from scanner_core.types import Frame, MarkerObservation
from service.engine_status import engine_status
from service.jobs import ScanJob, new_scan_id
from service.live_recording import LiveRecording
from scanner_core.recording.replay import REPORTS_UNTIL_SETTING

log = logging.getLogger("flyscan.engine")

#: A camera that raised CameraClosed is reopened after this long, s.
CAMERA_REOPEN_S = 1.0
#: The finisher waits at most this long for a pass's last profiles, s.
FINISH_WAIT_S = 30.0


class EngineBusy(RuntimeError):
    """A scan is already armed or in progress."""


class EngineFault(RuntimeError):
    """The engine cannot scan now (the camera is not streaming)."""


class Engine:
    """Camera, trigger, workers and finisher of the live service.

    Parameters
    ----------
    camera, robot : Camera, Robot
        The devices (simulated or real: the engine cannot tell).
    calibration : Calibration
    params : PipelineParams
    on_scan : callable(job, scan, finish_with)
        Called on the finisher thread when a scan is over, with the scan (empty when no frame
        was placed) and ``finish_with(part_model, on_pose=None)``, which finishes the pass
        (``scanner_core.pipeline.finish.finish_pass``: verdict, cross-check, pose, report; ``on_pose``
        as there: called as soon as the pose is known), updates the
        job's state and the engine's cross-check state, and returns the ``PassOutcome``; the
        caller publishes and stores.
    on_pass_armed : callable(job), optional
        Called after arming (the simulated cell sends its robot through the sheet).
    on_recorded : callable(job, info), optional
        Called on the finisher thread when a recorded pass's recording is in place (or has
        failed: ``info["error"]``), after ``on_scan``.
    workers, pose_ahead_frames, queue_frames, camera_timeout_s
        See ``service.settings.Settings`` (``pose_ahead_frames``: ``_ask_pose_ahead``).
    cross_check_state : scanner_core.pipeline.finish.CrossCheckState, optional
        Where the cross-check starts (clock offset, tolerance, a known correction of the LED
        offset); each finished pass hands the next the state it leaves
        (``Engine.cross_check_state``).
    pose_params : scanner_core.pose.registration.PoseParams, optional
    """

    def __init__(self, camera: Camera, robot: Robot, calibration: Calibration,
                 params: PipelineParams, *, on_scan, on_pass_armed=None, on_recorded=None,
                 workers: int = 2, pose_ahead_frames: int = 4,
                 queue_frames: int = 64, camera_timeout_s: float = 1.0,
                 cross_check_state: CrossCheckState | None = None, pose_params=None,
                 inspection_params: InspectionParams = InspectionParams()):
        self.camera, self.robot = camera, robot
        self.calibration, self.params = calibration, params
        self.on_scan, self.on_pass_armed = on_scan, on_pass_armed
        self.on_recorded = on_recorded
        self.n_workers = int(workers)
        self.pose_ahead_frames = int(pose_ahead_frames)
        self.camera_timeout_s = camera_timeout_s
        # read when a pass is armed, written by the finisher thread (one pass at a time)
        self.cross_check_state = cross_check_state or CrossCheckState()
        self.pose_params = pose_params
        self.inspection_params = inspection_params
        self.last_rotation_b: np.ndarray | None = None  # held when the robot is lost
        self._newest_frame_clock: tuple[float, float] | None = None  # (camera t, monotonic)
        self.trigger = Trigger(params.trigger)
        self._lock = threading.RLock()
        self._frames: queue.Queue = queue.Queue(maxsize=int(queue_frames))
        self._ended: queue.Queue = queue.Queue()
        self._threads: list[threading.Thread] = []
        self._running = threading.Event()
        self.job: ScanJob | None = None
        self._processing_job: ScanJob | None = None
        self.last_scan_id: str | None = None
        self.camera_state = "closed"
        self.camera_error: str | None = None
        self.frames_total = 0
        self.frames_dropped = 0
        self.queue_overflows = 0
        self.fps = 0.0
        self.latest: tuple[Frame, MarkerObservation | None] | None = None
        self.scans_done = 0
        self.scans_failed = 0
        self.warmup_ms: float | None = None
        self.exposure = ExposureController(camera, params.exposure,
                                           getattr(camera, "fps", 0.0) or 0.0)
        self.exposure_seen: tuple[float, float] = (float("nan"), 1.0)  # newest frame's

    # -- life cycle -------------------------------------------------------------------------

    def start(self) -> None:
        self.warmup_ms = (warm_up(self.calibration, self.params) + warm_up_pose()
                          + warm_up_inspection())
        self._running.set()
        self._open_camera()
        try:
            self.robot.connect()
        except (OSError, RuntimeError) as exc:  # the cross-check degrades, scans go on
            log.warning("robot not connected: %s", exc)
        targets = [("acquisition", self._acquire), ("finisher", self._finisher_loop)]
        targets += [(f"worker-{k}", self._work) for k in range(self.n_workers)]
        for name, target in targets:
            thread = threading.Thread(target=target, name=f"flyscan-{name}", daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self) -> None:
        """Stop acquiring; a pass in progress is finished as "reset" and stored, not lost."""
        self._running.clear()
        for thread in self._threads[:1]:  # the acquisition thread: no frame after this
            thread.join(self.camera_timeout_s + 5.0)
        with self._lock:
            step = self.trigger.reset()
            if step.ended is not None and self.job is not None:
                self._end_pass(self.job, step.ended, detail="the service stopped")
        for _ in range(self.n_workers):
            self._frames.put(None)  # the acquisition thread is gone: the workers drain the queue
        self._ended.put(None)
        for thread in self._threads[1:]:
            thread.join(FINISH_WAIT_S + 5.0)
        self._threads.clear()
        self.camera.close()
        self.robot.disconnect()

    # -- commands ---------------------------------------------------------------------------

    def arm(self, part: str | None = None, timeout_s: float | None = None, context=None,
            record_to: Path | None = None, part_model=None,
            record_keep_free_bytes: int = 0) -> ScanJob:
        """Arm the trigger for the next pass; raises EngineBusy or EngineFault. ``context``
        rides on the job to ``on_pass_armed`` (the simulated pass's misplacement). With
        ``record_to`` (a folder that must not exist: RecordingError), every frame from arming
        to the pass's end is recorded with the robot's samples and ``part_model``, the part's
        CAD model (``scanner_core.recording``); the recording stops rather than leave less
        than ``record_keep_free_bytes`` free."""
        if not self.cross_check_state.clock_offset_estimated:
            coarse = self._coarse_clock_offset()
            if coarse is not None:
                self.cross_check_state = dataclasses.replace(self.cross_check_state,
                                                             clock_offset_s=coarse)
        with self._lock:
            job = self._arm_locked(part, timeout_s, context, record_to, part_model,
                                   record_keep_free_bytes)
        if self.on_pass_armed is not None:
            self.on_pass_armed(job)
        return job

    def _coarse_clock_offset(self) -> float | None:
        """Robot minus camera clock from the newest pose and the newest frame, to a few ms
        (the age of each): enough to look the robot's poses up during the first pass, whose
        track then estimates the offset properly (``scanner_core.pipeline.crosscheck``). A real robot's
        clock counts from its controller's start, a camera's from its own: without this the
        first pass would find no pose at all. None without a frame or a report."""
        newest_frame = self._newest_frame_clock
        if newest_frame is None or not self.robot.connected:
            return None
        try:
            robot_t = self.robot.latest().t
        except RuntimeError:
            return None
        frame_t, received = newest_frame
        return robot_t - (frame_t + time.monotonic() - received)

    @property
    def clock_offset_s(self) -> float:
        """Robot minus camera clock, s: the one the next pass starts from."""
        return self.cross_check_state.clock_offset_s

    def clock_offset_for_lookups(self) -> float:
        """Robot minus camera clock, s, to look the robot's poses up by a frame's time: the
        one a pass estimated, or before any has, the coarse one from the newest pose and
        frame (a calibration session's first still frame comes before any pass)."""
        state = self.cross_check_state
        if state.clock_offset_estimated:
            return state.clock_offset_s
        coarse = self._coarse_clock_offset()  # read only: the finisher owns the state
        return state.clock_offset_s if coarse is None else coarse

    def _arm_locked(self, part, timeout_s, context, record_to, part_model,
                    record_keep_free_bytes=0) -> ScanJob:
        """Under ``self._lock``."""
        if self.camera_state != "streaming":
            raise EngineFault(f"the camera is {self.camera_state}"
                              + (f": {self.camera_error}" if self.camera_error else ""))
        if self.trigger.state is TriggerState.FAULT:
            self.trigger.reset()
        try:
            self.trigger.arm(timeout_s)
        except TriggerError as exc:
            raise EngineBusy(f"a scan is in progress ({self.job.scan_id if self.job else '?'}: "
                             f"{self.trigger.state.value})") from exc
        job = ScanJob(scan_id=new_scan_id(), part=part, created=time.time(), context=context,
                      accumulator=PassAccumulator(
                          self.calibration, self.robot, self.clock_offset_s,
                          fallback_rotation=self.last_rotation_b,
                          merge_exposure_pairs=self.params.exposure.mode == "multiple",
                          partly_lit_ratio=self.params.partly_lit_ratio,
                          measured_box_t=self.params.measured_box_t))
        if record_to is not None:
            try:
                job.recording = LiveRecording(
                    Path(record_to) / job.scan_id, camera=self.camera,
                    calibration=self.calibration, part=part_model,
                    keep_free_bytes=record_keep_free_bytes,
                    settings={"scan_id": job.scan_id, "part": part,
                              "clock_offset_s": self.clock_offset_s,
                              "cross_check_state": self.cross_check_state.to_dict(),
                              "stripe_method": self.params.stripe_method,
                              "exposure_mode": self.params.exposure.mode,
                              "trigger": dataclasses.asdict(self.params.trigger)})
            except BaseException:
                self.trigger.reset()
                raise
        job.part_model = part_model
        self.job = job
        return job

    def check_calibration(self, calibration: Calibration) -> None:
        """ValueError when the calibration's image is not the camera's."""
        cam = calibration.camera
        if (cam.width, cam.height) != (self.camera.width, self.camera.height):
            raise ValueError(f"the calibration is for {cam.width} x {cam.height} images, the camera "
                             f"gives {self.camera.width} x {self.camera.height}")

    def set_calibration(self, calibration: Calibration) -> None:
        self.check_calibration(calibration)
        with self._lock:
            if self.trigger.state in (TriggerState.ARMED, TriggerState.SCANNING, TriggerState.PROCESSING) \
                    or self._processing_job is not None:
                raise EngineBusy("cannot change the calibration while a scan is in progress")
            self.calibration = calibration

    def status(self) -> dict:
        return engine_status(self)

    # -- threads ----------------------------------------------------------------------------

    def _open_camera(self) -> None:
        try:
            self.camera.open()
        except (OSError, RuntimeError) as exc:
            with self._lock:
                self.camera_state, self.camera_error = "error", str(exc)
                self.trigger.fault(f"camera error: {exc}")
            return
        with self._lock:
            self.camera_state, self.camera_error = "streaming", None
            if self.trigger.state is TriggerState.FAULT:
                self.trigger.reset()

    def _acquire(self) -> None:
        tracker = MarkerTracker(self.calibration, self.params)
        last_id, last_t = None, None
        lag_floor = math.inf
        while self._running.is_set():
            if self.camera_state in ("closed", "error"):
                time.sleep(CAMERA_REOPEN_S)
                self._open_camera()
                last_id = None
                continue
            try:
                frame = self.camera.grab(self.camera_timeout_s)
            except CameraTimeout as exc:
                self._camera_stopped("stalled", f"no frame for {self.camera_timeout_s:g} s ({exc})")
                continue
            except CameraClosed as exc:
                if self._running.is_set():
                    self._camera_stopped("closed", str(exc))
                continue
            except Exception as exc:  # a backend's own failure: reopened like a closed camera
                log.exception("camera failed")
                self._camera_stopped("error", repr(exc))
                continue
            if self.camera_state != "streaming":  # a stalled camera came back
                with self._lock:
                    self.camera_state, self.camera_error = "streaming", None
                    if self.trigger.state is TriggerState.FAULT:
                        self.trigger.reset()
            received = time.monotonic()
            self.frames_total += 1
            # The frame's wait in the camera's buffer beyond the promptest read since the camera
            # opened (the clocks' offset and the read's own time cancel in received - exposed).
            if last_id is None:
                lag_floor = math.inf
            lag_floor = min(lag_floor, received - frame.t)
            lag_ms = (received - frame.t - lag_floor) * 1e3
            gap = 0 if last_id is None else max(frame.frame_id - last_id - 1, 0)
            self.frames_dropped += gap
            if last_t is not None and frame.t > last_t:
                period = (frame.t - last_t) / (gap + 1)
                self.fps = 1.0 / period if self.fps == 0 else 0.95 * self.fps + 0.05 / period
            last_id, last_t = frame.frame_id, frame.t
            self._newest_frame_clock = (frame.t, received)
            self.exposure_seen = (frame.exposure_us, frame.gain)
            self.exposure.frame_grabbed(frame.exposure_us, frame.gain)
            try:
                self._on_frame(frame, gap, lag_ms, received, tracker)
            except Exception as exc:  # a frame the pipeline refuses (its size, its type)
                log.exception("frame %s could not be handled", frame.frame_id)
                self._camera_stopped("error", f"frame {frame.frame_id}: {exc!r}")

    def _on_frame(self, frame: Frame, gap: int, lag_ms: float, received: float,
                  tracker: MarkerTracker) -> None:
        # The marker search runs outside the lock, so that /status never waits for it; a
        # state that changes meanwhile takes effect from the next frame.
        with self._lock:
            state, job = self.trigger.state, self.job
            tracker.calibration = self.calibration  # changed only between passes
        marker, present = None, False
        if state in (TriggerState.ARMED, TriggerState.SCANNING):
            t0 = time.perf_counter()
            marker = tracker.observe(frame)
            present = marker_in_view(marker)
            if job is not None:
                job.marker_ms += (time.perf_counter() - t0) * 1e3
        else:
            tracker.reset()
        self.latest = (frame, marker)
        if job is not None and job.recording is not None and state in (TriggerState.ARMED,
                                                                      TriggerState.SCANNING):
            job.recording.add(frame)
        with self._lock:
            step = self.trigger.feed((frame, marker), frame.t, present, frame.frame_id)
            job = self.job
            if job is None:
                return
            if state is TriggerState.SCANNING:
                # a loss counts against the pass once a frame after it is the pass's (a gap
                # before the frame that ends it lies outside it, as in ``PassAccumulator.scan``)
                job.frames_dropped_pending += gap
                if step.emit:
                    job.frames_dropped += job.frames_dropped_pending
                    job.frames_dropped_pending = 0
                job.acquisition_lag_ms = max(job.acquisition_lag_ms, lag_ms)
            if self.trigger.state is TriggerState.SCANNING and job.state == "armed":
                job.state = "scanning"
            for item in step.emit:
                self._enqueue(job, item)
                job.last_frame_monotonic = received
            if step.ended is not None:
                self._end_pass(job, step.ended)

    def _enqueue(self, job: ScanJob, item) -> None:
        job.queued()
        try:
            self._frames.put_nowait((job, *item))
        except queue.Full:
            job.processed()
            job.queue_overflows += 1
            self.queue_overflows += 1

    def _camera_stopped(self, state: str, reason: str) -> None:
        """A stalled camera is grabbed again (it may come back); a closed one is reopened."""
        with self._lock:
            self.camera_state, self.camera_error = state, reason
            step = self.trigger.camera_stopped()
            if step.ended is not None and self.job is not None:
                self._end_pass(self.job, step.ended, detail=reason)
            self.trigger.fault(f"camera {state}: {reason}")
        if state in ("closed", "error"):
            self.camera.close()

    def _end_pass(self, job: ScanJob, reason: EndReason, detail: str | None = None) -> None:
        """Under the lock: hand the job to the finisher; only the job whose pass put the trigger
        in `processing` takes it back to idle."""
        if self.trigger.state is TriggerState.PROCESSING:
            self._processing_job = job
        job.end_monotonic = time.monotonic()
        job.state = "processing" if self.trigger.state is TriggerState.PROCESSING else job.state
        job.reason = reason.value + (f": {detail}" if detail else "")
        job.end_detail = detail
        self._ended.put((job, reason))

    def _work(self) -> None:
        while True:
            item = self._frames.get()
            if item is None:
                return
            job, frame, marker = item
            t0 = time.perf_counter()
            try:
                measure_frame(frame, marker, job.accumulator, self.params, self.exposure)
            except Exception as exc:  # a frame that cannot be processed: recorded, never fatal
                log.exception("frame %s not processed", frame.frame_id)
                job.worker_errors.append(f"frame {frame.frame_id}: {exc!r}")
            finally:
                job.processed((time.perf_counter() - t0) * 1e3)
            self._ask_pose_ahead(job)

    def _ask_pose_ahead(self, job: ScanJob) -> None:
        """Queue the scan of the pass so far (and its pose) for the finisher, once per newest
        frame with points, when no point has come for ``pose_ahead_frames`` frames."""
        accumulator = job.accumulator
        if job.end_monotonic is not None or accumulator is None or self.pose_ahead_frames <= 0:
            return
        newest = accumulator.quiet_since(self.pose_ahead_frames)
        with self._lock:
            if newest is not None and newest > job.ahead_asked:
                job.ahead_asked = newest
                self._ended.put((job, None))

    def _pose_ahead(self, job: ScanJob) -> None:
        """Finisher thread, during the pass: the scan so far (``PassAccumulator.scan`` keeps
        its points for the pass's end) and its pose (``scanner_core.pose.ahead``)."""
        accumulator = job.accumulator
        if job.end_monotonic is not None or accumulator is None:
            return  # the pass has ended: its finish is next
        try:
            scan = accumulator.scan()
            # Only with the part's models built: building them holds the interpreter's lock
            # for a second, which the pass's frames must not wait for (the finish builds them).
            if job.part_model is not None and job.part_model.prepared:
                job.ahead = pose_ahead(scan, job.part_model, self.pose_params)
        except Exception:  # the pass's end assembles and computes as ever
            log.exception("scan ahead of %s failed", job.scan_id)

    def _finisher_loop(self) -> None:
        while True:
            item = self._ended.get()
            if item is None:
                return
            job, reason = item
            if reason is None:
                self._pose_ahead(job)
                continue
            try:
                self._assemble_and_finish(job, reason)
            except Exception as exc:  # the scan fails with the reason; the finisher goes on
                log.exception("scan %s could not be finished", job.scan_id)
                job.state, job.reason = "failed", f"could not be finished: {exc!r}"
            finally:
                if job.recording is not None:  # after the scan is out: it never waits for it
                    self._close_recording(job)
                with self._lock:
                    if self._processing_job is job:
                        self.trigger.finish()
                        self._processing_job = None
                    self.last_scan_id = job.scan_id
                    self.scans_done += job.state == "done"
                    self.scans_failed += job.state == "failed"
                job.finished = time.time()
                job.accumulator = job.ahead = None  # the scan is out: not kept in memory

    def _close_recording(self, job: ScanJob) -> None:
        try:
            info = job.recording.finish(self.robot, job.accumulator.clock_offset_s)
        except Exception as exc:  # a recording that fails never fails the scan
            log.exception("recording of %s failed", job.scan_id)
            info = {"path": None, "error": repr(exc)}
        job.recording = None
        if self.on_recorded is not None:
            self.on_recorded(job, info)

    def _assemble_and_finish(self, job: ScanJob, reason: EndReason) -> None:
        """Finisher thread: the pass's scan assembled from its profiles and judged (the verdict
        goes out with the cloud); the daemon's ``on_scan`` then finishes it with the part's
        model (``finish_with``: ``scanner_core.pipeline.finish.finish_pass``), publishes and
        stores it."""
        t0 = time.perf_counter()
        job.latency_ms["finisher_monotonic"] = time.monotonic()  # the daemon's breakdown
        if not job.wait_processed(timeout=FINISH_WAIT_S):
            job.worker_errors.append(f"frames still processing after {FINISH_WAIT_S:g} s: left out")
        t1 = time.perf_counter()
        scan = job.accumulator.scan(frames_dropped=job.frames_dropped, end_reason=reason,
                                    stopped_because=job.reason)
        scan.queue_overflows = job.queue_overflows
        scan.timings_ms = {"marker": round(job.marker_ms, 3), "profiles": round(job.profiles_ms, 3),
                           "acquisition_lag": round(job.acquisition_lag_ms, 3),
                           "wait_workers": round((t1 - t0) * 1e3, 3),
                           "assemble": round((time.perf_counter() - t1) * 1e3, 3)}
        if scan.frames > scan.frames_held_rotation:  # the robot gave this pass's rotation
            self.last_rotation_b = scan.tcp_rotations_b[-1].copy()
        # the verdict now (the cloud goes out with it), handed to the finisher
        failure = pass_failure(scan, reason, detail=job.end_detail, note=job.note,
                               frames_lost=job.frames_dropped, queue_overflows=job.queue_overflows,
                               worker_errors=job.worker_errors)
        job.state = "failed" if failure else "done"
        job.reason = failure or job.reason

        def finish_with(part_model, on_pose=None) -> PassOutcome:
            outcome = finish_pass(
                scan, reason, self.robot, self.cross_check_state, part_model,
                pose_params=self.pose_params, inspection_params=self.inspection_params,
                scan_id=job.scan_id, detail=job.end_detail,
                note=job.note, frames_lost=job.frames_dropped,
                queue_overflows=job.queue_overflows, worker_errors=job.worker_errors,
                verdict=(failure,), on_pose=on_pose, pose_ahead=job.ahead, part=job.part,
                created=job.created)
            self.cross_check_state = outcome.cross_check_state
            job.state, job.reason = outcome.state, outcome.reason
            if job.recording is not None and outcome.cross_check is not None:
                # a replay's robot then ends its reports where this check's did
                try:
                    job.recording.keep(REPORTS_UNTIL_SETTING,
                                       outcome.cross_check.get("reports_until_s"))
                except (TypeError, ValueError):  # a recording never fails a scan
                    log.exception("recording of %s: the check's report cut-off not kept",
                                  job.scan_id)
            return outcome

        self.on_scan(job, scan, finish_with)
