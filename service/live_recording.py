"""Recording a live pass beside acquisition: frames go to disk from a thread of their own.

A pass of the reference cell is about 300 frames of 2.3 MB, 370 MB/s at 162 fps: written on
the acquisition thread it would make the camera's buffer overflow. The acquisition thread
only queues the frame (the image is not copied: cameras hand out a new array per frame), a
writer thread streams them to a ``PassRecorder``, and the pass's robot samples are read from
the robot's history when the pass has ended. The recording appears (atomically) after the
scan has been published and stored: it never delays a scan.
"""
from __future__ import annotations

import errno
import json
import logging
import queue
import threading
from pathlib import Path

from scanner_core.geometry.calibration import Calibration
from scanner_core.devices import Camera, Robot
from scanner_core.types import Frame
from scanner_core.recording import ROBOT_MARGIN_S, PassRecorder, robot_samples
from scanner_core.recording.replay import REPORTS_UNTIL_SETTING
from service.store import free_bytes

log = logging.getLogger("flyscan.recording")

#: The robot's samples are recorded up to the newest report the pass's cross-check read, when
#: it came at most this long after the pass (s): the check runs after the pose and waits for
#: the last frame's report; a cut-off much later is a clock offset gone wrong, whose samples
#: (and the look-ups that make them) would only hold up the finisher.
REPORTS_AFTER_PASS_S = 5.0


class LiveRecording:
    """One pass being recorded into ``folder`` (see ``scanner_core.recording`` for the format).

    Parameters
    ----------
    folder : Path
        Must not exist.
    keep_free_bytes : int
        The recording stops (and is removed at its end) rather than leave less than this free
        on its disk: the scan's own files must still fit.
    camera : Camera
        Gives the image size and fps.
    calibration : Calibration
        The calibration the pass runs with.
    settings : dict
        What the replay needs to run the pass as it ran (the clock offset, the cross-check's
        state, the pipeline's parameters), JSON-serialisable.
    part : scanner_core.cad.PartModel, optional
        The part the pass scans, kept with the recording so that a replay registers it.
    """

    def __init__(self, folder: Path, *, camera: Camera, calibration: Calibration,
                 settings: dict, part=None, keep_free_bytes: int = 0):
        self.folder = Path(folder)
        self.keep_free_bytes = int(keep_free_bytes)
        self._frame_bytes = int(camera.width) * int(camera.height)
        self._recorder = PassRecorder(self.folder, width=camera.width, height=camera.height,
                                      fps=camera.fps, calibration=calibration, settings=settings,
                                      part=part)
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._times: list[float] = []
        self.error: str | None = None
        self._thread = threading.Thread(target=self._write, name="flyscan-recorder",
                                        daemon=True)
        self._thread.start()

    def add(self, frame: Frame) -> None:
        """Queue one frame (from the acquisition thread; never blocks)."""
        self._times.append(frame.t)
        self._queue.put(frame)

    def _write(self) -> None:
        while (frame := self._queue.get()) is not None:
            if self.error is not None:
                continue  # drained, not written: the recording is lost already
            try:
                if free_bytes(self.folder.parent) - self._frame_bytes < self.keep_free_bytes:
                    # stopped before the scan's own files lack room: the scan goes on
                    raise OSError(errno.ENOSPC, f"stopped: less than "
                                                f"{self.keep_free_bytes / 2**20:.0f} MB would be "
                                                f"left free for the scans (disk_reserve_mb)")
                self._recorder.add_frame(frame)
            except (OSError, ValueError) as exc:
                self.error = f"frame {frame.frame_id}: {exc}"
                log.error("recording %s failed: %s", self.folder, self.error)

    def keep(self, name: str, value) -> None:
        """One more setting (JSON-serialisable), kept once the pass has ended: what the replay
        needs that the pass learned only at its end."""
        json.dumps(value, allow_nan=False)
        self._recorder.settings[name] = value

    def finish(self, robot: Robot, clock_offset_s: float) -> dict:
        """Wait for the frames to be written, add the robot's samples over the pass (and on
        to the newest report its cross-check read, `keep`'s ``REPORTS_UNTIL_SETTING``, within
        ``REPORTS_AFTER_PASS_S``), and move the recording into place. Returns what
        ``GET /scans/{id}`` shows of it."""
        self._queue.put(None)
        self._thread.join()
        if self.error is None and not self._times:
            self.error = "no frame arrived while the scan was armed"
        if self.error is not None:
            self._recorder.abort()
            return {"path": None, "error": self.error}
        try:
            end = max(self._times) + clock_offset_s + ROBOT_MARGIN_S
            samples = robot_samples(robot, min(self._times) + clock_offset_s - ROBOT_MARGIN_S,
                                    end)
            # Up to the newest report the pass's cross-check read, which its replay's robot
            # ends at, and that report itself (off the samples' grid on a real robot).
            until = self._recorder.settings.get(REPORTS_UNTIL_SETTING)
            if until is not None and until <= end + REPORTS_AFTER_PASS_S:
                if until > end:
                    samples += robot_samples(robot, end, until)
                try:
                    samples.append(robot.pose_at(until))
                except (LookupError, RuntimeError):  # gone from its history: the replay interpolates
                    pass
                samples.sort(key=lambda pose: pose.t)
            self._recorder.add_robot_poses(samples)
            path = self._recorder.finish()
        except (OSError, ValueError) as exc:
            self._recorder.abort()
            return {"path": None, "error": str(exc)}
        return {"path": str(path), "frames": self._recorder.frames,
                "robot_samples": self._recorder.robot_samples,
                "bytes": sum(f.stat().st_size for f in path.iterdir())}

    def abort(self) -> None:
        self._queue.put(None)
        self._thread.join()
        self._recorder.abort()
