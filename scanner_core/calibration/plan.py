"""The plan of a calibration session with the robot: where the robot should take the TCP.

A calibration session (``scanner_core.calibration.session``) needs the LED at many known positions
across the three views, a sphere of known radius at known positions across the light sheet,
and one pass. With a stage those positions come from the stage; with the robot they come from
the TCP poses the robot reports, and the plan says which poses to go to, generated for the
cell's volume:

- ``led`` steps: the LED's nominal position (the TCP pose times the LED's offset as drawn,
  ``marker_offset_t``) spread over a volume about the sheet's centre (the direct view) and one
  along the LED's track in a pass (the mirror views), the tool in its pass orientation; and a
  share of them (half) with the tool turned by ``tilt_deg`` (20 degrees) about x, y or z of {B} around the LED, so
  that the LED's true offset from the TCP can be told from the cell's frame
  (``scanner_core.calibration.session``: the LED's offset is fitted from the turned poses);
- ``sphere`` steps: the sphere's centre (the TCP pose times ``sphere_offset_t_mm``) across the
  volume, the sheet cutting it 8 to 20 mm from its centre on either side;
- the ``pass``: the robot carries the sphere through the sheet, as in a scan.

Poses are given in UR's convention (:func:`plan_to_dict`): the TCP in the robot's base, x, y, z
in metres and a rotation vector in radians, ready for a URScript ``movel(p[...])`` (``scanner_core.io.rtde.ur_pose_to_matrix``). The geometry assumes {B} as
the reference cell puts it: passes run along +y_B at x_B = 0 and the sheet lies near y_B = 0.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scanner_core.io.rtde import matrix_to_ur_pose, ur_pose_to_matrix

__all__ = ["TILT_DEG", "TILTED_FRACTION", "PlanGeometry", "PlanStep", "CalibrationPlan", "make_plan", "led_targets",
           "sphere_targets", "plan_to_dict", "plan_from_dict", "PLAN_FORMAT", "TILT_AXES"]

PLAN_FORMAT = "flyscan-calibration-plan"
PLAN_VERSION = 1
#: The share of LED poses with the tool turned, and by how much, degrees. The LED's offset
#: comes from them (``scanner_core.calibration.ledpivot``), and its error shifts the views' frame against
#: the sphere's centres, which the light plane feels: in the realistic cell of perturb seeds
#: 3, 11 and 12, 30 % turned by 10 degrees left the offset 6-9 um off and the plane's normal
#: 0.0025-0.005 degrees; half turned by 20 degrees, 3-4 um and 0.0017-0.0019 degrees.
TILTED_FRACTION = 0.5
TILT_DEG = 20.0
#: The axes of {B} the tool is turned about in the turned LED steps: every axis, both ways,
#: so that the LED's offset is fixed in all three directions.
TILT_AXES = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0], [0, 0, 1.0],
                      [0, 0, -1.0]])


@dataclass(frozen=True)
class PlanGeometry:
    """What the plan is generated from: the cell's pass and the tools as drawn.

    Attributes
    ----------
    tcp_rotation_b : (3, 3) float64
        The tool's orientation in a pass ({T}'s axes in {B}).
    pass_start_y_mm, pass_end_y_mm, pass_height_mm : float
        The pass: along +y_B from start to end, the TCP at x_B = 0 and this height, mm.
    led_offset_t_mm : (3,) float64
        The LED in {T} as drawn (the nominal calibration's ``marker_offset_t``), mm.
    sphere_offset_t_mm : (3,) float64
        The sphere's centre in {T} (its holder as drawn, or measured with the robot's TCP
        wizard), mm.
    sphere_radius_mm : float
    """

    tcp_rotation_b: np.ndarray
    pass_start_y_mm: float
    pass_end_y_mm: float
    pass_height_mm: float
    led_offset_t_mm: np.ndarray
    sphere_offset_t_mm: np.ndarray
    sphere_radius_mm: float


@dataclass(frozen=True)
class PlanStep:
    """One pose: ``kind`` "led" or "sphere", ``tcp_b`` (4, 4) float64 ^B X_T in mm."""

    kind: str
    tcp_b: np.ndarray


@dataclass(frozen=True)
class CalibrationPlan:
    """The steps in order, the pass's start and end TCP poses, and the geometry."""

    steps: tuple[PlanStep, ...]
    pass_start_b: np.ndarray
    pass_end_b: np.ndarray
    geometry: PlanGeometry
    tilt_deg: float = 0.0
    notes: dict = field(default_factory=dict)

    def of_kind(self, kind: str) -> list[PlanStep]:
        return [s for s in self.steps if s.kind == kind]


