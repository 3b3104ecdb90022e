"""The pose computed before the pass ends (``scanner_core.pose.ahead``): kept only when the
whole pass's scan gives the pose the same inputs, and then the very pose the pass's end would
have computed; any other pose ahead is recomputed."""
import dataclasses
import itertools

import numpy as np
import pytest

from scanner_core.pipeline.finish import CrossCheckState, finish_pass
from scanner_core.pose.registration import PoseParams
from scanner_core.pose.ahead import pose_ahead
from scanner_core.pose.inputs import ScanPoseInputs
from scanner_core.pipeline.trigger import EndReason


def _pass(part, cell, last_frame=None):
    """The simulated pass of `part`, its camera stopped after `last_frame` (a pass so far)."""
    from scanner_core.pipeline import PipelineParams, camera_frames, run_pass
    from simulator.session import simulated_cell

    sim = simulated_cell(part, cell, seed=3)
    sim.camera.open()
    sim.robot.connect()
    frames = camera_frames(sim.camera)
    if last_frame is not None:
        frames = itertools.takewhile(lambda frame: frame.frame_id <= last_frame, frames)
    return run_pass(frames, cell.calibration, sim.robot, PipelineParams())


def _pass_spacing(scan) -> float:
    """The median step of the whole pass's track, the part's profiles or not."""
    return float(np.median(np.linalg.norm(np.diff(scan.tcp_positions_b, axis=0), axis=1)))


def _passes(speed_mm_s=None):
    """A part, its whole pass, the pass so far with the part out of the sheet for 4 frames
    (the service's rule), and the pass so far with the part's last 3 profiles to come."""
    from scanner_core.pipeline import warm_up
    from simulator.cell import load_cell
    from simulator.parts import block_with_holes_and_steps, part_from_mesh

    cell = load_cell()
    if speed_mm_s is not None:
        cell = cell.with_pass(speed_mm_s=speed_mm_s)
    part = part_from_mesh(block_with_holes_and_steps(), name="demo")
    warm_up(cell.calibration)
    whole = _pass(part, cell)
    last_point = int(max(whole.frame_ids.max(), whole.edge_frame_ids.max()))
    assert whole.tcp_frame_ids.max() > last_point + 4  # the gripper goes on after the part
    out = _pass(part, cell, last_frame=last_point + 4)
    inside = _pass(part, cell, last_frame=last_point - 3)
    return part, whole, out, inside


@pytest.fixture(scope="module")
def passes():
    return _passes()


def test_a_pose_ahead_is_kept_when_the_rest_of_the_pass_adds_nothing_it_reads(passes):
    part, whole, out, _ = passes
    assert out.frames < whole.frames and _pass_spacing(out) != _pass_spacing(whole)
    ahead = pose_ahead(out, part)
    kept = finish_pass(whole, EndReason.MARKER_GONE, None, CrossCheckState(), part,
                       pose_ahead=ahead)
    computed = finish_pass(whole, EndReason.MARKER_GONE, None, CrossCheckState(), part)
    assert "ahead" in kept.timings_ms and "registration" not in kept.timings_ms
    assert "ahead" not in computed.timings_ms and "registration" in computed.timings_ms
    # the very pose the pass's end computes, bit for bit (its own time aside)
    assert kept.pose is ahead.pose
    assert np.array_equal(kept.pose.matrix, computed.pose.matrix)
    assert np.array_equal(kept.pose.std, computed.pose.std)
    untimed = lambda report: {k: ({kk: vv for kk, vv in v.items() if kk != "time_ms"}
                                  if k == "inspection" else v)
                              for k, v in report.items()
                              if not k.endswith("time_ms") and k != "normals_ms"}
    same = untimed(computed.pose_report)
    assert {k: untimed(kept.pose_report)[k] for k in same} == same
    assert computed.pose_report["observable"] and np.allclose(computed.pose.matrix, part.grasp,
                                                              atol=0.05)


