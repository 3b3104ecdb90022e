"""Read a recorded pass back, validated (the format: ``scanner_core.recording``).

:func:`load_recording` checks every file against the metadata (each failure a
``RecordingError`` naming the file and the field) and gives a :class:`Recording`, whose frames
are mapped from disk when asked for, not read; ``scanner_core.recording.replay`` replays it as a camera
and a robot.
"""
from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scanner_core.geometry.calibration import Calibration, CalibrationError
from scanner_core.recording.format import (FORMAT_NAME, FORMAT_VERSION, FRAME_INDEX_FILE,
                                           FRAMES_FILE, INDEX_COLUMNS, METADATA_FILE, PART_FILE,
                                           ROBOT_COLUMNS, ROBOT_FILE, RecordingError)

__all__ = ["Recording", "load_recording"]


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
