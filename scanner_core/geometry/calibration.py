"""What the scanner must know about its cell: the result of calibration.

The camera (intrinsics, lens distortion and the paper's T and O), the light plane in {C}
(Eq. 2), the two mirrors, which image columns hold which view, where the LED marker sits on the
gripper and the robot's clock against the camera's. Saved as one versioned JSON file (mm, unit
vectors, row-major matrices) that also records where it came from (``provenance``: the date,
the cell, the models fitted, their residuals and the number of observations), as
``flyscan calibrate`` writes it.

File versions: 1 (no ``version`` field: the camera an ideal pinhole, no clock offset) and 2.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from scanner_core.fileio import save_json_atomic
from scanner_core.geometry.model import (NO_DISTORTION, Mirror, PinholeCamera, Plane,
                                         distort_normalized)
from scanner_core.geometry.triangulation import MarkerViews, marker_views, reproject_marker

#: Rotation matrices read from files must be orthonormal to this tolerance.
ROTATION_TOL = 1e-6
#: The version this code writes, and the versions it reads.
CALIBRATION_VERSION = 2
#: A marker offset known no better than this (mm) is no calibration.
MAX_MARKER_STD_MM = 10.0
READABLE_VERSIONS = (1, 2)


class CalibrationError(ValueError):
    """A calibration file or dictionary is missing a field or holds impossible values."""


@dataclass(frozen=True)
class PlaneUncertainty:
    """How well a calibration knows its light plane: the covariance of the plane's three
    degrees of freedom about a point of it, in {B}.

    The plane moved by ``theta = (alpha, beta, delta)`` is ``(n + alpha a_1 + beta a_2) .
    (x - c) = delta``: its normal `n` tilted by `alpha` and `beta` rad along the two `axes_b`
    in it, and shifted by `delta` mm along `n` at `centre_b`.

    Attributes
    ----------
    centre_b : (3,) float64
        `c`, mm in {B}: a point of the plane (the calibration's stripe points' centroid).
    axes_b : (2, 3) float64
        `a_1`, `a_2`: orthonormal, in the plane.
    covariance : (3, 3) float64
        Of ``(alpha, beta, delta)``: rad^2, rad mm, mm^2.
    """

    centre_b: np.ndarray
    axes_b: np.ndarray
    covariance: np.ndarray

    def to_dict(self) -> dict:
        return {"centre_mm": np.asarray(self.centre_b).tolist(),
                "axes": np.asarray(self.axes_b).tolist(),
                "covariance": np.asarray(self.covariance).tolist()}

    @classmethod
    def from_dict(cls, data: dict) -> "PlaneUncertainty":
        """From `to_dict`'s form; ValueError naming what is wrong."""
        if not isinstance(data, dict):
            raise ValueError(f"a plane's uncertainty must be an object, got {type(data).__name__}")
        out = {}
        for key, shape in (("centre_mm", (3,)), ("axes", (2, 3)), ("covariance", (3, 3))):
            try:
                value = np.asarray(data[key], dtype=np.float64)
            except (KeyError, TypeError, ValueError):
                raise ValueError(f"`{key}` must be a {shape} array of numbers") from None
            if value.shape != shape or not np.isfinite(value).all():
                raise ValueError(f"`{key}` must be a {shape} array of finite numbers, got "
                                 f"shape {value.shape}")
            out[key] = value
        axes, cov = out["axes"], out["covariance"]
        if not np.allclose(axes @ axes.T, np.eye(2), atol=1e-6):
            raise ValueError("`axes` must be two orthonormal vectors")
        scale = max(float(np.abs(cov).max()), 1e-300)
        if (not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-9 * scale)
                or np.linalg.eigvalsh(cov).min() < -1e-9 * scale):
            raise ValueError("`covariance` must be symmetric and positive semi-definite")
        return cls(out["centre_mm"], axes, cov)



