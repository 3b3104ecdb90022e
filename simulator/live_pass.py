"""A pass of the live simulated cell: its frames' geometry rendered once, then placed on the
live clock.

``_prepare`` renders the geometry of every frame of a pass (``simulator.render.PartScene``: its
``FrameTruth``, all the image model needs) into a :class:`PreparedPass`, which
``simulator.live.LiveSimCell`` keeps in a small cache; :class:`LivePass` places a prepared pass
on the cell's clock, with the robot's motion through it (``simulator.track.TrackSegment``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from simulator.cell import Cell, PassProfile
from simulator.motion import PassMotion
from simulator.parts import Part
from simulator.render import PartScene
from simulator.track import TrackSegment, pass_frame_count

__all__ = ["PreparedPass", "LivePass"]


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
