"""Per-column sub-pixel estimators of the stripe's centre, and its width.

Each takes the frame ``img`` (H, W) uint8, a column ``c``, the row ``a`` of the chosen peak
(its integer argmax) and the frame height ``h``, reads a few pixels about ``a`` and returns the
stripe's centre in rows (pixel centres at integers), or NaN when the estimate degenerates:
``scanner_core.stripe.extractor.extract`` flags the column then, never guesses. The references are those
of ``extract``'s docstring.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from scanner_core.numeric.linsolve import solve_in_place

__all__ = ["SATURATION_DN", "FWHM_PER_SIGMA", "fwhm_width", "count_above", "cog",
           "top_centroid", "within_window", "width_count_cog", "parabola", "gaussian3", "blais_rioux",
           "lsq_gauss", "saturated_centre", "narrow_clip_centre", "cut_flank", "uncut_centre",
           "narrow_cut", "narrow_cut_centre"]

# Pixel value taken as saturated (uint8 full scale).
SATURATION_DN = 255
# FWHM of a Gaussian in sigmas: 2 sqrt(2 ln 2).
FWHM_PER_SIGMA = 2.3548200450309493
# Gauss-Newton iterations of the least-squares Gaussian fit (converges in 3-4 from the centroid).
LSQ_ITERATIONS = 6
# The least-squares fit is rejected if its centre leaves the argmax by more than this (px),
# or by LSQ_MAX_SHIFT_SIGMAS of the stripe's width where that is more: the top of a wide
# stripe is flat within the noise over a few rows, and its argmax wanders there.
LSQ_MAX_SHIFT_PX = 1.5
LSQ_MAX_SHIFT_SIGMAS = 0.5
#: A clipped peak at most this many rows long, with an unclipped sample on either side, is
#: a narrow stripe (sigma ~0.5 px) that reached full scale: too few samples for the flank fit.
NARROW_CLIP_ROWS = 2
#: The least-squares fit spans at least this many of the stripe's sigmas either side of the
#: argmax (``window`` rows at the least): 2.5 sigma hold 98.8 % of a Gaussian's area and reach
#: the background on either flank, which the fit's offset needs; for the reference stripe
#: (sigma 1.5 px) that is the default 4 rows.
LSQ_HALF_WIDTH_SIGMAS = 2.5
# Half width at half maximum of a Gaussian in sigmas: sqrt(2 ln 2).
HWHM_PER_SIGMA = 0.5 * FWHM_PER_SIGMA
#: A flank is cut (a texture's edge under the stripe, its far side dark) where it falls in one
#: pixel by more than CUT_MIN_FALL of the peak's height over its background and by more than a
#: Gaussian as wide as the other flank can: CUT_SLOPE / sigma of the height (a unit Gaussian's
#: steepest slope is 1 / sqrt(e) = 0.607 / sigma; the margin covers the width read short or
#: long by a pixel's sampling on a narrow stripe, whose peak pixel also reads under its
#: height), plus CUT_NOISE_SIGMAS of the difference of two pixels' noise (a frame's thousands
#: of columns hold a few falls each: at 3 sigmas, noise cut a dim stripe about once a frame;
#: at 5, about once in two hundred).  CUT_MIN_FALL keeps a speckled stripe's grain (one pixel
#: of a wide flank darker than the next) from passing for an edge.
CUT_MIN_FALL = 0.5
CUT_SLOPE = 0.75
CUT_NOISE_SIGMAS = 5.0
#: The whole flank is no steeper than its own width allows within FLANK_NOISE_SIGMAS of two
#: pixels' noise (a wider margin let an overexposed core's halo through: a flat top between
#: two cliffs is no stripe cut on one side).
FLANK_NOISE_SIGMAS = 3.0
#: ... and where the pixel past the fall falls again by less than CUT_STEP_RATIO of it, and
#: FLANK_NOISE_SIGMAS of two pixels' noise (an edge between two pixels; one that straddles a
#: pixel splits the step in two falls, and is found only where one of them holds most of it;
#: the dark square's own share of a stripe cut near its centre goes on falling, by its
#: reflectance's share of the stripe's slope).
CUT_STEP_RATIO = 0.25
#: The whole flank's fit takes its pixels above CUT_RUN_LEVEL of the peak's height over that
#: flank's own foot.
CUT_RUN_LEVEL = 0.15
#: Where the whole flank's half width reads too short for the fall to stand out of it (its
#: half width taken from the argmax, less half a pixel, and the noise's wide margin: a stripe
#: of sigma 1.6 px on a dim surface), the pixel past the fall is compared with the whole
#: flank's own Gaussian extrapolated there (``_falls_past_fit``): a cut where it reads under
#: it by CUT_MODEL_SLACK of the height plus CUT_MODEL_SIGMAS of its expected spread (the
#: pixel's noise and the fit's, from the fit's covariance).  A one-sided test on the few
#: columns whose fall already passes CUT_MIN_FALL, with the foot set as high as the profile
#: allows.  The slack and the sigmas trade cuts missed on a 12 px print against whole dim
#: stripes (15 DN over 1 DN of noise, whose pixels' own shot noise the frame's noise leaves
#: out) taken for cut: at 2 sigmas and a tenth of the height one such stripe in 1900 was.
CUT_MODEL_SLACK = 0.1
CUT_MODEL_SIGMAS = 2.5
#: ... and by CUT_EDGE_MODEL_SIGMAS where the cut side's own foot lies under the whole
#: flank's by more than CUT_SURFACES_SIGMAS of the noise: two surfaces, so an edge lies
#: within the reach and the test need only say where.  A narrow stripe cut at its centre on a
#: dim print keeps two or three pixels of whole flank, whose extrapolation spreads wide: the
#: narrower margin finds it four times as often, and takes a narrow whole stripe for cut now
#: and then where a dark square lies just past its steep side (docs/stripe.md).  Each foot is
#: the mean of two pixels, so their difference has the pixels' own noise sigma: on one
#: surface it passes 3 of them once in about 700 columns tested.
CUT_SURFACES_SIGMAS = 3.0
CUT_EDGE_MODEL_SIGMAS = 1.5
#: The uncut flank's fit is rejected if its centre leaves the argmax by more than this, px.
CUT_MAX_SHIFT_PX = 2.0
#: The uncut flank's foot is looked for no further from the argmax than this many of the
#: stripe's widths (sigmas) plus a row: a Gaussian has fallen to its foot within three, and a
#: walk that goes on falling past them has left the stripe (a print finer than the line: into
#: the next dark square, a surface under the flank's fit that widens it).
CUT_FOOT_WIDTHS = 3.0
#: A narrow stripe cut near its centre keeps two pixels of whole flank, too few for its own
#: fit: it is told by its three pixels about the argmax (``narrow_cut``), the cut side's read
#: NARROW_CUT_NOISE_SIGMAS of noise high, implying a Gaussian narrower than the narrowest
#: stripe, where that side lies on a darker surface (``CUT_SURFACES_SIGMAS``) and the whole
#: side's foot stands within NARROW_CUT_FOOT of the peak's height over its background (the
#: surface the stripe lies on, not a dip in a speckled top).
NARROW_CUT_NOISE_SIGMAS = 1.0
NARROW_CUT_FOOT = 0.25


@njit(nogil=True, cache=True)
def fwhm_width(col_img, c, a, h, level, max_walk):
    """Sigma-like width: interpolated full width at ``level`` around row ``a``, / 2.3548."""
    lo = a
    steps = 0
    while lo > 0 and col_img[lo - 1, c] >= level and steps < max_walk:
        lo -= 1
        steps += 1
    if steps >= max_walk:
        return math.inf
    if lo > 0:
        v0 = float(col_img[lo - 1, c])
        v1 = float(col_img[lo, c])
        left = lo - (v1 - level) / (v1 - v0)
    else:
        left = -0.5
    hi = a
    steps = 0
    while hi < h - 1 and col_img[hi + 1, c] >= level and steps < max_walk:
        hi += 1
        steps += 1
    if steps >= max_walk:
        return math.inf
    if hi < h - 1:
        v0 = float(col_img[hi + 1, c])
        v1 = float(col_img[hi, c])
        right = hi + (v1 - level) / (v1 - v0)
    else:
        right = h - 0.5
    return (right - left) / FWHM_PER_SIGMA


@njit(nogil=True, cache=True)
def count_above(img, c, a, h, threshold, window):
    k = 0
    for r in range(max(a - window, 0), min(a + window, h - 1) + 1):
        if img[r, c] > threshold:
            k += 1
    return k


@njit(nogil=True, cache=True)
def cog(img, c, a, h, threshold, window, bg, reach):
    """Windowed centre of gravity, Fisher & Naidu Eq. (CoG): sum(r w) / sum(w).

    Over the pixels above ``threshold`` within ``window`` rows of ``a``, and beyond them as
    long as the run above the threshold goes on unbroken (at most ``reach`` rows from ``a``):
    a stripe wider than the window (sigma 6 px: 29 rows above a 20 DN threshold at 200 DN) is
    weighed whole, where a fixed window would cut its flanks unevenly and pull the centre
    toward the argmax (sigma 6 px: 0.058 px RMS, 0.54 px with the window alone).  A
    background above the threshold beside the stripe (ambient light on a white surface) is
    followed too: the threshold belongs above the background (``threshold="auto"`` puts it
    there).  Bounding the run by three of the stripe's measured widths instead made a
    speckled line's error 18 % larger (its width measured short where the speckle darkens a
    flank).  Weights ``v - threshold``, or ``v - bg`` with a background.
    """
    off = threshold if math.isnan(bg) else bg
    lo = max(a - window, 0)
    while img[lo, c] > threshold and lo > 0 and a - lo < reach and img[lo - 1, c] > threshold:
        lo -= 1
    hi = min(a + window, h - 1)
    while img[hi, c] > threshold and hi < h - 1 and hi - a < reach and img[hi + 1, c] > threshold:
        hi += 1
    s0 = 0.0
    s1 = 0.0
    for r in range(lo, hi + 1):
        v = float(img[r, c])
        if v > threshold:
            wgt = v - off
            s0 += wgt
            s1 += wgt * (r - a)
    if s0 <= 0.0:
        return math.nan
    return a + s1 / s0


@njit(nogil=True, cache=True)
def top_centroid(img, c, a, h, level, reach):
    """Centre of the part of the profile above ``level``, the profile taken as linear between
    the pixel centres: ``int x (f(x) - level) dx / int (f(x) - level) dx`` over the run above
    ``level`` through ``a`` (at most ``reach`` rows each way), its ends where the linear profile
    crosses ``level``.

    A centroid of the pixels above a level high on the peak moves by whole pixels as a pixel
    crosses it (a flat top, a clipped run, makes every row a whole or half pixel); the crossings
    move smoothly.  NaN when nothing lies above ``level``.
    """
    lo = a
    while lo > 0 and a - lo < reach and img[lo - 1, c] > level:
        lo -= 1
    hi = a
    while hi < h - 1 and hi - a < reach and img[hi + 1, c] > level:
        hi += 1
    # the segments from the last pixel below the level to the first one below it again
    r0 = max(lo - 1, 0)
    r1 = min(hi + 1, h - 1)
    s0 = 0.0
    s1 = 0.0
    for r in range(r0, r1):
        u0 = float(img[r, c]) - level
        u1 = float(img[r + 1, c]) - level
        x = float(r - a)
        if u0 > 0.0 and u1 > 0.0:
            area = 0.5 * (u0 + u1)
            s0 += area
            s1 += x * area + (u0 + 2.0 * u1) / 6.0
        elif u0 > 0.0:  # falls through the level at z
            z = u0 / (u0 - u1)
            area = 0.5 * u0 * z
            s0 += area
            s1 += x * area + u0 * z * z / 6.0
        elif u1 > 0.0:  # rises through the level at z
            z = u0 / (u0 - u1)
            area = 0.5 * u1 * (1.0 - z)
            s0 += area
            s1 += x * area + u1 * (1.0 / 3.0 - 0.5 * z + z * z * z / 6.0) / (1.0 - z)
    if s0 <= 0.0:
        return math.nan
    return a + s1 / s0


@njit(nogil=True, cache=True)
def within_window(img, c, a, h, level, max_walk, threshold, window, t_cog, bg, out):
    """``width_count_cog`` when the peak lies wholly within ``+-window`` rows of ``a`` (the
    half-level run ends inside it, the centroid's run does not go on past it, no ``bg``), as
    fixed-length loops without data-dependent branches: a noisy flank's pixels cross the
    levels at random, and a branch on each costs more than the reads (``out[3]``, the run
    past the window, is 0; ``out[6]``, where ``out`` holds it, the largest one-pixel fall
    away from ``a`` within the window).  False (``out`` unset) otherwise: call ``width_count_cog`` then (a separate call, since the general walk's frame
    made this one cost twice as much when they were one function)."""
    if not (math.isnan(bg) and a > window and a + window < h - 1 and window < max_walk):
        return False
    v = float(img[a, c])
    count = 1.0 if v > threshold else 0.0
    s0 = max(v - t_cog, 0.0)
    s1 = 0.0
    down = 0
    up = 0
    alive_down = 1
    alive_up = 1
    fall = 0.0
    prev_down = v
    prev_up = v
    for d in range(1, window + 1):
        u = float(img[a - d, c])
        fall = max(fall, prev_down - u)
        prev_down = u
        alive_down = alive_down if u >= level else 0
        down += alive_down
        count += 1.0 if u > threshold else 0.0
        wgt = max(u - t_cog, 0.0)
        s0 += wgt
        s1 -= wgt * d
        u = float(img[a + d, c])
        fall = max(fall, prev_up - u)
        prev_up = u
        alive_up = alive_up if u >= level else 0
        up += alive_up
        count += 1.0 if u > threshold else 0.0
        wgt = max(u - t_cog, 0.0)
        s0 += wgt
        s1 += wgt * d
    if down == window or up == window:
        return False
    if float(img[a - window, c]) > t_cog and float(img[a - window - 1, c]) > t_cog:
        return False  # the centroid's run goes on beyond the window
    if float(img[a + window, c]) > t_cog and float(img[a + window + 1, c]) > t_cog:
        return False
    lo = a - down
    v1 = float(img[lo, c])
    left = lo - (v1 - level) / (v1 - float(img[lo - 1, c]))
    hi = a + up
    v1 = float(img[hi, c])
    right = hi + (v1 - level) / (v1 - float(img[hi + 1, c]))
    out[0] = (right - left) / FWHM_PER_SIGMA
    out[1] = count
    out[2] = a + s1 / s0 if s0 > 0.0 else math.nan
    out[3] = 0.0
    if out.shape[0] > 6:
        out[6] = fall
    return True


@njit(nogil=True, cache=True)
def width_count_cog(img, c, a, h, level, max_walk, threshold, window, t_cog, bg, reach, out):
    """``fwhm_width``, ``count_above`` and ``cog`` of one peak, reading each pixel once.

    The three walk the same pixels about ``a``; a column's pixels lie a frame's row apart in
    memory, and reading them once is what the frame's time allows.  ``out`` (4,) float64
    receives the width (px, inf past ``max_walk``), the count of pixels above ``threshold``
    within ``+-window`` and the centre of gravity above ``t_cog`` (NaN if none), each equal to
    what the separate function returns (the centroid's sums added in another order), the
    rows the centroid's run goes on past the window, and (where ``out`` holds seven) the
    highest last pixel of a run past the window where it fell under ``t_cog`` and the largest
    fall there (a flank ends just over the level, one pixel's slope above the next, a lit
    square's edge far over it and by a step; 0 where no such run ended), and the largest
    one-pixel fall away from ``a`` within the window; (where it holds eight) the most any such
    run fell from the window's edge pixel to its last (a flank falls all along it, a surface
    just over the level stays flat; -inf where no run ended)."""
    off = t_cog if math.isnan(bg) else bg
    v = float(img[a, c])
    count = 1.0 if v > threshold else 0.0
    s0 = v - off if v > t_cog else 0.0
    s1 = 0.0
    beyond = 0
    cliff = 0.0
    cliff_fall = 0.0
    run_drop = -math.inf
    fall = 0.0
    width_inf = False
    left = right = 0.0
    for side in range(2):
        step = -1 if side == 0 else 1
        end = 0 if side == 0 else h - 1  # the last row on this side
        prev = v
        steps = 0
        half = True  # still walking the half-level run
        edge = -0.5 if side == 0 else h - 0.5
        w_end = a - window if side == 0 else a + window
        if side == 0 and w_end < 0:
            w_end = 0
        if side == 1 and w_end > h - 1:
            w_end = h - 1
        run = img[w_end, c] > t_cog  # the run beyond the window starts at its edge pixel
        run_top = float(img[w_end, c])
        r = a
        while r != end:
            r += step
            d = r - a if side == 1 else a - r
            u = float(img[r, c])
            if half:
                if u >= level and steps < max_walk:
                    steps += 1
                    if steps >= max_walk:
                        width_inf = True
                        half = False
                else:
                    if steps >= max_walk:
                        width_inf = True
                    else:
                        # the level crossed between the previous row and this one
                        edge = (r - step) + step * (prev - level) / (prev - u)
                    half = False
            inside = d <= window
            if inside:
                fall = max(fall, prev - u)
                if u > threshold:
                    count += 1.0
                if u > t_cog:
                    s0 += u - off
                    s1 += (u - off) * (r - a)
            elif run and d <= reach and u > t_cog:
                s0 += u - off
                s1 += (u - off) * (r - a)
                beyond += 1
            else:
                if run and d <= reach:
                    # where the run past the window fell under the level, and by how much
                    cliff = max(cliff, prev)
                    cliff_fall = max(cliff_fall, prev - u)
                    run_drop = max(run_drop, run_top - prev)
                run = False
            prev = u
            if not half and not inside and not run:
                break
        if side == 0:
            left = edge
        else:
            right = edge
    out[0] = math.inf if width_inf else (right - left) / FWHM_PER_SIGMA
    out[1] = count
    out[2] = a + s1 / s0 if s0 > 0.0 else math.nan
    out[3] = beyond
    if out.shape[0] > 6:
        out[4] = cliff
        out[5] = cliff_fall
        out[6] = fall
    if out.shape[0] > 7:
        out[7] = run_drop


@njit(nogil=True, cache=True)
def _three_points(img, c, a, h):
    if a == 0 or a == h - 1:
        return math.nan, math.nan, math.nan
    return float(img[a - 1, c]), float(img[a, c]), float(img[a + 1, c])


@njit(nogil=True, cache=True)
def parabola(img, c, a, h):
    ym, y0, yp = _three_points(img, c, a, h)
    den = ym - 2.0 * y0 + yp
    if not den < 0.0:  # flat top or NaN: no curvature, no centre
        return math.nan
    return a + 0.5 * (ym - yp) / den


@njit(nogil=True, cache=True)
def gaussian3(img, c, a, h, bg):
    ym, y0, yp = _three_points(img, c, a, h)
    off = 0.0 if math.isnan(bg) else bg
    # clamp to 1 DN above the offset so that the logarithms stay finite
    lm = math.log(max(ym - off, 1.0))
    l0 = math.log(max(y0 - off, 1.0))
    lp = math.log(max(yp - off, 1.0))
    den = lm - 2.0 * l0 + lp
    if not den < 0.0:
        return math.nan
    return a + 0.5 * (lm - lp) / den


@njit(nogil=True, cache=True)
def blais_rioux(img, c, a, h):
    """Blais & Rioux (1986) 4th-order filter g(i) = f(i-2)+f(i-1)-f(i+1)-f(i+2), zero crossing."""
    if a < 3 or a > h - 4:
        return math.nan
    g = np.empty(3)
    for k in range(3):
        i = a - 1 + k
        g[k] = (float(img[i - 2, c]) + float(img[i - 1, c])
                - float(img[i + 1, c]) - float(img[i + 2, c]))
    # g < 0 left of the peak, > 0 right of it: crossing in [a-1, a] or [a, a+1]
    for k in range(2):
        if g[k] <= 0.0 and g[k + 1] > 0.0:
            return a - 1 + k + g[k] / (g[k] - g[k + 1])
    if g[1] == 0.0:
        return float(a)
    return math.nan


@njit(nogil=True, cache=True)
def lsq_gauss(img, c, a, h, threshold, window, mu0, s0):
    """Gauss-Newton fit of b + A exp(-(x - mu)^2 / (2 s^2)) on rows a +- half, where half is
    ``window`` or ``LSQ_HALF_WIDTH_SIGMAS`` times the stripe's width ``s0``, the larger.

    Coordinates are centred on the argmax (x = r - a) and intensities scaled by the peak, so the
    normal equations are well conditioned.  Returns NaN when the fit degenerates.
    """
    half = window
    if math.isfinite(s0):
        half = max(window, int(math.ceil(LSQ_HALF_WIDTH_SIGMAS * s0)))
    r0 = max(a - half, 0)
    r1 = min(a + half, h - 1)
    n = r1 - r0 + 1
    if n < 5:
        return math.nan
    x = np.empty(n)
    y = np.empty(n)
    ymin = 255.0
    for i in range(n):
        x[i] = r0 + i - a
        y[i] = float(img[r0 + i, c])
        ymin = min(ymin, y[i])
    scale = 1.0 / max(float(img[a, c]), 1.0)
    for i in range(n):
        y[i] *= scale
    b = ymin * scale
    amp = 1.0 - b
    mu = mu0 - a
    s = min(max(s0, 0.7), 0.5 * half) if math.isfinite(s0) else 0.7
    max_shift = max(LSQ_MAX_SHIFT_PX, LSQ_MAX_SHIFT_SIGMAS * s)
    jt = np.empty((4, n))
    res = np.empty(n)
    m = np.empty((4, 4))
    v = np.empty(4)
    for _ in range(LSQ_ITERATIONS):
        inv2 = 1.0 / (s * s)
        for i in range(n):
            d = x[i] - mu
            e = math.exp(-0.5 * d * d * inv2)
            res[i] = y[i] - (b + amp * e)
            jt[0, i] = 1.0  # d/db
            jt[1, i] = e  # d/dA
            jt[2, i] = amp * e * d * inv2  # d/dmu
            jt[3, i] = amp * e * d * d * inv2 / s  # d/ds
        for p in range(4):
            acc = 0.0
            for i in range(n):
                acc += jt[p, i] * res[i]
            v[p] = acc
            for q in range(p, 4):
                acc = 0.0
                for i in range(n):
                    acc += jt[p, i] * jt[q, i]
                m[p, q] = acc
                m[q, p] = acc
        if not solve_in_place(m, v):
            return math.nan
        b += v[0]
        amp += v[1]
        mu += max(min(v[2], 1.0), -1.0)  # bounded step: the fit starts within a pixel
        s += max(min(v[3], 0.5 * s), -0.5 * s)
        if not (amp > 0.0 and s > 0.0 and abs(mu) <= max_shift):
            return math.nan
    return a + mu


@njit(nogil=True, cache=True)
def saturated_centre(img, c, a, h, level, window, bgl, max_walk):
    """Centre of a clipped peak from its unclipped flanks (censored Gaussian fit).

    The plateau is the run of full-scale rows through ``a``; the samples within ``window`` rows
    of it that are above ``level`` and below full scale are fitted with
    ``ln(v - bgl) = p0 + p1 x + p2 x^2`` (``x`` from the plateau's middle) by least squares with
    weights ``(v - bgl)^2`` (Guo 2011: the logarithm's noise is ``sigma_n / (v - bgl)``); the
    clipped samples only say "at least full scale" and are left out.  Needs samples on both
    flanks (else the centre is not constrained) and a concave parabola; NaN otherwise.
    """
    lo = a
    steps = 0
    while lo > 0 and img[lo - 1, c] >= SATURATION_DN and steps < max_walk:
        lo -= 1
        steps += 1
    hi = a
    steps = 0
    while hi < h - 1 and img[hi + 1, c] >= SATURATION_DN and steps < max_walk:
        hi += 1
        steps += 1
    mid = 0.5 * (lo + hi)
    m = np.zeros((3, 3))
    v = np.zeros(3)
    n_left = 0
    n_right = 0
    for r in range(max(lo - window, 0), min(hi + window, h - 1) + 1):
        val = float(img[r, c])
        if val >= SATURATION_DN or not val > level or not val > bgl + 1.0:
            continue
        if r < lo:
            n_left += 1
        elif r > hi:
            n_right += 1
        y = val - bgl
        wgt = y * y
        ly = math.log(y)
        x = r - mid
        xp = 1.0
        for p in range(3):
            v[p] += wgt * ly * xp
            xq = 1.0
            for q in range(3):
                m[p, q] += wgt * xp * xq
                xq *= x
            xp *= x
    if n_left < 1 or n_right < 1 or n_left + n_right < 3:
        return math.nan
    # scale the weights (up to 6e4 each) so that the pivots compare with SINGULAR_PIVOT sanely
    s = 1.0 / m[0, 0]
    for p in range(3):
        v[p] *= s
        for q in range(3):
            m[p, q] *= s
    if not solve_in_place(m, v):
        return math.nan
    if not v[2] < 0.0:
        return math.nan
    mu = mid - 0.5 * v[1] / v[2]
    if abs(mu - mid) > 0.5 * (hi - lo) + 1.0:
        return math.nan
    return mu


@njit(nogil=True, cache=True)
def narrow_clip_centre(img, c, a, h, level, bgl):
    """Centre of a narrow clipped peak: the centroid, weights ``v - bgl``, of its clipped run
    (at most ``NARROW_CLIP_ROWS`` rows) and one sample either side, both above ``level``.

    The flank fit (:func:`saturated_centre`) needs three unclipped samples; a stripe of sigma
    0.5 px clipped at full scale leaves one on each side. The clipped samples weigh what they
    show (the truth is brighter), so the centre is pulled toward the run's middle by a share
    of a pixel; the column stays flagged ``saturated``. NaN for a longer run, or one without a
    sample above ``level`` on both sides (a plateau at the frame's edge: never guessed).
    """
    lo = a
    while lo > 0 and img[lo - 1, c] >= SATURATION_DN and a - lo < NARROW_CLIP_ROWS:
        lo -= 1
    hi = a
    while hi < h - 1 and img[hi + 1, c] >= SATURATION_DN and hi - a < NARROW_CLIP_ROWS:
        hi += 1
    if hi - lo + 1 > NARROW_CLIP_ROWS or lo == 0 or hi == h - 1:
        return math.nan
    if not (float(img[lo - 1, c]) > level and float(img[hi + 1, c]) > level):
        return math.nan
    if img[lo - 1, c] >= SATURATION_DN or img[hi + 1, c] >= SATURATION_DN:
        return math.nan
    s0 = 0.0
    s1 = 0.0
    for r in range(lo - 1, hi + 2):
        wgt = float(img[r, c]) - bgl
        s0 += wgt
        s1 += wgt * r
    return s1 / s0 if s0 > 0.0 else math.nan


@njit(nogil=True, cache=True)
def flank_crossing(img, c, a, h, step, half, reach):
    """Down one flank from row ``a`` (``step`` -1: up the frame, +1: down it) to where it
    crosses ``half``: the largest one-pixel fall on the way (the last one, out of the part
    above ``half``, included), the row before it, and the distance from ``a`` to the crossing
    (the profile linear between pixels; NaN where the frame's edge or ``reach`` comes first).
    A fall that starts under ``half`` is not looked for: an edge there cuts the stripe's tail,
    which moves its centroid little."""
    r = a
    best = -math.inf
    r_best = a
    k = 0
    while 0 <= r + step < h and k < reach:
        v1 = float(img[r, c])
        v0 = float(img[r + step, c])
        if v1 - v0 > best:
            best = v1 - v0
            r_best = r
        if not v0 > half:
            return best, r_best, abs(r - a) + (v1 - half) / (v1 - v0)
        r += step
        k += 1
    return best, r_best, math.nan


@njit(nogil=True, cache=True)
def _steepest_fall(half_width, height, noise, sigmas):
    """The largest one-pixel fall a Gaussian stripe ``height`` high whose half width at half
    maximum from its argmax is ``half_width`` (its centre up to half a pixel nearer) shows
    with pixel noise ``noise``, ``sigmas`` of two pixels' noise over the noiseless one."""
    sigma = max(half_width - 0.5, 0.3) / HWHM_PER_SIGMA
    return min(1.0, CUT_SLOPE / sigma) * height + sigmas * math.sqrt(2.0) * noise


@njit(nogil=True, cache=True)
def _tail_level(img, c, a, h, step, half_width):
    """The median of the three pixels from the first past the flank's half-maximum crossing
    (``half_width`` from row ``a`` by ``step``) on: the surface beside a narrow stripe's
    flank, or a level above it (a wide stripe's tail), one pixel past a texture's edge there
    not included (NaN at the frame's edge)."""
    d = max(2, int(math.ceil(half_width)) + 1)
    r = a + step * d
    if not (0 <= r < h and 0 <= r + 2 * step < h):
        return math.nan
    v0 = float(img[r, c])
    v1 = float(img[r + step, c])
    v2 = float(img[r + 2 * step, c])
    return max(min(v0, v1), min(max(v0, v1), v2))


@njit(nogil=True, cache=True)
def _falls_past_fit(img, c, a, h, step, r_cut, height, noise, reach, half_width):
    """Whether the pixel past row ``r_cut`` (by ``step``) reads under the whole flank's own
    Gaussian there (``_whole_flank_fit``, through ``r_cut``, extrapolated one pixel) by more
    than ``CUT_MODEL_SLACK`` of the peak's ``height`` plus ``CUT_MODEL_SIGMAS`` of its
    expected spread (``CUT_EDGE_MODEL_SIGMAS`` where the cut side's own foot lies under the
    whole flank's: two surfaces),

        spread^2 = noise^2 (1 + e^2 g^T N^-1 g),  g = (1, x, x^2),

    ``e`` the fit's value over its foot at the pixel's ``x = r - a`` and ``N`` its normal
    matrix.  The foot is the highest the profile allows: the whole flank's walked foot, its
    level past the half-maximum crossing (``half_width``, ``_tail_level``) and the cut side's
    own foot (a stripe whose far side is lit is no stripe cut there)."""
    r_past = r_cut + step
    if not 0 <= r_past < h:
        return False
    foot = _foot(img, c, a, h, -step, noise, reach)
    if not math.isfinite(foot):
        return False
    foot_whole = foot
    # the highest foot the profile allows: the whole flank's Gaussian narrowest, the cut
    # hardest to claim (a narrow stripe's walk runs on past a square's edge a pixel beyond
    # its tail; a stripe whose far side is lit is no stripe cut there)
    tail = _tail_level(img, c, a, h, -step, half_width)
    if math.isfinite(tail):
        foot = max(foot, tail)
    foot_cut = _foot(img, c, r_past, h, step, noise, reach)
    sigmas = CUT_MODEL_SIGMAS
    if math.isfinite(foot_cut):
        if foot_cut < foot_whole - CUT_SURFACES_SIGMAS * noise:
            sigmas = CUT_EDGE_MODEL_SIGMAS  # the surfaces differ: an edge lies between them
        foot = max(foot, foot_cut)
    fit = np.empty(4)
    normal = np.empty((3, 3))
    if not _whole_flank_fit(img, c, a, h, step, r_cut, foot, reach, fit, normal):
        return False
    x = float(r_past - a)
    g = np.array([1.0, x, x * x])
    z = g.copy()
    if not solve_in_place(normal, z):
        return False
    log_var = max(g[0] * z[0] + g[1] * z[1] + g[2] * z[2], 0.0)
    expected = math.exp(min(fit[1] + fit[2] * x + fit[3] * x * x, 30.0))
    spread = math.sqrt(noise * noise * (1.0 + expected * expected * log_var))
    return (fit[0] + expected - float(img[r_past, c])
            > CUT_MODEL_SLACK * height + sigmas * spread)


@njit(nogil=True, cache=True)
def cut_flank(img, c, a, h, bg, noise, reach):
    """Which flank of the peak at ``a``, if one, a texture's edge cuts.

    Where a dark square's edge crosses the stripe, its far side is the stripe times the dark
    reflectance: that flank drops in one pixel further than a Gaussian as wide as the other
    flank can (see ``CUT_MIN_FALL``), or, where that width reads short, further than the
    other flank's own fit extrapolated past the fall (``_falls_past_fit``), and a centroid of
    the whole stripe is pulled toward the lit side by up to a sigma.

    Parameters
    ----------
    bg : float
        The peak's background, DN (its height is ``img[a, c] - bg``).
    noise : float
        The frame's pixel noise sigma, DN.
    reach : int
        The farthest row from ``a`` either flank is followed to.

    Returns
    -------
    step : int
        -1 when the flank toward row 0 is cut, +1 the other, 0 when neither or both are.
    row : int
        The last row before the cut's fall (on the stripe's lit side).
    """
    height = float(img[a, c]) - bg
    if not height > 0.0:
        return 0, a
    half = bg + 0.5 * height
    fall_up, r_up, hw_up = flank_crossing(img, c, a, h, -1, half, reach)
    fall_dn, r_dn, hw_dn = flank_crossing(img, c, a, h, 1, half, reach)
    if not (max(fall_up, fall_dn) > CUT_MIN_FALL * height and math.isfinite(hw_up)
            and math.isfinite(hw_dn)):
        return 0, a
    cut_up = fall_up > max(CUT_MIN_FALL * height,
                           _steepest_fall(hw_dn, height, noise, CUT_NOISE_SIGMAS))
    cut_dn = fall_dn > max(CUT_MIN_FALL * height,
                           _steepest_fall(hw_up, height, noise, CUT_NOISE_SIGMAS))
    if cut_up and cut_dn:
        return 0, a
    if not (cut_up or cut_dn):
        # the whole flank's width read short (a narrow stripe's half width from its argmax,
        # the noise's margin on a dim one): the fall against the whole flank's own fit, where
        # that flank has no cliff of its own (a print finer than the stripe chops it into
        # runs between cliffs, none of them a stripe's flank): it falls by no more than half
        # the height in one pixel, or than a Gaussian as wide as itself (a narrow stripe's
        # whole flank falls by more than half its height from the argmax)
        model_step = -1 if fall_up > fall_dn else 1
        whole_fall, whole_hw = (fall_dn, hw_dn) if model_step < 0 else (fall_up, hw_up)
        if not whole_fall <= max(CUT_MIN_FALL * height,
                                 _steepest_fall(whole_hw, height, noise, FLANK_NOISE_SIGMAS)):
            return 0, a
        if not _falls_past_fit(img, c, a, h, model_step, r_up if model_step < 0 else r_dn,
                               height, noise, reach, hw_dn if model_step < 0 else hw_up):
            return 0, a
        cut_up = model_step < 0
        cut_dn = not cut_up
    # the other flank must be a Gaussian's, no steeper than its own width allows: a flat top
    # between two cliffs (an overexposed colour line's carried-on core through JPEG) is no
    # stripe cut on one side
    if cut_up and fall_dn > _steepest_fall(hw_dn, height, noise, FLANK_NOISE_SIGMAS):
        return 0, a
    if cut_dn and fall_up > _steepest_fall(hw_up, height, noise, FLANK_NOISE_SIGMAS):
        return 0, a
    step = -1 if cut_up else 1
    r_cut = r_up if cut_up else r_dn
    fall = fall_up if cut_up else fall_dn
    # an edge is a step: past it the dark side's stripe falls as the lit side's would, times
    # the dark reflectance; a flank that goes on falling steeply is a flank (the carried-on
    # core of a colour line whose channel clipped)
    r_next = r_cut + 2 * step
    if 0 <= r_next < h and (float(img[r_cut + step, c]) - float(img[r_next, c])
                            > CUT_STEP_RATIO * fall
                            + FLANK_NOISE_SIGMAS * math.sqrt(2.0) * noise):
        return 0, a
    return step, r_cut


@njit(nogil=True, cache=True)
def _foot(img, c, r, h, step, noise, reach):
    """Where the profile, followed from row ``r`` by ``step``, stops falling (by more than
    ``noise`` over two pixels): the mean of that row and the next, DN (NaN at the frame's
    edge)."""
    k = 0
    while (0 <= r + 2 * step < h and k < reach
           and (img[r + step, c] < img[r, c]
                or float(img[r + 2 * step, c]) < float(img[r, c]) - noise)):
        r += step
        k += 1
    if not 0 <= r + step < h:
        return math.nan
    return 0.5 * (float(img[r, c]) + float(img[r + step, c]))


@njit(nogil=True, cache=True)
def _whole_flank_fit(img, c, a, h, step, r_cut, foot, reach, fit, normal):
    """Guo's weighted fit [6] of a parabola to the logarithm of the profile over the whole
    flank's foot (the flank away from ``step``),

        ln(v_r - f) = k0 + k1 x + k2 x^2,  x = r - a,  weights (v_r - f)^2,

    over the pixels from ``r_cut`` to the whole flank's end above ``CUT_RUN_LEVEL`` of the
    height over ``foot`` (``f``, DN: the lit surface's own level, the caller's choice; the
    peak's background, read farther out past the squares, is not it).  Writes ``f, k0, k1,
    k2`` into ``fit`` (4,) and the normal matrix (the weights ``(v_r - f)^2``: a pixel's log
    has the variance ``noise^2 / (v_r - f)^2``, so ``noise^2`` times its inverse is the
    coefficients' covariance) into ``normal`` (3, 3); False when fewer than 3 pixels stand
    above the level or the system is singular."""
    s = -step  # toward the whole flank
    level = foot + CUT_RUN_LEVEL * (float(img[a, c]) - foot)
    lo = min(a, r_cut)
    hi = max(a, r_cut)
    if s > 0:
        while hi < h - 1 and hi - a < reach and float(img[hi + 1, c]) > level:
            hi += 1
    else:
        while lo > 0 and a - lo < reach and float(img[lo - 1, c]) > level:
            lo -= 1
    if hi - lo < 2:
        # a narrow stripe's flank: the next pixel over the foot is its third point
        if s > 0 and hi < h - 1 and float(img[hi + 1, c]) > foot:
            hi += 1
        elif s < 0 and lo > 0 and float(img[lo - 1, c]) > foot:
            lo -= 1
        level = foot
    m = np.zeros((3, 3))
    v = np.zeros(3)
    n = 0
    for rr in range(lo, hi + 1):
        u = float(img[rr, c]) - foot
        if not u > level - foot:
            continue
        x = float(rr - a)
        w = u * u
        y = math.log(u)
        x2 = x * x
        m[0, 0] += w
        m[0, 1] += w * x
        m[0, 2] += w * x2
        m[1, 2] += w * x2 * x
        m[2, 2] += w * x2 * x2
        v[0] += w * y
        v[1] += w * x * y
        v[2] += w * x2 * y
        n += 1
    if n < 3:
        return False
    m[1, 1] = m[0, 2]
    m[1, 0] = m[0, 1]
    m[2, 0] = m[0, 2]
    m[2, 1] = m[1, 2]
    normal[:, :] = m
    if not solve_in_place(m, v):
        return False
    fit[0] = foot
    fit[1] = v[0]
    fit[2] = v[1]
    fit[3] = v[2]
    return True


@njit(nogil=True, cache=True)
def uncut_centre(img, c, a, h, step, r_cut, noise, reach, width, same_foot):
    """Centre of a stripe cut on one flank (``cut_flank``'s ``step`` and ``row``), from its
    other, whole, flank: the vertex ``a - k1 / (2 k2)`` of the parabola fitted to the
    logarithm of that flank (``_whole_flank_fit``) over its foot, where it stops falling (by
    more than ``noise`` over two pixels, ``_foot``), at most ``CUT_FOOT_WIDTHS`` of the
    stripe's ``width`` (its sigma, px; NaN: ``reach``) and a row out.  The centre lies no further
    than half a pixel past the cut (the edge's side of the last lit pixel): where the whole
    flank still rises toward the cut (the centre past the edge, in the dark), the centre is
    put at the edge, where the fit would extrapolate.

    With ``same_foot`` (a colour excess, where a grey texture's squares read alike), the cut
    flank's foot must lie within ``CUT_NOISE_SIGMAS`` of ``noise`` of the whole one's: a
    shoulder beside a bright core (a halo through JPEG) stands on no surface of its own.

    NaN when the fit fails, the parabola opens upward (and the flank falls toward the cut),
    or its vertex leaves ``a`` by more than ``CUT_MAX_SHIFT_PX`` on the whole flank's side, or
    the feet differ.
    """
    foot_reach = reach
    if math.isfinite(width):
        foot_reach = min(reach, int(math.ceil(CUT_FOOT_WIDTHS * width)) + 1)
    foot = _foot(img, c, a, h, -step, noise, foot_reach)
    if not math.isfinite(foot):
        return math.nan
    if same_foot:
        foot_cut = _foot(img, c, r_cut + step, h, step, noise, reach)
        if not abs(foot_cut - foot) <= CUT_NOISE_SIGMAS * noise:
            return math.nan
    return flank_vertex(img, c, a, h, step, r_cut, foot, reach)


@njit(nogil=True, cache=True)
def flank_vertex(img, c, a, h, step, r_cut, foot, reach):
    """Centre of a stripe cut on one flank (the cut past row ``r_cut`` by ``step``), from
    its whole flank over ``foot`` (DN): ``uncut_centre`` with the foot given, the edge where
    the flank still rises toward it.  NaN when the fit fails, the parabola opens upward, or
    its vertex leaves ``a`` by more than ``CUT_MAX_SHIFT_PX``."""
    fit = np.empty(4)
    if not _whole_flank_fit(img, c, a, h, step, r_cut, foot, reach, fit, np.empty((3, 3))):
        return math.nan
    k1 = fit[2]
    k2 = fit[3]
    # the flank still rising toward the cut where it ends (the centre past it, in the dark):
    # the centre is at the edge
    edge = r_cut + 0.5 * step
    if k1 * step > 0.0 and (k2 >= 0.0 or -k1 / (2.0 * k2) * step > (edge - a) * step):
        return edge if abs(edge - a) <= CUT_MAX_SHIFT_PX else math.nan
    if not k2 < 0.0:
        return math.nan
    off = -k1 / (2.0 * k2)
    if not abs(off) <= CUT_MAX_SHIFT_PX:
        return math.nan
    return a + off


@njit(nogil=True, cache=True)
def _two_pixel_flank(img, c, a, h, step, noise, reach, out):
    """The whole flank from row ``a`` by ``step`` where it is two pixels above its foot: the
    argmax and the next over ``CUT_RUN_LEVEL`` of the height, the one after under it.  Writes
    the foot (``_foot``, DN) and the two pixels over it into ``out`` (3,); False otherwise."""
    if not (0 <= a + 2 * step < h and 0 <= a - step < h):
        return False
    foot = _foot(img, c, a, h, step, noise, reach)
    if not math.isfinite(foot):
        return False
    u0 = float(img[a, c]) - foot
    u1 = float(img[a + step, c]) - foot
    if not (u0 >= u1 > CUT_RUN_LEVEL * u0
            and float(img[a + 2 * step, c]) - foot <= CUT_RUN_LEVEL * u0):
        return False
    out[0] = foot
    out[1] = u0
    out[2] = u1
    return True


@njit(nogil=True, cache=True)
def narrow_cut(img, c, a, h, bg, noise, reach, min_width):
    """Which flank of a narrow peak at ``a``, if one, a texture's edge cuts next to the argmax,
    where ``cut_flank`` finds none (its whole flank's fit needs three pixels).

    The three pixels about the argmax, over the whole flank's foot ``f``, the cut side's read
    ``NARROW_CUT_NOISE_SIGMAS`` of ``noise`` high (``u_c``), bound the width of a Gaussian
    through them: ``1 / sigma^2 = ln(u_0 / u_w) + ln(u_0 / u_c)``, the same for any centre.
    Under ``min_width`` (px), and with the cut side's foot under the whole side's by
    ``CUT_SURFACES_SIGMAS`` of noise (two surfaces: a dark square past the cut) and the whole
    side's foot within ``NARROW_CUT_FOOT`` of the height over ``bg``, the stripe is cut.

    Returns the cut side: -1 toward row 0, +1 the other, 0 none (both: the narrower bound).
    """
    height = float(img[a, c]) - bg
    if not height > 0.0:
        return 0
    flank = np.empty(3)
    best = min_width
    side = 0
    for cut in (-1, 1):
        if not _two_pixel_flank(img, c, a, h, -cut, noise, reach, flank):
            continue
        foot, u0, u1 = flank[0], flank[1], flank[2]
        if not foot - bg <= NARROW_CUT_FOOT * height:
            continue
        if not _foot(img, c, a + cut, h, cut, noise, reach) < foot - CUT_SURFACES_SIGMAS * noise:
            continue
        uc = float(img[a + cut, c]) - foot + NARROW_CUT_NOISE_SIGMAS * noise
        inverse = math.log(u0 / u1) + (math.log(u0 / uc) if uc > 0.0 else math.inf)
        if inverse > 0.0 and 1.0 / math.sqrt(inverse) < best:
            best = 1.0 / math.sqrt(inverse)
            side = cut
    return side


@njit(nogil=True, cache=True)
def narrow_cut_centre(img, c, a, h, cut, sigma, noise, reach):
    """Centre of a narrow stripe cut next to its argmax (``narrow_cut``'s side ``cut``) from its
    two whole pixels and a width ``sigma`` (px) taken elsewhere (the stripe's beside it):

        y = a - cut / 2 + cut sigma^2 ln(u_0 / u_w),

    the Gaussian of that width through both, no further than the edge (``a + cut / 2``).  NaN
    where the flank is not two pixels over its foot."""
    flank = np.empty(3)
    if not _two_pixel_flank(img, c, a, h, -cut, noise, reach, flank):
        return math.nan
    y = a - 0.5 * cut + cut * sigma * sigma * math.log(flank[1] / flank[2])
    edge = a + 0.5 * cut
    return edge if (y - edge) * cut > 0.0 else y
