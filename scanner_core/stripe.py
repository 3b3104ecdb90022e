"""Sub-pixel laser-stripe extraction, one estimate per image column.

The stripe runs roughly along the image rows; in each column its cross-section is a narrow peak
(Gaussian, sigma ~1.5 px).  ``extract`` finds, per column, up to two candidate peaks (the
brightest pixel and the brightest one well separated from it), picks one by a selection policy,
and refines its row to sub-pixel precision with one of several classic estimators, flagging
(never guessing) columns where no trustworthy peak exists.  Real surfaces are handled as
industrial profilers do: a clipped (saturated) plateau is still measured, a reflection beside the
stripe is resolved by a policy (strongest, nearest to an expected row, continuity with the
neighbouring columns), a geometric window excludes rows the inspection volume cannot produce,
and the floors can follow the frame's own noise (dark surfaces).

Speed.  Every method is one numba kernel over the whole frame in three stages:

1. one row-major pass over the image keeping, per column, the running maximum (uint8), its row
   (uint16: the narrow index type is what lets LLVM vectorise the loop), the largest value seen
   farther than ``2 * window`` rows from the current maximum and its row, all branch-free;
2. a robust estimate of the background and its noise (median and interquartile range of a
   sparse subsample of pixels, from a 256-bin histogram);
3. per column, the choice between the candidates and a few pixel reads around the chosen one for
   the sub-pixel refinement.

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

__all__ = ["METHODS", "POLICIES", "StripeResult", "extract", "Reason", "estimate_noise"]

METHODS = ("cog", "gaussian3", "parabola", "blais_rioux", "lsq_gauss")
_METHOD_CODE = {name: i for i, name in enumerate(METHODS)}
#: Peak selection policies (see ``extract``); "reject" is the historical behaviour.
POLICIES = ("strongest", "nearest", "continuity", "reject")
_POLICY_CODE = {name: i for i, name in enumerate(POLICIES)}

# Pixel value taken as saturated (uint8 full scale).
SATURATION_DN = 255
# A second local maximum counts as a second candidate peak when it reaches this fraction of the
# main one (weaker ones are ignored: a faint reflection never competes with the stripe).
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

# --- noise-derived floors (threshold="auto")
# Subsample of the noise estimate: a run of NOISE_RUN_PX contiguous pixels in every
# NOISE_ROW_STEP-th row (75 x 64 = 4800 pixels of a 1920 x 1200 frame, ~5 us: the median to
# ~0.05 sigma, the noise to ~3 %); the stripe's ~0.6 % of the rows moves the quartiles by
# ~0.02 sigma.
NOISE_ROW_STEP = 16
NOISE_RUN_PX = 64
# Median minus lower quartile of a normal distribution in sigmas: Phi^-1(0.75).
HALF_IQR_PER_SIGMA = 0.6744897501960817
# The saturated-peak fit uses the unclipped samples above background + this many noise sigmas:
# low samples weigh little ((v - b)^2 weights) but keep the fit determined when the flanks are
# steep (at 10x full scale only one sample per flank clears a 20 DN threshold).
SAT_FIT_MIN_SIGMAS = 2.0
# Smallest noise accepted (DN): below it the floors would sit within the 1 DN quantisation.
MIN_NOISE_DN = 1.0
# threshold = background + AUTO_THRESHOLD_SIGMAS * noise: 3.33 reproduces the fixed 20 DN on the
# reference model (background 10, noise 3), where it measured best for ``cog``.
AUTO_THRESHOLD_SIGMAS = 10.0 / 3.0
# A candidate peak must reach background + AUTO_MIN_PEAK_SIGMAS * noise in "auto" mode: the
# largest of 1200 normal noise samples is ~3.2 sigma, so 5 sigma leaves ~3e-7 false peaks per
# pixel, which the MIN_PIXELS_ABOVE and width tests then reject.
AUTO_MIN_PEAK_SIGMAS = 5.0

# With threshold="auto", ``cog`` weighs ``v - t`` above a level ``t`` of its own per column:
# background + max(AUTO_COG_SIGMAS * noise, AUTO_COG_PEAK_FRACTION * (peak - background)).
# On bright stripes the second term rules (10 DN on a 200 DN stripe: the 20 DN that measured best
# on the reference model); on dim ones the first (measured on 30 DN over 3 DN, RMS: 0.1495 px
# at 20 DN, 0.1468 at 18.5, 0.1472 at 17, against a Cramer-Rao bound of 0.130).
AUTO_COG_SIGMAS = 2.8
AUTO_COG_PEAK_FRACTION = 0.05

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


class Reason:
    """Codes of ``StripeResult.reason`` (uint8): why a column is invalid."""

    OK = 0
    NO_PEAK = 1  # no pixel above the threshold (or, with threshold="auto", below the peak floor)
    SATURATED = 2  # peak at full scale and saturation="reject"
    DOUBLE = 3  # a second, separated peak of >= double_ratio of the main one, policy="reject"
    TOO_WIDE = 4  # width > max_width
    TOO_NARROW = 5  # width < min_width or < MIN_PIXELS_ABOVE pixels above threshold: noise
    FIT_FAILED = 6  # sub-pixel refinement degenerate (flat top, diverged fit, no zero crossing)
    NOT_PROCESSED = 7  # outside ``columns``
    OUTSIDE_WINDOW = 8  # a peak exists only outside [row_min, row_max]: never the stripe


@dataclass(frozen=True)
class StripeResult:
    """Per-column stripe measurement of one frame.

    Attributes
    ----------
    row : (W,) float32
        Sub-pixel row of the stripe centre, px (pixel centres at integers); NaN where invalid.
    peak : (W,) float32
        Maximum pixel value of the chosen peak, DN (the column's maximum when the strongest
        candidate is chosen, always so on a single stripe); NaN outside the processed columns.
    width : (W,) float32
        Sigma-like width of the peak, px: the full width at half height above the threshold
        (linearly interpolated) divided by 2.3548; NaN where not measured.  For a saturated
        peak, the width at half of full scale (a lower bound of the stripe's).
    valid : (W,) bool
        True where ``row`` holds a trustworthy estimate.
    reason : (W,) uint8
        ``Reason`` code, ``Reason.OK`` where valid.
    saturated : (W,) bool
        The chosen peak reaches full scale (255): its centre comes from the plateau's flanks
        (see ``extract``); trust it less than an unclipped one.
    snr : (W,) float32
        Peak signal-to-noise ratio ``(peak - background_dn) / noise_dn`` of the chosen peak
        (a lower bound where saturated); NaN outside the processed columns.
    n_peaks : (W,) uint8
        Candidate peaks found (0, 1 or 2): 2 means another peak of at least ``double_ratio``
        of the main one lies farther than ``2 * window`` rows away (a reflection, or the stripe
        if the chosen one is the reflection).
    background_dn, noise_dn : float
        Robust background level and noise (sigma) of the frame, DN (``estimate_noise``).
    """

    row: np.ndarray
    peak: np.ndarray
    width: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    saturated: np.ndarray
    snr: np.ndarray
    n_peaks: np.ndarray
    background_dn: float
    noise_dn: float


def _check_image(image) -> np.ndarray:
    img = check_image(image)
    if img.shape[0] > 65535:  # row indices are kept as uint16 for speed (NOTES.md)
        raise ValueError(f"`image` must have at most 65535 rows, got {img.shape[0]}")
    return img


def _check_columns(columns, width: int) -> tuple[int, int]:
    return (0, width) if columns is None else check_columns(columns, width, allow_empty=True)


def _per_column(name, value, width, default):
    """A per-column float64 array from a scalar, (W,) array or None (-> ``default``)."""
    if value is None:
        return np.full(width, default, np.float64)
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        return np.full(width, float(arr), np.float64)
    if arr.shape != (width,):
        raise ValueError(f"`{name}` must be a scalar or have shape ({width},), got {arr.shape}")
    return np.ascontiguousarray(arr)


def isolated_runs(row, valid, *, max_jump_px=20.0, min_run=3, max_gap=2) -> np.ndarray:
    """Columns whose stripe is a short run contradicted by a longer stripe beside it.

    A run is a stretch of valid columns, each within ``max_jump_px`` rows of the previous.
    A run of fewer than ``min_run`` columns is isolated when a valid column at most ``max_gap``
    columns away on either side belongs to a run of at least ``min_run`` columns: the surface
    cannot be in two places that close, so the short run is a reflection or a glint that won
    its column where the true stripe is too dim to compete (on a shiny part, the laser
    mirrored onto another face: measured 64 mm off in the cloud). A short run with no long
    run beside it (a thin rib between drop-outs) is kept.

    Parameters
    ----------
    row : (W,) float
        Stripe row per column, px.
    valid : (W,) bool
    max_jump_px : float
        Largest row step within a run: 20 px passes surfaces up to ~87 degrees from facing
        the camera in the reference cell, while a reflection lands tens to hundreds of rows away.
    min_run : int
    max_gap : int

    Returns
    -------
    (W,) bool
        True for the columns to drop.
    """
    row = np.asarray(row, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    cols = np.flatnonzero(valid)
    out = np.zeros(len(valid), dtype=bool)
    if len(cols) == 0 or min_run <= 1:
        return out
    r = row[cols]
    breaks = (np.diff(cols) > 1) | (np.abs(np.diff(r)) > max_jump_px)
    run_id = np.concatenate([[0], np.cumsum(breaks)])
    length = np.bincount(run_id)[run_id]
    short = length < min_run
    if not short.any():
        return out
    # For each valid column, is its predecessor / successor (in valid order) close enough in
    # columns and in a long run? A short run is judged by its ends.
    prev_long = np.zeros(len(cols), dtype=bool)
    next_long = np.zeros(len(cols), dtype=bool)
    near = np.diff(cols) <= max_gap + 1
    other = run_id[1:] != run_id[:-1]
    prev_long[1:] = near & other & ~short[:-1]
    next_long[:-1] = near & other & ~short[1:]
    contradicted = np.zeros(run_id[-1] + 1, dtype=bool)
    np.logical_or.at(contradicted, run_id, (prev_long | next_long) & short)
    out[cols[contradicted[run_id] & short]] = True
    return out


def estimate_noise(image) -> tuple[float, float]:
    """Robust background level and noise of a frame from a sparse subsample of its pixels.

    A run of ``NOISE_RUN_PX`` pixels in every ``NOISE_ROW_STEP``-th row (the runs spread over
    the width) is histogrammed; the background is the median and the noise
    (median - lower quartile) / 0.6745, the sigma of a normal distribution with that spread (the
    lower half because stripe and marker pixels are all bright), both read off the histogram
    with linear interpolation inside the integer bins (grouped-data quantiles), so that a 3 DN
    noise is not quantised to whole DN.  The stripe covers well under 1 % of the rows and
    barely moves the quartiles; a smooth ambient gradient widens the spread and raises the
    floors, which is the safe side.

    Parameters
    ----------
    image : (H, W) uint8

    Returns
    -------
    background_dn, noise_dn : float
        DN; ``noise_dn >= MIN_NOISE_DN``.
    """
    img = _check_image(image)
    return _noise_estimate(img)


def extract(image, method="cog", *, threshold=20.0, window=4, max_width=4.0, columns=None,
            policy="continuity", expected_row=None, row_min=None, row_max=None,
            saturation="fit", **params) -> StripeResult:
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

        A saturated peak is measured the same way whatever the method (``saturation``).
    threshold : float or "auto"
        DN; a column needs a pixel above it to hold a stripe.  ``"auto"``: set from the frame's
        noise (``estimate_noise``): ``background + AUTO_THRESHOLD_SIGMAS * noise`` (20 DN on the
        reference model), and every candidate peak must also reach
        ``background + AUTO_MIN_PEAK_SIGMAS * noise`` (else ``Reason.NO_PEAK``); ``cog`` weighs
        above a level of its own per column (``AUTO_COG_*``: lower on dim stripes).  Dark
        surfaces then keep their stripe; ``snr`` says how far to trust it.  Measured on a 30 DN
        stripe over 3 DN of noise (``flyscan bench stripe``): 99.9 % of the columns, 0.147 px
        RMS (``cog``), 0.135 (``lsq_gauss``); Cramer-Rao bound 0.130 px.
    window : int
        Half-size (rows) of the neighbourhood of the argmax used by ``cog`` and ``lsq_gauss``;
        a second peak counts as separate beyond ``2 * window`` rows.
    max_width : float
        Largest accepted sigma-like width, px.
    columns : (int, int), optional
        Process only columns ``c0 <= c < c1``; the others are returned invalid
        (``Reason.NOT_PROCESSED``).
    policy : str
        Which candidate is the stripe when a column holds two (one of ``POLICIES``):

        - ``"strongest"``: the brightest (LMI's "best").
        - ``"nearest"``: the one nearest to ``expected_row`` (the strongest where that is NaN).
        - ``"continuity"`` (default): the path through the columns minimising the row jumps
          between neighbouring columns plus a brightness cost (a Viterbi pass over two states
          per column [5]_; ``CONTINUITY_*`` constants), plus the distance to ``expected_row``
          (e.g. the previous profile) when given.  Measured (tests/scanner_core/
          test_stripe_surfaces.py, ``flyscan bench stripe``): under a reflection at half the
          stripe's brightness 20-40 rows away it keeps 100 % of the columns on the stripe, as
          ``"strongest"`` does, whether the stripe is smooth or jumps at random between columns;
          unlike ``"strongest"`` it bridges glints brighter than the stripe over one or two
          columns (100 % / 95 % vs 80 % of the columns on the stripe), and longer ones with
          ``expected_row``.  It costs nothing on frames without a second peak (the pass is
          skipped) and ~10 us per frame with one.
        - ``"reject"``: the historical behaviour, the column is flagged ``Reason.DOUBLE``.
    expected_row : float or (W,) float, optional
        Expected stripe row per column, px (NaN: no expectation), for ``"nearest"`` and
        ``"continuity"``.
    row_min, row_max : float or (W,) float, optional
        Geometric window: per column, the rows the inspection volume can produce (from the
        calibration); a peak outside ``[row_min, row_max]`` is never the stripe.  A column whose
        only peak lies outside is flagged ``Reason.OUTSIDE_WINDOW``.  Only the columns whose
        maximum lies outside are searched again (inside it), so a frame without a reflection
        out there costs what the plain pass does.
    saturation : str
        ``"fit"`` (default): a peak that reaches 255 is measured from the unclipped samples of
        its flanks, treating the clipped ones as censored: a weighted least-squares parabola
        through ``ln(v - background)`` (the logarithm of a Gaussian is a parabola; weights
        ``(v - background)^2`` make the residuals' variance uniform [6]_), centre
        ``-b / (2 c)``; the column stays valid with ``saturated`` True.  ``"reject"``: flagged
        ``Reason.SATURATED`` (historical).
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
        ``row``, ``peak``, ``width``, ``snr`` (W,) float32, ``valid``, ``saturated`` (W,) bool,
        ``reason``, ``n_peaks`` (W,) uint8, ``background_dn``, ``noise_dn`` float.

    Raises
    ------
    ValueError
        If ``image`` is not 2-D uint8, ``method`` or ``policy`` is unknown, or an option is out of
        range.

    Notes
    -----
    Validity (flagged, never guessed): no pixel above ``threshold``; peak only outside the
    geometric window; peak at 255 with ``saturation="reject"``; with ``policy="reject"`` a second
    maximum farther than ``2 * window`` rows from the main one, above the threshold and at least
    ``double_ratio`` of the peak (tracked in the single pass; exact for stripes with sigma below
    ``2 * window / 5`` px); width outside ``[min_width, max_width]`` or fewer than
    ``MIN_PIXELS_ABOVE`` pixels above the threshold within ``+-window`` (isolated noise pixels);
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
    .. [5] G. D. Forney, "The Viterbi algorithm", *Proc. IEEE* 61(3), pp. 268-278, 1973.
    .. [6] H. Guo, "A simple algorithm for fitting a Gaussian function", *IEEE Signal Processing
       Magazine* 28(5), pp. 134-137, 2011.
    """
    img = _check_image(image)
    if method not in _METHOD_CODE:
        raise ValueError(f"`method` must be one of {METHODS}, got {method!r}")
    if policy not in _POLICY_CODE:
        raise ValueError(f"`policy` must be one of {POLICIES}, got {policy!r}")
    if saturation not in ("fit", "reject"):
        raise ValueError(f"`saturation` must be 'fit' or 'reject', got {saturation!r}")
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
    h, w = img.shape
    if isinstance(threshold, str):
        if threshold != "auto":
            raise ValueError(f"`threshold` must be a number or 'auto', got {threshold!r}")
        auto = True
        thr = math.nan
    else:
        auto = False
        thr = float(threshold)
    expected = _per_column("expected_row", expected_row, w, math.nan)
    use_window = row_min is not None or row_max is not None
    if use_window:
        lo = np.clip(np.ceil(_per_column("row_min", row_min, w, 0.0)), 0, 65535)
        hi = np.clip(np.floor(_per_column("row_max", row_max, w, h - 1.0)), 0, 65535)
        if np.isnan(lo).any() or np.isnan(hi).any():
            raise ValueError("`row_min` and `row_max` must not be NaN")
        rmin, rmax = lo.astype(np.uint16), hi.astype(np.uint16)
    else:
        rmin = rmax = np.zeros(0, np.uint16)
    row = np.full(w, np.nan, np.float32)
    peak = np.full(w, np.nan, np.float32)
    width = np.full(w, np.nan, np.float32)
    snr = np.full(w, np.nan, np.float32)
    reason = np.full(w, Reason.NOT_PROCESSED, np.uint8)
    saturated = np.zeros(w, np.bool_)
    n_peaks = np.zeros(w, np.uint8)
    noise = np.zeros(2)
    _extract_kernel(img, c0, c1, _METHOD_CODE[method], auto, thr, window, float(max_width),
                    min_width, double_ratio, bg, _POLICY_CODE[policy], expected, use_window,
                    rmin, rmax, saturation == "fit", row, peak, width, reason, saturated, snr,
                    n_peaks, noise)
    return StripeResult(row=row, peak=peak, width=width, valid=reason == Reason.OK, reason=reason,
                        saturated=saturated, snr=snr, n_peaks=n_peaks,
                        background_dn=float(noise[0]), noise_dn=float(noise[1]))


# ----------------------------------------------------------------------------------------------
# kernels


@njit(nogil=True, cache=True)
def _quantile_from_hist(hist, total, p):
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
def _noise_estimate(img):
    """(median, (median - lower quartile) / 0.6745) of a sparse subsample, DN; see
    ``estimate_noise``."""
    h, w = img.shape
    hist = np.zeros(256, np.int64)
    run = min(NOISE_RUN_PX, w)
    k = 0
    for r in range(NOISE_ROW_STEP // 2, h, NOISE_ROW_STEP):
        # one contiguous run per sampled row (two cache lines: scattered single pixels would
        # each cost a cache miss), its start stepping across the width by the golden ratio
        c_start = int(((k * 0.6180339887498949) % 1.0) * (w - run + 1))
        k += 1
        for c in range(c_start, c_start + run):
            hist[img[r, c]] += 1
    total = float(hist.sum())
    if total == 0.0:  # frames smaller than one step: every pixel
        for r in range(h):
            for c in range(w):
                hist[img[r, c]] += 1
        total = float(hist.sum())
    med = _quantile_from_hist(hist, total, 0.5)
    # the lower half only: every stripe or marker pixel in the sample is bright, so the lower
    # quartile moves far less than the upper one when they are many (a short frame, a wide stripe)
    low = med - _quantile_from_hist(hist, total, 0.25)
    return med, max(low / HALF_IQR_PER_SIGMA, MIN_NOISE_DN)


@njit(nogil=True, cache=True)
def _column_max(img, c0, c1, sep, mx, am, sec):
    """Row-major pass: per-column max (uint8), its row (uint16), far second max (uint8).

    ``sec`` holds the largest value seen more than ``sep`` rows from the running argmax at the
    time it was seen (the old maximum is demoted into it when a new maximum appears far away).
    Rows ascend, so ``r - am >= 0``.  Branch-free so that the loop vectorises.  The row of the
    second maximum is not kept here: it costs half as much again (one more uint16 array per
    pixel) and only frames with double peaks need it (``_column_max2``).
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
def _column_max2(img, c0, c1, sep, mx, am, sec, a2):
    """Row-major pass: per-column max (uint8), its row (uint16), far second max and its row.

    ``sec`` holds the largest value seen more than ``sep`` rows from the running argmax at the
    time it was seen (the old maximum is demoted into it, with its row, when a new maximum
    appears far away); ``a2`` its row.  Rows ascend, so ``r - am >= 0``.  Branch-free so that
    the loop vectorises.
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
def _column_max_window(img, c0, c1, sep, rmin, rmax, mx, am, sec, a2, out):
    """``_column_max2`` over the rows ``rmin[c] <= r <= rmax[c]`` of each column only; ``out``
    keeps the maximum outside them (to tell "no peak" from "a peak outside the window").  Rows
    that lie outside every column's window (most of the frame: the inspection volume's section
    spans ~30 % of the rows in the reference cell) only update ``out``."""
    h = img.shape[0]
    n = c1 - c0
    if n == 0:
        return
    zero = np.uint8(0)
    lo_b = rmin[c0:c1]
    hi_b = rmax[c0:c1]
    r_first = int(lo_b.min())
    r_last = int(hi_b.max())
    for r in range(h):
        row = img[r, c0:c1]
        if r < r_first or r > r_last:
            for j in range(n):
                out[j] = max(out[j], row[j])
            continue
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
def _saturated_centre(img, c, a, h, level, window, bgl, max_walk):
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


@njit(nogil=True, cache=True)
def _extract_kernel(img, c0, c1, method, auto, thr, window, max_width, min_width, double_ratio,
                    bg, policy, expected, use_window, rmin, rmax, fit_saturated, row, peak, width,
                    reason, saturated, snr, n_peaks, noise):
    h = img.shape[0]
    n = c1 - c0
    med, sig = _noise_estimate(img)
    noise[0] = med
    noise[1] = sig
    if auto:
        threshold = med + AUTO_THRESHOLD_SIGMAS * sig
        floor = med + AUTO_MIN_PEAK_SIGMAS * sig
    else:
        threshold = thr
        floor = thr
    if n == 0:
        return
    sep = 2 * window
    mx = np.zeros(n, np.uint8)
    am = np.zeros(n, np.uint16)
    sec = np.zeros(n, np.uint8)
    a2 = np.zeros(n, np.uint16)
    out = np.zeros(n, np.uint8)
    j0 = 0
    j1 = n - 1
    _column_max(img, c0, c1, sep, mx, am, sec)
    # the rows of the second maxima, only over the columns that hold one (none on a clean
    # frame): a second pass there is cheaper than tracking them in every frame
    j0 = n
    j1 = -1
    for j in range(n):
        s = float(sec[j])
        if s > threshold and s >= floor and s >= double_ratio * float(mx[j]):
            j0 = min(j0, j)
            j1 = max(j1, j)
    if j1 >= j0:
        mx[j0:j1 + 1] = 0  # the second pass starts afresh (it finds the same maxima)
        am[j0:j1 + 1] = 0
        sec[j0:j1 + 1] = 0
        _column_max2(img, c0 + j0, c0 + j1 + 1, sep, mx[j0:j1 + 1], am[j0:j1 + 1],
                     sec[j0:j1 + 1], a2[j0:j1 + 1])
    if use_window:
        # Only the columns whose maximum lies outside their window (a reflection brighter than
        # the stripe, rare) are searched again, inside it: a frame without one costs what the
        # plain pass costs.
        k0 = n
        k1 = -1
        for j in range(n):
            p = float(mx[j])
            a = am[j]
            if p > threshold and p >= floor and (a < rmin[c0 + j] or a > rmax[c0 + j]):
                k0 = min(k0, j)
                k1 = max(k1, j)
        if k1 >= k0:
            for j in range(k0, k1 + 1):
                mx[j] = 0
                am[j] = 0
                sec[j] = 0
                a2[j] = 0
            _column_max_window(img, c0 + k0, c0 + k1 + 1, sep, rmin, rmax, mx[k0:k1 + 1],
                               am[k0:k1 + 1], sec[k0:k1 + 1], a2[k0:k1 + 1], out[k0:k1 + 1])
            j0 = min(j0, k0)
            j1 = max(j1, k1)
    # candidates: the maximum, and the far second maximum if it is strong enough and a local
    # maximum (on a wide stripe the far "second" is only its own flank)
    ncand = np.zeros(n, np.int8)
    for j in range(n):
        p = float(mx[j])
        if not (p > threshold and p >= floor):
            continue
        ncand[j] = 1
        s = float(sec[j])
        if s > threshold and s >= floor and s >= double_ratio * p:
            b = int(a2[j])
            c = c0 + j
            inside = not use_window or (b >= rmin[c] and b <= rmax[c])
            if (inside and b > 0 and b < h - 1 and img[b - 1, c] <= img[b, c]
                    and img[b + 1, c] <= img[b, c]):
                ncand[j] = 2
    choice = np.zeros(n, np.int8)
    if policy == 1:  # nearest
        for j in range(n):
            e = expected[c0 + j]
            if ncand[j] == 2 and math.isfinite(e):
                if abs(float(a2[j]) - e) < abs(float(am[j]) - e):
                    choice[j] = 1
    elif policy == 2 and j1 >= j0:  # continuity, when some column holds two candidates
        choice[:] = -1
        _continuity(ncand, mx, am, sec, a2, expected, c0, choice)
    max_walk = int(math.ceil(max_width * FWHM_PER_SIGMA)) + 2
    bg_sat = med if math.isnan(bg) else bg
    for j in range(n):
        c = c0 + j
        n_peaks[c] = ncand[j]
        if ncand[j] == 0:
            peak[c] = float(mx[j])
            snr[c] = (float(mx[j]) - med) / sig
            o = float(out[j])
            reason[c] = 8 if (o > threshold and o >= floor) else 1  # OUTSIDE_WINDOW / NO_PEAK
            continue
        if choice[j] == 1:
            p = float(sec[j])
            a = int(a2[j])
        else:
            p = float(mx[j])
            a = int(am[j])
        peak[c] = p
        snr[c] = (p - med) / sig
        sat = p >= SATURATION_DN
        if sat:
            if not fit_saturated:
                reason[c] = 2  # SATURATED
                continue
            saturated[c] = True
        wd = _fwhm_width(img, c, a, h, 0.5 * (p + threshold), max_walk)
        width[c] = wd
        if wd > max_width:
            reason[c] = 4  # TOO_WIDE
            continue
        if policy == 3 and ncand[j] == 2:
            reason[c] = 3  # DOUBLE
            continue
        if wd < min_width or _count_above(img, c, a, h, threshold, window) < MIN_PIXELS_ABOVE:
            reason[c] = 5  # TOO_NARROW
            continue
        if sat:
            y = _saturated_centre(img, c, a, h, bg_sat + SAT_FIT_MIN_SIGMAS * sig, window, bg_sat,
                                  max_walk)
        elif method == 0:
            t_cog = threshold
            if auto:
                t_cog = med + max(AUTO_COG_SIGMAS * sig, AUTO_COG_PEAK_FRACTION * (p - med))
            y = _cog(img, c, a, h, t_cog, window, bg)
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
