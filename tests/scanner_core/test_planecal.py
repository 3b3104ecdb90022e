"""The light plane from a sphere: recovery, outliers, a sheet that misses the sphere."""
import numpy as np
import pytest

from scanner_core.geometry import Plane, angle_between, unit
from scanner_core.calibration.plane import PlaneCalibrationError, calibrate_plane
from simulator.cell import load_cell

RADIUS = 28.625


def _stripe(camera, plane: Plane, centre, n=400):
    """The sphere-plane circle's pixels, the part of it the camera sees from outside."""
    c = np.asarray(centre, float)
    h = plane.signed_distance(c)[0]
    r = np.sqrt(max(RADIUS**2 - h**2, 0.0))
    foot = c - h * plane.normal
    e1 = unit(np.cross(plane.normal, [1.0, 0, 0]))
    e2 = np.cross(plane.normal, e1)
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    pts = foot + r * (np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2)
    facing = np.einsum("ij,ij->i", pts - c, camera.origin - pts) > 0
    return camera.project(pts[facing])


def _frames(cell, rng, count=20, miss=False):
    cam = cell.calibration.camera
    plane = cell.light_plane_b
    frames = []
    for _ in range(count):
        y = (RADIUS + 5 if miss else rng.uniform(8, 20)) * rng.choice([-1, 1])
        centre = np.array([rng.uniform(-45, 45), y, rng.uniform(-25, 25)])
        frames.append((_stripe(cam, plane, centre), centre))
    return frames


def test_noise_free_plane_to_numerical_precision():
    cell = load_cell(perturb_seed=4)
    fit = calibrate_plane(_frames(cell, np.random.default_rng(0)), cell.calibration.camera, RADIUS)
    true = cell.light_plane_b
    assert np.degrees(angle_between(fit.plane_b.normal, true.normal, undirected=True)) < 1e-6
    assert abs(fit.plane_b.signed_distance(true.normal * true.offset)[0]) < 1e-6
    assert fit.rms_mm < 1e-6
    assert fit.centre_rms_mm < 1e-6


def test_five_percent_stray_points_do_not_move_the_plane():
    """A reflection of the stripe lights pixels off the circle: they are outvoted."""
    cell = load_cell()
    rng = np.random.default_rng(1)
    frames = []
    for px, centre in _frames(cell, rng):
        px = px + rng.normal(0, 0.05, px.shape)
        stray = rng.random(len(px)) < 0.05
        px[stray, 1] += rng.uniform(5, 30, stray.sum())
        frames.append((px, centre))
    fit = calibrate_plane(frames, cell.calibration.camera, RADIUS)
    true = cell.light_plane_b
    assert np.degrees(angle_between(fit.plane_b.normal, true.normal, undirected=True)) < 0.005
    assert abs(fit.plane_b.signed_distance(true.normal * true.offset)[0]) < 0.010


def test_a_sheet_that_never_cuts_the_sphere_is_refused():
    cell = load_cell()
    frames = [(np.zeros((0, 2)), c) for _, c in _frames(cell, np.random.default_rng(2), miss=True)]
    with pytest.raises(PlaneCalibrationError, match="does the sheet cut the sphere"):
        calibrate_plane(frames, cell.calibration.camera, RADIUS)


def test_the_plane_s_uncertainty_matches_its_spread_over_repeated_sessions():
    """Each frame's stripe off by its own sphere position error (the stage's) and its pixels'
    noise: over repeated sessions the fitted plane's tilts and shift scatter as
    ``plane_uncertainty`` says, within the spread of a 40-session estimate."""
    cell = load_cell(perturb_seed=4)
    camera, true = cell.calibration.camera, cell.light_plane_b
    thetas, predicted = [], []
    for session in range(40):
        rng = np.random.default_rng([7, session])
        frames = []
        for pixels, centre in _frames(cell, rng, count=15):
            stage_error = rng.normal(0.0, 0.02, 3)          # the sphere not where the stage says
            frames.append((pixels + rng.normal(0.0, 0.1, pixels.shape), centre + stage_error))
        fit = calibrate_plane(frames, camera, RADIUS)
        u = fit.uncertainty
        n = np.cross(*u.axes_b)
        tn = true.normal * np.sign(true.normal @ n)
        to = true.offset * np.sign(true.normal @ n)
        thetas.append([(tn - n) @ u.axes_b[0], (tn - n) @ u.axes_b[1], to - tn @ u.centre_b])
        predicted.append(np.sqrt(np.diag(u.covariance)))
    z = np.array(thetas) / np.array(predicted)
    rms = np.sqrt(np.mean(z**2, axis=0))
    # 40 sessions: an RMS of unit normal deviates estimates within about 0.75-1.25
    assert np.all((rms > 0.7) & (rms < 1.35)), rms


def test_a_plane_uncertainty_round_trips_and_refuses_nonsense():
    from scanner_core.calibration.plane import PlaneUncertainty

    u = PlaneUncertainty(np.array([1.0, 2.0, 3.0]), np.array([[1.0, 0, 0], [0, 0, 1.0]]),
                         np.diag([1e-9, 4e-10, 1e-6]))
    back = PlaneUncertainty.from_dict(u.to_dict())
    np.testing.assert_array_equal(back.covariance, u.covariance)
    bad = u.to_dict()
    bad["axes"] = [[1.0, 0, 0], [1.0, 0, 0]]
    with pytest.raises(ValueError, match="orthonormal"):
        PlaneUncertainty.from_dict(bad)
    bad = u.to_dict()
    bad["covariance"] = [[1e-9, 0, 0], [0, -1e-6, 0], [0, 0, 1e-6]]
    with pytest.raises(ValueError, match="positive semi-definite"):
        PlaneUncertainty.from_dict(bad)
    with pytest.raises(ValueError, match="centre_mm"):
        PlaneUncertainty.from_dict({"axes": u.to_dict()["axes"]})


def test_three_frames_fix_a_plane_but_not_its_uncertainty():
    """The fewest frames a plane takes (``MIN_FRAMES``) leave too few leave-one-out fits to
    say how well they fix it: the plane, and no uncertainty (taken as not measured)."""
    from scanner_core.calibration.plane import MIN_FRAMES, MIN_UNCERTAINTY_FRAMES

    cell = load_cell(perturb_seed=4)
    frames = _frames(cell, np.random.default_rng(3), count=MIN_FRAMES)
    fit = calibrate_plane(frames, cell.calibration.camera, RADIUS)
    assert fit.frames == MIN_FRAMES < MIN_UNCERTAINTY_FRAMES and fit.uncertainty is None
    assert angle_between(fit.plane_b.normal, cell.light_plane_b.normal, undirected=True) < 1e-6
    more = calibrate_plane(_frames(cell, np.random.default_rng(3), count=MIN_UNCERTAINTY_FRAMES),
                           cell.calibration.camera, RADIUS)
    assert more.uncertainty is not None
