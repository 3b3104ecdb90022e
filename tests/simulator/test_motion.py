import numpy as np
from numpy.testing import assert_allclose

from simulator.cell import PassProfile
from simulator.motion import PassMotion


def test_pass_accelerates_and_curves():
    motion = PassMotion(PassProfile())
    t = np.linspace(0, motion.duration_s, 101)
    v = motion.speed(t)
    p = PassProfile()
    assert_allclose(v[-1] / v[0], (1 + p.accel_fraction) / (1 - p.accel_fraction), rtol=1e-9)
    assert np.all(np.diff(v) > 0)  # never constant speed
    xyz = motion.tcp_position(t)
    assert_allclose(xyz[[0, -1], 1], [p.start_y_mm, p.end_y_mm], atol=1e-9)
    assert_allclose(xyz[:, 0].max(), p.bow_mm, rtol=1e-3)  # not a straight line
    # The speed is the derivative of the distance.
    ds = np.gradient(motion.distance(t), t)
    assert_allclose(ds[1:-1], v[1:-1], rtol=1e-6)


def test_robot_arrives_and_leaves_moving():
    motion = PassMotion(PassProfile())
    p = PassProfile()
    before, start = motion.tcp_position(-0.1), motion.tcp_position(0.0)
    assert_allclose(start[1] - before[1], 0.1 * p.speed_mm_s * (1 - p.accel_fraction))
    end, after = motion.tcp_position(motion.duration_s), motion.tcp_position(motion.duration_s + 0.1)
    assert_allclose(after[1] - end[1], 0.1 * p.speed_mm_s * (1 + p.accel_fraction))


def test_one_time_gives_what_many_times_give():
    """The scalar path (the simulated robot's per-frame lookups) is the vectorised one."""
    motion = PassMotion(PassProfile())
    t = np.linspace(-0.3, motion.duration_s + 0.3, 257)
    one_by_one = np.array([motion.tcp_position(float(ti)) for ti in t])
    assert_allclose(one_by_one, motion.tcp_position(t), rtol=1e-12, atol=1e-9)


def test_a_peaked_pass_is_symmetric_in_speed_and_as_long():
    """The calibration pass's shape: up to v (1 + a) at the middle and down again, the same
    length in the same time, arriving and leaving at v (1 - a)."""
    import pytest

    p = PassProfile(speed_shape="peak")
    motion, ramp = PassMotion(p), PassMotion(PassProfile())
    assert motion.duration_s == ramp.duration_s
    t = np.linspace(0, motion.duration_s, 201)
    v = motion.speed(t)
    assert_allclose(v, v[::-1], rtol=1e-12)  # symmetric about the middle
    assert_allclose([v[0], v[100]], [p.speed_mm_s * (1 - p.accel_fraction),
                                     p.speed_mm_s * (1 + p.accel_fraction)], rtol=1e-12)
    assert np.all(np.diff(v[:101]) > 0) and np.all(np.diff(v[100:]) < 0)
    xyz = motion.tcp_position(t)
    assert_allclose(xyz[[0, -1], 1], [p.start_y_mm, p.end_y_mm], atol=1e-9)
    ds = np.gradient(motion.distance(t), t)
    assert_allclose(ds[1:100], v[1:100], rtol=1e-6)
    before, after = motion.tcp_position(-0.1), motion.tcp_position(motion.duration_s + 0.1)
    assert_allclose(motion.tcp_position(0.0)[1] - before[1], 0.1 * v[0])
    assert_allclose(after[1] - xyz[-1, 1], 0.1 * v[-1])
    one_by_one = np.array([motion.tcp_position(float(ti)) for ti in t])
    assert_allclose(one_by_one, xyz, rtol=1e-12, atol=1e-9)
    with pytest.raises(ValueError, match="speed_shape"):
        PassProfile(speed_shape="sine")


def test_the_simulated_calibration_pass_is_peaked(cell):
    from simulator.calsession import simulate_session

    session = simulate_session(cell, led_count=4, sphere_count=2)
    _, robot = session.pass_devices()
    assert robot.motion.profile.speed_shape == "peak"
