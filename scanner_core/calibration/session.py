"""A calibration session from frames to a calibration file (``flyscan calibrate``).

Three steps, each through the scanner's own detectors:

1. the views: the LED at known positions (a stage's, or the robot's poses times the LED's
   offset, which is then fitted too: ``scanner_core.calibration.ledpivot``), its centroid in each view
   (``scanner_core.marker.finder.find_markers``), the ladder of view models
   (``scanner_core.calibration.views``);
2. the light plane: the stripe on a sphere of known radius at known centres
   (``scanner_core.pipeline.frame_stripe``, ``scanner_core.calibration.plane``);
3. the clocks and the LED's offset from the TCP: a pass of the sphere held by the robot,
   processed with the geometry of steps 1-2 (``scanner_core.pipeline.crosscheck.estimate_led_and_clock``).

The session folder (``flyscan calibrate --session DIR``) is read and written by
``scanner_core.calibration.folder``; its names are re-exported here.
"""
from __future__ import annotations

import datetime as _dt
from dataclasses import replace
from typing import Callable, Iterable

import numpy as np

from scanner_core.geometry.calibration import Calibration
from scanner_core.calibration.folder import (SESSION_FORMAT, SESSION_VERSION, Session,
                                             SessionError, SessionWriter, load_session,
                                             write_session)
from scanner_core.pipeline.crosscheck import (clock_and_offset_rows, estimate_led_and_clock,
                                              led_offset_spread, robot_rotations, track_at)
from scanner_core.geometry import Plane
from scanner_core.calibration.ledpivot import led_from_robot_poses
from scanner_core.marker.finder import find_markers
from scanner_core.pipeline import PipelineParams, camera_frames, frame_stripe, run_pass
from scanner_core.calibration.plane import (PlaneUncertainty, calibrate_plane, jackknife_covariance,
                                            plane_parameters, sphere_plane)
from scanner_core.types import MarkerObservation
from scanner_core.calibration.views import calibrate_views, fit_physical, project_views, views_as_mirrors
from scanner_core.devices import Robot
from scanner_core.geometry.triangulation import marker_views, reproject_marker, triangulate_marker

#: The LED positions fall into this many groups, each left out in turn to see how far the
#: views' error moves the light plane (`views_jackknife`): ten refits of the views.
VIEW_JACKKNIFE_GROUPS = 10

__all__ = ["Session", "SessionError", "SessionWriter", "SESSION_FORMAT", "SESSION_VERSION",
           "calibrate_session", "load_session", "write_session", "observe_led", "observe_sphere"]


def observe_led(images: Iterable[np.ndarray], strips, params: PipelineParams) -> np.ndarray:
    """(N, V, 2) the LED's centroid per frame and view, NaN where not found."""
    return np.array([find_markers(img, strips=strips, params=params.marker) for img in images])


def observe_sphere(images: Iterable[np.ndarray], layout: Calibration,
                   params: PipelineParams) -> list[np.ndarray]:
    """Per frame, the stripe's (N, 2) pixels (u, v) on the sphere: the scanner's extraction."""
    no_marker = MarkerObservation(np.full((1 + len(layout.mirrors), 2), np.nan), np.full(3, np.nan),
                                  float("nan"))
    out = []
    for img in images:
        result, valid, _ = frame_stripe(img, layout, params, no_marker)
        cols = np.nonzero(valid)[0]
        out.append(np.column_stack([cols.astype(np.float64), result.row[cols].astype(np.float64)]))
    return out


