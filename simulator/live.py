"""The simulated cell in real time: the camera and robot of the daemon's simulated mode.

Offline (``simulator.devices``) the camera drives a simulated clock and renders every frame
from scratch. Live, frames must arrive at the camera's rate (162 fps) on the real clock while
the daemon processes them on the same two cores, and a full render (mesh section, Embree
visibility and the image model: about 4.5 ms) leaves too little of a 6.2 ms frame period. So
the work is split:

* :meth:`LiveSimCell.prepare_pass` computes the geometry of every frame of a pass once (its
  ``FrameTruth``: the stripe samples and marker pixels, all the image model needs) and keeps
  it in a small LRU cache per (part, misplacement, pass profile);
* each grabbed frame of a pass then costs only the image model with fresh noise
  (``render_image`` with the camera's own seeded generator, about 2.5 ms);
* between passes the camera cycles a small ring of noise-only frames rendered at ``open``;
  so does it for the frames of a pass that show nothing but background (before the marker
  enters the views and after it leaves them).

One clock is shared by the camera and the robot: seconds of ``time.monotonic()`` since the
cell's clock started (the first ``camera.open()`` or ``robot.connect()``). The camera exposes
frame ``k`` at ``k / fps`` and, like a real camera, keeps only the newest ``buffer_frames``
frames for a late reader: older ones are lost, their ids skipped. The robot reports its pose
every ``1 / 500`` s of its own clock, which is the camera clock plus ``clock_offset_s``.

Threads: ``grab`` from one acquisition thread, ``start_pass`` from another (an HTTP handler),
``pose_at`` and ``latest`` from workers. The schedule of passes is guarded by one lock;
rendering happens outside it.
"""
from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from scanner_core.devices import CameraClosed, CameraTimeout, TcpPose
from scanner_core.types import Frame
from simulator.cell import Cell, PassProfile
from simulator.devices import ROBOT_HISTORY_S, ROBOT_RATE_HZ
from simulator.imaging import (EXPOSURE_RANGE_US, GAIN_RANGE, NOMINAL_EXPOSURE_US,
                               check_exposure, exposed_model, render_image)
from simulator.motion import PassMotion
from simulator.parts import Part
from simulator.render import FrameTruth, PartScene, frame_image

__all__ = ["LiveSimCell", "LiveSimCamera", "LiveSimRobot", "LivePass", "PreparedPass",
           "PassInProgress", "TrackSegment", "tcp_on_track", "frame_image", "pass_frame_count",
           "CAMERA_BUFFER_FRAMES", "BACKGROUND_RING_FRAMES", "PASS_CACHE_SIZE"]

#: Frames the camera's on-board buffer holds for a late reader (a few frames, as in the
#: transport buffers of USB3 and GigE Vision cameras); older frames are lost.
CAMERA_BUFFER_FRAMES = 4
#: Noise-only frames rendered once at ``open`` and cycled between passes: enough that
#: consecutive idle frames differ, few enough to cost about 20 ms and 18 MB once. Rendering
#: fresh noise for every idle frame would take a third of a core at 162 fps.
BACKGROUND_RING_FRAMES = 8
#: Prepared passes kept (least recently used dropped first): a pass of the default profile is
#: about 300 frame truths, a few MB.
PASS_CACHE_SIZE = 4
#: The robot's motion towards a pass starts this many robot periods before the pass's first
#: frame, so that interpolating between its samples is exact for every frame of the pass
#: (before the lead-in the robot arrives at its initial speed: ``PassMotion.distance``).
ROBOT_LEAD_SAMPLES = 2
#: Extra time, s, for which a finished pass stays in the schedule beyond the robot's history
#: and the camera's buffer, so that no look-up at the edge of the history misses it.
SCHEDULE_MARGIN_S = 1.0


class PassInProgress(RuntimeError):
    """A pass was started while the previous one is still running."""


# --------------------------------------------------------------------------------------------
# Geometry of a frame, without the image model
# --------------------------------------------------------------------------------------------

