"""Recording a pass and replaying it: the replay gives the live pass's cloud point for point."""
import json
import shutil
import time
from dataclasses import replace

import numpy as np
import pytest

from scanner_core.devices import (Camera, CameraClosed, CameraTimeout, Robot, RobotConnection,
                                   TcpPose)
from scanner_core.pipeline.finish import CrossCheckState, check_against_robot
from scanner_core.pipeline import camera_frames, run_pass, warm_up
from scanner_core.types import Frame
from scanner_core.recording import FORMAT_VERSION, PassRecorder, RecordingError, load_recording
from scanner_core.recording.replay import REPORTS_UNTIL_SETTING, ReplayCamera, ReplayRobot
from simulator.devices import ROBOT_RATE_HZ
from simulator.session import simulated_cell


def fast_cell(cell):
    """The paper's fast pass (1 m/s, 162 fps) with short leads: 75 frames."""
    return cell.with_pass(speed_mm_s=1000.0, fps=162.0, lead_in_s=0.1, lead_out_s=0.1)


def robot_samples(sim):
    """The simulated robot's 500 Hz samples from the start of the pass to its clock's now."""
    k0 = int(np.ceil(-sim.cell.pass_profile.lead_in_s * ROBOT_RATE_HZ))
    k1 = int(np.floor(sim.robot.clock.now * ROBOT_RATE_HZ))
    return [sim.robot.pose_at(k / ROBOT_RATE_HZ) for k in range(k0, k1 + 1)]


@pytest.fixture(scope="module")
def recorded(cell, block_part, tmp_path_factory):
    """A live simulated pass, recorded as it runs: every frame the camera gives (the frames
    after the pass's end too) and the robot's samples over the pass."""
    fast = fast_cell(cell)
    sim = simulated_cell(block_part, fast)
    warm_up(fast.calibration)
    folder = tmp_path_factory.mktemp("recording") / "pass"
    sim.camera.open()
    sim.robot.connect()
    with PassRecorder(folder, width=sim.camera.width, height=sim.camera.height, fps=sim.camera.fps,
                      calibration=fast.calibration, settings={"speed_mm_s": 1000.0},
                      notes="test pass") as recorder:
        def frames():
            for frame in camera_frames(sim.camera):
                recorder.add_frame(frame)
                yield frame
        stream = frames()
        live = run_pass(stream, fast.calibration, sim.robot)
        for _ in stream:  # the rest of the stream, as a recorder on the camera would see it
            pass
        recorder.add_robot_poses(robot_samples(sim))
    sim.camera.close()
    return {"folder": folder, "live": live, "sim": sim, "cell": fast}


def test_replay_gives_the_live_cloud(recorded):
    recording = load_recording(recorded["folder"])
    live, sim = recorded["live"], recorded["sim"]
    assert recording.frame_count == sim.camera.frame_count
    assert recording.version == FORMAT_VERSION
    assert recording.settings == {"speed_mm_s": 1000.0} and recording.notes == "test pass"
    assert recording.calibration.to_dict() == recorded["cell"].calibration.to_dict()
    camera, robot = ReplayCamera(recording), ReplayRobot(recording.robot_samples)
    assert isinstance(camera, Camera) and isinstance(robot, Robot)
    camera.open()
    robot.connect()
    replay = run_pass(camera_frames(camera), recording.calibration, robot)
    assert live.frames > 20 and len(live.cloud) > 1000
    assert np.array_equal(replay.cloud, live.cloud)
    assert np.array_equal(replay.frame_ids, live.frame_ids)
    assert np.array_equal(replay.tcp_frame_ids, live.tcp_frame_ids)
    assert np.array_equal(replay.edges, live.edges)
    assert replay.end_reason == live.end_reason


def test_replay_camera_gives_the_recorded_frames_then_closes(recorded):
    recording = load_recording(recorded["folder"])
    camera = ReplayCamera(recording)
    with pytest.raises(CameraClosed):
        camera.grab(1.0)  # not open
    camera.open()
    frames = list(camera_frames(camera))
    assert [f.frame_id for f in frames] == list(range(recording.frame_count))
    assert [f.t for f in frames] == [recorded["sim"].camera.time_of(i) for i in range(len(frames))]
    assert frames[0].image.shape == (camera.height, camera.width)
    assert frames[0].image.dtype == np.uint8 and not frames[0].image.flags.writeable
    with pytest.raises(CameraClosed):
        camera.grab(1.0)