def calibrate_session(session: Session, params: PipelineParams = PipelineParams(), *,
                      progress: Callable[[str], None] = lambda _: None,
                      seed: int = 0) -> tuple[Calibration, dict]:
    """The calibration a session gives, and the report of how it was found.

    Raises
    ------
    ValueError
        (``ViewCalibrationError``, ``PlaneCalibrationError``) when the session cannot determine
        the views or the plane: the message says what is missing.
    """
    nominal = session.nominal
    nominal.check_image_size(session.width, session.height)
    progress(f"views: finding the LED in {len(session.led_positions_b)} frames")
    led_px = observe_led(session.led_images(), nominal.strips, params)
    led_fit = None
    if session.led_tcp_b is None:
        led_positions_b = session.led_positions_b
    else:
        led_positions_b, led_fit = _led_from_robot(session, led_px, seed)
        progress(f"LED offset from {led_fit['poses']} robot poses ({led_fit['turned']} turned): "
                 f"{np.round(led_fit['led_t_mm'], 3).tolist()} mm in {{T}}, "
                 f"{led_fit['rms_mm'] * 1e3:.1f} um RMS")
    views = calibrate_views(led_positions_b, led_px, session.width, session.height, seed=seed)
    progress(f"views: {views.model}, {views.rms_px:.4f} px RMS "
             f"({views.outliers} observation(s) dropped)")
    mirrors = views_as_mirrors(views.mirror_planes, [m.columns for m in nominal.mirrors])
    camera = views.camera
    progress(f"light plane: the stripe on the sphere in {len(session.sphere_centres_b)} frames")
    stripes = observe_sphere(session.sphere_images(), nominal, params)
    sphere_frames = list(zip(stripes, session.sphere_centres_b))
    plane = calibrate_plane(sphere_frames, camera, session.sphere_radius_mm)
    plane_c = plane.plane_b.transformed(camera.rotation, -camera.rotation @ camera.origin)
    progress(f"light plane: {plane.points} points from {plane.frames} frames, "
             f"{plane.rms_mm * 1e3:.1f} um RMS; sphere centres {plane.centre_rms_mm * 1e3:.1f} um RMS")
    # The views refitted without each tenth of the LED positions: how far their error moves
    # the light plane and, through the pass's marker, the LED's offset.
    refits = None
    if plane.uncertainty is not None or session.pass_devices is not None:
        progress(f"views: refitted {VIEW_JACKKNIFE_GROUPS} times, each without a tenth of the "
                 f"LED positions")
        refits = refit_views(led_positions_b, led_px, views, session.width, session.height,
                             seed=seed)
    plane_uncertainty = None  # too few sphere frames to tell
    if plane.uncertainty is not None:
        plane_uncertainty = views_jackknife(
            refits, lambda cam: sphere_plane(sphere_frames, cam, session.sphere_radius_mm)[0],
            plane.uncertainty)
    led_t = nominal.marker_offset_t.copy() if led_fit is None else np.array(led_fit["led_t_mm"])
    calibration = Calibration(camera, Plane(plane_c.normal, plane_c.offset), mirrors,
                              nominal.direct_columns, led_t, nominal.clock_offset_s,
                              light_plane_uncertainty=plane_uncertainty)
    clocks = None
    if session.pass_devices is not None:
        progress("clocks and LED offset: a pass of the robot")
        calibration, clocks = _led_and_clock(session, calibration, params, refits)
        progress(f"clocks: robot minus camera {clocks['clock_offset_s'] * 1e3:.3f} ms; LED at "
                 f"{np.round(calibration.marker_offset_t, 3).tolist()} mm in {{T}} "
                 f"({clocks['rms_mm'] * 1e3:.1f} um RMS)")
    report = {
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "cell": session.cell_name,
        "observations": {"led_positions": int(len(session.led_positions_b)),
                         "led_centroids": int(np.isfinite(led_px[..., 0]).sum()),
                         "sphere_positions": int(len(session.sphere_centres_b)),
                         "stripe_points": plane.points,
                         "pass_frames": None if clocks is None else clocks["frames"]},
        "models": {"views": views.model,
                   "ladder": [r.to_dict() for r in views.reports]},
        "residuals": {"views_rms_px": views.rms_px, "views_per_view_rms_px": views.per_view_rms_px,
                      "views_outliers": views.outliers,
                      "plane_rms_mm": plane.rms_mm,
                      "sphere_centre_rms_mm": plane.centre_rms_mm,
                      "led_pass_rms_mm": None if clocks is None else clocks["rms_mm"]},
        "per_position": {
            "led_px": _per_position_px(views, led_positions_b, led_px).tolist(),
            "sphere_centre_mm": plane.centre_errors_mm.tolist()},
        "led_from_robot": led_fit,
        # the LED offset's sigma (the file's marker_offset_std_mm) term by term, mm along {T}
        "led_offset_std_terms_mm": None if clocks is None else clocks["led_std_terms_t_mm"],
    }
    report = _json_safe(report)
    return replace(calibration, provenance=report), report


