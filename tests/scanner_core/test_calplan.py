"""The calibration plan (UR poses for the cell's volume), the LED's offset from turned robot
poses, and the session folder recorded with the robot, read back as written."""
import numpy as np
import pytest

from clients.placement import ur_pose_to_matrix
from scanner_core.geometry.calibration import Calibration
from scanner_core.calibration.plan import (PlanGeometry, make_plan, plan_from_dict, plan_to_dict)
from scanner_core.calibration.folder import SessionError, SessionWriter, load_session
from scanner_core.calibration.ledpivot import fit_led_offset

#: Poses round-trip through UR's metres and rotation vectors, 9 decimals: 1 nm, 1e-9 rad.
UR_ROUND_MM = 1e-5
LED_T = np.array([88.0, -60.0, -30.0])
SPHERE_T = np.array([0.0, 0.0, 50.0])
#: The reference cell's tool orientation in a pass (z_T down).
R0 = np.diag([1.0, -1.0, -1.0])


@pytest.fixture
def geometry():
    return PlanGeometry(R0, -130.0, 130.0, 50.0, LED_T, SPHERE_T, 28.625)


def test_the_plan_puts_the_led_and_the_sphere_where_the_session_needs_them(geometry):
    plan = make_plan(geometry, led_count=60, sphere_count=10, tilt_deg=10.0,
                     tilted_fraction=0.3, seed=4)
    led, sphere = plan.of_kind("led"), plan.of_kind("sphere")
    assert (len(led), len(sphere)) == (60, 10)
    leds = np.array([s.tcp_b[:3, 3] + s.tcp_b[:3, :3] @ LED_T for s in led])
    # half about the sheet's centre, half along the LED's track (y within the pass)
    assert np.all(np.abs(leds[:30, 0]) <= 60) and np.all(np.abs(leds[:30, 1]) <= 25)
    track_y = leds[30:, 1] - (R0 @ LED_T)[1]  # the TCP's y where the LED would be
    assert np.all((track_y > -130) & (track_y < 130))
    turns = [np.degrees(np.arccos(np.clip((np.trace(R0.T @ s.tcp_b[:3, :3]) - 1) / 2, -1, 1)))
             for s in led]
    np.testing.assert_allclose(sorted(turns)[-18:], 10.0, atol=1e-9)  # 30 % turned by 10 deg
    assert sorted(turns)[-19] < 1e-6
    centres = np.array([s.tcp_b[:3, 3] + R0 @ SPHERE_T for s in sphere])
    cut = np.abs(centres[:, 1])  # the sheet at y = 0 cuts each 8 to 20 mm from its centre
    assert np.all((cut >= 0.28 * 28.625) & (cut <= 0.7 * 28.625))
    # repeatable, and another seed moves it
    again = make_plan(geometry, led_count=60, sphere_count=10, tilt_deg=10.0,
                      tilted_fraction=0.3, seed=4)
    assert all(np.array_equal(a.tcp_b, b.tcp_b) for a, b in zip(plan.steps, again.steps))
    other = make_plan(geometry, led_count=60, sphere_count=10, seed=5)
    assert not np.array_equal(other.steps[0].tcp_b, plan.steps[0].tcp_b)


def test_the_plan_is_in_urs_convention_and_reads_back(geometry):
    plan = make_plan(geometry, led_count=12, sphere_count=3)
    data = plan_to_dict(plan)
    assert data["convention"].startswith("UR")
    for step, original in zip(data["steps"], plan.steps):
        x, y, z, rx, ry, rz = step["tcp"]
        np.testing.assert_allclose(np.array([x, y, z]) * 1e3, original.tcp_b[:3, 3],
                                   atol=UR_ROUND_MM)  # metres
        assert np.linalg.norm([rx, ry, rz]) <= np.pi + 1e-9  # a rotation vector, rad
        np.testing.assert_allclose(ur_pose_to_matrix(step["tcp"]), original.tcp_b, atol=UR_ROUND_MM)
    back = plan_from_dict(data)
    assert [s.kind for s in back.steps] == [s.kind for s in plan.steps]
    np.testing.assert_allclose(back.pass_end_b, plan.pass_end_b, atol=UR_ROUND_MM)
    with pytest.raises(ValueError, match="format"):
        plan_from_dict({"format": "other"})
    with pytest.raises(ValueError, match="at least 12 LED and 3 sphere"):
        make_plan(geometry, led_count=5)
    with pytest.raises(ValueError, match="tilt_deg"):
        make_plan(geometry, tilt_deg=45.0)


