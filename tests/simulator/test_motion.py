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
