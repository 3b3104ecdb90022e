"""The place correction (clients.placement): the equation, its refusals, and the UR pose
vector conversions against scipy (which the clients themselves do not import)."""
import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation

from clients import (PoseNotActionable, corrected_tcp_place, matrix_to_ur_pose, place_correction,
                     pose_actionable, ur_pose_to_matrix)
from clients.placement import FRAMES, correction_entry, matrix_to_rotvec, rotvec_to_matrix

#: Composed rigid transforms of a few hundred mm agree to rounding: 1e-9 mm and 1e-12 of a
#: rotation element leave a wide margin.
PLACE_ATOL_MM = 1e-9
ROTATION_ATOL = 1e-12
#: A rotation vector from a matrix, against scipy's, rad (near 180 degrees the matrix holds
#: the axis to about 1e-8 only: both methods lose the same digits).
ROTVEC_ATOL = 1e-10


def rigid(rng, *, translation_mm=300.0):
    m = np.eye(4)
    m[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    m[:3, 3] = rng.uniform(-translation_mm, translation_mm, 3)
    return m


def misplaced(nominal, values):
    """The true ^T X_P of a part misplaced by [tx, ty, tz mm, rotation vector deg] in {T}."""
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(values[3:], degrees=True).as_matrix()
    m[:3, 3] = values[:3]
    return m @ nominal


def pose_entry(matrix, **extra):
    return {"matrix": np.asarray(matrix).tolist(), "act": True, "act_reasons": [], **extra}


# -- the equation ------------------------------------------------------------------------------

def test_the_part_lands_where_the_nominal_part_would(rng):
    for _ in range(20):
        taught, nominal = rigid(rng), rigid(rng, translation_mm=50.0)
        pose = misplaced(nominal, [*rng.uniform(-3, 3, 3), *rng.uniform(-5, 5, 3)])
        correction = place_correction(taught, pose_entry(pose), nominal)
        placed = correction.tcp_place_mm @ pose
        assert_allclose(placed[:3, 3], (taught @ nominal)[:3, 3], atol=PLACE_ATOL_MM)
        assert_allclose(placed[:3, :3], (taught @ nominal)[:3, :3], atol=ROTATION_ATOL)
        assert_allclose(correction.tcp_place_mm, corrected_tcp_place(taught, pose, nominal),
                        atol=PLACE_ATOL_MM)
        assert_allclose(correction.misplacement @ nominal, pose, atol=PLACE_ATOL_MM)
        assert_allclose(ur_pose_to_matrix(correction.ur_pose), correction.tcp_place_mm,
                        atol=PLACE_ATOL_MM)


def test_no_misplacement_no_correction(rng):
    taught, nominal = rigid(rng), rigid(rng)
    assert_allclose(corrected_tcp_place(taught, nominal, nominal), taught, atol=PLACE_ATOL_MM)


def test_a_part_held_1_mm_along_x_t_is_placed_by_a_tcp_1_mm_back():
    taught = np.eye(4)
    taught[:3, 3] = [400.0, -200.0, 100.0]
    taught[:3, :3] = np.diag([1.0, -1.0, -1.0])       # TCP pointing down: z_T = -z_B
    nominal = np.eye(4)
    pose = nominal.copy()
    pose[0, 3] = 1.0                                   # 1 mm along x_T
    corrected = corrected_tcp_place(taught, pose, nominal)
    assert_allclose(corrected[:3, 3], [399.0, -200.0, 100.0], atol=PLACE_ATOL_MM)
    assert_allclose(corrected[:3, :3], taught[:3, :3], atol=ROTATION_ATOL)


def test_the_entry_carries_the_move_and_its_frames(rng):
    taught, nominal = rigid(rng), rigid(rng)
    entry = correction_entry(taught, pose_entry(nominal), nominal)
    assert entry["act"] is True and entry["reasons"] == []
    assert_allclose(entry["tcp_place_mm"], taught, atol=PLACE_ATOL_MM)
    assert len(entry["ur_pose"]) == 6 and entry["frames"] == FRAMES
    assert "{B}" in FRAMES and "{T}" in FRAMES and "inv(" in FRAMES


# -- what must not move the robot --------------------------------------------------------------

@pytest.mark.parametrize("pose, reason", [
    (None, "no pose"),
    ({"refused": "a pose needs at least 50 points, the scan has 3"}, "at least 50 points"),
    (pose_entry(np.eye(4), act=False, act_reasons=["not observable: about z_T"]), "about z_T"),
    (pose_entry(np.eye(4), act=False, act_reasons=[]), "not to act"),
    (pose_entry(np.eye(4), act="yes"), "not to act"),            # only JSON true acts
    # A service older than `act`: observable and unflagged only.
    ({"matrix": np.eye(4).tolist(), "observable": True, "flags": ["rms 0.4 mm"]}, "rms 0.4"),
    ({"matrix": np.eye(4).tolist(), "observable": False, "flags": [],
      "free_axes": [{"kind": "rotation", "label": "about z_T"}]}, "not observable: about z_T"),
    ({"matrix": np.eye(4).tolist()}, "not observable"),
    ({"act": True}, "no matrix"),
])
def test_a_pose_not_to_act_on_gives_no_move(pose, reason):
    with pytest.raises(PoseNotActionable, match=reason) as caught:
        place_correction(np.eye(4), pose, np.eye(4))
    assert caught.value.reasons and isinstance(caught.value, ValueError)
    entry = correction_entry(np.eye(4), pose, np.eye(4))
    assert entry["act"] is False and entry["tcp_place_mm"] is None and entry["ur_pose"] is None
    assert any(reason in r for r in entry["reasons"])


def test_a_pose_matrix_that_is_not_rigid_is_a_reason_not_to_act():
    entry = correction_entry(np.eye(4), pose_entry(np.diag([2.0, 1.0, 1.0, 1.0])), np.eye(4))
    assert entry["act"] is False and entry["tcp_place_mm"] is None
    assert "orthonormal" in entry["reasons"][0]
    with pytest.raises(ValueError, match="taught_place"):
        correction_entry(np.zeros(6), pose_entry(np.eye(4)), np.eye(4))


def test_an_old_style_pose_that_is_observable_and_unflagged_acts():
    assert pose_actionable({"matrix": np.eye(4).tolist(), "observable": True, "flags": []}) \
        == (True, [])


def test_a_pose_that_is_not_an_entry_is_a_type_error():
    with pytest.raises(TypeError, match="pose entry"):
        place_correction(np.eye(4), np.eye(4), np.eye(4))


@pytest.mark.parametrize("matrix, message", [
    (np.zeros(6), "UR pose vector"),
    (np.zeros((3, 4)), "shape"),
    (np.full((4, 4), np.nan), "finite"),
    (np.diag([1.0, 1.0, 1.0, 2.0]), "last row"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "determinant"),
    (np.diag([1.001, 1.0, 1.0, 1.0]), "orthonormal"),
    ("not a matrix", "4x4"),
])
def test_a_matrix_that_is_not_a_rigid_transform_is_refused(matrix, message):
    with pytest.raises(ValueError, match=message) as caught:
        corrected_tcp_place(matrix, np.eye(4), np.eye(4))
    assert "taught_place" in str(caught.value)


# -- UR pose vectors ---------------------------------------------------------------------------

def rotvecs(rng):
    """Random rotations, and those near the ends of the angle range."""
    axes = rng.normal(size=(12, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    cases = [Rotation.random(random_state=rng).as_rotvec() for _ in range(50)]
    for angle in (0.0, 1e-15, 1e-9, 1e-5, 9.9e-5, 1.01e-4, 1e-3, 1.0, np.pi - 1e-3,
                  np.pi - 1e-6, np.pi - 1e-9, np.pi):
        cases += [axis * angle for axis in axes[:4]]
    cases += [np.array([np.pi, 0.0, 0.0]), np.array([0.0, np.pi, 0.0]),
              np.array([0.0, 0.0, np.pi]), np.array([0.0, 0.0, -np.pi])]
    return cases


def test_rotation_vector_to_matrix_matches_scipy(rng):
    for r in rotvecs(rng):
        assert_allclose(rotvec_to_matrix(r), Rotation.from_rotvec(r).as_matrix(),
                        atol=ROTATION_ATOL, err_msg=f"{r}")


def test_matrix_to_rotation_vector_matches_scipy(rng):
    for r in rotvecs(rng):
        matrix = Rotation.from_rotvec(r).as_matrix()
        ours, theirs = matrix_to_rotvec(matrix), Rotation.from_matrix(matrix).as_rotvec()
        assert np.linalg.norm(ours) <= np.pi + 1e-12
        if np.linalg.norm(theirs) > np.pi - 1e-6 and ours @ theirs < 0:
            theirs = -theirs                 # 180 degrees: r and -r are the same rotation
        assert_allclose(ours, theirs, atol=ROTVEC_ATOL, err_msg=f"{r}")
        assert_allclose(rotvec_to_matrix(ours), matrix, atol=ROTATION_ATOL, err_msg=f"{r}")


def test_tiny_angles_keep_their_relative_precision():
    for r in (np.array([1e-12, -2e-12, 3e-12]), np.array([0.0, 0.0, 1e-300])):
        matrix = rotvec_to_matrix(r)
        assert_allclose(matrix_to_rotvec(matrix), Rotation.from_matrix(matrix).as_rotvec(),
                        rtol=1e-6, atol=0)


def test_ur_pose_round_trip_and_units(rng):
    for r in rotvecs(rng):
        vector = np.concatenate([rng.uniform(-1.0, 1.0, 3), r])
        matrix = ur_pose_to_matrix(vector)
        assert_allclose(matrix[:3, 3], vector[:3] * 1000.0)         # metres -> mm
        assert_allclose(matrix[:3, :3], Rotation.from_rotvec(r).as_matrix(), atol=ROTATION_ATOL)
        back = matrix_to_ur_pose(matrix)
        assert_allclose(back[:3], vector[:3], atol=1e-15)
        assert_allclose(ur_pose_to_matrix(back), matrix, atol=PLACE_ATOL_MM)


@pytest.mark.parametrize("vector", [[0.0] * 5, [0.0] * 5 + [np.inf], np.eye(4)])
def test_a_ur_pose_must_be_six_finite_numbers(vector):
    with pytest.raises(ValueError, match="six finite numbers"):
        ur_pose_to_matrix(vector)


def test_the_clients_ur_poses_are_the_scanner_s(rng):
    """The clients convert UR poses with numpy alone (they import nothing of the project);
    the scanner's own conversion (``scanner_core.io.rtde``) gives the same, 180 degrees
    included (where r and -r are the same turn, the matrices agree)."""
    from scanner_core.io.rtde import matrix_to_ur_pose as scanner_to_ur
    from scanner_core.io.rtde import ur_pose_to_matrix as scanner_from_ur

    angles = np.concatenate([rng.uniform(0.0, np.pi, 200), [0.0, 1e-9, np.pi]])
    for angle in angles:
        axis = rng.normal(size=3)
        ur = np.concatenate([rng.uniform(-1.0, 1.0, 3), angle * axis / np.linalg.norm(axis)])
        assert_allclose(scanner_from_ur(ur), ur_pose_to_matrix(ur), atol=1e-12)
        matrix = ur_pose_to_matrix(ur)
        assert_allclose(scanner_from_ur(scanner_to_ur(matrix)),
                        ur_pose_to_matrix(matrix_to_ur_pose(matrix)), atol=1e-9)
        if angle < np.pi - 1e-6:
            assert_allclose(scanner_to_ur(matrix), matrix_to_ur_pose(matrix), atol=1e-9)
