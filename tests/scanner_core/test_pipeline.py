"""The streaming core: trigger over real frames, tracking, placement in any order, a camera
that stops, a robot that gives no pose."""
import numpy as np
import pytest
from numpy.testing import assert_allclose

from scanner_core.devices import CameraTimeout, TcpPose
from scanner_core.pipeline import (MarkerTracker, PassAccumulator, PipelineParams, camera_frames,
                                   observe_marker, process_frame, run_pass)
from scanner_core.pipeline.trigger import TriggerParams
from scanner_core.types import Frame, MarkerObservation, Profile
from simulator.session import simulated_cell


class FixedRobot:
    """A robot that always reports one pose (or none, when disconnected)."""

    def __init__(self, rotation, connected=True):
        self.rotation = np.asarray(rotation)
        self.connected = connected

    def connect(self):
        self.connected = True

    def disconnect(self):
        self.connected = False

    def latest(self):
        if not self.connected:
            raise RuntimeError("not connected")
        return TcpPose(0.0, np.zeros(3), self.rotation)

    def pose_at(self, t):
        if not self.connected:
            raise RuntimeError("not connected")
        return TcpPose(t, np.zeros(3), self.rotation)


@pytest.fixture(scope="module")
def recorded(block_part, cell):
    """One pass's frames (40 fps, so that it is short) and its robot, whose history covers it."""
    sim = simulated_cell(block_part, cell.with_pass(fps=40.0), seed=9)
    sim.camera.open()
    sim.robot.connect()
    return list(camera_frames(sim.camera)), sim.robot


@pytest.fixture(scope="module")
def full_scan(recorded, cell):
    frames, robot = recorded
    return run_pass(iter(frames), cell.calibration, robot)


def _blank(frame):
    return Frame(np.full_like(frame.image, 10), frame.frame_id, frame.t)


def _frame_span(scan):
    return int(scan.tcp_frame_ids[0]), int(scan.tcp_frame_ids[-1])


def test_pass_spans_the_marker(recorded, full_scan):
    frames, _ = recorded
    first, last = _frame_span(full_scan)
    assert 0 < first and last < frames[-1].frame_id  # lead-in and lead-out left out
    assert full_scan.end_reason == "marker gone" and full_scan.interrupted is None
    assert full_scan.frames_unplaced == 0 and full_scan.frames_held_rotation == 0
    assert np.all(np.diff(full_scan.frame_ids) >= 0)  # sorted by frame


