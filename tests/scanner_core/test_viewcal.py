"""The views from LED positions: the ladder of models, recovery, outliers, refusals."""
from dataclasses import replace

import numpy as np
import pytest

from scanner_core.geometry import angle_between, reproject_marker
from scanner_core.calibration.views import (ViewCalibrationError, calibrate_views, fit_affine, fit_dlt,
                                            project_affine, project_dlt)
from simulator.cell import load_cell
from simulator.effects import REAL_LENS_DISTORTION


def _session(distortion=REAL_LENS_DISTORTION, n=200, seed=0):
    cell = load_cell(perturb_seed=2)
    cal = cell.calibration
    cal = replace(cal, camera=replace(cal.camera, distortion=distortion))
    rng = np.random.default_rng(seed)
    a = np.column_stack([rng.uniform(-60, 60, n // 2), rng.uniform(-25, 25, n // 2),
                         rng.uniform(-40, 40, n // 2)])
    b = np.column_stack([rng.uniform(60, 115, n // 2), rng.uniform(-90, 210, n // 2),
                         rng.uniform(55, 105, n // 2)])
    points = np.vstack([a, b])
    px = reproject_marker(points, cal.camera, cal.mirrors)
    for v, (c0, c1) in enumerate(cal.strips):
        out = ~((px[:, v, 0] >= c0 + 8) & (px[:, v, 0] <= c1 - 9) & (px[:, v, 1] >= 8)
                & (px[:, v, 1] <= cal.camera.height - 9))
        px[out, v] = np.nan
    return cal, points, px


def _angle_deg(a, b):
    return np.degrees(angle_between(a, b, undirected=True))


def test_noise_free_recovery_to_numerical_precision():
    cal, points, px = _session()
    views = calibrate_views(points, px, 1920, 1200)
    assert views.model == "pinhole+distortion"
    assert views.rms_px < 1e-6
    cam = views.camera
    assert abs(cam.fx - cal.camera.fx) < 1e-5 and abs(cam.cx - cal.camera.cx) < 1e-5
    np.testing.assert_allclose(cam.distortion, cal.camera.distortion, atol=1e-7)
    np.testing.assert_allclose(cam.origin, cal.camera.origin, atol=1e-6)
    np.testing.assert_allclose(cam.rotation, cal.camera.rotation, atol=1e-9)
    for plane, mirror in zip(views.mirror_planes, cal.mirrors):
        assert _angle_deg(plane.normal, mirror.plane.normal) < 1e-6
        assert abs(abs(plane.offset) - abs(mirror.plane.offset)) < 1e-6


def test_the_ladder_keeps_the_simplest_model_that_fits():
    """An ideal lens keeps the projective model; a real one needs the distortion, and the
    affine Eq. (1) misses by pixels in a perspective camera."""
    rng = np.random.default_rng(1)
    cal, points, px = _session(distortion=(0.0,) * 5)
    ideal = calibrate_views(points, px + rng.normal(0, 0.02, px.shape), 1920, 1200)
    assert ideal.model == "projective"
    assert all(r.chosen == "projective" for r in ideal.reports)
    assert all(r.heldout_rms_px["affine"] > 1.0 for r in ideal.reports)
    assert not ideal.camera.distorted
    cal, points, px = _session()
    real = calibrate_views(points, px + rng.normal(0, 0.02, px.shape), 1920, 1200)
    assert real.model == "pinhole+distortion"
    for r in real.reports:
        assert r.chosen == "pinhole+distortion"
        assert r.heldout_rms_px["pinhole+distortion"] < 0.05  # the target
        assert r.heldout_rms_px["projective"] > 0.1


def test_five_percent_outliers_do_not_move_the_views():
    rng = np.random.default_rng(2)
    cal, points, px = _session()
    noisy = px + rng.normal(0, 0.02, px.shape)
    wrong = rng.random(px.shape[:2]) < 0.05
    noisy[wrong] += rng.uniform(5, 40, (wrong.sum(), 2)) * rng.choice([-1, 1], (wrong.sum(), 2))
    views = calibrate_views(points, noisy, 1920, 1200)
    assert views.outliers >= 0.8 * np.sum(wrong & np.isfinite(px[..., 0]))
    assert np.linalg.norm(views.camera.origin - cal.camera.origin) < 0.2
    assert max(views.per_view_rms_px) < 0.05


@pytest.mark.parametrize("shape", ["line", "plane"])
def test_degenerate_positions_are_refused(shape):
    cal, points, _ = _session()
    if shape == "line":
        points = np.outer(np.linspace(-50, 50, len(points)), [1.0, 0.3, 0.2]) + [40, 0, 0]
    else:
        points = points.copy()
        points[:, 1] = 0.0
    px = reproject_marker(points, cal.camera, cal.mirrors)
    with pytest.raises(ViewCalibrationError, match=shape):
        calibrate_views(points, px, 1920, 1200)


def test_too_few_positions_name_the_view():
    cal, points, px = _session(n=40)
    px[:, 2] = np.nan
    px[:5, 2] = 100.0
    with pytest.raises(ViewCalibrationError, match="right mirror"):
        calibrate_views(points, px, 1920, 1200)


def test_affine_and_dlt_fit_their_own_models_exactly():
    rng = np.random.default_rng(3)
    points = rng.uniform(-50, 50, (30, 3))
    a = rng.normal(size=(2, 4))
    np.testing.assert_allclose(project_affine(fit_affine(points, project_affine(a, points)),
                                              points), project_affine(a, points), atol=1e-9)
    p = np.array([[2000.0, 0, 960, 10], [0, 2000, 600, 20], [0, 0, 1, 500]])
    px = project_dlt(p, points)
    np.testing.assert_allclose(project_dlt(fit_dlt(points, px), points), px, atol=1e-8)


def test_the_lens_model_is_opencvs():
    """The camera projects as OpenCV's projectPoints does with the same (k1, k2, p1, p2, k3),
    and OpenCV's calibrateCamera, started from the DLT (CALIB_USE_INTRINSIC_GUESS), finds the
    same lens in the direct view's observations as the joint fit."""
    import cv2

    cal, points, px = _session()
    cam = cal.camera
    rvec, _ = cv2.Rodrigues(cam.rotation)
    tvec = -cam.rotation @ cam.origin
    cv_px, _ = cv2.projectPoints(points, rvec, tvec, cam.matrix, np.array(cam.distortion))
    np.testing.assert_allclose(cv_px.reshape(-1, 2), cam.project(points), atol=1e-6)
    seen = np.isfinite(px[:, 0, 0])
    from scanner_core.calibration.views import decompose_dlt
    k, _, _ = decompose_dlt(fit_dlt(points[seen], px[seen, 0]))
    k[0, 1] = 0.0
    rms, k_cv, dist_cv, _, _ = cv2.calibrateCamera(
        [points[seen].astype(np.float32)], [px[seen, 0].astype(np.float32)], (1920, 1200), k,
        np.zeros(5), flags=cv2.CALIB_USE_INTRINSIC_GUESS)
    assert rms < 0.01
    views = calibrate_views(points, px, 1920, 1200)
    assert abs(k_cv[0, 0] - views.camera.fx) < 1.0
    np.testing.assert_allclose(dist_cv.ravel()[:2], views.camera.distortion[:2], atol=0.01)
