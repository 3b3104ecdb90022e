"""One pass, from frames to a scan: the one pipeline the CLI, the service and the benchmarks run.

Per frame (:func:`process_frame`): the LED marker in the three views, its multi-view
triangulation, the stripe per column of the direct view, and the stripe's triangulation
(pixel ray x light plane). Per pass (:func:`stitch`): each profile is placed in {T} by the
gripper position derived from the marker, with the gripper's orientation fixed for the pass
(paper section II) — no assumption of constant speed or straight motion.

References
----------
.. [1] "Fast visual part inspection for bin picking", section II (../shared/paper.md).
"""
from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from scanner_core import marker as marker_mod
from scanner_core import stripe as stripe_mod
from scanner_core.calibration import Calibration
from scanner_core.devices import CameraTimeout
from scanner_core.geometry import (base_to_tcp, reproject_marker, triangulate_marker,
                                   triangulate_stripe)
from scanner_core.types import Frame, MarkerObservation, Profile, Scan


#: The marker's mask spans this many times ``marker_mask_px`` along the columns: the blob's
#: halo reaches farther along a column than the stripe's rows vary across a few columns.
MASK_ROW_FACTOR = 4


@dataclass(frozen=True)
class PipelineParams:
    """Settings of the per-frame processing.

    Attributes
    ----------
    stripe_method : str
        One of ``scanner_core.stripe.METHODS``.
    stripe_threshold_dn : float
    min_peak_dn : float
        Columns whose stripe peaks lower are dropped: on grazing surfaces the stripe fades
        into the noise and its centre errs by tenths of a pixel.
    marker : scanner_core.marker.MarkerParams
    marker_mask_px : float
        Stripe columns closer than this to the marker in the direct view are dropped: the LED
        is bright enough to pass for the stripe there.
    max_marker_residual_px : float
        A marker whose views disagree by more than this (RMS reprojection) is rejected.
    trigger_gap_frames : int
        The pass ends after this many consecutive frames without the marker.
    """

    stripe_method: str = "cog"
    stripe_threshold_dn: float = 20.0
    min_peak_dn: float = 40.0
    marker: marker_mod.MarkerParams = field(default_factory=marker_mod.MarkerParams)
    marker_mask_px: float = 12.0
    max_marker_residual_px: float = 1.0
    trigger_gap_frames: int = 3


def observe_marker(image: np.ndarray, calibration: Calibration, params: PipelineParams) -> MarkerObservation:
    """Find and triangulate the LED marker in one image."""
    pixels = marker_mod.find_markers(image, strips=calibration.strips, params=params.marker)
    try:
        position, residual = triangulate_marker(pixels, calibration.camera, calibration.mirrors)
    except ValueError:  # views (nearly) parallel: this frame cannot be placed
        position, residual = np.full(3, np.nan), float("nan")
    if np.isfinite(residual) and residual > params.max_marker_residual_px:
        position = np.full(3, np.nan)
    return MarkerObservation(pixels, position, residual)


def process_frame(frame: Frame, calibration: Calibration, params: PipelineParams = PipelineParams()) -> Profile:
    """One frame -> one profile (stripe points in {B}) and the marker position.

    Parameters
    ----------
    frame : Frame
        ``frame.image`` (H, W) uint8.
    calibration : Calibration
    params : PipelineParams

    Returns
    -------
    Profile
    """
    image = frame.image
    marker = observe_marker(image, calibration, params)
    result = stripe_mod.extract(image, method=params.stripe_method,
                                threshold=params.stripe_threshold_dn,
                                columns=calibration.direct_columns)
    valid = result.valid & (result.peak >= params.min_peak_dn)
    direct_px = marker.pixels[0]
    if not np.all(np.isfinite(direct_px)) and marker.valid:
        # Seen only in the mirrors (cut off at the image edge, or hidden): mask where the
        # direct view must show it, since a partial blob still passes for the stripe.
        direct_px = reproject_marker(marker.position_b, calibration.camera, calibration.mirrors)[0]
    if np.all(np.isfinite(direct_px)):
        near = np.abs(np.arange(image.shape[1]) - direct_px[0]) <= params.marker_mask_px
        valid &= ~(near & (np.abs(result.row - direct_px[1]) <= params.marker_mask_px * MASK_ROW_FACTOR))
    columns = np.nonzero(valid)[0].astype(np.int32)
    pixels = np.stack([columns.astype(np.float64), result.row[columns].astype(np.float64)], axis=1)
    points_b = triangulate_stripe(pixels, calibration.camera, calibration.light_plane_c)
    finite = np.isfinite(points_b).all(axis=1)  # rays parallel to the sheet, or behind the camera
    columns, points_b = columns[finite], points_b[finite]
    return Profile(frame.frame_id, frame.t, points_b, columns,
                   result.peak[columns].astype(np.float32), marker)


def warm_up(calibration: Calibration, params: PipelineParams = PipelineParams()) -> float:
    """Compile the numba kernels before the first pass, so that no frame of a pass waits for
    the JIT: a synthetic frame with a stripe and a marker blob in every view goes through the
    trigger and the frame processing once. Returns the time it took, ms."""
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
    frame = Frame(np.clip(image, 0, 255).astype(np.uint8), -1, 0.0)
    marker_mod.marker_present(frame.image, strips=calibration.strips, params=params.marker)
    process_frame(frame, calibration, params)
    return (time.perf_counter() - t0) * 1e3