@dataclass(frozen=True)
class Calibration:
    """Cell geometry as the scanner knows it.

    Attributes
    ----------
    camera : PinholeCamera
    light_plane_c : Plane
        Light plane in {C}, mm.
    mirrors : tuple of Mirror
        Left and right mirrors in {B}, each with its strip of columns.
    direct_columns : (int, int)
        Columns [c0, c1) of the direct view.
    marker_offset_t : (3,) float64
        LED marker position in {T}, mm.
    clock_offset_s : float
        The robot's clock minus the camera's, s: where the cross-check starts its estimate.
    provenance : dict
        How the calibration was made (``flyscan calibrate``): ``date``, ``cell``,
        ``observations``, ``models`` and their ``residuals``. Empty for a hand-made one.
    marker_offset_std_mm : (3,) float64 or None
        Standard deviation of `marker_offset_t` along the {T} axes, mm, as the calibration
        measured it (``scanner_core.pipeline.crosscheck.estimate_led_and_clock``). Every profile of a
        scan shares its marker offset's error, so a pose's translation carries it whole
        (``scanner_core.pose.registration.scan_pose``). None: not measured (a hand-made or a true cell's
        calibration), taken as 0.
    """

    camera: PinholeCamera
    light_plane_c: Plane
    mirrors: tuple[Mirror, ...]
    direct_columns: tuple[int, int]
    marker_offset_t: np.ndarray
    clock_offset_s: float = 0.0
    provenance: dict = field(default_factory=dict, compare=False, repr=False)
    marker_offset_std_mm: np.ndarray | None = None
    light_plane_uncertainty: PlaneUncertainty | None = None

    @property
    def strips(self) -> tuple[tuple[int, int], ...]:
        """Column strips of the direct view then each mirror view."""
        return (self.direct_columns,) + tuple(m.columns for m in self.mirrors)

    @cached_property
    def marker_views(self) -> MarkerViews:
        """The direct and mirror views as cameras in {B}: computed once, used every frame."""
        return marker_views(self.camera, self.mirrors)

    @property
    def light_plane_b(self) -> Plane:
        """The light plane in {B} (through Eq. 3)."""
        cam = self.camera
        return self.light_plane_c.transformed(cam.rotation.T, cam.origin)

    def check_image_size(self, width: int, height: int) -> None:
        """CalibrationError when the calibration was made for images of another size."""
        cam = self.camera
        if (cam.width, cam.height) != (int(width), int(height)):
            raise CalibrationError(f"the calibration is for {cam.width} x {cam.height} images, "
                                   f"the camera gives {int(width)} x {int(height)}")

    def to_dict(self) -> dict:
        cam = self.camera
        return {
            "version": CALIBRATION_VERSION,
            "camera": {
                "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                "width": cam.width, "height": cam.height,
                "rotation": cam.rotation.tolist(), "origin_mm": cam.origin.tolist(),
                "distortion": list(cam.distortion),
            },
            "light_plane_c": {"normal": self.light_plane_c.normal.tolist(),
                              "offset_mm": self.light_plane_c.offset},
            "mirrors": [{"normal": m.plane.normal.tolist(), "offset_mm": m.plane.offset,
                         "columns": list(m.columns)} for m in self.mirrors],
            "direct_columns": list(self.direct_columns),
            "marker_offset_t_mm": self.marker_offset_t.tolist(),
            "clock_offset_s": self.clock_offset_s,
            "provenance": self.provenance,
            **({} if self.marker_offset_std_mm is None
               else {"marker_offset_std_mm": np.asarray(self.marker_offset_std_mm).tolist()}),
            **({} if self.light_plane_uncertainty is None
               else {"light_plane_uncertainty_b": self.light_plane_uncertainty.to_dict()}),
        }

    @classmethod
    def from_dict(cls, data: dict) -> "Calibration":
        """Build from the JSON form (`to_dict`); a missing or malformed field is named."""
        if not isinstance(data, dict):
            raise CalibrationError(f"a calibration must be a JSON object, got {_short(data)}")
        version = data.get("version", 1)
        if isinstance(version, bool) or version not in READABLE_VERSIONS:
            raise CalibrationError(f"calibration file version {_short(version)} is not one this "
                                   f"flyscan reads ({', '.join(map(str, READABLE_VERSIONS))})")
        c = _field(data, "camera")
        distortion = NO_DISTORTION
        if version >= 2:
            distortion = tuple(float(v) for v in _array(c, "camera", "distortion", (5,)))
        camera = PinholeCamera(
            fx=_number(c, "camera", "fx"), fy=_number(c, "camera", "fy"),
            cx=_number(c, "camera", "cx"), cy=_number(c, "camera", "cy"),
            width=_number(c, "camera", "width", int), height=_number(c, "camera", "height", int),
            rotation=_array(c, "camera", "rotation", (3, 3)),
            origin=_array(c, "camera", "origin_mm", (3,)),
            distortion=distortion,
        )
        lp = _field(data, "light_plane_c")
        plane = Plane(_array(lp, "light_plane_c", "normal", (3,)),
                      _number(lp, "light_plane_c", "offset_mm"))
        mirror_list = _field(data, "mirrors")
        if not isinstance(mirror_list, list):
            raise CalibrationError(f"calibration field `mirrors` must be a list, got {_short(mirror_list)}")
        mirrors = []
        for i, m in enumerate(mirror_list):
            where = f"mirrors[{i}]"
            mirrors.append(Mirror(
                Plane(_array(m, where, "normal", (3,)), _number(m, where, "offset_mm")),
                _columns(m, where)))
        direct = _columns(data, "", "direct_columns")
        marker = _array(data, "", "marker_offset_t_mm", (3,))
        clock = _number(data, "", "clock_offset_s") if version >= 2 else 0.0
        provenance = data.get("provenance", {}) if version >= 2 else {}
        if not isinstance(provenance, dict):
            raise CalibrationError(f"calibration field `provenance` must be a JSON object, "
                                   f"got {_short(provenance)}")
        _check(camera, plane, tuple(mirrors), direct, marker)
        if not np.isfinite(clock):
            raise CalibrationError(f"`clock_offset_s` must be finite, got {clock}")
        marker_std = None
        if data.get("marker_offset_std_mm") is not None:
            marker_std = _array(data, "", "marker_offset_std_mm", (3,))
            if not (np.all(marker_std >= 0) and np.all(marker_std <= MAX_MARKER_STD_MM)):
                raise CalibrationError(f"`marker_offset_std_mm` must be 3 numbers in [0, "
                                       f"{MAX_MARKER_STD_MM:g}] mm, got {marker_std.tolist()}")
        plane_std = None
        if data.get("light_plane_uncertainty_b") is not None:
            try:
                plane_std = PlaneUncertainty.from_dict(data["light_plane_uncertainty_b"])
            except ValueError as exc:
                raise CalibrationError(f"calibration field `light_plane_uncertainty_b`: {exc}") \
                    from None
        return cls(camera, plane, tuple(mirrors), direct, marker, clock, provenance, marker_std,
                   plane_std)