def _rotations(rng, n, degrees):
    from scipy.spatial.transform import Rotation
    turns = Rotation.from_rotvec(np.radians(degrees) * rng.standard_normal((n, 3)) / 1.7)
    return np.einsum("nij,jk->nik", turns.as_matrix(), R0)


def test_the_led_offset_is_told_from_the_frame_by_turning_the_tool():
    rng = np.random.default_rng(2)
    n = 40
    tcp = np.tile(np.eye(4), (n, 1, 1))
    tcp[:, :3, :3] = _rotations(rng, n, 10.0)
    tcp[:, :3, 3] = rng.uniform(-60, 60, (n, 3))
    true_led, shift = LED_T + [0.3, -0.2, 0.25], np.array([-0.35, 0.39, -0.02])
    marker = tcp[:, :3, 3] + tcp[:, :3, :3] @ true_led + shift
    marker[3] = np.nan  # not triangulated: left out
    led, found_shift, rms = fit_led_offset(marker + rng.normal(0, 0.005, marker.shape), tcp)
    np.testing.assert_allclose(led, true_led, atol=0.01)  # 5 um noise -> well under 10 um
    np.testing.assert_allclose(found_shift, shift, atol=0.01)
    assert rms < 0.01
    still = tcp.copy()
    still[:, :3, :3] = R0  # one orientation: the offset cannot be told from the frame
    with pytest.raises(ValueError, match="do not turn the tool .* unobservable"):
        fit_led_offset(still[:, :3, 3] + R0 @ true_led, still)


def test_a_session_recorded_with_the_robot_reads_back(cell, tmp_path):
    nominal = cell.calibration
    tcp = np.eye(4)
    tcp[:3, :3], tcp[:3, 3] = R0, [10.0, -5.0, 60.0]
    image = np.full((nominal.camera.height, nominal.camera.width), 10, np.uint8)
    with SessionWriter(tmp_path / "s", width=nominal.camera.width, height=nominal.camera.height,
                       fps=162.0, sphere_radius_mm=28.625, nominal=nominal,
                       sphere_offset_t_mm=SPHERE_T, plan={"format": "x"}) as writer:
        for _ in range(2):
            writer.add("led", image, tcp_b=tcp, samples=50)
        writer.add("sphere", image, tcp_b=tcp, samples=50)
        with pytest.raises(ValueError, match="give tcp_b"):
            writer.add("led", image, position_b=[0, 0, 0])
    session = load_session(tmp_path / "s")
    np.testing.assert_allclose(session.led_tcp_b, [tcp, tcp], atol=UR_ROUND_MM)
    np.testing.assert_allclose(session.led_positions_b[0], tcp[:3, 3] + R0 @ nominal.marker_offset_t,
                               atol=UR_ROUND_MM)
    np.testing.assert_allclose(session.sphere_centres_b[0], tcp[:3, 3] + R0 @ SPHERE_T,
                               atol=UR_ROUND_MM)
    assert session.plan == {"format": "x"} and session.sphere_offset_t_mm.tolist() == SPHERE_T.tolist()
    assert len(list(session.led_images())) == 2
    # a robot's poses without the sphere's holder cannot be read: said so
    meta = (tmp_path / "s" / "session.json")
    meta.write_text(meta.read_text().replace('"sphere_offset_t_mm"', '"unused"'))
    with pytest.raises(SessionError, match="sphere_offset_t_mm"):
        load_session(tmp_path / "s")
