"""One pass, from frames to a scan: the one streaming core the CLI, the service and the
benchmarks drive.

Per frame: the LED marker in the three views, found once (:class:`MarkerTracker` searches near
where the previous frames put it) and shared by the trigger's presence test and the frame's
processing; then (:func:`process_frame`) the stripe per column of the direct view and its
triangulation (pixel ray x light plane). Per pass: :class:`PassAccumulator` places each
profile in {T} as it arrives, in any order, by the marker-derived gripper position and the
gripper's orientation from the robot (``Robot.pose_at`` at the frame's time plus the
camera-to-robot clock offset; paper section II: no assumption of constant speed or straight
motion), and yields a scan sorted by frame id.

:func:`run_pass` is the single-threaded driver (``flyscan scan``, the benchmarks); the service
runs the same pieces with the marker and trigger on its acquisition thread and
:func:`process_frame` + :meth:`PassAccumulator.add` on worker threads.

References
----------
.. [1] "Fast visual part inspection for bin picking", section II (../shared/paper.md).
"""
from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from scanner_core import marker as marker_mod
from scanner_core import stripe as stripe_mod
from scanner_core.calibration import Calibration
from scanner_core.devices import Camera, CameraClosed, CameraTimeout, Robot
from scanner_core.exposure import (ExposureController, ExposureParams, merge_exposure_pairs,
                                   partly_lit)
from scanner_core.edge_kinds import AsideEdges, sheet_range_b, turned_away
from scanner_core.edges import (EdgeKind, EdgeParams, EdgePoints, chamfered_dropouts, find_edges,
                                grazing_edges, occluded_dropouts)
from scanner_core.geometry import (base_to_tcp, reproject_marker, triangulate_marker,
                                   triangulate_stripe)
from scanner_core.trigger import EndReason, Trigger, TriggerParams, TriggerStep
from scanner_core.types import Frame, MarkerObservation, Profile, Scan
from scanner_core.window import volume_rows


#: A frame newer than the robot's newest pose by at most this, s, takes that pose's rotation:
#: the robot reports at 125-500 Hz, the frame may arrive before the next report, and the
#: gripper turns by far less than a millidegree in that time.
MAX_POSE_AGE_S = 0.02

#: The marker's mask spans this many times ``marker_mask_px`` along the columns: the blob's
#: halo reaches farther along a column than the stripe's rows vary across a few columns.
MASK_ROW_FACTOR = 4

#: The previous profile guides a frame's stripe (``follow_previous_profile``) when it is at most
#: this many frames older: the stripe moves by a few px per frame on a smooth surface.
PREVIOUS_PROFILE_FRAMES = 3

#: Stripe reasons of a column that holds no stripe at all (for exposure control).
_NO_STRIPE = (stripe_mod.Reason.NO_PEAK, stripe_mod.Reason.NOT_PROCESSED,
              stripe_mod.Reason.OUTSIDE_WINDOW)
#: ... as a lookup table over the uint8 reason codes (np.isin costs 10 us a frame).
_HOLDS_STRIPE = np.ones(256, dtype=bool)
_HOLDS_STRIPE[list(_NO_STRIPE)] = False


