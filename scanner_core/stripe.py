"""Sub-pixel laser-stripe extraction, one estimate per image column.

The stripe runs roughly along the image rows; in each column its cross-section is a narrow peak
(Gaussian, sigma ~1.5 px).  ``extract`` finds, per column, the brightest pixel and refines its row
to sub-pixel precision with one of several classic estimators, flagging (never guessing) columns
where no trustworthy peak exists.

Speed.  Every method is one numba kernel over the whole frame in two stages:

1. one row-major pass over the image keeping, per column, the running maximum (uint8), its row
   (uint16: the narrow index type is what lets LLVM vectorise the loop) and the largest value seen
   farther than ``2 * window`` rows below the current maximum (for the double-peak test), all
   branch-free;
2. per column, a few pixel reads around the argmax for the sub-pixel refinement.

Conventions: ``image`` is ``(H, W)`` uint8, rows down, pixel centres at integer coordinates;
results are per column, rows in px, intensities in DN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from scanner_core._linsolve import solve_in_place
from scanner_core.validate import check_columns, check_image

__all__ = ["METHODS", "StripeResult", "extract", "Reason"]

METHODS = ("cog", "gaussian3", "parabola", "blais_rioux", "lsq_gauss")
_METHOD_CODE = {name: i for i, name in enumerate(METHODS)}

# Pixel value taken as saturated (uint8 full scale).
SATURATION_DN = 255
# A second local maximum counts as a second stripe when it reaches this fraction of the peak.
DOUBLE_PEAK_RATIO = 0.3
# Sigma-like widths below this are isolated noise spikes, not a stripe (a Gaussian stripe
# sampled at 1 px has sigma >= ~0.5 px to be resolved at all).
MIN_WIDTH_PX = 0.5
# A stripe must have at least this many pixels above the threshold within +-window of its
# argmax; rejects isolated noise pixels (the reference stripe has 7, a lone spike 1).
MIN_PIXELS_ABOVE = 3
# FWHM of a Gaussian in sigmas: 2 sqrt(2 ln 2).
FWHM_PER_SIGMA = 2.3548200450309493
# Gauss-Newton iterations of the least-squares Gaussian fit (converges in 3-4 from the centroid).
LSQ_ITERATIONS = 6
# The least-squares fit is rejected if its centre leaves the argmax by more than this (px).
LSQ_MAX_SHIFT_PX = 1.5


class Reason:
    """Codes of ``StripeResult.reason`` (uint8): why a column is invalid."""

    OK = 0
    NO_PEAK = 1  # no pixel above the threshold
    SATURATED = 2  # peak pixel at full scale (255): the centre is not measurable
    DOUBLE = 3  # a second, separated peak of >= DOUBLE_PEAK_RATIO of the main one
    TOO_WIDE = 4  # width > max_width
    TOO_NARROW = 5  # width < min_width or < MIN_PIXELS_ABOVE pixels above threshold: noise
    FIT_FAILED = 6  # sub-pixel refinement degenerate (flat top, diverged fit, no zero crossing)
    NOT_PROCESSED = 7  # outside ``columns``


@dataclass(frozen=True)
class StripeResult:
    """Per-column stripe measurement of one frame.

    Attributes
    ----------
    row : (W,) float32
        Sub-pixel row of the stripe centre, px (pixel centres at integers); NaN where invalid.
    peak : (W,) float32
        Maximum pixel value in the column, DN; NaN outside the processed columns.
    width : (W,) float32
        Sigma-like width of the peak, px: the full width at half height above the threshold
        (linearly interpolated) divided by 2.3548; NaN where not measured.
    valid : (W,) bool
        True where ``row`` holds a trustworthy estimate.
    reason : (W,) uint8
        ``Reason`` code, ``Reason.OK`` where valid.
    """

    row: np.ndarray
    peak: np.ndarray
    width: np.ndarray
    valid: np.ndarray
    reason: np.ndarray


def _check_image(image) -> np.ndarray:
    img = check_image(image)
    if img.shape[0] > 65535:  # row indices are kept as uint16 for speed (NOTES.md)
        raise ValueError(f"`image` must have at most 65535 rows, got {img.shape[0]}")
    return img


def _check_columns(columns, width: int) -> tuple[int, int]:
    return (0, width) if columns is None else check_columns(columns, width, allow_empty=True)


def extract(image, method="cog", *, threshold=20.0, window=4, max_width=4.0, columns=None,
            **params) -> StripeResult:
    """Sub-pixel row of the laser stripe in every column of a frame.

    Parameters
    ----------
    image : (H, W) uint8
        Camera frame, DN.  ``H <= 65535``.
    method : str
        One of ``METHODS``:

        - ``"cog"``: windowed centre of gravity, rows within ``+-window`` of the argmax, weights
          ``v - threshold`` for pixels above the threshold [1]_.  Subtracting the threshold
          (rather than the background) measured best on the reference model (see
          ``background`` below).
        - ``"gaussian3"``: 3-point Gaussian (parabola through the logarithms) [1]_, [2]_.
        - ``"parabola"``: 3-point parabola through the argmax and its neighbours [1]_.
        - ``"blais_rioux"``: zero crossing of the 4th-order derivative filter
          ``g(i) = f(i-2) + f(i-1) - f(i+1) - f(i+2)``, linearly interpolated [3]_.
        - ``"lsq_gauss"``: least-squares fit of ``b + A exp(-(r - mu)^2 / (2 s^2))`` to the
          ``+-window`` rows by Gauss-Newton from the centroid; reaches the Cramer-Rao bound for
          white noise [4]_.
    threshold : float
        DN; a column needs a pixel above it to hold a stripe.
    window : int
        Half-size (rows) of the neighbourhood of the argmax used by ``cog`` and ``lsq_gauss``;
        a second peak counts as separate beyond ``2 * window`` rows.
    max_width : float
        Largest accepted sigma-like width, px.
    columns : (int, int), optional
        Process only columns ``c0 <= c < c1``; the others are returned invalid
        (``Reason.NOT_PROCESSED``).
    **params
        ``min_width`` (float, px, default ``MIN_WIDTH_PX``): smallest accepted width.
        ``double_ratio`` (float, default ``DOUBLE_PEAK_RATIO``).
        ``background`` (float, DN, default None): for ``cog``, subtract this level instead of the
        threshold (pixels above the threshold only); for ``gaussian3`` the level subtracted
        before the logarithms (default 0).  On the reference model (background 10 DN, noise
        3 DN, 15 k columns) ``cog`` gave 0.026 px RMS subtracting the threshold (20 DN) vs
        0.038 px subtracting the true background (10 DN), both with |bias| < 0.001 px: the
        threshold offset down-weights the noisy flanks.  ``gaussian3`` gave 0.038 px either way.

    Returns
    -------
    StripeResult
        ``row``, ``peak``, ``width`` (W,) float32, ``valid`` (W,) bool, ``reason`` (W,) uint8.

    Raises
    ------
    ValueError
        If ``image`` is not 2-D uint8, ``method`` is unknown, or an option is out of range.

    Notes
    -----
    Validity (flagged, never guessed): no pixel above ``threshold``; peak pixel at 255
    (saturation: since the argmax is in the window, "any pixel at 255 in the window" is the same
    test); a second maximum farther than ``2 * window`` rows from the main one, above the
    threshold and at least ``double_ratio`` of the peak (tracked in the single pass; exact for
    stripes with sigma below ``2 * window / 5`` px); width outside ``[min_width, max_width]`` or
    fewer than ``MIN_PIXELS_ABOVE`` pixels above the threshold within ``+-window`` (isolated
    noise pixels);
    degenerate refinement.

    References
    ----------
    .. [1] R. B. Fisher and D. K. Naidu, "A comparison of algorithms for subpixel peak
       detection", in *Image Technology*, Springer, 1996, pp. 385-404.
    .. [2] D. K. Naidu and R. B. Fisher, "A comparative analysis of algorithms for determining
       the peak position of a stripe to sub-pixel accuracy", Proc. BMVC 1991, pp. 217-225.
    .. [3] F. Blais and M. Rioux, "Real-time numerical peak detector", *Signal Processing* 11(2),
       pp. 145-155, 1986.
    .. [4] S. M. Kay, *Fundamentals of Statistical Signal Processing: Estimation Theory*,
       Prentice Hall, 1993, ch. 3 and 7.
    """
    img = _check_image(image)
    if method not in _METHOD_CODE:
        raise ValueError(f"`method` must be one of {METHODS}, got {method!r}")
    window = int(window)
    if window < 2:
        raise ValueError(f"`window` must be >= 2, got {window}")
    if not max_width > 0:
        raise ValueError(f"`max_width` must be > 0, got {max_width}")
    unknown = set(params) - {"min_width", "double_ratio", "background"}
    if unknown:
        raise ValueError(f"unknown parameter(s) {sorted(unknown)}")
    min_width = float(params.get("min_width", MIN_WIDTH_PX))
    double_ratio = float(params.get("double_ratio", DOUBLE_PEAK_RATIO))
    background = params.get("background")
    bg = math.nan if background is None else float(background)
    c0, c1 = _check_columns(columns, img.shape[1])
    w = img.shape[1]
    row = np.full(w, np.nan, np.float32)
    peak = np.full(w, np.nan, np.float32)
    width = np.full(w, np.nan, np.float32)
    reason = np.full(w, Reason.NOT_PROCESSED, np.uint8)
    _extract_kernel(img, c0, c1, _METHOD_CODE[method], float(threshold), window,
                    float(max_width), min_width, double_ratio, bg, row, peak, width, reason)
    return StripeResult(row=row, peak=peak, width=width, valid=reason == Reason.OK, reason=reason)


# ----------------------------------------------------------------------------------------------
# kernels


@njit(nogil=True, cache=True)
def _column_max(img, c0, c1, sep, mx, am, sec):
    """Row-major pass: per-column max (uint8), its row (uint16), far second max (uint8).

    ``sec`` holds the largest value seen more than ``sep`` rows from the running argmax at the
    time it was seen (the old maximum is demoted into it when a new maximum appears far away).
    Rows ascend, so ``r - am >= 0``.  Branch-free so that the loop vectorises.
    """
    h = img.shape[0]
    n = c1 - c0
    for r in range(h):
        r16 = np.uint16(r)
        # r - a > sep  <=>  a < r - sep: a uint16 compare (no widening, so it vectorises)
        lim16 = np.uint16(max(r - sep, 0))
        row = img[r, c0:c1]
        for j in range(n):
            v = row[j]
            m = mx[j]
            a = am[j]
            far = a < lim16
            lo = min(m, v)
            s = sec[j]
            sec[j] = max(s, lo) if far else s
            am[j] = r16 if v > m else a
            mx[j] = max(m, v)


@njit(nogil=True, cache=True)
def _fwhm_width(col_img, c, a, h, level, max_walk):
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
def _count_above(img, c, a, h, threshold, window):
    k = 0
    for r in range(max(a - window, 0), min(a + window, h - 1) + 1):
        if img[r, c] > threshold:
            k += 1
    return k


@njit(nogil=True, cache=True)
def _cog(img, c, a, h, threshold, window, bg):
    """Windowed centre of gravity, Fisher & Naidu Eq. (CoG): sum(r w) / sum(w)."""
    off = threshold if math.isnan(bg) else bg
    s0 = 0.0
    s1 = 0.0
    for r in range(max(a - window, 0), min(a + window, h - 1) + 1):
        v = float(img[r, c])
        if v > threshold:
            wgt = v - off
            s0 += wgt
            s1 += wgt * (r - a)
    if s0 <= 0.0:
        return math.nan
    return a + s1 / s0


@njit(nogil=True, cache=True)
def _three_points(img, c, a, h):
    if a == 0 or a == h - 1:
        return math.nan, math.nan, math.nan
    return float(img[a - 1, c]), float(img[a, c]), float(img[a + 1, c])


@njit(nogil=True, cache=True)
def _parabola(img, c, a, h):
    ym, y0, yp = _three_points(img, c, a, h)
    den = ym - 2.0 * y0 + yp
    if not den < 0.0:  # flat top or NaN: no curvature, no centre
        return math.nan
    return a + 0.5 * (ym - yp) / den


@njit(nogil=True, cache=True)
def _gaussian3(img, c, a, h, bg):
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
def _blais_rioux(img, c, a, h):
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
def _lsq_gauss(img, c, a, h, threshold, window, mu0, s0):
    """Gauss-Newton fit of b + A exp(-(x - mu)^2 / (2 s^2)) on rows a +- window.

    Coordinates are centred on the argmax (x = r - a) and intensities scaled by the peak, so the
    normal equations are well conditioned.  Returns NaN when the fit degenerates.
    """
    r0 = max(a - window, 0)
    r1 = min(a + window, h - 1)
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
    s = min(max(s0, 0.7), 3.0)
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
        if not (amp > 0.0 and s > 0.0 and abs(mu) <= LSQ_MAX_SHIFT_PX):
            return math.nan
    return a + mu


@njit(nogil=True, cache=True)
def _extract_kernel(img, c0, c1, method, threshold, window, max_width, min_width, double_ratio,
                    bg, row, peak, width, reason):
    h = img.shape[0]
    n = c1 - c0
    mx = np.zeros(n, np.uint8)
    am = np.zeros(n, np.uint16)
    sec = np.zeros(n, np.uint8)
    _column_max(img, c0, c1, 2 * window, mx, am, sec)
    max_walk = int(math.ceil(max_width * FWHM_PER_SIGMA)) + 2
    for j in range(n):
        c = c0 + j
        p = float(mx[j])
        a = int(am[j])
        peak[c] = p
        if not p > threshold:
            reason[c] = 1  # NO_PEAK
            continue
        if mx[j] >= SATURATION_DN:
            reason[c] = 2  # SATURATED
            continue
        wd = _fwhm_width(img, c, a, h, 0.5 * (p + threshold), max_walk)
        width[c] = wd
        if wd > max_width:
            reason[c] = 4  # TOO_WIDE
            continue
        sv = float(sec[j])
        if sv > threshold and sv >= double_ratio * p:
            reason[c] = 3  # DOUBLE
            continue
        if wd < min_width or _count_above(img, c, a, h, threshold, window) < MIN_PIXELS_ABOVE:
            reason[c] = 5  # TOO_NARROW
            continue
        if method == 0:
            y = _cog(img, c, a, h, threshold, window, bg)
        elif method == 1:
            y = _gaussian3(img, c, a, h, bg)
        elif method == 2:
            y = _parabola(img, c, a, h)
        elif method == 3:
            y = _blais_rioux(img, c, a, h)
        else:
            y0 = _cog(img, c, a, h, threshold, window, math.nan)
            y = _lsq_gauss(img, c, a, h, threshold, window, y0, wd) if math.isfinite(y0) else y0
        if not math.isfinite(y):
            reason[c] = 6  # FIT_FAILED
            continue
        row[c] = y
        reason[c] = 0