@pytest.mark.parametrize("gap, continues", [(2, True), (3, False)])
def test_trigger_rides_over_short_gaps(recorded, full_scan, cell, gap, continues):
    frames, robot = recorded
    ids = full_scan.tcp_frame_ids
    mid = int(ids[len(ids) // 2])
    holed = [_blank(f) if mid <= f.frame_id < mid + gap else f for f in frames]
    scan = run_pass(iter(holed), cell.calibration, robot)
    if continues:
        assert scan.frames_unplaced == gap  # the blank frames are in the pass, unplaceable
        assert _frame_span(scan) == _frame_span(full_scan)
    else:
        assert _frame_span(scan)[1] < mid and scan.end_reason == "marker gone"


def test_camera_that_stops_keeps_what_was_acquired(recorded, full_scan, cell):
    frames, robot = recorded
    ids = full_scan.tcp_frame_ids
    stop_at = int(ids[len(ids) // 2])

    def stopping():
        for f in frames:
            if f.frame_id == stop_at:
                raise CameraTimeout("no frame for 1.0 s")
            yield f

    partial = run_pass(stopping(), cell.calibration, robot)
    assert partial.end_reason == "camera stopped"
    assert partial.interrupted.startswith("camera timeout")
    assert 0 < partial.frames < full_scan.frames
    kept = full_scan.frame_ids < stop_at
    assert_allclose(partial.cloud, full_scan.cloud[kept])  # nothing acquired is lost


def test_a_marker_that_never_leaves_ends_at_the_maximum_length(recorded, full_scan, cell):
    frames, robot = recorded
    first, _ = _frame_span(full_scan)
    marker_frame = next(f for f in frames if f.frame_id == first + 3)

    def forever():
        for k in range(100000):
            yield Frame(marker_frame.image, k, marker_frame.t + k / 40.0)

    params = PipelineParams(trigger=TriggerParams(max_pass_s=0.5))
    scan = run_pass(forever(), cell.calibration, FixedRobot(cell.gripper_rotation_b), params)
    assert scan.end_reason == "too long"
    assert scan.frames == int(0.5 * 40) + 1


def test_profiles_placed_in_any_order_give_the_same_scan(recorded, full_scan, cell):
    frames, robot = recorded
    cal = cell.calibration
    first, last = _frame_span(full_scan)
    profiles = [process_frame(f, cal) for f in frames if first <= f.frame_id <= last]
    acc = PassAccumulator(cal, robot, partly_lit_ratio=PipelineParams().partly_lit_ratio)
    for k in np.random.default_rng(3).permutation(len(profiles)):
        acc.add(profiles[k])
    shuffled = acc.scan()
    assert_allclose(shuffled.cloud, full_scan.cloud)
    assert_allclose(shuffled.frame_ids, full_scan.frame_ids)
    assert_allclose(shuffled.tcp_times, full_scan.tcp_times)


def test_tracked_marker_equals_the_whole_strip_search(recorded, full_scan, cell):
    frames, _ = recorded
    cal = cell.calibration
    params = PipelineParams()
    tracker = MarkerTracker(cal, params)
    first, last = _frame_span(full_scan)
    for f in frames[first - 2: last + 3]:
        tracked = tracker.observe(f)
        assert_allclose(tracked.pixels, observe_marker(f.image, cal, params).pixels, atol=1e-9)


def test_placement_by_the_marker_and_the_robots_rotation(cell):
    """Two frames of the same {T} point at different gripper positions land on one point."""
    cal = cell.calibration
    r = cell.gripper_rotation_b
    point_t = np.array([5.0, -3.0, 12.0])
    acc = PassAccumulator(cal, FixedRobot(r))
    for i, tcp in enumerate(([1.0, -20.0, 50.0], [1.7, 14.0, 50.4])):
        tcp = np.array(tcp)
        obs = MarkerObservation(np.zeros((3, 2)), tcp + r @ cal.marker_offset_t, 0.0)
        acc.add(Profile(i, 0.01 * i, (tcp + r @ point_t)[None], np.array([0], np.int32),
                        np.array([200.0], np.float32), obs))
    scan = acc.scan()
    assert_allclose(scan.cloud, [point_t, point_t], atol=1e-5)
    assert scan.frames == 2 and scan.frames_dropped == 0


def test_a_robot_that_drops_out_holds_its_last_rotation(cell):
    cal = cell.calibration
    r = cell.gripper_rotation_b
    robot = FixedRobot(r, connected=False)
    acc = PassAccumulator(cal, robot)
    obs = MarkerObservation(np.zeros((3, 2)), np.array([0.0, 0.0, 50.0]), 0.1)
    nan_obs = MarkerObservation(np.full((3, 2), np.nan), np.full(3, np.nan), float("nan"))
    empty = (np.zeros((0, 3)), np.zeros(0, np.int32), np.zeros(0, np.float32))

    def profile(fid, marker):
        return Profile(fid, fid / 100.0, *empty, marker)

    assert not acc.add(profile(10, obs))  # no rotation known yet: cannot be placed
    robot.connect()
    assert acc.add(profile(11, obs))
    robot.disconnect()
    assert acc.add(profile(12, obs))  # the rotation of frame 11 is held
    assert not acc.add(profile(15, nan_obs))
    scan = acc.scan()
    assert (scan.frames, scan.frames_unplaced, scan.frames_held_rotation) == (2, 2, 1)
    assert scan.frames_without_rotation == 1  # frame 10; frame 15 had no marker
    assert scan.frames_dropped == 2  # ids 13 and 14


def test_warm_up_frame_finds_the_marker_everywhere(cell, monkeypatch):
    """The warm-up frame must reach every kernel: a marker in all three views and a stripe."""
    from scanner_core.pipeline import frame as pipeline_frame
    seen = {}
    real = pipeline_frame.process_frame

    def spy(frame, calibration, params=pipeline_frame.PipelineParams(), marker=None):
        seen["profile"] = real(frame, calibration, params, marker)
        return seen["profile"]

    monkeypatch.setattr(pipeline_frame, "process_frame", spy)
    pipeline_frame.warm_up(cell.calibration)
    profile = seen["profile"]
    assert profile.marker.views == 3
    assert len(profile.columns) > 500


def _compiled_signatures() -> dict:
    """Every numba kernel of scanner_core loaded so far: its compiled signatures."""
    import sys

    from numba.core.registry import CPUDispatcher

    found = {}
    for name, module in list(sys.modules.items()):
        if name.startswith("scanner_core"):
            for attr, value in vars(module).items():
                if isinstance(value, CPUDispatcher):
                    found[f"{name}.{attr}"] = len(value.signatures)
    return found


def test_a_read_only_frame_after_the_warm_up_compiles_nothing(recorded, cell):
    """A camera's or a recording's read-only buffer reaches the kernels as a writable copy:
    after the warm-up (which compiles writable frames only) a pass of read-only frames
    compiles no kernel anew, which would hold the GIL for seconds mid-pass."""
    from scanner_core.pipeline import frame as pipeline_frame

    pipeline_frame.warm_up(cell.calibration)
    before = _compiled_signatures()
    assert sum(before.values()) >= 8
    frames, _ = recorded
    tracker, profiles = MarkerTracker(cell.calibration, PipelineParams()), []
    for frame in frames:
        image = frame.image.copy()
        image.setflags(write=False)
        read_only = Frame(image, frame.frame_id, frame.t)
        marker = tracker.observe(read_only)
        profiles.append(pipeline_frame.process_frame(read_only, cell.calibration, marker=marker))
    assert sum(len(p.columns) > 0 for p in profiles) > 5  # the part was seen
    assert _compiled_signatures() == before


def test_the_previous_profile_guides_the_next_frames_stripe(cell):
    """A glint brighter than the stripe over 60 columns (longer than continuity bridges): the
    frame alone takes it there; with the previous profile's rows (what the accumulator hands
    the next frames, for at most PREVIOUS_PROFILE_FRAMES of them) the stripe is kept."""
    from scanner_core.pipeline import PREVIOUS_PROFILE_FRAMES, frame_stripe
    from simulator.imaging import ImageModel, render_image

    cal = cell.calibration
    w, h = cal.camera.width, cal.camera.height
    c0, c1 = cal.direct_columns
    cols = np.arange(c0 + 100, c0 + 500)
    rows = 600.0 + 20.0 * np.sin(cols / 80.0)
    glint = (cols >= c0 + 250) & (cols < c0 + 310)
    image = render_image(h, w, ImageModel(), np.random.default_rng(5),
                         stripe_cols=np.concatenate([cols, cols[glint]]),
                         stripe_rows=np.concatenate([rows, rows[glint] + 25.0]),
                         stripe_gain=np.concatenate([np.ones(len(cols)),
                                                     np.full(glint.sum(), 1.2)]))
    no_marker = MarkerObservation(np.full((3, 2), np.nan), np.full(3, np.nan), float("nan"))
    acc = PassAccumulator(cal, FixedRobot(cell.gripper_rotation_b))
    obs = MarkerObservation(np.zeros((3, 2)), np.array([0.0, 0.0, 50.0]), 0.1)
    acc.add(Profile(10, 0.1, np.zeros((len(cols), 3)), cols.astype(np.int32),
                    np.full(len(cols), 200.0, np.float32), obs, rows=rows.astype(np.float32)))
    assert acc.expected_rows(10) is None  # not for its own frame
    assert acc.expected_rows(10 + PREVIOUS_PROFILE_FRAMES + 1) is None  # too old
    expected = acc.expected_rows(11)
    assert_allclose(expected[cols], rows, atol=1e-4)
    assert np.isnan(expected[:c0]).all()
    g = cols[glint]
    alone, valid_alone, _ = frame_stripe(image, cal, PipelineParams(), no_marker)
    guided, valid, _ = frame_stripe(image, cal, PipelineParams(), no_marker, expected_row=expected)
    on_alone = valid_alone[g] & (np.abs(alone.row[g] - rows[glint]) < 1.0)
    on_guided = valid[g] & (np.abs(guided.row[g] - rows[glint]) < 1.0)
    assert on_alone.mean() < 0.5
    assert on_guided.mean() >= 0.98