@dataclass(frozen=True)
class PipelineParams:
    """Settings of the per-frame processing.

    Attributes
    ----------
    stripe_method : str
        One of ``scanner_core.stripe.METHODS``.
    stripe_threshold_dn : float
    min_peak_dn : float
        With ``stripe_floor="fixed"``: columns whose stripe peaks lower are dropped (on grazing
        surfaces the stripe fades into the noise and its centre errs by tenths of a pixel).
    stripe_floor : str
        ``"auto"`` (default): the threshold and the minimum peak follow the frame's noise
        (``scanner_core.stripe``, ``threshold="auto"``: 20 DN on the reference model) and a
        column is kept when its peak SNR reaches ``min_peak_snr``, so that a dark part's stripe
        (30 DN over 3 DN of noise) still counts, its ``quality`` (the peak) saying how much to
        trust it.  ``"fixed"``: ``stripe_threshold_dn`` and ``min_peak_dn`` (before issue 12).
        On the block's reference pass (cog) "auto" gave 10.85 um RMS and 1 unmatched point in
        10.6k against 10.36 um and 0 with the fixed floors: the grazing columns of 30-40 DN come
        back, with their tenths of a pixel.
    min_peak_snr : float
        With ``stripe_floor="auto"``: smallest peak SNR kept, ``(peak - background) / noise``.
        7 keeps 97.6-99.7 % of the columns of a 30 DN stripe over 3 DN of noise (SNR ~10 less
        speckle; its centre to ~0.15 px RMS) over five frames, and drops what barely clears the
        extraction's own 5-sigma floor (~0.25 px); 8 kept 88-96 %, 6 let a 0.6 px outlier of a
        19 DN grazing column into the block's cloud.
    stripe_policy : str
        Which peak is the stripe where a column holds two (``scanner_core.stripe.POLICIES``);
        default "continuity": under a reflection at half the stripe's brightness it keeps the
        true stripe in every column.  "reject" drops such columns (before issue 12).
    stripe_saturation : str
        ``"fit"`` (default): clipped peaks are measured from their flanks
        (``scanner_core.stripe``: up to 10x full scale to ~0.02 px RMS) and flagged
        ``saturated``; ``"reject"``: dropped (before issue 12).
    marker : scanner_core.marker.MarkerParams
    marker_mask_px : float
        Stripe columns closer than this to the marker in the direct view are dropped: the LED
        is bright enough to pass for the stripe there.
    max_marker_residual_px : float
        A marker whose views disagree by more than this (RMS reprojection) is rejected.
    min_stripe_run : int
        A stretch of fewer stripe columns than this, contradicted by a longer stretch beside it,
        is dropped (``scanner_core.stripe.isolated_runs``: a reflection that wins the columns
        where the true stripe is too dim); 1 keeps everything.
    follow_previous_profile : bool
        With ``stripe_policy="continuity"``: prefer, where a column holds two peaks, the one
        nearer to the stripe's row in the newest profile of the last ``PREVIOUS_PROFILE_FRAMES``
        frames (``scanner_core.stripe``, ``expected_row``): a glint longer than the neighbouring
        columns can bridge is not taken for the stripe.
    geometric_window : bool
        Look for the stripe only in the rows the inspection volume's section of the sheet can
        reach in each column (``scanner_core.window``), for frames whose TCP pose is known
        (the marker, and the robot's rotation).  A reflection outside them (onto the cell, the
        gripper's fingers) is never taken for the stripe.
    inspection_volume_mm : (3,) float
        Its size along x_T, y_T, z_T below the TCP, mm.
    window_margin_mm : float
        The volume grown by this on every side for the window (a misplaced part may reach out
        of it by the gripper's tolerance).
    exposure : scanner_core.exposure.ExposureParams
        Exposure control (fixed, dynamic or multiple).
    trigger : TriggerParams
    edges : scanner_core.edges.EdgeParams
        Drop-out and step detection along each profile.
    partly_lit_ratio : float
        A point dimmer than this share of the same place in the one neighbouring profile that
        sees it was lit for part of the exposure (its surface reached or left the sheet
        meanwhile) and is not kept (``scanner_core.exposure.partly_lit``); 0 keeps them. At
        0.5, on idler_riser, 0.6 % of the points of the ideal cell and 1.4 % of the realistic
        one, ADIS16480's RMS in the realistic cell 18.6 -> 11.2 um.
    """

    stripe_method: str = "cog"
    stripe_threshold_dn: float = 20.0
    min_peak_dn: float = 40.0
    stripe_floor: str = "auto"
    min_peak_snr: float = 7.0
    stripe_policy: str = "continuity"
    stripe_saturation: str = "fit"
    marker: marker_mod.MarkerParams = field(default_factory=marker_mod.MarkerParams)
    marker_mask_px: float = 12.0
    max_marker_residual_px: float = 1.0
    min_stripe_run: int = 5
    follow_previous_profile: bool = True
    geometric_window: bool = True
    inspection_volume_mm: tuple[float, float, float] = (150.0, 150.0, 100.0)
    window_margin_mm: float = 5.0
    exposure: ExposureParams = field(default_factory=ExposureParams)
    trigger: TriggerParams = field(default_factory=TriggerParams)
    edges: EdgeParams = field(default_factory=EdgeParams)
    partly_lit_ratio: float = 0.5


