"""Calibration sessions recorded by the service, with the robot.

A session follows a plan (``scanner_core.calibration.plan``): the cell controller takes the robot to
each of the plan's TCP poses in turn and asks the service to capture it
(``POST /calibration/sessions/{id}/steps/{index}``); the service takes the first frame after
the robot has settled and the mean of the robot's reports around it, and writes both into the
session folder (``scanner_core.calibration.folder``: the folder ``flyscan calibrate --session``
reads). Then a pass of the sphere through the sheet is recorded (the service's own recording,
moved into the folder's ``pass/``), and the fit (``scanner_core.calibration.session.calibrate_session``,
in a thread) keeps its calibration as a new version of the history (``service.calhistory``),
not active until asked. In the simulated cell the driver takes the simulated robot to each pose
(``simulator.driver.SimPassDriver.hold``); the service does not know which.

``DATA/calibration/sessions/<id>/``: the session folder, ``plan.json``, ``service.json`` (the
steps captured, the pass's and the session's state: written at each change, so that a service
restarted, even killed, resumes its sessions) and, once fitted, ``calibration.json``,
``calibration.report.json`` and ``residuals.png``.
"""
from __future__ import annotations

import datetime as _dt
import json
import logging
import math
import os
import secrets
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scanner_core.calibration.plan import (TILT_DEG, TILTED_FRACTION, CalibrationPlan, PlanGeometry,
                                           make_plan, plan_from_dict, plan_to_dict)
from scanner_core.calibration.session import SessionWriter, calibrate_session, load_session
from scanner_core.geometry.calibration import save_calibration
from scanner_core.fileio import save_json_atomic
from scanner_core.recording import robot_samples
from scanner_core.io.rtde import matrix_to_ur_pose, ur_pose_to_matrix
from service.engine import EngineBusy

log = logging.getLogger("flyscan.calibration")

__all__ = ["CalibrationSessions", "NoSuchSession", "SessionStateError", "SETTLE_S",
           "AVERAGE_S"]

#: After the capture is asked for, frames for this long are skipped, s: the robot has
#: settled, and a frame exposed before it arrived is not taken.
SETTLE_S = 0.1
#: The robot's reports averaged about the frame's time, s (+-half): a UR reports at 500 Hz,
#: each report noisy by some microns; 50 of them average it down sevenfold.
AVERAGE_S = 0.1
#: The robot's reports about a frame must lie within this of their median, mm: a robot that
#: stands still wanders by microns (a UR's reports, 5 um); one still arriving moves by more.
STILL_MM = 0.05
#: The longest wait for a frame or for the robot's reports, s.
CAPTURE_TIMEOUT_S = 5.0
#: How long the pass may take to be recorded, s (arming, the pass, writing its frames).
PASS_TIMEOUT_S = 120.0
#: Sessions kept on disk (a session with its pass is about 1 GB); the oldest go first.
SESSIONS_KEPT = 4
#: A session's state beside its folder, what a restarted service resumes it from.
STATE_FILE = "service.json"


class NoSuchSession(KeyError):
    """No calibration session of that id."""


class SessionStateError(RuntimeError):
    """What was asked does not fit the session's state (a step captured twice, a fit before
    the pass): the message says what is missing."""


@dataclass
class _Session:
    session_id: str
    folder: Path
    plan: CalibrationPlan
    plan_dict: dict
    writer: SessionWriter
    captured: dict = field(default_factory=dict)  # index -> StepCaptured dict
    pass_scan_id: str | None = None
    pass_state: str = "not recorded"
    state: str = "recording"
    version: int | None = None
    figures: dict | None = None
    error: str | None = None
    lock: threading.Lock = field(default_factory=threading.Lock)

    def to_dict(self) -> dict:
        """What ``service.json`` keeps of the session."""
        return {"captured": [self.captured[i] for i in sorted(self.captured)],
                "pass_scan_id": self.pass_scan_id, "pass_state": self.pass_state,
                "state": self.state, "version": self.version, "figures": self.figures,
                "error": self.error}

    def info(self, with_plan: bool = False) -> dict:
        return {"session_id": self.session_id, "state": self.state,
                "steps": len(self.plan.steps), "captured": len(self.captured),
                "pass_scan_id": self.pass_scan_id, "pass_state": self.pass_state,
                "version": self.version, "figures": self.figures, "error": self.error,
                "plan": self.plan_dict if with_plan else None}


