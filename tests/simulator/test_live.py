"""The live simulated cell: replayed passes, real-time pacing, the robot, faults."""
import threading
import time

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from scanner_core.devices import Camera, CameraClosed, CameraTimeout, Robot
from scanner_core.marker.finder import find_markers
from scanner_core.stripe.extractor import extract
from simulator.live import LiveSimCell, PassInProgress, frame_image
from simulator.motion import PassMotion
from simulator.parts import block_with_holes_and_steps, part_from_mesh
from simulator.render import PartScene
from scanner_core.pipeline import camera_frames
from simulator.session import parse_misplacement, simulated_cell

#: Robot clock minus camera clock in the replay, s: any value, to check it is applied.
CLOCK_OFFSET_S = 12.5
#: Same pass-relative time, same float arithmetic: only rounding of the time, far below 1 nm.
EXACT_MM = 1e-6
#: Linear interpolation between 500 Hz samples: a * dt**2 / 8 with a <= 2000 mm/s**2 at
#: 1 m/s (the speed ramp) and dt = 2 ms gives 1e-3 mm.
INTERP_TOL_MM = 2e-3
#: Two independent noise draws of N(0, 3 DN): E|a - b| = 2 * 3 / sqrt(pi) = 3.4 DN per pixel.
NOISE_MEAN_ABS_DIFF_DN = (3.0, 3.8)
#: The frames' means differ only by noise and speckle over about 2 M pixels.
MEAN_LEVEL_TOL_DN = 0.05
#: Stripe columns found in both renderings of a frame: noise flips the validity of a few
#: weak or grazing columns at the steps and ends (97-100 % measured on the demo part).
SAME_COLUMNS_FRACTION = 0.93
#: Median difference of the stripe rows between two noise draws, px (CoG noise ~0.03 px).
SAME_ROWS_PX = 0.1
#: A grab returns within this of its frame's exposure (sleep granularity and a loaded CI).
GRAB_LATENCY_S = 0.004


@pytest.fixture(scope="module")
def demo_part():
    return part_from_mesh(block_with_holes_and_steps(), name="demo")


@pytest.fixture(scope="module")
def fast_cell(cell):
    """The paper's fast configuration (1 m/s, 162 fps) with short leads: a 0.46 s pass."""
    return cell.with_pass(speed_mm_s=1000.0, fps=162.0, lead_in_s=0.1, lead_out_s=0.1)


@pytest.fixture(scope="module")
def misplacement():
    return parse_misplacement("1.5,-2,0.5,0,0,3")


@pytest.fixture(scope="module")
def replay(fast_cell, demo_part, misplacement):
    """One live pass, read by an acquisition thread while this thread starts it."""
    sim = LiveSimCell(fast_cell, seed=11, clock_offset_s=CLOCK_OFFSET_S, buffer_frames=10_000,
                      robot_history_s=120.0)
    prepared = sim.prepare_pass(demo_part, misplacement)
    sim.camera.open()
    sim.robot.connect()
    frames, errors = [], []
    stop = threading.Event()

    def acquire():
        try:
            while not stop.is_set():
                frames.append(sim.camera.grab(1.0))
        except CameraClosed:
            pass
        except Exception as e:  # handed to the test below
            errors.append(e)

    thread = threading.Thread(target=acquire)
    thread.start()
    time.sleep(0.05)
    idle_tcp = sim.robot.latest().position
    live = sim.start_pass(demo_part, misplacement)
    state = {"active_at_start": sim.pass_active, "done_at_start": sim.pass_done,
             "idle_tcp": idle_tcp}
    with pytest.raises(PassInProgress):
        sim.start_pass(demo_part, misplacement)
    deadline = time.monotonic() + 10.0
    while ((not frames or frames[-1].frame_id < live.last_frame_id + 3)
           and time.monotonic() < deadline):
        time.sleep(0.02)
    stop.set()
    thread.join()
    assert not errors, errors
    state["done_at_end"] = sim.pass_done
    yield sim, prepared, live, frames, state
    sim.camera.close()
    sim.robot.disconnect()


