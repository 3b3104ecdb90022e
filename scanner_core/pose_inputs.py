"""The pose's inputs, checked and prepared (`check_inputs`, `edge_steps`, `scan_steps`), and
the errors every profile's placement shares, added to its covariance (`add_placement_error`).

Units: mm; the covariance's rotations in rad, the reported sigmas in degrees.
"""
from __future__ import annotations

import numpy as np

__all__ = ["add_placement_error", "scan_steps", "check_inputs", "edge_steps"]


def add_placement_error(result, std_mm, rotation_std_deg: float = 0.0) -> None:
    """The errors every profile's placement shares, added to `result`'s (a ``PoseResult``)
    covariance in place: they move the whole cloud in {T}, so the pose carries them whole,
    however many profiles average their own errors away.

    - `std_mm` (3,): the calibration's marker offset (``Scan.placement_std_mm``), mm along
      the {T} axes, onto the translations. In ``flyscan bench place``'s calibrated cell the
      marker offset 19 um off its truth put every pose acted on 17-18 um off along y_T
      against sigmas of 4 um.
    - `rotation_std_deg`: the robot's orientation report (``PoseParams
      .robot_rotation_std_deg``), onto each rotation: a turn of the cloud about the TCP, the
      {T} origin, which moves no translation of it.
    """
    std = np.asarray(std_mm, dtype=np.float64).reshape(3)
    if not (np.isfinite(std).all() and np.all(std >= 0)):
        raise ValueError(f"placement_std_mm must be 3 finite numbers >= 0, got {std.tolist()}")
    result.covariance = result.covariance.copy()
    result.covariance[:3, :3] += np.diag(std**2)
    result.covariance[3:, 3:] += np.eye(3) * np.radians(rotation_std_deg) ** 2
    with np.errstate(invalid="ignore"):
        variance = np.diag(result.covariance)
        result.std[:3] = np.sqrt(variance[:3])
        result.std[3:] = np.degrees(np.sqrt(variance[3:]))


def scan_steps(scan) -> np.ndarray | None:
    """(M,) the height of each step point of the scan's edge cloud, 0 for a drop-out; None
    when the scan carries no kinds and sizes for its edge points."""
    from scanner_core.edges import EdgeKind

    kinds = getattr(scan, "edge_kind", None)
    sizes = getattr(scan, "edge_size_mm", None)
    if kinds is None or sizes is None or len(kinds) != len(scan.edges):
        return None
    return np.where(np.asarray(kinds) == EdgeKind.STEP,
                    np.nan_to_num(np.asarray(sizes, dtype=np.float64)), 0.0)


def check_inputs(points_t, normals_t, frame_ids, minimum: int = 6):
    points = np.asarray(points_t, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points_t must be (N, 3), got {points.shape}")
    normals = (np.full(points.shape, np.nan) if normals_t is None
               else np.asarray(normals_t, dtype=np.float64))
    if normals.shape != points.shape:
        raise ValueError(f"normals_t must be {points.shape}, got {normals.shape}")
    frames = (np.arange(len(points)) if frame_ids is None
              else np.asarray(frame_ids, dtype=np.int64))
    if frames.shape != (len(points),):
        raise ValueError(f"frame_ids must be ({len(points)},), got {frames.shape}")
    keep = np.isfinite(points).all(axis=1)
    if keep.sum() < minimum:
        raise ValueError(f"a pose needs at least {minimum} finite points, got {int(keep.sum())}")
    return points[keep], normals[keep], frames[keep]


def edge_steps(edges_t, edge_steps_mm) -> np.ndarray | None:
    """(K,) step heights of the finite edge points (as `check_inputs` keeps them), mm, 0 for
    a drop-out; None without `edge_steps_mm`."""
    if edge_steps_mm is None:
        return None
    points = np.asarray(edges_t, dtype=np.float64)
    steps = np.asarray(edge_steps_mm, dtype=np.float64).reshape(-1)
    if steps.shape != (len(points),):
        raise ValueError(f"edge_steps_mm must be ({len(points)},), got {steps.shape}")
    if np.any(steps < 0) or np.any(np.isinf(steps)):
        raise ValueError("edge_steps_mm must be finite and >= 0 (a step's height, 0 or NaN "
                         "for a drop-out)")
    return np.nan_to_num(steps[np.isfinite(points).all(axis=1)], nan=0.0)
