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

1. one row-major pass over the image (``scanner_core.stripe.passes``) keeping, per column, the
   running maximum (uint8), its row (uint16: the narrow index type is what lets LLVM vectorise
   the loop), the largest value seen farther than ``2 * window`` rows from the current maximum,
   all branch-free; over whole rows (a sequential stream, which the prefetchers follow) and,
   with a geometric window, over the rows it reaches only;
2. a robust estimate of the background and its noise (median and interquartile range of a
   sparse subsample of pixels, from a 256-bin histogram);
3. per column, the choice between the candidates, the stripe's width and the gates on it
   (set from the frame's own stripe widths), and a few pixel reads around the chosen peak for
   the sub-pixel refinement (``scanner_core.stripe.estimators``).

Conventions: ``image`` is ``(H, W)`` uint8, rows down, pixel centres at integer coordinates;
results are per column, rows in px, intensities in DN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from scanner_core.stripe import passes as passes
from scanner_core.stripe.estimators import FWHM_PER_SIGMA, SATURATION_DN  # noqa: F401
from scanner_core.stripe.kernel import (  # noqa: F401  (the gates' constants, documented there)
    COG_PEAK_FRACTION, COG_SIGMAS, AUTO_MIN_PEAK_SIGMAS, AUTO_THRESHOLD_SIGMAS,
    CONTINUITY_BRIGHTNESS_PX, CONTINUITY_JUMP_CAP_PX, CONTINUITY_MAX_GAP, CORE_WIDTH_FACTOR,
    LINKED_WIDTH_FACTOR, MIN_PIXELS_ABOVE, MIN_WIDTH_PX, NARROW_MIN_SIGMAS, SEPARATE_SIGMAS,
    SHOULDER_FRACTION,
    extract_kernel, window_bounds)
from scanner_core.validate import check_columns, check_image

__all__ = ["METHODS", "POLICIES", "SIGNALS", "BAYER_PATTERNS", "StripeResult", "extract",
           "stripe_signal", "demosaic", "Reason", "estimate_noise", "isolated_runs"]

METHODS = ("cog", "gaussian3", "parabola", "blais_rioux", "lsq_gauss")
#: Largest `window` (rows): a second peak counts beyond twice it, which the column maxima
#: track in bytes (``passes.MAX_SEP``).
MAX_WINDOW = passes.MAX_SEP // 2
_METHOD_CODE = {name: i for i, name in enumerate(METHODS)}
#: Peak selection policies (see ``extract``); "reject" is the historical behaviour.
POLICIES = ("strongest", "nearest", "continuity", "reject")
_POLICY_CODE = {name: i for i, name in enumerate(POLICIES)}

#: What ``stripe_signal`` makes of a frame (see there).
SIGNALS = ("auto", "mono", "red", "green", "blue", "red_excess", "green_excess", "blue_excess",
           "colour_excess")
_CHANNEL = {"red": 0, "green": 1, "blue": 2}
#: A colour excess is stored this much above zero: a grey surface's excess is zero give or
#: take the noise, and clipped at zero the noise's lower half would be lost with it (the
#: frame's noise estimate, which the stripe's floors and levels stand on, would read a
#: chroma-subsampled JPEG's structured noise as none).
EXCESS_OFFSET_DN = 16
#: A colour channel at or above this is taken as clipped by ``stripe_signal``'s excess: full
#: scale, less the ringing JPEG's blocks leave about a clipped run (pixels of 245-254 inside
#: the white cores of overexposed red lines in the photographs of ``flyscan bench real``).
CLIPPED_DN = 245
#: Bayer mosaics by their first row's first two pixels and the second row's first (RGGB: red
#: at (0, 0)), and the OpenCV conversion that demosaics each (OpenCV names a mosaic by its
#: second row's second and third pixels).
BAYER_PATTERNS = {"RGGB": "COLOR_BayerBG2RGB", "BGGR": "COLOR_BayerRG2RGB",
                  "GRBG": "COLOR_BayerGB2RGB", "GBRG": "COLOR_BayerGR2RGB"}

# A second local maximum counts as a second candidate peak when it reaches this fraction of the
# main one (weaker ones are ignored: a faint reflection never competes with the stripe).
DOUBLE_PEAK_RATIO = 0.3


class Reason:
    """Codes of ``StripeResult.reason`` (uint8): why a column is invalid."""

    OK = 0
    NO_PEAK = 1  # no pixel above the threshold (or, with threshold="auto", below the peak floor)
    SATURATED = 2  # peak at full scale and saturation="reject"
    DOUBLE = 3  # a second, separated peak of >= double_ratio of the main one, policy="reject"
    TOO_WIDE = 4  # wider than the frame's width gate (see ``extract``, ``max_width``)
    TOO_NARROW = 5  # a narrow peak (noise-like) that no neighbouring column's peak continues
    FIT_FAILED = 6  # sub-pixel refinement degenerate (flat top, diverged fit, no zero crossing)
    NOT_PROCESSED = 7  # outside ``columns``
    OUTSIDE_WINDOW = 8  # a peak only outside [row_min, row_max] (in the rows read): never the stripe


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
    width_gate_px : float
        The frame's gate on ``width``, px: wider peaks are a stripe only where they continue
        one (``extract``, ``max_width``); up to twice it with ``max_width="auto"``.
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
    width_gate_px: float = float("nan")


def _check_image(image) -> np.ndarray:
    img = check_image(image)
    if img.shape[0] > 65535:  # row indices are kept as uint16 for speed (docs/design.md)
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
    row = np.ascontiguousarray(row, dtype=np.float64)
    valid = np.ascontiguousarray(valid, dtype=np.bool_)
    if row.shape != valid.shape or row.ndim != 1:
        raise ValueError(f"`row` and `valid` must be (W,) arrays of one length, got {row.shape} "
                         f"and {valid.shape}")
    return _isolated_runs(row, valid, float(max_jump_px), int(min_run), int(max_gap))


@njit(nogil=True, cache=True)
def _isolated_runs(row, valid, max_jump_px, min_run, max_gap):
    """:func:`isolated_runs` in one pass over the runs (numpy's version cost 10 us a frame)."""
    n = valid.shape[0]
    out = np.zeros(n, np.bool_)
    if min_run <= 1:
        return out
    # runs of valid columns: [start, stop) in column index, length in valid columns
    starts = np.empty(n, np.int64)
    stops = np.empty(n, np.int64)
    lengths = np.empty(n, np.int64)
    k = -1
    last = -1
    for c in range(n):
        if not valid[c]:
            continue
        if k < 0 or c - last > 1 or abs(row[c] - row[last]) > max_jump_px:
            k += 1
            starts[k] = c
            lengths[k] = 0
        stops[k] = c + 1
        lengths[k] += 1
        last = c
    # a short run is judged by its ends: a long run at most max_gap columns beyond either
    for i in range(k + 1):
        if lengths[i] >= min_run:
            continue
        before = i > 0 and lengths[i - 1] >= min_run and starts[i] - stops[i - 1] <= max_gap
        after = i < k and lengths[i + 1] >= min_run and starts[i + 1] - stops[i] <= max_gap
        if before or after:
            for c in range(starts[i], stops[i]):
                out[c] = valid[c]
    return out


def stripe_signal(frame, signal="auto", *, bayer=None) -> np.ndarray:
    """The image the stripe is looked for in, from a camera frame.

    A colour camera sees a laser of one colour over surfaces lit by white light: the laser's
    channel alone also shows the surface's texture (a printed checkerboard under ambient light),
    while its *colour excess* ``e_k = v_k - (v_i + v_j) / 2`` (``k`` the laser's channel, ``i``,
    ``j`` the others) is zero on grey surfaces, whatever their brightness, and holds the
    stripe.  ``colour_excess`` takes the largest excess of the three channels, so that a laser
    of any one colour stands out without being named.

    Parameters
    ----------
    frame : (H, W) uint8 or (H, W, 3) uint8
        A mono frame, a raw Bayer mosaic (``bayer`` given), or an RGB frame (channels in the
        order red, green, blue: pypylon's ``RGB8``, scikit-image; an OpenCV ``imread`` gives
        BGR, reverse it with ``frame[..., ::-1]``).
    signal : str
        One of ``SIGNALS``. ``"auto"`` (default): a mono frame as it is, a colour one (or a
        mosaic) its ``"colour_excess"``. ``"mono"``: a mono frame as it is (a colour one is
        refused). ``"red"``, ``"green"``, ``"blue"``: that channel. ``"red_excess"``,
        ``"green_excess"``, ``"blue_excess"``: that channel's excess, rounded half up, plus
        ``EXCESS_OFFSET_DN``, clipped to [0, 255]; where the channel itself is clipped
        (``CLIPPED_DN``), carried on from the rows either side of the clipped run by the
        other channels' rise (the white core of an overexposed line). ``"colour_excess"``:
        the largest of the three.
    bayer : str, optional
        The frame is a raw mosaic with this pattern (one of ``BAYER_PATTERNS``): it is
        demosaiced (OpenCV's bilinear demosaicing) first.

    Returns
    -------
    (H, W) uint8
        The frame itself for a mono frame, else a new C-contiguous image.

    Raises
    ------
    ValueError
        On a frame that is not uint8 (H, W) or (H, W, 3), an unknown ``signal`` or ``bayer``, a
        mosaic given as a colour frame, or a colour signal asked of a mono frame.
    """
    if signal not in SIGNALS:
        raise ValueError(f"`signal` must be one of {SIGNALS}, got {signal!r}")
    frame = np.asarray(frame)
    if frame.dtype != np.uint8:
        raise ValueError(f"a frame must be uint8, got {frame.dtype}")
    if bayer is not None:
        frame = demosaic(frame, bayer)
    if frame.ndim == 2:
        if signal not in ("auto", "mono"):
            raise ValueError(f"`signal` {signal!r} needs a colour frame (H, W, 3) or a Bayer "
                             f"mosaic (`bayer`); this frame is mono, shape {frame.shape}")
        return frame
    if frame.ndim != 3 or frame.shape[2] != 3:
        raise ValueError(f"a frame must be (H, W) or (H, W, 3), got shape {frame.shape}")
    if signal == "mono":
        raise ValueError("`signal` 'mono' was asked of a colour frame: name a channel or an "
                         "excess (or 'auto')")
    if signal == "auto":
        signal = "colour_excess"
    if signal in _CHANNEL:
        return np.ascontiguousarray(frame[:, :, _CHANNEL[signal]])
    which = -1 if signal == "colour_excess" else _CHANNEL[signal.split("_")[0]]
    out = np.empty(frame.shape[:2], np.uint8)
    _colour_excess(frame, which, out)
    return out


def demosaic(mosaic, bayer: str) -> np.ndarray:
    """(H, W) uint8 raw Bayer mosaic of pattern ``bayer`` (one of ``BAYER_PATTERNS``) ->
    (H, W, 3) uint8 RGB, by OpenCV's bilinear demosaicing; ValueError on another pattern or
    shape."""
    if bayer not in BAYER_PATTERNS:
        raise ValueError(f"`bayer` must be one of {tuple(BAYER_PATTERNS)}, got {bayer!r}")
    mosaic = np.asarray(mosaic)
    if mosaic.ndim != 2:
        raise ValueError(f"a Bayer mosaic is (H, W), got shape {mosaic.shape}")
    return cv2.cvtColor(np.ascontiguousarray(mosaic), getattr(cv2, BAYER_PATTERNS[bayer]))


@njit(nogil=True, cache=True)
def _colour_excess(rgb, which, out):
    """``out = clip(round_half_up(v_k - (v_i + v_j) / 2) + EXCESS_OFFSET_DN, 0, 255)`` for
    channel ``which``, or the largest of the three excesses for ``which = -1``; integer
    arithmetic, except over a run of rows where the channel is clipped (``_continue_run``).

    The excess in one pass in row order, noting the rows that hold a clipped pixel; then the
    clipped runs, through those rows only (and the row after each run), keeping per channel
    and column the row its open run began and the first unclipped row after it.  A run is
    carried on once the row after that one is read unclipped too: one unclipped row between
    two clipped runs joins them (JPEG's ringing leaves single pixels under full scale inside
    a clipped core)."""
    h, w = out.shape
    clipped_rows = np.zeros(h, np.bool_)
    if which < 0:
        _largest_excess(rgb, out, clipped_rows)
    else:
        _excess(rgb, which, (which + 1) % 3, (which + 2) % 3, out, clipped_rows)
    k0 = 0 if which < 0 else which
    k1 = 3 if which < 0 else which + 1
    first = np.full((3, w), -1, np.int64)
    after = np.full((3, w), -1, np.int64)
    open_runs = 0
    for r in range(h):
        if not clipped_rows[r] and open_runs == 0:
            continue
        for c in range(w):
            for k in range(k0, k1):
                if np.int32(rgb[r, c, k]) >= CLIPPED_DN:
                    if first[k, c] < 0:
                        first[k, c] = r
                        open_runs += 1
                    after[k, c] = -1
                elif first[k, c] >= 0:
                    if after[k, c] < 0:
                        after[k, c] = r
                    else:
                        _continue_run(rgb, k, c, first[k, c], after[k, c], out)
                        first[k, c] = -1
                        after[k, c] = -1
                        open_runs -= 1
    if open_runs > 0:
        for k in range(k0, k1):
            for c in range(w):
                if first[k, c] >= 0:
                    _continue_run(rgb, k, c, first[k, c],
                                  after[k, c] if after[k, c] >= 0 else h, out)


@njit(nogil=True, cache=True)
def _excess(rgb, k, i, j, out, clipped_rows):
    """Channel ``k``'s excess into ``out``; ``clipped_rows[r]``: row ``r`` holds a pixel whose
    channel ``k`` is clipped."""
    h, w = out.shape
    for r in range(h):
        n_clipped = 0
        for c in range(w):
            vk = np.int32(rgb[r, c, k])
            e2 = 2 * vk - np.int32(rgb[r, c, i]) - np.int32(rgb[r, c, j])
            n_clipped += vk >= CLIPPED_DN
            out[r, c] = np.uint8(min(max(((e2 + 1) >> 1) + EXCESS_OFFSET_DN, 0), 255))
        clipped_rows[r] = n_clipped > 0


@njit(nogil=True, cache=True)
def _largest_excess(rgb, out, clipped_rows):
    """The largest of the three channels' excesses into ``out``; ``clipped_rows[r]``: row
    ``r`` holds a pixel with a clipped channel."""
    h, w = out.shape
    for r in range(h):
        n_clipped = 0
        for c in range(w):
            v0 = np.int32(rgb[r, c, 0])
            v1 = np.int32(rgb[r, c, 1])
            v2 = np.int32(rgb[r, c, 2])
            e2 = max(2 * v0 - v1 - v2, 2 * v1 - v0 - v2, 2 * v2 - v0 - v1)
            n_clipped += max(v0, v1, v2) >= CLIPPED_DN
            out[r, c] = np.uint8(min(max(((e2 + 1) >> 1) + EXCESS_OFFSET_DN, 0), 255))
        clipped_rows[r] = n_clipped > 0


@njit(nogil=True, cache=True)
def _continue_run(rgb, k, c, first, end, out):
    """Channel ``k``'s excess over its clipped rows ``first <= r < end`` of column ``c``.

    There ``v_k`` no longer grows with the light, and its excess would fall as the others rise
    (a line bright enough turns white: hollow, or a hole where JPEG's ringing leaves one pixel
    under full scale): it is carried on from the unclipped rows either side (``b``, ``a``),
    interpolated along the run (a texture edge under it), plus what the other two channels rose
    above theirs there: ``e(r) = e_b + t (e_a - e_b) + (o(r) - o_b - t (o_a - o_b)) / 2``,
    ``o = v_i + v_j``, ``t`` from 0 at ``b`` to 1 at ``a``.  Monotonic in the light where
    ``v_i`` and ``v_j`` grow with it, so a symmetric line stays symmetric; a white surface
    (its excess about zero either side, its other channels no brighter inside) stays about
    zero.  Full scale where it reaches it: clipped, measured from its flanks.  Written only
    where larger than what ``out`` holds, the pixel's own excess (or another channel's, for
    ``colour_excess``): both are lower bounds where the channel clips, and a pixel counted
    clipped within JPEG's margin may be a bright flank's."""
    h = out.shape[0]
    i = (k + 1) % 3
    j = (k + 2) % 3
    b = first - 1
    a = end
    if b < 0 and a >= h:
        return  # the whole column clipped: nothing to carry on from, its own excess stays
    if b < 0:
        b = a
    if a >= h:
        a = b
    o_b = np.int32(rgb[b, c, i]) + np.int32(rgb[b, c, j])
    o_a = np.int32(rgb[a, c, i]) + np.int32(rgb[a, c, j])
    e_b = 2 * np.int32(rgb[b, c, k]) - o_b
    e_a = 2 * np.int32(rgb[a, c, k]) - o_a
    span = max(a - b, 1)
    for r in range(first, end):
        t = (r - b) / span
        o = np.int32(rgb[r, c, i]) + np.int32(rgb[r, c, j])
        e2 = e_b + t * (e_a - e_b) + o - (o_b + t * (o_a - o_b))
        e = min(max(int(math.floor(0.5 * e2 + 0.5)) + EXCESS_OFFSET_DN, 0), 255)
        if e > out[r, c]:
            out[r, c] = np.uint8(e)


def estimate_noise(image) -> tuple[float, float]:
    """Robust background level and noise of a frame from a sparse subsample of its pixels.

    A run of ``stripe_passes.NOISE_RUN_PX`` pixels in every ``NOISE_ROW_STEP``-th row (the runs
    spread over the width) is histogrammed, and so are the differences of its pixels
    ``NOISE_LAG`` columns apart. The background is the values' median; the noise is the
    differences' median over ``0.6745 sqrt(2)`` (two pixels' independent noise of sigma
    ``s`` differ by a half-normal of scale ``s sqrt(2)``), both read off the histograms with
    linear interpolation inside the integer bins (grouped-data quantiles), so that a 3 DN
    noise is not quantised to whole DN. The stripe runs along the rows and barely changes
    between neighbouring columns; a printed texture, an ambient gradient or a bright part
    changes only at its edges, so the noise is the sensor's, not the scene's spread.

    Parameters
    ----------
    image : (H, W) uint8

    Returns
    -------
    background_dn, noise_dn : float
        DN; ``noise_dn >= stripe_passes.MIN_NOISE_DN``.
    """
    img = _check_image(image)
    return passes.noise_estimate(img)


def extract(image, method="cog", *, threshold="auto", window=4, max_width="auto", columns=None,
            policy="continuity", expected_row=None, row_min=None, row_max=None,
            saturation="fit", shoulders=False, **params) -> StripeResult:
    """Sub-pixel row of the laser stripe in every column of a frame.

    Parameters
    ----------
    image : (H, W) uint8
        Camera frame, DN.  ``H <= 65535``.
    method : str
        One of ``METHODS``:

        - ``"cog"``: windowed centre of gravity, rows within ``+-window`` of the argmax, weights
          ``v - t`` for the pixels above a level ``t`` of the column's own [1]_: ``background +
          max(COG_SIGMAS * noise, COG_PEAK_FRACTION * (peak - background))``, whatever
          ``threshold`` is (a level near a dim stripe's top would leave one or two pixels above
          it, and their centroid is the brightest one's row: pixel locking).  On a bright
          stripe that level (20 DN on the reference model) measured better than the
          background (see ``background`` below).
        - ``"gaussian3"``: 3-point Gaussian (parabola through the logarithms) [1]_, [2]_.
        - ``"parabola"``: 3-point parabola through the argmax and its neighbours [1]_.
        - ``"blais_rioux"``: zero crossing of the 4th-order derivative filter
          ``g(i) = f(i-2) + f(i-1) - f(i+1) - f(i+2)``, linearly interpolated [3]_.
        - ``"lsq_gauss"``: least-squares fit of ``b + A exp(-(r - mu)^2 / (2 s^2))`` to the
          ``+-window`` rows by Gauss-Newton from the centroid; reaches the Cramer-Rao bound for
          white noise [4]_.

        A saturated peak is measured the same way whatever the method (``saturation``).
    threshold : "auto" or float
        A column needs a pixel above it to hold a stripe.  ``"auto"`` (default): what stands
        clear of the frame's own background and noise (``estimate_noise``): ``background +
        AUTO_THRESHOLD_SIGMAS * noise`` (20 DN on the reference model), and every candidate
        peak must also reach ``background + AUTO_MIN_PEAK_SIGMAS * noise`` (else
        ``Reason.NO_PEAK``).  Dark surfaces then keep their stripe; ``snr`` says how far to
        trust it.  Where a column's brightest pixel is no stripe (a texture's lit square, a
        bright part) beside a column whose stripe passed, the stripe is looked for where that
        one goes on, dimmer than the brightest pixel (``kernel.prominent_peak``).  A number:
        a fixed level, DN.  Measured on a 30 DN
        stripe over 3 DN of noise (``flyscan bench stripe``): 99.9 % of the columns, 0.147 px
        RMS (``cog``), 0.135 (``lsq_gauss``); Cramer-Rao bound 0.130 px.
    window : int
        Half-size (rows) of the neighbourhood of the argmax used by ``cog`` and ``lsq_gauss``,
        at the least: ``cog`` goes on beyond it while the pixels stay above its threshold,
        ``lsq_gauss`` spans 2.5 of the stripe's sigmas; a second peak counts as separate
        beyond ``2 * window`` rows and 2.5 of the main peak's sigmas. 2 to ``MAX_WINDOW``.
    max_width : float or "auto"
        Gate on the sigma-like width, px. A number: wider peaks are ``Reason.TOO_WIDE``.
        ``"auto"`` (default): the gate follows the frame's own stripe: ``max(4, 2 * median
        width of the frame's unclipped peaks)``, and a peak up to twice that is kept where it
        continues, column by column, a stripe within the gate (``CORE_WIDTH_FACTOR``,
        ``LINKED_WIDTH_FACTOR``: a stripe widening along its length stays whole, a blob apart
        from it does not). The gate used is ``StripeResult.width_gate_px``. With either, a
        narrow peak (``min_width``, ``MIN_PIXELS_ABOVE``: what a lone noise pixel and a stripe
        of sigma 0.5 px both look like in one column) is kept where a neighbouring column's
        peak continues it and it reaches ``NARROW_MIN_SIGMAS`` noise sigmas.
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
        only peak lies outside is flagged ``Reason.OUTSIDE_WINDOW``.  Rows outside every
        column's window are not read at all (a peak there leaves its column ``NO_PEAK``): the
        window of the reference cell's inspection volume spans about 30 % of the rows, and the
        frame is read in a third of the time.  Only the columns whose maximum lies outside
        their own window are searched again (inside it).
    saturation : str
        ``"fit"`` (default): a peak that reaches 255 is measured from the unclipped samples of
        its flanks, treating the clipped ones as censored: a weighted least-squares parabola
        through ``ln(v - background)`` (the logarithm of a Gaussian is a parabola; weights
        ``(v - background)^2`` make the residuals' variance uniform [6]_), centre
        ``-b / (2 c)``; the column stays valid with ``saturated`` True.  ``"reject"``: flagged
        ``Reason.SATURATED`` (historical).
    shoulders : bool
        ``cog`` weighs only a stripe's top, above ``SHOULDER_FRACTION`` (half) of its height
        over its own background, and a clipped peak whose flank fit fails takes the centre of
        its part above that level (``estimators.top_centroid``).  For a colour camera's excess
        (``stripe_signal``): JPEG's 4:2:0 chroma and demosaicing spread it to one side of the
        line, and a printed texture's edge under the line weighs one flank more than the
        other.  Off for a mono camera, where a speckled line's flanks average its speckle out
        (``docs/stripe.md``).
    **params
        ``min_width`` (float, px, default ``MIN_WIDTH_PX``): narrower peaks need a neighbour.
        ``double_ratio`` (float, default ``DOUBLE_PEAK_RATIO``).
        ``background`` (float, DN, default None): for ``cog``, subtract this level instead of
        the column's own (pixels above that level only); for ``gaussian3`` the level
        subtracted before the logarithms (default 0).  On the reference model (background
        10 DN, noise 3 DN) ``cog`` measured better subtracting a level near 20 DN than the true
        background: the offset down-weights the noisy flanks (``docs/stripe.md``).

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
    ``double_ratio`` of the peak (tracked in the single pass); wider than the width gate (and,
    within twice it with ``max_width="auto"``, not continuing a stripe); narrow (below
    ``min_width``, or fewer than ``MIN_PIXELS_ABOVE`` pixels above the threshold within
    ``+-window``) with no neighbouring column's peak continuing it; degenerate refinement.
    Measured on stripes of sigma 0.5 to 6 px, textured, speckled, and on a colour camera's
    channel: ``tests/scanner_core/test_stripe_widths.py`` and ``flyscan bench stripe``.

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
    if not 2 <= window <= MAX_WINDOW:
        raise ValueError(f"`window` must be 2 to {MAX_WINDOW} rows, got {window}")
    auto_width = isinstance(max_width, str)
    if auto_width:
        if max_width != "auto":
            raise ValueError(f"`max_width` must be a number or 'auto', got {max_width!r}")
        gate = 4.0
    else:
        gate = float(max_width)
        if not gate > 0:
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
        rmin, rmax, ok = window_bounds(_per_column("row_min", row_min, w, 0.0),
                                       _per_column("row_max", row_max, w, h - 1.0), h)
        if not ok:
            raise ValueError("`row_min` and `row_max` must not be NaN")
    else:
        rmin = rmax = np.zeros(0, np.uint16)
    (row, peak, width, reason, saturated, snr, n_peaks, background, noise,
     gate) = extract_kernel(img, c0, c1, _METHOD_CODE[method], auto, thr, window, gate, auto_width,
                            min_width, double_ratio, bg, _POLICY_CODE[policy], expected,
                            use_window, rmin, rmax, saturation == "fit", bool(shoulders))
    return StripeResult(row=row, peak=peak, width=width, valid=reason == Reason.OK, reason=reason,
                        saturated=saturated, snr=snr, n_peaks=n_peaks, background_dn=background,
                        noise_dn=noise, width_gate_px=gate)


