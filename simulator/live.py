"""The simulated cell in real time: the camera and robot of the daemon's simulated mode.

Offline (``simulator.devices``) the camera drives a simulated clock and renders every frame
from scratch. Live, frames must arrive at the camera's rate (162 fps) on the real clock while
the daemon processes them on the same two cores, and a full render (mesh section, Embree
visibility and the image model: about 4.5 ms) leaves too little of a 6.2 ms frame period. So
the work is split:

* :meth:`LiveSimCell.prepare_pass` computes the geometry of every frame of a pass once (its
  ``FrameTruth``: the stripe samples and marker pixels, all the image model needs) and keeps
  it in a small LRU cache per (part, misplacement, pass profile);
* between passes the camera cycles a small ring of noise-only frames rendered at ``open``;
  so does it for the frames of a pass that show nothing but background (before the marker
  enters the views and after it leaves them);
* each grabbed frame of a pass that shows the stripe or the marker is the ring's background
  with the pixels of their supports drawn afresh (``render_image(..., background=)`` with the
  camera's own seeded generator): a copy and a few thousand pixels, where a whole frame's
  noise took as long as the frame period on a machine that copies a frame in 0.2 ms. Under
  another exposure or gain than the cell's own, the background is the same ring frame's
  uniform draw through that model's tables (``background_image``).

One clock is shared by the camera and the robot: seconds of ``time.monotonic()`` since the
cell's clock started (the first ``camera.open()`` or ``robot.connect()``). The camera exposes
frame ``k`` at ``k / fps`` and, like a real camera, keeps only the newest ``buffer_frames``
frames for a late reader: older ones are lost, their ids skipped. The robot reports its pose
every ``1 / 500`` s of its own clock, which is the camera clock plus ``clock_offset_s``.

Threads: ``grab`` from one acquisition thread, ``start_pass`` from another (an HTTP handler),
``pose_at`` and ``latest`` from workers. The schedule of passes is guarded by one lock;
rendering happens outside it.

The parts: the robot's track in ``simulator.track``, the prepared and placed passes in
``simulator.live_pass``, the camera and the robot in ``simulator.live_devices``. This module
holds the cell (:class:`LiveSimCell`: its clock and its schedule of passes) and gathers the
public names of the four.
"""
from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from scanner_core.devices import CameraClosed
from simulator.cell import Cell, PassProfile
from simulator.devices import ROBOT_HISTORY_S, ROBOT_RATE_HZ
from simulator.frame_truth import FrameTruth, frame_image
from simulator.live_devices import LiveSimCamera, LiveSimRobot
from simulator.live_pass import LivePass, PreparedPass, _check_misplacement, _prepare
from simulator.motion import PassMotion
from simulator.parts import Part
from simulator.track import TrackSegment, pass_frame_count, tcp_on_track

__all__ = ["LiveSimCell", "LiveSimCamera", "LiveSimRobot", "LivePass", "PreparedPass",
           "PassInProgress", "Hold", "TrackSegment", "tcp_on_track", "frame_image", "pass_frame_count",
           "CAMERA_BUFFER_FRAMES", "BACKGROUND_RING_FRAMES", "PASS_CACHE_SIZE"]

#: Frames the camera keeps for a late reader; older frames are lost. As many as the real
#: camera path queues: the Basler camera's grab engine is given 16 buffers
#: (``service.pylon_camera.GRAB_BUFFERS``, 0.1 s at 162 fps; pylon's own default is 10), which
#: its driver fills whatever the Python side does. With 4 (25 ms) the simulated camera lost
#: frames to stalls of the reader the real one rides out: 1 of 20 passes with no client on
#: an idle machine, 8 of 100 under the web load of bench abuse's target.
CAMERA_BUFFER_FRAMES = 16
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


@dataclass(frozen=True)
class Hold:
    """The robot holding the TCP still at a pose (a calibration session's step).

    From camera frame ``first_frame_id`` (camera clock ``t_start``) until a pass starts, the
    camera shows ``truth`` (None: background) and the robot reports ``tcp_b`` ((4, 4) ^B X_T,
    mm), as a real robot does: with its per-sample noise and its orientation error
    (``simulator.effects``).
    """

    first_frame_id: int
    t_start: float
    tcp_b: np.ndarray
    truth: FrameTruth | None


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
        self._hold: Hold | None = None  # a calibration step's pose, until the next pass
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
            self._hold = None
            # Drop passes that neither the robot's history nor the camera's buffer can reach.
            while len(self._passes) > 1 and self._passes[1].robot_start_t < now - self._keep_s:
                self._passes.pop(0)
        return live

    def hold(self, tcp_b, truth: FrameTruth | None) -> Hold:
        """Hold the TCP still at ``tcp_b`` ((4, 4) ^B X_T, mm) from the camera's next frame on,
        the camera showing ``truth`` (``simulator.calsession.step_truth``), until the next
        pass; as :meth:`start_pass`, from the next frame exposed at least ``ROBOT_LEAD_SAMPLES``
        robot periods from now. PassInProgress while a pass runs."""
        tcp_b = np.array(tcp_b, dtype=np.float64)
        if tcp_b.shape != (4, 4) or not np.all(np.isfinite(tcp_b)):
            raise ValueError(f"`tcp_b` must be a finite (4, 4) pose, got shape {tcp_b.shape}")
        lead_s = ROBOT_LEAD_SAMPLES / self.robot.rate_hz
        with self._lock:
            now = self._now_locked()
            if self._passes and self._exposed_id(now) < self._passes[-1].last_frame_id:
                raise PassInProgress("the simulated robot is in a pass")
            first = math.ceil((now + lead_s) * self.fps)
            self._hold = Hold(first, first / self.fps - lead_s, tcp_b, truth)
            return self._hold

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
        hold = self._hold
        if hold is not None and frame_id >= hold.first_frame_id:
            return hold.truth
        for p in reversed(self._passes):
            if p.first_frame_id <= frame_id <= p.last_frame_id:
                j = frame_id - p.first_frame_id
                return None if p.prepared.blank[j] else p.prepared.truths[j]
            if p.last_frame_id < frame_id:
                return None
        return None

    def _trajectory(self) -> tuple[float, tuple, Hold | None]:
        """Camera clock now, the passes and the hold, as one consistent snapshot."""
        with self._lock:
            return self._now_locked(), tuple(self._passes), self._hold

    @property
    def idle_tcp_b(self) -> np.ndarray:
        """(3,) float64: where the robot waits before the first pass, mm in {B}."""
        return self._idle_tcp_b.copy()

    def _tcp_at(self, passes: tuple, t_cam: float) -> np.ndarray:
        """(3,) float64: TCP in {B}, mm, at camera clock ``t_cam`` given the schedule."""
        return tcp_on_track([p.segment for p in passes], self._idle_tcp_b, t_cam)
