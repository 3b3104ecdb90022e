"""The simulated cell's devices for the service: the only place they are wired in.

``flyscan serve --sim`` builds the reference cell (perturbed, with a real cell's effects, at
the pass asked for), its live camera and robot on the real clock, and the driver that sends
the robot through the sheet when a scan is armed (``simulator.driver.simulated_cell_devices``),
and hands them to the service like real devices. With ``--robot ur://HOST`` an RTDE emulator
is started at HOST (its own process) serving the simulated track, and the service reads it
through the real ur-rtde client.

What the simulated cell is told comes from the same places as the service's settings, under
names of its own: ``sim`` and ``sim_*`` in the settings file, ``FLYSCAN_SIM`` and
``FLYSCAN_SIM_*`` in the environment.
"""
from __future__ import annotations

import re
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, InitSettingsSource, SettingsConfigDict

__all__ = ["SimSettings", "load_sim_settings", "split_sim_settings", "simulated_devices"]


class SimSettings(BaseSettings):
    """The simulated cell ``flyscan serve --sim`` runs (``simulator.driver.SimulatedCellOptions``)."""

    model_config = SettingsConfigDict(env_prefix="FLYSCAN_", extra="forbid")

    sim: bool = Field(False, description="simulated devices: the reference cell with its "
                                         "camera and robot")
    sim_seed: int = Field(0, ge=0, description="the frames' noise")
    sim_clock_offset_s: float = Field(0.0, ge=-1e6, le=1e6,
                                      description="the simulated robot's clock minus the camera's, s")
    sim_surface: Literal["default", "matte", "dark", "shiny"] = Field(
        "default", description="the simulated parts' surface (simulator.surfaces)")
    sim_perturb_seed: int | None = Field(
        None, ge=0, description="the simulated cell's geometry (and effects) perturbed, as "
                                "flyscan scan --perturb-seed")
    sim_effects: str = Field(
        "none", description="the simulated cell's real-cell effects: all, none or a comma-"
                            "separated choice of lens, exposure, clocks, robot, led (the live "
                            "cell draws the lens and the LED; it does not blur frames nor add "
                            "robot report errors)")
    sim_speed_mm_s: float | None = Field(None, gt=0, le=5000)
    sim_fps: float | None = Field(None, gt=0, le=2000)

    @field_validator("sim_effects")
    @classmethod
    def _effects_list(cls, value: str) -> str:
        # Only the form here: the simulated cell names an unknown effect when it is built.
        if not re.fullmatch(r"\s*[A-Za-z_]+(\s*,\s*[A-Za-z_]+)*\s*", value):
            raise ValueError(f"must be all, none or a comma-separated list of effect names, "
                             f"got {value!r}")
        return value

    def options(self):
        """As ``simulator.driver.SimulatedCellOptions``."""
        from simulator.driver import SimulatedCellOptions

        return SimulatedCellOptions(
            seed=self.sim_seed, clock_offset_s=self.sim_clock_offset_s, surface=self.sim_surface,
            perturb_seed=self.sim_perturb_seed, effects=self.sim_effects,
            speed_mm_s=self.sim_speed_mm_s, fps=self.sim_fps)


def split_sim_settings(file_settings: dict) -> tuple[dict, dict]:
    """A settings file's table split into (the service's, the simulated cell's: ``sim`` and
    ``sim_*``)."""
    sim = {k: v for k, v in file_settings.items() if k == "sim" or k.startswith("sim_")}
    return {k: v for k, v in file_settings.items() if k not in sim}, sim


def load_sim_settings(file_settings: dict | None = None, **overrides) -> SimSettings:
    """The simulated cell's settings from a settings file's ``sim`` and ``sim_*`` entries
    (``split_sim_settings``), the environment and ``overrides`` (None left out), in rising
    priority."""
    overrides = {k: v for k, v in overrides.items() if v is not None}
    data = dict(file_settings or {})

    class FileSimSettings(SimSettings):
        @classmethod
        def settings_customise_sources(cls, settings_cls, init_settings, env_settings,
                                       dotenv_settings, file_secret_settings):
            return init_settings, env_settings, InitSettingsSource(settings_cls, data)

    return FileSimSettings(**overrides)


def simulated_devices(sim: SimSettings, robot: str | None = None):
    """(camera, robot, driver, calibration) of the simulated cell ``sim`` describes; with
    ``robot`` (``ur://HOST``) an RTDE emulator at HOST and the real ur-rtde client reading it.
    ValueError for an unknown effect."""
    from service.ur_robot import URRobot, parse_robot_url
    from simulator.driver import simulated_cell_devices

    host = None if robot is None else parse_robot_url(robot)
    return simulated_cell_devices(sim.options(), rtde_host=host, robot_client=URRobot)
