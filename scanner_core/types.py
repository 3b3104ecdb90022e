"""The data of one pass: frames in, profiles per frame, one scan out.

Units: millimetres and seconds. Frames are named in the attribute docs: {B} robot base,
{C} camera, {T} gripper (TCP), {P} part.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Frame:
    """One camera image.

    Attributes
    ----------
    image : (H, W) uint8
        The raw mono image.
    frame_id : int
        Camera frame counter; a gap between consecutive ids is a dropped frame.
    t : float
        Camera clock at exposure, seconds.
    exposure_us : float
        Exposure time this frame was taken with, microseconds; NaN when the camera does not
        say (then exposure control has nothing to work with).
    gain : float
        Analogue gain it was taken with (1: none).
    """

    image: np.ndarray
    frame_id: int
    t: float
    exposure_us: float = float("nan")
    gain: float = 1.0


@dataclass(frozen=True)
class MarkerObservation:
    """The LED marker in the three views of one frame.

    Attributes
    ----------
    pixels : (3, 2) float64
        Sub-pixel centroid (column, row) in the direct, left-mirror and right-mirror views;
        NaN where the marker was not found in that view.
    position_b : (3,) float64
        Triangulated marker position in {B}, mm; NaN when fewer than two views saw it.
    residual_px : float
        RMS reprojection residual of the triangulation, pixels.
    """

    pixels: np.ndarray
    position_b: np.ndarray
    residual_px: float

    @property
    def views(self) -> int:
        return int(np.isfinite(self.pixels[:, 0]).sum())

    @property
    def valid(self) -> bool:
        return bool(np.all(np.isfinite(self.position_b)))


@dataclass(frozen=True)
class Profile:
    """What one frame yields: the stripe points and the gripper position.

    Attributes
    ----------
    frame_id : int
    t : float
        Camera clock, seconds.
    points_b : (N, 3) float64
        Stripe points in {B}, mm.
    columns : (N,) int32
        Image column each point came from.
    quality : (N,) float32
        Peak intensity of the stripe at that column, DN (a proxy for the point's reliability).
    marker : MarkerObservation
    edges : scanner_core.edges.EdgePoints or None
        Drop-out and step edge points of the profile, {B}.
    saturated : (N,) bool or None
        The stripe clipped at full scale there (its centre measured from the flanks).
    exposure_us, gain : float
        The frame's exposure (``Frame``).
    background_dn : float
        The frame's background level, DN (``scanner_core.stripe.extractor.estimate_noise``).
    rows : (N,) float32 or None
        The stripe's image row at each of ``columns``, px.
    stripe_peaks : (M,) float32 or None
        Peak of the stripe in every column that holds one, valid or not (clipped ones at full
        scale, the marker's columns excluded), DN: what exposure control steers by.
    """

    frame_id: int
    t: float
    points_b: np.ndarray
    columns: np.ndarray
    quality: np.ndarray
    marker: MarkerObservation
    edges: object = None
    saturated: np.ndarray | None = None
    exposure_us: float = float("nan")
    gain: float = 1.0
    background_dn: float = float("nan")
    stripe_peaks: np.ndarray | None = None
    rows: np.ndarray | None = None


@dataclass
class Scan:
    """The stitched result of one pass, in {T}.

    Attributes
    ----------
    cloud : (N, 3) float32
        Surface points in {T}, mm.
    frame_ids : (N,) int32
        Frame each point came from.
    quality : (N,) float32
        Stripe peak intensity, DN.
    edges : (M, 3) float32
        Edge points in {T}, mm (``scanner_core.edges``: drop-outs and steps along each
        profile, stitched like the cloud), sorted by frame.
    tcp_positions_b : (F, 3) float64
        Marker-derived TCP position per used frame, {B}, mm.
    tcp_times : (F,) float64
        Camera time of those frames, s.
    tcp_frame_ids : (F,) int64
        Their frame ids (every placed frame, with or without stripe points).
    frames : int
        Frames that contributed a profile.
    frames_dropped : int
        Gaps in the camera's frame ids during the pass.
    frames_unplaced : int
        Triggered frames left out because the marker could not be triangulated (fewer than
        two views, or views that disagree: a calibration that does not fit the cell).
    marker_residual_px : float
        Median RMS reprojection residual of the marker over the triggered frames.
    timings_ms : dict
        Wall time per stage.
    interrupted : str or None
        Why the pass ended early (the camera stopped), or None for a complete pass.
    end_reason : str or None
        Why the pass ended (``scanner_core.pipeline.trigger.EndReason`` value): "marker gone",
        "timeout", "camera stopped", "too long" or "reset".
    frames_held_rotation : int
        Frames placed with the robot's last rotation because it had none for their time.
    frames_without_rotation : int
        Frames with a marker left unplaced because the robot had given no rotation yet.
    queue_overflows : int
        Frames of the pass lost because the processing queue was full (the service).
    tcp_rotations_b : (F, 3, 3) float64
        {T}'s rotation in {B} per placed frame (the robot's, as used to place it), in the
        order of ``tcp_frame_ids``.
    sensor_positions_t : (F, 3) float64
        The camera's optical centre in {T} per placed frame, mm: ``R^T (C_B - p)`` for the
        camera centre ``C_B`` in {B} and the frame's TCP position ``p`` and rotation ``R``;
        the viewpoint of that frame's points (the stripe is seen in the direct view).
    sheet_planes_t : (F, 4) float64
        The light plane in {T} per placed frame, ``n . x = offset`` as ``(n_x, n_y, n_z,
        offset)`` (unit n, mm): ``n = R^T n_B``, ``offset = offset_B - n_B . p``. Where the
        sheet swept the part, and so what each frame could have seen
        (``scanner_core.inspection.coverage``).
    edge_frame_ids : (M,) int32
        Frame of each edge point.
    edge_kind : (M,) uint8
        ``scanner_core.edges.EdgeKind``: 0 drop-out, 1 step.
    edge_size_mm : (M,) float32
        Drop-out: the gap's width, mm (NaN when the stripe does not come back); step: its
        height, mm.
    edge_quality : (M,) float32
        Stripe peak on the edge's side, DN.
    points_partly_lit : int
        Points not kept because their surface reached or left the sheet during the exposure
        (``scanner_core.pipeline.exposure.partly_lit``).
    measured_box_t : (2, 3) float64 or None
        The box in {T} (lower and upper corners, mm) outside which the pass measured nothing:
        the geometric window's inspection volume and margin
        (``scanner_core.stripe.window.volume_box_t``); None: no such bound.
    edges_occluded : int
        Drop-outs dropped because the camera's view past them ran into the part (an
        occlusion's boundary, not an edge).
    edges_grazing : int
        Edge points dropped because the light sheet grazes the surface they lie on
        (``scanner_core.edges.grazing_edges``).
    edges_aside : scanner_core.edges.kinds.AsideEdges or None
        The edge points kept out of ``edges``, each with its reason (``EdgeKind.OCCLUDED``,
        ``GRAZING``, ``TURNED_AWAY``, ``OFF_MODEL``); None for a scan built by hand.
    normals : (N, 3) float32 or None
        Unit normals of the cloud toward the camera; computed once, on first use, by
        ``scanner_core.io.scanfiles.scan_normals``.
    deviations_mm : (N,) float32 or None
        Each point's signed deviation from the part's model at its pose, mm, outward
        positive (``scanner_core.inspection``); None without a pose.
    placement_std_mm : (3,) float64 or None
        Standard deviation, mm along the {T} axes, of the error every profile's placement
        shares: the calibration's ``marker_offset_std_mm`` (None: not measured).
    light_plane_uncertainty : scanner_core.calibration.plane.PlaneUncertainty or None
        The calibration's ``light_plane_uncertainty``: every profile was triangulated on that
        plane (None: not measured).
    """

    cloud: np.ndarray
    frame_ids: np.ndarray
    quality: np.ndarray
    edges: np.ndarray
    tcp_positions_b: np.ndarray
    tcp_times: np.ndarray
    frames: int
    frames_dropped: int
    frames_unplaced: int = 0
    marker_residual_px: float = float("nan")
    timings_ms: dict = field(default_factory=dict)
    interrupted: str | None = None
    end_reason: str | None = None
    frames_held_rotation: int = 0
    frames_without_rotation: int = 0
    tcp_frame_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    queue_overflows: int = 0
    tcp_rotations_b: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    sensor_positions_t: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    sheet_planes_t: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    edge_frame_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    edge_kind: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    edge_size_mm: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    edge_quality: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    edges_occluded: int = 0
    edges_grazing: int = 0
    edges_aside: object = None
    points_partly_lit: int = 0
    measured_box_t: np.ndarray | None = None
    placement_std_mm: np.ndarray | None = None
    light_plane_uncertainty: object = None
    normals: np.ndarray | None = None
    deviations_mm: np.ndarray | None = None

    @property
    def profile_spacing_mm(self) -> float:
        """Median distance between consecutive profiles on the part (the TCP's steps from the
        first to the last frame that placed a point), mm; NaN with fewer than two profiles.
        The pass's start and end (the robot speeding up; the gripper's way out once the part
        has left the sheet) sample nothing, and would move the median with every frame.
        Over the whole pass when the scan does not list its frames (``tcp_frame_ids``) or has
        no point."""
        track = np.asarray(self.tcp_positions_b, dtype=np.float64).reshape(-1, 3)
        frames = np.asarray(self.tcp_frame_ids)
        if len(frames) == len(track) and len(self.frame_ids):
            track = track[(frames >= self.frame_ids.min()) & (frames <= self.frame_ids.max())]
        if len(track) < 2:
            return float("nan")
        return float(np.median(np.linalg.norm(np.diff(track, axis=0), axis=1)))
