import numpy as np
import pytest
from numpy.testing import assert_allclose

from scanner_core.devices import Camera, CameraClosed, Robot
from scanner_core.pipeline import camera_frames
from simulator.session import simulated_cell

#: Linear interpolation between 500 Hz samples of a smooth 200 mm/s path.
INTERP_TOL_MM = 1e-3


@pytest.fixture
def sim(block_part, cell):
    return simulated_cell(block_part, cell.with_pass(fps=40.0), seed=3, drop_rate=0.2)


def test_devices_implement_the_protocols(sim):
    assert isinstance(sim.camera, Camera)
    assert isinstance(sim.robot, Robot)


def test_camera_needs_open_and_ends(sim):
    with pytest.raises(CameraClosed):
        sim.camera.grab(0.1)
    sim.camera.open()
    frames = list(camera_frames(sim.camera))
    ids = np.array([f.frame_id for f in frames])
    assert np.all(np.diff(ids) >= 1)
    missing = sim.camera.frame_count - len(ids)
    assert 0 < missing < sim.camera.frame_count * 0.4  # 20 % dropped, give or take
    assert_allclose([f.t for f in frames], [sim.camera.time_of(i) for i in ids])
    with pytest.raises(CameraClosed):
        sim.camera.grab(0.1)


def test_robot_reports_only_the_past(sim):
    with pytest.raises(RuntimeError, match="not connected"):
        sim.robot.latest()
    sim.robot.connect()
    sim.camera.clock.now = 0.5
    latest = sim.robot.latest()
    assert latest.t <= 0.5
    assert_allclose(sim.robot.pose_at(0.2513).position, sim.motion.tcp_position(0.2513),
                    atol=INTERP_TOL_MM)
    with pytest.raises(LookupError):
        sim.robot.pose_at(0.6)  # the future
    assert sim.robot.connected
    sim.robot.disconnect()
    assert not sim.robot.connected
