"""A pass's pose computed before the pass ends, kept only when the pass adds nothing it reads.

The gripper carries the part through the sheet and on, until the marker leaves the view: in
the reference cell the part has left the sheet 240-1 200 ms before the pass ends (bench
pose_time's scans, 100-400 mm/s), and the frames after it place no point. The pose needs only
the points, so the service computes it then (:func:`pose_ahead`, on the finisher thread,
which is idle during a pass) and, when the pass ends, keeps it if what the pose reads of the
whole pass's scan (``scanner_core.pose.inputs.ScanPoseInputs``) is the same, value for value
(:meth:`PoseAhead.serves`); else the pose is computed then, as it always was. The pose is a
function of those inputs alone, so a kept pose is the one the end of the pass would have
computed, bit for bit: a replay (which computes it at the end) reports the same pose.

The scan of the pass so far also leaves its points and edge points to the pass's end
(``PassAccumulator.scan`` takes them when no profile with points came since). What the robot
waits for is then the pass's end, the rest of the scan's assembly and this comparison; the
pose's own time (``PoseResult.time_ms``) is unchanged and still reported.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

from scanner_core.pose.inputs import ScanPoseInputs

__all__ = ["PoseAhead", "pose_ahead", "inputs_pose_report"]


@dataclass(frozen=True, eq=False)
class PoseAhead:
    """A pose computed from a scan of the pass so far.

    Attributes
    ----------
    inputs : ScanPoseInputs
        What the pose read of that scan.
    part_model : scanner_core.cad.PartModel
        The model it was computed against (the same object must finish the pass).
    params : scanner_core.pose.registration.PoseParams
    pose : scanner_core.pose.registration.PoseResult or None
        None when the pose was refused.
    report : dict
        ``PoseResult.to_dict()``, or ``{"refused": reason}``.
    timings_ms : dict
        ``pose`` (the whole of it), ``normals`` and ``registration``, as ``finish_pass``
        reports them, ms.
    """

    inputs: ScanPoseInputs
    part_model: object
    params: object
    pose: object
    report: dict
    timings_ms: dict

    def serves(self, inputs: ScanPoseInputs, part_model, params) -> bool:
        """Whether this pose is the pose of a scan with `inputs`, against `part_model` with
        `params`: the same inputs, value for value, the same model object, equal params."""
        return (part_model is self.part_model and params == self.params
                and inputs.same_as(self.inputs))


def inputs_pose_report(inputs: ScanPoseInputs, part_model, params):
    """``(pose, report, timings_ms)``: the pose of a scan's `inputs` against `part_model`
    (``scanner_core.pose.registration.inputs_pose`` from the model's grasp, with its edge model), or
    ``(None, {"refused": reason}, timings)`` when it is refused (too few points)."""
    from scanner_core.pose.registration import inputs_pose

    timings = {}
    t0 = time.perf_counter()
    try:
        pose = inputs_pose(inputs, part_model.surface_model, part_model.grasp,
                           edge_model=part_model.edge_model, params=params)
    except ValueError as exc:
        pose, report = None, {"refused": str(exc)}
    else:
        report = pose.to_dict()
        timings["normals"] = round(pose.normals_ms, 3)
        timings["registration"] = round(pose.time_ms, 3)
    timings["pose"] = round((time.perf_counter() - t0) * 1e3, 3)
    return pose, report, timings


def pose_ahead(scan, part_model, params=None) -> PoseAhead:
    """The pose of `scan` (the pass so far: ``PassAccumulator.scan``), to be kept at the
    pass's end if the whole pass's scan reads the same (``finish_pass(pose_ahead=...)``)."""
    from scanner_core.pose.registration import PoseParams

    params = params or PoseParams()
    inputs = ScanPoseInputs.of(scan)
    pose, report, timings = inputs_pose_report(inputs, part_model, params)
    return PoseAhead(inputs, part_model, params, pose, report, timings)
