"""Record a pass to a folder, and read it back as a Camera and a Robot.

A recording holds what the scanner received during a pass (every camera frame, the robot's
pose samples) with the calibration and settings it ran with, so that the pass can be replayed
offline through the same pipeline (``Recording.camera()``, ``Recording.robot()``) and gives the
same cloud.

Format, version 1
-----------------
A folder with four files:

``recording.json``
    A JSON object::

        {"format": "flyscan-recording", "version": 1,
         "created_utc": "2025-01-31T12:00:00.000000Z",      # ISO 8601, UTC
         "camera": {"width": W, "height": H, "fps": F},     # px, px, frames/s
         "frames": N,                                       # frames in frames.u8
         "robot_samples": M,                                # rows of robot.npy
         "calibration": {...},   # the object scanner_core.calibration.save_calibration writes
         "settings": {...},      # free, JSON-serialisable (the settings of the pass)
         "notes": "..."}         # free text

``frames.u8``
    The images, raw uint8, shape (N, H, W), C order (frame after frame, row after row), no
    header: exactly N * H * W bytes.
``frames.csv``
    A header line ``frame_id,t,exposure_us,gain`` then N lines, one per frame in the order of
    ``frames.u8``: the camera's frame id (integer; a gap is a dropped frame), its time on the
    camera clock, s (written with Python's ``repr``, which reads back to the same float64), and
    the exposure and gain it was taken with (``nan`` when the camera does not say). Recordings
    whose header is ``frame_id,t`` (before exposure control) read as taken at unknown exposure.
``robot.npy``
    NumPy ``.npy`` (no pickle), float64, shape (M, 13), one row per robot sample in strictly
    increasing time: ``t`` (robot clock, s), ``x, y, z`` (TCP position in {B}, mm), then the
    rotation of {T} in {B} as its 3x3 matrix flattened row-major (``r00, r01, r02, r10, ...``;
    columns are the {T} axes).

A recording appears atomically: :class:`PassRecorder` writes into a hidden sibling folder
(``.<name>.<random>.partial``) and renames it into place on :meth:`PassRecorder.finish`; it
never replaces an existing folder.
"""
from __future__ import annotations

import csv
import datetime as _dt
import io
import json
import math
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scanner_core.calibration import Calibration, CalibrationError
from scanner_core.devices import CameraClosed, CameraTimeout, TcpPose
from scanner_core.fileio import save_json_atomic, write_bytes_atomic
from scanner_core.types import Frame

FORMAT_NAME = "flyscan-recording"
FORMAT_VERSION = 1
METADATA_FILE = "recording.json"
FRAMES_FILE = "frames.u8"
FRAME_INDEX_FILE = "frames.csv"
INDEX_COLUMNS = ("frame_id", "t", "exposure_us", "gain")
ROBOT_FILE = "robot.npy"
#: Columns of robot.npy: t, x, y, z, then the rotation matrix row-major.
ROBOT_COLUMNS = 13


