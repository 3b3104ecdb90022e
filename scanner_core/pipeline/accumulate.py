"""One pass's profiles placed in the gripper's frame {T}, and the scan they make.

:class:`PassAccumulator` places each profile in {T} as it arrives, in any order, by the
marker-derived gripper position and the gripper's orientation from the robot
(``Robot.pose_at`` at the frame's time plus the camera-to-robot clock offset; paper section
II: no assumption of constant speed or straight motion), and yields a scan sorted by frame id
(:meth:`PassAccumulator.scan`): of each pair of frames taken at two exposures the better
exposed measurement of each column (`_best_exposed`), less the points lit for part of the
exposure (`_without_partly_lit`), and with the profiles' edge points stitched into the scan's
edge cloud and those it sets aside (`_stitch_edges`).

References
----------
.. [1] "Fast visual part inspection for bin picking", section II.
"""
from __future__ import annotations

import dataclasses
import threading
from dataclasses import dataclass

import numpy as np

from scanner_core.geometry.calibration import Calibration
from scanner_core.devices import Robot
from scanner_core.edges.kinds import AsideEdges, sheet_range_b, turned_away
from scanner_core.edges import (EdgeKind, EdgePoints, chamfered_dropouts, grazing_edges,
                                occluded_dropouts)
from scanner_core.pipeline.exposure import merge_exposure_pairs, partly_lit
from scanner_core.geometry import base_to_tcp, planes_moved
from scanner_core.pipeline.trigger import EndReason
from scanner_core.types import Profile, Scan

__all__ = ["PlacedProfile", "PassAccumulator", "MAX_POSE_AGE_S", "PREVIOUS_PROFILE_FRAMES"]

#: A frame newer than the robot's newest pose by at most this, s, takes that pose's rotation:
#: the robot reports at 125-500 Hz, the frame may arrive before the next report, and the
#: gripper turns by far less than a millidegree in that time.
MAX_POSE_AGE_S = 0.02

#: The previous profile guides a frame's stripe (``follow_previous_profile``) when it is at most
#: this many frames older: the stripe moves by a few px per frame on a smooth surface.
PREVIOUS_PROFILE_FRAMES = 3


@dataclass(frozen=True)
class PlacedProfile:
    """A profile in {T}: what the accumulator keeps of a frame."""

    frame_id: int
    t: float
    cloud_t: np.ndarray
    quality: np.ndarray
    tcp_b: np.ndarray
    residual_px: float
    rotation_b: np.ndarray | None = None
    edges_t: np.ndarray | None = None      # (M, 3) float32
    edge_across_t: np.ndarray | None = None  # (M, 3) float64, unit, into the gap
    edge_per_px_t: np.ndarray | None = None  # (M, 3) float64, mm per px outward (drop-outs)
    edges: EdgePoints | None = None
    columns: np.ndarray | None = None       # (N,) int32
    saturated: np.ndarray | None = None     # (N,) bool
    brightness: float = float("nan")        # exposure_us * gain


