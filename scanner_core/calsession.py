"""A calibration session from frames to a calibration file (``flyscan calibrate``, issue 9).

Three steps, each through the scanner's own detectors:

1. the views: the LED at known stage positions, its centroid in each view
   (``scanner_core.marker.find_markers``), the ladder of view models
   (``scanner_core.viewcal``);
2. the light plane: the stripe on a sphere of known radius at known centres
   (``scanner_core.pipeline.frame_stripe``, ``scanner_core.planecal``);
3. the clocks and the LED's offset from the TCP: a pass of the sphere held by the robot,
   processed with the geometry of steps 1-2 (``scanner_core.crosscheck.estimate_led_and_clock``).

Session folder (``flyscan calibrate --session DIR``; ``write_session`` writes one)
------------------------------------------------------------------------------------
``session.json``
    ``{"format": "flyscan-calibration-session", "version": 1, "image": {"width": W,
    "height": H, "fps": F}, "sphere_radius_mm": R, "cell": "name",
    "nominal": {...}}`` where ``nominal`` is a calibration object (the design the installer
    knows: the view strips and the LED's offset as built; its geometry is only a label).
``led.csv``
    Header ``image,x_mm,y_mm,z_mm``; one line per stage position of the LED in {B}, the image a
    file name in ``led/`` (8-bit greyscale PNG, W x H).
``sphere.csv``
    The same for the sphere's centre, images in ``sphere/``.
``pass/`` (optional)
    A recording of a pass of the robot (``scanner_core.recording``'s format): the clocks and the LED's
    offset are estimated from it; without it the nominal LED offset and a zero clock offset
    are kept.
"""
from __future__ import annotations

import csv
import datetime as _dt
import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from scanner_core.calibration import Calibration, CalibrationError
from scanner_core.crosscheck import estimate_led_and_clock, led_offset_spread
from scanner_core.geometry import Plane
from scanner_core.marker import find_markers
from scanner_core.pipeline import PipelineParams, camera_frames, frame_stripe, run_pass
from scanner_core.planecal import calibrate_plane
from scanner_core.types import MarkerObservation
from scanner_core.viewcal import calibrate_views, views_as_mirrors

SESSION_FORMAT = "flyscan-calibration-session"
SESSION_VERSION = 1


class SessionError(ValueError):
    """A session folder that cannot be read: the message names the file and the field."""


@dataclass
class Session:
    """What a calibration session gave: frames, the stage's positions, the robot's pass.

    ``led_images`` and ``sphere_images`` are called once each and yield (H, W) uint8 frames in
    the order of their positions; ``pass_devices`` returns a (camera, robot) pair.
    """

    width: int
    height: int
    fps: float
    sphere_radius_mm: float
    nominal: Calibration
    led_positions_b: np.ndarray
    led_images: Callable[[], Iterable[np.ndarray]]
    sphere_centres_b: np.ndarray
    sphere_images: Callable[[], Iterable[np.ndarray]]
    pass_devices: Callable[[], tuple] | None = None
    cell_name: str = ""


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
    views = calibrate_views(session.led_positions_b, led_px, session.width, session.height,
                            seed=seed)
    progress(f"views: {views.model}, {views.rms_px:.4f} px RMS "
             f"({views.outliers} observation(s) dropped)")
    mirrors = views_as_mirrors(views.mirror_planes, [m.columns for m in nominal.mirrors])
    camera = views.camera
    progress(f"light plane: the stripe on the sphere in {len(session.sphere_centres_b)} frames")
    stripes = observe_sphere(session.sphere_images(), nominal, params)
    plane = calibrate_plane(list(zip(stripes, session.sphere_centres_b)), camera,
                            session.sphere_radius_mm)
    plane_c = plane.plane_b.transformed(camera.rotation, -camera.rotation @ camera.origin)
    progress(f"light plane: {plane.points} points from {plane.frames} frames, "
             f"{plane.rms_mm * 1e3:.1f} um RMS; sphere centres {plane.centre_rms_mm * 1e3:.1f} um RMS")
    calibration = Calibration(camera, Plane(plane_c.normal, plane_c.offset), mirrors,
                              nominal.direct_columns, nominal.marker_offset_t.copy(),
                              nominal.clock_offset_s)
    clocks = None
    if session.pass_devices is not None:
        progress("clocks and LED offset: a pass of the robot")
        calibration, clocks = _led_and_clock(session, calibration, params)
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
    }
    report = _json_safe(report)
    return replace(calibration, provenance=report), report


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


def _led_and_clock(session: Session, calibration: Calibration,
                   params: PipelineParams) -> tuple[Calibration, dict]:
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
        spread = led_offset_spread(scan.tcp_times, marker_b, robot, offset)
    finally:
        camera.close()
        robot.disconnect()
    led_std = None if not np.isfinite(spread).all() else spread
    return (replace(calibration, marker_offset_t=led, clock_offset_s=offset,
                    marker_offset_std_mm=led_std),
            {"clock_offset_s": offset, "led_t_mm": led.tolist(), "rms_mm": rms,
             "led_std_t_mm": None if led_std is None else led_std.tolist(),
             "frames": int(len(scan.tcp_times))})


# ---------------------------------------------------------------------------------------------
# session folders