# ---------------------------------------------------------------------------------------------
# Per frame


def observe_marker(image: np.ndarray, calibration: Calibration, params: PipelineParams,
                   near: np.ndarray | None = None) -> MarkerObservation:
    """Find and triangulate the LED marker in one image.

    Parameters
    ----------
    image : (H, W) uint8
    calibration : Calibration
    params : PipelineParams
    near : (3, 2) float64, optional
        Predicted (column, row) per view (NaN: no prediction); each view is searched there
        first, then over its whole strip.
    """
    pixels = marker_mod.find_markers(image, strips=calibration.strips, params=params.marker,
                                     near=near)
    try:
        position, residual = triangulate_marker(pixels, calibration.camera, calibration.mirrors,
                                                views=calibration.marker_views)
    except ValueError:  # views (nearly) parallel: this frame cannot be placed
        position, residual = np.full(3, np.nan), float("nan")
    if np.isfinite(residual) and residual > params.max_marker_residual_px:
        position = np.full(3, np.nan)
    return MarkerObservation(pixels, position, residual)


class MarkerTracker:
    """Finds the marker frame after frame, searching each view near where it will be.

    The prediction extrapolates the last two observations of each view linearly in the frame
    id (the marker moves smoothly between frames, a few to tens of pixels). Not thread-safe:
    the thread that owns the camera runs it, in frame order.
    """

    def __init__(self, calibration: Calibration, params: PipelineParams):
        self.calibration = calibration
        self.params = params
        self.reset()

    def reset(self) -> None:
        self._last: tuple[int, np.ndarray] | None = None
        self._previous: tuple[int, np.ndarray] | None = None

    def predict(self, frame_id: int) -> np.ndarray | None:
        """(3, 2) predicted pixels for ``frame_id`` (NaN where unknown), or None."""
        if self._last is None:
            return None
        last_id, last = self._last
        if self._previous is None:
            return last
        prev_id, prev = self._previous
        velocity = (last - prev) / max(last_id - prev_id, 1)
        predicted = last + velocity * (frame_id - last_id)
        # A view seen last frame but not the one before: stay where it was.
        return np.where(np.isnan(predicted), last, predicted)

    def observe(self, frame: Frame) -> MarkerObservation:
        obs = observe_marker(frame.image, self.calibration, self.params,
                             near=self.predict(frame.frame_id))
        if obs.views:
            self._previous, self._last = self._last, (frame.frame_id, obs.pixels)
        else:
            self.reset()
        return obs


def marker_in_view(marker: MarkerObservation) -> bool:
    """The trigger's presence test: the marker found in at least two views."""
    return marker.views >= 2


