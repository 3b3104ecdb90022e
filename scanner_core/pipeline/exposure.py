"""Exposure control within a pass: fixed, dynamic (from the previous frames' peaks) or
multiple (two exposures alternating, the better exposed column of each pair kept).

A stripe on a dark anodised part peaks at a few tens of DN at the exposure a matte part
needs, and machined metal near the specular angle clips at full scale; industrial profilers
answer with exposure control (LMI Gocator: single, dynamic and multiple exposure). Here:

- ``"fixed"``: the camera keeps the exposure it has.
- ``"dynamic"``: after each frame that shows the stripe, the next exposure brings the
  ``percentile``-th column peak (above the background) to ``target_peak_dn``, scaling the
  exposure of *that* frame (a deadbeat step on a surface of constant brightness, whatever the
  delay between the frame and its processing); exposure time first, up to the frame period
  (``max_duty``), then gain.
- ``"multiple"``: frames alternate between a long exposure and one ``multiple_ratio`` times
  shorter; :func:`merge_exposure_pairs` keeps, in each column of each pair of consecutive
  frames, the measurement of the better exposed one (the brightest that is not clipped; the
  shorter exposure where both clip). The long exposure starts at the camera's and is steered
  like the dynamic one, from the long frames, but on a lower percentile
  (``multiple_percentile``): the short frames take care of what clips.

The brightness the controller works with is the product ``exposure_us * gain``
(``Frame.exposure_us``, ``Frame.gain``); a camera that implements
``scanner_core.devices.ExposureControl`` is driven through ``set_exposure``.

References
----------
.. [1] LMI Technologies, Gocator line profile sensors user manual: exposure modes (single,
   dynamic, multiple) and spot selection.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from scanner_core.devices import ExposureControl

EXPOSURE_MODES = ("fixed", "dynamic", "multiple")

#: A stripe over fewer valid columns than this says too little of the surface to steer by.
MIN_STRIPE_COLUMNS = 20
#: Multiple exposure: what a clipped column scores against an unclipped one's peak, DN.
CLIPPED_SCORE_DN = 128.0
#: A steered peak this far above the background is taken as clipped (full scale 255 less a
#: background of ~10 DN and its noise).
CLIPPED_DN = 240.0


@dataclass(frozen=True)
class ExposureParams:
    """Settings of exposure control.

    Attributes
    ----------
    mode : str
        One of ``EXPOSURE_MODES``.
    target_peak_dn : float
        Dynamic: the aim for the ``percentile``-th column peak above the background, DN. 180 DN
        over a 10 DN background keeps the bulk of the stripe unclipped with 65 DN of headroom;
        the brightest columns may clip, which the stripe's saturation fit measures.
    percentile : float
        Dynamic: which column peak is steered, percent of the stripe's columns.
    max_step : float
        Dynamic: largest change of brightness per update (either way), a factor.
    deadband : float
        Dynamic: relative errors smaller than this leave the exposure alone (no chatter on
        noise).
    max_duty : float
        Dynamic: the exposure time stays below this fraction of the frame period; beyond it the
        gain rises.
    multiple_ratio : float
        Multiple: the second exposure is this many times shorter than the first.
    multiple_percentile : float
        Multiple: the long exposure brings this percentile of the column peaks to
        ``target_peak_dn``. 25: three quarters of the stripe may clip in the long frame (the
        short one measures them) and the darkest quarter still gets the long exposure's SNR.
    """

    mode: str = "fixed"
    target_peak_dn: float = 180.0
    percentile: float = 75.0
    max_step: float = 4.0
    deadband: float = 0.1
    max_duty: float = 0.9
    multiple_ratio: float = 8.0
    multiple_percentile: float = 25.0

    def __post_init__(self):
        if self.mode not in EXPOSURE_MODES:
            raise ValueError(f"exposure mode must be one of {EXPOSURE_MODES}, got {self.mode!r}")
        if not 0 < self.target_peak_dn < 255:
            raise ValueError(f"`target_peak_dn` must be in (0, 255), got {self.target_peak_dn}")
        for name in ("percentile", "multiple_percentile"):
            if not 0 < getattr(self, name) <= 100:
                raise ValueError(f"`{name}` must be in (0, 100], got {getattr(self, name)}")
        if not self.max_step > 1:
            raise ValueError(f"`max_step` must be > 1, got {self.max_step}")
        if not 0 < self.max_duty <= 1:
            raise ValueError(f"`max_duty` must be in (0, 1], got {self.max_duty}")
        if not self.multiple_ratio > 1:
            raise ValueError(f"`multiple_ratio` must be > 1, got {self.multiple_ratio}")


def stripe_brightness(peaks_dn, background_dn: float, percentile: float) -> float:
    """The steered statistic: the ``percentile``-th column peak above the background, DN.

    Parameters
    ----------
    peaks_dn : (N,) float
        Peak of the stripe in each column that holds one (clipped ones at full scale).
    background_dn : float

    Returns
    -------
    float
        NaN with fewer than ``MIN_STRIPE_COLUMNS`` columns.
    """
    peaks = np.asarray(peaks_dn, dtype=np.float64)
    peaks = peaks[np.isfinite(peaks)]
    if len(peaks) < MIN_STRIPE_COLUMNS:
        return math.nan
    bg = background_dn if math.isfinite(background_dn) else 0.0
    return float(np.percentile(peaks, percentile) - bg)


def next_brightness(level: float, brightness_dn: float, params: ExposureParams) -> float | None:
    """Dynamic exposure's step: the brightness (``exposure_us * gain``) for the next frames.

    Parameters
    ----------
    level : float
        ``exposure_us * gain`` of the frame measured.
    brightness_dn : float
        Its ``stripe_brightness``.

    Returns
    -------
    float or None
        None to leave the exposure as it is (no stripe, or within the dead band).
    """
    if not (math.isfinite(level) and math.isfinite(brightness_dn)) or level <= 0:
        return None
    if brightness_dn >= CLIPPED_DN:
        # the steered peak clips: how far over is unknown, so step down as far as allowed
        return level / params.max_step
    factor = params.target_peak_dn / max(brightness_dn, 1.0)
    if abs(factor - 1.0) <= params.deadband:
        return None
    factor = min(max(factor, 1.0 / params.max_step), params.max_step)
    return level * factor


def split_brightness(level: float, exposure_range_us, gain_range, max_exposure_us: float
                     ) -> tuple[float, float]:
    """Exposure time and gain for a brightness ``level = exposure_us * gain``: time first (gain
    adds noise), up to ``max_exposure_us``, then gain; clipped to what the camera accepts."""
    e_lo, e_hi = exposure_range_us
    g_lo, g_hi = gain_range
    e_max = max(min(e_hi, max_exposure_us), e_lo)
    exposure = min(max(level / g_lo, e_lo), e_max)
    gain = min(max(level / exposure, g_lo), g_hi)
    return float(exposure), float(gain)


class ExposureController:
    """Drives a camera's exposure during passes (``ExposureParams.mode``).

    Call :meth:`frame_grabbed` for every frame the camera delivers (multiple: the next frame
    takes the other exposure) and :meth:`profile_measured` for every frame whose stripe was
    measured (dynamic). Thread-safe: the service measures on worker threads while its
    acquisition thread grabs.

    Parameters
    ----------
    camera : object
        The camera; control is off unless it implements
        ``scanner_core.devices.ExposureControl``.
    params : ExposureParams
    fps : float
        Frame rate, Hz: the exposure time stays below ``max_duty`` of the period.
    """

    def __init__(self, camera, params: ExposureParams, fps: float):
        self.params = params
        self.camera = camera if isinstance(camera, ExposureControl) else None
        self._lock = threading.Lock()
        self._max_exposure_us = params.max_duty * 1e6 / fps if fps > 0 else math.inf
        self._long = None  # multiple: (exposure_us, gain) of the long exposure
        self._next_short = False
        self.updates = 0

    @property
    def active(self) -> bool:
        return self.camera is not None and self.params.mode != "fixed"

    def _set(self, level: float) -> tuple[float, float]:
        cam = self.camera
        exposure, gain = split_brightness(level, cam.exposure_range_us, cam.gain_range,
                                          self._max_exposure_us)
        cam.set_exposure(exposure, gain)
        self.updates += 1
        return exposure, gain

    def frame_grabbed(self, exposure_us: float, gain: float) -> None:
        """Multiple: set the exposure the next frame takes (the other one of the pair)."""
        if not self.active or self.params.mode != "multiple":
            return
        with self._lock:
            if self._long is None:
                if not math.isfinite(exposure_us):
                    return
                self._long = (float(exposure_us), float(gain))
            exposure, gain_long = self._long
            level = exposure * gain_long
            self._next_short = not self._next_short
            if self._next_short:
                level /= self.params.multiple_ratio
            self._set(level)

    def profile_measured(self, exposure_us: float, gain: float, peaks_dn,
                         background_dn: float) -> None:
        """Steer from one measured frame (the peaks of the columns holding the stripe,
        clipped ones included, DN): dynamic, every frame; multiple, the long ones."""
        if not self.active or self.params.mode == "fixed":
            return
        measured = exposure_us * gain
        if self.params.mode == "dynamic":
            brightness = stripe_brightness(peaks_dn, background_dn, self.params.percentile)
            level = next_brightness(measured, brightness, self.params)
            if level is not None:
                with self._lock:
                    self._set(level)
            return
        with self._lock:
            if self._long is None or not math.isclose(measured, self._long[0] * self._long[1],
                                                      rel_tol=1e-6):
                return  # a short frame, or a long one from before the last change
            brightness = stripe_brightness(peaks_dn, background_dn,
                                           self.params.multiple_percentile)
            level = next_brightness(measured, brightness, self.params)
            if level is not None:
                cam = self.camera
                self._long = split_brightness(level, cam.exposure_range_us, cam.gain_range,
                                              self._max_exposure_us)


def merge_exposure_pairs(frame_ids, levels, columns, peaks, saturated) -> list[np.ndarray]:
    """Multiple exposure: per pair of consecutive frames taken at different exposures, keep
    in each column the measurement of the better exposed frame.

    Frames pair up in order of ``frame_ids`` when their ids follow each other and their levels
    differ (a dropped frame leaves its partner alone, kept whole). In a column measured in both
    frames of a pair, the brighter wins, a clipped peak counting as ``CLIPPED_SCORE_DN`` (its
    centre comes from the flanks, ~0.02 px up to 10x full scale: as good as an unclipped stripe
    of about half full scale); between two clipped ones, the shorter exposure (the narrower
    plateau). Measured on idler_riser (matte preset): preferring any unclipped peak gave
    23.8 um RMS, this rule 15.8 um, the fixed exposure 13.5 um.

    Parameters
    ----------
    frame_ids : (F,) int
    levels : (F,) float
        ``exposure_us * gain`` of each frame.
    columns : list of (N_f,) int
        Image column of each measurement of frame f.
    peaks : list of (N_f,) float
        Its peak, DN.
    saturated : list of (N_f,) bool

    Returns
    -------
    list of (N_f,) bool
        Which measurements of each frame are kept.
    """
    order = np.argsort(np.asarray(frame_ids), kind="stable")
    keep = [np.ones(len(c), bool) for c in columns]
    i = 0
    while i < len(order) - 1:
        a, b = order[i], order[i + 1]
        if frame_ids[b] != frame_ids[a] + 1 or levels[a] == levels[b]:
            i += 1
            continue
        _resolve_pair(a, b, levels, columns, peaks, saturated, keep)
        i += 2
    return keep


def _resolve_pair(a, b, levels, columns, peaks, saturated, keep) -> None:
    common, ia, ib = np.intersect1d(columns[a], columns[b], assume_unique=True,
                                    return_indices=True)
    if len(common) == 0:
        return
    sat_a, sat_b = saturated[a][ia], saturated[b][ib]
    shorter_a = levels[a] < levels[b]
    score_a = np.where(sat_a, CLIPPED_SCORE_DN, peaks[a][ia])
    score_b = np.where(sat_b, CLIPPED_SCORE_DN, peaks[b][ib])
    a_wins = np.where(sat_a & sat_b, shorter_a, score_a >= score_b)
    keep[a][ia[~a_wins]] = False
    keep[b][ib[a_wins]] = False


#: Points of two consecutive profiles this close along x_T (mm: about a pixel's footprint) look
#: at the same place of the part.
PARTLY_LIT_MATCH_MM = 0.2


def partly_lit(frame_ids, cloud_t, quality, brightness, ratio: float,
               match_mm: float = PARTLY_LIT_MATCH_MM) -> np.ndarray:
    """Points whose surface the sheet reached or left during the exposure.

    The part moves during an exposure (0.2 mm in 1 ms at 200 mm/s): a surface that enters or
    leaves the sheet meanwhile is lit for part of it, and placed where the gripper was at its
    middle, up to half that travel off. Such a point is dimmer than the same place of the same
    surface in the one neighbouring profile that sees it (the surface's other side lies
    beyond the sheet): by more than ``ratio``, it is not kept.

    Parameters
    ----------
    frame_ids : (N,) int
        The profile of each point; consecutive ids are consecutive frames.
    cloud_t : (N, 3) float
        The points in {T}, mm.
    quality : (N,) float
        Each point's stripe peak, DN.
    brightness : (N,) float
        Its frame's exposure times gain (NaN: unknown, taken as 1): peaks are compared per
        unit of light collected.
    ratio : float
        In (0, 1); 0 keeps every point.

    Returns
    -------
    (N,) bool
        The points lit for part of the exposure.
    """
    frame_ids = np.asarray(frame_ids).reshape(-1)
    cloud = np.asarray(cloud_t, dtype=np.float64).reshape(-1, 3)
    light = np.asarray(brightness, dtype=np.float64)
    level = np.asarray(quality, dtype=np.float64) / np.where(np.isfinite(light) & (light > 0),
                                                              light, 1.0)
    out = np.zeros(len(cloud), bool)
    if ratio <= 0 or len(cloud) == 0:
        return out
    # Every point's nearest along x_T in each neighbouring profile at once: the points sorted
    # by profile, then x, under one key (the profile's rank times a span wider than the
    # cloud, plus x), and each looked up between its two sorted neighbours there.
    ids, rank = np.unique(frame_ids, return_inverse=True)
    x = cloud[:, 0] - cloud[:, 0].min()
    span = float(x.max()) + 4.0 * match_mm + 1.0
    order = np.lexsort((x, rank))
    key = rank[order] * span + x[order]
    seen, reference = [], []
    for step in (-1, 1):
        wanted = frame_ids + step
        where = np.minimum(np.searchsorted(ids, wanted), len(ids) - 1)
        exists = ids[where] == wanted
        place = np.searchsorted(key, where * span + x)
        best = np.full(len(cloud), -1, np.int64)
        best_d = np.full(len(cloud), np.inf)
        for candidate in (place - 1, place):  # the left one first: it keeps a tie
            inside = (candidate >= 0) & (candidate < len(order))
            other = order[np.clip(candidate, 0, len(order) - 1)]
            d = np.abs(x[other] - x)
            nearer = inside & exists & (rank[other] == where) & (d < best_d)
            best = np.where(nearer, other, best)
            best_d = np.where(nearer, d, best_d)
        found = best_d < match_mm
        other = np.where(found, best, 0)
        # The same surface: no steeper than about 56 degrees between the two profiles.
        dz = np.abs(cloud[other, 2] - cloud[:, 2])
        dy = np.abs(cloud[other, 1] - cloud[:, 1])
        same = found & (dz <= np.maximum(0.5, 1.5 * dy))
        seen.append(same)
        reference.append(np.where(same, level[other], 0.0))
    one_side = seen[0] ^ seen[1]
    return one_side & (level < ratio * np.where(seen[0], reference[0], reference[1]))
