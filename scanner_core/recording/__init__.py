"""Record a pass to a folder, and read it back as a Camera and a Robot.

A recording holds what the scanner received during a pass (every camera frame, the robot's
pose samples) with the calibration and settings it ran with, so that the pass can be replayed
offline through the same pipeline (``scanner_core.recording.replay``: the recording as a camera and a
robot) and gives the same cloud.

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
         "calibration": {...},   # the object scanner_core.geometry.calibration.save_calibration writes
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

The parts live in modules of their own: the format's names and its error in
``scanner_core.recording.format``, the writer (:class:`PassRecorder`, :func:`robot_samples`)
in ``scanner_core.recording.writer``, the reader (:class:`Recording`, :func:`load_recording`)
in ``scanner_core.recording.reader``. This module describes the format and gathers their
public names.
"""
from __future__ import annotations

from scanner_core.recording.format import (FORMAT_NAME, FORMAT_VERSION, FRAME_INDEX_FILE,
                                           FRAMES_FILE, INDEX_COLUMNS, METADATA_FILE, PART_FILE,
                                           ROBOT_COLUMNS, ROBOT_FILE, ROBOT_MARGIN_S,
                                           ROBOT_SAMPLE_HZ, RecordingError)
from scanner_core.recording.reader import Recording, load_recording
from scanner_core.recording.writer import PassRecorder, robot_samples

__all__ = ["FORMAT_VERSION", "PassRecorder", "Recording", "RecordingError", "load_recording",
           "robot_samples", "ROBOT_SAMPLE_HZ", "ROBOT_MARGIN_S", "FORMAT_NAME", "METADATA_FILE",
           "FRAMES_FILE", "FRAME_INDEX_FILE", "INDEX_COLUMNS", "ROBOT_FILE", "PART_FILE",
           "ROBOT_COLUMNS"]