def test_a_pose_ahead_carrying_the_light_plane_is_kept_too(passes):
    """With the calibration's light plane uncertainty, the pose reads the plane at each
    frame with a point: the frames the gripper goes on through after the part has left the
    sheet change nothing, and the pose ahead is kept, its light plane term in."""
    import copy

    from scanner_core.calibration.plane import PlaneUncertainty

    part, whole, out, _ = passes
    plane = PlaneUncertainty(np.array([0.0, 0.0, -20.0]),
                             np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
                             np.diag([(30e-6) ** 2, (12e-6) ** 2, 0.0005**2]))
    whole, out = copy.copy(whole), copy.copy(out)
    whole.light_plane_uncertainty = out.light_plane_uncertainty = plane
    assert len(whole.tcp_frame_ids) > len(out.tcp_frame_ids)
    ahead = pose_ahead(out, part)
    kept = finish_pass(whole, EndReason.MARKER_GONE, None, CrossCheckState(), part,
                       pose_ahead=ahead)
    assert "ahead" in kept.timings_ms and kept.pose is ahead.pose
    terms = kept.pose_report["std_terms"]["light_plane"]
    assert terms["tz_mm"] > 1e-4 and terms["ry_deg"] > 1e-4


def test_a_pose_ahead_of_points_still_to_come_is_computed_again(passes):
    part, whole, _, inside = passes
    ahead = pose_ahead(inside, part)
    assert ahead.pose is not None and len(ahead.inputs.cloud) < len(whole.cloud)
    outcome = finish_pass(whole, EndReason.MARKER_GONE, None, CrossCheckState(), part,
                          pose_ahead=ahead)
    computed = finish_pass(whole, EndReason.MARKER_GONE, None, CrossCheckState(), part)
    assert "ahead" not in outcome.timings_ms and "registration" in outcome.timings_ms
    assert outcome.pose is not ahead.pose
    assert np.array_equal(outcome.pose.matrix, computed.pose.matrix)


def test_a_pose_ahead_serves_only_its_own_inputs_model_and_params(passes):
    part, whole, out, _ = passes
    ahead = pose_ahead(out, part)
    inputs = ScanPoseInputs.of(whole)
    assert ahead.serves(inputs, part, PoseParams())
    assert not ahead.serves(inputs, dataclasses.replace(part), PoseParams())  # re-uploaded
    assert not ahead.serves(inputs, part, PoseParams(seed=1))
    # one value changed anywhere is another scan
    cloud = inputs.cloud.copy()
    cloud[7, 2] = np.nextafter(cloud[7, 2], np.float32(np.inf))
    assert not ahead.serves(dataclasses.replace(inputs, cloud=cloud), part, PoseParams())
    assert not ahead.serves(dataclasses.replace(inputs, edges=None), part, PoseParams())
    assert not ahead.serves(dataclasses.replace(inputs, sparse="sparse: 3.5 mm"), part,
                            PoseParams())
    # NaN sensors (frames without a camera centre) compare equal to themselves
    sensors = inputs.sensors.copy()
    sensors[0] = np.nan
    nan_inputs = dataclasses.replace(inputs, sensors=sensors)
    assert nan_inputs.same_as(dataclasses.replace(inputs, sensors=sensors.copy()))


def test_a_refused_pose_ahead_is_kept_as_refused(passes):
    part, whole, _, _ = passes
    few = dataclasses.replace(whole)
    few.cloud, few.frame_ids, few.quality = whole.cloud[:20], whole.frame_ids[:20], whole.quality[:20]
    ahead = pose_ahead(few, part)
    assert ahead.pose is None and "at least" in ahead.report["refused"]
    outcome = finish_pass(few, EndReason.MARKER_GONE, None, CrossCheckState(), part,
                          pose_ahead=ahead)
    assert outcome.pose is None and outcome.pose_report == ahead.report
    assert "ahead" in outcome.timings_ms