def refit_views(points_b, pixels, views, width: int, height: int, *,
                groups: int = VIEW_JACKKNIFE_GROUPS, seed: int = 0) -> list[tuple]:
    """The replicates of the views' delete-a-group jackknife (Efron and Stein 1981): the views
    refitted without each of `groups` random groups of the LED positions in turn, from the
    fit's own camera and mirrors.

    Returns
    -------
    list of (PinholeCamera, list of Plane)
        Per group, the camera and the mirror planes.
    """
    points_b = np.asarray(points_b, dtype=np.float64)
    pixels = np.asarray(pixels, dtype=np.float64)
    label = np.random.default_rng([seed, groups]).permutation(len(points_b)) % groups
    refits = []
    for g in range(groups):
        keep = label != g
        camera, planes, _ = fit_physical(points_b[keep], pixels[keep], width, height,
                                         distortion=views.camera.distorted,
                                         initial=(views.camera, list(views.mirror_planes)))
        refits.append((camera, list(planes)))
    return refits


def views_jackknife(refits, plane_of: Callable, uncertainty: PlaneUncertainty) -> PlaneUncertainty:
    """The light plane's uncertainty with the views' own: `uncertainty` (the sphere frames'
    scatter, ``scanner_core.calibration.plane.plane_uncertainty``) plus the jackknife of the
    plane fitted again through each of the views' `refits` (`refit_views`; `plane_of`:
    camera -> Plane in {B}). The sphere's points come through the direct view's rays, so the
    views' error tilts and shifts the plane as well (docs/calibration.md measures both against
    the truth).

    Returns
    -------
    PlaneUncertainty
        About `uncertainty`'s centre and axes: the two covariances added.
    """
    thetas = [plane_parameters(plane_of(camera), uncertainty.centre_b, uncertainty.axes_b)
              for camera, _ in refits]
    return replace(uncertainty,
                   covariance=uncertainty.covariance + jackknife_covariance(thetas))


def led_views_jackknife(refits, calibration: Calibration, times, marker_b, robot: Robot,
                        clock_offset_s: float) -> np.ndarray:
    """How far the views' error moves the LED's offset fitted on a pass: its standard
    deviation per {T} axis, mm, the jackknife over the views' `refits` (`refit_views`).

    The marker's positions on the pass are projected into the views it was seen in (the
    calibration's, within each view's strip of columns) and triangulated again through each
    refit, and the offset and the clock fitted again on them, linearised about the pass's
    fit (``scanner_core.pipeline.crosscheck.estimate_led_and_clock``'s last step: the refits
    move the marker by microns). The views' error moves every position of the pass alike,
    which the stretches of one pass (``led_offset_spread``) cannot tell from the offset.

    Parameters
    ----------
    refits : list of (PinholeCamera, list of Plane)
    calibration : Calibration
        The views the pass was triangulated through.
    times : (N,) float64
        Camera times, s.
    marker_b : (N, 3) float64
        The LED's positions in {B}, mm.
    robot : Robot
    clock_offset_s : float
        The pass's fitted robot-minus-camera clock, s.

    Returns
    -------
    (3,) float64
        mm along x_T, y_T, z_T; NaN where fewer than 10 of the pass's frames have a robot
        pose and the marker in two views.
    """
    marker_b = np.asarray(marker_b, dtype=np.float64).reshape(-1, 3)
    pixels = reproject_marker(marker_b, calibration.camera, calibration.mirrors)
    for view, (c0, c1) in enumerate(calibration.strips):
        u, v = pixels[:, view, 0], pixels[:, view, 1]
        outside = ~((u >= c0) & (u < c1) & (v >= 0) & (v < calibration.camera.height))
        pixels[outside, view] = np.nan
    times = np.asarray(times, dtype=np.float64)
    clock = times + clock_offset_s
    _, velocity, ok = track_at(robot, clock)
    ok &= np.isfinite(pixels[..., 0]).sum(axis=1) >= 2
    if ok.sum() < 10:
        return np.full(3, np.nan)
    pixels = pixels[ok]
    rows = clock_and_offset_rows(velocity[ok], robot_rotations(robot, clock[ok]))

    def triangulated(camera, planes):
        mirrors = views_as_mirrors(planes, [m.columns for m in calibration.mirrors])
        views = marker_views(camera, mirrors)
        return np.array([triangulate_marker(px, camera, mirrors, views=views)[0]
                         for px in pixels])

    here = triangulated(calibration.camera, [m.plane for m in calibration.mirrors])
    offsets = []
    for camera, planes in refits:
        moved = (triangulated(camera, planes) - here).ravel()
        if not np.isfinite(moved).all():
            return np.full(3, np.nan)
        offsets.append(np.linalg.lstsq(rows, moved, rcond=None)[0][1:])
    return np.sqrt(np.diag(jackknife_covariance(offsets)))


