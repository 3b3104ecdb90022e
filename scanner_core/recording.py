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
``part.npz`` (when the pass scanned a known part)
    NumPy ``.npz`` (no pickle): ``vertices`` (V, 3) float64 mm in {P}, ``faces`` (F, 3) int64,
    ``grasp`` (4, 4) float64, the nominal ^T X_P: the part's CAD model as the scanner held it
    (``scanner_core.cad.PartModel``), so that a replay registers the pass against the same
    model. ``recording.json`` then has ``"part": {"name", "units", "source", "file":
    "part.npz"}``; a recording without them replays without a pose unless a part is given.

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
PART_FILE = "part.npz"
#: Columns of robot.npy: t, x, y, z, then the rotation matrix row-major.
ROBOT_COLUMNS = 13
#: Robot samples are read back on this grid of the robot clock, Hz (UR controllers: 500 Hz).
ROBOT_SAMPLE_HZ = 500.0
#: ... from this long before the first frame to this long after the last, s.
ROBOT_MARGIN_S = 0.05


class RecordingError(ValueError):
    """A recording folder is missing, incomplete, corrupt, of another format version, or
    would overwrite an existing folder."""


def robot_samples(robot, t0: float, t1: float) -> list:
    """The robot's poses (``TcpPose``) on the sample grid (``ROBOT_SAMPLE_HZ``) between robot
    times t0 and t1: what it has of them."""
    poses = []
    for k in range(int(np.ceil(t0 * ROBOT_SAMPLE_HZ)), int(np.floor(t1 * ROBOT_SAMPLE_HZ)) + 1):
        try:
            poses.append(robot.pose_at(k / ROBOT_SAMPLE_HZ))
        except (LookupError, RuntimeError):
            continue
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
    part_info: dict | None = None

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

    def part(self):
        """The part the pass scanned (``scanner_core.cad.PartModel``), or None when the
        recording holds none. RecordingError when its file is missing or corrupt."""
        if self.part_info is None:
            return None
        from scanner_core.cad import PartError, saved_part

        path = self.folder / PART_FILE
        try:
            with np.load(path, allow_pickle=False) as data:
                return saved_part(data["vertices"], data["faces"], data["grasp"],
                                  name=str(self.part_info["name"]),
                                  units=str(self.part_info["units"]),
                                  source=str(self.part_info["source"]))
        except FileNotFoundError:
            _fail(self.folder, f"{METADATA_FILE} names a part but {PART_FILE} is missing")
        except (OSError, ValueError, KeyError, PartError) as exc:
            _fail(self.folder, f"{PART_FILE} is not a valid part: {exc}")


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
    part = meta.get("part")
    if part is not None:
        for key in ("name", "units", "source"):
            _get(meta, folder, f"part.{key}", str)
    return Recording(folder, width, height, fps, ids, times, robot, calibration,
                     settings, notes, created, version, exposures, part)


__all__ = ["FORMAT_VERSION", "PassRecorder", "Recording", "RecordingError", "load_recording",
           "robot_samples", "ROBOT_SAMPLE_HZ", "ROBOT_MARGIN_S"]
