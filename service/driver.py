"""What the cell's robot does when the service asks: the driver protocol.

In a real cell the cell controller's robot program carries the part through the sheet after
arming a scan, takes the robot to a calibration step before asking for its capture, and parks
it before a calibration pass: the service asks nothing of the robot, and its driver,
:class:`ControllerDriven`, does nothing. A simulated cell hands the service a driver that moves
its simulated robot on those same requests (``simulator.driver.SimPassDriver``). The service
calls the driver it was given and never asks which it is.
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ["PassDriver", "ControllerDriven", "MisplaceUnsupported", "FaultUnsupported"]


class MisplaceUnsupported(ValueError):
    """A misplacement was asked of a cell that cannot put the part anywhere but where the
    gripper took it."""


class FaultUnsupported(ValueError):
    """A fault was asked of a cell whose gripper holds whatever it picked."""


@runtime_checkable
class PassDriver(Protocol):
    """The cell's robot as the service drives it.

    Attributes
    ----------
    simulated : bool
        The cell is simulated (the status page says so).
    calibration_part : str or None
        The part a calibration session's pass carries, by name (None: the service's default).
    """

    simulated: bool
    calibration_part: str | None

    def start(self) -> None:
        """Before the service's camera streams (an emulator is started, say)."""

    def close(self) -> None:
        """When the service stops."""

    def builtin_parts(self) -> dict:
        """The parts the cell comes with, name -> ``scanner_core.cad.PartModel``."""

    def prepare(self, part) -> None:
        """Ready a pass of ``part`` (a ``PartModel``) ahead of its first scan."""

    def before_arm(self) -> None:
        """Return once the robot has finished the pass under way, if any."""

    def start_pass(self, part, misplacement: np.ndarray | None, wanted, holding=None) -> None:
        """Carry ``part`` through the sheet, held off its grasp by ``misplacement`` ((4, 4) in
        {T}, mm, or None), unless ``wanted()`` says False first (the scan timed out); with
        ``holding`` (``holding``'s answer), the gripper holds that instead."""

    def park(self, *, calibration_pass: bool = False) -> None:
        """Take the TCP out of the views to where a pass begins; ``calibration_pass``: the
        next pass is a calibration session's."""

    def hold(self, kind: str, tcp_b: np.ndarray) -> None:
        """Take the TCP to a calibration step's pose ((4, 4) ^B X_T, mm) and hold it."""

    def misplacement(self, part, values) -> np.ndarray | None:
        """``[tx, ty, tz, rx, ry, rz]`` (mm, degrees) as the (4, 4) transform in {T} the next
        pass holds ``part`` with; None for None. MisplaceUnsupported where the cell cannot."""

    def holding(self, part, fault: str):
        """What the gripper is to hold instead of ``part`` on the next pass: the fault
        ``KIND[:SIZE_MM]`` (``flyscan scan --fault``), for ``start_pass``. FaultUnsupported
        where the cell cannot, ValueError for a malformed fault."""

    def plan_geometry(self, nominal):
        """The cell's pass and tools for a calibration plan
        (``scanner_core.calibration.plan.PlanGeometry``), or None where the installer gives them."""


class ControllerDriven:
    """A real cell's driver: the cell controller's robot program moves the robot itself."""

    simulated = False
    calibration_part = None

    def start(self) -> None:
        pass

    def close(self) -> None:
        pass

    def builtin_parts(self) -> dict:
        return {}

    def prepare(self, part) -> None:
        pass

    def before_arm(self) -> None:
        pass

    def start_pass(self, part, misplacement, wanted, holding=None) -> None:
        pass

    def park(self, *, calibration_pass: bool = False) -> None:
        pass

    def hold(self, kind: str, tcp_b) -> None:
        pass

    def misplacement(self, part, values):
        if values is None:
            return None
        raise MisplaceUnsupported("misplace is for the simulated cell only: a real cell's "
                                  "part sits where the gripper took it")

    def holding(self, part, fault):
        raise FaultUnsupported("fault is for the simulated cell only: a real cell's gripper "
                               "holds what it picked")

    def plan_geometry(self, nominal):
        return None
