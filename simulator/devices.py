"""Simulated camera and robot: ordinary devices implementing ``scanner_core.devices``.

They share a ``SimClock`` (seconds since the pass was started). Offline, the camera drives
the clock: each grab renders the next frame and moves the clock to its exposure time, so the
robot can only report poses up to "now", as a real one would.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from scanner_core.devices import CameraClosed, RobotConnection, TcpPose, chord_deviation_mm
from scanner_core.io.rtde import MAX_FREQUENCY_HZ
from scanner_core.types import Frame
from simulator.effects import BLUR_SAMPLES, CellEffects
from simulator.imaging import (EXPOSURE_RANGE_US, GAIN_RANGE, NOMINAL_EXPOSURE_US,
                               check_exposure, exposed_model)
from simulator.motion import PassMotion
from simulator.render import PartScene

#: Robot reporting rate (UR controllers with major version > 3 stream RTDE at 500 Hz).
ROBOT_RATE_HZ = MAX_FREQUENCY_HZ
#: How much pose history the robot keeps for look-ups by time.
ROBOT_HISTORY_S = 10.0


@dataclass
class SimClock:
    """Simulated time, seconds."""

    now: float = 0.0


@dataclass
class SimCamera:
    """Renders the pass frame by frame.

    Parameters
    ----------
    scene : PartScene
    motion : PassMotion
    grasp : (4, 4) float64
        True ^T X_P (nominal grasp composed with any misplacement).
    seed : int
        Seeds image noise and dropped frames.
    drop_rate : float
        Probability that a frame is lost between camera and host (its id is skipped).
    clock : SimClock
    exposure_us, gain : float
        The exposure the next frame is taken with (``scanner_core.devices.ExposureControl``):
        ``simulator.imaging.exposed_model`` scales the image model by it.
    """

    scene: PartScene
    motion: PassMotion
    grasp: np.ndarray
    seed: int = 0
    drop_rate: float = 0.0
    clock: SimClock = field(default_factory=SimClock)
    truths: dict = field(default_factory=dict, repr=False)
    exposure_us: float = NOMINAL_EXPOSURE_US
    gain: float = 1.0
    exposure_range_us = EXPOSURE_RANGE_US
    gain_range = GAIN_RANGE

    def set_exposure(self, exposure_us: float, gain: float = 1.0) -> None:
        """From the next frame on; ValueError outside ``exposure_range_us``/``gain_range``."""
        self.exposure_us, self.gain = check_exposure(exposure_us, gain)

    def __post_init__(self):
        cam = self.scene.cell.calibration.camera
        self.width, self.height = cam.width, cam.height
        self.fps = self.scene.cell.pass_profile.fps
        self._next_id = 0
        self._rng = None

    def open(self) -> None:
        self._rng = np.random.default_rng(self.seed)
        self._next_id = 0
        self.truths.clear()

    def close(self) -> None:
        self._rng = None

    @property
    def frame_count(self) -> int:
        """Frames the pass spans from lead-in to lead-out."""
        p = self.scene.cell.pass_profile
        return int(np.floor((p.lead_in_s + self.motion.duration_s + p.lead_out_s) * self.fps)) + 1

    def time_of(self, frame_id: int) -> float:
        """Exposure time of a frame on the pass clock (lead-in before t = 0)."""
        return frame_id / self.fps - self.scene.cell.pass_profile.lead_in_s

    def grab(self, timeout: float = 1.0) -> Frame:
        if self._rng is None:
            raise CameraClosed("SimCamera is not open")
        while True:
            frame_id = self._next_id
            if frame_id >= self.frame_count:
                raise CameraClosed("the simulated pass has ended")
            self._next_id += 1
            dropped = self.drop_rate > 0 and self._rng.random() < self.drop_rate
            if not dropped:
                break
        t = self.time_of(frame_id)
        self.clock.now = t
        exposure_us, gain = self.exposure_us, self.gain
        model = exposed_model(self.scene.cell.image_model, exposure_us, gain)
        if self.scene.cell.effects.exposure_blur:
            # The frame's time stamp is the start of its exposure; it integrates what follows.
            instants = t + (np.arange(BLUR_SAMPLES) + 0.5) / BLUR_SAMPLES * exposure_us * 1e-6
            image, truth = self.scene.render_blurred(self.motion.tcp_position(instants),
                                                     self.grasp, self._rng, image_model=model)
        else:
            image, truth = self.scene.render(self.motion.tcp_position(t), self.grasp, self._rng,
                                             image_model=model)
        self.truths[frame_id] = truth
        return Frame(image, frame_id, t, exposure_us, gain)


@dataclass
class SimRobot(RobotConnection):
    """Reports the TCP pose of the pass at 500 Hz, up to the shared clock's "now".

    With ``effects`` (``simulator.effects.CellEffects``) it reports as a real robot does: on
    its own clock (offset and drifting from the camera's), its position with a little noise
    per sample and its orientation a little off. The shared clock is the camera's.
    """

    motion: PassMotion
    rotation: np.ndarray
    clock: SimClock = field(default_factory=SimClock)
    effects: CellEffects = field(default_factory=CellEffects)

    _not_connected = "SimRobot is not connected"

    def __post_init__(self):
        self._reported_rotation = self.effects.robot_rotation_error @ self.rotation

    def _position(self, t_robot: float) -> np.ndarray:
        """The reported position at a sample time on the robot's clock."""
        effects = self.effects
        position = self.motion.tcp_position(float(effects.camera_time(t_robot)))
        if effects.tcp_noise_mm > 0:
            k = int(round(t_robot * ROBOT_RATE_HZ))
            noise = np.random.default_rng([effects.seed, k & 0xFFFFFFFF]).standard_normal(3)
            position = position + effects.tcp_noise_mm * noise
        return position

    def _pose(self, t: float) -> TcpPose:
        return TcpPose(float(t), self._position(t), self._reported_rotation.copy())

    def _sample_range(self) -> tuple[float, float]:
        """Indices (k_first, k_last) of the 500 Hz samples reported so far and still kept;
        k_last < k_first when there is none."""
        now = float(self.effects.robot_time(float(self.clock.now)))
        start = float(self.effects.robot_time(-float(self.motion.profile.lead_in_s)))
        first = max(now - ROBOT_HISTORY_S, start)
        return float(math.ceil(first * ROBOT_RATE_HZ)), float(math.floor(now * ROBOT_RATE_HZ))

    def latest(self) -> TcpPose:
        self._require_connected()
        k_first, k_last = self._sample_range()
        if k_last < k_first:
            raise RuntimeError("no pose has arrived yet")
        return self._pose(k_last / ROBOT_RATE_HZ)

    def pose_at(self, t: float) -> TcpPose:
        """Linear interpolation between the 500 Hz samples around ``t``."""
        self._require_connected()
        k_first, k_last = self._sample_range()
        if k_last < k_first or not k_first / ROBOT_RATE_HZ <= t <= k_last / ROBOT_RATE_HZ:
            raise LookupError(f"t = {t:.4f} s is outside the robot's history")
        # The two samples around t (one sample when the history holds only one).
        k0 = min(max(float(math.floor(t * ROBOT_RATE_HZ)), k_first), max(k_last - 1, k_first))
        t0, t1 = k0 / ROBOT_RATE_HZ, min(k0 + 1, k_last) / ROBOT_RATE_HZ
        w = 0.0 if t1 == t0 else (t - t0) / (t1 - t0)
        p0, p1 = self._position(t0), self._position(t1)
        pos = (1 - w) * p0 + w * p1
        # as a reader of these reports would bound the chord (a pass's start is a corner)
        before, after = (k0 - 1) / ROBOT_RATE_HZ, (k0 + 2) / ROBOT_RATE_HZ
        deviation = 0.0 if not 0.0 < w < 1.0 else chord_deviation_mm(
            (before, self._position(before)) if k0 > k_first else None, (t0, p0), (t1, p1),
            (after, self._position(after)) if k0 + 2 <= k_last else None)
        return TcpPose(float(t), pos, self._reported_rotation.copy(), deviation)
