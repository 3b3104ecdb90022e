"""One frame of a pass: the LED marker in the three views, and the profile of the stripe.

The LED marker is found once per frame (:func:`observe_marker`; :class:`MarkerTracker`
searches near where the previous frames put it) and shared by the trigger's presence test
(:func:`marker_in_view`) and the frame's processing; then (:func:`process_frame`) the stripe
per column of the direct view (:func:`frame_stripe`, in the geometric window when the gripper's
pose is known), its edge points, and its triangulation (pixel ray x light plane), in {B}.
:func:`warm_up` compiles the numba kernels all this runs before the first pass.
:class:`PipelineParams` holds the settings of the whole streaming core (``scanner_core.pipeline``).

References
----------
.. [1] "Fast visual part inspection for bin picking", section II.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from scanner_core.marker import finder as marker_mod
from scanner_core.stripe import extractor as stripe_mod
from scanner_core.geometry.calibration import Calibration
from scanner_core.edges import EdgeParams, find_edges
from scanner_core.pipeline.exposure import ExposureParams
from scanner_core.geometry import reproject_marker, triangulate_marker, triangulate_stripe
from scanner_core.pipeline.trigger import TriggerParams
from scanner_core.types import Frame, MarkerObservation, Profile
from scanner_core.stripe.window import volume_box_t, volume_rows

__all__ = ["PipelineParams", "observe_marker", "MarkerTracker", "marker_in_view",
           "marker_image", "stripe_image", "frame_stripe", "process_frame", "warm_up",
           "MASK_ROW_FACTOR"]

#: The marker's mask spans this many times ``marker_mask_px`` along the columns: the blob's
#: halo reaches farther along a column than the stripe's rows vary across a few columns.
MASK_ROW_FACTOR = 4

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
        One of ``scanner_core.stripe.extractor.METHODS``.
    stripe_threshold_dn : float
    min_peak_dn : float
        With ``stripe_floor="fixed"``: columns whose stripe peaks lower are dropped (on grazing
        surfaces the stripe fades into the noise and its centre errs by tenths of a pixel).
    stripe_floor : str
        ``"auto"`` (default): the threshold and the minimum peak follow the frame's noise
        (``scanner_core.stripe.extractor``, ``threshold="auto"``: 20 DN on the reference model) and a
        column is kept when its peak SNR reaches ``min_peak_snr``, so that a dark part's stripe
        (30 DN over 3 DN of noise) still counts, its ``quality`` (the peak) saying how much to
        trust it.  ``"fixed"``: ``stripe_threshold_dn`` and ``min_peak_dn`` (the earlier default).
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
        Which peak is the stripe where a column holds two (``scanner_core.stripe.extractor.POLICIES``);
        default "continuity": under a reflection at half the stripe's brightness it keeps the
        true stripe in every column.  "reject" drops such columns (the earlier default).
    stripe_saturation : str
        ``"fit"`` (default): clipped peaks are measured from their flanks
        (``scanner_core.stripe.extractor``: up to 10x full scale to ~0.02 px RMS) and flagged
        ``saturated``; ``"reject"``: dropped (the earlier default).
    marker : scanner_core.marker.finder.MarkerParams
    marker_mask_px : float
        Stripe columns closer than this to the marker in the direct view are dropped: the LED
        is bright enough to pass for the stripe there.
    max_marker_residual_px : float
        A marker whose views disagree by more than this (RMS reprojection) is rejected.
    min_stripe_run : int
        A stretch of fewer stripe columns than this, contradicted by a longer stretch beside it,
        is dropped (``scanner_core.stripe.extractor.isolated_runs``: a reflection that wins the columns
        where the true stripe is too dim); 1 keeps everything.
    follow_previous_profile : bool
        With ``stripe_policy="continuity"``: prefer, where a column holds two peaks, the one
        nearer to the stripe's row in the newest profile of the last ``PREVIOUS_PROFILE_FRAMES``
        frames (``scanner_core.stripe.extractor``, ``expected_row``): a glint longer than the neighbouring
        columns can bridge is not taken for the stripe.
    geometric_window : bool
        Look for the stripe only in the rows the inspection volume's section of the sheet can
        reach in each column (``scanner_core.stripe.window``), for frames whose TCP pose is known
        (the marker, and the robot's rotation).  A reflection outside them (onto the cell, the
        gripper's fingers) is never taken for the stripe.
    inspection_volume_mm : (3,) float
        Its size along x_T, y_T, z_T below the TCP, mm.
    window_margin_mm : float
        The volume grown by this on every side for the window (a misplaced part may reach out
        of it by the gripper's tolerance).
    exposure : scanner_core.pipeline.exposure.ExposureParams
        Exposure control (fixed, dynamic or multiple).
    trigger : TriggerParams
    edges : scanner_core.edges.EdgeParams
        Drop-out and step detection along each profile.
    stripe_signal : str
        What the stripe is looked for in (``scanner_core.stripe.extractor.stripe_signal``): a mono frame
        as it is, and by default (``"auto"``) a colour frame's (or a mosaic's) largest colour
        excess, measured with ``shoulders`` (its chroma, which JPEG's 4:2:0 and demosaicing
        spread about the line); or a channel, or one colour's excess. The LED marker is looked
        for in the frame's grey (``marker_image``).
    bayer : str or None
        The camera's frames are raw Bayer mosaics with this pattern
        (``scanner_core.stripe.extractor.BAYER_PATTERNS``), demosaiced for both.
    partly_lit_ratio : float
        A point dimmer than this share of the same place in the one neighbouring profile that
        sees it was lit for part of the exposure (its surface reached or left the sheet
        meanwhile) and is not kept (``scanner_core.pipeline.exposure.partly_lit``); 0 keeps them. At
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
    stripe_signal: str = "auto"
    bayer: str | None = None
    partly_lit_ratio: float = 0.5

    @property
    def measured_box_t(self) -> np.ndarray | None:
        """(2, 3): the box in {T} outside which a pass measures nothing (the geometric
        window's inspection volume and margin: ``Scan.measured_box_t``); None without the
        window."""
        return (volume_box_t(self.inspection_volume_mm, self.window_margin_mm)
                if self.geometric_window else None)


# ---------------------------------------------------------------------------------------------
# Per frame


def marker_image(image: np.ndarray, params: PipelineParams) -> np.ndarray:
    """The frame the LED marker is looked for in: a mono frame as it is, a colour one (or a
    ``params.bayer`` mosaic, demosaiced) in grey (the white LED is bright in every channel,
    where the colour excess that holds the stripe would lose it).

    Parameters
    ----------
    image : (H, W) uint8, or (H, W, 3) uint8 RGB"""
    if params.bayer is not None:
        image = stripe_mod.demosaic(image, params.bayer)
    if image.ndim == 3:
        return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    return image


def stripe_image(image: np.ndarray, params: PipelineParams) -> tuple[np.ndarray, bool]:
    """The frame the stripe is looked for in (``params.stripe_signal``), and whether it came
    from a colour frame (then measured with ``shoulders``, ``scanner_core.stripe.extractor.extract``)."""
    colour = image.ndim == 3 or params.bayer is not None
    return stripe_mod.stripe_signal(image, params.stripe_signal, bayer=params.bayer), colour


def observe_marker(image: np.ndarray, calibration: Calibration, params: PipelineParams,
                   near: np.ndarray | None = None) -> MarkerObservation:
    """Find and triangulate the LED marker in one image.

    Parameters
    ----------
    image : (H, W) uint8, or a colour frame (``marker_image``)
    calibration : Calibration
    params : PipelineParams
    near : (3, 2) float64, optional
        Predicted (column, row) per view (NaN: no prediction); each view is searched there
        first, then over its whole strip.
    """
    pixels = marker_mod.find_markers(marker_image(image, params), strips=calibration.strips,
                                     params=params.marker, near=near)
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
    result : scanner_core.stripe.extractor.StripeResult
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
    signal, colour = stripe_image(image, params)
    result = stripe_mod.extract(signal, method=params.stripe_method, shoulders=colour,
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
    marker search (whole strips and near a prediction) and the frame processing, the
    geometric window's rows are found for the inspection volume, and a frame without the
    marker goes through the search. (Read-only frames reach the kernels as writable
    copies: ``validate.check_image``.) Returns the time it took, ms."""
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
    pixels = np.clip(image, 0, 255).astype(np.uint8)
    if params.bayer is None and params.stripe_signal not in ("auto", "mono"):
        pixels = np.repeat(pixels[:, :, None], 3, axis=2)  # the colour frames it will get
    frame = Frame(pixels, -1, 0.0)
    tracker = MarkerTracker(calibration, params)
    marker = tracker.observe(frame)
    tracker.observe(frame)
    process_frame(frame, calibration, params, marker)
    if params.geometric_window:  # the window's kernels and the windowed search compile apart
        volume_rows(calibration, np.zeros(3), np.eye(3), params.inspection_volume_mm,
                    margin_mm=params.window_margin_mm)
        stripe_mod.extract(stripe_image(pixels, params)[0], columns=calibration.direct_columns,
                           row_min=0.0, row_max=cam.height / 2.0)
    tracker.observe(Frame(np.full_like(pixels, 10), -1, 0.0))  # no marker anywhere
    return (time.perf_counter() - t0) * 1e3
