"""The pass logic: trigger gaps, a camera that stops, stitching by the marker."""
import numpy as np
import pytest
from numpy.testing import assert_allclose

from scanner_core.devices import CameraTimeout
from scanner_core.pipeline import pass_frames, scan_frames, stitch
from scanner_core.types import Frame, MarkerObservation, Profile
from simulator.session import camera_frames, simulated_cell


@pytest.fixture(scope="module")
def pass_frames_list(block_part, cell):
    sim = simulated_cell(block_part, cell.with_pass(fps=40.0), seed=9)
    sim.camera.open()
    return list(camera_frames(sim.camera)), sim


def _blank(frame):
    return Frame(np.full_like(frame.image, 10), frame.frame_id, frame.t)


def test_trigger_spans_the_marker(pass_frames_list, cell):
    frames, _ = pass_frames_list
    got = [f.frame_id for f in pass_frames(iter(frames), cell.calibration)]
    assert got == list(range(got[0], got[-1] + 1))
    assert 0 < got[0] and got[-1] < frames[-1].frame_id  # lead-in and lead-out left out


@pytest.mark.parametrize("gap, continues", [(2, True), (3, False)])
def test_trigger_rides_over_short_gaps(pass_frames_list, cell, gap, continues):
    frames, _ = pass_frames_list
    full = [f.frame_id for f in pass_frames(iter(frames), cell.calibration)]
    mid = full[len(full) // 2]
    holed = [_blank(f) if mid <= f.frame_id < mid + gap else f for f in frames]
    got = [f.frame_id for f in pass_frames(iter(holed), cell.calibration)]
    assert got == (full if continues else full[: full.index(mid)])


def test_camera_that_stops_keeps_what_was_acquired(pass_frames_list, cell):
    frames, sim = pass_frames_list
    full = scan_frames(iter(frames), cell.calibration, cell.gripper_rotation_b)
    cut = [f.frame_id for f in pass_frames(iter(frames), cell.calibration)]
    stop_at = cut[len(cut) // 2]

    def stopping():
        for f in frames:
            if f.frame_id == stop_at:
                raise CameraTimeout("no frame for 1.0 s")
            yield f

    partial = scan_frames(stopping(), cell.calibration, cell.gripper_rotation_b)
    assert full.interrupted is None
    assert partial.interrupted.startswith("camera timeout")
    assert 0 < partial.frames < full.frames
    kept = full.frame_ids < stop_at
    assert_allclose(partial.cloud, full.cloud[kept])  # nothing acquired is lost


def test_stitch_places_profiles_by_the_marker(cell):
    """Two frames of the same {T} point at different gripper positions land on one point."""
    cal = cell.calibration
    r = cell.gripper_rotation_b
    point_t = np.array([5.0, -3.0, 12.0])
    profiles = []
    for i, tcp in enumerate(([1.0, -20.0, 50.0], [1.7, 14.0, 50.4])):
        tcp = np.array(tcp)
        marker_b = tcp + r @ cal.marker_offset_t
        obs = MarkerObservation(np.zeros((3, 2)), marker_b, 0.0)
        profiles.append(Profile(i, 0.01 * i, (tcp + r @ point_t)[None], np.array([0], np.int32),
                                np.array([200.0], np.float32), obs))
    scan = stitch(profiles, cal, r)
    assert_allclose(scan.cloud, [point_t, point_t], atol=1e-5)
    assert scan.frames == 2 and scan.frames_dropped == 0


def test_stitch_counts_gaps_and_unplaced(cell):
    r = cell.gripper_rotation_b
    nan_obs = MarkerObservation(np.full((3, 2), np.nan), np.full(3, np.nan), float("nan"))
    ok_obs = MarkerObservation(np.zeros((3, 2)), np.zeros(3), 0.1)
    empty = np.zeros((0, 3))
    profiles = [Profile(fid, 0.0, empty, np.zeros(0, np.int32), np.zeros(0, np.float32), obs)
                for fid, obs in ((10, ok_obs), (11, nan_obs), (14, ok_obs))]
    scan = stitch(profiles, cell.calibration, r)
    assert scan.frames == 2 and scan.frames_unplaced == 1 and scan.frames_dropped == 2


def test_warm_up_frame_finds_the_marker_everywhere(cell, monkeypatch):
    """The warm-up frame must reach every kernel: a marker in all three views and a stripe."""
    from scanner_core import pipeline
    seen = {}
    real = pipeline.process_frame

    def spy(frame, calibration, params=pipeline.PipelineParams()):
        profile = real(frame, calibration, params)
        seen["profile"] = profile
        return profile

    monkeypatch.setattr(pipeline, "process_frame", spy)
    pipeline.warm_up(cell.calibration)
    profile = seen["profile"]
    assert profile.marker.views == 3
    assert len(profile.columns) > 500
