"""The simulated robot's passes, driven as a cell controller's robot program would drive a
real one: when the service arms a scan, the simulated robot carries the part through the sheet.

``flyscan serve --sim`` hands the service the devices of :func:`simulated_cell_devices`: the
simulated camera and robot, and a :class:`SimPassDriver` (``service.driver.PassDriver``); the
service only calls it, never knows what is behind it.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np

from scanner_core.cad import check_fits
from simulator.cell import CALIBRATION_SPEED_SHAPE
from simulator.faults import faulty_part
from simulator.live import PassInProgress
from simulator.parts import simulated
from simulator.session import misplacement_matrix
from simulator.surfaces import with_surface

__all__ = ["SimPassDriver", "SimulatedCellOptions", "CellDevices", "simulated_cell_devices",
           "PREVIOUS_PASS_WAIT_S", "CALIBRATION_PART"]

#: The simulated robot finishes its previous pass (its lead-out) before starting the next, s.
PREVIOUS_PASS_WAIT_S = 5.0
#: The seed of the faults a simulated pass's gripper is asked to hold (``holding``).
FAULT_SEED = 44
#: Parts the simulated cell keeps dressed for its ray casting (each holds its scene).
DRESSED_PARTS = 4
#: The demo block's name in the service's parts (``service.parts.DEMO_PART``).
DEMO_PART = "demo"
#: What a calibration session's pass carries through the sheet in the simulated cell: the
#: demo block (the pass serves the clocks and the LED's offset, from the marker alone; the
#: sphere itself cannot be a part yet: a part without edges has no edge model to register).
CALIBRATION_PART = DEMO_PART


class SimPassDriver:
    """Sends the simulated robot through the sheet when a scan is armed; with an RTDE
    emulator (``--sim --robot ur://HOST``) the emulator serves the same track to the real
    ur-rtde client. Every part is simulated with ``surface`` (``simulator.surfaces``)."""

    simulated = True
    calibration_part = CALIBRATION_PART

    def __init__(self, sim, emulator=None, surface: str = "default"):
        self.sim = sim
        self.emulator = emulator
        self.surface = surface
        self._dressed: dict[int, tuple] = {}  # id -> (the library's part, the simulated one)
        self._scenes = None  # simulator.calsession.StepScenes, made at the first hold
        self._held_at = None  # the TCP position of the emulator's hold, (3,) mm
        self._calibration_next = False  # the next pass is a calibration session's (park)
        self._fault_rng = np.random.default_rng(FAULT_SEED)  # the faults' draws (``holding``)

    def _simulated(self, part):
        """The part as the simulator shows it (the same object every time, so that its
        rendered pass is reused): the service's model of it, with the surface asked for."""
        key = id(part)
        if key not in self._dressed or self._dressed[key][0] is not part:
            shown = simulated(part)
            if self.surface != "default":
                shown = with_surface(shown, self.surface)
            self._dressed[key] = (part, shown)
            while len(self._dressed) > DRESSED_PARTS:  # a catalogue's parts, not all kept
                self._dressed.pop(next(iter(self._dressed)))
        return self._dressed[key][1]

    def builtin_parts(self) -> dict:
        """The parts the simulated cell comes with: the demo block, ``service.parts.DEMO_PART``
        (a ``scanner_core.cad.PartModel``)."""
        from scanner_core.cad import part_from_mesh
        from simulator.procedural import block_with_holes_and_steps

        return {DEMO_PART: part_from_mesh(block_with_holes_and_steps(), name=DEMO_PART,
                                          source="procedural:block_with_holes_and_steps")}

    def plan_geometry(self, nominal):
        """The simulated cell's pass and tools for a calibration plan, the LED's offset as
        ``nominal`` (a ``Calibration``: what the installer knows) draws it."""
        from simulator.calsession import plan_geometry

        return plan_geometry(self.sim.cell, led_offset_t_mm=nominal.marker_offset_t)

    def park(self, *, calibration_pass: bool = False) -> None:
        """Take the TCP out of the views, to where the default pass begins (after a
        calibration session's last pose: the LED held in view would start the next pass).
        With `calibration_pass` the next pass is a calibration session's: its speed goes up
        to the middle and down again (``simulator.cell.CALIBRATION_SPEED_SHAPE``), as the
        cell's robot program runs it."""
        self._calibration_next = bool(calibration_pass)
        cell = self.sim.cell
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = cell.gripper_rotation_b, self.sim.idle_tcp_b
        self._after_the_pass(lambda: self.sim.hold(pose, None))
        if self.emulator is not None:
            self.emulator.set_track(self.sim.start_clock(), self.sim.robot.clock_offset_s,
                                    cell.gripper_rotation_b, pose[:3, 3])
            self._held_at = pose[:3, 3].copy()

    def hold(self, kind: str, tcp_b) -> None:
        """Take the TCP to a calibration step's pose ((4, 4) ^B X_T, mm) and hold it there, as
        the cell controller's robot program would: the camera shows the LED (``led``) or the
        sphere in the sheet (``sphere``), the robot reports the pose (with a real robot's
        errors, the RTDE emulator with its orientation error). A pass's lead-out still under
        way is finished first, as for :meth:`start_pass`."""
        from simulator.calsession import StepScenes

        if self._scenes is None:
            self._scenes = StepScenes(self.sim.cell)
        tcp_b = np.asarray(tcp_b, dtype=np.float64)
        truth = self._scenes.truth(kind, tcp_b)
        self._after_the_pass(lambda: self.sim.hold(tcp_b, truth))
        if self.emulator is not None:
            cell = self.sim.cell
            self.emulator.set_track(self.sim.start_clock(), self.sim.robot.clock_offset_s,
                                    cell.effects.robot_rotation_error @ tcp_b[:3, :3],
                                    tcp_b[:3, 3])
            self._held_at = tcp_b[:3, 3].copy()

    def misplacement(self, part, values):
        """The misplacement ``[tx, ty, tz, rx, ry, rz]`` (mm, degrees) the simulated robot's
        part is held with, as a transform in {T}; PartError when it leaves the inspection
        volume, ValueError unless six finite numbers or without a part. None for None."""
        if values is not None and part is None:
            raise ValueError("misplace needs a part to misplace")
        matrix = misplacement_matrix(values)
        if matrix is not None:
            check_fits(part, pose=matrix @ part.grasp)
        return matrix

    def start(self) -> None:
        """Start the emulator (its own process) on the cell's clock, before the robot connects."""
        if self.emulator is None:
            return
        self.emulator.start()
        try:
            cell = self.sim.cell
            self.emulator.set_track(self.sim.start_clock(), self.sim.robot.clock_offset_s,
                                    cell.gripper_rotation_b, self.sim.idle_tcp_b)
        except BaseException:
            self.emulator.stop()
            raise

    def prepare(self, part) -> None:
        self.sim.prepare_pass(self._simulated(part))

    def before_arm(self) -> None:
        """Wait (up to ``PREVIOUS_PASS_WAIT_S``) for the robot to finish a pass still under
        way, as a robot program does before the controller arms the next scan: a pass whose
        scan timed out before its marker appeared must not be taken by the next scan."""
        deadline = time.monotonic() + PREVIOUS_PASS_WAIT_S
        while self.sim.pass_active and time.monotonic() < deadline:
            time.sleep(0.01)

    def holding(self, part, fault: str):
        """The fault ``KIND[:SIZE_MM]`` built on ``part`` (``simulator.faults.faulty_part``,
        drawn from the driver's own generator, seeded): ValueError for a malformed one."""
        if part is None:
            raise ValueError("fault needs a part to put it in")
        return faulty_part(self._simulated(part), fault, self._fault_rng)

    def start_pass(self, part, misplacement: np.ndarray | None, wanted=lambda: True,
                   holding=None) -> None:
        """Start the pass once the robot has finished the previous one (its lead-out goes on
        after the scan has ended), as a robot program would; not at all when ``wanted()`` says
        False by then (the scan it was for has timed out while the part's pass was prepared:
        the next scan, of another part, must not take it). The gripper holds ``holding``
        (``holding``'s) where given, else ``part``."""
        profile = None
        if self._calibration_next:
            self._calibration_next = False
            profile = self.sim.cell.with_pass(speed_shape=CALIBRATION_SPEED_SHAPE).pass_profile
        simulated = self._simulated(part) if holding is None else holding
        self.sim.prepare_pass(simulated, misplacement, profile=profile)  # cached for the start
        live = self._after_the_pass(
            lambda: self.sim.start_pass(simulated, misplacement, profile=profile), wanted)
        if live is None:
            return
        if self.emulator is not None:
            if self._held_at is not None:  # back in the pass's orientation after a hold
                self.emulator.set_track(self.sim.start_clock(), self.sim.robot.clock_offset_s,
                                        self.sim.cell.gripper_rotation_b, self._held_at)
                self._held_at = None
            self.emulator.add_segment(live.segment)

    def _after_the_pass(self, move, wanted=lambda: True):
        """``move()`` once the robot has finished the pass under way (its lead-out goes on
        after the scan has ended: the robot program moves on only after it), waiting up to
        ``PREVIOUS_PASS_WAIT_S``; None without moving when ``wanted()`` says False first."""
        deadline = time.monotonic() + PREVIOUS_PASS_WAIT_S
        while True:
            if not wanted():
                return None
            try:
                return move()
            except PassInProgress:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.01)

    def close(self) -> None:
        if self.emulator is not None:
            self.emulator.stop()