class PassAccumulator:
    """Profiles placed one at a time, in any order; a scan sorted by frame id at the end.

    With the marker at ``m_T`` in {T} and {T}'s rotation ``R`` in {B}, the TCP is at
    ``p = M_B - R m_T`` and a stripe point goes to ``X_T = R^T (X_B - p)``. ``R`` is the robot's
    at the frame's time on the robot clock (camera time + ``clock_offset_s``), or its newest
    if the frame is newer by at most ``MAX_POSE_AGE_S``; when the robot
    has no pose for that time (disconnected, history too short), the last rotation it gave
    this pass, or else ``fallback_rotation``, is used and the frame counted in
    ``frames_held_rotation`` (the pass's rotation is fixed: a lost robot connection costs the
    cross-check, not the scan); without either, the frame cannot be placed. Thread-safe:
    worker threads call :meth:`add` concurrently.

    Parameters
    ----------
    calibration : Calibration
    robot : Robot
    clock_offset_s : float
        Robot clock minus camera clock, s.
    fallback_rotation : (3, 3) float64, optional
        {T}'s rotation in {B} to hold when the robot gives none (the service passes the last
        one the robot reported).
    merge_exposure_pairs : bool
        Multiple exposure: the scan keeps, per pair of frames, the better exposed measurement
        of each column (``scanner_core.pipeline.exposure.merge_exposure_pairs``).
    measured_box_t : (2, 3) float64, optional
        The box in {T} outside which the frames were not measured (``PipelineParams
        .measured_box_t``): the scan's ``measured_box_t``.
    """

    def __init__(self, calibration: Calibration, robot: Robot, clock_offset_s: float = 0.0,
                 fallback_rotation: np.ndarray | None = None, *,
                 merge_exposure_pairs: bool = False, partly_lit_ratio: float = 0.0,
                 measured_box_t: np.ndarray | None = None):
        self.calibration = calibration
        self.measured_box_t = measured_box_t
        self.merge_exposure_pairs = merge_exposure_pairs
        self.partly_lit_ratio = float(partly_lit_ratio)
        self.robot = robot
        self.clock_offset_s = float(clock_offset_s)
        self._lock = threading.Lock()
        self._placed: list[PlacedProfile] = []
        self._frame_ids: list[int] = []
        self._residuals: list[float] = []
        self._unplaced = 0
        self._held_rotation = 0
        self._no_rotation = 0
        self._rotation: np.ndarray | None = (None if fallback_rotation is None
                                             else np.asarray(fallback_rotation, np.float64))
        self._rotation_t = -np.inf
        self._newest: tuple[int, np.ndarray, np.ndarray] | None = None  # id, columns, rows
        self._newest_id = -1           # the newest frame added
        # (profiles up to the last with points, the scan's point and edge fields): `scan`
        self._points_cache: tuple[list, dict] | None = None
        self._newest_with_points = -1  # the newest frame placed with points or edge points

    def expected_rows(self, frame_id: int) -> np.ndarray | None:
        """(W,) float64: the stripe's rows in the newest profile placed at most
        ``PREVIOUS_PROFILE_FRAMES`` frames before ``frame_id`` (NaN where it had none), or None."""
        with self._lock:
            newest = self._newest
        if newest is None or not 0 < frame_id - newest[0] <= PREVIOUS_PROFILE_FRAMES:
            return None
        out = np.full(self.calibration.camera.width, np.nan)
        out[newest[1]] = newest[2]
        return out

    def rotation_at(self, t_camera: float) -> tuple[np.ndarray | None, bool]:
        """{T}'s rotation in {B} at a camera time, and whether the robot gave it."""
        t_robot = t_camera + self.clock_offset_s
        try:
            rotation = np.asarray(self.robot.pose_at(t_robot).rotation)
        except (LookupError, RuntimeError):
            try:
                newest = self.robot.latest()
            except RuntimeError:
                newest = None
            if newest is None or not 0.0 <= t_robot - newest.t <= MAX_POSE_AGE_S:
                with self._lock:
                    return self._rotation, False
            rotation = np.asarray(newest.rotation)
        with self._lock:
            if t_camera >= self._rotation_t:
                self._rotation, self._rotation_t = rotation, t_camera
        return rotation, True

    def add(self, profile: Profile, looked_up: tuple | None = None) -> bool:
        """Place one profile; returns whether it was placed. ``looked_up``: what
        :meth:`rotation_at` gave for the profile's time, when the caller has it already."""
        placed = None
        from_robot = True
        rotation = None
        if profile.marker.valid:
            rotation, from_robot = looked_up if looked_up is not None else self.rotation_at(profile.t)
            if rotation is not None:
                tcp = profile.marker.position_b - rotation @ self.calibration.marker_offset_t
                edges = profile.edges if profile.edges is not None else EdgePoints.empty()
                placed = PlacedProfile(profile.frame_id, profile.t,
                                       base_to_tcp(profile.points_b, tcp, rotation).astype(np.float32),
                                       profile.quality, tcp, profile.marker.residual_px,
                                       rotation,
                                       _up_the_wall(edges, tcp, rotation).astype(np.float32),
                                       edges.across_b @ rotation, edges.per_px_b @ rotation,
                                       edges, profile.columns,
                                       profile.saturated,
                                       profile.exposure_us * profile.gain)
        with self._lock:
            self._frame_ids.append(profile.frame_id)
            self._newest_id = max(self._newest_id, profile.frame_id)
            if placed is not None and (len(placed.cloud_t) or len(placed.edges_t)):
                self._newest_with_points = max(self._newest_with_points, profile.frame_id)
            if np.isfinite(profile.marker.residual_px):
                self._residuals.append(profile.marker.residual_px)
            if placed is None:
                self._unplaced += 1
                self._no_rotation += profile.marker.valid and rotation is None
            else:
                self._placed.append(placed)
                self._held_rotation += not from_robot
                if profile.rows is not None and (self._newest is None
                                                 or profile.frame_id > self._newest[0]):
                    self._newest = (profile.frame_id, profile.columns, profile.rows)
        return placed is not None

    def quiet_since(self, frames: int) -> int | None:
        """The newest frame that placed points (or edge points), when the `frames` frames
        after it have placed none: the part has left the sheet (or a gap in it is passing);
        None before the first point, or while points still come."""
        with self._lock:
            if self._newest_with_points < 0 or self._newest_id - self._newest_with_points < frames:
                return None
            return self._newest_with_points

    @property
    def frames_seen(self) -> int:
        with self._lock:
            return len(self._frame_ids)

    def scan(self, *, frames_dropped: int | None = None, end_reason: EndReason | None = None,
             stopped_because: str | None = None) -> Scan:
        """The scan so far, sorted by frame id.

        ``frames_dropped`` defaults to the gaps between the frame ids received; a caller that
        knows better (frames lost by the camera, not by its own queue) passes its count. A pass
        that ended because the camera stopped, with frames placed, is ``interrupted`` with
        ``stopped_because``.
        """
        with self._lock:
            placed = sorted(self._placed, key=lambda p: p.frame_id)
            on_part = _up_to_the_last_point(placed)
            cached = self._points_cache
            if not (cached is not None and len(cached[0]) == len(on_part)
                    and all(a is b for a, b in zip(cached[0], on_part))):
                cached = None
                measured = _best_exposed(placed) if self.merge_exposure_pairs else placed
                measured, partly_lit_points = _without_partly_lit(measured,
                                                                  self.partly_lit_ratio)
            ids = sorted(self._frame_ids)
            residuals = list(self._residuals)
            unplaced, held, no_rotation = self._unplaced, self._held_rotation, self._no_rotation
        if frames_dropped is None:
            frames_dropped = int(ids[-1] - ids[0] + 1 - len(ids)) if ids else 0
        if cached is None:
            counts = [len(p.cloud_t) for p in measured]
            points = {
                "cloud": (np.concatenate([p.cloud_t for p in measured]) if measured
                          else np.zeros((0, 3), np.float32)),
                "frame_ids": np.repeat(np.array([p.frame_id for p in measured], np.int32),
                                       counts),
                "quality": (np.concatenate([p.quality for p in measured]).astype(np.float32)
                            if measured else np.zeros(0, np.float32)),
                "points_partly_lit": partly_lit_points}
        else:
            points = {name: _copied(value) for name, value in cached[1].items()
                      if name in _POINT_FIELDS}
        scan = Scan(
            cloud=points["cloud"], frame_ids=points["frame_ids"], quality=points["quality"],
            edges=np.zeros((0, 3), np.float32),
            tcp_positions_b=np.array([p.tcp_b for p in placed]).reshape(-1, 3),
            tcp_times=np.array([p.t for p in placed], dtype=np.float64),
            frames=len(placed),
            frames_dropped=frames_dropped,
            frames_unplaced=unplaced,
            marker_residual_px=float(np.median(residuals)) if residuals else float("nan"),
        )
        scan.points_partly_lit = points["points_partly_lit"]
        scan.measured_box_t = (None if self.measured_box_t is None
                               else np.array(self.measured_box_t, dtype=np.float64))
        scan.placement_std_mm = self.calibration.marker_offset_std_mm
        scan.light_plane_uncertainty = self.calibration.light_plane_uncertainty
        scan.frames_held_rotation = held
        scan.frames_without_rotation = no_rotation
        scan.tcp_frame_ids = np.array([p.frame_id for p in placed], dtype=np.int64)
        scan.tcp_rotations_b = np.array([p.rotation_b for p in placed],
                                        dtype=np.float64).reshape(-1, 3, 3)
        # The camera centre in {T} per frame: R^T (C_B - p), as base_to_tcp places points.
        scan.sensor_positions_t = np.einsum(
            "fji,fj->fi", scan.tcp_rotations_b,
            self.calibration.camera.origin - scan.tcp_positions_b)
        # x_T = R^T (x_B - p) per frame
        sheet = self.calibration.light_plane_b
        inverse = scan.tcp_rotations_b.transpose(0, 2, 1)
        scan.sheet_planes_t = planes_moved(
            np.tile(np.r_[sheet.normal, sheet.offset], (len(inverse), 1)), inverse,
            -np.einsum("fij,fj->fi", inverse, scan.tcp_positions_b))
        if cached is None:
            _stitch_edges(scan, placed, self.calibration)
            # What the points and edges came from (the profiles up to the last with points,
            # the same objects) and what they are: a later scan of the same profiles (the
            # pass's end, after the pose was computed ahead) takes them as they are.
            if not self.merge_exposure_pairs:  # a pair may straddle the last point
                with self._lock:
                    self._points_cache = (on_part, {name: _copied(getattr(scan, name))
                                                    for name in (*_POINT_FIELDS, *_EDGE_FIELDS)})
        else:
            for name in _EDGE_FIELDS:
                setattr(scan, name, _copied(cached[1][name]))
        scan.end_reason = end_reason.value if end_reason is not None else None
        if end_reason is EndReason.CAMERA_STOPPED and scan.frames:
            scan.interrupted = stopped_because
        return scan


