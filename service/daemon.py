"""The service as one object: devices, engine, store, parts, publisher and metrics, wired.

``Service.start``/``stop`` are what the FastAPI lifespan calls. The devices are chosen here,
once: the simulated cell in simulated mode (``simulator.live``), the real backends otherwise;
nothing downstream knows which. In simulated mode arming also sends the simulated robot
through the sheet (``SimPassDriver``), as a cell controller's robot program would.
"""
from __future__ import annotations

import gc
import logging
import shutil
import threading
import time
from collections import OrderedDict
from pathlib import Path

import numpy as np

from scanner_core.calibration import Calibration, load_calibration, save_calibration
from scanner_core.exposure import ExposureParams
from scanner_core.pipeline import PipelineParams
from scanner_core.pose import PoseParams, scan_pose
from scanner_core.trigger import TriggerParams
from scanner_core.types import Scan
from service.engine import Engine, ScanJob
from service.metrics import Metrics
from service.parts import DEMO_PART, PartLibrary
from service.publisher import Publisher
from service.settings import Settings
from service.store import ScanStore
from simulator.live import PassInProgress
from simulator.parts import check_fits
from simulator.session import misplacement_matrix

log = logging.getLogger("flyscan.service")

#: How long the finisher waits for the cloud to leave on ZeroMQ before storing, s (only to
#: record the latency: the store never depends on the subscriber).
PUBLISH_WAIT_S = 1.0
#: The simulated robot finishes its previous pass (its lead-out) before starting the next, s.
PREVIOUS_PASS_WAIT_S = 5.0
#: Scans kept in memory (also those the store could not take), oldest dropped first.
RECENT_JOBS = 32


class SimPassDriver:
    """Sends the simulated robot through the sheet when a scan is armed; with an RTDE
    emulator (``--sim --robot ur://HOST``) the emulator serves the same track to the real
    ur-rtde client. Every part is simulated with ``surface`` (``simulator.surfaces``)."""

    def __init__(self, sim, emulator=None, surface: str = "default"):
        self.sim = sim
        self.emulator = emulator
        self.surface = surface
        self._dressed: dict[int, tuple] = {}  # id -> (the library's part, the simulated one)

    def _simulated(self, part):
        """The part as the simulator shows it (the same object every time, so that its
        rendered pass is reused)."""
        if self.surface == "default":
            return part
        from simulator.surfaces import with_surface

        key = id(part)
        if key not in self._dressed or self._dressed[key][0] is not part:
            self._dressed[key] = (part, with_surface(part, self.surface))
        return self._dressed[key][1]

    def start(self) -> None:
        """Start the emulator (its own process) on the cell's clock, before the robot connects."""
        if self.emulator is None:
            return
        self.emulator.start()
        try:
            cell = self.sim.cell
            self.emulator.set_track(self.sim.start_clock(), self.sim.robot.clock_offset_s,
                                    cell.gripper_rotation_b, self.sim.idle_tcp_b)
        except BaseException:
            self.emulator.stop()
            raise

    def prepare(self, part) -> None:
        self.sim.prepare_pass(self._simulated(part))

    def start_pass(self, part, misplacement: np.ndarray | None) -> None:
        """Start the pass once the robot has finished the previous one (its lead-out goes on
        after the scan has ended), as a robot program would."""
        deadline = time.monotonic() + PREVIOUS_PASS_WAIT_S
        while True:
            try:
                live = self.sim.start_pass(self._simulated(part), misplacement)
                break
            except PassInProgress:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.01)
        if self.emulator is not None:
            self.emulator.add_segment(live.segment)

    def close(self) -> None:
        if self.emulator is not None:
            self.emulator.stop()


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


def build_devices(settings: Settings):
    """(camera, robot, driver, calibration) for the settings.

    Simulated mode: the reference cell's camera, and its robot, or, with ``--robot
    ur://HOST``, an RTDE emulator started at HOST (its own process) serving the simulated
    track to the real ur-rtde client. Otherwise ``settings.camera`` (``service.cameras``) and
    the UR robot, or none.
    """
    from service.ur_robot import URRobot, parse_robot_url

    host = parse_robot_url(settings.robot) if settings.robot is not None else None
    if not settings.sim:
        if settings.camera is None:
            raise ValueError("no camera: give --camera SPEC (opencv:0, video:FILE, "
                             "genicam:PRODUCER.cti, replay:FOLDER) or run with --sim")
        from service.cameras import open_camera

        camera = open_camera(settings.camera)
        return camera, URRobot(host) if host else NoRobot(), None, None
    if settings.camera is not None:
        raise ValueError(f"--camera {settings.camera}: the simulated cell has its own camera")
    from simulator.effects import simulated_cell
    from simulator.live import LiveSimCell

    cell = simulated_cell(settings.sim_perturb_seed, settings.sim_effects)
    changes = {k: v for k, v in (("speed_mm_s", settings.sim_speed_mm_s), ("fps", settings.sim_fps))
               if v is not None}
    if changes:
        cell = cell.with_pass(**changes)
    sim = LiveSimCell(cell, seed=settings.sim_seed, clock_offset_s=settings.sim_clock_offset_s)
    if host is None:
        return sim.camera, sim.robot, SimPassDriver(sim, surface=settings.sim_surface), cell.calibration
    from service.rtde_emulator import RtdeEmulator

    return (sim.camera, URRobot(host), SimPassDriver(sim, RtdeEmulator(host), settings.sim_surface),
            cell.calibration)