def write_session(folder, session: Session) -> None:
    """Write ``session`` as a folder (module docstring), its pass (if any) as a recording in
    ``pass/`` (raw frames: about 2.3 MB per 1920 x 1200 frame)."""
    import cv2

    folder = Path(folder)
    if folder.exists():
        raise SessionError(f"{folder} exists already")
    for kind in ("led", "sphere"):
        (folder / kind).mkdir(parents=True)
    meta = {"format": SESSION_FORMAT, "version": SESSION_VERSION,
            "image": {"width": session.width, "height": session.height, "fps": session.fps},
            "sphere_radius_mm": session.sphere_radius_mm, "cell": session.cell_name,
            "nominal": session.nominal.to_dict()}
    (folder / "session.json").write_text(json.dumps(meta, indent=1))
    for kind, positions, images in (("led", session.led_positions_b, session.led_images),
                                    ("sphere", session.sphere_centres_b, session.sphere_images)):
        with open(folder / f"{kind}.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["image", "x_mm", "y_mm", "z_mm"])
            for i, (p, img) in enumerate(zip(positions, images())):
                name = f"{i:06d}.png"
                if not cv2.imwrite(str(folder / kind / name), img):
                    raise OSError(f"could not write {folder / kind / name}")
                w.writerow([name] + [repr(float(v)) for v in p])
    if session.pass_devices is not None:
        _record_pass(folder / "pass", session)


def _record_pass(folder: Path, session: Session) -> None:
    """The session's pass as a recording: every frame, and the robot's samples it still holds."""
    from scanner_core.devices import CameraClosed
    from scanner_core.recording import ROBOT_SAMPLE_HZ, robot_samples
    from scanner_core.recording import PassRecorder

    camera, robot = session.pass_devices()
    camera.open()
    robot.connect()
    try:
        with PassRecorder(folder, width=session.width, height=session.height, fps=session.fps,
                          calibration=session.nominal,
                          notes="calibration pass (flyscan calibrate)") as recorder:
            while True:
                try:
                    recorder.add_frame(camera.grab(1.0))
                except CameraClosed:
                    break
            newest = robot.latest().t
            recorder.add_robot_poses(robot_samples(robot, newest - 10.0 + 1.0 / ROBOT_SAMPLE_HZ,
                                                    newest))
    finally:
        camera.close()
        robot.disconnect()


def load_session(folder) -> Session:
    """Read a session folder; SessionError naming the file and field that is wrong."""
    import cv2

    folder = Path(folder)
    meta_path = folder / "session.json"
    try:
        meta = json.loads(meta_path.read_text())
    except FileNotFoundError:
        raise SessionError(f"{meta_path} not found: not a calibration session folder") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SessionError(f"{meta_path} is not valid JSON: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format") != SESSION_FORMAT:
        raise SessionError(f"{meta_path}: `format` must be {SESSION_FORMAT!r}")
    if meta.get("version") != SESSION_VERSION:
        raise SessionError(f"{meta_path}: session version {meta.get('version')!r} is not one "
                           f"this flyscan reads ({SESSION_VERSION})")
    try:
        width, height = int(meta["image"]["width"]), int(meta["image"]["height"])
        fps = float(meta["image"]["fps"])
        radius = float(meta["sphere_radius_mm"])
        nominal = Calibration.from_dict(meta["nominal"])
    except (KeyError, TypeError, ValueError) as exc:
        raise SessionError(f"{meta_path}: missing or malformed field {exc}") from None
    if not radius > 0:
        raise SessionError(f"{meta_path}: `sphere_radius_mm` must be positive, got {radius}")

    def table(kind):
        path = folder / f"{kind}.csv"
        try:
            with open(path, newline="") as f:
                rows = list(csv.reader(f))
        except FileNotFoundError:
            raise SessionError(f"{path} not found") from None
        if not rows or rows[0] != ["image", "x_mm", "y_mm", "z_mm"]:
            raise SessionError(f"{path}: the header must be image,x_mm,y_mm,z_mm")
        try:
            names = [r[0] for r in rows[1:]]
            positions = np.array([[float(v) for v in r[1:4]] for r in rows[1:]]).reshape(-1, 3)
        except (ValueError, IndexError) as exc:
            raise SessionError(f"{path}: {exc}") from None
        if not np.isfinite(positions).all():
            raise SessionError(f"{path}: positions must be finite numbers")

        def images():
            for name in names:
                img = cv2.imread(str(folder / kind / name), cv2.IMREAD_UNCHANGED)
                if img is None or img.shape != (height, width) or img.dtype != np.uint8:
                    raise SessionError(f"{folder / kind / name}: not an 8-bit {width} x {height} "
                                       f"greyscale image")
                yield img
        return positions, images

    led, led_images = table("led")
    sphere, sphere_images = table("sphere")
    pass_devices = None
    if (folder / "pass").is_dir():
        from scanner_core.recording import load_recording
        from scanner_core.replay import ReplayCamera, ReplayRobot

        recording = load_recording(folder / "pass")

        def pass_devices():
            return ReplayCamera(recording), ReplayRobot(recording.robot_samples)
    try:
        nominal.check_image_size(width, height)
    except CalibrationError as exc:
        raise SessionError(f"{meta_path}: nominal calibration: {exc}") from None
    return Session(width, height, fps, radius, nominal, led, led_images, sphere, sphere_images,
                   pass_devices, str(meta.get("cell", "")))
