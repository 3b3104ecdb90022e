"""Save a scan as the contract's files: ``cloud.ply``, ``edges.ply`` and ``report.json``.

The clouds are binary little-endian PLY, float32 x, y, z in mm in {T}. ``cloud.ply`` adds per
vertex, in this order: the unit normal ``nx, ny, nz`` (float32, toward the camera that saw the
point; :func:`scanner_core.normals.estimate_normals`), the camera's optical centre at the
point's frame ``sensor_x, sensor_y, sensor_z`` (float32, mm in {T}), ``frame_id`` (int32, the
camera frame counter) and ``quality`` (float32, the stripe's peak, DN). The names are those
Open3D, CloudCompare and PCL read as normals. ``edges.ply`` has the same fields (the normal
of the nearest cloud point), then ``kind`` (uchar: 0 drop-out, 1 step) and ``size_mm``
(float32: the gap's width or the step's height). Every file is written atomically and the report
last, so a directory with a ``report.json`` holds a complete scan.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from scanner_core.fileio import save_json_atomic
from scanner_core.normals import estimate_normals
from scanner_core.io.ply import write_ply
from scanner_core.types import Scan


def save_scan(out_dir, scan: Scan, report: dict) -> dict[str, Path]:
    """Write a scan's files into ``out_dir`` (created if missing). Returns their paths.

    A scan that does not carry its per-frame camera centres (``Scan.sensor_positions_t``,
    e.g. one built by hand) is written with NaN sensor positions and normals: there is no
    viewpoint to orient them by.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"cloud": out / "cloud.ply", "edges": out / "edges.ply", "report": out / "report.json"}
    comments = ("flyscan scan", "frame T", "units mm")
    sensors = point_sensors(scan)
    normals = scan_normals(scan)
    fields = {f"n{c}": normals[:, i] for i, c in enumerate("xyz")}
    fields.update({f"sensor_{c}": sensors[:, i].astype(np.float32) for i, c in enumerate("xyz")})
    fields.update({"frame_id": scan.frame_ids.astype(np.int32),
                   "quality": scan.quality.astype(np.float32)})
    if scan.deviations_mm is not None and len(scan.deviations_mm) == len(scan.cloud):
        # a scalar field that CloudCompare and Open3D read: the point's deviation from the
        # model at the pose, mm, outward positive (scanner_core.inspection)
        fields["deviation"] = np.asarray(scan.deviations_mm, dtype=np.float32)
    write_ply(paths["cloud"], scan.cloud, fields=fields, comments=comments)
    write_ply(paths["edges"], scan.edges, fields=edge_fields(scan), comments=comments)
    save_json_atomic(paths["report"], report)
    return paths


def edge_fields(scan: Scan) -> dict[str, np.ndarray]:
    """Per-vertex fields of ``edges.ply``: those of ``cloud.ply`` (the normal is the nearest
    cloud point's, the surface the edge bounds), then ``kind`` (uchar: 0 drop-out, 1 step)
    and ``size_mm`` (float32: the gap's width or the step's height)."""
    m = len(scan.edges)
    normals = np.full((m, 3), np.nan, np.float32)
    if m and len(scan.cloud):
        from scipy.spatial import cKDTree
        _, nearest = cKDTree(scan.cloud).query(scan.edges, k=1)
        normals = scan_normals(scan)[nearest]
    sensors = _frame_lookup(scan, scan.edge_frame_ids)
    fields = {f"n{c}": normals[:, i] for i, c in enumerate("xyz")}
    fields.update({f"sensor_{c}": sensors[:, i].astype(np.float32) for i, c in enumerate("xyz")})
    fields.update({"frame_id": scan.edge_frame_ids.astype(np.int32),
                   "quality": scan.edge_quality.astype(np.float32),
                   "kind": scan.edge_kind.astype(np.uint8),
                   "size_mm": scan.edge_size_mm.astype(np.float32)})
    return fields


def scan_normals(scan: Scan) -> np.ndarray:
    """The cloud's unit normals toward the camera, (N, 3) float32: estimated on first use
    (``scanner_core.normals.estimate_normals`` over the neighbouring profiles) and kept on
    ``scan.normals`` for the file writer and the registration alike."""
    if scan.normals is None or len(scan.normals) != len(scan.cloud):
        scan.normals = estimate_normals(scan.cloud, sensors=point_sensors(scan),
                                        frame_ids=scan.frame_ids)
    return scan.normals


def point_sensors(scan: Scan) -> np.ndarray:
    """The camera's optical centre at each point's frame: (N, 3) float64, mm in {T}.

    Looked up by ``Scan.frame_ids`` in ``Scan.tcp_frame_ids`` / ``Scan.sensor_positions_t``;
    NaN for a point whose frame has no sensor position (none at all for a scan that does not
    carry them). ValueError when the two per-frame arrays disagree in length.
    """
    return _frame_lookup(scan, scan.frame_ids)


def _frame_lookup(scan: Scan, frame_ids) -> np.ndarray:
    """``Scan.sensor_positions_t`` of each of `frame_ids`: (K, 3) float64, NaN where unknown."""
    n = len(frame_ids)
    out = np.full((n, 3), np.nan)
    frames = np.asarray(scan.tcp_frame_ids)
    positions = np.asarray(scan.sensor_positions_t, dtype=np.float64).reshape(-1, 3)
    if len(positions) == 0:
        return out
    if frames.shape != (len(positions),):
        raise ValueError(f"`scan.tcp_frame_ids` {frames.shape} and `scan.sensor_positions_t` "
                         f"{positions.shape} must list the same frames")
    order = np.argsort(frames, kind="stable")
    ids = np.asarray(frame_ids, dtype=np.int64)
    slot = np.clip(np.searchsorted(frames[order], ids), 0, len(frames) - 1)
    known = frames[order][slot] == ids
    out[known] = positions[order[slot[known]]]
    return out