# A scan's fields that come from its profiles' points and edge points alone.
_POINT_FIELDS = ("cloud", "frame_ids", "quality", "points_partly_lit")
_EDGE_FIELDS = ("edges", "edge_frame_ids", "edge_kind", "edge_size_mm", "edge_quality",
                "edges_aside", "edges_occluded", "edges_grazing")


def _up_the_wall(edges: EdgePoints, tcp, rotation) -> np.ndarray:
    """(M, 3) float64: the profile's edge points in {T}, mm, each step's moved from its near
    side's end up the wall along z_T rather than along the sheet's range axis
    (``EdgePoints.up_wall_b``): the pose matches a step's point from half its height above
    and below it along z_T, and where the sheet leans from the part's walls a move along its
    range axis leaves the wall by half the step times the lean."""
    points = base_to_tcp(edges.point_b, tcp, rotation)
    move = edges.up_wall_b @ rotation  # {B} -> {T}
    points[:, :2] -= move[:, :2]       # up the wall along z_T only
    return points


def _up_to_the_last_point(placed: list[PlacedProfile]) -> list[PlacedProfile]:
    """The sorted `placed` profiles up to the last that has points or edge points: all that
    a scan's points and edge points depend on (the later ones add no point, and the
    profiles' spacing on the part, ``Scan.profile_spacing_mm``, ends there)."""
    last = max((k for k, p in enumerate(placed) if len(p.cloud_t) or len(p.edges_t)),
               default=-1)
    return placed[:last + 1]