def pass_frame_count(profile: PassProfile) -> int:
    """Frames a pass spans from lead-in to lead-out (as ``SimCamera.frame_count``)."""
    duration = PassMotion(profile).duration_s
    return int(np.floor((profile.lead_in_s + duration + profile.lead_out_s) * profile.fps)) + 1


# --------------------------------------------------------------------------------------------
# Passes: prepared (geometry) and scheduled (on the live clock)
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class TrackSegment:
    """The robot's motion through one pass, on the camera clock: pure and picklable.

    The simulated robot of the cell and the RTDE emulator (``simulator.rtde_emulator``, in
    another process) both compute the TCP from these, so that the two agree to the bit.

    Attributes
    ----------
    robot_start_t : float
        Camera clock, s, from which the robot follows this segment.
    t_zero : float
        Camera clock, s, of the pass's t = 0 (the end of its lead-in).
    t_last : float
        Camera clock, s, at which the robot stops (held there afterwards).
    profile : PassProfile
    """

    robot_start_t: float
    t_zero: float
    t_last: float
    profile: PassProfile
    # Built once: tcp_position runs for every robot sample.
    _motion: PassMotion = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "_motion", PassMotion(self.profile))

    def __getstate__(self):
        return (self.robot_start_t, self.t_zero, self.t_last, self.profile)

    def __setstate__(self, state):
        for name, value in zip(("robot_start_t", "t_zero", "t_last", "profile"), state):
            object.__setattr__(self, name, value)
        self.__post_init__()

    def tcp_position(self, t_cam: float) -> np.ndarray:
        """(3,) float64, mm in {B}: the TCP at camera clock ``t_cam``, s, held after ``t_last``."""
        return self._motion.tcp_position(min(t_cam, self.t_last) - self.t_zero)


def tcp_on_track(segments, idle_tcp_b: np.ndarray, t_cam: float) -> np.ndarray:
    """The TCP at camera clock ``t_cam`` given a schedule of segments.

    Parameters
    ----------
    segments : sequence of TrackSegment
        In time order (increasing ``robot_start_t``).
    idle_tcp_b : (3,) float64
        Where the robot waits before the first segment, mm in {B}.
    t_cam : float
        Camera clock, s.

    Returns
    -------
    (3,) float64
        TCP position in {B}, mm: that of the last segment started at ``t_cam``, else idle.
    """
    for seg in reversed(segments):
        if t_cam >= seg.robot_start_t:
            return seg.tcp_position(t_cam)
    return idle_tcp_b


@dataclass(frozen=True, eq=False)
class PreparedPass:
    """The geometry of every frame of one pass, rendered once.

    Attributes
    ----------
    part : Part
    misplacement : (4, 4) float64
        Applied in {T} on top of the nominal grasp, mm.
    true_grasp : (4, 4) float64
        ``misplacement @ part.grasp``: the true ^T X_P, mm.
    profile : PassProfile
    motion : PassMotion
    truths : tuple of FrameTruth, length ``frame_count``
        Frame ``j`` is exposed at pass time ``time_of(j)``.
    blank : (frame_count,) bool
        Frames with nothing but background (no stripe sample, the marker in no view): the
        camera shows a background-ring frame for them instead of rendering one.
    prepare_s : float
        Wall time the rendering took, s.
    """

    part: Part
    misplacement: np.ndarray
    true_grasp: np.ndarray
    profile: PassProfile
    motion: PassMotion
    truths: tuple
    blank: np.ndarray
    prepare_s: float

    @property
    def frame_count(self) -> int:
        return len(self.truths)

    def time_of(self, j: int) -> float:
        """Pass time of frame ``j`` (as ``SimCamera.time_of``: lead-in before t = 0), s."""
        return j / self.profile.fps - self.profile.lead_in_s


