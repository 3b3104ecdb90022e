"""The per-frame kernel of stripe extraction: candidates, the choice between them, the width
gates and the sub-pixel refinement (``scanner_core.stripe.extractor.extract`` documents the behaviour;
this module holds its constants and its numba code).

Per frame: the row-major passes (``scanner_core.stripe.passes``) give, per column, the maximum,
its row and a far second maximum; here each column gets its candidates (the maximum, and the
second one if it is strong, a local maximum and apart from the first), their widths, the
frame's typical width, the choice between two candidates (a policy), the gates (too narrow,
too wide, linked to the neighbouring columns) and the refinement of the chosen peak
(``scanner_core.stripe.estimators``). Reason codes are ``scanner_core.stripe.extractor.Reason``'s.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from scanner_core.stripe import estimators as est
from scanner_core.stripe import passes as passes
from scanner_core.stripe.estimators import FWHM_PER_SIGMA, SATURATION_DN

__all__ = ["extract_kernel", "window_bounds"]

# A second peak must lie farther than this many of the main peak's sigmas from it (and than
# 2 * window rows): at 2 sigma a Gaussian stripe's own flank is down to 13.5 % of its peak, and
# lifting it to ``DOUBLE_PEAK_RATIO`` (0.3) takes a noise excursion of a sixth of the peak (11
# sigmas at 200 DN over 3 DN); on a wide stripe, sigma 6 px, the flank 2 * window = 8 rows out
# is still at 41 % of the peak and its noise bumps are local maxima.
SEPARATE_SIGMAS = 2.0

# --- width gates (``max_width="auto"``)
# Narrow peaks: a peak narrower than MIN_WIDTH_PX (sigma-like), or with fewer than
# MIN_PIXELS_ABOVE pixels above the threshold within +-window, looks like a lone noise pixel
# (width ~0.42 px, 1 pixel above) - and so does a stripe of sigma 0.5 px (0.44-0.6 px, 1 to 3
# pixels above). A stripe goes on into the next column, a noise or hot pixel does not: a narrow
# peak is kept when a neighbouring column holds a peak within LINK_ROWS_PX (+ the widths) of
# its row, and its own peak reaches NARROW_MIN_SIGMAS noise sigmas above the background (the
# largest of 1e6 normal noise samples is ~4.9 sigma: two such neighbours by chance, never).
MIN_WIDTH_PX = 0.5
MIN_PIXELS_ABOVE = 3
NARROW_MIN_SIGMAS = 8.0
# Wide peaks: the widest stripe of a frame depends on the optics and the surface (sigma 0.7 to
# 4.7 px along one line on a photograph of a laser line crossing a printed checkerboard; 1.5 px
# in the reference cell), so the gate follows the frame: its typical width is the median of its
# unclipped candidate peaks' widths (at least WIDTH_MIN_SAMPLES of them, else ``max_width``
# alone), and a peak up to CORE_WIDTH_FACTOR times it (never under ``max_width``) is a stripe.
# A peak up to LINKED_WIDTH_FACTOR times that is one too when it continues, column by column
# (rows within LINK_ROWS_PX + the widths), a stripe that passed: a stripe widening along its
# length (defocus, a surface turning) stays whole, while a broad blob apart from the stripe
# (ambient light, a diffuse reflection) is rejected as before. Beyond WIDTH_CAP_PX nothing is
# measured (the width walk stops there).
CORE_WIDTH_FACTOR = 2.0
LINKED_WIDTH_FACTOR = 2.0
WIDTH_MIN_SAMPLES = 16
WIDTH_CAP_PX = 16.0
LINK_ROWS_PX = 2.0
# Histogram of the widths for the median: bins of WIDTH_BIN_PX up to WIDTH_CAP_PX.
WIDTH_BIN_PX = 0.05
_WIDTH_BINS = int(WIDTH_CAP_PX / WIDTH_BIN_PX) + 1
# Column classes in the gate pass.
_CORE, _NARROW, _WIDE, _REJECTED = 0, 1, 2, 3

# --- noise-derived floors (threshold="auto"): the noise estimate is
# ``scanner_core.stripe.passes.noise_estimate``.
# The saturated-peak fit uses the unclipped samples above background + this many noise sigmas:
# low samples weigh little ((v - b)^2 weights) but keep the fit determined when the flanks are
# steep (at 10x full scale only one sample per flank clears a 20 DN threshold).
SAT_FIT_MIN_SIGMAS = 2.0
# threshold = background + AUTO_THRESHOLD_SIGMAS * noise: 3.33 reproduces the fixed 20 DN on the
# reference model (background 10, noise 3), where it measured best for ``cog``.
AUTO_THRESHOLD_SIGMAS = 10.0 / 3.0
# A candidate peak must reach background + AUTO_MIN_PEAK_SIGMAS * noise in "auto" mode: the
# largest of 1200 normal noise samples is ~3.2 sigma, so 5 sigma leaves ~3e-7 false peaks per
# pixel, which the MIN_PIXELS_ABOVE and width tests then reject.
AUTO_MIN_PEAK_SIGMAS = 5.0

# ``cog`` weighs ``v - t`` above a level ``t`` of its own per column, whatever the threshold:
# background + max(COG_SIGMAS * noise, COG_PEAK_FRACTION * (peak - background)).
# On bright stripes the second term rules (10 DN on a 200 DN stripe: the 20 DN that measured best
# on the reference model); on dim ones the first (measured on 30 DN over 3 DN, RMS: 0.1495 px
# at 20 DN, 0.1468 at 18.5, 0.1472 at 17, against a Cramer-Rao bound of 0.130).
COG_SIGMAS = 2.8
COG_PEAK_FRACTION = 0.05

# A peak's background is read beside it (``local_background``), first BACKGROUND_NEAR_WINDOWS
# and BACKGROUND_FAR_WINDOWS windows out; where the peak turns out wider, BACKGROUND_CLEAR_SIGMAS
# of its sigma-like width and BACKGROUND_FAR_RATIO times that out (a Gaussian is down to 4 %
# and 0.04 % of its peak there), at most BACKGROUND_ROUNDS times: a blob of sigma 10 px reads
# its own flank first, and its background by the third round. Read nearer (1.5 and 2.5
# windows), a speckled stripe's flank passed for its background and raised the centroid's
# level: 0.19 against 0.15 sigma RMS on a speckled line of sigma 0.5-6 px.
BACKGROUND_NEAR_WINDOWS = 3
BACKGROUND_FAR_WINDOWS = 5
BACKGROUND_CLEAR_SIGMAS = 2.5
BACKGROUND_FAR_RATIO = 1.6
BACKGROUND_ROUNDS = 4

# With ``shoulders``: ``cog`` weighs the stripe's top only, above SHOULDER_FRACTION of its
# height over its own background (the half maximum).  A colour excess has shoulders a mono
# camera's line has not: JPEG's 4:2:0 chroma and demosaicing spread it to one side, and a
# printed texture's edge under the line (its reflectance, its chroma) weighs one flank more
# than the other; the top sits where the light is.  Off for mono frames: a speckled line's
# flanks average its speckle out (0.15 -> 0.19 sigma RMS on a speckled line of sigma 0.5-6 px
# with only its top weighed).  A clipped colour peak whose flank fit fails (the flanks of an
# overexposed line's excess are no Gaussian's) takes the centre of its part above that level,
# the profile linear between the pixels (``top_centroid``: a flat top's pixel sum would sit on
# whole and half pixels).
SHOULDER_FRACTION = 0.5

# Without ``shoulders``: a centroid's run past the window that ends at a cliff, its last pixel
# over the peak's background by more than CLIFF_FRACTION of the peak's height, ended on a
# texture's edge (a lit square under the line, its plateau followed to the square's edge),
# not down the stripe's flank (which ends at the level, within a pixel's step of it); the
# stripe is then weighed above that plateau (the cliff's top plus COG_SIGMAS of noise)
# (docs/stripe.md, a line across printed squares).  So is a run that goes on past the window
# by more than CLIFF_RUN_WIDTHS of the stripe's width and ends by a fall of more than
# CLIFF_NOISE_SIGMAS of two pixels' noise: a Gaussian falls under a level a few noise sigmas
# over its background within about three sigmas of its centre, and down its flank there by
# less than the noise; a lit square's plateau, its background probes on the dark squares past
# it, runs on to the square's edge and drops there.  Or that run, as long, stays flat: it falls
# from the window's edge to its end by no more than CLIFF_NOISE_SIGMAS of two pixels' noise (a
# lit square just over the level, its run broken by the noise, not by its edge), where a
# flank falls all along it.
CLIFF_FRACTION = 0.25
CLIFF_RUN_WIDTHS = 3.0
CLIFF_NOISE_SIGMAS = 3.0 * math.sqrt(2.0)
# A narrow stripe's centroid stands on the surface just past its window where that reads
# more than SURFACE_SIGMAS noise sigmas over the peak's background (``_surface_centroid``): a
# lit square about the stripe.  Each side's surface is the mean of the two pixels past the
# window, the higher side's taken, so noise alone passes it in about one column of two
# hundred (the higher level costs a dim stripe its flanks); and only where the two pixels
# differ by no more than SURFACE_FLAT_SIGMAS: a flat surface, where a wide stripe whose
# measured width a fine print cut short still falls.
SURFACE_SIGMAS = 2.0
SURFACE_FLAT_SIGMAS = 2.0
# A centroid whose stripe a texture's edge cuts (``est.cut_flank``) is replaced by the fit of
# its whole flank (``est.uncut_centre``); tested only where the window's walk saw a one-pixel
# fall of more than ``est.CUT_MIN_FALL`` of the height (on a clean frame, testing every
# column showed in the frame's time; docs/stripe.md).  With ``shoulders`` (a colour excess)
# only where the two flanks' feet agree: on real photographs an overexposed core through JPEG
# (a flat top between cliffs, a halo beside) passed for a cut stripe, and the fit of its halo
# read worse than the top's centroid.

# A narrow stripe cut next to its argmax (``est.narrow_cut``) keeps two whole pixels: its
# centre is the Gaussian's through them with the width of the uncut stripes about it
# (``_narrow_cuts``), those within NARROW_CUT_SPAN columns that stand at least
# NARROW_CUT_PEAK_RATIO as high over the noise (on the same lit surface, not on a dark square,
# whose stripe reads narrower), where NARROW_CUT_MIN_COLUMNS are.  CUT_FIT marks a centre
# taken from a cut stripe's whole flank (``est.uncut_centre``).
NARROW_CUT_SPAN = 30
NARROW_CUT_PEAK_RATIO = 0.7
NARROW_CUT_MIN_COLUMNS = 5
CUT_FIT = 2

# A peak at least FLAT_MIN_WIDTH_PX wide whose top (within FLAT_LEVEL of its height) runs
# longer than FLAT_TOP_WIDTHS of its width plus FLAT_TOP_SLACK_ROWS is a plateau (``_flat_top``).
FLAT_MIN_WIDTH_PX = 2.0
FLAT_LEVEL = 0.8
FLAT_TOP_SLACK_ROWS = 1.5
FLAT_TOP_WIDTHS = 1.8

# A column whose brightest pixel is no stripe (no peak over its own background, a plateau, a
# lone pixel) may hold one dimmer than that, where the stripe of the column beside it goes on:
# on a dark square of a texture lit brighter elsewhere, on a dark part beside a bright one.
# Beside a column that passed, the rows its peak links to (``_linked``) are searched for the
# one that stands highest over the lower of the pixels within PROMINENCE_REACH_WIDTHS of the
# frame's width gate (``core``) on each side (``prominent_peak``: a texture's step stands over
# neither side's lowest, a bump over both; a stripe is down to 4 % of its height 2.5 of its
# widths out); it is the stripe if it stands PROMINENCE_MIN_SIGMAS of noise over the higher of
# the two and is as wide as the frame's stripes are (with ``threshold="auto"`` only).  In a
# column of noise alone the largest of a link's dozen pixels is about 2 sigmas up and the
# lowest of ten about 1.5 down: noise stands about 4 sigmas "over" its surround, and rarely 8.
PROMINENCE_REACH_WIDTHS = 2.5
PROMINENCE_MIN_SIGMAS = 8.0

# A stripe whose centre lies on a dark surface past a lit one's edge (a line dimmer than the
# lit squares of a texture, crossing a dark one): the lit surface's last rows hold the
# stripe's flank, brighter than its centre, and are the column's brightest pixels, a peak a
# fraction of a pixel wide (under PAST_EDGE_WIDTH_RATIO of the frame's typical width) that
# falls into the dark over the edge's two rows (its own lit in part), by half its height and
# by PAST_EDGE_ASYMMETRY times its fall on the other side (a narrow stripe falls alike on
# both).  Past that fall, within PAST_EDGE_REACH_WIDTHS of the frame's width gate, the
# brightest row on the dark surface is the stripe where it stands PROMINENCE_MIN_SIGMAS of
# noise over the lowest beyond it, over the lowest between it and the edge by
# PAST_EDGE_DIP_SIGMAS and PAST_EDGE_DIP_FRACTION of its height (a peak, not the dark
# surface's own share of a stripe centred on the lit side, falling from the edge) or, too near
# the edge to dip, with its centre PAST_EDGE_DEPTH_PX past the dark's first row, is at least
# twice as wide as the peak it replaces, is not flat on top, and where the surface beyond it
# (the median of PAST_EDGE_SURFACE_ROWS pixels past its flank) lies no higher than that dip
# and a noise sigma (a lit surface past a dark line is no darker surface).  A lone pixel
# refused as too narrow, anywhere in its column, gets its stripe only where that continues a
# stripe within PAST_EDGE_GAP columns.  Mono frames only: on colour frames a speckled line's
# lobe past a dip passed for such an end (docs/stripe.md).  The search where a stripe goes on
# then continues those found, and they it, for PAST_EDGE_ROUNDS rounds at most.
PAST_EDGE_WIDTH_RATIO = 0.5
PAST_EDGE_REACH_WIDTHS = 3.0
PAST_EDGE_DIP_SIGMAS = 2.0
PAST_EDGE_DIP_FRACTION = 0.15
PAST_EDGE_DEPTH_PX = 1.0
PAST_EDGE_SURFACE_ROWS = 5
PAST_EDGE_GAP = 2
PAST_EDGE_ASYMMETRY = 1.5
PAST_EDGE_ROUNDS = 3

# The peak's width, count and centroid are read with the window a compile-time constant when
# ``window`` is this (the default): the loops over it unrolled, the candidates' pass took half
# the time.
UNROLLED_WINDOW = 4

# --- continuity policy (a Viterbi path over the columns, two states per column)
# Cost, in px of row jump, of choosing a candidate of zero brightness over the brightest one
# (linear in the brightness ratio).  40 px makes a candidate at half the brightness cost 20 px per
# column, more than the two capped links it could save: a reflection at <= half the stripe's
# brightness is never chosen over it however the rows jump (measured: 100 % of the columns on the
# stripe with smooth and with random per-column rows; 4 px kept glints over 10 columns but fell
# to 89 % on random rows), while a glint 1.5x the stripe over 1 (2) columns is still bridged in
# 100 % (95 %) of the columns.  Longer glints need ``expected_row`` (the previous profile).
CONTINUITY_BRIGHTNESS_PX = 40.0
# Row jumps between linked columns are charged up to this (px): a real step of the surface costs
# every path the same.
CONTINUITY_JUMP_CAP_PX = 10.0
# Columns farther apart than this (without a candidate between them) are not linked.
CONTINUITY_MAX_GAP = 8
# Weight (per px of distance, capped like the jumps) of the expected row when one is given.
EXPECTED_WEIGHT = 1.0



@njit(nogil=True, cache=True)
def _continuity(ncand, mx, am, sec, a2, expected, c0, choice):
    """Viterbi path over the columns (states: candidate 0 or 1), written into ``choice``.

    Cost of a path: per column ``CONTINUITY_BRIGHTNESS_PX * (1 - p_k / p_max)`` (+ the capped
    distance to the expected row, if any), per link ``min(|row jump|, CONTINUITY_JUMP_CAP_PX)``
    between columns at most ``CONTINUITY_MAX_GAP`` apart.  Unlinked stretches are separate paths.
    """
    n = ncand.shape[0]
    cost = np.zeros((n, 2))
    back = np.zeros((n, 2), np.int8)
    link = np.full(n, -1, np.int64)
    last = -1
    for j in range(n):
        kn = ncand[j]
        if kn == 0:
            continue
        linked = last >= 0 and j - last <= CONTINUITY_MAX_GAP
        e = expected[c0 + j]
        pm = float(mx[j])
        for k in range(kn):
            rk = float(am[j]) if k == 0 else float(a2[j])
            pk = float(mx[j]) if k == 0 else float(sec[j])
            u = CONTINUITY_BRIGHTNESS_PX * (1.0 - pk / pm)
            if math.isfinite(e):
                u += EXPECTED_WEIGHT * min(abs(rk - e), CONTINUITY_JUMP_CAP_PX)
            best = 0.0
            bk = 0
            if linked:
                best = math.inf
                for kp in range(ncand[last]):
                    rp = float(am[last]) if kp == 0 else float(a2[last])
                    t = cost[last, kp] + min(abs(rk - rp), CONTINUITY_JUMP_CAP_PX)
                    if t < best:
                        best = t
                        bk = kp
            cost[j, k] = u + best
            back[j, k] = bk
        if linked:
            link[j] = last
        last = j
    for j in range(n - 1, -1, -1):
        if ncand[j] == 0:
            continue
        if choice[j] < 0:  # end of a path: its cheaper state
            choice[j] = 1 if ncand[j] == 2 and cost[j, 1] < cost[j, 0] else 0
        if link[j] >= 0:
            choice[link[j]] = back[j, choice[j]]


@njit(nogil=True, cache=True, inline="always")
def local_background(img, c, a, h, near, far, frame_bg):
    """The background a peak at row ``a`` of column ``c`` stands on, DN.

    On each side the lower of the pixels ``near`` and ``far`` rows out, and the higher of the
    two sides: the stripe must stand clear of what lies on both sides of it (a JPEG's chroma
    spread about a coloured line, a bright surface beside it, a texture's edge), not only of
    the frame's typical level ``frame_bg``, which it never goes under: two pixels are a noisy
    estimate, and under the frame's level a column of noise alone would pass for a stripe now
    and then (a dark part in a bright frame still shows its stripe above the frame's level)."""
    left = right = -1.0
    if a - far >= 0:
        left = float(min(img[a - near, c], img[a - far, c]))
    if a + far <= h - 1:
        right = float(min(img[a + near, c], img[a + far, c]))
    return max(frame_bg, left, right)


@njit(nogil=True, cache=True)
def _window_min(pre, suf, s, e, reach):
    """The minimum of rows ``s .. e`` (``e - s < reach``) from the blocks' prefix and suffix
    minima: across two blocks the suffix of the first and the prefix of the second; within
    one, the window starts at its block's start or (cut at the band's end) ends at its end."""
    if s // reach != e // reach:
        return min(suf[s], pre[e])
    return pre[e] if s % reach == 0 else suf[s]


@njit(nogil=True, cache=True)
def prominent_peak(img, c, r0, r1, s0, s1, reach, out):
    """The row of column ``c`` within ``s0 <= r < s1`` that stands highest over its surround,

        P_r = v_r - max(min(v_{r-reach} .. v_{r-1}), min(v_{r+1} .. v_{r+reach})),

    the windows cut at the band ``r0 <= r < r1`` (a row with no pixel on one side within it
    is skipped).  A step (a texture's edge) stands over neither side's lowest pixel, a bump
    over both.  The minima are the running minima of van Herk and Gil-Werman (per block of
    ``reach`` rows, a prefix and a suffix minimum: three reads a row whatever ``reach``).

    ``out`` (2,) float64 receives the row and the background (the higher of the two minima);
    returns ``P`` (DN), -inf where no row qualifies."""
    lo = max(r0, s0 - reach)
    hi = min(r1, s1 + reach)
    n = hi - lo
    best = -math.inf
    if n < 3 or reach < 1:
        return best
    pre = np.empty(n, np.int32)  # minimum from its block's start to the row
    suf = np.empty(n, np.int32)  # minimum from the row to its block's end
    for i in range(n):
        v = np.int32(img[lo + i, c])
        pre[i] = v if i % reach == 0 else min(pre[i - 1], v)
    for i in range(n - 1, -1, -1):
        v = np.int32(img[lo + i, c])
        suf[i] = v if (i % reach == reach - 1 or i == n - 1) else min(suf[i + 1], v)
    for i in range(max(s0 - lo, 1), min(s1 - lo, n - 1)):
        # rows above i from max(i - reach, 0), below to min(i + reach, n - 1)
        b = max(_window_min(pre, suf, max(i - reach, 0), i - 1, reach),
                _window_min(pre, suf, i + 1, min(i + reach, n - 1), reach))
        prom = float(np.int32(img[lo + i, c]) - b)
        if prom > best:
            best = prom
            out[0] = lo + i
            out[1] = b
    return best


@njit(nogil=True, cache=True)
def _flat_top(img, c, a, h, b, p, width):
    """A plateau rather than a peak: the rows joined to ``a`` within ``FLAT_LEVEL`` of the
    height ``p`` over the background ``b`` run longer than ``FLAT_TOP_WIDTHS`` of the
    sigma-like ``width`` (a Gaussian's top above 80 % spans 1.34 of its sigma; a lit square of
    a printed texture or a bright surface is as wide on top as at half height). Peaks narrower
    than ``FLAT_MIN_WIDTH_PX`` are not judged (too few rows to tell)."""
    if not (math.isfinite(width) and width >= FLAT_MIN_WIDTH_PX):
        return False
    level = b + FLAT_LEVEL * (p - b)
    limit = int(math.ceil(FLAT_TOP_WIDTHS * width + FLAT_TOP_SLACK_ROWS))
    top = 1
    r = a - 1
    while r >= 0 and img[r, c] >= level and top <= limit:
        top += 1
        r -= 1
    r = a + 1
    while r < h and img[r, c] >= level and top <= limit:
        top += 1
        r += 1
    return top > limit


@njit(nogil=True, cache=True)
def _levels(auto, thr, b, sig):
    """A column's threshold and peak floor over its background ``b``: ``b + AUTO_*_SIGMAS *
    sig`` with ``auto``, else the fixed ``thr`` for both."""
    if auto:
        return b + AUTO_THRESHOLD_SIGMAS * sig, b + AUTO_MIN_PEAK_SIGMAS * sig
    return thr, thr


@njit(nogil=True, cache=True)
def _cog_level(med, sig, p):
    """The level ``cog`` weighs above for a peak ``p`` (DN) over a background ``med`` and a
    noise ``sig``: it follows the peak and the noise whatever the threshold, since a fixed
    threshold near a dim stripe's top leaves one or two pixels above it, and their centroid is
    the brightest pixel's row (pixel locking)."""
    return med + max(COG_SIGMAS * sig, COG_PEAK_FRACTION * (p - med))


@njit(nogil=True, cache=True)
def _whole_span(k0, k1, n):
    """Columns ``k0 <= j < k1`` of a read span ``n`` wide, widened to all of it when they
    cover half of it (a sequential stream: ``scanner_core.stripe.passes``)."""
    if k1 - k0 >= passes.READ_WHOLE_ROWS_SHARE * n:
        return 0, n
    return k0, k1


@njit(nogil=True, cache=True)
def _linked(a0, w0, a1, w1):
    """Neighbouring columns' peaks continue one another: rows within LINK_ROWS_PX plus the
    wider one's sigma-like width."""
    return abs(a0 - a1) <= LINK_ROWS_PX + max(w0, w1)


@njit(nogil=True, cache=True)
def window_bounds(row_min, row_max, h):
    """The geometric window's rows as uint16 per column: ``ceil(row_min)`` and
    ``floor(row_max)`` clipped to ``[0, 65535]``, and False if any is NaN."""
    n = row_min.shape[0]
    lo = np.empty(n, np.uint16)
    hi = np.empty(n, np.uint16)
    for c in range(n):
        a, b = row_min[c], row_max[c]
        if math.isnan(a) or math.isnan(b):
            return lo, hi, False
        lo[c] = np.uint16(min(max(math.ceil(a), 0.0), 65535.0))
        hi[c] = np.uint16(min(max(math.floor(b), 0.0), 65535.0))
    return lo, hi, True


@njit(nogil=True, cache=True)
def extract_kernel(img, c0, c1, method, auto, thr, window, max_width, auto_width, min_width,
                   double_ratio, bg, policy, expected, use_window, rmin, rmax, fit_saturated,
                   shoulders):
    """``scanner_core.stripe.extractor.extract``'s work on a checked frame.

    Returns the per-column arrays (W,) indexed by the frame's column, ``row, peak, width,
    reason, saturated, snr, n_peaks``, then the frame's background, noise and width gate."""
    h, w = img.shape
    row = np.full(w, np.nan, np.float32)
    peak = np.full(w, np.nan, np.float32)
    width = np.full(w, np.nan, np.float32)
    snr = np.full(w, np.nan, np.float32)
    reason = np.full(w, 7, np.uint8)  # NOT_PROCESSED
    saturated = np.zeros(w, np.bool_)
    n_peaks = np.zeros(w, np.uint8)
    med, sig = passes.noise_estimate(img)
    core = _columns(img, c0, c1, method, auto, thr, window, max_width, auto_width, min_width,
                    double_ratio, bg, policy, expected, use_window, rmin, rmax, fit_saturated,
                    shoulders, med, sig, row, peak, width, reason, saturated, snr, n_peaks)
    return row, peak, width, reason, saturated, snr, n_peaks, med, sig, core


@njit(nogil=True, cache=True)
def _ends_at_cliff(stats, b, p, sig):
    """The centroid's run past the window (``est.width_count_cog``'s ``stats``) of a peak ``p``
    over ``b`` ended at a cliff, or ran flat over a surface (``CLIFF_FRACTION``,
    ``CLIFF_RUN_WIDTHS``), not down a flank."""
    return (p < SATURATION_DN and stats[3] > 0
            and (stats[4] > b + CLIFF_FRACTION * (p - b)
                 or (stats[3] > CLIFF_RUN_WIDTHS * stats[0]
                     and (stats[5] > CLIFF_NOISE_SIGMAS * sig
                          or stats[7] <= CLIFF_NOISE_SIGMAS * sig))))


@njit(nogil=True, cache=True)
def _surface_centroid(img, c, a, h, p, b, sig, stats, window, max_walk, bg):
    """The centroid of the peak ``p`` at row ``a`` over ``b`` (``stats`` from
    ``est.width_count_cog`` or ``est.within_window``), weighed above the surface it stands on
    where that lies over ``b``: a lit square past the window's edge (``_ends_at_cliff``), or,
    for a stripe that has fallen within ``BACKGROUND_CLEAR_SIGMAS`` of its widths a row inside
    the window's edge, the higher of the two pixel pairs just past the window (each pair's
    mean, where its two pixels differ by no more than ``SURFACE_FLAT_SIGMAS`` noise sigmas:
    a surface, not the flank of a stripe whose width a texture cut short) by more than
    ``SURFACE_SIGMAS`` noise sigmas.  ``b``, read three and five windows out, can lie on
    the dark squares past a lit one the stripe crosses; a centroid over ``b`` then weighs the
    lit pixels beside the stripe, by ``v - level`` each, as far as the noise lifts each over
    the level, at random (docs/stripe.md)."""
    if not _ends_at_cliff(stats, b, p, sig):
        if (not math.isnan(bg) or p >= SATURATION_DN or a <= window + 1
                or a + window + 1 >= h - 1
                or not BACKGROUND_CLEAR_SIGMAS * stats[0] <= window - 1):
            return stats[2]
        s = -math.inf
        for step in (-1, 1):
            near = float(img[a + step * (window + 1), c])
            far = float(img[a + step * (window + 2), c])
            if abs(near - far) <= SURFACE_FLAT_SIGMAS * sig:  # a surface, not a flank
                s = max(s, 0.5 * (near + far))
        if not s > b + SURFACE_SIGMAS * sig:
            return stats[2]
        return est.cog(img, c, a, h, _cog_level(s, sig, p), window, math.nan, max_walk)
    return est.cog(img, c, a, h, stats[4] + COG_SIGMAS * sig, window, math.nan, max_walk)


@njit(nogil=True, cache=True)
def _candidates(img, ca, js, je, mx, am, sec, a2, auto, thr, threshold, floor, max_walk, window,
                shoulders, med, sig, bg, double_ratio, use_window, rmin, rmax, min_width, ncand,
                wmain, nmain, ymain, bloc, tloc, hist, steep):
    """Each column's local background (``bloc``) and threshold (``tloc``), its candidates
    (``ncand``), the main one's width, count above the threshold and centre of gravity, and the
    histogram of the widths; returns the widths counted.  A function of its own, calling the
    two walks itself (through a function holding both, or inside ``_columns``, the loop ran at
    half the speed or less)."""
    h = img.shape[0]
    stats = np.zeros(8)
    n_widths = 0
    for j in range(js, je):
        p = float(mx[j])
        c = ca + j
        a = int(am[j])
        # on the frame's background first: a peak that stands clear of it and ends within its
        # window (its half-height and its centroid's runs) stands on it, and costs no more
        # reads; another is read against its own (a bright surface beside it, a shoulder, a
        # wide or a clipped stripe)
        t_c, f_c = threshold, floor  # the frame's: _levels(auto, thr, med, sig)
        bloc[j] = med
        tloc[j] = t_c
        if not (p > t_c and p >= f_c):
            continue  # its own background lies no lower than the frame's
        t_cog = _cog_level(med, sig, p)
        if window == UNROLLED_WINDOW:  # a constant: LLVM unrolls the loops over the window
            fast = est.within_window(img, c, a, h, 0.5 * (p + t_c), max_walk, t_c,
                                     UNROLLED_WINDOW, t_cog, bg, stats)
        else:
            fast = est.within_window(img, c, a, h, 0.5 * (p + t_c), max_walk, t_c, window,
                                     t_cog, bg, stats)
        near, far = BACKGROUND_NEAR_WINDOWS * window, BACKGROUND_FAR_WINDOWS * window
        b = med if fast else local_background(img, c, a, h, near, far, med)
        for _ in range(BACKGROUND_ROUNDS if not fast else 0):
            t_c, f_c = _levels(auto, thr, b, sig)
            bloc[j] = b
            tloc[j] = t_c
            if not (p > t_c and p >= f_c):
                break
            level = 0.5 * (p + t_c)
            t_cog = _cog_level(b, sig, p)
            if window == UNROLLED_WINDOW:  # a constant: LLVM unrolls the loops over the window
                fast = est.within_window(img, c, a, h, level, max_walk, t_c, UNROLLED_WINDOW,
                                         t_cog, bg, stats)
            else:
                fast = est.within_window(img, c, a, h, level, max_walk, t_c, window, t_cog,
                                         bg, stats)
            if not fast:
                est.width_count_cog(img, c, a, h, level, max_walk, t_c, window, t_cog, bg,
                                    max_walk, stats)
            # a peak wider than the background's pixels are far: they lay on its flanks, read
            # the background past them
            reach = BACKGROUND_CLEAR_SIGMAS * stats[0]
            if not reach > near or not math.isfinite(reach):
                break
            near = int(math.ceil(reach))
            far = int(math.ceil(BACKGROUND_FAR_RATIO * reach))
            b_out = local_background(img, c, a, h, near, far, med)
            if b_out == b:
                break
            b = b_out
        if not (p > t_c and p >= f_c):
            continue
        ncand[j] = 1
        steep[j] = stats[6]
        if not fast and p < SATURATION_DN and _flat_top(img, c, a, h, b, p, stats[0]):
            stats[0] = math.inf  # a lit surface's plateau, not a peak: too wide
        wd = stats[0]
        wmain[j] = wd
        nmain[j] = stats[1]
        ymain[j] = stats[2]
        if not shoulders and (not fast or BACKGROUND_CLEAR_SIGMAS * stats[0] <= window - 1):
            # a lit surface under the line (a texture): the stripe is what stands over it (a
            # peak within its window has no run past it: only a narrow one's ends are read)
            ymain[j] = _surface_centroid(img, c, a, h, p, b, sig, stats, window, max_walk, bg)
        s = float(sec[j])
        if s > threshold and s >= floor and s >= double_ratio * p:
            r2 = int(a2[j])  # the second candidate's row
            inside = not use_window or (r2 >= rmin[c] and r2 <= rmax[c])
            apart = not math.isfinite(wd) or abs(r2 - a) > SEPARATE_SIGMAS * wd
            if (inside and apart and r2 > 0 and r2 < h - 1 and img[r2 - 1, c] <= img[r2, c]
                    and img[r2 + 1, c] <= img[r2, c]):
                ncand[j] = 2
        if p < SATURATION_DN and wd >= min_width and wd < WIDTH_CAP_PX:
            hist[int(wd / WIDTH_BIN_PX)] += 1
            n_widths += 1
    return n_widths


@njit(nogil=True, cache=True)
def _centre(img, c, a, h, p, b, sig, sat, bg_sat, method, shoulders, window, max_walk, y_cog,
            t_c, wd, bg, test_cut, min_width):
    """The centre row of the peak at row ``a`` of column ``c`` (``p`` DN over a background
    ``b``; ``y_cog`` its centroid, ``t_c`` its threshold, ``wd`` its width) by ``method``, a
    saturated one from its flanks; with ``test_cut`` (a fall within the window steep enough,
    or a reflection chosen) a centroid whose stripe a texture's edge cuts is replaced by its
    whole flank's fit (``est.cut_flank``, ``est.uncut_centre``).

    Returns the centre and how it was cut: ``CUT_FIT`` (replaced by the fit), -1 or +1 (a
    narrow stripe cut next to its argmax on that side, ``est.narrow_cut``: the centroid is
    left for ``_narrow_cuts``), 0 (not cut)."""
    y = math.nan
    kind = 0
    if sat:
        y = est.saturated_centre(img, c, a, h, bg_sat + SAT_FIT_MIN_SIGMAS * sig, window,
                                 bg_sat, max_walk)
        if not math.isfinite(y):  # too few samples for the fit: a narrow stripe?
            y = est.narrow_clip_centre(img, c, a, h, bg_sat + SAT_FIT_MIN_SIGMAS * sig, bg_sat)
        if not math.isfinite(y) and shoulders:
            y = est.top_centroid(img, c, a, h, b + SHOULDER_FRACTION * (p - b), max_walk)
    elif method == 0 and shoulders:
        y = est.cog(img, c, a, h, b + SHOULDER_FRACTION * (p - b), window, math.nan, max_walk)
    elif method == 0:
        y = y_cog
    elif method == 1:
        y = est.gaussian3(img, c, a, h, bg)
    elif method == 2:
        y = est.parabola(img, c, a, h)
    elif method == 3:
        y = est.blais_rioux(img, c, a, h)
    else:
        y0 = est.cog(img, c, a, h, t_c, window, math.nan, max_walk)
        y = est.lsq_gauss(img, c, a, h, t_c, window, y0, wd) if math.isfinite(y0) else y0
    if method == 0 and not sat and math.isfinite(y) and test_cut:
        # a texture's edge across the stripe: its centre from the flank the edge leaves
        step, r_cut = est.cut_flank(img, c, a, h, b, sig, max_walk)
        if step != 0:
            y_cut = est.uncut_centre(img, c, a, h, step, r_cut, sig, max_walk, wd, shoulders)
            if math.isfinite(y_cut):
                y = y_cut
                kind = CUT_FIT
        else:
            kind = est.narrow_cut(img, c, a, h, b, sig, max_walk, min_width)
    return y, kind


@njit(nogil=True, cache=True)
def _narrow_cuts(img, ca, js, je, ok, cut, arow, yrow, width, snr, sig, max_walk):
    """The columns whose narrow stripe a texture's edge cuts next to its argmax (``cut`` -1 or
    +1, ``est.narrow_cut``): the centre from their two whole pixels (``est.narrow_cut_centre``)
    with the median width of the uncut stripes within ``NARROW_CUT_SPAN`` columns that stand
    at least ``NARROW_CUT_PEAK_RATIO`` as high over the noise (the same surface's, lit); a
    column without ``NARROW_CUT_MIN_COLUMNS`` such keeps its centroid."""
    h = img.shape[0]
    widths = np.empty(2 * NARROW_CUT_SPAN)
    for j in range(js, je):
        if not (ok[j] and (cut[j] == -1 or cut[j] == 1)):
            continue
        c = ca + j
        n = 0
        for i in range(max(js, j - NARROW_CUT_SPAN), min(je, j + NARROW_CUT_SPAN + 1)):
            if (i != j and ok[i] and cut[i] == 0 and math.isfinite(width[ca + i])
                    and snr[ca + i] >= NARROW_CUT_PEAK_RATIO * snr[c]):
                widths[n] = width[ca + i]
                n += 1
        if n < NARROW_CUT_MIN_COLUMNS:
            continue
        y = est.narrow_cut_centre(img, c, int(arow[j]), h, int(cut[j]),
                                  np.median(widths[:n]), sig, max_walk)
        if math.isfinite(y):
            yrow[j] = y


@njit(nogil=True, cache=True)
def _continued_stripe(img, c, h, r0, r1, a_prev, w_prev, reach_rows, use_window, rmin, rmax,
                      reach, core, min_width, max_walk, window, shoulders, method, sig, bg,
                      spot, stats):
    """The centre of the stripe in column ``c`` where its neighbour's (at row ``a_prev``,
    width ``w_prev``) goes on, within ``reach_rows`` of it: the most prominent row there
    (``prominent_peak``; its row and background left in ``spot``, its walk in ``stats``) if
    it is a stripe as the frame's others are and linked to the neighbour's; NaN otherwise.
    With it, how it was cut (``_centre``)."""
    s0 = max(r0, int(math.ceil(a_prev - reach_rows)))
    s1 = min(r1, int(math.floor(a_prev + reach_rows)) + 1)
    if use_window:
        s0 = max(s0, int(rmin[c]))
        s1 = min(s1, int(rmax[c]) + 1)
    if not prominent_peak(img, c, r0, r1, s0, s1, reach, spot) >= PROMINENCE_MIN_SIGMAS * sig:
        return math.nan, 0
    a = int(spot[0])
    b = spot[1]
    p = float(img[a, c])
    if p >= SATURATION_DN:
        return math.nan, 0  # the column's brightest: refused as it was
    t_c = b + AUTO_THRESHOLD_SIGMAS * sig
    est.width_count_cog(img, c, a, h, 0.5 * (p + t_c), max_walk, t_c, window,
                        _cog_level(b, sig, p), bg, max_walk, stats)
    wd = stats[0]
    if not (min_width <= wd <= core and stats[1] >= MIN_PIXELS_ABOVE
            and _linked(a_prev, w_prev, a, wd)):
        return math.nan, 0  # a stripe as the frame's others are, where the neighbour's goes on
    if _flat_top(img, c, a, h, b, p, wd):
        return math.nan, 0
    y_cog = stats[2]
    if not shoulders:
        y_cog = _surface_centroid(img, c, a, h, p, b, sig, stats, window, max_walk, bg)
    return _centre(img, c, a, h, p, b, sig, False, b, method, shoulders, window, max_walk,
                   y_cog, t_c, wd, bg, stats[6] > est.CUT_MIN_FALL * (p - b),
                   min_width)


@njit(nogil=True, cache=True)
def _surface_level(img, c, r, step):
    """The median of ``PAST_EDGE_SURFACE_ROWS`` pixels of column ``c`` from row ``r`` on by
    ``step``, DN: a surface's level (a minimum would follow its noise down)."""
    v = np.empty(PAST_EDGE_SURFACE_ROWS)
    for k in range(PAST_EDGE_SURFACE_ROWS):
        v[k] = float(img[r + step * k, c])
    return np.median(v)


@njit(nogil=True, cache=True)
def _stripe_past_edge(img, c, h, r0, r1, a, step, rows, reach, min_width, max_width, max_walk,
                      sig, use_window, rmin, rmax):
    """The stripe in column ``c`` on the darker surface past the edge that ends a brighter
    one at row ``a`` (``step`` toward the darker; the row after ``a`` is the edge's own),
    within ``rows`` of ``a`` (``PAST_EDGE_*``): the brightest row there, ``f`` the lowest
    within ``reach`` rows beyond it, its width (px, sigma-like) from the half maximum over
    ``f`` of its flank away from the edge, ``min_width`` to ``max_width``; its centre from
    the darker surface's pixels over ``f``, the edge's side cut (``est.flank_vertex``).

    Returns the centre (NaN if none), the peak's row, ``f`` and the width."""
    none = (math.nan, -1, math.nan, math.nan)
    first = a + 2 * step  # the darker surface's first whole row
    lo, hi = (first, a + rows) if step > 0 else (a - rows, first)
    lo = max(lo, r0)
    hi = min(hi, r1 - 1)
    if use_window:
        lo = max(lo, int(rmin[c]))
        hi = min(hi, int(rmax[c]))
    if hi - lo < 2:
        return none
    m = lo
    for r in range(lo, hi + 1):
        if img[r, c] > img[m, c]:
            m = r
    near = math.inf  # the lowest between it and the edge (itself where it is the first row)
    for r in range(min(first, m - step), max(first, m - step) + 1):
        if r != first - step:
            near = min(near, float(img[r, c]))
    far = math.inf
    for k in range(1, reach + 1):
        r = m + step * k
        if r < r0 or r >= r1:
            break
        far = min(far, float(img[r, c]))
    p = float(img[m, c])
    if not (p - far >= PROMINENCE_MIN_SIGMAS * sig and p < SATURATION_DN):
        return none
    dips = p - near >= max(PAST_EDGE_DIP_SIGMAS * sig, PAST_EDGE_DIP_FRACTION * (p - far))
    half_width = est.flank_crossing(img, c, m, h, step, 0.5 * (p + far), max_walk)[2]
    wd = half_width / est.HWHM_PER_SIGMA
    if not min_width <= wd <= max_width or _flat_top(img, c, m, h, far, p, wd):
        return none
    k0 = int(math.ceil(BACKGROUND_CLEAR_SIGMAS * wd))
    if not (0 <= m + step * (k0 + PAST_EDGE_SURFACE_ROWS - 1) < h
            and _surface_level(img, c, m + step * k0, step) <= min(near, p) + sig):
        return none  # a brighter surface beyond it: the stripe's flank past a dark line
    y = est.flank_vertex(img, c, m, h, -step, first, far, max_walk)
    if not (dips or (y - first) * step >= PAST_EDGE_DEPTH_PX):
        return none  # the dark surface's share of a stripe on the bright one, falling
    return y, m, far, wd


@njit(nogil=True, cache=True)
def _past_edge_candidates(img, ca, js, je, r0, r1, klass, arow, wsel, typical, core, linked,
                          min_width, max_walk, sig, use_window, rmin, rmax, snr, reason, corner,
                          found):
    """Per column ``js <= j < je`` (index ``j - js``): ``corner``, the row of a peak that may
    be a brighter surface's end on the stripe's flank (-1 if none: no narrow peak, or no
    edge's fall beside it), and ``found``, the stripe on the darker surface past that edge
    (``_stripe_past_edge``: centre, row, background, width; NaN if none)."""
    h = img.shape[0]
    rows = int(math.ceil(PAST_EDGE_REACH_WIDTHS * core))
    reach = max(2, int(math.ceil(PROMINENCE_REACH_WIDTHS * core)))
    narrow = PAST_EDGE_WIDTH_RATIO * typical
    for k in range(je - js):
        j = js + k
        c = ca + j
        if not ((klass[j] != _REJECTED or reason[c] == 5) and wsel[j] < narrow):
            continue  # no narrow peak (TOO_NARROW: a lone pixel)
        a = int(arow[j])
        if a < 2 or a > h - 3:
            continue
        # the edge's fall, over two rows (the row the edge crosses is lit in part), steeper
        # than the brighter surface's flank rising to it (a narrow stripe falls alike)
        step = 1 if img[a + 2, c] < img[a - 2, c] else -1
        fall = float(img[a, c]) - float(img[a + 2 * step, c])
        other = float(img[a, c]) - float(img[a - 2 * step, c])
        if not (fall > est.CUT_MIN_FALL * snr[c] * sig and fall >= PAST_EDGE_ASYMMETRY * other):
            continue
        corner[k] = a
        y, m, b, wd = _stripe_past_edge(img, c, h, r0, r1, a, step, rows, reach,
                                        max(min_width, narrow), linked, max_walk, sig,
                                        use_window, rmin, rmax)
        if math.isfinite(y) and wsel[j] < PAST_EDGE_WIDTH_RATIO * wd:
            found[k, 0] = y
            found[k, 1] = m
            found[k, 2] = b
            found[k, 3] = wd


@njit(nogil=True, cache=True)
def _stripes_past_edges(img, ca, js, je, klass, ok, arow, wsel, yrow, cut, peak, width, snr,
                        saturated, sig, corner, found):
    """The stripes past the edges of ``_past_edge_candidates``, in place of the peaks before
    them; a lone pixel's (refused as too narrow: anywhere in its column) only where it
    continues a stripe within ``PAST_EDGE_GAP`` columns (``_linked``), swept both ways.  The
    gate arrays and outputs updated in place; returns how many were taken."""
    n = je - js
    taken = 0
    for sweep in range(2):
        k0, k1, d = (0, n, 1) if sweep == 0 else (n - 1, -1, -1)
        for k in range(k0, k1, d):
            j = js + k
            if not (math.isfinite(found[k, 0]) and corner[k] >= 0 and arow[j] == corner[k]):
                continue  # none, taken, or its stripe found otherwise since
            m = found[k, 1]
            wd = found[k, 3]
            if not ok[j]:
                beside = False
                for g in range(1, PAST_EDGE_GAP + 1):
                    for i in (k - g, k + g):
                        if (0 <= i < n and ok[js + i] and arow[js + i] != corner[i]
                                and _linked(arow[js + i], wsel[js + i], m, wd)):
                            beside = True
                if not beside:
                    continue
            c = ca + j
            p = float(img[int(m), c])
            klass[j] = _CORE
            ok[j] = True
            arow[j] = int(m)
            wsel[j] = wd
            yrow[j] = found[k, 0]
            cut[j] = CUT_FIT
            peak[c] = p
            width[c] = wd
            snr[c] = (p - found[k, 2]) / sig
            saturated[c] = False
            taken += 1
    return taken


@njit(nogil=True, cache=True)
def _continued_stripes(img, ca, js, je, r0, r1, klass, ok, arow, wsel, yrow, cut, core,
                       min_width, max_walk, window, shoulders, method, sig, bg, use_window, rmin,
                       rmax, peak, width, snr, saturated, reason):
    """Columns whose peak is no stripe (no peak, too wide, too narrow, unlinked) beside one
    that passed: the stripe where that one's goes on, dimmer than the column's
    brightest pixel (``PROMINENCE_*``), swept both ways so that a run of them continues; the
    gate arrays and outputs updated in place.  A column refused by a policy (saturated,
    double, outside the geometric window) stays refused."""
    h = img.shape[0]
    reach = max(2, int(math.ceil(PROMINENCE_REACH_WIDTHS * core)))
    spot = np.zeros(2)
    stats = np.zeros(8)
    for sweep in range(2):
        j0, j1, d = (js + 1, je, 1) if sweep == 0 else (je - 2, js - 1, -1)
        for j in range(j0, j1, d):
            i = j - d  # the neighbour the sweep comes from
            c = ca + j
            if ok[j]:
                continue  # a stripe (a failed fit there is no reason to look elsewhere)
            if klass[j] == _REJECTED and not (reason[c] == 1 or reason[c] == 4
                                              or reason[c] == 5):
                continue
            if not (ok[i] and math.isfinite(yrow[i])):
                continue
            # where the neighbour's stripe goes on first (its own width), then as far as the
            # frame's widest stripe links: a lit square's corner in the wider rows can stand
            # higher over its surround than the stripe and hide it
            y = math.nan
            kind = 0
            for k in range(2 if wsel[i] < core else 1):
                spread = wsel[i] if k == 0 else core
                y, kind = _continued_stripe(img, c, h, r0, r1, arow[i], wsel[i],
                                            LINK_ROWS_PX + spread, use_window, rmin, rmax, reach,
                                            core, min_width, max_walk, window, shoulders, method,
                                            sig, bg, spot, stats)
                if math.isfinite(y):
                    break
            if not math.isfinite(y):
                continue
            a = int(spot[0])
            b = spot[1]
            p = float(img[a, c])
            wd = stats[0]
            klass[j] = _CORE
            ok[j] = True
            arow[j] = a
            wsel[j] = wd
            yrow[j] = y
            cut[j] = kind
            peak[c] = p
            width[c] = wd
            snr[c] = (p - b) / sig
            saturated[c] = False


@njit(nogil=True, cache=True)
def _columns(img, c0, c1, method, auto, thr, window, max_width, auto_width, min_width,
             double_ratio, bg, policy, expected, use_window, rmin, rmax, fit_saturated, shoulders,
             med, sig, row, peak, width, reason, saturated, snr, n_peaks):
    """The columns ``c0 <= c < c1``: outputs written in place; returns the width gate."""
    h, w = img.shape
    if auto:
        threshold = med + AUTO_THRESHOLD_SIGMAS * sig
        floor = med + AUTO_MIN_PEAK_SIGMAS * sig
    else:
        threshold = thr
        floor = thr
    if c1 == c0:
        return max_width
    sep = 2 * window
    r0, r1 = 0, h
    if use_window:
        r0, r1 = passes.window_band(rmin, rmax, c0, c1, h)
    ca, cb = passes.read_span(c0, c1, w)
    n = cb - ca
    js, je = c0 - ca, c1 - ca  # the requested columns in the read span
    mx = np.zeros(n, np.uint8)
    am = np.zeros(n, np.uint16)
    sec = np.zeros(n, np.uint8)
    a2 = np.zeros(n, np.uint16)
    out = np.zeros(n, np.uint8)
    passes.column_max(img, r0, r1, ca, cb, sep, mx, am, sec)
    # the rows of the second maxima, only over the columns that hold one (none on a clean
    # frame): a second pass there is cheaper than tracking them in every frame
    maybe_double = False
    k0, k1 = n, -1
    for j in range(js, je):
        s = float(sec[j])
        if s > threshold and s >= floor and s >= double_ratio * float(mx[j]):
            k0 = min(k0, j)
            k1 = max(k1, j)
    if k1 >= k0:
        maybe_double = True
        k0, k1 = _whole_span(k0, k1 + 1, n)
        mx[k0:k1] = 0  # the second pass starts afresh (it finds the same maxima)
        am[k0:k1] = 0
        sec[k0:k1] = 0
        passes.column_max2(img, r0, r1, ca + k0, ca + k1, sep, mx[k0:k1], am[k0:k1],
                           sec[k0:k1], a2[k0:k1])
    if use_window:
        # Only the columns whose maximum lies outside their window (a reflection brighter than
        # the stripe, rare) are searched again, inside it: a frame without one costs what the
        # plain pass costs.
        k0, k1 = n, -1
        for j in range(js, je):
            p = float(mx[j])
            a = am[j]
            if p > threshold and p >= floor and (a < rmin[ca + j] or a > rmax[ca + j]):
                k0 = min(k0, j)
                k1 = max(k1, j)
        if k1 >= k0:
            maybe_double = True
            k0, k1 = _whole_span(k0, k1 + 1, n)
            mx[k0:k1] = 0
            am[k0:k1] = 0
            sec[k0:k1] = 0
            a2[k0:k1] = 0
            passes.column_max_window(img, r0, r1, ca + k0, ca + k1, sep, rmin, rmax,
                                     mx[k0:k1], am[k0:k1], sec[k0:k1], a2[k0:k1], out[k0:k1])
    # candidates (the maximum, and the far second maximum if it is strong, a local maximum and
    # apart from the first: on a wide stripe the far "second" is only its own flank), the main
    # one's width, and the frame's widths
    if auto_width:
        max_walk = int(math.ceil(WIDTH_CAP_PX * FWHM_PER_SIGMA)) + 2
    else:
        max_walk = int(math.ceil(max_width * FWHM_PER_SIGMA)) + 2
    ncand = np.zeros(n, np.int8)
    wmain = np.full(n, np.inf)
    # the main peak's count above the threshold and its centre of gravity, read with its width
    nmain = np.zeros(n)
    ymain = np.full(n, np.nan)
    # the main peak's largest one-pixel fall within its window: where a cut may be
    steep = np.zeros(n)
    stats = np.zeros(8)
    hist = np.zeros(_WIDTH_BINS, np.int64)
    bloc = np.full(n, med)
    tloc = np.full(n, threshold)
    n_widths = _candidates(img, ca, js, je, mx, am, sec, a2, auto, thr, threshold, floor,
                           max_walk, window, shoulders, med, sig, bg, double_ratio, use_window,
                           rmin, rmax, min_width, ncand, wmain, nmain, ymain, bloc, tloc, hist,
                           steep)
    core = max_width
    linked = max_width
    typical = math.nan
    if auto_width:
        if n_widths >= WIDTH_MIN_SAMPLES:
            # bin k holds widths in [k, k + 1) * WIDTH_BIN_PX; the quantile puts it at k +- 0.5
            typical = (passes.quantile_from_hist(hist, float(n_widths), 0.5) + 0.5) * WIDTH_BIN_PX
            core = max(max_width, CORE_WIDTH_FACTOR * typical)
        linked = min(LINKED_WIDTH_FACTOR * core, WIDTH_CAP_PX)
    choice = np.zeros(n, np.int8)
    if policy == 1:  # nearest
        for j in range(js, je):
            e = expected[ca + j]
            if ncand[j] == 2 and math.isfinite(e):
                if abs(float(a2[j]) - e) < abs(float(am[j]) - e):
                    choice[j] = 1
    elif policy == 2 and maybe_double:  # continuity, when some column may hold two candidates
        choice[js:je] = -1
        _continuity(ncand[js:je], mx[js:je], am[js:je], sec[js:je], a2[js:je], expected, c0,
                    choice[js:je])
    # the chosen peak of each column and its class for the gates
    klass = np.full(n, _REJECTED, np.int8)
    arow = np.zeros(n, np.int64)
    wsel = np.full(n, np.inf)
    yrow = np.full(n, np.nan)
    cut = np.zeros(n, np.int8)
    for j in range(js, je):
        c = ca + j
        n_peaks[c] = ncand[j]
        if ncand[j] == 0:
            peak[c] = float(mx[j])
            snr[c] = (float(mx[j]) - bloc[j]) / sig
            o = float(out[j])
            reason[c] = 8 if (o > threshold and o >= floor) else 1  # OUTSIDE_WINDOW / NO_PEAK
            continue
        if choice[j] == 1:
            p = float(sec[j])
            a = int(a2[j])
            b = local_background(img, c, a, h, BACKGROUND_NEAR_WINDOWS * window,
                                 BACKGROUND_FAR_WINDOWS * window, med)
            t_c, f_c = _levels(auto, thr, b, sig)
            if not (p > t_c and p >= f_c):  # the reflection does not stand clear of its own
                peak[c] = p                 # background
                snr[c] = (p - b) / sig
                reason[c] = 1  # NO_PEAK
                continue
            est.width_count_cog(img, c, a, h, 0.5 * (p + t_c), max_walk, t_c, window,
                                _cog_level(b, sig, p), bg, max_walk, stats)
            wd, above, y_cog = stats[0], stats[1], stats[2]
            if not shoulders:
                y_cog = _surface_centroid(img, c, a, h, p, b, sig, stats, window, max_walk, bg)
        else:
            p = float(mx[j])
            a = int(am[j])
            b = bloc[j]
            t_c = tloc[j]
            wd, above, y_cog = wmain[j], nmain[j], ymain[j]
        peak[c] = p
        snr[c] = (p - b) / sig
        bg_sat = b if math.isnan(bg) else bg
        if p >= SATURATION_DN:
            if not fit_saturated:
                reason[c] = 2  # SATURATED
                continue
            saturated[c] = True
        width[c] = wd
        if wd > linked:
            reason[c] = 4  # TOO_WIDE
            continue
        if policy == 3 and ncand[j] == 2:
            reason[c] = 3  # DOUBLE
            continue
        arow[j] = a
        wsel[j] = wd
        if wd < min_width or above < MIN_PIXELS_ABOVE:
            if snr[c] < NARROW_MIN_SIGMAS:
                reason[c] = 5  # TOO_NARROW
                continue
            klass[j] = _NARROW
        elif wd > core:
            klass[j] = _WIDE
        else:
            klass[j] = _CORE
        # the refinement, here while the column's pixels are in the cache (a peak the gates
        # then reject is refined for nothing: rare)
        test_cut = choice[j] != 0 or steep[j] > est.CUT_MIN_FALL * (p - b)
        if method == 0 and not shoulders and not saturated[c] and not test_cut:
            yrow[j] = y_cog  # what _centre returns, without the call: most columns
        else:
            yrow[j], cut[j] = _centre(img, c, a, h, p, b, sig, saturated[c], bg_sat, method,
                                      shoulders, window, max_walk, y_cog, t_c, wd, bg, test_cut,
                                      min_width)
    # the gates: a narrow peak continued by a neighbour's, a wide one by a chain of them from a
    # stripe within the gate
    ok = np.zeros(n, np.bool_)
    for j in range(js, je):
        if klass[j] == _CORE:
            ok[j] = True
        elif klass[j] == _NARROW:
            for i in (j - 1, j + 1):
                if (i >= js and i < je and klass[i] != _REJECTED
                        and _linked(arow[i], wsel[i], arow[j], wsel[j])):
                    ok[j] = True
    for j in range(js + 1, je):
        if (klass[j] == _WIDE and not ok[j] and ok[j - 1]
                and _linked(arow[j - 1], wsel[j - 1], arow[j], wsel[j])):
            ok[j] = True
    for j in range(je - 2, js - 1, -1):
        if (klass[j] == _WIDE and not ok[j] and ok[j + 1]
                and _linked(arow[j + 1], wsel[j + 1], arow[j], wsel[j])):
            ok[j] = True
    if auto:
        past_edges = math.isfinite(typical) and not shoulders
        m_cols = je - js if past_edges else 0  # no arrays where there is nothing to look for
        corner = np.full(m_cols, -1, np.int64)
        found = np.full((m_cols, 4), math.nan)
        if past_edges:
            _past_edge_candidates(img, ca, js, je, r0, r1, klass, arow, wsel, typical, core,
                                  linked, min_width, max_walk, sig, use_window, rmin, rmax, snr,
                                  reason, corner, found)
        for _ in range(PAST_EDGE_ROUNDS):
            # the stripes past the edges continue those that passed, and the search where a
            # stripe goes on continues them in turn
            taken = 0
            if past_edges:
                taken = _stripes_past_edges(img, ca, js, je, klass, ok, arow, wsel, yrow, cut,
                                            peak, width, snr, saturated, sig, corner, found)
            _continued_stripes(img, ca, js, je, r0, r1, klass, ok, arow, wsel, yrow, cut, core,
                               min_width, max_walk, window, shoulders, method, sig, bg,
                               use_window, rmin, rmax, peak, width, snr, saturated, reason)
            if taken == 0:
                break
    _narrow_cuts(img, ca, js, je, ok, cut, arow, yrow, width, snr, sig, max_walk)
    # the peaks that passed
    for j in range(js, je):
        if klass[j] == _REJECTED:
            continue
        c = ca + j
        if not ok[j]:
            reason[c] = 5 if klass[j] == _NARROW else 4  # TOO_NARROW / TOO_WIDE
        elif not math.isfinite(yrow[j]):
            reason[c] = 6  # FIT_FAILED
        else:
            row[c] = yrow[j]
            reason[c] = 0
    return core