def led_targets(geometry: PlanGeometry, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) positions of the LED in {B}, mm: half in a volume about the sheet's centre
    (120 x 50 x 80 mm), half along the LED's track in a pass (50 mm across, 60 mm short of
    the pass's ends)."""
    g = geometry
    led = np.array([0.0, 0.0, g.pass_height_mm]) + g.tcp_rotation_b @ np.asarray(g.led_offset_t_mm)
    half = n // 2
    around = rng.uniform([-60.0, -25.0, -40.0], [60.0, 25.0, 40.0], (half, 3))
    track = rng.uniform([led[0] - 25.0, g.pass_start_y_mm + led[1] + 30.0, led[2] - 25.0],
                        [led[0] + 25.0, g.pass_end_y_mm + led[1] - 30.0, led[2] + 25.0],
                        (n - half, 3))
    return np.vstack([around, track])


def sphere_targets(radius_mm: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) sphere centres in {B}, mm: across the inspection volume (x within 45 mm, z
    within 25 mm), the sheet (y_B = 0) cutting the sphere 0.28 to 0.7 radii from its centre,
    on either side."""
    y = rng.uniform(0.28 * radius_mm, 0.7 * radius_mm, n) * rng.choice([-1.0, 1.0], n)
    return np.column_stack([rng.uniform(-45.0, 45.0, n), y, rng.uniform(-25.0, 25.0, n)])


def _pose(rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rotation, position
    return m


def _turn(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotation by ``angle_rad`` about unit ``axis`` (Rodrigues)."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1.0 - np.cos(angle_rad)) * (k @ k)


def make_plan(geometry: PlanGeometry, *, led_count: int = 200, sphere_count: int = 40,
              tilted_fraction: float = TILTED_FRACTION, tilt_deg: float = TILT_DEG,
              seed: int = 0
              ) -> CalibrationPlan:
    """The plan for a cell (see the module's notes).

    Parameters
    ----------
    geometry : PlanGeometry
    led_count, sphere_count : int
        Poses of the LED and of the sphere; at least 12 and 3.
    tilted_fraction : float
        Share of the LED poses with the tool turned (0 to 1): taken evenly from both volumes.
    tilt_deg : float
        How far the tool is turned, degrees (0 < tilt <= 30: a real gripper's LED stays in
        the views' sight).
    seed : int
        Seeds the positions (the same plan for the same seed).

    Returns
    -------
    CalibrationPlan
    """
    if int(led_count) < 12 or int(sphere_count) < 3:
        raise ValueError(f"a plan needs at least 12 LED and 3 sphere poses, got {led_count} "
                         f"and {sphere_count}")
    if not 0.0 <= tilted_fraction <= 1.0:
        raise ValueError(f"`tilted_fraction` must be within 0 to 1, got {tilted_fraction}")
    if not 0.0 < tilt_deg <= 30.0:
        raise ValueError(f"`tilt_deg` must be within 0 to 30 degrees, got {tilt_deg}")
    g = geometry
    rng = np.random.default_rng([0x91A2, seed])
    r0 = np.asarray(g.tcp_rotation_b, dtype=np.float64)
    led_t = np.asarray(g.led_offset_t_mm, dtype=np.float64)
    sphere_t = np.asarray(g.sphere_offset_t_mm, dtype=np.float64)
    steps = []
    targets = led_targets(g, int(led_count), rng)
    tilted = np.zeros(len(targets), bool)
    count = int(round(tilted_fraction * len(targets)))
    if count:
        tilted[np.round(np.linspace(0, len(targets) - 1, count)).astype(int)] = True
    k = 0
    for p, turn in zip(targets, tilted):
        rotation = r0
        if turn:  # about the LED: it stays where the views see it
            rotation = _turn(TILT_AXES[k % len(TILT_AXES)], np.radians(tilt_deg)) @ r0
            k += 1
        steps.append(PlanStep("led", _pose(rotation, p - rotation @ led_t)))
    for c in sphere_targets(g.sphere_radius_mm, int(sphere_count), rng):
        steps.append(PlanStep("sphere", _pose(r0, c - r0 @ sphere_t)))
    start = _pose(r0, np.array([0.0, g.pass_start_y_mm, g.pass_height_mm]))
    end = _pose(r0, np.array([0.0, g.pass_end_y_mm, g.pass_height_mm]))
    return CalibrationPlan(tuple(steps), start, end, g, float(tilt_deg),
                           {"seed": int(seed), "tilted": int(count)})


def plan_to_dict(plan: CalibrationPlan) -> dict:
    """The plan as JSON: every pose a UR pose [x, y, z (m), rx, ry, rz (rad)] of the TCP in
    the robot's base."""
    g = plan.geometry
    ur = lambda m: [round(float(v), 9) for v in matrix_to_ur_pose(m)]
    return {"format": PLAN_FORMAT, "version": PLAN_VERSION,
            "convention": "UR: TCP in the robot base, x, y, z in m, rotation vector in rad",
            "geometry": {"tcp_rotation_b": np.asarray(g.tcp_rotation_b).tolist(),
                         "pass_start_y_mm": g.pass_start_y_mm, "pass_end_y_mm": g.pass_end_y_mm,
                         "pass_height_mm": g.pass_height_mm,
                         "led_offset_t_mm": np.asarray(g.led_offset_t_mm).tolist(),
                         "sphere_offset_t_mm": np.asarray(g.sphere_offset_t_mm).tolist(),
                         "sphere_radius_mm": g.sphere_radius_mm},
            "tilt_deg": plan.tilt_deg, "notes": plan.notes,
            "steps": [{"kind": s.kind, "tcp": ur(s.tcp_b)} for s in plan.steps],
            "pass": {"start": ur(plan.pass_start_b), "end": ur(plan.pass_end_b)}}


def plan_from_dict(data: dict) -> CalibrationPlan:
    """:func:`plan_to_dict`'s inverse; ValueError naming what is wrong."""
    if not isinstance(data, dict) or data.get("format") != PLAN_FORMAT:
        raise ValueError(f"a calibration plan must have format {PLAN_FORMAT!r}")
    if data.get("version") != PLAN_VERSION:
        raise ValueError(f"calibration plan version {data.get('version')!r} is not one this "
                         f"flyscan reads ({PLAN_VERSION})")
    try:
        g = data["geometry"]
        geometry = PlanGeometry(np.array(g["tcp_rotation_b"], dtype=np.float64),
                                float(g["pass_start_y_mm"]), float(g["pass_end_y_mm"]),
                                float(g["pass_height_mm"]),
                                np.array(g["led_offset_t_mm"], dtype=np.float64),
                                np.array(g["sphere_offset_t_mm"], dtype=np.float64),
                                float(g["sphere_radius_mm"]))
        steps = []
        for i, s in enumerate(data["steps"]):
            if s["kind"] not in ("led", "sphere"):
                raise ValueError(f"step {i}: kind must be led or sphere, got {s['kind']!r}")
            steps.append(PlanStep(s["kind"], ur_pose_to_matrix(s["tcp"])))
        start = ur_pose_to_matrix(data["pass"]["start"])
        end = ur_pose_to_matrix(data["pass"]["end"])
    except (KeyError, TypeError) as exc:
        raise ValueError(f"calibration plan: missing or malformed field {exc}") from None
    return CalibrationPlan(tuple(steps), start, end, geometry, float(data.get("tilt_deg", 0.0)),
                           dict(data.get("notes") or {}))
