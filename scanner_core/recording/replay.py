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

from scanner_core.devices import CameraClosed, CameraTimeout, RobotConnection, TcpPose
from scanner_core.types import Frame
from scanner_core.recording.format import ROBOT_COLUMNS
from scanner_core.recording.reader import Recording

__all__ = ["ReplayCamera", "ReplayRobot", "replay_recording", "replay_pass"]


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
    passed. Not thread-safe for connect/disconnect; the look-ups only read.

    Parameters
    ----------
    samples : (M, 13) float64
        See the module docstring (robot.npy).
    """

    _not_connected = "ReplayRobot is not connected"

    def __init__(self, samples: np.ndarray):
        samples = np.asarray(samples, dtype=np.float64)
        if samples.ndim != 2 or samples.shape[1] != ROBOT_COLUMNS:
            raise ValueError(f"robot samples must be (M, {ROBOT_COLUMNS}), got {samples.shape}")
        self._t = samples[:, 0].copy()
        self._p = samples[:, 1:4].copy()
        self._r = samples[:, 4:].reshape(-1, 3, 3).copy()

    def _check(self) -> None:
        self._require_connected()
        if not len(self._t):
            raise RuntimeError("the recording holds no robot sample")

    def latest(self) -> TcpPose:
        """The last recorded sample."""
        self._check()
        return TcpPose(float(self._t[-1]), self._p[-1].copy(), self._r[-1].copy())

    def pose_at(self, t: float) -> TcpPose:
        """The pose at robot time ``t``: positions interpolated linearly between the two
        samples around it (as the simulated robot does), the rotation slerped (kept as is when
        both samples hold the same one).

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
        r0, r1 = self._r[k], self._r[k + 1]
        if np.array_equal(r0, r1):
            rotation = r0.copy()
        else:
            from scipy.spatial.transform import Rotation, Slerp
            rotation = Slerp([t0, t1], Rotation.from_matrix(np.stack([r0, r1])))(t).as_matrix()
        return TcpPose(float(t), position, rotation)


def replay_recording(recording: Recording, params=None):
    """Run a recorded pass through the offline pipeline as it ran live.

    Parameters
    ----------
    recording : Recording
    params : scanner_core.pipeline.PipelineParams, optional
        Default: the stripe method and trigger settings the recording was made with
        (``settings["stripe_method"]``, ``settings["trigger"]``), with no arming timeout (the
        recording ends by itself).

    Returns
    -------
    scanner_core.types.Scan
        The scan of the recording's pass (``run_pass`` on the replayed camera and robot, with
        the clock offset the pass ran with, ``settings["clock_offset_s"]``).
    """
    from dataclasses import replace

    from scanner_core.pipeline.exposure import ExposureParams
    from scanner_core.pipeline import PipelineParams, camera_frames, run_pass
    from scanner_core.pipeline.trigger import TriggerParams

    settings = recording.settings
    if params is None:
        trigger = TriggerParams(**{**settings.get("trigger", {}), "arm_timeout_s": math.inf})
        params = replace(PipelineParams(), trigger=trigger,
                         stripe_method=settings.get("stripe_method", "cog"),
                         exposure=ExposureParams(mode=settings.get("exposure_mode", "fixed")))
    camera, robot = ReplayCamera(recording), ReplayRobot(recording.robot_samples)
    camera.open()
    robot.connect()
    try:
        return run_pass(camera_frames(camera), recording.calibration, robot, params,
                        clock_offset_s=float(settings.get("clock_offset_s", 0.0)))
    finally:
        camera.close()
        robot.disconnect()


def replay_pass(recording: Recording, part=None, *, params=None, pose_params=None,
                **report_extra):
    """A recorded pass, finished as the live one was (``scanner_core.pipeline.finish.finish_pass``).

    Parameters
    ----------
    recording : Recording
    part : scanner_core.cad.PartModel, optional
        Default: the part the recording holds (``Recording.part``); None there too: no pose.
    params : scanner_core.pipeline.PipelineParams, optional
        As for :func:`replay_recording`.
    pose_params : scanner_core.pose.registration.PoseParams, optional
    **report_extra
        Further ``report.json`` entries.

    Returns
    -------
    scanner_core.pipeline.finish.PassOutcome
        The cross-check runs against the recorded robot samples from the state the live pass
        started from (``settings["cross_check_state"]``; a recording made before it was kept:
        its clock offset, nothing learned).
    """
    from scanner_core.pipeline.finish import CrossCheckState, finish_pass
    from scanner_core.pipeline.trigger import EndReason

    settings = recording.settings
    scan = replay_recording(recording, params)
    state = CrossCheckState.from_dict(settings.get("cross_check_state") or {
        "clock_offset_s": float(settings.get("clock_offset_s", 0.0))})
    part = recording.part() if part is None else part
    robot = ReplayRobot(recording.robot_samples)
    robot.connect()
    try:
        return finish_pass(scan, EndReason(scan.end_reason) if scan.end_reason else None, robot,
                           state, part, pose_params=pose_params,
                           scan_id=settings.get("scan_id"), detail=scan.interrupted,
                           **report_extra)
    finally:
        robot.disconnect()
