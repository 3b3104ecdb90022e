"""The simulated cell's devices for the service: the only place they are wired in.

``flyscan serve --sim`` builds the reference cell (perturbed, with a real cell's effects, at
the pass asked for), its live camera and robot on the real clock (``simulator.live``), and the
driver that sends the robot through the sheet when a scan is armed
(``simulator.driver.SimPassDriver``), and hands them to the service like real devices. With
``--robot ur://HOST`` an RTDE emulator is started at HOST (its own process) serving the
simulated track, and the service reads it through the real ur-rtde client.
"""
from __future__ import annotations

__all__ = ["simulated_devices"]


def simulated_devices(settings):
    """(camera, robot, driver, calibration) of the simulated cell that ``settings`` describe
    (``service.settings.Settings``: ``sim_*``, ``robot``)."""
    from simulator.driver import SimPassDriver
    from simulator.cell import cell_with_effects
    from simulator.live import LiveSimCell

    if settings.camera is not None:
        raise ValueError(f"--camera {settings.camera}: the simulated cell has its own camera")
    cell = cell_with_effects(settings.sim_perturb_seed, settings.sim_effects)
    changes = {k: v for k, v in (("speed_mm_s", settings.sim_speed_mm_s), ("fps", settings.sim_fps))
               if v is not None}
    if changes:
        cell = cell.with_pass(**changes)
    sim = LiveSimCell(cell, seed=settings.sim_seed, clock_offset_s=settings.sim_clock_offset_s)
    if settings.robot is None:
        return (sim.camera, sim.robot, SimPassDriver(sim, surface=settings.sim_surface),
                cell.calibration)
    from service.ur_robot import URRobot, parse_robot_url
    from simulator.rtde_emulator import RtdeEmulator

    host = parse_robot_url(settings.robot)
    return (sim.camera, URRobot(host), SimPassDriver(sim, RtdeEmulator(host), settings.sim_surface),
            cell.calibration)
