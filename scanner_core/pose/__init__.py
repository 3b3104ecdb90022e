"""The part's pose in the gripper: the scan registered against the CAD model, its
uncertainty, and whether to act on it.

This is the package's public face; its modules hold the code."""
from __future__ import annotations

from scanner_core.pose.registration import (PoseParams, SurfaceModel, EdgeModel, PoseResult, register, scan_pose, inputs_pose, ScanPoseInputs, AXIS_NAMES, MIN_POSE_POINTS, BEVEL_MM, TOWARD_MIN, merge_bevels, outline_adjacency, MAX_PROFILE_SPACING_MM, MIN_COVERAGE)
from scanner_core.pose.symmetry import (name_symmetry, self_match, NEAR, exact_symmetries, nearest_equivalent, equivalent_to, surface_moments, EXACT_TOL_MM, EXACT_FRACTION)
from scanner_core.pose.warm import (warm_up_pose)
from scanner_core.pose.ahead import (PoseAhead, pose_ahead, inputs_pose_report)

__all__ = ["PoseParams", "SurfaceModel", "EdgeModel", "PoseResult", "register", "scan_pose", "inputs_pose", "ScanPoseInputs", "AXIS_NAMES", "MIN_POSE_POINTS", "BEVEL_MM", "TOWARD_MIN", "merge_bevels", "outline_adjacency", "MAX_PROFILE_SPACING_MM", "MIN_COVERAGE", "name_symmetry", "self_match", "NEAR", "exact_symmetries", "nearest_equivalent", "equivalent_to", "surface_moments", "EXACT_TOL_MM", "EXACT_FRACTION", "warm_up_pose", "PoseAhead", "pose_ahead", "inputs_pose_report"]
