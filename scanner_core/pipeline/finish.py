"""The pass finisher: from a finished pass to its verdict, cross-check, edges, pose and report.

One copy of what happens when a pass ends, whatever drove it: the service's finisher thread,
``flyscan scan`` (the simulated cell, a recording, a camera and a robot), ``flyscan replay``
and the benchmarks all call :func:`finish_pass`, so a replayed recording reports what the
live pass reported.

1. **Verdict** (:func:`pass_failure`): the one rule that makes a finished pass a failed scan
   (it timed out, the camera stopped, no profile was placed, no point was found...).
2. **Pose** (``scanner_core.pose.registration.scan_pose``) against the part's CAD model
   (``scanner_core.cad.PartModel``), when the pass is a scan and a model is given, handed
   at once to ``on_pose`` (the service publishes it: the robot waits for it alone), or the
   pose computed before the pass ended, when the pass added nothing it reads
   (``scanner_core.pose.ahead``); with a
   pose that constrains every axis the edge points off the model's edges are then set aside
   (``scanner_core.edges.kinds.reclassify_with_model``: the model says where its edges are).
3. **Cross-check** (:func:`check_against_robot`): the marker-derived TCP track against the
   robot's reports, with the clock offset and the LED offset's correction it learns. What it
   carries from pass to pass is a :class:`CrossCheckState`, passed in and returned, never
   hidden in the finisher. After the pose, which does not use it.
4. **Report** (``scanner_core.pipeline.report.scan_report``): ``report.json``, with the verdict.

Pure: no threads, sockets or files. The caller publishes and stores.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from scanner_core.pipeline.crosscheck import (DEFAULT_TOLERANCE_MM, MAX_DRIFT_STEP_S, MAX_OFFSET_STEP_S,
                                              cross_check, robot_positions)
from scanner_core.devices import Robot, TcpPose
from scanner_core.edges.kinds import reclassify_with_model
from scanner_core.inspection import Inspection, InspectionParams, inspect_scan, point_spacing
from scanner_core.pose.ahead import PoseAhead, inputs_pose_report
from scanner_core.pose.inputs import ScanPoseInputs
from scanner_core.pipeline.report import scan_report
from scanner_core.pipeline.trigger import EndReason
from scanner_core.types import Scan

#: How long the cross-check waits for the robot's reports to reach the pass's last frame, s,
#: and how often it looks. It runs after the pose is out: the robot never waits for it.
REPORT_WAIT_S, REPORT_POLL_S = 0.2, 0.002

__all__ = ["CrossCheckState", "PassOutcome", "pass_failure", "check_against_robot",
           "finish_pass"]


@dataclass(frozen=True)
class CrossCheckState:
    """What the cross-check carries from one pass to the next.

    Attributes
    ----------
    clock_offset_s : float
        Robot minus camera clock, s.
    clock_offset_estimated : bool
        A pass has estimated the offset: the next may only drift from it
        (``crosscheck.MAX_DRIFT_STEP_S``), not jump (``MAX_OFFSET_STEP_S``).
    led_correction_t_mm : (3,) tuple of float or None
        The constant difference marker minus robot in {T}, mm (what the calibration's LED
        offset misses); None: learned from the first pass the robot reports, then kept.
    led_correction_from : str or None
        Where it came from (the settings, or the scan it was learned from).
    tolerance_mm : float
        Deviations above this flag the check.
    """

    clock_offset_s: float = 0.0
    clock_offset_estimated: bool = False
    led_correction_t_mm: tuple | None = None
    led_correction_from: str | None = None
    tolerance_mm: float = DEFAULT_TOLERANCE_MM

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "CrossCheckState":
        names = {f.name for f in dataclasses.fields(cls)}
        data = {k: v for k, v in dict(data).items() if k in names}
        if data.get("led_correction_t_mm") is not None:
            data["led_correction_t_mm"] = tuple(float(v) for v in data["led_correction_t_mm"])
        return cls(**data)


@dataclass
class PassOutcome:
    """A finished pass.

    Attributes
    ----------
    state : str
        ``"done"`` or ``"failed"``.
    reason : str or None
        Why it failed (``pass_failure``), or why the pass ended when it did not fail.
    scan : Scan
        The scan, its edge points reclassified by the model when a pose fixed every axis.
    cross_check : dict or None
        ``scanner_core.pipeline.crosscheck.cross_check`` of the pass (None: no profile was placed).
    pose : scanner_core.pose.registration.PoseResult or None
    pose_report : dict or None
        ``report.json``'s ``pose``: the pose's dict, ``{"refused": reason}``, or None when no
        pose was asked for (no model, or a failed pass).
    report : dict
        ``report.json``.
    cross_check_state : CrossCheckState
        The state to hand the next pass.
    timings_ms : dict
        Wall, ms: ``cross_check``; with a pose, ``pose`` (the whole of it), of which
        ``normals`` (the scan's normals) and ``registration`` (``PoseResult.time_ms``), and
        ``reclassify`` (the edge points by the model, after it); ``report``.
    """

    state: str
    reason: str | None
    scan: Scan
    cross_check: dict | None
    pose: object
    pose_report: dict | None
    report: dict
    cross_check_state: CrossCheckState
    timings_ms: dict


def pass_failure(scan: Scan, end_reason: EndReason | None, *, detail: str | None = None,
                 note: str | None = None, frames_lost: int = 0, queue_overflows: int = 0,
                 worker_errors=()) -> str | None:
    """Why a finished pass is a failed scan, or None: the one rule.

    Parameters
    ----------
    scan : Scan
    end_reason : EndReason or None
        Why the trigger ended the pass (None: the frames ran out, as in a replay).
    detail : str, optional
        What the caller knows of the end (the camera's error, who reset the pass).
    note : str, optional
        Said with a timeout (why the marker may never have appeared: the simulated pass did
        not start, say).
    frames_lost : int
        Frames of the pass that never arrived from the camera.
    queue_overflows : int
        Frames the machine could not keep up with.
    worker_errors : sequence of str
        Frames that failed to process.
    """
    if end_reason is EndReason.TIMEOUT:
        return "timeout: the marker never appeared" + (f" ({note})" if note else "")
    if end_reason is EndReason.CAMERA_STOPPED:
        return "camera stopped" + (f": {detail}" if detail else "")
    if end_reason is EndReason.TOO_LONG:
        return "too long: the marker did not leave the view within the maximum pass length"
    if end_reason is EndReason.RESET:
        return f"reset: {detail}" if detail else "reset during the pass"
    if scan.frames == 0 and scan.frames_without_rotation:
        return ("no profile could be placed: the robot gave no pose to take the gripper's "
                "rotation from")
    if scan.frames == 0 and scan.frames_unplaced:
        # found but never placed: something hides or stands for part of the LED's views
        residual = scan.marker_residual_px
        views = (f"its views disagreeing by {residual:.0f} px" if np.isfinite(residual)
                 else "in fewer than two views")
        return (f"no profile could be placed: the marker was found in {scan.frames_unplaced} "
                f"frame{'s' if scan.frames_unplaced != 1 else ''} and never triangulated "
                f"({views}); something may hide the gripper's LED (a second part held, say), "
                f"or the calibration does not fit the cell")
    if scan.frames == 0:
        return "no profile could be placed (the marker was never triangulated)"
    if len(scan.cloud) == 0:
        lost = []
        if frames_lost:
            lost.append(f"{frames_lost} frames of the pass never arrived from the camera")
        if queue_overflows:
            lost.append(f"{queue_overflows} overflowed the processing queue")
        return (f"no points: {scan.frames} profiles were placed but the stripe was found on none"
                + (f" ({'; '.join(lost)}: the machine fell behind the camera)" if lost else ""))
    if worker_errors:
        return f"{len(worker_errors)} frames failed to process: {worker_errors[0]}"
    return None


def check_against_robot(scan: Scan, robot: Robot, state: CrossCheckState, *,
                        scan_id: str | None = None) -> tuple[dict, CrossCheckState]:
    """The pass's marker-derived TCP track against the robot's, and the state it leaves.

    The clock offset is estimated within ``MAX_OFFSET_STEP_S`` of the state's until a pass
    has estimated it, then within ``MAX_DRIFT_STEP_S``; an unflagged estimate is kept for the
    next pass. Without a correction of the LED offset, the first pass the robot reports
    learns one (its constant difference marker minus robot) and is checked again with it;
    learned every pass it would hide inconsistencies.

    Returns
    -------
    check : dict
        ``scanner_core.pipeline.crosscheck.cross_check``'s on the robot's reports up to its
        newest when the check began (``reports_until_s``, robot clock, s; None: it had none),
        with ``led_correction_learned`` when it learned the correction; when frames were
        placed on a held rotation and the robot has no pose for some of the pass's frames
        (lost for part of it) ``frames_held_rotation``, ``held_rotation_fraction`` (of the
        frames placed), ``flagged`` and the ``reason``.
    state : CrossCheckState
    """
    _await_reports(robot, scan.tcp_times, state.clock_offset_s)
    # The reports the check reads are those it had once it stopped waiting: one arriving
    # while it runs would change its samples halfway, and a recording of the pass keeps this
    # cut-off so that its replay reads the same ones (``ReplayRobot``).
    robot = _ReportedBy(robot)

    def check(correction, offset_s, max_step_s):
        return cross_check(scan.tcp_times, scan.tcp_positions_b, robot, clock_offset_s=offset_s,
                           max_offset_step_s=max_step_s, led_correction_t_mm=correction,
                           tolerance_mm=state.tolerance_mm)

    max_step_s = MAX_DRIFT_STEP_S if state.clock_offset_estimated else MAX_OFFSET_STEP_S
    result = check(state.led_correction_t_mm, state.clock_offset_s, max_step_s)
    if state.led_correction_t_mm is None and result["samples"] and result["offset_estimated"]:
        learned = tuple(float(v) for v in result["mean_difference_t_mm"])
        result = check(learned, result["clock_offset_s"], MAX_DRIFT_STEP_S)
        state = dataclasses.replace(state, led_correction_t_mm=learned,
                                    led_correction_from=scan_id or "a scan")
        result["led_correction_learned"] = True
    held = int(getattr(scan, "frames_held_rotation", 0))
    # the frames the robot still gives no pose for (not those the check left out for another
    # reason, a chord too far from the path, say)
    unposed = 0 if not held else int((~robot_positions(
        robot, np.asarray(scan.tcp_times, dtype=np.float64) + float(result["clock_offset_s"]),
        max_chord_mm=np.inf)[1]).sum())
    if held and unposed > 0:
        # The robot lost for part of the pass: frames placed on a held rotation that it still
        # has no pose for were never checked, and their placement is a guess; the check says
        # so, and how much. (A frame held only because the robot's report came late, and
        # checked since, is not: under load the last frames of a pass can outrun the reports.)
        result["frames_held_rotation"] = held
        result["held_rotation_fraction"] = round(held / scan.frames, 4)
        held_reason = (f"the robot gave no pose for {held} of {scan.frames} frames "
                       f"({held / scan.frames:.0%}): their rotation was held")
        result["reason"] = "; ".join(filter(None, (result.get("reason"), held_reason)))
        result["flagged"] = True
    if result.get("offset_estimated") and not result.get("flagged"):
        state = dataclasses.replace(state, clock_offset_s=float(result["clock_offset_s"]),
                                    clock_offset_estimated=True)
    result["reports_until_s"] = robot.until
    return result, state


class _ReportedBy:
    """A robot as it stood when made: its look-ups end at the report that was its newest then
    (``until``, robot clock, s; None when none had arrived or it was not connected), whatever
    arrives after."""

    def __init__(self, robot: Robot):
        self._robot = robot
        self.connected = bool(robot.connected)
        self.until = None
        if self.connected:
            try:
                self.until = float(robot.latest().t)
            except RuntimeError:  # none has arrived
                pass

    def latest(self) -> TcpPose:
        try:
            if self.until is not None:
                return self._robot.pose_at(self.until)
        except LookupError:  # gone from a bounded history since
            pass
        raise RuntimeError("no robot report had arrived at the check")

    def pose_at(self, t: float) -> TcpPose:
        if self.until is None or t > self.until:
            raise LookupError(f"t = {t:.4f} s is past the robot's reports at the check")
        return self._robot.pose_at(t)


def _await_reports(robot: Robot, tcp_times, clock_offset_s: float,
                   timeout_s: float = REPORT_WAIT_S) -> None:
    """Wait, at most `timeout_s`, until the robot has reported for the pass's last frame
    (its time on the robot's clock through `clock_offset_s`): the reports come over the
    network behind the frames, and a pass checked before they arrive would call its last
    frames unchecked. Returns at once without a robot, a connection or a report."""
    times = np.asarray(tcp_times, dtype=np.float64)
    if robot is None or not robot.connected or not np.isfinite(times).any():
        return
    until = float(np.nanmax(times)) + clock_offset_s
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            if robot.latest().t >= until:
                return
        except RuntimeError:  # none has arrived
            return
        if time.monotonic() >= deadline:
            return
        time.sleep(REPORT_POLL_S)


def inspect_pass(scan: Scan, part_model, pose_matrix: np.ndarray,
                 params: InspectionParams = InspectionParams()) -> Inspection:
    """The check of a pass's scan against its part's model at the registered pose
    ``pose_matrix`` (^T X_P, (4, 4)): ``scanner_core.inspection.inspect_scan`` with the
    part's own thresholds over `params`. Changes nothing in `scan`."""
    if part_model.inspection is not None:  # the part's own thresholds first
        params = part_model.inspection.over(params)
    return inspect_scan(scan.cloud, scan.frame_ids, pose_matrix, part_model.surface_model,
                        profile_spacing_mm=scan.profile_spacing_mm,
                        point_spacing_mm=point_spacing(scan.cloud, scan.frame_ids),
                        params=params, coverage_model=part_model.coverage_model,
                        occluded=part_model.occluded, sheet_planes_t=scan.sheet_planes_t,
                        sensor_positions_t=scan.sensor_positions_t,
                        sheet_frame_ids=scan.tcp_frame_ids, sharp_edges=part_model.edge_model,
                        measured_box_t=scan.measured_box_t)


def _inspect(scan: Scan, part_model, pose, pose_report: dict,
             params: InspectionParams) -> Inspection:
    """The check at the pose (`inspect_pass`): its verdict into the pose's report
    (``inspection``; ``act`` false with the reasons when it fails), every point's deviation
    into the scan."""
    inspection = inspect_pass(scan, part_model, pose.matrix, params)
    scan.deviations_mm = inspection.deviations_mm
    pose_report["inspection"] = inspection.to_dict()
    if not inspection.conforms and pose_report.get("act"):
        pose_report["act"] = False
    if not inspection.conforms:
        pose_report["act_reasons"] = [*pose_report.get("act_reasons", []),
                                      *(f"inspection: {r}" for r in inspection.reasons)]
    return inspection


def finish_pass(scan: Scan, end_reason: EndReason | None, robot: Robot | None,
                state: CrossCheckState, part_model=None, *, register: bool = True,
                pose_params=None, scan_id: str | None = None, detail: str | None = None,
                note: str | None = None, frames_lost: int = 0, queue_overflows: int = 0,
                worker_errors=(), verdict=None, on_pose=None,
                pose_ahead: PoseAhead | None = None,
                inspection_params: InspectionParams = InspectionParams(),
                **report_extra) -> PassOutcome:
    """A finished pass's verdict, cross-check, pose, edges and report.

    Parameters
    ----------
    scan : Scan
        ``PassAccumulator.scan`` of the pass (its edge points may be reclassified in place).
    end_reason : EndReason or None
    robot : Robot or None
        The robot whose reports the pass is checked against (a live one, the simulated one,
        or a recording's samples); None: no cross-check.
    state : CrossCheckState
    part_model : scanner_core.cad.PartModel, optional
        The part's CAD model; None: no pose, and the report's pose says why (the part
        ``report_extra["part"]`` names has no model).
    register : bool
        Ask for the pose; False: the report's pose is None (a pass scanned for its cloud).
    pose_params : scanner_core.pose.registration.PoseParams, optional
    scan_id : str, optional
        Named in the report, and as where a learned LED correction came from.
    detail, note, frames_lost, queue_overflows, worker_errors
        As for :func:`pass_failure`.
    verdict : tuple, optional
        ``(pass_failure(...),)`` when the caller has judged the pass already (the service,
        to send the cloud out with its state): not judged again.
    on_pose : callable(pose_report, timings_ms), optional
        Called as soon as the pose is known (or refused), before anything the robot does not
        need (the edge points' reclassification, the report): the service publishes the pose
        from it, so the robot never waits for those. ``pose_report`` is what the outcome's
        ``pose_report`` will be; ``timings_ms`` the timings so far (``pose``, ``normals``,
        ``registration``: the cross-check comes after the pose, which does not use it). Not
        called when no pose is asked for (``register`` False, a failed pass).
    inspection_params : scanner_core.inspection.InspectionParams
        The check of the cloud against the model at the pose (``scanner_core.inspection``):
        it runs on every pose with a matrix, before ``on_pose``; a failing check makes
        ``act`` false with its reasons, and every cloud point's deviation is kept
        (``Scan.deviations_mm``).
    pose_ahead : scanner_core.pose.ahead.PoseAhead, optional
        A pose computed before the pass ended (``scanner_core.pose.ahead.pose_ahead``): kept
        when this scan's pose inputs, model and params are its own (then ``timings_ms`` has
        ``ahead``, that pose's own time, and no ``normals`` or ``registration``), else the
        pose is computed here.
    **report_extra
        Further ``report.json`` entries (the service's scan id and times, a replay's source).

    Returns
    -------
    PassOutcome
    """
    from scanner_core.pose.registration import PoseParams

    timings = {}
    failure = verdict[0] if verdict is not None else pass_failure(
        scan, end_reason, detail=detail, note=note, frames_lost=frames_lost,
        queue_overflows=queue_overflows, worker_errors=worker_errors)
    pose = pose_report = None
    if failure is None and register and part_model is None:
        named = report_extra.get("part")
        pose_report = {"refused": "no CAD model" + (f" for part {named!r}" if named else "")}
        timings["pose"] = 0.0
        if on_pose is not None:
            on_pose(pose_report, dict(timings))
    if failure is None and register and part_model is not None:
        t0 = time.perf_counter()
        params = pose_params or PoseParams()
        inputs = ScanPoseInputs.of(scan)
        if pose_ahead is not None and pose_ahead.serves(inputs, part_model, params):
            pose, pose_report = pose_ahead.pose, dict(pose_ahead.report)
            timings["ahead"] = pose_ahead.timings_ms["pose"]
        else:
            pose, pose_report, computed = inputs_pose_report(inputs, part_model, params)
            timings.update(computed)
        timings["pose"] = round((time.perf_counter() - t0) * 1e3, 3)
        if pose is not None:
            inspection = _inspect(scan, part_model, pose, pose_report, inspection_params)
            timings["inspection"] = round(inspection.time_ms, 3)
        if on_pose is not None:
            on_pose(pose_report, dict(timings))
        if pose is not None and pose.observable:
            t0 = time.perf_counter()
            reclassify_with_model(scan, part_model.model_edges, pose.matrix)
            timings["reclassify"] = round((time.perf_counter() - t0) * 1e3, 3)
    # After the pose, which does not use it: the robot need not wait for it (it judges the
    # track the pass was placed by, and hands the next pass its clock offset).
    check = None
    t0 = time.perf_counter()
    if robot is not None and scan.frames > 0:
        check, state = check_against_robot(scan, robot, state, scan_id=scan_id)
    timings["cross_check"] = round((time.perf_counter() - t0) * 1e3, 3)
    t0 = time.perf_counter()
    state_name = "failed" if failure else "done"
    ended = None if end_reason is None else end_reason.value + (f": {detail}" if detail else "")
    if scan_id is not None:
        report_extra = {"scan_id": scan_id, **report_extra}
    if worker_errors:
        report_extra["worker_errors"] = list(worker_errors)[:10]
    report = scan_report(scan, check, state=state_name, reason=failure or ended,
                         **report_extra)
    report["pose"] = pose_report
    report["inspection"] = (pose_report or {}).get("inspection")
    if failure:
        report.update(status="failed", failure=failure)
    timings["report"] = round((time.perf_counter() - t0) * 1e3, 3)
    return PassOutcome(state=state_name, reason=failure or ended, scan=scan, cross_check=check,
                       pose=pose, pose_report=pose_report, report=report,
                       cross_check_state=state, timings_ms=timings)