def _columns(obj, where: str, key: str = "columns") -> tuple[int, int]:
    c0, c1 = _array(obj, where, key, (2,))
    if c0 != int(c0) or c1 != int(c1):
        name = f"{where}.{key}" if where else key
        raise CalibrationError(f"calibration field `{name}` must be two whole column numbers, "
                               f"got {[c0, c1]}")
    return int(c0), int(c1)


def _short(value) -> str:
    text = json.dumps(value) if isinstance(value, (int, float, str, list, dict, type(None))) \
        else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _lookup(obj, where: str, key: str):
    """``obj[key]``, or a CalibrationError naming ``where.key``."""
    name = f"{where}.{key}" if where else key
    if not isinstance(obj, dict):
        raise CalibrationError(f"calibration field `{where or 'top level'}` must be a JSON "
                               f"object, got {_short(obj)}")
    if key not in obj:
        raise CalibrationError(f"calibration field `{name}` is missing")
    return obj[key], name


def _field(obj, key: str):
    return _lookup(obj, "", key)[0]


def _number(obj, where: str, key: str, kind=float):
    value, name = _lookup(obj, where, key)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise CalibrationError(f"calibration field `{name}` must be a number, got {_short(value)}")
    if kind is int and value != int(value):
        raise CalibrationError(f"calibration field `{name}` must be a whole number, got {value}")
    return kind(value)


def _array(obj, where: str, key: str, shape: tuple[int, ...]) -> np.ndarray:
    value, name = _lookup(obj, where, key)
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        array = None
    if array is None or array.shape != shape:
        form = " x ".join(map(str, shape))
        raise CalibrationError(f"calibration field `{name}` must be {form} numbers, "
                               f"got {_short(value)}")
    return array