def frame_stripe(image: np.ndarray, calibration: Calibration, params: PipelineParams,
                 marker: MarkerObservation, rotation_b: np.ndarray | None = None,
                 expected_row: np.ndarray | None = None):
    """The stripe of one frame, the columns kept, and the columns beside the marker.

    With ``rotation_b`` ({T}'s rotation in {B} at the frame) and a placed marker, and
    ``params.geometric_window``, only the rows the inspection volume can reach are searched.
    ``expected_row`` (W,) (NaN: none), e.g. the previous profile's rows, guides the choice
    between two peaks (``follow_previous_profile``).

    Returns
    -------
    result : scanner_core.stripe.StripeResult
    valid : (W,) bool
        Valid, bright enough (``min_peak_dn``) and not the marker's blob.
    near : (W,) bool or None
        The columns within ``marker_mask_px`` of the marker in the direct view (None when it
        is not there): where a missing stripe says nothing.
    """
    auto = params.stripe_floor == "auto"
    if not auto and params.stripe_floor != "fixed":
        raise ValueError(f"`stripe_floor` must be 'fixed' or 'auto', got {params.stripe_floor!r}")
    row_min = row_max = None
    if params.geometric_window and rotation_b is not None and marker.valid:
        tcp_b = marker.position_b - rotation_b @ calibration.marker_offset_t
        row_min, row_max = volume_rows(calibration, tcp_b, rotation_b,
                                       params.inspection_volume_mm,
                                       margin_mm=params.window_margin_mm)
    result = stripe_mod.extract(image, method=params.stripe_method,
                                threshold="auto" if auto else params.stripe_threshold_dn,
                                columns=calibration.direct_columns, policy=params.stripe_policy,
                                saturation=params.stripe_saturation, row_min=row_min,
                                row_max=row_max,
                                expected_row=(expected_row if params.follow_previous_profile
                                              else None))
    if auto:
        valid = result.valid & (result.snr >= params.min_peak_snr)
    else:
        valid = result.valid & (result.peak >= params.min_peak_dn)
    if params.min_stripe_run > 1:
        valid &= ~stripe_mod.isolated_runs(result.row, valid, min_run=params.min_stripe_run)
    direct_px = marker.pixels[0]
    if not np.all(np.isfinite(direct_px)) and marker.valid:
        # Seen only in the mirrors (cut off at the image edge, or hidden): mask where the
        # direct view must show it, since a partial blob still passes for the stripe.
        direct_px = reproject_marker(marker.position_b, calibration.camera, calibration.mirrors)[0]
    near = None
    if np.all(np.isfinite(direct_px)):
        near = np.abs(np.arange(image.shape[1]) - direct_px[0]) <= params.marker_mask_px
        valid &= ~(near & (np.abs(result.row - direct_px[1]) <= params.marker_mask_px * MASK_ROW_FACTOR))
    return result, valid, near


def process_frame(frame: Frame, calibration: Calibration, params: PipelineParams = PipelineParams(),
                  marker: MarkerObservation | None = None,
                  rotation_b: np.ndarray | None = None,
                  expected_row: np.ndarray | None = None) -> Profile:
    """One frame -> one profile (stripe points in {B}) and the marker position.

    Parameters
    ----------
    frame : Frame
        ``frame.image`` (H, W) uint8.
    calibration : Calibration
    params : PipelineParams
    marker : MarkerObservation, optional
        The frame's marker, when the trigger has already found it; searched otherwise.
    rotation_b : (3, 3) float64, optional
        {T}'s rotation in {B} at the frame (the robot's): enables the geometric window.
    expected_row : (W,) float, optional
        Where the stripe was in the previous profile, px (NaN: nowhere).

    Returns
    -------
    Profile
    """
    image = frame.image
    if marker is None:
        marker = observe_marker(image, calibration, params)
    result, valid, near = frame_stripe(image, calibration, params, marker, rotation_b,
                                       expected_row)
    # Columns by the marker say nothing of the stripe: no drop-out there.
    edges = find_edges(result, valid, calibration.camera, calibration.light_plane_c,
                       params=params.edges, masked=near)
    columns = np.nonzero(valid)[0].astype(np.int32)
    pixels = np.stack([columns.astype(np.float64), result.row[columns].astype(np.float64)], axis=1)
    points_b = triangulate_stripe(pixels, calibration.camera, calibration.light_plane_c)
    finite = np.isfinite(points_b).all(axis=1)  # rays parallel to the sheet, or behind the camera
    columns, points_b, rows = columns[finite], points_b[finite], pixels[finite, 1]
    stripe_cols = _HOLDS_STRIPE[result.reason]
    if near is not None:
        stripe_cols &= ~near
    return Profile(frame.frame_id, frame.t, points_b, columns,
                   result.peak[columns].astype(np.float32), marker, edges,
                   saturated=result.saturated[columns], exposure_us=frame.exposure_us,
                   gain=frame.gain, background_dn=result.background_dn,
                   stripe_peaks=result.peak[stripe_cols], rows=rows.astype(np.float32))


