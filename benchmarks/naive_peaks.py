"""The naive peak finder flyscan's stripe is compared with on photographs: per column the
argmax and a 3-point parabola through it, on the laser's channel or its colour excess as the
photograph's pixels give it (``flyscan bench real``, ``benchmarks.synthesised_photos``)."""
from __future__ import annotations

import numpy as np

from scanner_core.stripe.extractor import EXCESS_OFFSET_DN

__all__ = ["BASELINE_DN", "baseline_rows", "naive_signal"]

#: The naive peak finder keeps a column whose argmax reaches this (DN of the signal).
BASELINE_DN = 20.0


def baseline_rows(signal: np.ndarray, min_dn: float = BASELINE_DN):
    """The naive peak finder: per column the argmax and a 3-point parabola through it.

    Returns ``rows`` (W,) float64 (NaN where the argmax is under ``min_dn`` or on the frame's
    edge) for ``signal`` (H, W) uint8."""
    img = signal.astype(np.float64)
    h, w = img.shape
    cols = np.arange(w)
    a = np.argmax(img, axis=0)
    peak = img[a, cols]
    inner = (a > 0) & (a < h - 1) & (peak >= min_dn)
    a1 = np.clip(a, 1, h - 2)
    y0, y1, y2 = img[a1 - 1, cols], img[a1, cols], img[a1 + 1, cols]
    den = y0 - 2.0 * y1 + y2
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(den < 0, 0.5 * (y0 - y2) / den, 0.0)
    return np.where(inner, a1 + off, np.nan)


def naive_signal(rgb: np.ndarray, ps_signal: str) -> np.ndarray:
    """The signal the naive baseline reads: ``ps_signal``'s channel, or its colour excess
    ``v_k - (v_i + v_j) / 2`` rounded half up, ``EXCESS_OFFSET_DN`` above zero, clipped to
    [0, 255] and nothing more (flyscan's ``stripe_signal`` carries the excess on over a clipped
    channel; the baseline takes the photograph's pixels as they are).

    ``rgb`` (H, W, 3) uint8 -> (H, W) uint8."""
    channel = {"red": 0, "green": 1, "blue": 2}[ps_signal.split("_")[0]]
    if not ps_signal.endswith("_excess"):
        return np.ascontiguousarray(rgb[:, :, channel])
    v = rgb.astype(np.int32)
    e2 = 2 * v[:, :, channel] - v[:, :, (channel + 1) % 3] - v[:, :, (channel + 2) % 3]
    return np.clip(((e2 + 1) >> 1) + EXCESS_OFFSET_DN, 0, 255).astype(np.uint8)
