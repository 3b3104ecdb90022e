"""A recorded pass replayed: its camera and robot, and the pass run again as it ran live.

``replay_pass`` runs a recording (``scanner_core.recording``) through the same pipeline
(``scanner_core.pipeline.run_pass``) with the settings it was recorded with, and ends it as
every pass ends (``scanner_core.pipeline.finish.finish_pass``): the cross-check against the recorded
robot samples from the cross-check state the live pass started from, the pose against the part
the recording holds (or one given), so that a replay reports what the live pass reported.
"""
from __future__ import annotations

import math
import time

import numpy as np

from scanner_core.devices import (CameraClosed, CameraTimeout, RobotConnection, TcpPose,
                                   chord_deviation_mm)
from scanner_core.types import Frame
from scanner_core.recording.format import ROBOT_COLUMNS
from scanner_core.recording.reader import Recording

__all__ = ["ReplayCamera", "ReplayRobot", "replay_recording", "replay_pass",
           "REPORTS_UNTIL_SETTING"]

#: The recording's setting that keeps the robot time of the newest report the live pass's
#: cross-check had (``scanner_core.pipeline.finish.check_against_robot``'s
#: ``reports_until_s``).
REPORTS_UNTIL_SETTING = "cross_check_reports_until_s"


class ReplayCamera:
    """A Camera giving a recording's frames, mapped from disk.

    As fast as they are read by default; with ``realtime`` paced by their recorded times (the
    first frame at once, frame i ``t_i - t_0`` after it; a recorded gap longer than the grab's
    timeout raises ``CameraTimeout``, as the live camera would have). ``CameraClosed`` after
    the last frame. Images are read-only views of the mapping (no copy). Not thread-safe.

    Parameters
    ----------
    recording : Recording
    realtime : bool
    """

    def __init__(self, recording: Recording, *, realtime: bool = False):
        self.recording = recording
        self.realtime = bool(realtime)
        self.width, self.height, self.fps = recording.width, recording.height, recording.fps
        self._images = None
        self._next = 0
        self._start = 0.0

    def __repr__(self) -> str:
        return f"ReplayCamera({str(self.recording.folder)!r}, realtime={self.realtime})"

    def open(self) -> None:
        self._images = self.recording.images()
        self._next = 0
        self._start = time.monotonic()

    def close(self) -> None:
        self._images = None

    def grab(self, timeout: float = 1.0) -> Frame:
        images = self._images
        if images is None:
            raise CameraClosed(f"replay of {self.recording.folder} is not open")
        i = self._next
        if i >= len(images):
            raise CameraClosed(f"the recording {self.recording.folder} has ended ({i} frames)")
        times = self.recording.times
        if self.realtime:
            wait = self._start + (times[i] - times[0]) - time.monotonic()
            if wait > timeout:
                time.sleep(timeout)
                raise CameraTimeout(f"no frame within {timeout:g} s (recorded gap)")
            if wait > 0:
                time.sleep(wait)
        self._next = i + 1
        # np.asarray: a plain read-only ndarray view (the memmap subclass buys nothing here).
        exposure = self.recording.exposures
        exposure_us, gain = (math.nan, 1.0) if exposure is None else exposure[i]
        return Frame(np.asarray(images[i]), int(self.recording.frame_ids[i]), float(times[i]),
                     float(exposure_us), float(gain))


