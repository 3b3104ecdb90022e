"""The live simulated cell's camera and robot: ordinary devices on the cell's real clock.

Both are made by ``simulator.live.LiveSimCell`` and read its schedule of passes under its
lock. The camera delivers frame ``k`` at camera clock ``k / fps``, drawing only the image
model's stripe and marker (with fresh noise) over a frame of its background ring, from the
geometry the cell prepared; the robot samples its TCP on the cell's track every
``1 / rate_hz`` s of its own clock.
"""
from __future__ import annotations

import math
import threading
import time
from typing import TYPE_CHECKING

import numpy as np

from scanner_core.devices import (CameraClosed, CameraTimeout, RobotConnection, TcpPose,
                                   chord_deviation_mm)
from scanner_core.types import Frame
from simulator.cell import Cell
from simulator.frame_truth import frame_image
from simulator.imaging import (EXPOSURE_RANGE_US, GAIN_RANGE, NOMINAL_EXPOSURE_US,
                               background_image, check_exposure, exposed_model, render_image,
                               uniform_bytes)

if TYPE_CHECKING:
    from simulator.live import LiveSimCell

__all__ = ["LiveSimCamera", "LiveSimRobot"]


class LiveSimCamera:
    """The simulated camera on the live clock (``scanner_core.devices.Camera``).

    Frame ``k`` is exposed at camera clock ``k / fps``; ``grab`` returns the oldest frame not yet
    read, waiting for its exposure. Only the newest ``buffer_frames`` exposed frames are kept:
    a reader late by more loses the older ones (their ids are skipped, ``frames_lost`` counts
    them). Frame ids keep increasing for the life of the cell, across passes and re-opens.
    Its exposure and gain (``scanner_core.devices.ExposureControl``) apply from the next frame
    delivered. Made by :class:`LiveSimCell`.
    """

    exposure_range_us = EXPOSURE_RANGE_US
    gain_range = GAIN_RANGE

    def __init__(self, sim: LiveSimCell, *, seed: int, buffer_frames: int,
                 background_frames: int):
        cam = sim.cell.calibration.camera
        self.width, self.height = int(cam.width), int(cam.height)
        self.fps = sim.fps
        self.seed = seed
        self.buffer_frames = buffer_frames
        self.background_frames = background_frames
        self._sim = sim
        self._open = False
        self._stalled = False
        self._next_id = 0
        self._lost = 0
        self._delivered = 0
        self._rng: np.random.Generator | None = None
        self._ring: tuple[np.ndarray, ...] = ()
        self._ring_draws: tuple[np.ndarray, ...] = ()  # each ring frame's uniform bytes
        self._render_lock = threading.Lock()  # the generator is not thread-safe
        self.exposure_us, self.gain = NOMINAL_EXPOSURE_US, 1.0

    def set_exposure(self, exposure_us: float, gain: float = 1.0) -> None:
        """From the next frame delivered; ValueError outside the camera's ranges."""
        exposure_us, gain = check_exposure(exposure_us, gain)
        with self._sim._lock:  # a grab on another thread reads both under it
            self.exposure_us, self.gain = exposure_us, gain

    @property
    def is_open(self) -> bool:
        return self._open

    @property
    def frames_lost(self) -> int:
        """Frames lost since the cell was made: buffer overruns and stalls."""
        with self._sim._lock:
            return self._lost

    @property
    def frames_delivered(self) -> int:
        """Frames returned by ``grab`` since the cell was made."""
        with self._sim._lock:
            return self._delivered

    def open(self) -> None:
        """Start the cell's clock if needed, seed the noise and render the background ring."""
        if self._open:
            return
        rng = np.random.default_rng(self.seed)
        _warm_up_image_model(self._sim.cell)
        cam = self._sim.cell.calibration.camera
        draws, ring = [], []
        for _ in range(self.background_frames):
            draws.append(uniform_bytes(cam.height, cam.width, rng))
            image = background_image(draws[-1], self._sim.cell.image_model)
            image.setflags(write=False)  # shared by every idle frame that shows it
            ring.append(image)
        with self._sim._lock:
            started_here = self._sim._epoch is None
            self._sim._start_clock_locked()
            self._rng, self._ring, self._ring_draws = rng, tuple(ring), tuple(draws)
            # The first frame delivered is the first exposed after opening (frame 0 when this
            # opening started the clock).
            self._next_id = 0 if started_here else math.ceil(self._sim._now_locked() * self.fps)
            self._stalled = False
            self._open = True

    def close(self) -> None:
        """Stop delivering; a ``grab`` waiting in another thread raises CameraClosed."""
        with self._sim._lock:
            self._open = False
            self._ring, self._ring_draws = (), ()
            self._sim._lock.notify_all()

    def stall(self) -> None:
        """Fault injection: the camera stops delivering frames (``grab`` times out)."""
        with self._sim._lock:
            self._stalled = True
            self._sim._lock.notify_all()

    def resume(self) -> None:
        """End a stall: delivery resumes with the next exposure; the frames missed are lost."""
        with self._sim._lock:
            if self._stalled and self._open:
                upcoming = self._sim._exposed_id(self._sim._now_locked()) + 1
                if upcoming > self._next_id:
                    self._lost += upcoming - self._next_id
                    self._next_id = upcoming
            self._stalled = False
            self._sim._lock.notify_all()

    def grab(self, timeout: float | None = 1.0) -> Frame:
        """The next frame, waiting for its exposure.

        Parameters
        ----------
        timeout : float or None
            Longest wait, s; None waits for ever.

        Returns
        -------
        Frame
            ``image`` (H, W) uint8 (read-only between passes), ``frame_id``, and ``t``, the
            camera clock of its exposure, s.

        Raises
        ------
        CameraTimeout
            No frame within ``timeout`` (for instance while stalled).
        CameraClosed
            The camera is not open, or was closed while waiting.
        """
        sim = self._sim
        deadline = math.inf if timeout is None else time.monotonic() + max(float(timeout), 0.0)
        with sim._lock:
            while True:
                if not self._open:
                    raise CameraClosed("the simulated camera is not open")
                wait = math.inf
                if not self._stalled:
                    now = sim._now_locked()
                    newest = sim._exposed_id(now)
                    if self._next_id <= newest:
                        oldest_kept = newest - self.buffer_frames + 1
                        if self._next_id < oldest_kept:
                            self._lost += oldest_kept - self._next_id
                            self._next_id = oldest_kept
                        break
                    wait = self._next_id / self.fps - now
                remaining = deadline - time.monotonic()
                if remaining <= 0.0:
                    raise CameraTimeout(f"no frame within {timeout} s")
                sim._lock.wait(None if math.isinf(min(wait, remaining)) else min(wait, remaining))
            frame_id = self._next_id
            self._next_id += 1
            self._delivered += 1
            truth = sim._frame_source(frame_id)
            rng, ring, draws = self._rng, self._ring, self._ring_draws
            exposure_us, gain = self.exposure_us, self.gain
        model = exposed_model(sim.cell.image_model, exposure_us, gain)
        # A real camera's frame costs its reader nothing: a pass's frame is its stripe and LED
        # drawn over a ring frame's background, which leaves the reader most of a frame period.
        # Under another exposure or gain, that frame's draw through the exposed model's tables.
        slot = frame_id % len(ring)
        background = ring[slot] if model is sim.cell.image_model \
            else background_image(draws[slot], model)
        if truth is None:
            image = background
        else:
            with self._render_lock:
                image = frame_image(sim.cell, truth, rng, model, background)
        return Frame(image, frame_id, frame_id / self.fps, exposure_us, gain)