def _copied(value):
    """A copy of an array (or of ``AsideEdges``' arrays): scans never share one."""
    if isinstance(value, np.ndarray):
        return value.copy()
    if dataclasses.is_dataclass(value):
        return dataclasses.replace(value, **{f.name: _copied(getattr(value, f.name))
                                             for f in dataclasses.fields(value)})
    return value


def _best_exposed(placed: list[PlacedProfile]) -> list[PlacedProfile]:
    """Multiple exposure: of each pair of consecutive frames taken at different exposures,
    only the better exposed measurement of each column (``merge_exposure_pairs``)."""
    levels = np.array([p.brightness for p in placed])
    finite = levels[np.isfinite(levels)]
    if len(finite) < 2 or np.all(finite == finite[0]) or any(p.columns is None for p in placed):
        return placed
    keep = merge_exposure_pairs(
        [p.frame_id for p in placed], levels, [p.columns for p in placed],
        [p.quality for p in placed],
        [p.saturated if p.saturated is not None else np.zeros(len(p.columns), bool)
         for p in placed])
    return [p if k.all() else dataclasses.replace(
                p, cloud_t=p.cloud_t[k], quality=p.quality[k], columns=p.columns[k],
                saturated=None if p.saturated is None else p.saturated[k])
            for p, k in zip(placed, keep)]


def _without_partly_lit(placed: list[PlacedProfile], ratio: float):
    """The profiles less their points lit for part of the exposure (``partly_lit``), and how
    many those were."""
    if ratio <= 0 or len(placed) < 2:
        return placed, 0
    counts = [len(p.cloud_t) for p in placed]
    frame_ids = np.repeat(np.array([p.frame_id for p in placed]), counts)
    drop = partly_lit(frame_ids, np.concatenate([p.cloud_t for p in placed]),
                      np.concatenate([p.quality for p in placed]),
                      np.repeat(np.array([p.brightness for p in placed]), counts), ratio)
    if not drop.any():
        return placed, 0
    keep = np.split(~drop, np.cumsum(counts)[:-1])
    return [p if k.all() else dataclasses.replace(
                p, cloud_t=p.cloud_t[k], quality=p.quality[k],
                columns=None if p.columns is None else p.columns[k],
                saturated=None if p.saturated is None else p.saturated[k])
            for p, k in zip(placed, keep)], int(drop.sum())