@dataclass(frozen=True, eq=False)
class LivePass:
    """A prepared pass placed on the live clock.

    Attributes
    ----------
    prepared : PreparedPass
    first_frame_id : int
        Camera frame id of the pass's frame 0; frame ``j`` of the pass is camera frame
        ``first_frame_id + j``.
    fps : float
    robot_start_t : float
        Camera clock, s, from which the robot follows the pass's motion (a few robot periods
        before the first frame).
    """

    prepared: PreparedPass
    first_frame_id: int
    fps: float
    robot_start_t: float

    @property
    def frame_count(self) -> int:
        return self.prepared.frame_count

    @property
    def last_frame_id(self) -> int:
        return self.first_frame_id + self.frame_count - 1

    @property
    def t_first(self) -> float:
        """Camera clock of the first frame's exposure, s."""
        return self.first_frame_id / self.fps

    @property
    def t_last(self) -> float:
        """Camera clock of the last frame's exposure, s; the robot stops there."""
        return self.last_frame_id / self.fps

    @property
    def t_zero(self) -> float:
        """Camera clock of the pass's t = 0 (the end of the lead-in), s."""
        return self.t_first + self.prepared.profile.lead_in_s

    @property
    def true_grasp(self) -> np.ndarray:
        return self.prepared.true_grasp

    @property
    def truths(self) -> dict:
        """Camera frame id -> FrameTruth, every frame of the pass (for evaluation only)."""
        return {self.first_frame_id + j: truth for j, truth in enumerate(self.prepared.truths)}

    @property
    def segment(self) -> TrackSegment:
        """The robot's motion through this pass (what an emulated robot needs of it)."""
        return self._segment

    def __post_init__(self):
        object.__setattr__(self, "_segment", TrackSegment(
            self.robot_start_t, self.t_zero, self.t_last, self.prepared.profile))

    def tcp_position(self, t_cam: float) -> np.ndarray:
        """(3,) float64, mm in {B}: the TCP at camera clock ``t_cam``, held after the pass."""
        return self._segment.tcp_position(t_cam)


# --------------------------------------------------------------------------------------------
# The cell
# --------------------------------------------------------------------------------------------

