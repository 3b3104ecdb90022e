"""A camera's clock mapped onto the host's, and the drift between the two measured.

An industrial camera stamps each frame with its own clock (a tick counter, usually 1 GHz on
USB3 Vision, the ``GevTimestampTickFrequency`` on GigE Vision); the robot's reports, looked up
by the cross-check and the accumulator, live on another clock, and the two are tied through the
host. The host receives frame ``k`` at ``host_k = offset + (1 + drift) * camera_k + latency_k``,
the latency (read-out, transfer, the driver) positive and varying from frame to frame. The
lower envelope of ``host_k - camera_k`` is therefore the offset plus the smallest latency and the
drift: :class:`CameraClock` fits a line through the minima of short buckets of it over a
sliding window and maps every camera time through that line. The mapped time is the exposure's
time on the host clock plus the smallest latency, a constant that the robot-minus-camera clock
offset (estimated per pass by the cross-check) absorbs.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

__all__ = ["CameraClock", "ClockEstimate", "BUCKET_S", "WINDOW_BUCKETS"]

#: Length of one bucket of the lower envelope, s of camera time: long enough that a bucket
#: holds a frame that came through with (nearly) the least latency (about 80 frames at
#: 162 fps), short enough that a drift of 100 ppm moves the offset by 50 us within it.
BUCKET_S = 0.5
#: Buckets in the sliding window that the line is fitted to (10 s): a drift of a few ppm shows
#: as tens of microseconds over it, well above the scatter of the bucket minima.
WINDOW_BUCKETS = 20


@dataclass(frozen=True)
class ClockEstimate:
    """The mapping as it stands.

    Attributes
    ----------
    offset_s : float
        Host minus camera time at camera time ``reference_s``, s (smallest latency included).
    drift_ppm : float
        How much faster the host clock runs than the camera's, parts per million; NaN until
        two buckets are complete.
    reference_s : float
        The camera time the offset refers to, s.
    frames : int
        Frames the mapping has seen.
    """

    offset_s: float
    drift_ppm: float
    reference_s: float
    frames: int


class CameraClock:
    """Maps camera timestamps (s) to host times (s); not thread-safe (one acquisition thread).

    Parameters
    ----------
    bucket_s : float
        See :data:`BUCKET_S`.
    window_buckets : int
        See :data:`WINDOW_BUCKETS`; at least 2.
    """

    def __init__(self, *, bucket_s: float = BUCKET_S, window_buckets: int = WINDOW_BUCKETS):
        if not (math.isfinite(bucket_s) and bucket_s > 0):
            raise ValueError(f"`bucket_s` must be > 0, got {bucket_s!r}")
        if int(window_buckets) < 2:
            raise ValueError(f"`window_buckets` must be >= 2, got {window_buckets!r}")
        self.bucket_s = float(bucket_s)
        self._buckets: deque[tuple[float, float]] = deque(maxlen=int(window_buckets))
        self._current: tuple[int, float, float] | None = None  # (index, camera_s, min offset)
        self._line = (math.nan, 0.0, math.nan)  # (reference camera_s, offset at it, slope)
        self._frames = 0

    def map(self, camera_s: float, host_s: float) -> float:
        """The host time of a frame stamped ``camera_s`` by the camera and received at
        ``host_s`` by the host (both s); the observation also updates the mapping."""
        camera_s, host_s = float(camera_s), float(host_s)
        if not (math.isfinite(camera_s) and math.isfinite(host_s)):
            raise ValueError(f"camera and host times must be finite, got {camera_s}, {host_s}")
        self._observe(camera_s, host_s - camera_s)
        reference, offset, slope = self._line
        if not math.isfinite(reference):
            return host_s  # the very first frame: nothing below it yet
        # Never later than it was received: a frame's exposure precedes its arrival.
        return min(camera_s + offset + slope * (camera_s - reference), host_s)

    def estimate(self) -> ClockEstimate:
        """The mapping now (see :class:`ClockEstimate`)."""
        reference, offset, slope = self._line
        drift = slope * 1e6 if len(self._buckets) >= 2 else math.nan
        return ClockEstimate(offset, drift, reference, self._frames)

    def _observe(self, camera_s: float, offset: float) -> None:
        self._frames += 1
        index = math.floor(camera_s / self.bucket_s)
        current = self._current
        if current is None or index != current[0]:
            if current is not None:
                self._buckets.append((current[1], current[2]))
            current = (index, camera_s, offset)
        elif offset < current[2]:
            current = (index, camera_s, offset)
        self._current = current
        self._fit(current)

    def _fit(self, current: tuple[int, float, float]) -> None:
        """The line through the complete buckets' minima (and the current bucket's until
        two are complete); a lone point keeps the previous slope."""
        points = list(self._buckets)
        if len(points) < 2:
            points.append((current[1], current[2]))
        if len(points) == 1:
            self._line = (points[0][0], points[0][1], self._line[2] if
                          math.isfinite(self._line[2]) else 0.0)
            return
        t = np.array([p[0] for p in points])
        y = np.array([p[1] for p in points])
        reference = float(t[-1])
        # Centred before the fit: camera clocks count from the camera's power-up, and
        # (t - mean) keeps the normal equations well conditioned.
        tc = t - t.mean()
        denominator = float(tc @ tc)
        slope = float(tc @ (y - y.mean())) / denominator if denominator > 0 else 0.0
        offset = float(y.mean() + slope * (reference - t.mean()))
        self._line = (reference, offset, slope)