def _check(camera, plane, mirrors, direct, marker) -> None:
    numbers = {"camera.fx": camera.fx, "camera.fy": camera.fy, "camera.cx": camera.cx,
               "camera.cy": camera.cy, "camera.rotation": camera.rotation,
               "camera.origin_mm": camera.origin, "camera.distortion": np.array(camera.distortion),
               "light_plane_c.normal": plane.normal,
               "light_plane_c.offset_mm": plane.offset, "marker_offset_t_mm": marker}
    for i, m in enumerate(mirrors):
        numbers[f"mirrors[{i}].normal"] = m.plane.normal
        numbers[f"mirrors[{i}].offset_mm"] = m.plane.offset
    for name, value in numbers.items():
        if not np.all(np.isfinite(value)):
            raise CalibrationError(f"`{name}` must be finite, got {np.asarray(value).tolist()}")
    r = camera.rotation
    if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=ROTATION_TOL) \
            or np.linalg.det(r) < 0:
        raise CalibrationError("camera.rotation must be a proper 3x3 rotation matrix")
    for name, vec in [("light_plane_c.normal", plane.normal)] + [
            (f"mirrors[{i}].normal", m.plane.normal) for i, m in enumerate(mirrors)]:
        if vec.shape != (3,) or abs(np.linalg.norm(vec) - 1.0) > ROTATION_TOL:
            raise CalibrationError(f"`{name}` must be a unit 3-vector, got {vec.tolist()}")
    if camera.origin.shape != (3,) or marker.shape != (3,):
        raise CalibrationError("camera.origin_mm and marker_offset_t_mm must be 3-vectors")
    if min(camera.fx, camera.fy) <= 0 or camera.width <= 0 or camera.height <= 0:
        raise CalibrationError("camera focal lengths and image size must be positive")
    for name, (c0, c1) in [("direct_columns", direct)] + [
            (f"mirrors[{i}].columns", m.columns) for i, m in enumerate(mirrors)]:
        if not 0 <= c0 < c1 <= camera.width:
            raise CalibrationError(f"`{name}` must satisfy 0 <= c0 < c1 <= {camera.width}, got {(c0, c1)}")


