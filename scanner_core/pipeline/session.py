"""One pass from devices: the pass session every source of a single pass drives.

``flyscan scan`` on the simulated cell (``simulator.session``), on a camera and a robot, and on
a recording, ``flyscan replay`` and the benchmarks call :func:`run_session`: warm the kernels
up, open the camera and connect the robot, control the exposure, run the pass
(``scanner_core.pipeline.run_pass``), finish it (``scanner_core.pipeline.finish.finish_pass``:
the verdict, the pose, the cross-check, the report), and close the devices whatever happened.
The service streams instead (its camera stays open between passes) and finishes each pass
with the same finisher, so every source reports the same for the same frames.

A recording is replayed with the parameters and the cross-check state it was recorded with
(:func:`recorded_params`, :func:`recorded_state`).
"""
from __future__ import annotations

import dataclasses
import math
import time

from scanner_core.devices import Camera, Robot
from scanner_core.pipeline.drive import camera_frames, run_pass
from scanner_core.pipeline.exposure import ExposureController, ExposureParams
from scanner_core.pipeline.finish import CrossCheckState, PassOutcome, finish_pass
from scanner_core.pipeline.frame import PipelineParams, warm_up
from scanner_core.pipeline.trigger import EndReason, TriggerParams

__all__ = ["run_session", "recorded_params", "recorded_state"]


def run_session(camera: Camera, robot: Robot, calibration, *,
                params: PipelineParams = PipelineParams(), part_model=None, register: bool = True,
                pose_params=None, state: CrossCheckState | None = None,
                clock_offset_s: float | None = None, frames_timeout_s: float | None = None,
                control_exposure: bool = True, **report_extra) -> PassOutcome:
    """One pass of ``camera`` and ``robot`` (neither open yet), finished.

    Parameters
    ----------
    camera, robot : scanner_core.devices.Camera, Robot
        Opened and connected here, closed and disconnected on the way out.
    calibration : scanner_core.geometry.calibration.Calibration
        What the scanner knows of the cell; its image size must be the camera's (ValueError).
    params : PipelineParams
    part_model : scanner_core.cad.PartModel, optional
        The part to register the scan against.
    register : bool
        Ask for the pose (without a model the report says why there is none); False: the
        report's pose is None.
    pose_params : scanner_core.pose.registration.PoseParams, optional
    state : CrossCheckState, optional
        What the cross-check carries in; default the calibration's clock offset, nothing
        learned.
    clock_offset_s : float, optional
        Robot minus camera clock the frames are placed with, s; default the state's.
    frames_timeout_s : float, optional
        A camera silent this long ends the pass (``camera_frames``).
    control_exposure : bool
        Control the camera's exposure during the pass (``params.exposure``); False for a
        camera whose frames are already taken (a recording).
    **report_extra
        Further ``report.json`` entries (``finish_pass``).

    Returns
    -------
    PassOutcome
        With ``timings_ms["warmup"]``: the kernels' warm-up, ms.
    """
    state = state or CrossCheckState(clock_offset_s=calibration.clock_offset_s)
    t0 = time.perf_counter()
    warm_up(calibration, params)
    warmup_ms = (time.perf_counter() - t0) * 1e3
    camera.open()
    try:
        calibration.check_image_size(camera.width, camera.height)
        robot.connect()
        exposure = (ExposureController(camera, params.exposure, float(getattr(camera, "fps", 0.0)
                                                                      or 0.0))
                    if control_exposure else None)
        scan = run_pass(camera_frames(camera, timeout=frames_timeout_s), calibration, robot,
                        params, exposure=exposure,
                        clock_offset_s=(state.clock_offset_s if clock_offset_s is None
                                        else clock_offset_s))
        outcome = finish_pass(scan, EndReason(scan.end_reason) if scan.end_reason else None,
                              robot, state, part_model, register=register,
                              pose_params=pose_params, detail=scan.interrupted, **report_extra)
    finally:
        camera.close()
        robot.disconnect()
    outcome.timings_ms["warmup"] = round(warmup_ms, 3)
    return outcome


def recorded_params(recording, *, stripe_method: str | None = None,
                    exposure_mode: str | None = None) -> PipelineParams:
    """The pipeline's parameters a recording was made with (its ``settings``: the stripe
    method, the exposure mode, the trigger), with no arming timeout (the recording ends by
    itself); ``stripe_method`` and ``exposure_mode`` replace the recorded ones when given."""
    settings = recording.settings
    trigger = TriggerParams(**{**settings.get("trigger", {}), "arm_timeout_s": math.inf})
    return dataclasses.replace(
        PipelineParams(), trigger=trigger,
        stripe_method=stripe_method or settings.get("stripe_method", "cog"),
        exposure=ExposureParams(mode=exposure_mode or settings.get("exposure_mode", "fixed")))


def recorded_state(recording) -> CrossCheckState:
    """The cross-check state the recorded pass started from (``settings["cross_check_state"]``;
    a recording made before it was kept: its clock offset, nothing learned)."""
    settings = recording.settings
    return CrossCheckState.from_dict(settings.get("cross_check_state") or {
        "clock_offset_s": float(settings.get("clock_offset_s", 0.0))})
