"""What the scanner must know about its cell: the result of calibration.

The camera (intrinsics and the paper's T and O), the light plane in {C} (Eq. 2), the two
mirrors, which image columns hold which view, and where the LED marker sits on the gripper.
Saved as JSON (mm, unit vectors, row-major matrices).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from scanner_core.fileio import save_json_atomic
from scanner_core.geometry import MarkerViews, Mirror, PinholeCamera, Plane, marker_views

#: Rotation matrices read from files must be orthonormal to this tolerance.
ROTATION_TOL = 1e-6


class CalibrationError(ValueError):
    """A calibration file or dictionary is missing a field or holds impossible values."""


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
    """

    camera: PinholeCamera
    light_plane_c: Plane
    mirrors: tuple[Mirror, ...]
    direct_columns: tuple[int, int]
    marker_offset_t: np.ndarray

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

    def to_dict(self) -> dict:
        cam = self.camera
        return {
            "camera": {
                "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                "width": cam.width, "height": cam.height,
                "rotation": cam.rotation.tolist(), "origin_mm": cam.origin.tolist(),
            },
            "light_plane_c": {"normal": self.light_plane_c.normal.tolist(),
                              "offset_mm": self.light_plane_c.offset},
            "mirrors": [{"normal": m.plane.normal.tolist(), "offset_mm": m.plane.offset,
                         "columns": list(m.columns)} for m in self.mirrors],
            "direct_columns": list(self.direct_columns),
            "marker_offset_t_mm": self.marker_offset_t.tolist(),
        }

    @classmethod
    def from_dict(cls, data: dict) -> "Calibration":
        try:
            c = data["camera"]
            rotation = np.array(c["rotation"], dtype=np.float64)
            camera = PinholeCamera(
                fx=float(c["fx"]), fy=float(c["fy"]), cx=float(c["cx"]), cy=float(c["cy"]),
                width=int(c["width"]), height=int(c["height"]),
                rotation=rotation, origin=np.array(c["origin_mm"], dtype=np.float64),
            )
            lp = data["light_plane_c"]
            plane = Plane(np.array(lp["normal"], dtype=np.float64), float(lp["offset_mm"]))
            mirrors = tuple(
                Mirror(Plane(np.array(m["normal"], dtype=np.float64), float(m["offset_mm"])),
                       (int(m["columns"][0]), int(m["columns"][1])))
                for m in data["mirrors"]
            )
            direct = (int(data["direct_columns"][0]), int(data["direct_columns"][1]))
            marker = np.array(data["marker_offset_t_mm"], dtype=np.float64)
        except (KeyError, TypeError, IndexError, ValueError) as exc:
            raise CalibrationError(f"calibration is missing or has a malformed field: {exc!r}") from exc
        _check(camera, plane, mirrors, direct, marker)
        return cls(camera, plane, mirrors, direct, marker)


def _check(camera, plane, mirrors, direct, marker) -> None:
    numbers = {"camera.fx": camera.fx, "camera.fy": camera.fy, "camera.cx": camera.cx,
               "camera.cy": camera.cy, "camera.rotation": camera.rotation,
               "camera.origin_mm": camera.origin, "light_plane_c.normal": plane.normal,
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