def load_calibration(path) -> Calibration:
    """Read a calibration JSON file (the ``calibration`` entry of a cell file also works)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise CalibrationError(f"calibration file not found: {path}") from None
    except OSError as exc:
        raise CalibrationError(f"cannot read calibration file {path}: {exc.strerror}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"calibration file {path} is not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"calibration file {path} must hold a JSON object")
    if "calibration" in data:
        data = data["calibration"]
    return Calibration.from_dict(data)


def save_calibration(path, calibration: Calibration) -> None:
    save_json_atomic(path, calibration.to_dict())


#: The bounds of a calibration a real cell can have (`check_cell_geometry`): square pixels
#: within this ratio, a lens whose distortion moves an image corner by less than this share of
#: its distance from the centre, the camera this far from the light plane at the image centre
#: (mm), clocks this far apart (s: a robot's clock counts from its controller's start, a
#: camera's from its own) and an LED this far from the TCP (mm).
MAX_PIXEL_ASPECT = 1.1
MAX_CORNER_DISTORTION = 0.3
SHEET_DISTANCE_MM = (50.0, 3000.0)
MAX_CLOCK_OFFSET_S = 1e8
MAX_MARKER_OFFSET_MM = 500.0
#: The inspection volume about the sheet's centre that the views are checked on, mm
#: (``scanner_core.cad.INSPECTION_VOLUME_MM``), and its samples per axis.
CHECK_VOLUME_MM = (150.0, 150.0, 100.0)
CHECK_SAMPLES = 7


def check_cell_geometry(calibration: Calibration) -> None:
    """CalibrationError unless `calibration`, taken whole, describes a cell the scanner can
    work in (what its fields' own checks cannot see):

    - the pixels square within ``MAX_PIXEL_ASPECT`` and the principal point in the image;
    - the lens: distortion moving each image corner by less than ``MAX_CORNER_DISTORTION`` of
      its distance from the centre, and the distorted radius growing with the radius out to
      the corners (a model that folds the image back cannot be inverted);
    - the light plane in front of the camera, ``SHEET_DISTANCE_MM`` away along the ray
      through the principal point: the sheet's centre `S`;
    - the marker's views: some point of the inspection volume about `S` lies in every view's
      strip (the direct view and each mirror's), so that a marker there is triangulated;
    - the clock offset within ``MAX_CLOCK_OFFSET_S`` and the marker offset within
      ``MAX_MARKER_OFFSET_MM`` of the TCP.
    """
    cam = calibration.camera
    aspect = cam.fx / cam.fy
    if not 1.0 / MAX_PIXEL_ASPECT <= aspect <= MAX_PIXEL_ASPECT:
        raise CalibrationError(f"camera fx / fy = {aspect:.4g}: a real camera's pixels are square "
                               f"within {MAX_PIXEL_ASPECT - 1:.0%}")
    if not (0.0 <= cam.cx < cam.width and 0.0 <= cam.cy < cam.height):
        raise CalibrationError(f"the principal point ({cam.cx:g}, {cam.cy:g}) px lies outside "
                               f"the {cam.width} x {cam.height} image")
    corners = (np.array([[0.0, 0.0], [cam.width, 0.0], [0.0, cam.height],
                         [cam.width, cam.height]]) - [cam.cx, cam.cy]) / [cam.fx, cam.fy]
    steps = np.linspace(0.0, 1.0, 50)[:, None, None] * corners[None]       # (50, 4, 2)
    distorted = distort_normalized(steps.reshape(-1, 2), cam.distortion).reshape(steps.shape)
    radius, radius_d = np.linalg.norm(steps, axis=2), np.linalg.norm(distorted, axis=2)
    moved = np.abs(radius_d[-1] - radius[-1]) / np.maximum(radius[-1], 1e-12)
    if not (np.all(moved < MAX_CORNER_DISTORTION) and np.all(np.diff(radius_d, axis=0) > 0)):
        raise CalibrationError(
            f"camera.distortion {list(np.round(cam.distortion, 6))} moves the image corners by "
            f"{np.max(moved):.0%} of their radius, or folds the image: no real lens does (at "
            f"most {MAX_CORNER_DISTORTION:.0%})")
    plane = calibration.light_plane_c
    along = float(plane.normal[2])
    depth = plane.offset / along if abs(along) > 1e-9 else np.inf
    if not SHEET_DISTANCE_MM[0] <= depth <= SHEET_DISTANCE_MM[1]:
        raise CalibrationError(
            f"the light plane meets the ray through the principal point {depth:.4g} mm in front "
            f"of the camera; a cell's sheet is {SHEET_DISTANCE_MM[0]:g} to "
            f"{SHEET_DISTANCE_MM[1]:g} mm away")
    centre = cam.to_base(np.array([[0.0, 0.0, depth]]))[0]
    axes = [np.linspace(-h / 2, h / 2, CHECK_SAMPLES) for h in CHECK_VOLUME_MM]
    grid = centre + np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    if not _in_every_view(calibration, grid).any():
        raise CalibrationError(
            "no point of the inspection volume about the sheet's centre lies in every view "
            "(the direct view and each mirror's strip): the marker could not be triangulated; "
            "are the camera's rotation and origin and the mirrors this cell's?")
    if not abs(calibration.clock_offset_s) <= MAX_CLOCK_OFFSET_S:
        raise CalibrationError(f"clock_offset_s {calibration.clock_offset_s:g} s: the robot's and "
                               f"the camera's clocks are within {MAX_CLOCK_OFFSET_S:g} s (three years)")
    offset = float(np.linalg.norm(calibration.marker_offset_t))
    if not offset <= MAX_MARKER_OFFSET_MM:
        raise CalibrationError(f"marker_offset_t_mm lies {offset:.4g} mm from the TCP: a gripper's "
                               f"LED is within {MAX_MARKER_OFFSET_MM:g} mm (given in m?)")


def check_marker_track(calibration: Calibration, geometry) -> None:
    """CalibrationError unless the LED, carried along the cell's pass (``geometry``, a
    ``scanner_core.calibration.plan.PlanGeometry``: the TCP at x_B = 0 and the pass's height, from its
    start to its end, turned as in a pass, the LED at the calibration's ``marker_offset_t``),
    lies in every view's strip somewhere along it: where it does not, no pass is ever
    triangulated (a camera rotation or origin of another cell)."""
    track_y = np.linspace(geometry.pass_start_y_mm, geometry.pass_end_y_mm, 81)
    tcp = np.column_stack([np.zeros_like(track_y), track_y,
                           np.full_like(track_y, geometry.pass_height_mm)])
    led = tcp + np.asarray(geometry.tcp_rotation_b) @ np.asarray(calibration.marker_offset_t)
    if not _in_every_view(calibration, led).any():
        raise CalibrationError(
            f"along the cell's pass (y_B {geometry.pass_start_y_mm:g} to "
            f"{geometry.pass_end_y_mm:g} mm at {geometry.pass_height_mm:g} mm) the LED never lies "
            f"in every view: no pass would be triangulated; are the camera's rotation and origin "
            f"and the mirrors this cell's?")


def _in_every_view(calibration: Calibration, points_b) -> np.ndarray:
    """(N,) bool: which of the (N, 3) points (mm in {B}) project inside every view's strip of
    columns and the image's rows (the direct view and each mirror's)."""
    pixels = reproject_marker(points_b, calibration.camera, calibration.mirrors)  # (N, V, 2)
    seen = np.ones(len(pixels), bool)
    for v, (c0, c1) in enumerate(calibration.strips):
        u, w = pixels[:, v, 0], pixels[:, v, 1]
        seen &= (u >= c0) & (u < c1) & (w >= 0) & (w < calibration.camera.height)
    return seen