@pytest.fixture(scope="module")
def offline(fast_cell, demo_part, misplacement):
    """The same pass rendered offline, frame by frame."""
    off = simulated_cell(demo_part, fast_cell, misplacement=misplacement, seed=11)
    off.camera.open()
    frames = list(camera_frames(off.camera))
    return off, frames


def test_devices_implement_the_protocols_and_construct_lazily(fast_cell):
    sim = LiveSimCell(fast_cell)
    assert isinstance(sim.camera, Camera)
    assert isinstance(sim.robot, Robot)
    assert (sim.camera.width, sim.camera.height, sim.camera.fps) == (1920, 1200, 162.0)
    with pytest.raises(RuntimeError, match="clock"):
        sim.now()
    with pytest.raises(CameraClosed):
        sim.camera.grab(0.01)
    with pytest.raises(RuntimeError, match="not connected"):
        sim.robot.latest()
    assert not sim.pass_active and not sim.pass_done and sim.last_pass is None
    assert sim.last_pass_truths == {} and sim.last_true_grasp is None


def test_geometry_then_image_model_equals_render(cell, demo_part):
    """The split used by the live camera gives PartScene.render's image bit for bit."""
    scene = PartScene(demo_part, cell)
    grasp = parse_misplacement("0,0,0,2,-3,5") @ demo_part.grasp
    for tcp in ([0.0, -8.0, 50.0], [1.0, 3.0, 51.0], [0.0, 300.0, 50.0]):
        image, truth = scene.render(tcp, grasp, np.random.default_rng(5))
        geometry = scene.geometry(tcp, grasp)
        assert_array_equal(frame_image(cell, geometry, np.random.default_rng(5)), image)
        for name in ("tcp_b", "part_pose_b", "stripe_columns", "stripe_rows", "stripe_points_b",
                     "stripe_gain", "marker_b", "marker_pixels"):
            assert_array_equal(getattr(geometry, name), getattr(truth, name), err_msg=name)
    assert len(truth.stripe_columns) == 0  # the last pose is past the sheet


def test_replayed_pass_matches_offline_frames(replay, offline, fast_cell):
    sim, prepared, live, frames, state = replay
    off, off_frames = offline
    by_id = {f.frame_id: f for f in frames}
    assert_array_equal(sorted(by_id), np.arange(frames[0].frame_id, frames[-1].frame_id + 1))
    assert live.frame_count == off.camera.frame_count == len(off_frames) == prepared.frame_count
    truths = sim.last_pass_truths
    assert sorted(truths) == list(range(live.first_frame_id, live.last_frame_id + 1))
    strips = fast_cell.calibration.direct_columns
    lit_frames = 0
    for j, off_frame in enumerate(off_frames):
        frame = by_id[live.first_frame_id + j]
        truth, off_truth = truths[frame.frame_id], off.camera.truths[j]
        for name in ("tcp_b", "stripe_columns", "stripe_rows", "stripe_gain", "marker_pixels"):
            assert_array_equal(getattr(truth, name), getattr(off_truth, name), err_msg=name)
        # Fresh noise: the same scene, not the same pixels.
        a, b = frame.image.astype(np.int16), off_frame.image.astype(np.int16)
        mad = np.abs(a - b).mean()
        assert NOISE_MEAN_ABS_DIFF_DN[0] < mad < NOISE_MEAN_ABS_DIFF_DN[1]
        assert abs(a.mean() - b.mean()) < MEAN_LEVEL_TOL_DN
        if len(truth.stripe_columns) < 50:
            continue
        lit_frames += 1
        live_s = extract(frame.image, columns=strips)
        off_s = extract(off_frame.image, columns=strips)
        both = live_s.valid & off_s.valid
        assert both.sum() >= SAME_COLUMNS_FRACTION * max(live_s.valid.sum(), off_s.valid.sum())
        assert np.median(np.abs(live_s.row[both] - off_s.row[both])) < SAME_ROWS_PX
    assert lit_frames >= 4  # the 40 mm block crosses the sheet in 40 ms at 1 m/s
    assert_allclose(sim.last_true_grasp, prepared.misplacement @ prepared.part.grasp, atol=0)


