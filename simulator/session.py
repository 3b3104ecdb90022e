"""A simulated pass, end to end: the simulated cell drives the same pipeline as the real one.

``flyscan scan``, the benchmarks and the tests call :func:`run_simulated_scan`; it builds the
devices and hands them to the pass session every source drives
(``scanner_core.pipeline.session.run_session``: the pass run and finished as every pass is),
then scores the cloud against the truth.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from scanner_core.geometry.calibration import Calibration
from scanner_core.pipeline import PipelineParams
from scanner_core.pipeline.session import run_session
from scanner_core.pose.registration import PoseParams, PoseResult
from scanner_core.pose.symmetry import nearest_equivalent
from scanner_core.types import Scan
from simulator.cell import Cell
from simulator.devices import SimCamera, SimClock, SimRobot
from simulator.evaluate import cloud_accuracy
from simulator.motion import PassMotion
from simulator.parts import Part
from simulator.render import PartScene


def misplacement_matrix(values) -> np.ndarray | None:
    """``[tx, ty, tz, rx, ry, rz]`` (mm, rotation vector in degrees) -> 4x4 transform in {T}
    (X_T = R X_P + t); None for None. ValueError unless six finite numbers."""
    if values is None:
        return None
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (6,) or not np.all(np.isfinite(values)):
        raise ValueError(f"a misplacement must be six finite numbers, got {values.tolist()}")
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(np.radians(values[3:])).as_matrix()
    m[:3, 3] = values[:3]
    return m


def parse_misplacement(text: str | None) -> np.ndarray:
    """``"tx,ty,tz,rx,ry,rz"`` (mm, rotation vector in degrees) -> 4x4 transform in {T}."""
    if text is None or text == "":
        return np.eye(4)
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--misplace must be six numbers 'tx,ty,tz,rx,ry,rz', got {text!r}") from None
    if len(values) != 6 or not np.all(np.isfinite(values)):
        raise ValueError(f"--misplace must be six finite numbers 'tx,ty,tz,rx,ry,rz', got {text!r}")
    return misplacement_matrix(values)


@dataclass
class SimulatedCell:
    """The devices of one simulated pass, sharing one clock."""

    cell: Cell
    part: Part
    scene: PartScene
    motion: PassMotion
    camera: SimCamera
    robot: SimRobot
    true_grasp: np.ndarray


def simulated_cell(part: Part, cell: Cell, *, misplacement=None, seed: int = 0,
                   drop_rate: float = 0.0, held: Part | None = None) -> SimulatedCell:
    """Devices for one pass of ``part`` held with its nominal grasp composed with
    ``misplacement`` (4x4 in {T}: X_T = R X_P + t on top of the nominal grasp); with ``held``
    the gripper holds that instead (a mesh in ``part``'s CAD frame: a fault,
    ``simulator.faults``), placed by ``part``'s grasp and the misplacement."""
    misplacement = np.eye(4) if misplacement is None else np.asarray(misplacement, dtype=np.float64)
    true_grasp = misplacement @ part.grasp
    scene = PartScene(part if held is None else held, cell)
    motion = PassMotion(cell.pass_profile)
    clock = SimClock()
    camera = SimCamera(scene, motion, true_grasp, seed=seed, drop_rate=drop_rate, clock=clock)
    robot = SimRobot(motion, cell.gripper_rotation_b, clock=clock, effects=cell.effects)
    return SimulatedCell(cell, part, scene, motion, camera, robot, true_grasp)