class LiveSimCell:
    """A simulated cell running on the real clock: ``camera`` and ``robot`` share its clock.

    Constructing does no I/O and no rendering; ``camera.open()`` renders the background ring.

    Parameters
    ----------
    cell : Cell
        The cell (``simulator.cell.load_cell()``); its pass profile is the default pass and its
        fps the camera's.
    seed : int
        Seeds the camera's image noise.
    clock_offset_s : float
        Added to every robot timestamp: robot clock = camera clock + offset, s.
    buffer_frames : int
        Frames the camera keeps for a late reader.
    background_frames : int
        Size of the ring of noise-only frames shown between passes.
    cache_size : int
        Prepared passes kept.
    robot_rate_hz : float
        Robot reporting rate.
    robot_history_s : float
        How far back ``robot.pose_at`` reaches, s.
    """

    def __init__(self, cell: Cell, *, seed: int = 0, clock_offset_s: float = 0.0,
                 buffer_frames: int = CAMERA_BUFFER_FRAMES,
                 background_frames: int = BACKGROUND_RING_FRAMES,
                 cache_size: int = PASS_CACHE_SIZE, robot_rate_hz: float = ROBOT_RATE_HZ,
                 robot_history_s: float = ROBOT_HISTORY_S):
        if int(buffer_frames) < 1:
            raise ValueError(f"`buffer_frames` must be >= 1, got {buffer_frames}")
        if int(background_frames) < 1:
            raise ValueError(f"`background_frames` must be >= 1, got {background_frames}")
        if int(cache_size) < 1:
            raise ValueError(f"`cache_size` must be >= 1, got {cache_size}")
        if not (robot_rate_hz > 0 and robot_history_s > 0):
            raise ValueError("`robot_rate_hz` and `robot_history_s` must be > 0, got "
                             f"{robot_rate_hz}, {robot_history_s}")
        if not math.isfinite(clock_offset_s):
            raise ValueError(f"`clock_offset_s` must be finite, got {clock_offset_s}")
        self.cell = cell
        self.fps = float(cell.pass_profile.fps)
        self.cache_size = int(cache_size)
        self._lock = threading.Condition()
        self._epoch: float | None = None
        self._passes: list[LivePass] = []  # in time order, pruned to what the history needs
        self._keep_s = max(robot_history_s, buffer_frames / self.fps) + SCHEDULE_MARGIN_S
        self._cache: OrderedDict = OrderedDict()
        self._prepare_lock = threading.Lock()
        profile = cell.pass_profile
        # Before the first pass the robot waits where the default pass begins.
        self._idle_tcp_b = PassMotion(profile).tcp_position(-profile.lead_in_s)
        self.camera = LiveSimCamera(self, seed=seed, buffer_frames=int(buffer_frames),
                                    background_frames=int(background_frames))
        self.robot = LiveSimRobot(self, clock_offset_s=float(clock_offset_s),
                                  rate_hz=float(robot_rate_hz), history_s=float(robot_history_s))

    # -- clock ---------------------------------------------------------------------------------
    def now(self) -> float:
        """Camera clock, s since the cell's clock started."""
        with self._lock:
            return self._now_locked()

    def start_clock(self) -> float:
        """Start the cell's clock now if it has not started; returns its epoch, the
        ``time.monotonic()`` of camera clock 0 (system-wide: another process may use it)."""
        with self._lock:
            self._start_clock_locked()
            return self._epoch

    def _now_locked(self) -> float:
        if self._epoch is None:
            raise RuntimeError("the simulated cell's clock starts when the camera is opened "
                               "or the robot connected")
        return time.monotonic() - self._epoch

    def _start_clock_locked(self) -> None:
        if self._epoch is None:
            self._epoch = time.monotonic()

    def _exposed_id(self, now: float) -> int:
        """Newest frame exposed at camera clock ``now``."""
        return math.floor(now * self.fps)

    # -- passes ----------------------------------------------------------------------------------
    def prepare_pass(self, part: Part, misplacement=None, *, profile: PassProfile | None = None
                     ) -> PreparedPass:
        """Render the geometry of every frame of a pass, or take it from the cache.

        Parameters
        ----------
        part : Part
        misplacement : (4, 4) float64, optional
            In {T} on top of the nominal grasp (X_T = R X_P + t), mm; default identity.
        profile : PassProfile, optional
            Default the cell's; its fps must be the camera's.

        Returns
        -------
        PreparedPass
        """
        profile = self.cell.pass_profile if profile is None else profile
        if profile.fps != self.fps:
            raise ValueError(f"the pass profile's fps ({profile.fps}) must be the camera's "
                             f"({self.fps})")
        misplacement = _check_misplacement(misplacement)
        # Keyed by the part object itself: the entry holds it, so its id is not reused.
        key = (id(part), misplacement.tobytes(), profile)
        with self._prepare_lock:
            hit = self._cache.get(key)
            if hit is not None and hit.part is part:
                self._cache.move_to_end(key)
                return hit
            prepared = _prepare(part, self.cell, misplacement, profile)
            self._cache[key] = prepared
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
            return prepared

    def start_pass(self, part: Part, misplacement=None, *, profile: PassProfile | None = None
                   ) -> LivePass:
        """Send the robot through the sheet with ``part``, from the camera's next frame on.

        Prepares the pass first when it is not cached (this may take a second). The pass
        begins at the next frame exposed at least ``ROBOT_LEAD_SAMPLES`` robot periods from
        now (the next frame, or the one after), so that no pose the robot has already reported
        changes.

        Raises
        ------
        CameraClosed
            The camera is not open.
        PassInProgress
            The previous pass has not ended.
        """
        prepared = self.prepare_pass(part, misplacement, profile=profile)
        lead_s = ROBOT_LEAD_SAMPLES / self.robot.rate_hz
        with self._lock:
            if not self.camera.is_open:
                raise CameraClosed("open the camera before starting a pass")
            now = self._now_locked()
            if self._passes and self._exposed_id(now) < self._passes[-1].last_frame_id:
                raise PassInProgress("the previous simulated pass has not ended")
            first = math.ceil((now + lead_s) * self.fps)
            if self._passes:
                first = max(first, self._passes[-1].last_frame_id + 1)
            live = LivePass(prepared, first, self.fps, first / self.fps - lead_s)
            self._passes.append(live)
            # Drop passes that neither the robot's history nor the camera's buffer can reach.
            while len(self._passes) > 1 and self._passes[1].robot_start_t < now - self._keep_s:
                self._passes.pop(0)
        return live

    @property
    def last_pass(self) -> LivePass | None:
        """The pass started last, None before the first."""
        with self._lock:
            return self._passes[-1] if self._passes else None

    @property
    def pass_active(self) -> bool:
        """A pass is started and its last frame not yet exposed."""
        with self._lock:
            return bool(self._passes) and (
                self._exposed_id(self._now_locked()) < self._passes[-1].last_frame_id)

    @property
    def pass_done(self) -> bool:
        """The last pass started has exposed its last frame (False before the first)."""
        with self._lock:
            return bool(self._passes) and (
                self._exposed_id(self._now_locked()) >= self._passes[-1].last_frame_id)

    @property
    def last_pass_truths(self) -> dict:
        """Camera frame id -> FrameTruth of the last pass (evaluation only); empty before."""
        last = self.last_pass
        return {} if last is None else last.truths

    @property
    def last_true_grasp(self) -> np.ndarray | None:
        """(4, 4) float64: the true ^T X_P of the last pass, mm; None before the first."""
        last = self.last_pass
        return None if last is None else last.true_grasp.copy()

    # -- what the devices see ----------------------------------------------------------------
    def _frame_source(self, frame_id: int) -> FrameTruth | None:
        """The geometry of camera frame ``frame_id``; None for a background frame (between
    passes, or blank in its pass). Under the lock."""
        for p in reversed(self._passes):
            if p.first_frame_id <= frame_id <= p.last_frame_id:
                j = frame_id - p.first_frame_id
                return None if p.prepared.blank[j] else p.prepared.truths[j]
            if p.last_frame_id < frame_id:
                return None
        return None

    def _trajectory(self) -> tuple[float, tuple]:
        """Camera clock now and the passes, as one consistent snapshot."""
        with self._lock:
            return self._now_locked(), tuple(self._passes)

    @property
    def idle_tcp_b(self) -> np.ndarray:
        """(3,) float64: where the robot waits before the first pass, mm in {B}."""
        return self._idle_tcp_b.copy()

    def _tcp_at(self, passes: tuple, t_cam: float) -> np.ndarray:
        """(3,) float64: TCP in {B}, mm, at camera clock ``t_cam`` given the schedule."""
        return tcp_on_track([p.segment for p in passes], self._idle_tcp_b, t_cam)


