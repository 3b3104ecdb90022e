"""The gripper's LED marker in the three views of a frame (direct and two mirrors).

This is the package's public face; its modules hold the code."""
from __future__ import annotations

from scanner_core.marker.finder import (MarkerParams, find_marker, find_markers, marker_present)

__all__ = ["MarkerParams", "find_marker", "find_markers", "marker_present"]