class ReplayRobot(RobotConnection):
    """A Robot answering from recorded samples.

    It knows the whole recording from the start (a live robot only knows the past): its
    answers for a time are the ones the live robot would have given once that time had
    passed, whatever `reports_until_s`. Its newest report (:meth:`latest`) is the one the live
    pass's cross-check had when it ran, where the recording kept it: a check that ran before
    the robot's reports for the pass's last frames arrived is replayed on as many (the check
    reads the robot up to its newest report, ``scanner_core.pipeline.finish
    .check_against_robot``). Not thread-safe for connect/disconnect; the look-ups only read.

    Parameters
    ----------
    samples : (M, 13) float64
        See ``scanner_core.recording`` (robot.npy).
    reports_until_s : float, optional
        The robot time of the newest report the live cross-check had
        (``settings["cross_check_reports_until_s"]``, :meth:`of`); -inf: it had none; default
        the last sample's.
    """

    _not_connected = "ReplayRobot is not connected"

    def __init__(self, samples: np.ndarray, reports_until_s: float | None = None):
        samples = np.asarray(samples, dtype=np.float64)
        if samples.ndim != 2 or samples.shape[1] != ROBOT_COLUMNS:
            raise ValueError(f"robot samples must be (M, {ROBOT_COLUMNS}), got {samples.shape}")
        self._t = samples[:, 0].copy()
        self._p = samples[:, 1:4].copy()
        self._r = samples[:, 4:].reshape(-1, 3, 3).copy()
        if reports_until_s is not None and not (np.isfinite(reports_until_s)
                                                or reports_until_s == -np.inf):
            raise ValueError(f"reports_until_s must be finite or -inf, got {reports_until_s!r}")
        self._until = reports_until_s

    @classmethod
    def of(cls, recording: Recording) -> "ReplayRobot":
        """The robot of `recording`, its newest report the one its cross-check had (a
        recording made before the cut-off was kept: its last sample)."""
        settings = recording.settings
        if REPORTS_UNTIL_SETTING not in settings:
            return cls(recording.robot_samples)
        until = settings[REPORTS_UNTIL_SETTING]
        return cls(recording.robot_samples, -np.inf if until is None else float(until))

    def _check(self) -> None:
        self._require_connected()
        if not len(self._t):
            raise RuntimeError("the recording holds no robot sample")

    def latest(self) -> TcpPose:
        """The newest report the live cross-check had (the pose at its time); the last
        recorded sample where the recording does not say, or where that report lies past
        the samples. RuntimeError where the check had none."""
        self._check()
        until = self._until
        if until is None or until >= self._t[-1]:
            return TcpPose(float(self._t[-1]), self._p[-1].copy(), self._r[-1].copy())
        if until < self._t[0]:
            raise RuntimeError("no robot report had arrived when the recorded pass was checked")
        return self.pose_at(until)

    def pose_at(self, t: float) -> TcpPose:
        """The pose at robot time ``t``: positions interpolated linearly between the two
        samples around it (as the simulated robot does; ``TcpPose.interpolation_mm`` how far
        the path may bow from that chord, where the recorded robot's stream had a gap), the
        rotation slerped (kept as is when both samples hold the same one).

        Raises
        ------
        LookupError
            ``t`` is outside the recorded samples.
        """
        self._require_connected()
        ts = self._t
        if not len(ts):
            raise LookupError("the recording holds no robot sample")
        if not ts[0] <= t <= ts[-1]:
            raise LookupError(f"t = {t:.4f} s is outside the recorded robot samples "
                              f"[{ts[0]:.4f}, {ts[-1]:.4f}] s")
        if len(ts) == 1:
            return TcpPose(float(t), self._p[0].copy(), self._r[0].copy())
        k = min(int(np.searchsorted(ts, t, side="right")) - 1, len(ts) - 2)
        t0, t1 = ts[k], ts[k + 1]
        w = (t - t0) / (t1 - t0)
        position = (1 - w) * self._p[k] + w * self._p[k + 1]
        deviation = 0.0 if not 0.0 < w < 1.0 else chord_deviation_mm(
            (ts[k - 1], self._p[k - 1]) if k >= 1 else None, (t0, self._p[k]),
            (t1, self._p[k + 1]), (ts[k + 2], self._p[k + 2]) if k + 2 < len(ts) else None)
        r0, r1 = self._r[k], self._r[k + 1]
        if np.array_equal(r0, r1):
            rotation = r0.copy()
        else:
            from scipy.spatial.transform import Rotation, Slerp
            rotation = Slerp([t0, t1], Rotation.from_matrix(np.stack([r0, r1])))(t).as_matrix()
        return TcpPose(float(t), position, rotation, deviation)


def replay_recording(recording: Recording, params=None):
    """The scan of a recorded pass, run through the pipeline as it ran live, unfinished by a
    pose (:func:`replay_pass` finishes it).

    Parameters
    ----------
    recording : Recording
    params : scanner_core.pipeline.PipelineParams, optional
        Default: those the recording was made with
        (``scanner_core.pipeline.session.recorded_params``).

    Returns
    -------
    scanner_core.types.Scan
    """
    return replay_pass(recording, params=params, register=False).scan


def replay_pass(recording: Recording, part=None, *, params=None, pose_params=None,
                register: bool = True, **report_extra):
    """A recorded pass, run and finished as the live one was: the pass session
    (``scanner_core.pipeline.session.run_session``) on the recording's camera and robot.

    Parameters
    ----------
    recording : Recording
    part : scanner_core.cad.PartModel, optional
        Default: the part the recording holds (``Recording.part``); None there too: no pose,
        and the report says so.
    params : scanner_core.pipeline.PipelineParams, optional
        Default: those the recording was made with (``recorded_params``).
    pose_params : scanner_core.pose.registration.PoseParams, optional
    register : bool
        Ask for the pose (``finish_pass``).
    **report_extra
        Further ``report.json`` entries.

    Returns
    -------
    scanner_core.pipeline.finish.PassOutcome
        The frames placed with the clock offset the pass ran with, the cross-check run
        against the recorded robot samples from the state the live pass started from
        (``recorded_state``).
    """
    from scanner_core.pipeline.session import recorded_params, recorded_state, run_session

    settings = recording.settings
    if register and part is None:
        part = recording.part()
    return run_session(ReplayCamera(recording), ReplayRobot.of(recording),
                       recording.calibration,
                       params=recorded_params(recording) if params is None else params,
                       part_model=part, register=register, pose_params=pose_params,
                       state=recorded_state(recording),
                       clock_offset_s=float(settings.get("clock_offset_s", 0.0)),
                       control_exposure=False, scan_id=settings.get("scan_id"),
                       **{"part": settings.get("part"), **report_extra})
