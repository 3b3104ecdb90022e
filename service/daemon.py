"""The service as one object: devices, engine, store, parts, publisher and metrics, wired.

``Service.start``/``stop`` are what the FastAPI lifespan calls. The devices are handed in
(``Service(settings, devices=...)``) or, for a real cell, built from the settings
(:func:`build_devices`); nothing downstream knows which. The cell's driver
(``service.driver.PassDriver``) is told of every arm, capture and park: a real cell's does
nothing (its controller moves the robot), a simulated cell's sends its robot through the sheet.
No module of this path imports the simulator.
"""
from __future__ import annotations

import errno
import gc
import json
import logging
import math
import shutil
import threading
import time
from collections import OrderedDict
from pathlib import Path
from typing import NamedTuple

from clients.placement import correction_entry
from scanner_core.geometry.calibration import (Calibration, check_cell_geometry, check_marker_track,
                                               load_calibration, save_calibration)
from scanner_core.inspection import InspectionParams
from scanner_core.pipeline.exposure import ExposureParams
from scanner_core.pipeline import PipelineParams
from scanner_core.pipeline.finish import CrossCheckState
from scanner_core.pose.registration import PoseParams
from scanner_core.pipeline.trigger import TriggerParams, TriggerState
from scanner_core.types import Scan
from service.calhistory import CalibrationHistory, open_history
from service.calsessions import CalibrationSessions
from service.driver import ControllerDriven, PassDriver
from service.engine import Engine
from service.jobs import ScanJob
from service.metrics import Metrics
from service.models import check_reach, taught_place_matrix
from service.parts import DEMO_PART, PartLibrary, return_memory, settle_objects
from service.pictures import FramePicture, PreviewPictures, deviation_map_png
from service.problems import disk_reason, relative_path, relative_text
from service.publisher import Publisher
from service.settings import Settings
from service.store import ScanStore, free_bytes

log = logging.getLogger("flyscan.service")

#: How long the finisher waits for the cloud and the pose to leave on ZeroMQ before storing, s
#: (only to record their latency: the store never depends on the subscriber).
PUBLISH_WAIT_S = 1.0
#: Scans kept in memory (also those the store could not take), oldest dropped first.
RECENT_JOBS = 32
#: What a stored scan takes per cloud or edge point (its PLY rows), bytes: the room a pose is
#: only acted on with.
STORED_BYTES_PER_POINT = 64


class PassOrder(NamedTuple):
    """What an armed scan asks of the cell's driver for its pass (``PassDriver.start_pass``):
    the part's misplacement in the gripper, and what the gripper holds instead of the part
    (``PassDriver.holding``), each None for none."""

    misplacement: object
    holding: object


def build_devices(settings: Settings):
    """(camera, robot, driver, calibration) of a real cell: ``settings.camera``
    (``service.cameras``) and ``settings.robot`` (``service.robots``: a UR robot, a
    recording's samples, or none); the cell controller drives the robot
    (``service.driver.ControllerDriven``), no calibration but the one given. Simulated
    devices are handed to the service by whoever wires them (``flyscan serve --sim``)."""
    from service.cameras import open_camera
    from service.robots import open_robot

    if settings.camera is None:
        raise ValueError("no camera: give --camera SPEC (opencv:0, video:FILE, "
                         "genicam:PRODUCER.cti, pylon:SERIAL, replay:FOLDER) or run with --sim")
    return open_camera(settings.camera), open_robot(settings.robot), ControllerDriven(), None


