"""A simulated calibration session: what a stage and a sphere show the camera in a cell.

The stage moves the LED to known positions (reported to +-``stage_accuracy_mm``, the truth
a little off), then the sphere of known radius across the sheet; a pass of the sphere held by
the robot gives the clocks and the LED's offset. The frames are rendered from the cell's truth
(``simulator.render``, ``simulator.imaging``); the session gives the scanner only the frames,
the stage's reported positions and the robot's reports (``scanner_core.calibration.session.Session``).
"""
from __future__ import annotations

import numpy as np
import trimesh

from scanner_core.geometry import angle_between, apply_transform
from scanner_core.calibration.plan import PlanGeometry, led_targets, sphere_targets
from scanner_core.calibration.session import Session
from simulator.cell import CALIBRATION_SPEED_SHAPE, Cell
from simulator.parts import Part, part_from_mesh
from simulator.render import PartScene, frame_image, FrameTruth
from simulator.session import simulated_cell

#: The sphere's mesh: an icosphere of this subdivision (81920 faces: its facets lie within
#: 2 um of the true sphere), scaled so that its surface's mean radius is the sphere's.
SPHERE_SUBDIVISIONS = 6
#: Barycentric steps per facet edge of the quadrature of the mesh's mean radius.
_RADIUS_QUADRATURE_STEPS = 4
#: Positions of a session: the LED's, half about the part's place in the sheet (the direct
#: view) and half along the LED's track (the mirror views); the sphere's.
LED_POSITIONS = 200
SPHERE_POSITIONS = 40
#: The sphere's centre in {T}, mm, as its holder puts it: 50 mm down the tool's axis.
SPHERE_OFFSET_T_MM = (0.0, 0.0, 50.0)


def sphere_part(radius_mm: float) -> Part:
    """The calibration sphere as a part, held 50 mm above its centre."""
    mesh = trimesh.creation.icosphere(subdivisions=SPHERE_SUBDIVISIONS, radius=radius_mm)
    # Each facet is a chord inside the sphere its corners lie on (1.3 um on average at this
    # subdivision); the calibration takes every stripe point to lie on the sphere of the given
    # radius, and the plane's shift took that deficit as a bias of about 1 um.
    mesh.apply_scale(radius_mm / mean_radius(mesh))
    grasp = np.eye(4)
    grasp[:3, 3] = SPHERE_OFFSET_T_MM  # its centre below the TCP, in the middle of the volume
    return part_from_mesh(mesh, name="sphere", source=f"procedural:sphere r={radius_mm} mm",
                          grasp=grasp)


def mean_radius(mesh) -> float:
    """The mean distance from the origin of a mesh's surface, area-weighted, mm: each facet
    cut into ``_RADIUS_QUADRATURE_STEPS`` squared equal triangles, each weighed at its
    centroid (the midpoint rule)."""
    n = _RADIUS_QUADRATURE_STEPS
    lattice = ([(i + 1 / 3, j + 1 / 3) for i in range(n) for j in range(n - i)]
               + [(i + 2 / 3, j + 2 / 3) for i in range(n - 1) for j in range(n - 1 - i)])
    weights = np.array([(a, b, n - a - b) for a, b in lattice]) / n
    corners = mesh.vertices[mesh.faces]  # (F, 3, 3)
    radii = np.linalg.norm(np.einsum("kc,fcd->fkd", weights, corners), axis=2).mean(axis=1)
    return float(np.average(radii, weights=mesh.area_faces))


def plan_geometry(cell: Cell, *, led_offset_t_mm=None, sphere_offset_t_mm=None):
    """The cell's pass and tools as a calibration plan is generated from them
    (``scanner_core.calibration.plan``): the LED's offset ``led_offset_t_mm`` (default the cell's),
    the sphere held as :func:`sphere_part` holds it."""
    p = cell.pass_profile
    led = cell.calibration.marker_offset_t if led_offset_t_mm is None else led_offset_t_mm
    offset = SPHERE_OFFSET_T_MM if sphere_offset_t_mm is None else sphere_offset_t_mm
    return PlanGeometry(np.asarray(cell.gripper_rotation_b, dtype=np.float64), p.start_y_mm,
                        p.end_y_mm, p.height_mm, np.asarray(led, dtype=np.float64),
                        np.asarray(offset, dtype=np.float64), cell.sphere_radius_mm)