def _check_misplacement(misplacement) -> np.ndarray:
    if misplacement is None:
        return np.eye(4)
    m = np.array(misplacement, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ValueError(f"`misplacement` must be a finite (4, 4) transform, got shape {m.shape}")
    m.setflags(write=False)
    return m


def _prepare(part: Part, cell: Cell, misplacement: np.ndarray, profile: PassProfile
             ) -> PreparedPass:
    t0 = time.perf_counter()
    scene = PartScene(part, cell)
    motion = PassMotion(profile)
    true_grasp = misplacement @ part.grasp
    n = pass_frame_count(profile)
    truths = tuple(scene.geometry(motion.tcp_position(j / profile.fps - profile.lead_in_s),
                               true_grasp) for j in range(n))
    blank = np.array([len(t.stripe_columns) == 0 and np.all(np.isnan(t.marker_pixels))
                      for t in truths], dtype=bool)
    for a in (true_grasp, blank):
        a.setflags(write=False)
    return PreparedPass(part, misplacement, true_grasp, profile, motion, truths, blank,
                        time.perf_counter() - t0)


# --------------------------------------------------------------------------------------------
# The devices
# --------------------------------------------------------------------------------------------

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
        ring = []
        for _ in range(self.background_frames):
            image = frame_image(self._sim.cell, None, rng)
            image.setflags(write=False)  # shared by every idle frame that shows it
            ring.append(image)
        with self._sim._lock:
            started_here = self._sim._epoch is None
            self._sim._start_clock_locked()
            self._rng, self._ring = rng, tuple(ring)
            # The first frame delivered is the first exposed after opening (frame 0 when this
            # opening started the clock).
            self._next_id = 0 if started_here else math.ceil(self._sim._now_locked() * self.fps)
            self._stalled = False
            self._open = True

    def close(self) -> None:
        """Stop delivering; a ``grab`` waiting in another thread raises CameraClosed."""
        with self._sim._lock:
            self._open = False
            self._ring = ()
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
            rng, ring = self._rng, self._ring
            exposure_us, gain = self.exposure_us, self.gain
        model = exposed_model(sim.cell.image_model, exposure_us, gain)
        if truth is None and model is sim.cell.image_model:
            image = ring[frame_id % len(ring)]
        else:
            with self._render_lock:
                image = frame_image(sim.cell, truth, rng, model)
        return Frame(image, frame_id, frame_id / self.fps, exposure_us, gain)


class LiveSimRobot:
    """The simulated robot on the live clock (``scanner_core.devices.Robot``).

    Samples the TCP every ``1 / rate_hz`` s of its clock (the camera clock plus
    ``clock_offset_s``), up to now and back ``history_s``; ``pose_at`` interpolates linearly
    between them. It follows each pass's ``PassMotion`` and stands still between passes (where
    the last pass ended; before the first, where the default pass begins). Made by
    :class:`LiveSimCell`.
    """

    def __init__(self, sim: LiveSimCell, *, clock_offset_s: float, rate_hz: float,
                 history_s: float):
        self.clock_offset_s = clock_offset_s
        self.rate_hz = rate_hz
        self.history_s = history_s
        self._sim = sim
        self._rotation = np.array(sim.cell.gripper_rotation_b, dtype=np.float64)
        self._connected = False

    def connect(self) -> None:
        with self._sim._lock:
            self._sim._start_clock_locked()
            self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    @property
    def connected(self) -> bool:
        return self._connected

    def _history(self) -> tuple[int, int, tuple]:
        """Sample indices ``k_lo..k_hi`` (robot time ``k / rate_hz``) and the schedule."""
        if not self._connected:
            raise RuntimeError("the simulated robot is not connected")
        now, passes = self._sim._trajectory()
        now_r = now + self.clock_offset_s
        k_hi = math.floor(now_r * self.rate_hz)
        k_lo = math.ceil(max(now_r - self.history_s, self.clock_offset_s) * self.rate_hz)
        return k_lo, k_hi, passes

    def _sample(self, passes: tuple, k: int) -> np.ndarray:
        return self._sim._tcp_at(passes, k / self.rate_hz - self.clock_offset_s)

    def latest(self) -> TcpPose:
        """Newest sample; RuntimeError when not connected or none has arrived."""
        k_lo, k_hi, passes = self._history()
        if k_hi < k_lo:
            raise RuntimeError("no pose has arrived yet")
        return TcpPose(k_hi / self.rate_hz, self._sample(passes, k_hi), self._rotation.copy())

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
            return TcpPose(t, self._sample(passes, k_lo), self._rotation.copy())
        k0 = min(max(math.floor(t * self.rate_hz), k_lo), k_hi - 1)
        t0, t1 = k0 / self.rate_hz, (k0 + 1) / self.rate_hz
        w = (t - t0) / (t1 - t0)
        pos = (1.0 - w) * self._sample(passes, k0) + w * self._sample(passes, k0 + 1)
        return TcpPose(t, pos, self._rotation.copy())


def _warm_up_image_model(cell: Cell) -> None:
    """Load the image model's compiled kernels (stripe and marker path included) on a tiny
    image, so that the first frame of the first pass is not late."""
    render_image(8, 8, cell.image_model, np.random.default_rng(0), stripe_cols=[4],
                 stripe_rows=[4.0], marker_xy=[[4.0, 4.0]])