class Service:
    """The daemon. Constructing does no I/O; ``start`` opens everything, ``stop`` closes it."""

    def __init__(self, settings: Settings, *, devices=None):
        self.settings = settings
        camera, robot, self.driver, default_calibration = devices or build_devices(settings)
        self.calibration_path = settings.data / "calibration.json"
        self._default_calibration = default_calibration
        self.store = ScanStore(settings.data, retention=settings.retention)
        self.parts = PartLibrary(settings.data)
        self.publisher = Publisher(settings.zmq, hwm=settings.zmq_hwm)
        self.metrics = Metrics()
        self.pose_params = PoseParams()
        params = PipelineParams(stripe_method=settings.stripe_method,
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
                             camera_timeout_s=settings.camera_timeout_s,
                             clock_offset_s=settings.clock_offset_s,
                             cross_check_tolerance_mm=settings.cross_check_tolerance_mm,
                             led_correction_t_mm=settings.led_correction_t_mm)
        self._jobs: OrderedDict[str, ScanJob] = OrderedDict()  # the recent ones, by arming
        self._jobs_lock = threading.Lock()
        self.started = time.time()

    def _initial_calibration(self) -> Calibration:
        if self.settings.calibration is not None:
            return load_calibration(self.settings.calibration)
        if self.calibration_path.is_file():
            return load_calibration(self.calibration_path)
        if self._default_calibration is None:
            raise ValueError("no calibration: give --calibration FILE or PUT /calibration")
        return self._default_calibration

    # -- life cycle -------------------------------------------------------------------------

    def start(self) -> None:
        """Open everything; if a step fails, what was started is stopped again."""
        self.settings.data.mkdir(parents=True, exist_ok=True)
        self.store.open()
        self.parts.open()
        default = self.parts.get(self.default_part)  # KeyError: an unknown default part
        default.surface_model, default.edge_model  # built now, not at the first scan's pose
        self.publisher.start()
        try:
            if self.driver is not None:
                self.driver.start()
                # The default part's pass is rendered (and the simulator's kernels compiled)
                # before the camera streams: a compiling kernel holds the GIL for a second,
                # and the acquisition thread would lose frames meanwhile. The first scan
                # does not wait for it either.
                self.driver.prepare(self.parts.get(self.default_part))
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
        if self.driver is not None:
            self.driver.close()

    @property
    def default_part(self) -> str:
        return self.settings.default_part or DEMO_PART

    # -- scans ------------------------------------------------------------------------------

    def arm(self, part: str | None, timeout_s: float | None, misplace=None, *,
            record: bool = False) -> ScanJob:
        """Arm a scan of ``part``; KeyError for an unknown part, PartError for a misplacement
        that leaves the inspection volume, EngineBusy, EngineFault. With ``record`` the pass
        is also recorded into ``recordings/<scan_id>`` of the data folder."""
        name = part or self.default_part
        held = self.parts.get(name)  # KeyError before anything is armed
        misplacement = misplacement_matrix(misplace)
        if misplacement is not None:
            check_fits(held, pose=misplacement @ held.grasp)
        if record:
            self._prune_recordings(keep=self.settings.recordings_kept - 1)
        job = self.engine.arm(name, timeout_s, context=misplacement,
                              record_to=self.recordings_dir if record else None)
        if record:
            job.info_extra = {"recording": {"path": None, "state": "recording"}}
        with self._jobs_lock:
            self._jobs[job.scan_id] = job
            while len(self._jobs) > RECENT_JOBS:
                self._jobs.popitem(last=False)
        return job

    @property
    def recordings_dir(self) -> Path:
        return self.settings.data / "recordings"

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
        job.info_extra = {"recording": recording}
        if job.info:
            job.info = {**job.info, "recording": recording}
            try:
                self.store.update_info(job.scan_id, job.info)
            except (KeyError, OSError) as exc:
                log.error("scan %s: the recording's place not stored: %s", job.scan_id, exc)

    def _on_pass_armed(self, job: ScanJob) -> None:
        if self.driver is None:
            return

        def go():
            try:
                self.driver.start_pass(self.parts.get(job.part), job.context)
            except Exception as exc:  # the pass never comes: the armed scan will time out
                log.error("simulated pass for %s not started: %s", job.scan_id, exc)
                job.note = f"simulated pass not started: {exc}"

        threading.Thread(target=go, name="flyscan-sim-pass", daemon=True).start()

    def _on_scan(self, job: ScanJob, scan: Scan, cross_check) -> None:
        """Finisher thread: publish, cross-check, store. A failure to store fails the scan, and
        its info stays served from memory (``RECENT_JOBS``)."""
        sent = threading.Event()

        def on_sent(topic, when):
            if job.last_frame_monotonic is not None:
                job.latency_ms["last_frame_to_zmq"] = round((when - job.last_frame_monotonic) * 1e3, 3)
            job.latency_ms["pass_end_to_zmq"] = round((when - job.end_monotonic) * 1e3, 3)
            sent.set()

        header = {"scan_id": job.scan_id, "part": job.part}
        placed = scan.frames > 0
        if placed:
            outcome = {"state": job.state, "end_reason": scan.end_reason}
            self.publisher.publish("cloud", {**header, **outcome}, scan.cloud, on_sent=on_sent)
            self.publisher.publish("edges", {**header, **outcome}, scan.edges)
            sent.wait(PUBLISH_WAIT_S)
        check = cross_check(scan, job.scan_id) if placed else None
        report = self.engine.report(job, scan, check)
        if job.state == "done":
            report["pose"] = self._pose(job, scan)
        report["latency_ms"] = dict(job.latency_ms)
        info = self._info(job, report)
        try:
            self.store.save(job.scan_id, info, scan if placed else None, report)
        except OSError as exc:
            log.error("scan %s not stored: %s", job.scan_id, exc)
            job.state, job.reason = "failed", f"could not store the scan: {exc}"
            info = self._info(job, report)
        job.info = info
        self.publisher.publish("pose", {**header, "pose": info["pose"], "state": job.state})
        self.publisher.publish("status", {**header, **self.status(), "scan_state": job.state,
                                          "reason": job.reason, "points": info["points"]})
        self.metrics.scan_finished(info)

    def _pose(self, job: ScanJob, scan: Scan) -> dict:
        """The part's pose in the gripper (``report.json`` ``pose``), or why there is none."""
        t0 = time.perf_counter()
        try:
            try:
                part = self.parts.get(job.part)
            except KeyError:
                raise ValueError(f"no CAD model for part {job.part!r}") from None
            pose = scan_pose(scan, part.surface_model, part.grasp, edge_model=part.edge_model,
                             params=self.pose_params).to_dict()
        except ValueError as exc:
            pose = {"refused": str(exc)}
        job.latency_ms["pose"] = round((time.perf_counter() - t0) * 1e3, 3)
        return pose

    def _info(self, job: ScanJob, report: dict) -> dict:
        keys = ("frames", "frames_dropped", "frames_unplaced", "queue_overflows", "points",
                "edge_points", "end_reason", "timings_ms", "cross_check", "pose", "latency_ms",
                "frames_held_rotation", "marker_residual_px")
        return {"scan_id": job.scan_id, "state": job.state, "reason": job.reason, "part": job.part,
                "created": job.created, "finished": time.time(),
                **{k: report.get(k) for k in keys}, **job.info_extra}

    @staticmethod
    def _live_info(job: ScanJob) -> dict:
        if job.finished is not None and job.info:
            return job.info
        # Finished but not yet handed back (stored, the trigger idle): still processing.
        state = "processing" if job.state in ("done", "failed") else job.state
        return {"scan_id": job.scan_id, "state": state, "reason": job.reason, "part": job.part,
                "created": job.created,
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
            recent = self._jobs.pop(scan_id, None)
        try:
            self.store.delete(scan_id)
        except KeyError:
            if recent is None:
                raise

    def list_scans(self) -> list[dict]:
        """Recent and stored scans, each once, newest first."""
        with self._jobs_lock:
            recent = {j.scan_id: self._live_info(j) for j in self._jobs.values()}
        stored = [i for i in self.store.list() if i["scan_id"] not in recent]
        return sorted([*recent.values(), *stored], key=lambda i: i["created"], reverse=True)

    # -- calibration ------------------------------------------------------------------------

    def set_calibration(self, calibration: Calibration) -> None:
        """Use and keep a calibration: ValueError if it does not fit the camera, EngineBusy
        during a scan, OSError if it cannot be saved (then the previous one stays)."""
        previous = self.engine.calibration
        self.engine.set_calibration(calibration)
        try:
            save_calibration(self.calibration_path, calibration)
        except OSError:
            self.engine.set_calibration(previous)
            raise

    def status(self) -> dict:
        status = self.engine.status()
        status["zmq"] = {"endpoint": self.publisher.bound_endpoint, "sent": self.publisher.sent,
                         "dropped": self.publisher.dropped}
        status["simulated"] = self.driver is not None
        return status