def _per_position_px(views, points_b, pixels) -> np.ndarray:
    """(N,) RMS over the views of the fitted views' reprojection error at each LED position,
    px (NaN where no view saw it)."""
    err = project_views(views.camera, views.mirror_planes, points_b) - pixels
    sq = np.nansum(err**2, axis=(1, 2))
    seen = np.isfinite(err[..., 0]).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(seen > 0, np.sqrt(sq / np.maximum(seen, 1)), np.nan)


def _json_safe(value):
    """The report as JSON holds it: numpy numbers as Python ones, a figure that could not be
    measured (NaN: a view with no held-out position) as null."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def _led_from_robot(session: Session, led_px: np.ndarray, seed: int):
    """The LED's positions and its offset in {T} from the robot's poses
    (``scanner_core.calibration.ledpivot``), with the views fitted as the stage's are."""
    def views_of(points_b, pixels):
        views = calibrate_views(points_b, pixels, session.width, session.height, seed=seed)
        return views.camera, views_as_mirrors(views.mirror_planes,
                                              [m.columns for m in session.nominal.mirrors])

    return led_from_robot_poses(session.led_tcp_b, led_px, session.nominal.marker_offset_t,
                                views_of)


def _led_and_clock(session: Session, calibration: Calibration, params: PipelineParams,
                   refits) -> tuple[Calibration, dict]:
    camera, robot = session.pass_devices()
    camera.open()
    robot.connect()
    try:
        scan = run_pass(camera_frames(camera), calibration, robot, params)
        if len(scan.tcp_times) < 10:
            raise ValueError(f"the pass placed {len(scan.tcp_times)} frames: too few for the "
                             f"clocks")
        # Back to the LED's own positions (the pass placed the TCP with the nominal offset).
        marker_b = scan.tcp_positions_b + np.einsum("fij,j->fi", scan.tcp_rotations_b,
                                                    calibration.marker_offset_t)
        led, offset, rms = estimate_led_and_clock(scan.tcp_times, marker_b, robot,
                                                  initial_offset_s=calibration.clock_offset_s)
        # Two terms, added: the pass's own (its stretches fitted apart) and the views' error,
        # which moves the whole pass alike (docs/calibration.md validates the sum).
        spread = led_offset_spread(scan.tcp_times, marker_b, robot, offset)
        views_std = led_views_jackknife(refits, calibration, scan.tcp_times, marker_b, robot,
                                        offset)
    finally:
        camera.close()
        robot.disconnect()
    led_std = np.hypot(spread, views_std)
    led_std = None if not np.isfinite(led_std).all() else led_std
    return (replace(calibration, marker_offset_t=led, clock_offset_s=offset,
                    marker_offset_std_mm=led_std),
            {"clock_offset_s": offset, "led_t_mm": led.tolist(), "rms_mm": rms,
             "led_std_t_mm": None if led_std is None else led_std.tolist(),
             "led_std_terms_t_mm": {"pass": spread.tolist(), "views": views_std.tolist()},
             "frames": int(len(scan.tcp_times))})