class Service:
    """The daemon. Constructing does no I/O; ``start`` opens everything, ``stop`` closes it."""

    def __init__(self, settings: Settings, *, devices=None):
        self.settings = settings
        camera, robot, self.driver, default_calibration = devices or build_devices(settings)
        self.calibration_path = settings.data / "calibration.json"
        self._default_calibration = default_calibration
        self.store = ScanStore(settings.data, retention=settings.retention)
        if not isinstance(self.driver, PassDriver):
            raise TypeError(f"the driver must follow service.driver.PassDriver, got "
                            f"{type(self.driver).__name__}")
        self.parts = PartLibrary(settings.data, builtin=self.driver.builtin_parts() or None,
            max_parts=settings.max_parts,
            prepared_budget_bytes=int(settings.prepared_parts_mb * 2**20),
            load_in_process=False)
        self.publisher = Publisher(settings.zmq, hwm=settings.zmq_hwm)
        self.metrics = Metrics()
        # The status page's pictures, bounded and cached (service.pictures)
        self.frame_picture = FramePicture()
        self.previews = PreviewPictures(max_pending=settings.max_pending_pictures)
        self.deviation_maps = PreviewPictures(max_pending=settings.max_pending_pictures,
                                              render=deviation_map_png)
        self.pose_params = PoseParams(act_tolerance_mm=settings.act_tolerance_mm,
                                      act_tolerance_deg=settings.act_tolerance_deg,
                                      robot_rotation_std_deg=settings.robot_rotation_std_deg)
        params = PipelineParams(stripe_method=settings.stripe_method,
                                stripe_signal=settings.stripe_signal, bayer=settings.bayer,
                                exposure=ExposureParams(mode=settings.exposure_mode,
                                                        target_peak_dn=settings.exposure_target_dn,
                                                        multiple_ratio=settings.exposure_ratio),
                                trigger=TriggerParams(gap_frames=settings.gap_frames,
                                                      max_pass_s=settings.max_pass_s,
                                                      arm_timeout_s=settings.arm_timeout_s))
        self.engine = Engine(camera, robot, self._initial_calibration(), params,
                             on_scan=self._on_scan, on_pass_armed=self._on_pass_armed,
                             on_recorded=self._on_recorded,
                             workers=settings.workers, queue_frames=settings.queue_frames,
                             pose_ahead_frames=settings.pose_ahead_frames,
                             camera_timeout_s=settings.camera_timeout_s,
                             cross_check_state=CrossCheckState(
                                 clock_offset_s=settings.clock_offset_s,
                                 tolerance_mm=settings.cross_check_tolerance_mm,
                                 led_correction_t_mm=(None if settings.led_correction_t_mm is None
                                                      else tuple(settings.led_correction_t_mm)),
                                 led_correction_from=(None if settings.led_correction_t_mm is None
                                                      else "settings")),
                             pose_params=self.pose_params,
                             inspection_params=InspectionParams(
                                 extra_mm=settings.inspect_extra_mm,
                                 deform_mm=settings.inspect_deform_mm,
                                 min_area_mm2=settings.inspect_min_area_mm2))
        self.calibration_history = CalibrationHistory(settings.data / "calibration" / "history")
        self.calibration_sessions = CalibrationSessions(self)
        self._jobs: OrderedDict[str, ScanJob] = OrderedDict()  # the recent ones, by arming
        self._between_passes = threading.RLock()  # an arm waits for `between_passes`' work
        self._jobs_lock = threading.Lock()
        self._status_event: tuple[float, str] | None = None  # (when, the status as an SSE)
        self._status_event_lock = threading.Lock()
        self.event_streams = 0  # /events streams open (the event loop's, no lock needed)
        self.started = time.time()

    def _initial_calibration(self) -> Calibration:
        if self.settings.calibration is not None:
            self._calibration_source = f"--calibration {self.settings.calibration.name}"
            return load_calibration(self.settings.calibration)
        if self.calibration_path.is_file():
            self._calibration_source = "the data folder's calibration.json"
            return load_calibration(self.calibration_path)
        if self._default_calibration is None:
            raise ValueError("no calibration: give --calibration FILE or PUT /calibration")
        self._calibration_source = "the simulated cell's geometry"
        return self._default_calibration

    # -- life cycle -------------------------------------------------------------------------

    def start(self) -> None:
        """Open everything; if a step fails, what was started is stopped again."""
        self.settings.data.mkdir(parents=True, exist_ok=True)
        self.store.open()
        self.parts.open()
        open_history(self, self._calibration_source)
        self._remove_partial_recordings()
        default = None
        if self.default_part is not None:
            default = self.parts.get(self.default_part)  # KeyError: an unknown default part
            self.parts.prepare(self.default_part)  # built now, not at the first pose
        self.publisher.start()
        try:
            self.driver.start()
            # The default part's pass is readied (a simulated cell's rendered, its kernels
            # compiled) before the camera streams: a compiling kernel holds the GIL for a
            # second, and the acquisition thread would lose frames meanwhile. The first scan
            # does not wait for it either.
            if default is not None:
                self.driver.prepare(default)
            # Start-up's long-lived objects (the part's models, the prepared pass: about
            # 160 000) leave the garbage collector's care. A full collection over them takes
            # about 54 ms, 9 frames at 162 fps: it had paused the acquisition thread mid-pass,
            # 8 or 9 frames of a 1000 mm/s pass lost in one scan of four.
            gc.collect()
            gc.freeze()
            self.engine.start()
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        gc.unfreeze()  # a service started again in this process freezes its own
        self.engine.stop()
        self.publisher.stop()
        self.parts.close()
        self.driver.close()
        self.frame_picture.close()

    @property
    def default_part(self) -> str | None:
        """The part a scan that names none scans: the settings', else the demo block when
        the cell has one (the simulated cell's), else none (a scan without a pose)."""
        if self.settings.default_part:
            return self.settings.default_part
        return DEMO_PART if DEMO_PART in self.parts.names() else None

    # -- scans ------------------------------------------------------------------------------

    def arm(self, part: str | None, timeout_s: float | None, misplace=None, *,
            record: bool = False, taught_place=None, fault: str | None = None) -> ScanJob:
        """Arm a scan of ``part``; KeyError for an unknown part, PartError for a misplacement
        that leaves the inspection volume, EngineBusy, EngineFault. With ``record`` the pass
        is also recorded into ``recordings/<scan_id>`` of the data folder. ``taught_place``
        (a UR pose vector, m and rad, or a 4x4 in mm; default the settings') is the taught
        place pose the finished scan's ``correction`` starts from (ValueError unless rigid).
        ``fault`` (``KIND[:SIZE_MM]``, a simulated cell's only: FaultUnsupported, a
        ValueError, elsewhere) has the gripper hold that fault of the part instead of the
        part, while the scan is registered against the part.
        Waits for work between passes under way (`between_passes`) to end first: a pass never
        runs beside it."""
        with self._between_passes:
            return self._arm(part, timeout_s, misplace, record=record, taught_place=taught_place,
                             fault=fault)

    def _arm(self, part, timeout_s, misplace, *, record, taught_place, fault) -> ScanJob:
        if taught_place is None:
            taught_place = self.settings.taught_place
        taught = None if taught_place is None else taught_place_matrix(taught_place)
        if taught is not None:
            check_reach(taught, self.settings.robot_reach_mm)
        name = part or self.default_part
        held = self.parts.get(name) if name is not None else None  # KeyError before arming
        misplacement = holding = None
        if misplace is not None:
            misplacement = self.driver.misplacement(held, misplace)
        if fault is not None:
            holding = self.driver.holding(held, fault)
        if held is not None and held.prepared:
            self.parts.prepare(name, held)  # the most recently armed, for the budget
        # A part not prepared (its upload's preparation skipped during a pass, released by
        # the budget, not armed since the start) is prepared by the finish, after its pass:
        # the arm answers at once whatever the part, and no pass waits for a second of
        # model building (0.1-3 s for the reference parts).
        reserve = int(self.settings.disk_reserve_mb * 2**20)
        if record:
            self._prune_recordings(keep=self.settings.recordings_kept - 1)
            self._check_room_to_record(reserve)
        if self.engine.trigger.state.value in ("idle", "fault"):
            self.driver.before_arm()
        job = self.engine.arm(name, timeout_s, context=PassOrder(misplacement, holding),
                              part_model=held,
                              record_to=self.recordings_dir if record else None,
                              record_keep_free_bytes=reserve)
        job.taught_place = taught  # read by the finisher, a pass (>= 0.1 s) later
        # The pass is registered against the model armed with, whatever replaces the part
        # under its name meanwhile (``PUT /parts``): the report names which.
        job.part_version = None if held is None else held.version
        if record:
            job.info_extra = {"recording": {"path": None, "state": "recording"}}
        with self._jobs_lock:
            self._jobs[job.scan_id] = job
            while len(self._jobs) > RECENT_JOBS:
                self._jobs.popitem(last=False)
        return job

    def _check_room_to_record(self, reserve: int) -> None:
        """OSError (ENOSPC: 507) unless the data folder's disk has ``reserve`` and a second
        of frames free: a recording started with less would stop at once."""
        camera = self.engine.camera
        second = int(camera.width * camera.height * max(camera.fps, 1.0))
        free = free_bytes(self.settings.data)
        if free < reserve + second:
            raise OSError(errno.ENOSPC, f"no room to record the pass: {free / 2**20:.1f} MB "
                                        f"free, a second of frames and the scans' reserve "
                                        f"(disk_reserve_mb) need {(reserve + second) / 2**20:.0f}")

    @property
    def recordings_dir(self) -> Path:
        return self.settings.data / "recordings"

    def _remove_partial_recordings(self) -> None:
        """What a recording killed (or failed) mid-write left: ``.<scan_id>.*.partial``."""
        if not self.recordings_dir.is_dir():
            return
        for leftover in self.recordings_dir.iterdir():
            if leftover.name.startswith(".") and leftover.is_dir():
                shutil.rmtree(leftover, ignore_errors=True)

    def _prune_recordings(self, keep: int) -> None:
        """Recordings are large (2.3 MB a frame): only the newest ``keep`` stay."""
        if not self.recordings_dir.is_dir():
            return
        done = sorted(p for p in self.recordings_dir.iterdir()
                      if p.is_dir() and not p.name.startswith("."))
        for old in done[:max(len(done) - keep, 0)]:
            shutil.rmtree(old, ignore_errors=True)

    def _on_recorded(self, job: ScanJob, recording: dict) -> None:
        """The recording is in place (or failed): the scan's info says where."""
        recording = {**recording, "state": "failed" if recording.get("error") else "done"}
        data = self.settings.data
        if recording.get("path"):  # said relative to the data folder: no server paths out
            recording["path"] = relative_path(recording["path"], data)
        if recording.get("error"):
            recording["error"] = relative_text(recording["error"], data)
        job.info_extra = {"recording": recording}
        if job.info:
            job.info = {**job.info, "recording": recording}
            try:
                self.store.update_info(job.scan_id, job.info)
            except (KeyError, OSError) as exc:
                log.error("scan %s: the recording's place not stored: %s", job.scan_id, exc)

    def _on_pass_armed(self, job: ScanJob) -> None:
        def go():
            try:
                self.driver.start_pass(job.part_model, job.context.misplacement,
                                       wanted=lambda: job.end_monotonic is None,
                                       holding=job.context.holding)
            except Exception as exc:  # the pass never comes: the armed scan will time out
                log.error("the pass for %s not started: %s", job.scan_id, exc)
                job.note = f"the cell's pass not started: {exc}"

        threading.Thread(target=go, name="flyscan-driver-pass", daemon=True).start()

    def _on_scan(self, job: ScanJob, scan: Scan, finish_with) -> None:
        """Finisher thread: `_publish_and_store`; whatever it raises fails the scan with the reason,
        and the scan is then served (from memory if the store cannot take it) and deletable:
        never ``processing`` for ever."""
        try:
            self._publish_and_store(job, scan, finish_with)
        except Exception as exc:
            log.exception("scan %s could not be finished", job.scan_id)
            job.state = "failed"
            job.reason = (f"could not be finished: {type(exc).__name__}: "
                          f"{relative_text(str(exc), self.settings.data)}")
            job.info = {**self._info(job, {}), "frames": scan.frames,
                        "frames_dropped": job.frames_dropped, "frames_unplaced": 0,
                        "queue_overflows": job.queue_overflows, "points": 0, "edge_points": 0,
                        "timings_ms": {}, "latency_ms": {}}
            try:
                self.store.save(job.scan_id, job.info)
            except Exception as stored:  # served from memory (RECENT_JOBS) all the same
                log.error("scan %s not stored: %s", job.scan_id, stored)
            self.publisher.publish("status", {"scan_id": job.scan_id, "part": job.part,
                                              **self.status(), "scan_state": job.state,
                                              "reason": job.reason, "points": 0})

    def _publish_and_store(self, job: ScanJob, scan: Scan, finish_with) -> None:
        """Finisher thread: publish the cloud, finish the pass (``finish_with``: the pose, the
        cross-check, the edges, the report), publish the pose as soon as it is known (before the edge points'
        reclassification, the report and the store: the robot waits for it alone), then the
        edges, store. A failure to store fails the scan (on ``status`` and REST; the pose has
        gone out by then), and its info stays served from memory (``RECENT_JOBS``)."""
        entered = time.monotonic()
        finisher = job.latency_ms.pop("finisher_monotonic", None)
        sent, pose_sent = threading.Event(), threading.Event()
        path: dict[str, float] = {}  # the pose's path, ms (``latency_ms.pose_path``)

        def on_sent(topic, when):
            if job.last_frame_monotonic is not None:
                job.latency_ms["last_frame_to_zmq"] = _ms(when - job.last_frame_monotonic)
            job.latency_ms["pass_end_to_zmq"] = _ms(when - job.end_monotonic)
            sent.set()

        def on_pose_sent(topic, when):
            if job.last_frame_monotonic is not None:
                job.latency_ms["pose_published"] = _ms(when - job.last_frame_monotonic)
            job.latency_ms["pass_end_to_pose"] = _ms(when - job.end_monotonic)
            path["publish"] = _ms(when - path.pop("handed"))
            pose_sent.set()

        header = {"scan_id": job.scan_id, "part": job.part, "part_version": job.part_version}
        placed = scan.frames > 0
        if placed:
            self.publisher.publish("cloud", {**header, "state": job.state,
                                             "end_reason": scan.end_reason},
                                   scan.cloud, on_sent=on_sent)
        model = job.part_model
        prepared_here = model is not None and not model.prepared
        if prepared_here:
            self.parts.prepare(job.part, model)  # its pass is over (see `arm`)
        called = time.monotonic()

        def on_pose(pose_report, timings):
            # the pose's path from the pass's last frame, each stage once, in order: they sum
            # to at most ``pose_published`` (the rest: hand-overs between them)
            if job.last_frame_monotonic is not None:
                path["pass_end"] = _ms(job.end_monotonic - job.last_frame_monotonic)
            if finisher is not None:
                path["handoff"] = _ms(finisher - job.end_monotonic)
            for key in ("wait_workers", "assemble"):
                if key in scan.timings_ms:
                    path[key] = scan.timings_ms[key]
            path["cloud"] = _ms(called - entered)
            for key in ("normals", "registration"):
                if key in timings:
                    path[key] = timings[key]
            if "ahead" in timings:  # computed before the pass ended: not on the path
                job.latency_ms["pose_ahead"] = timings["ahead"]
            path["pose_checks"] = max(round(timings["pose"] - timings.get("normals", 0.0)
                                            - timings.get("registration", 0.0), 3), 0.0)
            path["handed"] = time.monotonic()
            no_room = self._no_room_to_store(scan)
            if no_room is not None and isinstance(pose_report, dict) and "act" in pose_report:
                # Said before the pose goes out: ZeroMQ and REST must tell the same fate.
                pose_report["act"] = False
                pose_report["act_reasons"] = [*pose_report.get("act_reasons", []), no_room]
            correction = self._correction(job, pose_report, model)
            if not self.publisher.publish("pose", {**header, "pose": pose_report,
                                                   "state": job.state,
                                                   **({"correction": correction}
                                                      if correction is not None else {})},
                                          on_sent=on_pose_sent):
                pose_sent.set()  # the queue was full: counted as dropped, nothing to wait for

        result = finish_with(model, on_pose=on_pose)
        report = result.report
        report["part_version"] = job.part_version
        if result.state == "done" and job.taught_place is not None:
            report["correction"] = self._correction(job, report.get("pose"), model)
        if "pose" in result.timings_ms:
            job.latency_ms["pose"] = result.timings_ms["pose"]
        if placed:
            self.publisher.publish("edges", {**header, "state": job.state,
                                             "end_reason": scan.end_reason}, scan.edges)
        # only to record the latency: the store never depends on the subscriber
        if placed:
            sent.wait(PUBLISH_WAIT_S)
        if result.pose_report is not None:
            pose_sent.wait(PUBLISH_WAIT_S)
            if "publish" in path:
                job.latency_ms["pose_path"] = dict(path)
        report["latency_ms"] = dict(job.latency_ms)
        info = self._info(job, report)
        try:
            self.store.save(job.scan_id, info, scan if placed else None, report)
        except OSError as exc:
            log.error("scan %s not stored: %s", job.scan_id, exc)
            job.state = "failed"
            job.reason = f"could not store the scan: {disk_reason(exc, self.settings.data)}"
            info = self._info(job, report)
        except ValueError as exc:  # a report JSON cannot hold (a value not finite)
            log.error("scan %s not stored: %s", job.scan_id, exc)
            job.state, job.reason = "failed", f"could not store the scan: {exc}"
            info = self._info(job, report)
        job.info = info
        if result.pose_report is None:  # no pose was asked for: said once the scan is stored
            self.publisher.publish("pose", {**header, "pose": info["pose"], "state": job.state,
                                            **({"correction": info["correction"]}
                                               if info.get("correction") else {})})
        self.publisher.publish("status", {**header, **self.status(), "scan_state": job.state,
                                          "reason": job.reason, "points": info["points"]})
        self.metrics.scan_finished(info)
        job.part_model = None  # a part replaced since keeps no memory through its old scans
        if prepared_here:  # before the trigger is idle again: no pass runs beside it
            settle_objects()

    def _no_room_to_store(self, scan: Scan) -> str | None:
        """Why the scan's files would not fit on the data folder's disk (its cloud and edge
        points at ``STORED_BYTES_PER_POINT``, and its report), or None."""
        need = STORED_BYTES_PER_POINT * (len(scan.cloud) + len(scan.edges)) + (1 << 20)
        try:
            free = free_bytes(self.settings.data)
        except OSError as exc:
            return f"the scan cannot be stored: {disk_reason(exc, self.settings.data)}"
        if free >= need:
            return None
        return (f"the scan cannot be stored: {free / 2**20:.1f} MB free, its files need "
                f"{need / 2**20:.1f} MB")

    @staticmethod
    def _correction(job: ScanJob, pose: dict | None, model) -> dict | None:
        """The scan's ``correction`` entry (``clients.placement.correction_entry``): the TCP
        place pose that corrects the pose, or why not to place; None without a taught place."""
        if job.taught_place is None:
            return None
        return correction_entry(job.taught_place, pose, None if model is None else model.grasp)

    def _info(self, job: ScanJob, report: dict) -> dict:
        keys = ("frames", "frames_dropped", "frames_unplaced", "queue_overflows", "points",
                "edge_points", "edge_kinds", "end_reason", "timings_ms", "cross_check", "pose",
                "inspection", "correction", "latency_ms",
                "frames_held_rotation", "marker_residual_px")
        return _finite({"scan_id": job.scan_id, "state": job.state, "reason": job.reason,
                        "part": job.part, "part_version": job.part_version,
                        "created": job.created, "finished": time.time(),
                        **{k: report.get(k) for k in keys}, **job.info_extra})

    @staticmethod
    def _live_info(job: ScanJob) -> dict:
        if job.finished is not None and job.info:
            return job.info
        # Finished but not yet handed back (stored, the trigger idle): still processing; a
        # job the finisher gave up on (no info) is what it says, never processing for ever.
        state = ("processing" if job.state in ("done", "failed") and job.finished is None
                 else job.state)
        return {"scan_id": job.scan_id, "state": state, "reason": job.reason, "part": job.part,
                "part_version": job.part_version, "created": job.created,
                "frames": job.accumulator.frames_seen if job.accumulator is not None else 0,
                "frames_dropped": job.frames_dropped, "queue_overflows": job.queue_overflows,
                **job.info_extra}

    def scan_info(self, scan_id: str) -> dict:
        """A recent scan (in progress or finished) or a stored one; KeyError when unknown."""
        with self._jobs_lock:
            job = self._jobs.get(scan_id)
        return self._live_info(job) if job is not None else self.store.info(scan_id)

    def delete_scan(self, scan_id: str) -> None:
        """KeyError when unknown; ValueError while in progress."""
        info = self.scan_info(scan_id)
        if info["state"] not in ("done", "failed"):
            raise ValueError(f"scan {scan_id} is {info['state']}")
        with self._jobs_lock:
            recent = self._jobs.get(scan_id)
        try:
            self.store.delete(scan_id)  # OSError: the disk refused; the scan stays
        except KeyError:  # one the store never took: served from memory alone
            if recent is None:
                raise
        with self._jobs_lock:
            self._jobs.pop(scan_id, None)

    def list_scans(self) -> list[dict]:
        """Recent and stored scans, each once, newest first."""
        with self._jobs_lock:
            recent = {j.scan_id: self._live_info(j) for j in self._jobs.values()}
        stored = [i for i in self.store.list() if i["scan_id"] not in recent]
        return sorted([*recent.values(), *stored], key=lambda i: i["created"], reverse=True)

    # -- parts ------------------------------------------------------------------------------

    def delete_part(self, name: str) -> None:
        """Delete an uploaded part: KeyError when unknown, PartInUse when built in, the
        default part or the part of a scan not yet finished, OSError when the disk refuses."""
        in_use = {}
        if self.default_part is not None:
            in_use[self.default_part] = "the default part (settings.default_part)"
        with self._jobs_lock:
            for job in self._jobs.values():
                if job.finished is None and job.part is not None:
                    in_use[job.part] = f"scanned by scan {job.scan_id} ({job.state})"
        self.parts.remove(name, in_use=in_use)
        self.between_passes(return_memory)  # its models go now, not at some later pass

    def prepare_part(self, name: str) -> None:
        """Build what a scan's pose needs of `name` now, unless a pass is under way (then the
        finish of its first scan builds it): an uploaded part's first pose waits for none."""
        def prepare():
            try:
                if self.parts.prepare(name):
                    settle_objects()
            except KeyError:  # deleted meanwhile
                pass
            except Exception:  # said again, to its caller, by the arm that needs it
                log.exception("part %s could not be prepared", name)
        self.between_passes(prepare)

    def between_passes(self, work) -> bool:
        """Run `work` (a part's preparation, a full garbage collection: seconds or tens of
        milliseconds holding the interpreter's lock) only while no pass is armed or under
        way, an arm waiting for it to end; False (not run) during a pass."""
        with self._between_passes:
            if self.engine.trigger.state.value not in ("idle", "fault"):
                return False
            work()
            return True

    # -- calibration ------------------------------------------------------------------------

    def set_calibration(self, calibration: Calibration) -> None:
        """Use and keep a calibration: ValueError if it does not fit the camera, EngineBusy
        during a scan (a pass is never interrupted), OSError if it cannot be saved (then the
        previous one stays)."""
        check_cell_geometry(calibration)
        geometry = self.driver.plan_geometry(calibration)
        if geometry is not None:
            check_marker_track(calibration, geometry)
        previous = self.engine.calibration
        self.engine.set_calibration(calibration)
        try:
            save_calibration(self.calibration_path, calibration)
        except OSError:
            self.engine.set_calibration(previous)
            raise

    def status_event(self, max_age_s: float) -> str:
        """The status as one server-sent event, made at most every `max_age_s` and shared by
        every open status page (each made its own, twice a second, before)."""
        with self._status_event_lock:
            now = time.monotonic()
            if self._status_event is None or now - self._status_event[0] >= max_age_s:
                self._status_event = (now, f"event: status\ndata: {json.dumps(self.status())}\n\n")
            return self._status_event[1]

    def acquiring(self) -> bool:
        """Whether a scan is armed or its pass runs: the camera's frames must not wait (the
        edge reads request bodies slower then, ``service.edge``)."""
        return self.engine.trigger.state in (TriggerState.ARMED, TriggerState.SCANNING)

    def status(self) -> dict:
        status = self.engine.status()
        status["zmq"] = {"endpoint": self.publisher.bound_endpoint, "sent": self.publisher.sent,
                         "dropped": self.publisher.dropped}
        status["simulated"] = self.driver.simulated
        status["parts"] = {"prepared_mb": round(self.parts.prepared_mb(), 1),
                           "budget_mb": self.settings.prepared_parts_mb,
                           "released": self.parts.released}
        return status


def _finite(value):
    """``value`` with every float that is not finite made None: JSON (and the REST answer)
    cannot carry it, and a scan's info must always be servable."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def _ms(seconds: float) -> float:
    return round(seconds * 1e3, 3)
