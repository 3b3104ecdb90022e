"""What the scanner reads and writes: PLY clouds, scan files (``cloud.ply``, ``edges.ply``,
``report.json``), mesh files, and the UR controller's RTDE protocol and poses.

This is the package's public face; its modules hold the code."""
from __future__ import annotations

from scanner_core.io.ply import (write_ply, write_ply_rows, read_ply, PLY_TYPES)
from scanner_core.io.meshfile import (MERGE_TOL, read_mesh, read_binary_stl, is_binary_stl, clean_triangles, check_ply_counts)
from scanner_core.io.rtde import (RTDE_PORT, PROTOCOL_VERSION, MAX_FREQUENCY_HZ, HEADER, packet, REQUEST_PROTOCOL_VERSION, GET_URCONTROL_VERSION, SETUP_OUTPUTS, SETUP_INPUTS, START, PAUSE, DATA_PACKAGE, TEXT_MESSAGE, OUTPUT_TYPES, TYPE_FORMATS, output_type, output_setup, parse_output_setup, data_package, ur_pose_to_matrix, matrix_to_ur_pose)

__all__ = ["write_ply", "write_ply_rows", "read_ply", "PLY_TYPES", "MERGE_TOL", "read_mesh", "read_binary_stl", "is_binary_stl", "clean_triangles", "check_ply_counts", "RTDE_PORT", "PROTOCOL_VERSION", "MAX_FREQUENCY_HZ", "HEADER", "packet", "REQUEST_PROTOCOL_VERSION", "GET_URCONTROL_VERSION", "SETUP_OUTPUTS", "SETUP_INPUTS", "START", "PAUSE", "DATA_PACKAGE", "TEXT_MESSAGE", "OUTPUT_TYPES", "TYPE_FORMATS", "output_type", "output_setup", "parse_output_setup", "data_package", "ur_pose_to_matrix", "matrix_to_ur_pose"]