def test_replay_robot_matches_the_simulated_robot(recorded):
    recording = load_recording(recorded["folder"])
    sim, robot = recorded["sim"], ReplayRobot(recording.robot_samples)
    with pytest.raises(RuntimeError):
        robot.latest()  # not connected
    robot.connect()
    assert robot.connected
    times = recording.robot_samples[:, 0]
    assert np.allclose(np.diff(times), 1 / ROBOT_RATE_HZ)
    for t in np.linspace(times[0], times[-1], 37):
        ours, theirs = robot.pose_at(t), sim.robot.pose_at(t)
        np.testing.assert_allclose(ours.position, theirs.position, rtol=0, atol=1e-9)
        assert np.array_equal(ours.rotation, theirs.rotation)
    assert robot.latest().t == times[-1]
    with pytest.raises(LookupError):
        robot.pose_at(times[-1] + 1e-3)
    with pytest.raises(LookupError):
        robot.pose_at(times[0] - 1e-3)
    robot.disconnect()
    assert not robot.connected


class _LateRobot(RobotConnection):
    """A live robot whose reports for the pass's last frames have not arrived yet: its
    history ends at ``until``."""

    def __init__(self, recorded: ReplayRobot, until: float):
        self._recorded, self._until = recorded, until

    def latest(self) -> TcpPose:
        return self._recorded.pose_at(self._until)

    def pose_at(self, t: float) -> TcpPose:
        if t > self._until:
            raise LookupError("not reported yet")
        return self._recorded.pose_at(t)


def test_a_replay_checks_the_samples_its_live_check_had(recorded):
    """A live cross-check that ran before the robot's reports for the pass's last frames
    arrived checked fewer frames; the replay, its robot ending its reports where the live
    check's did, checks the same ones, not all the recording holds."""
    recording, live = load_recording(recorded["folder"]), recorded["live"]
    full = ReplayRobot(recording.robot_samples)
    full.connect()
    state = CrossCheckState()
    # a report's time (the camera's and the robot's clocks agree here), some frames before
    # the pass's last
    times = recording.robot_samples[:, 0]
    until = float(times[np.searchsorted(times, live.tcp_times[-6]) - 1])
    late = _LateRobot(full, until)
    late.connect()
    live_check, _ = check_against_robot(live, late, state)
    assert live_check["reports_until_s"] == pytest.approx(until, abs=1e-12)
    everything, _ = check_against_robot(live, full, state)
    assert everything["reports_until_s"] == recording.robot_samples[-1, 0]
    assert 0 < live_check["samples"] < everything["samples"]
    replay_robot = ReplayRobot.of(replace(recording, settings={
        REPORTS_UNTIL_SETTING: live_check["reports_until_s"]}))
    replay_robot.connect()
    assert replay_robot.latest().t == until
    replayed, _ = check_against_robot(live, replay_robot, state)
    for key in ("samples", "rms_mm", "max_mm", "clock_offset_s", "mean_difference_t_mm"):
        assert replayed[key] == live_check[key], key
    with pytest.raises(ValueError, match="finite"):
        ReplayRobot(recording.robot_samples, float("nan"))
    # a live check that had no report at all: the replay's has none either
    none_yet = ReplayRobot.of(replace(recording, settings={REPORTS_UNTIL_SETTING: None}))
    none_yet.connect()
    with pytest.raises(RuntimeError, match="no robot report"):
        none_yet.latest()
    assert check_against_robot(live, none_yet, state)[0]["samples"] == 0