class StepScenes:
    """What the camera sees at a calibration step's TCP pose, from the cell's truth: the LED
    alone (``led``), or the sphere cut by the sheet with the LED switched off (``sphere``: a
    robot output switches it, so that its blob is not taken for the stripe). The sphere's
    scene (its intersector) is built once."""

    def __init__(self, cell: Cell):
        self.cell = cell
        self._led = _LedScene(cell)
        self._sphere = None

    def truth(self, kind: str, tcp_b) -> FrameTruth:
        """The FrameTruth at ``tcp_b`` ((4, 4) ^B X_T, mm, the true pose)."""
        tcp_b = np.asarray(tcp_b, dtype=np.float64)
        if kind == "led":
            led_b = tcp_b[:3, 3] + tcp_b[:3, :3] @ self.cell.calibration.marker_offset_t
            return self._led.truth(led_b)
        if kind == "sphere":
            if not np.allclose(tcp_b[:3, :3], self.cell.gripper_rotation_b, atol=1e-6):
                raise ValueError("the simulated sphere is held in the pass orientation only")
            if self._sphere is None:
                self._sphere = PartScene(sphere_part(self.cell.sphere_radius_mm), self.cell)
            return self._sphere.geometry(tcp_b[:3, 3], self._sphere.part.grasp, with_marker=False)
        raise ValueError(f"`kind` must be led or sphere, got {kind!r}")


def led_positions(cell: Cell, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) stage positions of the LED in {B}, mm: a volume about the sheet's centre and a
    volume along the LED's track in a pass (``scanner_core.calibration.plan.led_targets``)."""
    return led_targets(plan_geometry(cell), n, rng)


def sphere_centres(cell: Cell, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) sphere centres in {B}, mm: across the inspection volume, the sheet cutting the
    sphere between 8 and 20 mm from its centre, on either side
    (``scanner_core.calibration.plan.sphere_targets``)."""
    return sphere_targets(cell.sphere_radius_mm, n, rng)


def stage_truth(reported: np.ndarray, accuracy_mm: float, rng: np.random.Generator) -> np.ndarray:
    """Where the stage really put things: uniformly within +-accuracy of what it reports."""
    return reported + rng.uniform(-accuracy_mm, accuracy_mm, reported.shape)


def led_frame(cell: Cell, led_b: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One frame of the LED alone at ``led_b`` (nothing in the sheet)."""
    scene = _LedScene(cell)
    return frame_image(cell, scene.truth(led_b), rng)


class _LedScene:
    """The LED's blobs without a part: nothing hides them."""

    def __init__(self, cell: Cell):
        self.cell = cell

    def truth(self, led_b) -> FrameTruth:
        cal = self.cell.calibration
        cam = cal.camera
        views = [np.asarray(led_b, dtype=np.float64)] + [
            apply_transform(m.reflection, led_b) for m in cal.mirrors]
        px = np.full((len(views), 2), np.nan)
        for k, (apparent, (c0, c1)) in enumerate(zip(views, cal.strips)):
            uv = cam.project(apparent)[0]
            if np.all(np.isfinite(uv)) and c0 <= uv[0] <= c1 - 1 and 0 <= uv[1] <= cam.height - 1:
                px[k] = uv
        blobs = None
        if self.cell.effects.led_radius_mm > 0:
            distance = np.linalg.norm(np.array(views) - cam.origin, axis=1)
            sigma = 0.5 * cam.fx * self.cell.effects.led_radius_mm / distance
            blobs = np.column_stack([px, np.ones(len(px)), sigma])
        none = np.zeros(0)
        return FrameTruth(np.zeros(3), np.eye(4), none.astype(np.int32), none, np.zeros((0, 3)),
                          none, np.asarray(led_b, dtype=np.float64), px, marker_blobs=blobs)