def _stitch_edges(scan: Scan, placed: list[PlacedProfile], calibration: Calibration) -> None:
    """The profiles' edge points in {T}, the drop-outs of a chamfered outline placed at it
    (``scanner_core.edges.chamfered_dropouts``), less those set aside
    (``Scan.edges_aside``, each with its ``EdgeKind``): the drop-outs that bound an
    occlusion (which a single profile cannot tell from a rim:
    ``scanner_core.edges.occluded_dropouts``), the points on a surface the sheet grazes
    (``scanner_core.edges.grazing_edges``), and those whose surface may go on unseen beyond
    them, turned from the view or the light by a soft crease
    (``scanner_core.edges.kinds.turned_away``)."""
    scan.edges_aside = AsideEdges.empty()
    if not placed:
        return
    counts = [len(p.edges_t) for p in placed]
    points = np.concatenate([p.edges_t for p in placed]).reshape(-1, 3)
    across = np.concatenate([p.edge_across_t for p in placed]).reshape(-1, 3)
    kind = np.concatenate([p.edges.kind for p in placed]).astype(np.uint8)
    size = np.concatenate([p.edges.size_mm for p in placed]).astype(np.float32)
    peak = np.concatenate([p.edges.peak for p in placed]).astype(np.float32)
    frames = np.repeat(np.array([p.frame_id for p in placed], np.int32), counts)
    sensors = np.repeat(scan.sensor_positions_t, counts, axis=0)
    why = np.zeros(len(points), np.uint8)  # 0: kept; else the EdgeKind it is set aside as
    dropout = np.nonzero(kind == EdgeKind.DROPOUT)[0]
    if len(dropout):
        stripe_end = np.concatenate([p.edges.stripe_end for p in placed]).reshape(-1, 5)
        per_px = np.concatenate([p.edge_per_px_t for p in placed]).reshape(-1, 3)
        moved, _ = chamfered_dropouts(points[dropout], across[dropout], frames[dropout],
                                      stripe_end[dropout], per_px[dropout],
                                      scan.profile_spacing_mm)
        points[dropout] = moved
    from scipy.spatial import cKDTree  # as the filters do: scipy only for the scan's end

    # one KD-tree over the cloud for the three filters that look around the edge points
    tree = cKDTree(np.asarray(scan.cloud, np.float64)) if len(scan.cloud) else None
    if len(dropout) and len(scan.cloud):
        why[dropout[occluded_dropouts(points[dropout], across[dropout], sensors[dropout],
                                      scan.cloud, cloud_tree=tree)]] = EdgeKind.OCCLUDED
    scan.edges_occluded = int((why == EdgeKind.OCCLUDED).sum())
    # The sheet's normal in {T} per frame: R^T n_B.
    sheet_b = calibration.light_plane_b.normal
    rotations = np.array([p.rotation_b for p in placed])
    sheets = np.repeat(np.einsum("fji,j->fi", rotations, sheet_b), counts, axis=0)
    grazed = grazing_edges(points, sheets, scan.cloud, scan.frame_ids, scan.profile_spacing_mm,
                           frame_ids=frames, cloud_tree=tree) & (why == 0)
    why[grazed] = EdgeKind.GRAZING
    scan.edges_grazing = int(grazed.sum())
    if len(points) and len(scan.cloud):
        from scanner_core.io.scanfiles import point_sensors  # its PLY and normals: not at import

        range_b = sheet_range_b(calibration)
        ranges = np.repeat(np.einsum("fji,j->fi", rotations, range_b), counts, axis=0)
        turned, _, _ = turned_away(points, kind, size, ranges, sensors, scan.cloud,
                                   scan.frame_ids, frames, point_sensors(scan), cloud_tree=tree)
        why[turned & (why == 0)] = EdgeKind.TURNED_AWAY
    keep = why == 0
    scan.edges, scan.edge_frame_ids, scan.edge_kind = points[keep], frames[keep], kind[keep]
    scan.edge_size_mm, scan.edge_quality = size[keep], peak[keep]
    scan.edges_aside = AsideEdges(points[~keep].astype(np.float32), frames[~keep], why[~keep],
                                  kind[~keep], size[~keep], peak[~keep])
