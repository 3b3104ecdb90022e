"""The device interface: one Camera and one Robot protocol.

The simulated devices (``simulator.devices``) and the real backends (``service``) implement
these; the pipeline and the service only ever see the protocol. Constructing a device does no
I/O; ``open``/``connect`` does.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from scanner_core.types import Frame


class CameraTimeout(TimeoutError):
    """No frame arrived within the timeout."""


class CameraClosed(RuntimeError):
    """The camera is closed or its stream has ended."""


@runtime_checkable
class Camera(Protocol):
    width: int
    height: int
    fps: float

    def open(self) -> None: ...

    def close(self) -> None: ...

    def grab(self, timeout: float) -> Frame:
        """Next frame; raises CameraTimeout, or CameraClosed when the stream has ended."""
        ...


@runtime_checkable
class ExposureControl(Protocol):
    """A camera whose exposure the scanner sets (``scanner_core.pipeline.exposure``).

    ``exposure_range_us`` and ``gain_range`` are the limits the camera accepts;
    ``set_exposure`` applies from the next frame grabbed, and every frame reports the
    exposure and gain it was taken with (``Frame.exposure_us``, ``Frame.gain``).
    """

    exposure_range_us: tuple[float, float]
    gain_range: tuple[float, float]

    def set_exposure(self, exposure_us: float, gain: float = 1.0) -> None: ...


@dataclass(frozen=True)
class TcpPose:
    """A TCP pose reported by the robot.

    Attributes
    ----------
    t : float
        Robot clock, seconds.
    position : (3,) float64
        TCP position in {B}, mm.
    rotation : (3, 3) float64
        Rotation of {T} in {B} (columns are the {T} axes).
    interpolation_mm : float
        How far ``position`` may lie from the TCP's true one, mm, where it was interpolated
        between two reports (``chord_deviation_mm``): 0 at a report, and for a robot that
        knows its pose at any time.
    """

    t: float
    position: np.ndarray
    rotation: np.ndarray
    interpolation_mm: float = 0.0


def chord_deviation_mm(before, start, end, after) -> float:
    """How far the straight chord between two robot reports may lie from the TCP's path, mm.

    Each argument is a report ``(t s, position (3,) mm)``; `before` and `after` are the
    reports beside the chord's ends, or None where there is none. The path's velocity turns
    from ``v0`` (from `before` to `start`) to ``v1`` (from `end` to `after`) within the chord's
    ``dt``; the chord's own velocity ``c`` lies between them. A turn in the middle puts the
    path ``|v1 - v0| dt / 4 = |c - v0| dt / 2`` off the chord; the larger of the two sides is
    returned (constant acceleration ``a``, ``a dt^2 / 8`` off, reads about twice that). On a
    stream without gaps ``dt`` is one sample period and this is micrometres at most; across
    samples a loaded reader missed it grows with ``dt^2``.
    """
    t0, p0 = start
    t1, p1 = end
    span = float(t1) - float(t0)
    if not span > 0:
        return 0.0
    chord = (np.asarray(p1, dtype=np.float64) - np.asarray(p0, dtype=np.float64)) / span
    worst = 0.0
    for first, second in ((before, start), (end, after)):
        if first is None or second is None:
            continue
        (ta, pa), (tb, pb) = first, second
        if not float(tb) > float(ta):
            continue
        velocity = (np.asarray(pb, dtype=np.float64) - np.asarray(pa, dtype=np.float64)) \
            / (float(tb) - float(ta))
        worst = max(worst, float(np.linalg.norm(chord - velocity)))
    return worst * span / 2.0


@runtime_checkable
class Robot(Protocol):
    def connect(self) -> None: ...

    def disconnect(self) -> None: ...

    @property
    def connected(self) -> bool: ...

    def latest(self) -> TcpPose:
        """Newest pose; raises RuntimeError when none has arrived."""
        ...

    def pose_at(self, t: float) -> TcpPose:
        """Pose interpolated at robot time ``t`` from the bounded history.

        Raises LookupError when ``t`` lies outside the history.
        """
        ...


class RobotConnection:
    """The connection of a robot that has nothing to open: a flag that ``connect`` sets and
    ``disconnect`` clears, read by ``connected``, and checked by the robot's look-ups.

    The base of the robots whose link cannot fail: a replayed recording's
    (``scanner_core.recording.replay.ReplayRobot``) and the simulated ones (``simulator.devices.SimRobot``,
    ``simulator.live_devices.LiveSimRobot``). A real robot's link is its own
    (``service.ur_robot.URRobot``). A subclass names itself in ``_not_connected``, the text of
    the RuntimeError that :meth:`_require_connected` raises before it connects or after it
    disconnects.
    """

    _not_connected = "the robot is not connected"
    _connected = False

    def connect(self) -> None:
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    @property
    def connected(self) -> bool:
        return self._connected

    def _require_connected(self) -> None:
        """RuntimeError (``_not_connected``) unless connected."""
        if not self._connected:
            raise RuntimeError(self._not_connected)