def simulate_session(cell: Cell, *, seed: int = 0, led_count: int = LED_POSITIONS,
                     sphere_count: int = SPHERE_POSITIONS, with_pass: bool = True,
                     nominal=None, pass_speed_shape: str = CALIBRATION_SPEED_SHAPE) -> Session:
    """A calibration session in ``cell`` (its truth renders the frames).

    Parameters
    ----------
    cell : Cell
        The true cell (``realistic_cell``, ``perturb``).
    seed : int
        Seeds the positions, the stage's errors and the image noise.
    led_count, sphere_count : int
    with_pass : bool
        Include a pass of the sphere held by the robot (the clocks and the LED's offset).
    nominal : Calibration, optional
        What the installer knows before calibrating: the view strips and the LED's offset as
        designed. Default: the reference design's.
    pass_speed_shape : str
        The pass's ``PassProfile.speed_shape``: the calibration pass's (``"peak"``), or
        ``"ramp"``, a scan's (``benchmarks.led_clock`` compares them).
    """
    from simulator.cell import load_cell

    rng = np.random.default_rng([0xCA1, seed])
    nominal = load_cell().calibration if nominal is None else nominal
    accuracy = cell.stage_accuracy_mm
    led_reported = led_positions(cell, led_count, rng)
    led_true = stage_truth(led_reported, accuracy, rng)
    sphere_reported = sphere_centres(cell, sphere_count, rng)
    sphere_true = stage_truth(sphere_reported, accuracy, rng)
    sphere = sphere_part(cell.sphere_radius_mm)
    scene = PartScene(sphere, cell)
    image_seed = int(rng.integers(2**31))

    def led_images():
        image_rng = np.random.default_rng([image_seed, 1])
        led_scene = _LedScene(cell)
        for p in led_true:
            yield frame_image(cell, led_scene.truth(p), image_rng)

    def sphere_images():
        image_rng = np.random.default_rng([image_seed, 2])
        for c in sphere_true:
            yield scene.render(c, np.eye(4), image_rng, with_marker=False)[0]

    def pass_devices():
        sim = simulated_cell(sphere, cell.with_pass(speed_shape=pass_speed_shape),
                             seed=image_seed)
        return sim.camera, sim.robot

    cam = cell.calibration.camera
    return Session(width=cam.width, height=cam.height, fps=cell.pass_profile.fps,
                   sphere_radius_mm=cell.sphere_radius_mm, nominal=nominal,
                   led_positions_b=led_reported, led_images=led_images,
                   sphere_centres_b=sphere_reported, sphere_images=sphere_images,
                   pass_devices=pass_devices if with_pass else None,
                   cell_name="simulated" + ("" if cell.effects == type(cell.effects)() else
                                            " realistic"))


def true_robot_clock(cell: Cell, camera_times):
    """The robot's clock (s) at camera time(s) `camera_times` (s), at the middle of the
    exposure, which is what the marker's time stamp stands for: the simulator's truth, for
    evaluation only. Minus `camera_times`, the true robot-minus-camera clock offset."""
    effects = cell.effects
    mid_exposure_s = 0.5e-3 if effects.exposure_blur else 0.0
    return effects.robot_time(np.asarray(camera_times, dtype=np.float64) + mid_exposure_s)


def evaluate_calibration(calibration, cell: Cell) -> dict:
    """How far a calibration is from the cell's truth (evaluation only: the simulator's truth).

    Returns the light plane's normal error (degrees) and offset error (um, along the normal
    at the sheet's centre), the camera's centre error (mm), each mirror's normal error
    (degrees), the LED offset's error (um) and the clock offset's error (ms, against the
    robot-minus-camera offset at the middle of the exposure, which is what the marker's time
    stamp stands for).
    """
    true = cell.calibration
    plane, true_plane = calibration.light_plane_b, true.light_plane_b
    normal_deg = float(np.degrees(angle_between(plane.normal, true_plane.normal, undirected=True)))
    # The offset error where it matters: at the point of the true sheet nearest {B}'s origin.
    centre = true_plane.normal * true_plane.offset
    offset_um = float(abs(plane.signed_distance(centre)[0]) * 1e3)
    mirrors = [float(np.degrees(angle_between(m.plane.normal, t.plane.normal, undirected=True)))
               for m, t in zip(calibration.mirrors, true.mirrors)]
    true_clock = float(true_robot_clock(cell, 0.0))
    return {"plane_normal_deg": normal_deg, "plane_offset_um": offset_um,
            "camera_centre_mm": float(np.linalg.norm(calibration.camera.origin
                                                     - true.camera.origin)),
            "mirror_normal_deg": mirrors,
            "led_offset_um": float(np.linalg.norm(calibration.marker_offset_t
                                                  - true.marker_offset_t) * 1e3),
            "clock_offset_ms": float((calibration.clock_offset_s - true_clock) * 1e3)}