class CalibrationSessions:
    """The service's calibration sessions, resumed from the data folder at start."""

    def __init__(self, service):
        self.service = service
        self.root = service.settings.data / "calibration" / "sessions"
        self._sessions: dict[str, _Session] = {}
        self._lock = threading.Lock()
        self._resume()

    def _resume(self) -> None:
        """The sessions of the data folder, as their ``service.json`` left them: a pass or a
        fit under way when the service stopped is to be done again."""
        if not self.root.is_dir():
            return
        for folder in sorted(p for p in self.root.iterdir() if p.is_dir()):
            try:
                plan_dict = json.loads((folder / "plan.json").read_text())
                plan = plan_from_dict(plan_dict)
                kept = (json.loads((folder / STATE_FILE).read_text())
                        if (folder / STATE_FILE).is_file() else {})
                session = _Session(folder.name, folder, plan, plan_dict,
                                   SessionWriter.reopen(folder))
            except (OSError, ValueError, KeyError, TypeError) as exc:
                log.error("calibration session %s not resumed: %s", folder.name, exc)
                continue
            session.captured = {int(c["index"]): c for c in kept.get("captured", [])}
            for key in ("pass_scan_id", "pass_state", "state", "version", "figures", "error"):
                if key in kept:
                    setattr(session, key, kept[key])
            if session.state == "recording pass":
                recorded = (session.writer.pass_folder / "recording.json").is_file()
                session.state = "ready to fit" if recorded else "recording"
                session.pass_state = "done" if recorded else "not recorded"
                if not recorded:
                    session.error = "the service stopped during the pass: record it again"
            elif session.state == "fitting":
                session.state = "failed"
                session.error = "the service stopped during the fit: fit again"
            self._sessions[session.session_id] = session
            log.info("calibration session %s resumed: %d of %d steps, %s", session.session_id,
                     len(session.captured), len(plan.steps), session.state)

    @staticmethod
    def _save(session: _Session) -> None:
        """``service.json`` as the session stands (under its lock)."""
        save_json_atomic(session.folder / STATE_FILE, session.to_dict())

    # -- creating ---------------------------------------------------------------------------
    def _geometry(self, request: dict, nominal) -> PlanGeometry:
        """The plan's geometry: the request's fields, the rest the cell's driver's (a
        simulated cell knows its own; a real cell's installer gives them)."""
        base = self.service.driver.plan_geometry(nominal)
        given = {"tcp_rotation": request.get("tcp_rotation"),
                 "pass_start_y_mm": request.get("pass_start_y_mm"),
                 "pass_end_y_mm": request.get("pass_end_y_mm"),
                 "pass_height_mm": request.get("pass_height_mm"),
                 "sphere_offset_t_mm": request.get("sphere_offset_t_mm")}
        missing = [k for k, v in given.items() if v is None]
        if base is None and missing:
            raise ValueError(f"a real cell's plan needs {', '.join(missing)} (the pass and the "
                             f"sphere's holder: docs/commissioning.md)")
        pick = lambda key, default: default if given[key] is None else given[key]
        rotation = (base.tcp_rotation_b if given["tcp_rotation"] is None
                    else ur_pose_to_matrix([0.0, 0.0, 0.0, *given["tcp_rotation"]])[:3, :3])
        geometry = PlanGeometry(
            rotation, float(pick("pass_start_y_mm", base and base.pass_start_y_mm)),
            float(pick("pass_end_y_mm", base and base.pass_end_y_mm)),
            float(pick("pass_height_mm", base and base.pass_height_mm)),
            np.asarray(nominal.marker_offset_t, dtype=np.float64),
            np.asarray(pick("sphere_offset_t_mm", base and base.sphere_offset_t_mm),
                       dtype=np.float64),
            float(request.get("sphere_radius_mm", 28.625)))
        if not geometry.pass_end_y_mm > geometry.pass_start_y_mm:
            raise ValueError("the pass must run along +y: pass_end_y_mm > pass_start_y_mm")
        return geometry

    def create(self, request: dict) -> dict:
        """A new session and its plan; ValueError for a plan that cannot be made."""
        nominal = self.service.engine.calibration
        geometry = self._geometry(request, nominal)
        plan = make_plan(geometry, led_count=request.get("led_count", 200),
                         sphere_count=request.get("sphere_count", 40),
                         tilted_fraction=request.get("tilted_fraction", TILTED_FRACTION),
                         tilt_deg=request.get("tilt_deg", TILT_DEG), seed=request.get("seed", 0))
        plan_dict = plan_to_dict(plan)
        stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S")
        session_id = f"cal-{stamp}-{secrets.token_hex(3)}"
        self._prune()
        folder = self.root / session_id
        camera = self.service.engine.camera
        writer = SessionWriter(folder, width=camera.width, height=camera.height,
                               fps=float(camera.fps), sphere_radius_mm=geometry.sphere_radius_mm,
                               nominal=nominal, cell_name=f"flyscan serve session {session_id}",
                               sphere_offset_t_mm=geometry.sphere_offset_t_mm, plan=plan_dict)
        save_json_atomic(folder / "plan.json", plan_dict)
        session = _Session(session_id, folder, plan, plan_dict, writer)
        self._save(session)
        with self._lock:
            self._sessions[session_id] = session
        return session.info(with_plan=True)

    def _prune(self) -> None:
        """Only the newest SESSIONS_KEPT - 1 session folders stay before a new one."""
        if not self.root.is_dir():
            return
        done = sorted(p for p in self.root.iterdir() if p.is_dir())
        for old in done[:max(len(done) - (SESSIONS_KEPT - 1), 0)]:
            with self._lock:
                self._sessions.pop(old.name, None)
            shutil.rmtree(old, ignore_errors=True)

    def get(self, session_id: str) -> _Session:
        with self._lock:
            session = self._sessions.get(session_id)
        if session is None:
            raise NoSuchSession(f"no calibration session {session_id!r}")
        return session

    # -- capturing --------------------------------------------------------------------------
    def capture(self, session_id: str, index: int) -> dict:
        """Capture step ``index``: in the simulated cell the robot is sent there first."""
        session = self.get(session_id)
        if not 0 <= index < len(session.plan.steps):
            raise IndexError(f"step {index} is not in the plan (0 to "
                             f"{len(session.plan.steps) - 1})")
        with session.lock:
            if session.state != "recording":
                raise SessionStateError(f"the session is {session.state}: its steps are done")
            if index in session.captured:
                raise SessionStateError(f"step {index} is captured already")
            engine = self.service.engine
            if engine.trigger.state.value not in ("idle", "fault"):
                raise EngineBusy(f"a scan is {engine.trigger.state.value}: capture after it")
            step = session.plan.steps[index]
            self.service.driver.hold(step.kind, step.tcp_b)
            image, tcp, samples = self._still_frame()
            name = session.writer.add(step.kind, image, tcp_b=tcp, samples=samples)
            turn = (np.trace(step.tcp_b[:3, :3].T @ tcp[:3, :3]) - 1.0) / 2.0
            captured = {"index": index, "kind": step.kind, "image": f"{step.kind}/{name}",
                        "tcp": [float(v) for v in matrix_to_ur_pose(tcp)], "samples": samples,
                        "off_plan_mm": float(np.linalg.norm(tcp[:3, 3] - step.tcp_b[:3, 3])),
                        "off_plan_deg": float(np.degrees(np.arccos(np.clip(turn, -1.0, 1.0))))}
            session.captured[index] = captured
            self._save(session)
            return captured

    def _still_frame(self) -> tuple[np.ndarray, np.ndarray, int]:
        """(image (H, W) uint8, the TCP ^B X_T (4, 4) mm the robot reported about it (the mean
        of its reports over AVERAGE_S), how many reports).

        The frame is chosen on the robot's clock: exposed SETTLE_S after the robot's newest
        report when asked (the robot had arrived then), its reports averaged about it; a frame
        whose reports are not still (within STILL_MM) is passed over for the next."""
        engine, robot = self.service.engine, self.service.engine.robot
        if not robot.connected:
            raise SessionStateError("the robot is not connected: a calibration session needs "
                                    "its reported poses")
        arrived = _newest_t(robot)
        if not math.isfinite(arrived):
            raise SessionStateError("the robot has reported no pose yet")
        ready = arrived + SETTLE_S + AVERAGE_S / 2  # robot clock
        deadline = time.monotonic() + CAPTURE_TIMEOUT_S
        while True:
            offset = engine.clock_offset_for_lookups()
            frame = _wait(lambda: (lambda f: f if f is not None and f[0].t + offset >= ready
                                   else None)(engine.latest), "frame after the robot settled")[0]
            t_robot = frame.t + offset
            _wait(lambda: _newest_t(robot) >= t_robot + AVERAGE_S / 2,
                  "robot report for the frame")
            poses = robot_samples(robot, t_robot - AVERAGE_S / 2, t_robot + AVERAGE_S / 2)
            positions = np.array([p.position for p in poses]).reshape(-1, 3)
            if len(poses) and np.max(np.linalg.norm(positions - np.median(positions, axis=0),
                                                    axis=1)) <= STILL_MM:
                break
            if time.monotonic() > deadline:
                raise SessionStateError(f"the robot did not stand still (within {STILL_MM} mm) "
                                        f"for {CAPTURE_TIMEOUT_S:g} s")
            ready = t_robot + AVERAGE_S  # the next window
        position = positions.mean(axis=0)
        # The mean rotation: the mean matrix projected back onto the rotations (its polar part).
        u, _, vt = np.linalg.svd(np.mean([p.rotation for p in poses], axis=0))
        rotation = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        tcp = np.eye(4)
        tcp[:3, :3], tcp[:3, 3] = rotation, position
        return np.array(frame.image, copy=True), tcp, len(poses)

    # -- the pass ---------------------------------------------------------------------------
    def record_pass(self, session_id: str) -> dict:
        """Arm a recorded scan; the cell controller (or the simulated robot) carries the
        sphere through the sheet; its recording becomes the session's ``pass/``."""
        session = self.get(session_id)
        with session.lock:
            missing = len(session.plan.steps) - len(session.captured)
            if missing:
                raise SessionStateError(f"{missing} of the plan's {len(session.plan.steps)} "
                                        f"steps are not captured yet")
            if session.state != "recording":
                raise SessionStateError(f"the session is {session.state}")
            driver = self.service.driver
            # Out of the views first: the LED held in view would start the pass at once (a
            # real cell's controller has parked the robot at the pass's start already).
            driver.park(calibration_pass=True)
            self._still_frame()
            job = self.service.arm(driver.calibration_part, None, record=True)
            session.pass_scan_id, session.pass_state = job.scan_id, "recording"
            session.state = "recording pass"
            self._save(session)
        threading.Thread(target=self._collect_pass, args=(session, job), daemon=True,
                         name=f"flyscan-calpass-{session_id}").start()
        return session.info()

    def _collect_pass(self, session: _Session, job) -> None:
        """Wait for the pass's recording and move it into the session. The scan itself may
        fail (the design's calibration does not fit the cell yet): the recording is what the
        fit needs (the marker's track and the robot's reports)."""
        deadline = time.monotonic() + PASS_TIMEOUT_S
        while time.monotonic() < deadline:
            recording = (job.info_extra or {}).get("recording", {})
            if recording.get("state") in ("done", "failed"):
                break
            time.sleep(0.05)
        recording = (job.info_extra or {}).get("recording", {})
        with session.lock:
            if recording.get("state") == "done" and recording.get("path"):
                os.replace(self.service.settings.data / recording["path"],
                           session.writer.pass_folder)
                session.pass_state, session.state = "done", "ready to fit"
            else:
                session.pass_state, session.state = "failed", "recording"
                reason = recording.get("error") or (job.info or {}).get("reason") or \
                    f"no recording within {PASS_TIMEOUT_S:g} s"
                session.error = f"the pass was not recorded: {reason}"
            self._save(session)

    # -- the fit ----------------------------------------------------------------------------
    def fit(self, session_id: str) -> dict:
        """Fit the session in a thread; its calibration becomes a version of the history."""
        session = self.get(session_id)
        with session.lock:
            if session.state not in ("ready to fit", "failed"):
                raise SessionStateError(f"the session is {session.state}: fit it once its "
                                        f"steps and its pass are recorded")
            if session.pass_state != "done":
                raise SessionStateError("the pass is not recorded yet")
            session.state, session.error = "fitting", None
            self._save(session)
        threading.Thread(target=self._fit, args=(session,), daemon=True,
                         name=f"flyscan-calfit-{session_id}").start()
        return session.info()

    def _fit(self, session: _Session) -> None:
        try:
            session.writer.close()
            calibration, report = calibrate_session(load_session(session.folder))
            figures = residual_figures(report)
            save_calibration(session.folder / "calibration.json", calibration)
            save_json_atomic(session.folder / "calibration.report.json", report)
            entry = self.service.calibration_history.add(
                calibration, source=f"session {session.session_id}", report=report,
                figures=figures)
            draw_residuals(report, session.folder / "residuals.png")
            # Kept with the version: the chart is drawn once, not for each request (drawing
            # holds the interpreter's lock for about 0.1 s, which the camera's thread needs).
            history = self.service.calibration_history
            shutil.copyfile(session.folder / "residuals.png",
                            history.residuals_path(entry["version"]))
            with session.lock:
                session.version, session.figures, session.state = entry["version"], figures, "fitted"
                self._save(session)
        except Exception as exc:  # the fit's own errors say what the session lacks
            log.exception("calibration session %s: the fit failed", session.session_id)
            with session.lock:
                session.state, session.error = "failed", f"{type(exc).__name__}: {exc}"
                try:
                    self._save(session)
                except OSError as saved:
                    log.error("calibration session %s: state not saved: %s",
                              session.session_id, saved)