def warm_up(calibration: Calibration, params: PipelineParams = PipelineParams()) -> float:
    """Compile the numba kernels before the first pass, so that no frame of a pass waits for
    the JIT: a synthetic frame with a stripe and a marker blob in every view goes through the
    marker search (whole strips and near a prediction) and the frame processing, as a writable
    and as a read-only array, and a frame without the marker through the search.
    Returns the time it took, ms."""
    t0 = time.perf_counter()
    cam = calibration.camera
    rows, cols = np.mgrid[0:cam.height, 0:cam.width].astype(np.float32)
    image = 10.0 + 200.0 * np.exp(-0.5 * ((rows - cam.height / 2.0) / 1.5) ** 2)
    image[:, : calibration.direct_columns[0]] = 10.0  # the stripe only in the direct view
    image[:, calibration.direct_columns[1]:] = 10.0
    sigma = params.marker.sigma_px
    for c0, c1 in calibration.strips:
        centre_col = c0 + 0.8 * (c1 - c0) if (c0, c1) == calibration.direct_columns else (c0 + c1) / 2
        image += 220.0 * np.exp(-0.5 * ((cols - centre_col) ** 2 + (rows - cam.height / 4.0) ** 2)
                                / sigma**2)
    writable = np.clip(image, 0, 255).astype(np.uint8)
    read_only = writable.copy()
    read_only.setflags(write=False)  # numba compiles read-only arrays apart; cameras give both
    for pixels in (writable, read_only):
        frame = Frame(pixels, -1, 0.0)
        tracker = MarkerTracker(calibration, params)
        marker = tracker.observe(frame)
        tracker.observe(frame)
        process_frame(frame, calibration, params, marker)
        if params.geometric_window:  # the windowed kernel compiles apart
            stripe_mod.extract(pixels, columns=calibration.direct_columns, row_min=0.0,
                               row_max=cam.height / 2.0)
        blank = np.full_like(writable, 10)  # no marker anywhere
        blank.setflags(write=pixels.flags.writeable)
        tracker.observe(Frame(blank, -1, 0.0))
    return (time.perf_counter() - t0) * 1e3