def pass_frames(frames: Iterable[Frame], calibration: Calibration,
                params: PipelineParams = PipelineParams()) -> Iterator[Frame]:
    """The trigger: yield the frames of one pass (paper section V: the LED triggers the scan).

    The pass starts at the first frame that shows the marker and ends once
    ``params.trigger_gap_frames`` frames in a row have not shown it; frames missing the marker
    inside the pass (a view hidden for a moment) are kept, those after its end are not.
    """
    started = False
    pending: list[Frame] = []
    for frame in frames:
        present = marker_mod.marker_present(frame.image, strips=calibration.strips,
                                            params=params.marker)
        if present:
            started = True
            yield from pending
            pending.clear()
            yield frame
        elif started:
            pending.append(frame)
            if len(pending) >= params.trigger_gap_frames:
                return


def stitch(profiles: list[Profile], calibration: Calibration, gripper_rotation_b: np.ndarray) -> Scan:
    """Place each profile in {T} by the marker-derived gripper position.

    With the marker at ``m_T`` in {T} and {T}'s rotation ``R`` in {B} fixed for the pass,
    the TCP is at ``p = M_B - R m_T`` and a stripe point goes to ``X_T = R^T (X_B - p)``.

    Parameters
    ----------
    profiles : list of Profile
    calibration : Calibration
    gripper_rotation_b : (3, 3) float64
        {T} in {B}, as the robot reports it.

    Returns
    -------
    Scan
        Profiles without a triangulated marker are left out (their frames do not count).
    """
    r = np.asarray(gripper_rotation_b, dtype=np.float64)
    placed = [p for p in profiles if p.marker.valid]
    clouds, ids, quality, tcps, times = [], [], [], [], []
    for p in placed:
        tcp = p.marker.position_b - r @ calibration.marker_offset_t
        clouds.append(base_to_tcp(p.points_b, tcp, r))
        ids.append(np.full(len(p.points_b), p.frame_id, dtype=np.int32))
        quality.append(p.quality)
        tcps.append(tcp)
        times.append(p.t)
    frame_ids = [p.frame_id for p in profiles]
    dropped = int(max(frame_ids) - min(frame_ids) + 1 - len(frame_ids)) if frame_ids else 0
    return Scan(
        cloud=np.concatenate(clouds).astype(np.float32) if clouds else np.zeros((0, 3), np.float32),
        frame_ids=np.concatenate(ids) if ids else np.zeros(0, np.int32),
        quality=np.concatenate(quality) if quality else np.zeros(0, np.float32),
        edges=np.zeros((0, 3), np.float32),
        tcp_positions_b=np.array(tcps).reshape(-1, 3),
        tcp_times=np.array(times),
        frames=len(placed),
        frames_dropped=dropped,
        frames_unplaced=len(profiles) - len(placed),
        marker_residual_px=_median_residual(profiles),
    )


def _median_residual(profiles: list[Profile]) -> float:
    residuals = [p.marker.residual_px for p in profiles if np.isfinite(p.marker.residual_px)]
    return float(np.median(residuals)) if residuals else float("nan")


def scan_frames(frames: Iterable[Frame], calibration: Calibration, gripper_rotation_b: np.ndarray,
                params: PipelineParams = PipelineParams()) -> Scan:
    """A stream of frames -> the scan of the pass it contains (trigger, profiles, stitching).

    Wall time per stage lands in ``Scan.timings_ms``: ``acquire`` (waiting for / producing
    frames), ``trigger``, ``profiles`` and ``stitch``. A camera that stops mid-pass (it raises
    ``CameraTimeout``) ends the pass: what was acquired is stitched and ``Scan.interrupted``
    says why.
    """
    timings = {"acquire": 0.0, "trigger": 0.0, "profiles": 0.0, "stitch": 0.0}
    source = iter(frames)
    interrupted = []

    def timed_source():
        while True:
            t0 = time.perf_counter()
            try:
                frame = next(source)
            except StopIteration:
                return
            except CameraTimeout as exc:
                interrupted.append(f"camera timeout: {exc}")
                return
            timings["acquire"] += time.perf_counter() - t0
            yield frame

    profiles = []
    t_loop = time.perf_counter()
    for frame in pass_frames(timed_source(), calibration, params):
        t0 = time.perf_counter()
        profiles.append(process_frame(frame, calibration, params))
        timings["profiles"] += time.perf_counter() - t0
    # The trigger's share is what the loop spent neither waiting for frames nor processing them.
    timings["trigger"] = time.perf_counter() - t_loop - timings["acquire"] - timings["profiles"]
    t0 = time.perf_counter()
    scan = stitch(profiles, calibration, gripper_rotation_b)
    timings["stitch"] = time.perf_counter() - t0
    scan.timings_ms = {k: round(v * 1e3, 3) for k, v in timings.items()}
    scan.interrupted = interrupted[0] if interrupted else None
    return scan