def _newest_t(robot) -> float:
    try:
        return robot.latest().t
    except RuntimeError:  # no report yet
        return -math.inf


def _wait(predicate, what: str):
    deadline = time.monotonic() + CAPTURE_TIMEOUT_S
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise SessionStateError(f"no {what} within {CAPTURE_TIMEOUT_S:g} s")
        time.sleep(0.005)


def residual_figures(report: dict) -> dict:
    """The figures a person compares: views held out (the worst view's chosen model), px;
    per view, px; the light plane's and the sphere centres' RMS, um; the pass's, um."""
    ladder = report["models"]["ladder"]
    r = report["residuals"]
    um = lambda v: None if v is None else round(v * 1e3, 2)
    return {"views_heldout_px": max(v["heldout_rms_px"][v["chosen"]] for v in ladder),
            "views_per_view_rms_px": r["views_per_view_rms_px"],
            "plane_rms_um": um(r["plane_rms_mm"]),
            "sphere_centre_rms_um": um(r["sphere_centre_rms_mm"]),
            "led_pass_rms_um": um(r["led_pass_rms_mm"])}


def draw_residuals(report: dict, path: Path) -> None:
    """A PNG of the residuals per view (train and held out) and per position (each LED pose's
    reprojection RMS, each sphere centre's error)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ladder = report["models"]["ladder"]
    per = report.get("per_position") or {}
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
    names = [v["view"] for v in ladder]
    chosen = [v["heldout_rms_px"][v["chosen"]] for v in ladder]
    axes[0].bar(names, report["residuals"]["views_per_view_rms_px"], label="all positions")
    axes[0].plot(names, chosen, "ko", label="held out")
    axes[0].set_ylabel("px RMS")
    axes[0].set_title("views")
    axes[0].legend(fontsize=8)
    led = np.array([np.nan if v is None else v for v in per.get("led_px", [])], dtype=float)
    axes[1].plot(led, ".", ms=3)
    axes[1].set_xlabel("LED pose")
    axes[1].set_ylabel("px RMS over the views")
    axes[1].set_title("LED poses")
    sphere = np.array([np.nan if v is None else v for v in per.get("sphere_centre_mm", [])],
                      dtype=float) * 1e3
    axes[2].plot(sphere, "o", ms=3)
    axes[2].set_xlabel("sphere pose")
    axes[2].set_ylabel("centre error, um")
    axes[2].set_title("sphere poses")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
