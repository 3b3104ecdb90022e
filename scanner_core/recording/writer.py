"""Record a pass to a folder as it arrives (the format: ``scanner_core.recording``).

:class:`PassRecorder` streams the frames to disk and keeps the robot's samples until
:meth:`PassRecorder.finish`, which writes the metadata (and the part, when there is one) and
moves the recording into place atomically; :func:`robot_samples` takes a robot's poses on the
recording's sample grid.
"""
from __future__ import annotations

import datetime as _dt
import io
import json
import math
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from scanner_core.geometry.calibration import Calibration
from scanner_core.devices import TcpPose
from scanner_core.fileio import save_json_atomic, write_bytes_atomic
from scanner_core.recording.format import (FORMAT_NAME, FORMAT_VERSION, FRAME_INDEX_FILE,
                                           FRAMES_FILE, INDEX_COLUMNS, METADATA_FILE, PART_FILE,
                                           ROBOT_COLUMNS, ROBOT_FILE, ROBOT_SAMPLE_HZ,
                                           RecordingError)
from scanner_core.pipeline.crosscheck import MAX_CHORD_DEVIATION_MM
from scanner_core.types import Frame

__all__ = ["PassRecorder", "robot_samples"]


def robot_samples(robot, t0: float, t1: float) -> list:
    """The robot's poses (``TcpPose``) on the sample grid (``ROBOT_SAMPLE_HZ``) between robot
    times t0 and t1: what it has of them. A pose interpolated over a chord that may lie
    farther than ``MAX_CHORD_DEVIATION_MM`` from the path (samples the live reader missed) is
    left out: the replay then sees the same gap, and checks no marker against it either."""
    poses = []
    for k in range(int(np.ceil(t0 * ROBOT_SAMPLE_HZ)), int(np.floor(t1 * ROBOT_SAMPLE_HZ)) + 1):
        try:
            pose = robot.pose_at(k / ROBOT_SAMPLE_HZ)
        except (LookupError, RuntimeError):
            continue
        if pose.interpolation_mm <= MAX_CHORD_DEVIATION_MM:
            poses.append(pose)
    return poses


def _pose_row(pose: TcpPose) -> np.ndarray:
    """A TcpPose -> one (13,) row of robot.npy."""
    row = np.empty(ROBOT_COLUMNS)
    row[0] = float(pose.t)
    row[1:4] = np.asarray(pose.position, dtype=np.float64).reshape(3)
    row[4:] = np.asarray(pose.rotation, dtype=np.float64).reshape(9)
    return row