def test_sparse_profiles_read_the_same_before_the_pass_ends():
    """At 1 000 mm/s the profiles lie 6 mm apart and the pose is flagged sparse, with the
    spacing in the flag: measured on the part's profiles, not the whole pass's (whose median
    moves with the robot's start and its way out), so the pass so far reads the same."""
    part, whole, out, _ = _passes(speed_mm_s=1000.0)
    assert _pass_spacing(whole) != _pass_spacing(out)
    assert whole.profile_spacing_mm == out.profile_spacing_mm
    inputs = ScanPoseInputs.of(whole)
    assert inputs.sparse is not None and inputs.sparse.startswith("sparse: 6.")
    assert ScanPoseInputs.of(out).same_as(inputs)


def test_the_pass_s_end_takes_the_points_and_edges_of_a_scan_of_the_same_profiles(
        passes, monkeypatch):
    """A scan taken once the part has left the sheet (the pose computed ahead) leaves its
    points and edge points to the pass's end, which takes them unless a profile with points
    came since: the same scan as the pass's end computes anew, every field, with no edge
    filter run again, in arrays of its own."""
    import scanner_core.pipeline.accumulate as accumulate
    from scanner_core.pipeline import (MarkerTracker, PassAccumulator, PipelineParams,
                                       camera_frames, feed_frame)
    from scanner_core.pipeline.trigger import Trigger
    from simulator.cell import load_cell
    from simulator.session import simulated_cell

    part, whole, out, _ = passes
    last_point = int(max(whole.frame_ids.max(), whole.edge_frame_ids.max()))
    cell, params = load_cell(), PipelineParams()
    sim = simulated_cell(part, cell, seed=3)
    sim.camera.open()
    sim.robot.connect()
    trigger, tracker = Trigger(params.trigger), MarkerTracker(cell.calibration, params)
    trigger.arm()
    accumulator = PassAccumulator(cell.calibration, sim.robot,
                                  partly_lit_ratio=params.partly_lit_ratio)
    timings = dict.fromkeys(("acquire", "marker", "profiles", "scan"), 0.0)
    stitched = []
    stitch = accumulate._stitch_edges
    monkeypatch.setattr(accumulate, "_stitch_edges",
                        lambda *args: stitched.append(1) or stitch(*args))
    snapshots, quiet = [], {}
    for frame in camera_frames(sim.camera):
        if trigger.state.value not in ("armed", "scanning"):
            break
        feed_frame(frame, tracker, trigger, accumulator, params, timings, None)
        quiet[frame.frame_id] = accumulator.quiet_since(4)
        if frame.frame_id in (last_point - 3, last_point + 4):
            snapshots.append(accumulator.scan())
    # the service's rule: the part has left the sheet 4 frames after its last point
    assert quiet[last_point + 3] is None and quiet[last_point + 4] == last_point
    assert quiet[max(quiet)] == last_point
    assert len(stitched) == 2  # the two scans of the pass so far
    end = accumulator.scan(end_reason=trigger.end_reason)
    assert len(stitched) == 2  # the pass's end took the second's
    fields = ("cloud", "frame_ids", "quality", "edges", "edge_frame_ids", "edge_kind",
              "edge_size_mm", "edge_quality", "tcp_positions_b", "tcp_frame_ids",
              "sensor_positions_t")
    for name in fields:
        mine, theirs = getattr(end, name), getattr(whole, name)
        assert mine.dtype == theirs.dtype, name
        assert np.array_equal(mine, theirs, equal_nan=mine.dtype.kind == "f"), name
    assert end.frames == whole.frames and end.frames > snapshots[1].frames
    assert (end.points_partly_lit, end.edges_occluded, end.edges_grazing) == (
        whole.points_partly_lit, whole.edges_occluded, whole.edges_grazing)
    assert np.array_equal(end.edges_aside.points, whole.edges_aside.points)
    assert end.cloud is not snapshots[1].cloud and end.edges is not snapshots[1].edges
    assert ScanPoseInputs.of(end).same_as(ScanPoseInputs.of(whole))
    # a profile with points after the first scan: computed anew, not taken
    assert len(snapshots[0].cloud) < len(end.cloud)
