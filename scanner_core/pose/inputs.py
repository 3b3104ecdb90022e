"""The pose's inputs, checked and prepared (`check_inputs`, `edge_steps`, `scan_steps`), what
a scan's pose reads of the scan (`ScanPoseInputs`), and the errors every profile's placement
shares, added to its covariance (`add_placement_error`).

Units: mm; the covariance's rotations in rad, the reported sigmas in degrees.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

__all__ = ["add_placement_error", "scan_steps", "check_inputs", "edge_steps", "ScanPoseInputs",
           "MAX_PROFILE_SPACING_MM", "sparse_flag"]

#: Profiles farther apart than this (mm) sample a part's features too coarsely for the
#: uncertainty to be trusted: a hole's rim crossed by two profiles pins little.
MAX_PROFILE_SPACING_MM = 3.0


def sparse_flag(spacing_mm: float) -> str | None:
    """The flag for profiles `spacing_mm` apart, or None when they are close enough (and for
    NaN: fewer than two profiles)."""
    if spacing_mm > MAX_PROFILE_SPACING_MM:
        return (f"sparse: {spacing_mm:.1f} mm between profiles (at most "
                f"{MAX_PROFILE_SPACING_MM:g})")
    return None


@dataclass(frozen=True, eq=False)
class ScanPoseInputs:
    """What a scan's pose (``scanner_core.pose.registration.scan_pose``) reads of the scan, and nothing
    else: two scans whose inputs are the same (:meth:`same_as`) have the same pose, bit for
    bit. The service computes a pass's pose once the part has left the sheet, while the
    gripper finishes the pass, and keeps it when the whole pass's inputs turn out the same
    (``scanner_core.pipeline.finish.pose_ahead``).

    Attributes
    ----------
    cloud : (N, 3) float32
        The points, mm in {T}.
    frame_ids : (N,) int
        Each point's frame.
    sensors : (N, 3) float64
        The camera's centre at each point's frame, mm in {T} (NaN where unknown).
    edges : (M, 3) float32 or None
        The edge cloud, mm in {T}; None when the scan has no frames for its edge points.
    edge_frame_ids : (M,) int or None
    edge_steps_mm : (M,) float64 or None
        ``scan_steps``: each edge point's step height, 0 for a drop-out.
    placement_std_mm : (3,) float64 or None
        ``Scan.placement_std_mm``.
    sparse : str or None
        ``sparse_flag`` of ``Scan.profile_spacing_mm`` (the profiles' on the part): the pose
        reads the spacing through it alone.
    sheet_frames : (F,) int64 or None
        The frames of `sheet_t`; None when the calibration did not measure its light plane's
        uncertainty.
    sheet_t : (F, 5, 3) float64 or None
        ``sheet_in_tcp``: per frame, the light plane and the camera in {T}.
    sheet_covariance : (3, 3) float64 or None
        ``PlaneUncertainty.covariance``: of the plane's tilts and shift (`sheet_t`'s axes).
    in_sheet_at : tuple of (bool, bool)
        Whether the part was in the sheet at the pass's first placed frame, and at its last
        (``cut_ends``): a pass that began or ended on the part saw only some of it.
    """

    cloud: np.ndarray
    frame_ids: np.ndarray
    sensors: np.ndarray
    edges: np.ndarray | None
    edge_frame_ids: np.ndarray | None
    edge_steps_mm: np.ndarray | None
    placement_std_mm: np.ndarray | None
    sparse: str | None
    sheet_frames: np.ndarray | None = None
    sheet_t: np.ndarray | None = None
    sheet_covariance: np.ndarray | None = None
    in_sheet_at: tuple = (False, False)

    @classmethod
    def of(cls, scan) -> "ScanPoseInputs":
        from scanner_core.io.scanfiles import point_sensors  # its PLY writer: not at import

        edge_frames = getattr(scan, "edge_frame_ids", None)
        placement = getattr(scan, "placement_std_mm", None)
        return cls(cloud=np.asarray(scan.cloud), frame_ids=np.asarray(scan.frame_ids),
                   sensors=point_sensors(scan),
                   edges=None if edge_frames is None else np.asarray(scan.edges),
                   edge_frame_ids=None if edge_frames is None else np.asarray(edge_frames),
                   edge_steps_mm=scan_steps(scan),
                   placement_std_mm=None if placement is None else np.asarray(placement,
                                                                              np.float64),
                   sparse=sparse_flag(scan.profile_spacing_mm), in_sheet_at=cut_ends(scan),
                   **sheet_in_tcp(scan))

    def same_as(self, other: "ScanPoseInputs") -> bool:
        """Whether every input is the same, value for value (NaN equal to NaN), in the same
        dtype and shape."""
        for field in fields(self):
            mine, theirs = getattr(self, field.name), getattr(other, field.name)
            if isinstance(mine, np.ndarray) or isinstance(theirs, np.ndarray):
                if not (isinstance(mine, np.ndarray) and isinstance(theirs, np.ndarray)
                        and mine.dtype == theirs.dtype and mine.shape == theirs.shape
                        and np.array_equal(mine, theirs,
                                           equal_nan=mine.dtype.kind in "fc")):
                    return False
            elif mine != theirs:
                return False
        return True


def _seen_frames(scan) -> np.ndarray:
    """The frames with a point or an edge point, sorted."""
    edge_frames = getattr(scan, "edge_frame_ids", None)
    return np.union1d(np.asarray(scan.frame_ids),
                      np.zeros(0, np.int64) if edge_frames is None else np.asarray(edge_frames))


def cut_ends(scan) -> tuple[bool, bool]:
    """Whether the pass's first placed frame (``Scan.tcp_frame_ids``) has a point or an edge
    point, and whether its last has: the part was in the sheet when the pass began (the
    trigger came late) or when it ended (the pass stopped early). (False, False) for a scan
    without placed frames. A pose computed once the part has left the sheet reads the same
    as the whole pass's (``scanner_core.pipeline.finish.pose_ahead``)."""
    frames = np.asarray(getattr(scan, "tcp_frame_ids", np.zeros(0)), dtype=np.int64)
    seen = _seen_frames(scan)
    if not len(frames) or not len(seen):
        return (False, False)
    return (bool(seen.min() <= frames.min()), bool(seen.max() >= frames.max()))