def test_replay_robot_slerps_a_turning_gripper():
    half_turn = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # 90 deg about z
    samples = np.zeros((2, 13))
    samples[:, 0] = [0.0, 1.0]
    samples[1, 1:4] = [10.0, 0, 0]
    samples[0, 4:] = np.eye(3).ravel()
    samples[1, 4:] = half_turn.ravel()
    robot = ReplayRobot(samples)
    robot.connect()
    pose = robot.pose_at(0.5)
    np.testing.assert_allclose(pose.position, [5.0, 0, 0])
    c = np.cos(np.pi / 4)
    np.testing.assert_allclose(pose.rotation, [[c, -c, 0], [c, c, 0], [0, 0, 1]], atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Small synthetic recordings for the format's edges


def tiny_recording(folder, calibration, times=(0.0, 0.05, 0.1), **kw):
    """Frames of 4x6 pixels, ids 0.. with a dropped frame after the first."""
    with PassRecorder(folder, width=6, height=4, fps=20.0, calibration=calibration, **kw) as rec:
        for i, t in enumerate(times):
            rec.add_frame(Frame(np.full((4, 6), i, np.uint8), i + (i > 0), t))
        rec.add_robot_poses([TcpPose(t, np.array([0.0, t, 0.0]), np.eye(3)) for t in (0.0, 0.1, 0.1)])
    return folder


def test_tiny_recording_round_trips(cell, tmp_path):
    recording = load_recording(tiny_recording(tmp_path / "r", cell.calibration))
    assert recording.frame_ids.tolist() == [0, 2, 3]
    assert recording.times.tolist() == [0.0, 0.05, 0.1]
    assert len(recording.robot_samples) == 2  # the repeated sample was skipped
    assert (tmp_path / "r" / "frames.u8").stat().st_size == 3 * 4 * 6
    meta = json.loads((tmp_path / "r" / "recording.json").read_text())
    assert meta["version"] == FORMAT_VERSION and meta["frames"] == 3
    assert meta["camera"] == {"width": 6, "height": 4, "fps": 20.0}
    assert meta["created_utc"].endswith("Z")
    camera = ReplayCamera(recording)
    camera.open()
    assert [camera.grab(1.0).image[0, 0] for _ in range(3)] == [0, 1, 2]


def test_exposures_round_trip_and_old_indexes_still_read(cell, tmp_path):
    """Each frame's exposure and gain are recorded (multiple exposure replays as it ran); an
    index written before exposure control (`frame_id,t`) reads as unknown exposure."""
    folder = tmp_path / "r"
    with PassRecorder(folder, width=6, height=4, fps=20.0, calibration=cell.calibration) as rec:
        for i, (exposure, gain) in enumerate([(1000.0, 1.0), (125.0, 2.5), (float("nan"), 1.0)]):
            rec.add_frame(Frame(np.full((4, 6), i, np.uint8), i, 0.05 * i, exposure, gain))
    camera = ReplayCamera(load_recording(folder))
    camera.open()
    taken = [(f.exposure_us, f.gain) for f in (camera.grab(1.0) for _ in range(3))]
    assert taken[:2] == [(1000.0, 1.0), (125.0, 2.5)]
    assert np.isnan(taken[2][0]) and taken[2][1] == 1.0
    (folder / "frames.csv").write_text("frame_id,t\n0,0.0\n1,0.05\n2,0.1\n")
    old = load_recording(folder)
    assert np.isnan(old.exposures[:, 0]).all() and (old.exposures[:, 1] == 1.0).all()


def test_realtime_replay_paces_frames_by_their_times(cell, tmp_path):
    recording = load_recording(tiny_recording(tmp_path / "r", cell.calibration))
    camera = ReplayCamera(recording, realtime=True)
    camera.open()
    t0 = time.monotonic()
    frames = list(camera_frames(camera))
    assert len(frames) == 3
    assert time.monotonic() - t0 >= 0.1 - 1e-3


def test_realtime_replay_times_out_on_a_recorded_gap(cell, tmp_path):
    recording = load_recording(tiny_recording(tmp_path / "r", cell.calibration, times=(0.0, 5.0)))
    camera = ReplayCamera(recording, realtime=True)
    camera.open()
    camera.grab(0.05)
    with pytest.raises(CameraTimeout):
        camera.grab(0.05)


def test_empty_recording_closes_at_once(cell, tmp_path):
    with PassRecorder(tmp_path / "r", width=6, height=4, fps=20.0, calibration=cell.calibration):
        pass
    camera = ReplayCamera(load_recording(tmp_path / "r"))
    camera.open()
    with pytest.raises(CameraClosed):
        camera.grab(1.0)
    robot = ReplayRobot(load_recording(tmp_path / "r").robot_samples)
    robot.connect()
    with pytest.raises(RuntimeError):
        robot.latest()


def test_overwriting_is_refused(cell, tmp_path):
    folder = tiny_recording(tmp_path / "r", cell.calibration)
    before = sorted(p.name for p in folder.iterdir())
    with pytest.raises(RecordingError, match="refusing to overwrite"):
        PassRecorder(folder, width=6, height=4, fps=20.0, calibration=cell.calibration)
    # A folder that appears while recording: finish refuses it and leaves nothing behind.
    recorder = PassRecorder(tmp_path / "late", width=6, height=4, fps=20.0,
                            calibration=cell.calibration)
    recorder.add_frame(Frame(np.zeros((4, 6), np.uint8), 0, 0.0))
    (tmp_path / "late").mkdir()
    (tmp_path / "late" / "mine.txt").write_text("someone else's")
    with pytest.raises(RecordingError, match="refusing to overwrite"):
        recorder.finish()
    assert sorted(p.name for p in (tmp_path / "late").iterdir()) == ["mine.txt"]
    assert sorted(p.name for p in folder.iterdir()) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["late", "r"]


def test_abort_leaves_nothing(cell, tmp_path):
    with pytest.raises(KeyError):
        with PassRecorder(tmp_path / "a", width=6, height=4, fps=20.0,
                          calibration=cell.calibration) as recorder:
            recorder.add_frame(Frame(np.zeros((4, 6), np.uint8), 0, 0.0))
            assert any(p.name.endswith(".partial") for p in tmp_path.iterdir())
            raise KeyError("the pass failed")
    recorder = PassRecorder(tmp_path / "b", width=6, height=4, fps=20.0, calibration=cell.calibration)
    recorder.add_frame(Frame(np.zeros((4, 6), np.uint8), 0, 0.0))
    recorder.abort()
    recorder.abort()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(RuntimeError, match="aborted"):
        recorder.add_frame(Frame(np.zeros((4, 6), np.uint8), 1, 0.1))


def test_recorder_refuses_a_frame_of_another_size(cell, tmp_path):
    with PassRecorder(tmp_path / "r", width=6, height=4, fps=20.0, calibration=cell.calibration) as rec:
        with pytest.raises(ValueError, match=r"\(4, 6\) uint8"):
            rec.add_frame(Frame(np.zeros((4, 7), np.uint8), 0, 0.0))
        with pytest.raises(ValueError, match=r"\(4, 6\) uint8"):
            rec.add_frame(Frame(np.zeros((4, 6), np.uint16), 0, 0.0))
    assert load_recording(tmp_path / "r").frame_count == 0


def _edit_json(folder, edit):
    path = folder / "recording.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


@pytest.mark.parametrize("damage, message", [
    (lambda f: shutil.rmtree(f), "no such folder"),
    (lambda f: (f / "recording.json").unlink(), "missing recording.json"),
    (lambda f: (f / "frames.u8").unlink(), "missing frames.u8"),
    (lambda f: (f / "frames.csv").unlink(), "missing frames.csv"),
    (lambda f: (f / "robot.npy").unlink(), "missing robot.npy"),
    (lambda f: (f / "recording.json").write_text('{"format": "flyscan-rec'), "not valid JSON"),
    (lambda f: _edit_json(f, lambda m: m.update(version=2)),
     "format version 2; this flyscan reads version 1"),
    (lambda f: _edit_json(f, lambda m: m.update(format="other")), "field `format`"),
    (lambda f: _edit_json(f, lambda m: m["camera"].update(width="6")), "field `camera.width`"),
    (lambda f: _edit_json(f, lambda m: m["camera"].pop("fps")), "no field `camera.fps`"),
    (lambda f: _edit_json(f, lambda m: m.update(frames=4)), "expected N\\*H\\*W = 4\\*4\\*6 = 96"),
    (lambda f: _edit_json(f, lambda m: m.update(settings=[])), "field `settings`"),
    (lambda f: _edit_json(f, lambda m: m["calibration"].pop("mirrors")), "field `calibration`.*mirrors"),
    (lambda f: (f / "frames.u8").write_bytes(b"\0" * 71), "frames.u8 holds 71 bytes"),
    (lambda f: (f / "frames.csv").write_text("frame_id,t\n0,0.0\n2,x\n3,0.1\n"), "line 3"),
    (lambda f: (f / "frames.csv").write_text("frame_id,t\n0,0.0\n"), "lists 1 frames"),
    (lambda f: (f / "robot.npy").write_bytes(b"garbage"), "robot.npy is not a valid .npy"),
    (lambda f: np.save(f / "robot.npy", np.zeros((2, 12))), r"float64 \(M, 13\)"),
    (lambda f: np.save(f / "robot.npy", np.zeros((2, 13))), "increase strictly"),
])
def test_damaged_recordings_are_refused_clearly(cell, tmp_path, damage, message):
    folder = tiny_recording(tmp_path / "r", cell.calibration)
    damage(folder)
    with pytest.raises(RecordingError, match=message):
        load_recording(folder)


def test_a_partial_recording_is_not_a_recording(cell, tmp_path):
    recorder = PassRecorder(tmp_path / "r", width=6, height=4, fps=20.0, calibration=cell.calibration)
    recorder.add_frame(Frame(np.zeros((4, 6), np.uint8), 0, 0.0))
    partial = next(tmp_path.iterdir())
    with pytest.raises(RecordingError, match="no such folder"):
        load_recording(tmp_path / "r")
    with pytest.raises(RecordingError, match="missing recording.json"):
        load_recording(partial)
    recorder.abort()
