"""The row-major passes of stripe extraction over a frame: where its time goes.

``scanner_core.stripe.extractor.extract`` reads a frame once, row after row, keeping per column the
running maximum, its row and the largest value far from it (``column_max``); the columns that
need more (a second peak's row, a search inside the geometric window) are read again over as
few rows as possible. A robust estimate of the frame's background and noise reads a sparse
subsample (``noise_estimate``).

Memory order decides the speed. A frame (1920 x 1200 uint8, 2.3 MB) is read from memory, not
from the cache, and the hardware prefetchers follow a sequential stream: reading a 1152-column
strip of every 1920-byte row leaves a gap in the stream at every row, and measured here
(2 cores, AMD EPYC) ran at 7.1 GB/s against 29.7 GB/s for whole rows: the strip took 0.195 ms,
the whole frame 0.078 ms (a copy of the frame: 0.08 ms). So :func:`read_span` widens a strip of
at least half the frame to whole rows, and :func:`window_band` limits the rows to those the
geometric window reaches (a contiguous block of whole rows: a sequential stream again).

Conventions: ``img`` is ``(H, W)`` uint8, C-contiguous; per-column arrays are indexed from the
first column read; rows are uint16, and bytes within the row-major loops (the narrow index
type is what lets LLVM vectorise them; :func:`column_max`).
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["NOISE_ROW_STEP", "NOISE_RUN_PX", "HALF_IQR_PER_SIGMA", "MIN_NOISE_DN", "MAX_SEP",
           "noise_estimate", "quantile_from_hist", "read_span", "window_band", "column_max",
           "column_max2", "column_max_window"]

# Subsample of the noise estimate: a run of NOISE_RUN_PX contiguous pixels in every
# NOISE_ROW_STEP-th row (75 x 64 = 4800 pixels of a 1920 x 1200 frame, ~5 us: the median to
# ~0.05 sigma, the noise to ~3 %); the stripe's ~0.6 % of the rows moves the quartiles by
# ~0.02 sigma.
NOISE_ROW_STEP = 16
NOISE_RUN_PX = 64
# Median minus lower quartile of a normal distribution in sigmas: Phi^-1(0.75).
HALF_IQR_PER_SIGMA = 0.6744897501960817
# The noise is read from the differences of pixels this many columns apart along a row: the
# stripe runs along the rows and barely changes between them, a printed texture or an ambient
# gradient changes only at its edges (a spread of the values themselves counts the texture as
# noise), and two columns apart the neighbours share less of a demosaicing's or a JPEG's
# smoothing than adjacent ones.
NOISE_LAG = 2
SQRT2 = 1.4142135623730951
# Smallest noise accepted (DN): below it the floors would sit within the 1 DN quantisation.
MIN_NOISE_DN = 1.0
#: A strip of columns at least this share of the frame's width is read as whole rows (see the
#: module docstring: the bytes read grow by at most 1 / READ_WHOLE_ROWS_SHARE, the stream
#: stays sequential).
READ_WHOLE_ROWS_SHARE = 0.5


@njit(nogil=True, cache=True)
def quantile_from_hist(hist, total, p):
    """Grouped-data quantile: bin k spans [k - 0.5, k + 0.5), linear inside it."""
    target = p * total
    cum = 0.0
    for k in range(hist.shape[0]):
        hk = float(hist[k])
        if hk > 0.0 and cum + hk >= target:
            return k - 0.5 + (target - cum) / hk
        cum += hk
    return hist.shape[0] - 0.5


@njit(nogil=True, cache=True)
def noise_estimate(img):
    """(median, noise sigma) of a sparse subsample, DN; see
    ``scanner_core.stripe.extractor.estimate_noise``."""
    h, w = img.shape
    hist = np.zeros(256, np.int64)
    diffs = np.zeros(256, np.int64)
    run = min(NOISE_RUN_PX, w)
    k = 0
    for r in range(NOISE_ROW_STEP // 2, h, NOISE_ROW_STEP):
        # one contiguous run per sampled row (two cache lines: scattered single pixels would
        # each cost a cache miss), its start stepping across the width by the golden ratio
        c_start = int(((k * 0.6180339887498949) % 1.0) * (w - run + 1))
        k += 1
        _sample_run(img, r, c_start, c_start + run, hist, diffs)
    total = float(hist.sum())
    if total == 0.0:  # frames smaller than one step: every pixel
        for r in range(h):
            _sample_run(img, r, 0, w, hist, diffs)
        total = float(hist.sum())
    med = quantile_from_hist(hist, total, 0.5)
    n_diffs = float(diffs.sum())
    if n_diffs == 0.0:
        # too narrow for a difference: the lower half of the values (every stripe or marker
        # pixel is bright, so the lower quartile moves far less than the upper one)
        low = med - quantile_from_hist(hist, total, 0.25)
        return med, max(low / HALF_IQR_PER_SIGMA, MIN_NOISE_DN)
    # |v(c + NOISE_LAG) - v(c)| of two pixels with independent noise sigma is half-normal of
    # scale sigma * sqrt(2): its median is 0.6745 sigma sqrt(2). The first bin holds [0, 0.5)
    # only (the differences are >= 0).
    target = 0.5 * n_diffs
    cum = float(diffs[0])
    if cum >= target:
        m = 0.5 * target / cum
    else:
        m = diffs.shape[0] - 0.5
        for j in range(1, diffs.shape[0]):
            hk = float(diffs[j])
            if hk > 0.0 and cum + hk >= target:
                m = j - 0.5 + (target - cum) / hk
                break
            cum += hk
    return med, max(m / (HALF_IQR_PER_SIGMA * SQRT2), MIN_NOISE_DN)


@njit(nogil=True, cache=True)
def _sample_run(img, r, c0, c1, hist, diffs):
    """Row ``r``'s pixels ``c0 <= c < c1`` into ``hist``, and the differences ``NOISE_LAG``
    columns apart of every other one into ``diffs`` (half the run's differences hold the noise
    to a few per cent, and the histogram's increments are what the estimate costs)."""
    for c in range(c0, c1):
        hist[img[r, c]] += 1
    for c in range(c0, c1 - NOISE_LAG, 2):
        d = np.int32(img[r, c + NOISE_LAG]) - np.int32(img[r, c])
        diffs[abs(d)] += 1


@njit(nogil=True, cache=True)
def read_span(c0, c1, w):
    """The columns to read for the strip ``c0 <= c < c1`` of a frame ``w`` wide: whole rows
    when the strip covers at least ``READ_WHOLE_ROWS_SHARE`` of them."""
    if (c1 - c0) >= READ_WHOLE_ROWS_SHARE * w:
        return 0, w
    return c0, c1


@njit(nogil=True, cache=True)
def window_band(rmin, rmax, c0, c1, h):
    """The rows ``r0 <= r < r1`` that the window ``rmin[c] <= r <= rmax[c]`` of some column
    ``c0 <= c < c1`` reaches (``r0 == r1``: none)."""
    lo = h
    hi = -1
    for c in range(c0, c1):
        if rmin[c] <= rmax[c]:
            lo = min(lo, int(rmin[c]))
            hi = max(hi, int(rmax[c]))
    if hi < lo:
        return 0, 0
    return lo, min(hi, h - 1) + 1


@njit(nogil=True, cache=True, inline="always")
def _max_step(v, m, a, s, q, lim):
    """One row of :func:`column_max` for one column: the new maximum, its row and the far
    second maximum after value ``v`` at row ``q`` (rows and ``lim`` coded as in
    :func:`column_max`)."""
    far = a < lim
    lo = min(m, v)
    s = max(s, lo) if far else s
    a = q if v > m else a
    m = max(m, v)
    return m, a, s


#: Largest ``sep`` :func:`column_max` takes: a block of rows needs ``sep + 1`` rows before it
#: and at least one of its own within a uint8's 256 codes.
MAX_SEP = 254


@njit(nogil=True, cache=True)
def column_max(img, r0, r1, c0, c1, sep, mx, am, sec):
    """Rows ``r0 <= r < r1``, columns ``c0 <= c < c1``: per column the maximum (uint8), its
    row (uint16) and the far second maximum (uint8).

    ``sec`` holds the largest value seen more than ``sep`` rows from the running argmax at the
    time it was seen (the old maximum is demoted into it when a new maximum appears far away).
    Rows ascend, so ``r - am >= 0``.  Branch-free so that the loop vectorises, and eight rows
    at a time: the per-column state stays in registers over them (loaded and stored once per
    row, it had cost as much as the frame's own reads); written out row by row, as a loop
    over the eight, LLVM does not vectorise it.  Every value is a byte, so that a vector holds
    32 columns (AVX2): the rows go in blocks of ``256 - (sep + 1)``, each row coded as its
    offset from ``sep + 1`` rows before its block, where a maximum carried from an older row
    is coded 0 (every row of the block is more than ``sep`` rows from it either way): an
    argmax held as uint16 would halve the columns per vector and widen every mask (timings
    in docs/stripe.md).  The row of the second
    maximum is not kept here: only frames with double peaks need it (:func:`column_max2`).
    ``sep`` at most ``MAX_SEP``.
    """
    n = c1 - c0
    keep = sep + 1
    code = np.empty(n, np.uint8)
    b0 = r0
    while b0 < r1:
        b1 = min(b0 + 256 - keep, r1)
        base = max(b0 - keep, 0)
        for j in range(n):
            code[j] = np.uint8(am[j] - base) if am[j] >= base else np.uint8(0)
        r = b0
        while r + 8 <= b1:
            row0 = img[r, c0:c1]
            row1 = img[r + 1, c0:c1]
            row2 = img[r + 2, c0:c1]
            row3 = img[r + 3, c0:c1]
            row4 = img[r + 4, c0:c1]
            row5 = img[r + 5, c0:c1]
            row6 = img[r + 6, c0:c1]
            row7 = img[r + 7, c0:c1]
            q0, q1 = np.uint8(r - base), np.uint8(r + 1 - base)
            q2, q3 = np.uint8(r + 2 - base), np.uint8(r + 3 - base)
            q4, q5 = np.uint8(r + 4 - base), np.uint8(r + 5 - base)
            q6, q7 = np.uint8(r + 6 - base), np.uint8(r + 7 - base)
            # r - a > sep  <=>  a < r - sep, in the block's codes
            l0 = np.uint8(max(r - sep, base) - base)
            l1 = np.uint8(max(r + 1 - sep, base) - base)
            l2 = np.uint8(max(r + 2 - sep, base) - base)
            l3 = np.uint8(max(r + 3 - sep, base) - base)
            l4 = np.uint8(max(r + 4 - sep, base) - base)
            l5 = np.uint8(max(r + 5 - sep, base) - base)
            l6 = np.uint8(max(r + 6 - sep, base) - base)
            l7 = np.uint8(max(r + 7 - sep, base) - base)
            for j in range(n):
                m, a, s = _max_step(row0[j], mx[j], code[j], sec[j], q0, l0)
                m, a, s = _max_step(row1[j], m, a, s, q1, l1)
                m, a, s = _max_step(row2[j], m, a, s, q2, l2)
                m, a, s = _max_step(row3[j], m, a, s, q3, l3)
                m, a, s = _max_step(row4[j], m, a, s, q4, l4)
                m, a, s = _max_step(row5[j], m, a, s, q5, l5)
                m, a, s = _max_step(row6[j], m, a, s, q6, l6)
                m, a, s = _max_step(row7[j], m, a, s, q7, l7)
                mx[j] = m
                code[j] = a
                sec[j] = s
            r += 8
        while r < b1:
            row = img[r, c0:c1]
            q = np.uint8(r - base)
            lim = np.uint8(max(r - sep, base) - base)
            for j in range(n):
                m, a, s = _max_step(row[j], mx[j], code[j], sec[j], q, lim)
                mx[j] = m
                code[j] = a
                sec[j] = s
            r += 1
        for j in range(n):
            if code[j] != 0:  # 0: the maximum carried into the block is still the maximum
                am[j] = np.uint16(base + code[j])
        b0 = b1


@njit(nogil=True, cache=True)
def column_max2(img, r0, r1, c0, c1, sep, mx, am, sec, a2):
    """As :func:`column_max`, and the far second maximum's row ``a2`` (uint16).

    The old maximum is demoted into ``sec``, with its row, when a new maximum appears far
    away.  Branch-free so that the loop vectorises.
    """
    n = c1 - c0
    for r in range(r0, r1):
        r16 = np.uint16(r)
        lim16 = np.uint16(max(r - sep, 0))
        row = img[r, c0:c1]
        for j in range(n):
            v = row[j]
            m = mx[j]
            a = am[j]
            s = sec[j]
            new = v > m
            lo = min(m, v)  # the demoted maximum, or the new far value
            # >= : on a tie the demoted maximum takes the row (else a flank equal to it would)
            up = (a < lim16) & (lo >= s)
            sec[j] = lo if up else s
            a2[j] = (a if new else r16) if up else a2[j]
            am[j] = r16 if new else a
            mx[j] = max(m, v)


@njit(nogil=True, cache=True)
def column_max_window(img, r0, r1, c0, c1, sep, rmin, rmax, mx, am, sec, a2, out):
    """:func:`column_max2` over the rows ``rmin[c] <= r <= rmax[c]`` of each column only
    (``rmin``, ``rmax`` indexed by the frame's column), within ``r0 <= r < r1``; ``out`` keeps
    the maximum outside the column's window (to tell "no peak" from "a peak outside the
    window")."""
    n = c1 - c0
    if n == 0:
        return
    zero = np.uint8(0)
    lo_b = rmin[c0:c1]
    hi_b = rmax[c0:c1]
    for r in range(r0, r1):
        row = img[r, c0:c1]
        r16 = np.uint16(r)
        lim16 = np.uint16(max(r - sep, 0))
        for j in range(n):
            v0 = row[j]
            inside = (r16 >= lo_b[j]) & (r16 <= hi_b[j])
            v = v0 if inside else zero
            out[j] = max(out[j], zero if inside else v0)
            m = mx[j]
            a = am[j]
            s = sec[j]
            new = v > m
            lo = min(m, v)
            up = (a < lim16) & (lo >= s)
            sec[j] = lo if up else s
            a2[j] = (a if new else r16) if up else a2[j]
            am[j] = r16 if new else a
            mx[j] = max(m, v)
