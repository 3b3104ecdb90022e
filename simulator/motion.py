"""The robot's pass through the sheet: an accelerating, slightly curved path.

Never constant speed, never a straight line: the scanner must not depend on either
(paper section II). Time is the simulated clock in seconds from the start of the pass.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from simulator.cell import PassProfile


@dataclass(frozen=True)
class PassMotion:
    """TCP position along the pass as a function of time.

    The speed ramps linearly from ``v (1 - a)`` to ``v (1 + a)`` over the pass ("ramp"), or
    to ``v (1 + a)`` at its middle and back ("peak"), so the mean speed is ``v`` and the
    duration ``L / v``; the path bows sideways (x) by a half sine and rises (z) quadratically
    with the distance travelled. With "peak" the speed is symmetric about the pass's middle:
    a clock that drifts linearly along the pass then moves the marker in a way neither a
    constant clock offset nor an offset of the LED does (``benchmarks.led_clock``).
    """

    profile: PassProfile

    @property
    def length_mm(self) -> float:
        return self.profile.end_y_mm - self.profile.start_y_mm

    @property
    def duration_s(self) -> float:
        return self.length_mm / self.profile.speed_mm_s

    def distance(self, t) -> np.ndarray:
        """Distance travelled along y since the start of the pass at time ``t`` (s), mm.

        Before the pass the robot arrives at its initial speed and after it leaves at its
        final speed: the marker enters and leaves the view while moving, as in a real cell.
        """
        p = self.profile
        t = np.asarray(t, dtype=np.float64)
        v, a, dur = p.speed_mm_s, p.accel_fraction, self.duration_s
        tau = np.clip(t, 0.0, dur)
        before = v * (1.0 - a) * np.minimum(t, 0.0)
        if p.speed_shape == "peak":
            half = 0.5 * dur
            up = np.minimum(tau, half)
            down = np.maximum(tau - half, 0.0)
            # up at 2 a v / dur to v (1 + a) at the middle, then down as fast
            inside = (v * ((1.0 - a) * up + a * up**2 / half)
                      + v * ((1.0 + a) * down - a * down**2 / half))
            return inside + before + v * (1.0 - a) * np.maximum(t - dur, 0.0)
        inside = v * ((1.0 - a) * tau + a * tau**2 / dur)
        after = v * (1.0 + a) * np.maximum(t - dur, 0.0)
        return inside + before + after

    def speed(self, t) -> np.ndarray:
        """Speed along y, mm/s."""
        p = self.profile
        tau = np.clip(np.asarray(t, dtype=np.float64), 0.0, self.duration_s)
        if p.speed_shape == "peak":
            rise = 1.0 - np.abs(2.0 * tau / self.duration_s - 1.0)  # 0 at the ends, 1 between
            return p.speed_mm_s * (1.0 - p.accel_fraction + 2.0 * p.accel_fraction * rise)
        return p.speed_mm_s * (1.0 - p.accel_fraction + 2.0 * p.accel_fraction * tau / self.duration_s)

    def tcp_position(self, t) -> np.ndarray:
        """TCP position in {B} at time(s) ``t``: (..., 3) mm."""
        p = self.profile
        if isinstance(t, float):
            return self._tcp_position_at(t)
        s = self.distance(t)
        frac = np.clip(s / self.length_mm, 0.0, 1.0)  # the bow and rise belong to the pass
        return np.stack([p.bow_mm * np.sin(np.pi * frac),
                         p.start_y_mm + s,
                         p.height_mm + p.rise_mm * frac**2], axis=-1)

    def _tcp_position_at(self, t: float) -> np.ndarray:
        """:meth:`tcp_position` at one time, in scalar arithmetic: the simulated robot answers
        every frame's pose lookup with it, and a dozen numpy calls on scalars cost about
        20 us a lookup, which the per-frame benchmark would charge to the scanner."""
        p = self.profile
        if p.speed_shape != "ramp":
            return self.tcp_position(np.asarray(t, dtype=np.float64))
        v, a, dur = p.speed_mm_s, p.accel_fraction, self.duration_s
        tau = min(max(t, 0.0), dur)
        s = (v * ((1.0 - a) * tau + a * tau * tau / dur) + v * (1.0 - a) * min(t, 0.0)
             + v * (1.0 + a) * max(t - dur, 0.0))
        frac = min(max(s / self.length_mm, 0.0), 1.0)
        return np.array([p.bow_mm * math.sin(math.pi * frac), p.start_y_mm + s,
                         p.height_mm + p.rise_mm * frac * frac])