def test_replay_state_and_idle_frames(replay, fast_cell):
    sim, _, live, frames, state = replay
    assert state["active_at_start"] and not state["done_at_start"] and state["done_at_end"]
    assert not sim.pass_active and sim.camera.frames_lost == 0
    idle = [f for f in frames
            if f.frame_id < live.first_frame_id or f.frame_id > live.last_frame_id]
    assert len(idle) >= 4
    for f in idle[:2] + idle[-2:]:
        assert not f.image.flags.writeable
        marker = find_markers(f.image, strips=fast_cell.calibration.strips)
        assert np.all(np.isnan(marker))
    assert np.any(idle[0].image != idle[1].image)  # the ring cycles
    # Inside the pass, frames showing nothing but background come from the ring too.
    prepared = live.prepared
    assert 0 < prepared.blank.sum() < live.frame_count
    for f in frames:
        if live.first_frame_id <= f.frame_id <= live.last_frame_id:
            assert f.image.flags.writeable != prepared.blank[f.frame_id - live.first_frame_id]


def test_robot_follows_the_pass(replay):
    sim, prepared, live, frames, state = replay
    robot = sim.robot
    rate = robot.rate_hz
    motion = PassMotion(prepared.profile)
    # Before the pass the robot waits where the pass begins.
    assert_allclose(state["idle_tcp"], motion.tcp_position(-prepared.profile.lead_in_s),
                    atol=EXACT_MM)
    assert abs(robot.latest().t - (sim.now() + CLOCK_OFFSET_S)) < 2.0 / rate
    frame_t = np.array([live.first_frame_id + j for j in range(live.frame_count)]) / live.fps
    t_zero = live.t_first + prepared.profile.lead_in_s  # camera clock of the pass's t = 0

    def pass_t(t_robot):
        return (t_robot - CLOCK_OFFSET_S) - t_zero

    for t_cam in frame_t[::4]:
        t_robot = t_cam + CLOCK_OFFSET_S
        sample = np.floor(t_robot * rate) / rate  # a sample the robot reported
        if sample - CLOCK_OFFSET_S >= live.t_first:
            assert_allclose(robot.pose_at(sample).position, motion.tcp_position(pass_t(sample)),
                            atol=EXACT_MM)
        pose = robot.pose_at(t_robot)
        assert pose.t == t_robot
        assert_allclose(pose.position, motion.tcp_position(pass_t(t_robot)), atol=INTERP_TOL_MM)
    assert_allclose(pose.rotation, sim.cell.gripper_rotation_b)
    # After the pass it stands where the pass ended.
    end = motion.tcp_position(prepared.time_of(live.frame_count - 1))
    assert_allclose(robot.latest().position, end, atol=EXACT_MM)
    with pytest.raises(LookupError):
        robot.pose_at(robot.latest().t + 0.05)  # the future
    with pytest.raises(LookupError):
        robot.pose_at(CLOCK_OFFSET_S - 0.01)  # before its clock started


def test_robot_history_is_bounded(fast_cell):
    sim = LiveSimCell(fast_cell, robot_history_s=0.1, clock_offset_s=-3.0)
    sim.robot.connect()
    time.sleep(0.15)
    newest = sim.robot.latest().t
    sim.robot.pose_at(newest - 0.05)
    with pytest.raises(LookupError):
        sim.robot.pose_at(newest - 0.12)
    sim.robot.disconnect()
    with pytest.raises(RuntimeError, match="not connected"):
        sim.robot.pose_at(newest)


