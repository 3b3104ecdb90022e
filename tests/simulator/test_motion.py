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


def test_position_clamped_outside_the_pass():
    motion = PassMotion(PassProfile())
    assert_allclose(motion.tcp_position(-1.0), motion.tcp_position(0.0))
    assert_allclose(motion.tcp_position(99.0), motion.tcp_position(motion.duration_s))
