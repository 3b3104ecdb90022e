"""The recording format's names and its one error: what the writer
(``scanner_core.recording.writer``) and the reader (``scanner_core.recording.reader``) share.
The format itself is described in ``scanner_core.recording``.
"""
from __future__ import annotations

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "METADATA_FILE", "FRAMES_FILE", "FRAME_INDEX_FILE",
           "INDEX_COLUMNS", "ROBOT_FILE", "PART_FILE", "ROBOT_COLUMNS", "ROBOT_SAMPLE_HZ",
           "ROBOT_MARGIN_S", "RecordingError"]

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