class RecordingError(ValueError):
    """A recording folder is missing, incomplete, corrupt, of another format version, or
    would overwrite an existing folder."""


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

    Raises
    ------
    RecordingError
        ``folder`` exists already.
    """

    def __init__(self, folder, *, width: int, height: int, fps: float,
                 calibration: Calibration, settings: dict | None = None, notes: str = ""):
        self.folder = Path(folder)
        if int(width) <= 0 or int(height) <= 0:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be a positive number, got {fps!r}")
        self.width, self.height, self.fps = int(width), int(height), float(fps)
        self.calibration = calibration
        self.settings = dict(settings or {})
        self.notes = str(notes)
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
            save_json_atomic(self._tmp / METADATA_FILE, {
                "format": FORMAT_NAME, "version": FORMAT_VERSION, "created_utc": created,
                "camera": {"width": self.width, "height": self.height, "fps": self.fps},
                "frames": self._count, "robot_samples": len(robot),
                "calibration": self.calibration.to_dict(),
                "settings": self.settings, "notes": self.notes,
            })
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
        self._close_files()
        shutil.rmtree(self._tmp, ignore_errors=True)
        self._state = "aborted"

    def __enter__(self) -> "PassRecorder":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()
        elif self._state == "recording":
            self.finish()


# ---------------------------------------------------------------------------------------------
# Reading


@dataclass(frozen=True)
class Recording:
    """A recorded pass, validated (:func:`load_recording`).

    Attributes
    ----------
    folder : Path
    width, height : int
        Image size, px.
    fps : float
        Camera frame rate, frames/s.
    frame_ids : (N,) int64
    times : (N,) float64
        Camera clock, s.
    exposures : (N, 2) float64
        Exposure (us; NaN: unknown) and gain of each frame.
    robot_samples : (M, 13) float64
        t (robot clock, s), x, y, z (mm, {B}), rotation row-major.
    calibration : Calibration
    settings : dict
    notes : str
    created_utc : str
    version : int
    """

    folder: Path
    width: int
    height: int
    fps: float
    frame_ids: np.ndarray
    times: np.ndarray
    robot_samples: np.ndarray
    calibration: Calibration
    settings: dict = field(default_factory=dict)
    notes: str = ""
    created_utc: str = ""
    version: int = FORMAT_VERSION
    exposures: np.ndarray | None = None

    @property
    def frame_count(self) -> int:
        return int(len(self.frame_ids))

    @property
    def frames_path(self) -> Path:
        return self.folder / FRAMES_FILE

    def images(self) -> np.ndarray:
        """(N, H, W) uint8, read-only, mapped from ``frames.u8`` (not read into memory)."""
        if self.frame_count == 0:
            return np.zeros((0, self.height, self.width), np.uint8)
        return np.memmap(self.frames_path, dtype=np.uint8, mode="r",
                         shape=(self.frame_count, self.height, self.width))

    def camera(self, realtime: bool = False) -> "ReplayCamera":
        """A Camera giving the recorded frames; see :class:`ReplayCamera`."""
        return ReplayCamera(self, realtime=realtime)

    def robot(self) -> "ReplayRobot":
        """A Robot answering from the recorded samples; see :class:`ReplayRobot`."""
        return ReplayRobot(self.robot_samples)


def _fail(folder: Path, message: str):
    raise RecordingError(f"recording {folder}: {message}")


def _get(meta: dict, folder: Path, path: str, kind):
    """``meta[a][b]`` for ``path`` "a.b", checked to be of ``kind``; the field is named."""
    value = meta
    for key in path.split("."):
        if not isinstance(value, dict) or key not in value:
            _fail(folder, f"{METADATA_FILE} has no field `{path}`")
        value = value[key]
    if kind is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif kind is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    else:
        ok = isinstance(value, kind)
    if not ok:
        _fail(folder, f"{METADATA_FILE} field `{path}` must be {getattr(kind, '__name__', kind)}, "
                      f"got {json.dumps(value)[:80]}")
    return value


def _read_index(folder: Path, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    path = folder / FRAME_INDEX_FILE
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except FileNotFoundError:
        _fail(folder, f"missing {FRAME_INDEX_FILE}")
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        _fail(folder, f"cannot read {FRAME_INDEX_FILE}: {exc}")
    if not rows or rows[0] not in (list(INDEX_COLUMNS), list(INDEX_COLUMNS[:2])):
        _fail(folder, f"{FRAME_INDEX_FILE} must start with the header `{','.join(INDEX_COLUMNS)}`")
    columns = len(rows[0])
    if len(rows) - 1 != count:
        _fail(folder, f"{FRAME_INDEX_FILE} lists {len(rows) - 1} frames, {METADATA_FILE} says {count}")
    ids = np.empty(count, np.int64)
    times = np.empty(count, np.float64)
    exposures = np.tile([np.nan, 1.0], (count, 1))
    for i, row in enumerate(rows[1:]):
        try:
            if len(row) != columns:
                raise ValueError
            ids[i], times[i] = int(row[0]), float(row[1])
            if columns == 4:
                exposures[i] = float(row[2]), float(row[3])
        except (ValueError, OverflowError):
            _fail(folder, f"{FRAME_INDEX_FILE} line {i + 2} is not `{','.join(rows[0])}`: "
                          f"{','.join(row)[:80]!r}")
        if not math.isfinite(times[i]):
            _fail(folder, f"{FRAME_INDEX_FILE} line {i + 2}: time is not finite")
    return ids, times, exposures


def _read_robot(folder: Path, count: int) -> np.ndarray:
    path = folder / ROBOT_FILE
    try:
        samples = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        _fail(folder, f"missing {ROBOT_FILE}")
    except (OSError, ValueError, EOFError) as exc:
        _fail(folder, f"{ROBOT_FILE} is not a valid .npy file: {exc}")
    if samples.dtype != np.float64 or samples.ndim != 2 or samples.shape[1] != ROBOT_COLUMNS:
        _fail(folder, f"{ROBOT_FILE} must be float64 (M, {ROBOT_COLUMNS}), got {samples.dtype} "
                      f"{samples.shape}")
    if len(samples) != count:
        _fail(folder, f"{ROBOT_FILE} holds {len(samples)} samples, {METADATA_FILE} says {count}")
    if not np.all(np.isfinite(samples)):
        _fail(folder, f"{ROBOT_FILE} holds non-finite values")
    if np.any(np.diff(samples[:, 0]) <= 0):
        _fail(folder, f"{ROBOT_FILE}: sample times must increase strictly")
    return samples


def load_recording(folder) -> Recording:
    """Read and validate a recording (the frames themselves are mapped later, not read).

    Raises
    ------
    RecordingError
        No such folder, a missing file, another format or version, a corrupt
        ``recording.json`` (the field is named), ``frames.u8`` not N*H*W bytes, an index or
        robot file that does not match.
    """
    folder = Path(folder)
    if not folder.is_dir():
        _fail(folder, "no such folder")
    try:
        meta = json.loads((folder / METADATA_FILE).read_text())
    except FileNotFoundError:
        _fail(folder, f"missing {METADATA_FILE} (not a recording, or an unfinished one)")
    except (OSError, UnicodeDecodeError) as exc:
        _fail(folder, f"cannot read {METADATA_FILE}: {exc}")
    except json.JSONDecodeError as exc:
        _fail(folder, f"{METADATA_FILE} is not valid JSON: {exc}")
    if not isinstance(meta, dict):
        _fail(folder, f"{METADATA_FILE} must hold a JSON object")
    if meta.get("format") != FORMAT_NAME:
        _fail(folder, f"{METADATA_FILE} field `format` must be {FORMAT_NAME!r}, "
                      f"got {json.dumps(meta.get('format'))[:80]}")
    version = meta.get("version")
    if version != FORMAT_VERSION:
        _fail(folder, f"format version {json.dumps(version)[:40]}; this flyscan reads version "
                      f"{FORMAT_VERSION}")
    width = _get(meta, folder, "camera.width", int)
    height = _get(meta, folder, "camera.height", int)
    fps = float(_get(meta, folder, "camera.fps", float))
    count = _get(meta, folder, "frames", int)
    robot_count = _get(meta, folder, "robot_samples", int)
    if width <= 0 or height <= 0 or fps <= 0 or count < 0 or robot_count < 0:
        _fail(folder, f"{METADATA_FILE}: camera size and fps must be positive and counts "
                      "non-negative")
    created = _get(meta, folder, "created_utc", str)
    settings = _get(meta, folder, "settings", dict)
    notes = _get(meta, folder, "notes", str)
    try:
        calibration = Calibration.from_dict(_get(meta, folder, "calibration", dict))
    except CalibrationError as exc:
        _fail(folder, f"{METADATA_FILE} field `calibration`: {exc}")
    frames = folder / FRAMES_FILE
    try:
        size = frames.stat().st_size
    except FileNotFoundError:
        _fail(folder, f"missing {FRAMES_FILE}")
    expected = count * height * width
    if size != expected:
        _fail(folder, f"{FRAMES_FILE} holds {size} bytes, expected N*H*W = {count}*{height}*{width} "
                      f"= {expected} (truncated or not this recording's)")
    ids, times, exposures = _read_index(folder, count)
    robot = _read_robot(folder, robot_count)
    return Recording(folder, width, height, fps, ids, times, robot, calibration,
                     settings, notes, created, version, exposures)


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


class ReplayRobot:
    """A Robot answering from recorded samples.

    It knows the whole recording from the start (a live robot only knows the past): its
    answers for a time are the ones the live robot would have given once that time had
    passed. Not thread-safe for connect/disconnect; the look-ups only read.

    Parameters
    ----------
    samples : (M, 13) float64
        See the module docstring (robot.npy).
    """

    def __init__(self, samples: np.ndarray):
        samples = np.asarray(samples, dtype=np.float64)
        if samples.ndim != 2 or samples.shape[1] != ROBOT_COLUMNS:
            raise ValueError(f"robot samples must be (M, {ROBOT_COLUMNS}), got {samples.shape}")
        self._t = samples[:, 0].copy()
        self._p = samples[:, 1:4].copy()
        self._r = samples[:, 4:].reshape(-1, 3, 3).copy()
        self._connected = False

    def connect(self) -> None:
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    @property
    def connected(self) -> bool:
        return self._connected

    def _check(self) -> None:
        if not self._connected:
            raise RuntimeError("ReplayRobot is not connected")
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
        if not self._connected:
            raise RuntimeError("ReplayRobot is not connected")
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


__all__ = ["FORMAT_VERSION", "PassRecorder", "Recording", "RecordingError", "ReplayCamera",
           "ReplayRobot", "load_recording"]


# ---------------------------------------------------------------------------------------------
# Replay


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

    from scanner_core.exposure import ExposureParams
    from scanner_core.pipeline import PipelineParams, camera_frames, run_pass
    from scanner_core.trigger import TriggerParams

    settings = recording.settings
    if params is None:
        trigger = TriggerParams(**{**settings.get("trigger", {}), "arm_timeout_s": math.inf})
        params = replace(PipelineParams(), trigger=trigger,
                         stripe_method=settings.get("stripe_method", "cog"),
                         exposure=ExposureParams(mode=settings.get("exposure_mode", "fixed")))
    camera, robot = recording.camera(), recording.robot()
    camera.open()
    robot.connect()
    try:
        return run_pass(camera_frames(camera), recording.calibration, robot, params,
                        clock_offset_s=float(settings.get("clock_offset_s", 0.0)))
    finally:
        camera.close()
        robot.disconnect()