# ---------------------------------------------------------------------------------------------
# Per pass


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
        of each column (``scanner_core.exposure.merge_exposure_pairs``).
    """

    def __init__(self, calibration: Calibration, robot: Robot, clock_offset_s: float = 0.0,
                 fallback_rotation: np.ndarray | None = None, *,
                 merge_exposure_pairs: bool = False, partly_lit_ratio: float = 0.0):
        self.calibration = calibration
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
                                       base_to_tcp(edges.point_b, tcp, rotation).astype(np.float32),
                                       edges.across_b @ rotation, edges.per_px_b @ rotation,
                                       edges, profile.columns,
                                       profile.saturated,
                                       profile.exposure_us * profile.gain)
        with self._lock:
            self._frame_ids.append(profile.frame_id)
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
            if self.merge_exposure_pairs:
                placed = _best_exposed(placed)
            placed, partly_lit_points = _without_partly_lit(placed, self.partly_lit_ratio)
            ids = sorted(self._frame_ids)
            residuals = list(self._residuals)
            unplaced, held, no_rotation = self._unplaced, self._held_rotation, self._no_rotation
        if frames_dropped is None:
            frames_dropped = int(ids[-1] - ids[0] + 1 - len(ids)) if ids else 0
        counts = [len(p.cloud_t) for p in placed]
        scan = Scan(
            cloud=(np.concatenate([p.cloud_t for p in placed]) if placed
                   else np.zeros((0, 3), np.float32)),
            frame_ids=np.repeat(np.array([p.frame_id for p in placed], np.int32), counts),
            quality=(np.concatenate([p.quality for p in placed]).astype(np.float32) if placed
                     else np.zeros(0, np.float32)),
            edges=np.zeros((0, 3), np.float32),
            tcp_positions_b=np.array([p.tcp_b for p in placed]).reshape(-1, 3),
            tcp_times=np.array([p.t for p in placed], dtype=np.float64),
            frames=len(placed),
            frames_dropped=frames_dropped,
            frames_unplaced=unplaced,
            marker_residual_px=float(np.median(residuals)) if residuals else float("nan"),
        )
        scan.points_partly_lit = partly_lit_points
        scan.frames_held_rotation = held
        scan.frames_without_rotation = no_rotation
        scan.tcp_frame_ids = np.array([p.frame_id for p in placed], dtype=np.int64)
        scan.tcp_rotations_b = np.array([p.rotation_b for p in placed],
                                        dtype=np.float64).reshape(-1, 3, 3)
        # The camera centre in {T} per frame: R^T (C_B - p), as base_to_tcp places points.
        scan.sensor_positions_t = np.einsum(
            "fji,fj->fi", scan.tcp_rotations_b,
            self.calibration.camera.origin - scan.tcp_positions_b)
        _stitch_edges(scan, placed, self.calibration)
        scan.end_reason = end_reason.value if end_reason is not None else None
        if end_reason is EndReason.CAMERA_STOPPED and scan.frames:
            scan.interrupted = stopped_because
        return scan


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
    (``scanner_core.edge_kinds.turned_away``)."""
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
    if len(dropout) and len(scan.cloud):
        why[dropout[occluded_dropouts(points[dropout], across[dropout], sensors[dropout],
                                      scan.cloud)]] = EdgeKind.OCCLUDED
    scan.edges_occluded = int((why == EdgeKind.OCCLUDED).sum())
    # The sheet's normal in {T} per frame: R^T n_B.
    sheet_b = calibration.light_plane_b.normal
    rotations = np.array([p.rotation_b for p in placed])
    sheets = np.repeat(np.einsum("fji,j->fi", rotations, sheet_b), counts, axis=0)
    grazed = grazing_edges(points, sheets, scan.cloud, scan.frame_ids, scan.profile_spacing_mm,
                           frame_ids=frames) & (why == 0)
    why[grazed] = EdgeKind.GRAZING
    scan.edges_grazing = int(grazed.sum())
    if len(points) and len(scan.cloud):
        from scanner_core.scanio import point_sensors  # its PLY and normals: not at import

        range_b = sheet_range_b(calibration)
        ranges = np.repeat(np.einsum("fji,j->fi", rotations, range_b), counts, axis=0)
        turned, _, _ = turned_away(points, kind, size, ranges, sensors, scan.cloud,
                                   scan.frame_ids, frames, point_sensors(scan))
        why[turned & (why == 0)] = EdgeKind.TURNED_AWAY
    keep = why == 0
    scan.edges, scan.edge_frame_ids, scan.edge_kind = points[keep], frames[keep], kind[keep]
    scan.edge_size_mm, scan.edge_quality = size[keep], peak[keep]
    scan.edges_aside = AsideEdges(points[~keep].astype(np.float32), frames[~keep], why[~keep],
                                  kind[~keep], size[~keep], peak[~keep])


def camera_frames(camera: Camera, timeout: float = 1.0) -> Iterator[Frame]:
    """The camera's frames until its stream ends (``CameraClosed``); ``CameraTimeout``
    propagates (the camera stopped)."""
    while True:
        try:
            yield camera.grab(timeout)
        except CameraClosed:
            return