def sheet_in_tcp(scan) -> dict:
    """The light plane's uncertainty as a scan's pose reads it: the plane (its normal `n`,
    its axes `a_1`, `a_2` and its centre `c`, ``PlaneUncertainty``) and the camera's centre,
    each in {T} at every placed frame with a point or an edge point (``x_T = R^T (x_B - p)``
    for the frame's TCP rotation `R` and position `p`).

    Returns
    -------
    dict
        ``sheet_frames`` (F,) int64, ``sheet_t`` (F, 5, 3) float64 (rows: `n`, `a_1`, `a_2`,
        `c`, the camera) and ``sheet_covariance`` (3, 3); all None when the scan's
        calibration did not measure the plane's uncertainty or the scan placed no frame.
    """
    none = {"sheet_frames": None, "sheet_t": None, "sheet_covariance": None}
    uncertainty = getattr(scan, "light_plane_uncertainty", None)
    rotations = np.asarray(getattr(scan, "tcp_rotations_b", np.zeros((0, 3, 3))),
                           dtype=np.float64).reshape(-1, 3, 3)
    positions = np.asarray(scan.tcp_positions_b, dtype=np.float64).reshape(-1, 3)
    frames = np.asarray(getattr(scan, "tcp_frame_ids", np.zeros(0)), dtype=np.int64)
    sensors = np.asarray(getattr(scan, "sensor_positions_t", np.zeros((0, 3))),
                         dtype=np.float64).reshape(-1, 3)
    if (uncertainty is None or not len(rotations)
            or not len(frames) == len(rotations) == len(positions) == len(sensors)):
        return none
    # Only the frames with a point or an edge point: the pose reads no other, and a pass's
    # frames after the part has left the sheet must not make its inputs differ from the pass
    # so far's (``scanner_core.pipeline.finish.pose_ahead``).
    seen = _seen_frames(scan)
    keep = np.isin(frames, seen)
    if not keep.any():
        return none
    frames, rotations, positions, sensors = (frames[keep], rotations[keep], positions[keep],
                                             sensors[keep])
    n = np.cross(uncertainty.axes_b[0], uncertainty.axes_b[1])
    directions = np.stack([n, *uncertainty.axes_b])                      # (3, 3) in {B}
    # R^T v for each frame's R and each direction v: (F, 3, 3)
    directions_t = np.einsum("fji,kj->fki", rotations, directions)
    centre_t = np.einsum("fji,fj->fi", rotations, uncertainty.centre_b - positions)
    table = np.concatenate([directions_t, centre_t[:, None], sensors[:, None]], axis=1)
    return {"sheet_frames": frames.copy(), "sheet_t": table,
            "sheet_covariance": np.asarray(uncertainty.covariance, dtype=np.float64)}


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
    marker, robot = np.zeros((6, 6)), np.zeros((6, 6))
    marker[:3, :3] = np.diag(std**2)
    robot[3:, 3:] = np.eye(3) * np.radians(rotation_std_deg) ** 2
    result.covariance = result.covariance + marker + robot
    if result.covariance_terms:
        nan = ~np.isfinite(result.covariance)
        result.covariance_terms = dict(result.covariance_terms, marker=marker, robot=robot)
        for term in result.covariance_terms.values():
            term[nan] = np.nan
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