class LiveSimRobot(RobotConnection):
    """The simulated robot on the live clock (``scanner_core.devices.Robot``).

    Samples the TCP every ``1 / rate_hz`` s of its clock (the camera clock plus
    ``clock_offset_s``), up to now and back ``history_s``; ``pose_at`` interpolates linearly
    between them. It follows each pass's ``PassMotion`` and stands still between passes (where
    the last pass ended; before the first, where the default pass begins). Made by
    :class:`LiveSimCell`.
    """

    _not_connected = "the simulated robot is not connected"

    def __init__(self, sim: LiveSimCell, *, clock_offset_s: float, rate_hz: float,
                 history_s: float):
        self.clock_offset_s = clock_offset_s
        self.rate_hz = rate_hz
        self.history_s = history_s
        self._sim = sim
        self._rotation = np.array(sim.cell.gripper_rotation_b, dtype=np.float64)
        self._effects = sim.cell.effects
        self._rotation_error = self._effects.robot_rotation_error

    def connect(self) -> None:
        """Start the cell's clock if needed, and report from now on."""
        with self._sim._lock:
            self._sim._start_clock_locked()
            super().connect()

    def _history(self) -> tuple[int, int, tuple]:
        """Sample indices ``k_lo..k_hi`` (robot time ``k / rate_hz``) and the schedule (the
        passes and the hold)."""
        self._require_connected()
        now, passes, hold = self._sim._trajectory()
        now_r = now + self.clock_offset_s
        k_hi = math.floor(now_r * self.rate_hz)
        k_lo = math.ceil(max(now_r - self.history_s, self.clock_offset_s) * self.rate_hz)
        return k_lo, k_hi, (passes, hold)

    def _held(self, schedule: tuple, k: int):
        """The hold that sample ``k`` falls in, or None."""
        hold = schedule[1]
        if hold is not None and k / self.rate_hz - self.clock_offset_s >= hold.t_start:
            return hold
        return None

    def _sample(self, schedule: tuple, k: int) -> np.ndarray:
        """(3,) the reported TCP position of sample ``k``: on the passes' track, or a hold's
        with the robot's per-sample noise (seeded by the sample, as ``SimRobot``'s)."""
        hold = self._held(schedule, k)
        if hold is None:
            return self._sim._tcp_at(schedule[0], k / self.rate_hz - self.clock_offset_s)
        position = hold.tcp_b[:3, 3].copy()
        if self._effects.tcp_noise_mm > 0:
            noise = np.random.default_rng([self._effects.seed, k & 0xFFFFFFFF]).standard_normal(3)
            position += self._effects.tcp_noise_mm * noise
        return position

    def _rotation_of(self, schedule: tuple, k: int) -> np.ndarray:
        """The reported rotation of sample ``k``: a hold's, as the robot reports it (its
        orientation error), else the passes' (the true one, as before holds existed)."""
        hold = self._held(schedule, k)
        if hold is None:
            return self._rotation.copy()
        return self._rotation_error @ hold.tcp_b[:3, :3]

    def latest(self) -> TcpPose:
        """Newest sample; RuntimeError when not connected or none has arrived."""
        k_lo, k_hi, passes = self._history()
        if k_hi < k_lo:
            raise RuntimeError("no pose has arrived yet")
        return TcpPose(k_hi / self.rate_hz, self._sample(passes, k_hi),
                       self._rotation_of(passes, k_hi))

    def pose_at(self, t: float) -> TcpPose:
        """Pose at robot time ``t``, s, linearly interpolated between the samples around it.

        Raises
        ------
        LookupError
            ``t`` lies outside the history (older than ``history_s`` or in the future).
        """
        k_lo, k_hi, passes = self._history()
        t = float(t)
        if k_hi < k_lo or not (k_lo / self.rate_hz <= t <= k_hi / self.rate_hz):
            raise LookupError(f"t = {t:.4f} s is outside the robot's history")
        if k_lo == k_hi:
            return TcpPose(t, self._sample(passes, k_lo), self._rotation_of(passes, k_lo))
        k0 = min(max(math.floor(t * self.rate_hz), k_lo), k_hi - 1)
        t0, t1 = k0 / self.rate_hz, (k0 + 1) / self.rate_hz
        w = (t - t0) / (t1 - t0)
        p0, p1 = self._sample(passes, k0), self._sample(passes, k0 + 1)
        pos = (1.0 - w) * p0 + w * p1
        # as a reader of these reports would bound the chord (a pass's start is a corner)
        deviation = 0.0 if not 0.0 < w < 1.0 else chord_deviation_mm(
            ((k0 - 1) / self.rate_hz, self._sample(passes, k0 - 1)) if k0 > k_lo else None,
            (t0, p0), (t1, p1),
            ((k0 + 2) / self.rate_hz, self._sample(passes, k0 + 2)) if k0 + 2 <= k_hi else None)
        # The rotation is the nearer sample's: it changes only where a hold begins.
        return TcpPose(t, pos, self._rotation_of(passes, k0 if w < 0.5 else k0 + 1), deviation)


def _warm_up_image_model(cell: Cell) -> None:
    """Load the image model's compiled kernels (stripe and marker path included) on a tiny
    image, so that the first frame of the first pass is not late."""
    render_image(8, 8, cell.image_model, np.random.default_rng(0), stripe_cols=[4],
                 stripe_rows=[4.0], marker_xy=[[4.0, 4.0]])