@dataclass(frozen=True)
class SimulatedCellOptions:
    """The simulated cell a service is given.

    Attributes
    ----------
    seed : int
        The frames' noise.
    clock_offset_s : float
        The simulated robot's clock minus the camera's, s.
    surface : str
        The parts' surface (``simulator.surfaces``): default, matte, dark or shiny.
    perturb_seed : int or None
        The cell's geometry (and effects) perturbed, as ``flyscan scan --perturb-seed``.
    effects : str
        A real cell's effects (``simulator.effects``): all, none or a comma-separated choice.
    speed_mm_s, fps : float or None
        The pass's speed (mm/s) and the camera's frame rate; None: the cell's.
    """

    seed: int = 0
    clock_offset_s: float = 0.0
    surface: str = "default"
    perturb_seed: int | None = None
    effects: str = "none"
    speed_mm_s: float | None = None
    fps: float | None = None


class CellDevices(NamedTuple):
    """What ``service.daemon.Service(settings, devices=...)`` takes."""

    camera: object
    robot: object
    driver: SimPassDriver
    calibration: object


def simulated_cell_devices(options: SimulatedCellOptions = SimulatedCellOptions(), *,
                           rtde_host: str | None = None,
                           robot_client: Callable[[str], object] | None = None) -> CellDevices:
    """The simulated cell's camera, robot, driver and calibration (its truth) for a service.

    With ``rtde_host`` an RTDE emulator (its own process, started with the driver) serves the
    simulated robot's track at that host, and the robot handed over is ``robot_client(host)``
    (``service.ur_robot.URRobot``: the real ur-rtde client). ValueError for unknown effects."""
    from simulator.cell import cell_with_effects
    from simulator.live import LiveSimCell

    cell = cell_with_effects(options.perturb_seed, options.effects)
    changes = {k: v for k, v in (("speed_mm_s", options.speed_mm_s), ("fps", options.fps))
               if v is not None}
    if changes:
        cell = cell.with_pass(**changes)
    sim = LiveSimCell(cell, seed=options.seed, clock_offset_s=options.clock_offset_s)
    if rtde_host is None:
        return CellDevices(sim.camera, sim.robot, SimPassDriver(sim, surface=options.surface),
                           cell.calibration)
    if robot_client is None:
        raise ValueError("an RTDE host needs the robot client that reads it")
    from simulator.rtde_emulator import RtdeEmulator

    return CellDevices(sim.camera, robot_client(rtde_host),
                       SimPassDriver(sim, RtdeEmulator(rtde_host), options.surface),
                       cell.calibration)