def test_camera_paces_frames_and_loses_them_when_read_late(fast_cell):
    sim = LiveSimCell(fast_cell, seed=2)
    cam = sim.camera
    cam.open()
    period = 1.0 / cam.fps
    frames, latency = [], []
    for _ in range(30):
        frames.append(cam.grab(1.0))
        latency.append(sim.now() - frames[-1].t)
    ids = np.array([f.frame_id for f in frames])
    assert_array_equal(ids, np.arange(30))
    assert_allclose(np.diff([f.t for f in frames]), period, rtol=1e-9)
    assert min(latency) >= 0.0 and np.median(latency) < GRAB_LATENCY_S
    assert cam.frames_lost == 0
    # A reader late by more than `buffer_frames` periods finds only the newest of them.
    late_by = cam.buffer_frames + 12
    time.sleep(late_by * period)
    late = cam.grab(1.0)
    gap = late.frame_id - ids[-1] - 1
    assert gap >= late_by - cam.buffer_frames - 1 and cam.frames_lost == gap
    assert sim.now() - late.t >= (cam.buffer_frames - 1) * period  # the oldest kept
    following = [cam.grab(1.0).frame_id for _ in range(cam.buffer_frames)]
    assert_array_equal(following, late.frame_id + 1 + np.arange(cam.buffer_frames))
    assert cam.frames_lost == gap and cam.frames_delivered == 31 + cam.buffer_frames
    cam.close()
    with pytest.raises(CameraClosed):
        cam.grab(0.1)


def test_stall_times_out_and_resume_skips_frames(fast_cell):
    sim = LiveSimCell(fast_cell, seed=3)
    cam = sim.camera
    cam.open()
    before = cam.grab(1.0)
    cam.stall()
    t0 = time.monotonic()
    with pytest.raises(CameraTimeout):
        cam.grab(0.05)
    assert time.monotonic() - t0 >= 0.05
    cam.resume()
    after = cam.grab(1.0)
    assert after.frame_id > before.frame_id + 1
    assert cam.frames_lost == after.frame_id - before.frame_id - 1
    # Closing wakes a reader waiting on a stalled camera.
    cam.stall()
    errors = []

    def wait():
        try:
            cam.grab(5.0)
        except CameraClosed as e:
            errors.append(e)

    thread = threading.Thread(target=wait)
    thread.start()
    time.sleep(0.05)
    cam.close()
    thread.join(1.0)
    assert not thread.is_alive() and len(errors) == 1


def test_passes_are_prepared_once_and_checked(fast_cell, demo_part, misplacement):
    sim = LiveSimCell(fast_cell, cache_size=1)
    with pytest.raises(CameraClosed):
        sim.start_pass(demo_part)  # prepares, then refuses: the camera is closed
    first = sim.prepare_pass(demo_part)
    assert sim.prepare_pass(demo_part, np.eye(4)) is first
    other = sim.prepare_pass(demo_part, misplacement)
    assert other is not first and sim.prepare_pass(demo_part, misplacement) is other
    assert sim.prepare_pass(demo_part) is not first  # evicted: the cache holds one pass
    with pytest.raises(ValueError, match="fps"):
        sim.prepare_pass(demo_part, profile=fast_cell.with_pass(fps=16.0).pass_profile)
    with pytest.raises(ValueError, match="misplacement"):
        sim.prepare_pass(demo_part, np.eye(3))


def test_a_gain_amplifies_the_live_cameras_background_noise(fast_cell):
    """Frames under another gain keep the black level and scale the read noise, from the
    same ring of draws; another exposure alone leaves the background as it was."""
    sim = LiveSimCell(fast_cell, seed=3)
    camera = sim.camera
    camera.open()
    try:
        nominal = camera.grab().image.astype(float)
        camera.set_exposure(camera.exposure_us * 2.0, 1.0)
        longer = camera.grab().image.astype(float)
        camera.set_exposure(camera.exposure_us / 2.0, 2.0)
        gained = camera.grab().image.astype(float)
    finally:
        camera.close()
    noise = fast_cell.image_model.read_noise_dn
    assert np.std(nominal) == pytest.approx(np.sqrt(noise**2 + 1 / 12), rel=0.05)
    assert np.std(longer) == pytest.approx(np.std(nominal), rel=0.02)
    assert np.std(gained) == pytest.approx(2.0 * noise, rel=0.05)
    assert np.median(gained) == pytest.approx(np.median(nominal), abs=0.5)