def measure_frame(frame: Frame, marker: MarkerObservation, accumulator: PassAccumulator,
                  params: PipelineParams, exposure: ExposureController | None = None) -> bool:
    """One triggered frame: its profile (in the geometric window of the robot's rotation at
    its time), placed; exposure control learns from its stripe. Returns whether it was
    placed. Thread-safe (the service's workers)."""
    looked_up = accumulator.rotation_at(frame.t) if marker.valid else None
    profile = process_frame(frame, accumulator.calibration, params, marker,
                            None if looked_up is None else looked_up[0],
                            accumulator.expected_rows(frame.frame_id))
    if exposure is not None:
        exposure.profile_measured(profile.exposure_us, profile.gain, profile.stripe_peaks,
                                  profile.background_dn)
    return accumulator.add(profile, looked_up)


def feed_frame(frame: Frame, tracker: MarkerTracker, trigger: Trigger,
               accumulator: PassAccumulator, params: PipelineParams,
               timings: dict | None = None,
               exposure: ExposureController | None = None) -> TriggerStep:
    """One frame through the single-threaded core: the tracked marker, the trigger, and the
    profiles of the frames it releases, placed. Adds seconds to ``timings["marker"]`` and
    ``timings["profiles"]`` when given. (The service runs the same steps on two threads.)"""
    if exposure is not None:
        exposure.frame_grabbed(frame.exposure_us, frame.gain)
    t0 = time.perf_counter()
    marker = tracker.observe(frame)
    t1 = time.perf_counter()
    step = trigger.feed((frame, marker), frame.t, marker_in_view(marker), frame.frame_id)
    for held_frame, held_marker in step.emit:
        measure_frame(held_frame, held_marker, accumulator, params, exposure)
    if timings is not None:
        timings["marker"] += t1 - t0
        timings["profiles"] += time.perf_counter() - t1
    return step


def run_pass(frames: Iterable[Frame], calibration: Calibration, robot: Robot,
             params: PipelineParams = PipelineParams(), *, clock_offset_s: float = 0.0,
             exposure: ExposureController | None = None) -> Scan:
    """A stream of frames -> the scan of the first pass it contains, on one thread.

    The trigger is armed at the first frame. Wall time per stage lands in
    ``Scan.timings_ms``: ``acquire`` (waiting for / producing frames), ``marker`` (the tracked
    search, which is also the trigger's presence test), ``profiles`` (stripe, triangulation,
    placement) and ``scan`` (assembling the sorted cloud). A camera that stops mid-pass (it
    raises ``CameraTimeout``, or its stream ends) ends the pass: what was acquired is kept and
    ``Scan.end_reason`` says why. ``exposure`` drives the camera's exposure during the pass
    (``scanner_core.exposure``).
    """
    timings = dict.fromkeys(("acquire", "marker", "profiles", "scan"), 0.0)
    trigger = Trigger(params.trigger)
    trigger.arm()
    tracker = MarkerTracker(calibration, params)
    accumulator = PassAccumulator(calibration, robot, clock_offset_s,
                                  merge_exposure_pairs=params.exposure.mode == "multiple",
                                  partly_lit_ratio=params.partly_lit_ratio)
    source = iter(frames)
    camera_error = None
    while trigger.state.value in ("armed", "scanning"):
        t0 = time.perf_counter()
        try:
            frame = next(source)
        except StopIteration:
            trigger.camera_stopped()
            break
        except CameraTimeout as exc:
            camera_error = f"camera timeout: {exc}"
            trigger.camera_stopped()
            break
        timings["acquire"] += time.perf_counter() - t0
        feed_frame(frame, tracker, trigger, accumulator, params, timings, exposure)
    t0 = time.perf_counter()
    scan = accumulator.scan(end_reason=trigger.end_reason,
                            stopped_because=camera_error or "camera stream ended")
    timings["scan"] = time.perf_counter() - t0
    scan.timings_ms = {k: round(v * 1e3, 3) for k, v in timings.items()}
    return scan