def run_simulated_scan(part: Part, cell: Cell, *, calibration: Calibration | None = None,
                       misplacement=None, seed: int = 0, drop_rate: float = 0.0,
                       params: PipelineParams = PipelineParams(), evaluate: bool = True,
                       pose: bool = True, pose_params: PoseParams = PoseParams(),
                       held: Part | None = None) -> tuple[Scan, dict]:
    """Scan ``part`` in the simulated ``cell``.

    Parameters
    ----------
    calibration : Calibration, optional
        What the scanner believes; default the cell's truth.
    pose : bool
        Register the scan against the part's CAD model (``scanner_core.pose.registration``).
    held : Part, optional
        What the gripper holds instead of ``part`` (``simulated_cell``), while the scanner
        registers ``part``: a fault (``simulator.faults``) or any mesh.

    Returns
    -------
    scan : Scan
    report : dict
        ``report.json`` content: frames, frames_dropped, points, edge_points, timings_ms,
        pose (None when not asked for, or ``{"refused": reason}``), cross_check and
        ground_truth (with the pose's error against the true grasp).
    """
    sim = simulated_cell(part, cell, misplacement=misplacement, seed=seed, drop_rate=drop_rate,
                         held=held)
    calibration = cell.calibration if calibration is None else calibration
    outcome = run_session(sim.camera, sim.robot, calibration, params=params,
                          part_model=part if pose else None, register=pose,
                          pose_params=pose_params)
    scan, report, result = outcome.scan, outcome.report, outcome.pose
    processing_ms = report["timings_ms"]["processing"]
    report["timings_ms"].update(outcome.timings_ms)  # the warm-up, the cross-check, the pose
    # The pass's span on the camera clock, frames lost or unplaced included.
    camera_time_s = (scan.frames + scan.frames_unplaced + scan.frames_dropped) / cell.pass_profile.fps
    report["camera_time_s"] = camera_time_s
    report["realtime_factor"] = (camera_time_s * 1e3 / processing_ms) if processing_ms > 0 else None
    report["ground_truth"] = {
        "grasp": sim.true_grasp.tolist(),
        "nominal_grasp": part.grasp.tolist(),
        "misplacement": (np.eye(4) if misplacement is None else np.asarray(misplacement)).tolist(),
        "part": {"name": part.name, "source": part.source, "units": part.units,
                 "faces": int(len(part.faces))},
        **({} if held is None else {"held": {"name": held.name, "source": held.source,
                                             "faces": int(len(held.faces))}}),
        "cell": cell.to_dict(),
    }
    if result is not None:
        report["ground_truth"]["pose_error"] = pose_error(result, sim.true_grasp,
                                                          part.surface_model.symmetries)
    if evaluate:
        t0 = time.perf_counter()
        report["ground_truth"]["accuracy"] = cloud_accuracy(
            scan.cloud, scan.frame_ids, (part if held is None else held).mesh, sim.true_grasp,
            sim.camera.truths,
            cell.gripper_rotation_b, seed=seed)
        report["ground_truth"]["accuracy"]["eval_ms"] = round((time.perf_counter() - t0) * 1e3, 1)
    return scan, report


def pose_error(result: PoseResult, true_grasp: np.ndarray, symmetries=None) -> dict:
    """How far a registered pose is from the truth, per axis, and in reported sigmas.

    The error is ``result.matrix @ inv(true_grasp)``: a motion in {T}, translation of the
    {T} origin in um, rotation vector in millidegrees; ``sigmas`` divides each axis by its
    reported standard deviation (None along a free motion). With `symmetries` ((K, 4, 4),
    ``SurfaceModel.symmetries``), the truth is its turn nearest the pose: a part its own
    turns map onto itself sits the same at each.
    """
    if symmetries is not None:
        true_grasp = true_grasp @ nearest_equivalent(true_grasp, result.matrix, symmetries)
    e = result.matrix @ np.linalg.inv(true_grasp)
    values = np.concatenate([e[:3, 3] * 1e3, Rotation.from_matrix(e[:3, :3]).as_rotvec(degrees=True) * 1e3])
    std = result.std * np.array([1e3, 1e3, 1e3, 1e3, 1e3, 1e3])
    with np.errstate(invalid="ignore", divide="ignore"):
        sigmas = np.abs(values) / std
    return {
        "translation_um": np.round(values[:3], 3).tolist(),
        "rotation_mdeg": np.round(values[3:], 3).tolist(),
        "sigmas": [None if not np.isfinite(v) else round(float(v), 3) for v in sigmas],
    }
