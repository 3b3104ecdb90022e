"""The reference cell: the numbers of a plausible real cell, in one settings file.

``data/reference_cell.json`` is read by the simulator, the service and the tests. It is
written by :func:`design_reference_cell` from the choices of docs/simulator.md ("the reference
cell"); what those leave open (mirror planes, the marker offset, the pass) is chosen here and
recorded in the file. :func:`perturb` makes the repeatable departures of ``--perturb-seed``.

Frames: {B} robot base, the laser sheet is the plane y = 0 and the robot passes along +y;
z is up. {T} has z pointing down (the tool points down), so the part hangs along +z_T.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from scanner_core.geometry.calibration import Calibration
from scanner_core.fileio import save_json_atomic
from scanner_core.geometry import (Mirror, PinholeCamera, Plane, apply_transform,
                                   reflection_matrix, reproject_marker, unit)
from simulator.effects import CellEffects, parse_effects, realistic_cell
from simulator.imaging import ImageModel

REFERENCE_CELL = Path(__file__).resolve().parent / "data" / "reference_cell.json"

#: Perturbation sizes for ``--perturb-seed`` (one standard deviation): mm and degrees.
PERTURB_CAMERA_MM, PERTURB_CAMERA_DEG = 1.0, 0.3
PERTURB_PLANE_MM, PERTURB_PLANE_DEG = 0.5, 0.2
PERTURB_MIRROR_MM, PERTURB_MIRROR_DEG = 0.5, 0.2


@dataclass(frozen=True)
class PassProfile:
    """The robot's pass through the sheet (see ``simulator.motion``).

    The TCP runs along +y of {B} from ``start_y_mm`` to ``end_y_mm`` at ``height_mm``; its
    speed ramps linearly from ``(1 - accel_fraction)`` to ``(1 + accel_fraction)`` times the
    nominal speed (``speed_shape`` "ramp"), or up to that at the pass's middle and down again
    ("peak": symmetric in time, the calibration pass's), and the path bows sideways by
    ``bow_mm`` and rises by ``rise_mm``.
    """

    speed_mm_s: float = 200.0
    fps: float = 162.0
    start_y_mm: float = -130.0
    end_y_mm: float = 130.0
    height_mm: float = 50.0
    accel_fraction: float = 0.25
    bow_mm: float = 3.0
    rise_mm: float = 1.5
    lead_in_s: float = 0.3
    lead_out_s: float = 0.3
    speed_shape: str = "ramp"

    def __post_init__(self):
        if self.speed_shape not in SPEED_SHAPES:
            raise ValueError(f"PassProfile.speed_shape must be one of {SPEED_SHAPES}, got "
                             f"{self.speed_shape!r}")


#: How the speed changes along a pass (``PassProfile.speed_shape``).
SPEED_SHAPES = ("ramp", "peak")
#: The calibration pass's: up to the middle and down again. With the speed ramping up all
#: the way, a robot clock that drifts along the pass (10-44 ppm in the realistic cells) reads
#: as a constant clock error of about ``v / a`` times the drift, and the LED's offset takes
#: the other side: 3-19 um along the pass (``benchmarks.led_clock``).
CALIBRATION_SPEED_SHAPE = "peak"


#: The paper's two configurations (section II and V).
PASS_PRESETS = {
    "default": PassProfile(),
    "fast": PassProfile(speed_mm_s=1000.0, fps=162.0),
    "slow": PassProfile(speed_mm_s=50.0, fps=16.0),
}


@dataclass(frozen=True)
class Cell:
    """The simulated cell: the scanner's true geometry plus what only the simulator knows.

    Attributes
    ----------
    calibration : Calibration
        The cell's true geometry, in the form calibration would estimate it.
    laser_origin_b : (3,) float64
        Laser source in {B}, mm (in the light plane).
    laser_fan_half_angle_deg : float
    gripper_rotation_b : (3, 3) float64
        Rotation of {T} in {B} during the pass (fixed: the paper's assumption).
    inspection_volume_mm : (3,) float
    image_model : ImageModel
    pass_profile : PassProfile
    sphere_radius_mm : float
        Calibration sphere.
    stage_accuracy_mm : float
    effects : CellEffects
        What a real cell does besides (``simulator.effects``): all off in the reference cell.
    """

    calibration: Calibration
    laser_origin_b: np.ndarray
    laser_fan_half_angle_deg: float
    gripper_rotation_b: np.ndarray
    inspection_volume_mm: tuple[float, float, float]
    image_model: ImageModel = field(default_factory=ImageModel)
    pass_profile: PassProfile = field(default_factory=PassProfile)
    sphere_radius_mm: float = 28.625
    stage_accuracy_mm: float = 0.005
    effects: CellEffects = field(default_factory=CellEffects)

    @cached_property
    def light_plane_b(self) -> Plane:
        return self.calibration.light_plane_b

    def to_dict(self) -> dict:
        return {
            "calibration": self.calibration.to_dict(),
            "laser_origin_b_mm": self.laser_origin_b.tolist(),
            "laser_fan_half_angle_deg": self.laser_fan_half_angle_deg,
            "gripper_rotation_b": self.gripper_rotation_b.tolist(),
            "inspection_volume_mm": list(self.inspection_volume_mm),
            "image_model": asdict(self.image_model),
            "pass_profile": asdict(self.pass_profile),
            "sphere_radius_mm": self.sphere_radius_mm,
            "stage_accuracy_mm": self.stage_accuracy_mm,
            "effects": self.effects.to_dict(),
        }

    @classmethod
    def from_dict(cls, data: dict) -> "Cell":
        return cls(
            calibration=Calibration.from_dict(data["calibration"]),
            laser_origin_b=np.array(data["laser_origin_b_mm"], dtype=np.float64),
            laser_fan_half_angle_deg=float(data["laser_fan_half_angle_deg"]),
            gripper_rotation_b=np.array(data["gripper_rotation_b"], dtype=np.float64),
            inspection_volume_mm=tuple(data["inspection_volume_mm"]),
            image_model=ImageModel(**data["image_model"]),
            pass_profile=PassProfile(**data["pass_profile"]),
            sphere_radius_mm=float(data["sphere_radius_mm"]),
            stage_accuracy_mm=float(data["stage_accuracy_mm"]),
            effects=CellEffects.from_dict(data.get("effects", {})),
        )

    def with_pass(self, **changes) -> "Cell":
        """The cell with its pass changed. A slower pass keeps at least the lead-out
        distance of this one (``lead_out_s`` scaled, unless given): the marker must leave
        the views for the pass to end, and the paper's slow pass (50 mm/s) carried it 15 mm
        in the default 0.3 s, still in view: every such pass failed, "camera stream
        ended"."""
        profile = replace(self.pass_profile, **changes)
        if "lead_out_s" not in changes and profile.speed_mm_s < self.pass_profile.speed_mm_s:
            reach_mm = self.pass_profile.lead_out_s * self.pass_profile.speed_mm_s
            profile = replace(profile, lead_out_s=reach_mm / profile.speed_mm_s)
        return replace(self, pass_profile=profile)


def load_cell(path=REFERENCE_CELL, *, perturb_seed: int | None = None) -> Cell:
    """The reference cell from its settings file, optionally perturbed."""
    cell = Cell.from_dict(json.loads(Path(path).read_text()))
    return cell if perturb_seed is None else perturb(cell, perturb_seed)


def save_cell(path, cell: Cell) -> None:
    save_json_atomic(path, cell.to_dict())


def look_at(origin, target, x_hint) -> np.ndarray:
    """Camera rotation T (rows = {C} axes in {B}) looking from ``origin`` at ``target`` with
    image columns along ``x_hint``."""
    z = unit(np.asarray(target, float) - np.asarray(origin, float))
    x = unit(np.asarray(x_hint, float) - (np.asarray(x_hint, float) @ z) * z)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def design_mirror(camera: PinholeCamera, target_b, pixel, guess_distance_mm: float) -> Plane:
    """The plane mirror, with its normal perpendicular to the pass direction (y), in which
    the camera sees ``target_b`` at ``pixel``.

    A normal without a y component keeps the pass direction unchanged by the reflection, so
    the marker's track runs along the mirror view's rows as it does in the direct view.
    The solution is started from the mirror met ``guess_distance_mm`` along the pixel's ray.
    """
    from scipy.optimize import least_squares  # only when designing a cell: a slow import

    target_b = np.asarray(target_b, dtype=np.float64)
    ray = camera.rays([pixel])[0]
    hit = camera.origin + guess_distance_mm * ray
    n0 = unit(unit(target_b - hit) - ray)

    def residual(params):
        theta, offset = params
        n = np.array([np.cos(theta), 0.0, np.sin(theta)])
        image = apply_transform(reflection_matrix(n, offset), target_b)
        return camera.project(image)[0] - np.asarray(pixel, dtype=np.float64)

    theta0 = np.arctan2(n0[2], n0[0])
    sol = least_squares(residual, [theta0, float(n0 @ hit)], x_scale=[0.1, 10.0])
    if not sol.success or np.max(np.abs(sol.fun)) > 1e-6:
        raise RuntimeError(f"no mirror puts the marker at pixel {pixel}: {sol.message}")
    theta, offset = sol.x
    return Plane(np.array([np.cos(theta), 0.0, np.sin(theta)]), float(offset))


def design_reference_cell() -> Cell:
    """The reference cell (docs/simulator.md), with the choices it leaves open made here."""
    width, height = 1920, 1200
    focal_px = 16.0 / 5.86e-3  # 16 mm lens, 5.86 um pixels
    standoff, triangulation_deg = 450.0, 30.0
    a = np.radians(triangulation_deg)
    # The camera sits below, in the y-z plane, viewing the sheet at 30 degrees to it.
    origin = standoff * np.array([0.0, -np.sin(a), -np.cos(a)])
    rotation = look_at(origin, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    camera = PinholeCamera(focal_px, focal_px, (width - 1) / 2.0, (height - 1) / 2.0,
                           width, height, rotation, origin)
    laser_origin = np.array([0.0, 0.0, -350.0])
    light_plane_b = Plane(np.array([0.0, 1.0, 0.0]), 0.0)
    light_plane_c = light_plane_b.transformed(rotation, -rotation @ origin)
    strip = 384
    direct = (strip, width - strip)
    # {T}: x_T = x_B, y_T = -y_B, z_T = -z_B (tool pointing down).
    gripper_rotation = np.diag([1.0, -1.0, -1.0])
    # The LED sits beside the part's footprint (|x| <= 75 mm), above the TCP, and ahead of it
    # along the pass so that it stays in the image from the first profile to the last.
    marker_b_offset = np.array([88.0, 60.0, 30.0])
    pass_profile = PassProfile()
    marker_mid = np.array([0.0, 0.0, pass_profile.height_mm]) + marker_b_offset
    mirrors = (
        Mirror(design_mirror(camera, marker_mid, (strip / 2.0, 640.0), 600.0), (0, strip)),
        Mirror(design_mirror(camera, marker_mid, (width - strip / 2.0, 640.0), 520.0),
               (width - strip, width)),
    )
    calibration = Calibration(camera, light_plane_c, mirrors, direct,
                              gripper_rotation.T @ marker_b_offset)
    return Cell(calibration, laser_origin, 30.0, gripper_rotation, (150.0, 150.0, 100.0),
                ImageModel(), pass_profile)


def _small_rotation(rng: np.random.Generator, sigma_deg: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(sigma_deg) * rng.standard_normal(3)).as_matrix()


def perturb(cell: Cell, seed: int) -> Cell:
    """The cell's true geometry departed from the reference by a repeatable random amount.

    Camera pose, light plane and mirrors move by millimetres and tenths of degrees (the
    PERTURB_* constants, one sigma); the same seed always gives the same cell.
    """
    rng = np.random.default_rng([0x5CA7, seed])
    cal = cell.calibration
    cam = cal.camera
    cam_rot = _small_rotation(rng, PERTURB_CAMERA_DEG) @ cam.rotation
    cam_origin = cam.origin + PERTURB_CAMERA_MM * rng.standard_normal(3)
    camera = replace(cam, rotation=cam_rot, origin=cam_origin)
    # The laser turns about its own source, and shifts a little.
    plane_b = cell.light_plane_b
    normal_b = _small_rotation(rng, PERTURB_PLANE_DEG) @ plane_b.normal
    laser = cell.laser_origin_b + PERTURB_PLANE_MM * rng.standard_normal(3)
    plane_b = Plane.from_point_normal(laser, normal_b)
    light_plane_c = plane_b.transformed(cam_rot, -cam_rot @ cam_origin)
    mirrors = []
    for m in cal.mirrors:
        n = _small_rotation(rng, PERTURB_MIRROR_DEG) @ m.plane.normal
        mirrors.append(Mirror(Plane(unit(n), m.plane.offset + PERTURB_MIRROR_MM * rng.standard_normal()),
                              m.columns))
    calibration = replace(cal, camera=camera, light_plane_c=light_plane_c, mirrors=tuple(mirrors))
    return replace(cell, calibration=calibration, laser_origin_b=laser)


def marker_pixels(cell: Cell, tcp_b) -> np.ndarray:
    """Marker pixels in the three views for TCP positions (N, 3) in {B}: (N, 3, 2)."""
    cal = cell.calibration
    tcp_b = np.atleast_2d(np.asarray(tcp_b, dtype=np.float64))
    led = tcp_b + cell.gripper_rotation_b @ cal.marker_offset_t
    return reproject_marker(led, cal.camera, cal.mirrors)


if __name__ == "__main__":  # python -m simulator.cell: rewrite the reference cell file
    REFERENCE_CELL.parent.mkdir(parents=True, exist_ok=True)
    save_cell(REFERENCE_CELL, design_reference_cell())
    print(f"wrote {REFERENCE_CELL}")


def cell_with_effects(perturb_seed: int | None = None, effects_text: str | None = None):
    """The simulated cell of ``--perturb-seed`` and ``--effects`` (the CLI and the service's
    simulated mode): the reference cell, perturbed, with the real cell's effects asked for.
    ValueError naming an unknown effect."""
    effects = parse_effects(effects_text)
    cell = load_cell(perturb_seed=perturb_seed)
    return realistic_cell(cell, effects, seed=perturb_seed) if effects else cell