class PassRecorder:
    """Writes a pass to ``folder`` as it arrives (see the module docstring for the format).

    Frames stream to disk (``add_frame`` keeps none in memory); robot samples (13 floats
    each, ~50 kB/s at 500 Hz) are kept until :meth:`finish`. Used as a context manager, it
    finishes on a normal exit and aborts on an exception. Not thread-safe: one thread adds.

    Parameters
    ----------
    folder : str or Path
        Where the recording will appear; must not exist. Its parent is created if needed.
    width, height : int
        Image size, px.
    fps : float
        Camera frame rate, frames/s.
    calibration : Calibration
        The calibration the pass ran with.
    settings : dict, optional
        Free JSON-serialisable settings of the pass.
    notes : str
        Free text.
    part : scanner_core.cad.PartModel, optional
        The part the pass scans (written as ``part.npz``).

    Raises
    ------
    RecordingError
        ``folder`` exists already.
    """

    def __init__(self, folder, *, width: int, height: int, fps: float,
                 calibration: Calibration, settings: dict | None = None, notes: str = "",
                 part=None):
        self.folder = Path(folder)
        if int(width) <= 0 or int(height) <= 0:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be a positive number, got {fps!r}")
        self.width, self.height, self.fps = int(width), int(height), float(fps)
        self.calibration = calibration
        self.settings = dict(settings or {})
        self.notes = str(notes)
        self.part = part
        # Fail now on what would only fail at finish(), not after a whole pass.
        json.dumps(self.settings, allow_nan=False)
        self._refuse_existing()
        self.folder.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = Path(tempfile.mkdtemp(dir=self.folder.parent, prefix=f".{self.folder.name}.",
                                          suffix=".partial"))
        self._frames = open(self._tmp / FRAMES_FILE, "wb")
        self._index = open(self._tmp / FRAME_INDEX_FILE, "w", newline="")
        self._index.write(",".join(INDEX_COLUMNS) + "\n")
        self._count = 0
        self._robot: list[np.ndarray] = []
        self._last_robot_t = -math.inf
        self._state = "recording"

    def _refuse_existing(self) -> None:
        if self.folder.exists() or self.folder.is_symlink():
            raise RecordingError(f"refusing to overwrite {self.folder}: it exists already")

    @property
    def frames(self) -> int:
        """Frames added so far."""
        return self._count

    @property
    def robot_samples(self) -> int:
        return len(self._robot)

    def _check_recording(self) -> None:
        if self._state != "recording":
            raise RuntimeError(f"the recorder of {self.folder} is {self._state}")

    def add_frame(self, frame: Frame) -> None:
        """Append one frame; ``frame.image`` must be (height, width) uint8."""
        self._check_recording()
        image = np.asarray(frame.image)
        if image.dtype != np.uint8 or image.shape != (self.height, self.width):
            raise ValueError(f"frame {frame.frame_id}: expected a ({self.height}, {self.width}) "
                             f"uint8 image, got {image.shape} {image.dtype}")
        t = float(frame.t)
        if not math.isfinite(t):
            raise ValueError(f"frame {frame.frame_id}: time {t} is not finite")
        self._frames.write(memoryview(np.ascontiguousarray(image)).cast("B"))
        self._index.write(f"{int(frame.frame_id)},{t!r},{float(frame.exposure_us)!r},"
                          f"{float(frame.gain)!r}\n")
        self._count += 1

    def add_robot_poses(self, poses) -> int:
        """Append robot samples (an iterable of ``TcpPose``) in time order.

        A sample not newer than the last one kept is skipped, so a poller may hand over the
        same pose twice. Returns how many were kept.
        """
        self._check_recording()
        kept = 0
        for pose in poses:
            row = _pose_row(pose)
            if not np.all(np.isfinite(row)):
                raise ValueError(f"robot sample at t = {row[0]} is not finite")
            if row[0] <= self._last_robot_t:
                continue
            self._robot.append(row)
            self._last_robot_t = row[0]
            kept += 1
        return kept

    def _close_files(self) -> None:
        for fh in (self._frames, self._index):
            if not fh.closed:
                fh.close()

    def finish(self) -> Path:
        """Write the metadata and move the recording into place; returns its folder.

        Raises
        ------
        RecordingError
            The folder has appeared meanwhile (the partial recording is removed).
        """
        self._check_recording()
        try:
            for fh in (self._frames, self._index):
                fh.flush()
                os.fsync(fh.fileno())
            self._close_files()
            robot = (np.stack(self._robot) if self._robot
                     else np.zeros((0, ROBOT_COLUMNS))).astype(np.float64)
            buffer = io.BytesIO()
            np.save(buffer, robot, allow_pickle=False)
            write_bytes_atomic(self._tmp / ROBOT_FILE, buffer.getvalue())
            created = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")
            meta = {
                "format": FORMAT_NAME, "version": FORMAT_VERSION, "created_utc": created,
                "camera": {"width": self.width, "height": self.height, "fps": self.fps},
                "frames": self._count, "robot_samples": len(robot),
                "calibration": self.calibration.to_dict(),
                "settings": self.settings, "notes": self.notes,
            }
            if self.part is not None:
                buffer = io.BytesIO()
                np.savez(buffer, vertices=np.asarray(self.part.vertices, np.float64),
                         faces=np.asarray(self.part.faces, np.int64),
                         grasp=np.asarray(self.part.grasp, np.float64))
                write_bytes_atomic(self._tmp / PART_FILE, buffer.getvalue())
                meta["part"] = {"name": self.part.name, "units": self.part.units,
                                "source": self.part.source, "file": PART_FILE}
            save_json_atomic(self._tmp / METADATA_FILE, meta)
            os.chmod(self._tmp, 0o755)  # mkdtemp makes 0700; recordings are meant to be shared
            self._refuse_existing()
            try:
                # rename() never replaces a non-empty folder (ENOTEMPTY/EEXIST): a recording
                # that appeared since the check above is safe too.
                os.rename(self._tmp, self.folder)
            except OSError as exc:
                raise RecordingError(f"refusing to overwrite {self.folder}: {exc.strerror}") from None
        except BaseException:
            self.abort()
            raise
        self._state = "finished"
        return self.folder

    def abort(self) -> None:
        """Drop the partial recording (nothing is left on disk). Idempotent."""
        if self._state == "finished":
            return
        try:
            self._close_files()  # may raise (a full disk refuses the buffered rest)
        except OSError:
            pass  # the files are dropped anyway: what they could not write does not matter
        finally:
            for fh in (self._frames, self._index):
                if not fh.closed:  # a close that raised leaves the file open on some systems
                    try:
                        fh.close()
                    except OSError:
                        pass
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._state = "aborted"

    def __enter__(self) -> "PassRecorder":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()
        elif self._state == "recording":
            self.finish()
