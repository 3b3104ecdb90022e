"""LED marker detection: find the gripper's LED blob in each view strip of a frame.

One camera image holds three views as column strips (left mirror, direct, right mirror). The LED
marker appears in each view as a small isotropic 2-D Gaussian blob; the direct view also holds the
laser stripe, a thin mostly-horizontal line that must never be taken for the marker.

Pipeline per strip (``find_marker``):

1. Candidates on a max-pooled copy of the strip (``decimation`` x ``decimation`` blocks, so every
   full-resolution pixel above the threshold shows in the pooled image): threshold + connected
   components, both in one row-major numba pass over the frame for all strips together
   (``scanner_core.numeric.pooling``: the labelling costs in proportion to the bright blocks only). A
   strip whose pooled maximum is not above the threshold is rejected at once.
2. Small pooled components are checked at full resolution in a small window: area and elongation
   (ratio of principal axes from the second moments of the thresholded pixels). The stripe, or a
   fragment of it, is long and thin and fails the elongation test.
3. Pooled components too large to be a blob (the stripe, possibly with the marker touching it) are
   only searched when no small candidate passed: the thresholded pixels are eroded with a disc of
   radius ``core_radius_px``, which removes the stripe (about 5 px thick at the threshold) but keeps
   the core of the marker blob (about 9 px across), and each surviving core is a candidate.
4. Sub-pixel centre: least-squares fit of an isotropic 2-D Gaussian plus background
   (Levenberg-Marquardt over centre, amplitude, background and width) in a
   ``2 * ceil(window_sigmas * sigma_px) + 1`` px window. Saturated pixels are left out (censored).
   Pixels far above the fitted blob (a stripe touching the marker, or a saturated pixel the blob
   alone would not saturate) are masked and the fit repeated; for seeds from step 3 the stripe's
   pixels away from the core are masked from the start. A fit that does not converge, whose
   residual or width does not look like the blob, or that needed too much of its core masked
   (the stripe running into the marker's core) is rejected: None, never a biased centre.
   Measured at the reference model (sigma 2.5 px, peak 230 DN, background 10 DN, noise 3 DN):
   bias < 0.001 px, RMS 0.0105 px per axis, the Cramer-Rao bound (0.0104 px). A Gaussian-
   weighted centroid (same ML fixed point) gave the same RMS on clean blobs but converged badly
   with masked pixels, so the fit is kept.
5. If several candidates survive, the one with the largest fitted amplitude (the brightest) wins.

Tracking (``near``): when the caller predicts where the marker is (its position in the previous
frames), steps 1-5 first run on a window of +-``near_px`` around the prediction only, then on
one of +-``search_px``, aligned on the strip's block grid and clipped to the strip; a pooled
component touching a side of the window that is not the strip's or the image's is left out there
(it may continue outside). Any component kept is therefore exactly the one the whole-strip search
sees, and the centre is bit for bit the same fit. When the windows yield no marker, the whole
strip is searched. The per-candidate steps run in compiled code (``scanner_core.marker.kernels``):
a tracked search of three views costs about 0.09 ms a frame.

Image convention: pixel centres at integer coordinates, (column, row) = (x, y), full-image
coordinates. No global state; the numba kernels are compiled on first use and cached on disk.

One concern that reads best whole, over 500 lines: the public searches, their input checks,
the candidates and the sub-pixel centre are steps 1-5 above, each feeding the next; the
compiled per-candidate steps are apart in ``scanner_core.marker.kernels``.

References
----------
.. [1] Paper, section II: one LED marker on the gripper, seen directly and through two mirrors,
   triangulated per frame to give the gripper position.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from scanner_core.numeric import pooling as _pooling
from scanner_core.marker import kernels as mk
from scanner_core.validate import check_columns, check_image

__all__ = ["MarkerParams", "find_marker", "find_markers", "marker_present"]

# The sensor's saturation value: clipped pixels carry no amplitude information.
_SATURATED_DN = mk.SATURATED_DN
# Sub-pixel fit stops when a step is below this (px); far below the noise-limited error (~0.01 px).
_FIT_TOL_PX = 1e-4
# Bounds on the iterative fit, so that it always ends.
_FIT_MAX_ITER = 30
_FIT_MAX_ROUNDS = 8
# Accepted fitted blob width, as a fraction of `sigma_px`: wide enough for focus and LED-size
# changes, narrow enough to reject noise spikes (s -> 0) and diffuse glare (s >> sigma).
_WIDTH_RANGE = (0.5, 2.0)


@dataclass(frozen=True)
class MarkerParams:
    """Parameters of the marker detector.

    Attributes
    ----------
    threshold_dn : float
        Detection threshold, DN (absolute grey level). Pixels strictly above it are "on".
    min_area_px, max_area_px : int
        Accepted area of a blob's thresholded connected component, full-resolution pixels.
    max_elongation : float
        Largest accepted ratio of principal axes (square root of the ratio of the eigenvalues of
        the second-moment matrix of the component's pixels). The stripe is long and thin.
    window_sigmas : float
        Half-size of the centroid window, in blob sigmas: the window is
        ``2 * ceil(window_sigmas * sigma_px) + 1`` px square. A marker whose window does not fit
        inside its strip (or the image) is reported absent.
    sigma_px : float
        Expected blob sigma, px: sets the window and seeds the fit; the fitted width must lie
        within 0.5-2 times it.
    decimation : int
        Block size of the max-pooled candidate search.
    core_radius_px : int
        Radius of the erosion disc that separates the marker core from a stripe touching it, px.
        Must exceed the stripe's half-thickness at the threshold (about 2.5 px) and stay below the
        blob's radius at the threshold (about 4.4 px at the reference model).
    outlier_dn : float
        Pixels brighter than the fitted blob by more than this (DN) are masked as not-marker
        (a stripe touching the marker), together with their 8-neighbours.
    max_residual : float
        Largest accepted RMS residual of the fit inside 2 sigma of the centre, as a fraction of the
        fitted amplitude; rejects stripe pieces and other shapes that are not the blob.
    max_masked_fraction : float
        Largest accepted fraction of masked pixels inside 2 sigma of the centre.
    max_candidates : int
        At most this many candidate components per strip are examined (brightest first).
    search_px : int
        Half-size of the tracked search window around a predicted position, px (see
        `find_markers`). The marker moves about 5 px per frame in the simulated pass at 162 fps;
        48 px covers that several times over (a dropped frame, a poor prediction) while the
        window (97 px square) stays a small part of a strip.
    near_px : int
        Half-size of a first, smaller window around the prediction, px: searched before the
        ``search_px`` one, which is searched only when this finds nothing. The prediction
        (from the last two frames) was off by 0.02 px (median) and 0.07 px (99th percentile)
        at 200 mm/s, 0.06 and 12.5 px at 1 m/s (25 px at most, as the marker enters a view),
        so a window of +-16 px holds the blob (4.4 px in radius at the threshold) nearly
        always, and reads a third of the rows: the window's rows come from memory, not from
        the cache, one or two cache lines each.
    """

    threshold_dn: float = 60.0
    min_area_px: int = 5
    max_area_px: int = 2000
    max_elongation: float = 2.0
    window_sigmas: float = 3.0
    sigma_px: float = 2.5
    decimation: int = 4
    core_radius_px: int = 3
    outlier_dn: float = 30.0
    max_residual: float = 0.15
    max_masked_fraction: float = 0.6
    max_candidates: int = 8
    search_px: int = 48
    near_px: int = 16

    def __post_init__(self) -> None:
        if not 0.0 <= self.threshold_dn < _SATURATED_DN:
            raise ValueError(f"`threshold_dn` must be in [0, 255), got {self.threshold_dn}")
        if not 1 <= self.min_area_px <= self.max_area_px:
            raise ValueError(
                f"`min_area_px`, `max_area_px` must satisfy 1 <= min <= max, "
                f"got {self.min_area_px}, {self.max_area_px}"
            )
        for name in ("max_elongation", "window_sigmas", "sigma_px", "outlier_dn",
                     "max_residual", "max_masked_fraction"):
            if not getattr(self, name) > 0:
                raise ValueError(f"`{name}` must be > 0, got {getattr(self, name)}")
        for name in ("decimation", "core_radius_px", "max_candidates", "search_px", "near_px"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"`{name}` must be an integer >= 1, got {getattr(self, name)}")

    @property
    def half_window_px(self) -> int:
        """Half-size of the centroid window, px."""
        return int(math.ceil(self.window_sigmas * self.sigma_px))


# ---------------------------------------------------------------------------------------------
# Public API


def find_marker(
    image: np.ndarray,
    *,
    columns: tuple[int, int],
    params: MarkerParams = MarkerParams(),
    near: tuple[float, float] | None = None,
    search_px: float | None = None,
) -> tuple[float, float] | None:
    """Sub-pixel centre of the LED marker in one view strip.

    Parameters
    ----------
    image : (H, W) uint8
        The full camera image, DN.
    columns : (int, int)
        The strip's column range ``[start, stop)`` in ``image``.
    params : MarkerParams
        Detector parameters.
    near : (float, float) or None
        Predicted centre (column, row), full-image pixels, or None (or NaN) for no prediction:
        the strip is searched near it first (see `find_markers`).
    search_px : float or None
        Half-size of the window around `near`, px; None uses ``params.search_px``.

    Returns
    -------
    (x, y) : (float, float) or None
        Marker centre (column, row) in full-image pixel coordinates (pixel centres at integers),
        or None when no marker is found. None is also returned when the marker's centroid window
        (``params.half_window_px`` around the centre) does not fit inside the strip or the image,
        since a truncated blob would give a biased centre.

    Raises
    ------
    ValueError
        If `image` is not 2-D uint8, `columns` is not a valid column range of `image`, `near` is
        not a pair of numbers or `search_px` is not > 0.

    Notes
    -----
    The centre comes from a least-squares fit of ``b + A exp(-r^2 / (2 s^2))`` over a window
    (module docstring, step 4): unbiased (< 0.001 px) with 0.0105 px RMS per axis at the
    reference model, the Cramer-Rao bound. A marker touching the end of the stripe is found with
    the stripe's pixels masked (errors up to about 0.06 px when the stripe ends 3-4 px from the
    centre); when the stripe runs into the marker's core, None is returned. When several blobs
    pass all tests, the one with the largest fitted amplitude (the brightest) is returned.

    References
    ----------
    .. [1] Paper, section II (LED marker seen in three views).
    """
    image = check_image(image)
    c0, c1 = check_columns(columns, image.shape[1], "columns")
    guesses = None if near is None else _check_near([near], 1, "near")
    return _find_in_strips(image, [(c0, c1)], params, guesses,
                           _check_search_px(search_px, params))[0]


def find_markers(
    image: np.ndarray,
    *,
    strips: Sequence[tuple[int, int]],
    params: MarkerParams = MarkerParams(),
    near: np.ndarray | None = None,
    search_px: float | None = None,
) -> np.ndarray:
    """Marker centres in several view strips of one image.

    Parameters
    ----------
    image : (H, W) uint8
        The full camera image, DN.
    strips : sequence of (int, int), length N
        Column ranges ``[start, stop)`` of the views, e.g. left mirror, direct, right mirror.
    params : MarkerParams
        Detector parameters.
    near : (N, 2) float, optional
        Predicted centre (column, row) per strip, full-image pixels (e.g. extrapolated from the
        previous frames); a row holding a NaN means no prediction for that strip.
    search_px : float, optional
        Half-size of the search window around a prediction, px; default ``params.search_px``.

    Returns
    -------
    centres : (N, 2) float64
        Marker centre (column, row) per strip in full-image pixel coordinates; a NaN row where
        the marker was not found (see `find_marker`).

    Raises
    ------
    ValueError
        If `image`, `strips`, `near` (shape ``(N, 2)``) or `search_px` (> 0) is invalid.

    Notes
    -----
    With a prediction, a strip is searched first in the window ``near +- params.near_px``,
    then ``near +- search_px`` (aligned on the strip's ``params.decimation`` block grid,
    clipped to the strip and the image); only if no marker is found there is the whole strip
    searched (all such strips in one pass over the frame). A marker found in the window is the same sub-pixel fit, bit for bit, as the
    whole-strip search gives for it (module docstring, "Tracking"); the two can differ only
    when the strip holds another accepted blob that is brighter than the one near the
    prediction (the whole-strip search keeps the brightest). A marker straddling the window's
    side, or merged with the stripe across it, is left to the whole-strip search.
    """
    image = check_image(image)
    ranges = _check_strips(strips, image.shape[1])
    guesses = None if near is None else _check_near(near, len(ranges), "near")
    half = _check_search_px(search_px, params)
    out = np.full((len(ranges), 2), np.nan)
    for k, found in enumerate(_find_in_strips(image, ranges, params, guesses, half)):
        if found is not None:
            out[k] = found
    return out


def marker_present(
    image: np.ndarray,
    *,
    strips: Sequence[tuple[int, int]],
    params: MarkerParams = MarkerParams(),
    min_views: int = 2,
) -> bool:
    """Cheap presence test for the trigger: is a marker-like blob seen in `min_views` strips?

    Parameters
    ----------
    image : (H, W) uint8
        The full camera image, DN.
    strips : sequence of (int, int)
        Column ranges ``[start, stop)`` of the views.
    params : MarkerParams
        Detector parameters (threshold, area, elongation, decimation).
    min_views : int
        Number of strips that must show a blob.

    Returns
    -------
    present : bool

    Notes
    -----
    Runs steps 1-2 of `find_marker` only (pooled candidates, full-resolution area and elongation
    check), without the sub-pixel fit, and stops as soon as the answer is known. The stripe alone
    never passes the elongation test. A marker merged with the stripe is not counted in that
    view (the mirror views still count), and a very short stripe piece could pass in one view,
    which `min_views` >= 2 guards against.
    """
    image = check_image(image)
    ranges = _check_strips(strips, image.shape[1])
    if not 1 <= int(min_views):
        raise ValueError(f"`min_views` must be >= 1, got {min_views}")
    # All strips are pooled in one pass over the frame (cheapest, `_pooling`); then the narrow
    # strips (the mirror views) are checked first: they usually decide it.
    spans = [(c0, c1, c0, c1) for c0, c1 in ranges]
    pooled = _pooled_candidates(image, (0, image.shape[0]), spans, params)
    order = sorted(range(len(ranges)), key=lambda k: ranges[k][1] - ranges[k][0])
    seen = 0
    for i, k in enumerate(order):
        if seen + (len(order) - i) < min_views:
            return False
        if pooled[k] is None:
            continue
        c0, c1 = ranges[k]
        for region in pooled[k][0]:
            if len(_blob_seeds(image, c0, c1, [region], params)):
                seen += 1
                break
        if seen >= min_views:
            return True
    return False


# ---------------------------------------------------------------------------------------------
# Input checks


def _check_strips(strips, width: int) -> list[tuple[int, int]]:
    try:
        items = list(strips)
    except TypeError:
        raise ValueError(f"`strips` must be a sequence of (start, stop) pairs, got {strips!r}") \
            from None
    if not items:
        raise ValueError("`strips` must hold at least one (start, stop) pair, got none")
    return [check_columns(s, width, f"strips[{k}]") for k, s in enumerate(items)]


def _check_near(near, n: int, name: str) -> list[tuple[float, float]]:
    """`n` predicted (x, y) pairs (NaN allowed) as Python floats, or ValueError naming `name`."""
    try:
        arr = np.asarray(near, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be ({n}, 2) float, got {near!r}") from None
    if arr.shape != (n, 2):
        got = f"{np.shape(near)} {getattr(near, 'dtype', type(near).__name__)}"
        want = "(x, y) pair" if name == "near" and n == 1 else f"({n}, 2) float"
        raise ValueError(f"`{name}` must be {want}, got {got}")
    return [(float(x), float(y)) for x, y in arr]


def _check_search_px(search_px, params: MarkerParams) -> float:
    half = params.search_px if search_px is None else search_px
    try:
        ok = float(half) > 0.0 and math.isfinite(float(half))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"`search_px` must be a finite number > 0, got {search_px!r}")
    return float(half)


# ---------------------------------------------------------------------------------------------
# Candidates


def _search_window(near: tuple[float, float], half: float, c0: int, c1: int, height: int,
                   f: int) -> tuple[int, int, int, int] | None:
    """Rows and columns ``(r0, r1, w0, w1)`` of the window ``near +- half`` on the strip's block
    grid (``w0 - c0`` and ``r0`` multiples of `f`), clipped to the strip and the image; None when
    there is no prediction, the window misses the strip or covers all of it."""
    x, y = near
    if not (math.isfinite(x) and math.isfinite(y)):
        return None
    w0 = max(c0, c0 + f * math.floor((x - half - c0) / f))
    w1 = min(c1, c0 + f * (math.floor((x + half - c0) / f) + 1))
    r0 = max(0, f * math.floor((y - half) / f))
    r1 = min(height, f * (math.floor((y + half) / f) + 1))
    if w0 >= w1 or r0 >= r1 or (w0, w1, r0, r1) == (c0, c1, 0, height):
        return None
    return r0, r1, w0, w1


def _pooled_candidates(image, rows, spans, params: MarkerParams):
    """Pooled above-threshold components of windows of strips, small and large, in one pass.

    `rows` ``(r0, r1)`` and each span ``(c0, c1, w0, w1)`` (strip ``[c0, c1)``, window columns
    ``[w0, w1)``) give windows on their strip's block grid (the whole strip, or a
    `_search_window`), so a window's blocks are the strip's blocks. Returns, per span, None when
    nothing in the window is above the threshold, else two lists of block bounding boxes
    ``(bx, by, bw, bh)`` in the strip's block coordinates, brightest first, at most
    ``params.max_candidates`` each: small ones could be a blob on their own, large ones (the
    stripe) could only hold a marker merged with the stripe. A component touching a side of the
    window that is not a side of the strip or the image is left out: it may continue outside
    the window.
    """
    f = params.decimation
    r0, r1 = rows
    # Plain Python on the few components: numpy's per-call overheads would cost more here.
    nbr = _pooling.pooled_shape(r1 - r0, 1, f)[0]
    widths = [_pooling.pooled_shape(1, w1 - w0, f)[1] for _, _, w0, w1 in spans]
    pooled = np.empty((nbr, sum(widths)), np.uint8)
    thr = _threshold_int(params)
    cols = np.array([(w0, w1) for _, _, w0, w1 in spans], dtype=np.int64)
    _, stats = _pooling.pool_components(image, r0, r1, cols, f, thr, pooled)
    # A window whose pooled maximum is not above the threshold has no components: rejected.
    per_window = [[] for _ in spans]
    for row in stats.tolist():
        per_window[row[_pooling.STAT_WINDOW]].append(row)
    # Largest blob diameter allowed by max_area_px, in blocks (+1 for block alignment).
    max_blocks = math.ceil(2.0 * math.sqrt(params.max_area_px / math.pi) / f) + 1
    top, bottom = r0 > 0, r1 < image.shape[0]
    out = []
    for k, (c0, c1, w0, w1) in enumerate(spans):
        mine = per_window[k]
        if not mine:
            out.append(None)
            continue
        nbc = widths[k]
        bx0, by0 = (w0 - c0) // f, r0 // f
        if len(mine) > params.max_candidates:
            # Too many to examine all: the brightest first (a stable sort).
            mine = sorted(mine, key=lambda row: -row[_pooling.STAT_PEAK])
        small, large = [], []
        for bx, by, bw, bh, *_ in mine:
            if ((w0 > c0 and bx == 0) or (w1 < c1 and bx + bw == nbc)
                    or (top and by == 0) or (bottom and by + bh == nbr)):
                continue
            box = (bx0 + bx, by0 + by, bw, bh)
            (small if max(bw, bh) <= max_blocks else large).append(box)
        out.append((small[: params.max_candidates], large[: params.max_candidates]))
    return out


def _threshold_int(params: MarkerParams) -> int:
    """The threshold as an integer: for uint8 ``v``, ``v > threshold_dn`` iff ``v > floor(it)``."""
    return int(math.floor(params.threshold_dn))


def _blob_seeds(image, c0, c1, boxes, params: MarkerParams) -> np.ndarray:
    """(K, 2) centroids (x, y) of the blob-like full-resolution components in pooled boxes
    (``marker_kernels.blob_seeds``)."""
    if not boxes:
        return np.zeros((0, 2))
    return mk.blob_seeds(image, c0, c1, np.asarray(boxes, dtype=np.int64).reshape(-1, 4),
                         params.decimation, _threshold_int(params), params.min_area_px,
                         params.max_area_px, float(params.max_elongation),
                         params.max_candidates)


def _merged_cores(image, c0, c1, box, params: MarkerParams) -> list[tuple[float, float]]:
    """Marker-core seeds (x, y) inside a large component: what survives a disc erosion."""
    r0, r1, q0, q1 = mk.region(*box, params.decimation, c0, c1, image.shape[0])
    binary = (image[r0:r1, q0:q1] > params.threshold_dn).view(np.uint8)
    d = 2 * params.core_radius_px + 1
    core = cv2.erode(binary, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d)))
    n, _, _, centroids = cv2.connectedComponentsWithStats(core, connectivity=8)
    return [(q0 + cx, r0 + cy) for cx, cy in centroids[1 : params.max_candidates + 1]]


# ---------------------------------------------------------------------------------------------
# Sub-pixel centre


def _find_in_strips(image, ranges, params: MarkerParams, near=None, half: float = 0.0
                    ) -> list[tuple[float, float] | None]:
    """The marker (x, y) or None in each strip ``(c0, c1)`` of `ranges`: near the prediction
    ``near[k]`` (x, y) if there is one and the marker is found there, else in the whole strip
    (the remaining strips together, in one pass over the frame)."""
    height = image.shape[0]
    found = [None] * len(ranges)
    todo = []
    halves = (min(float(params.near_px), half), half) if params.near_px < half else (half,)
    for k, (c0, c1) in enumerate(ranges):
        for h in halves if near is not None else ():
            window = _search_window(near[k], h, c0, c1, height, params.decimation)
            if window is None:
                break
            r0, r1, w0, w1 = window
            found[k] = _search(image, (r0, r1), [(c0, c1, w0, w1)], params)[0]
            if found[k] is not None:
                break
        if found[k] is None:
            todo.append(k)
    if todo:
        spans = [(*ranges[k], *ranges[k]) for k in todo]
        for k, best in zip(todo, _search(image, (0, height), spans, params)):
            found[k] = best
    return found


def _search(image, rows, spans, params: MarkerParams) -> list[tuple[float, float] | None]:
    """Steps 1-5 (module docstring) in windows of strips (see `_pooled_candidates`)."""
    out = []
    for (c0, c1, _, _), candidates in zip(spans, _pooled_candidates(image, rows, spans, params)):
        if candidates is None:
            out.append(None)
            continue
        small, large = candidates
        seeds = _blob_seeds(image, c0, c1, small, params)
        best = _best_fit(image, c0, c1, seeds, params, merged=False)
        if best is None and large:
            seeds = [s for box in large for s in _merged_cores(image, c0, c1, box, params)]
            best = _best_fit(image, c0, c1, seeds, params, merged=True)
        out.append(best)
    return out


def _best_fit(image, c0, c1, seeds, params: MarkerParams, merged: bool):
    """Refine every seed (``marker_kernels.fit_window``); the accepted fit (x, y) with the
    largest amplitude, or None."""
    if len(seeds) == 0:
        return None
    se_core, se_near, se_flank = _structuring_elements(params.core_radius_px)
    x, y, found = mk.best_fit(
        image, c0, c1, np.asarray(seeds, dtype=np.float64).reshape(-1, 2), merged,
        params.max_candidates, params.half_window_px, float(params.threshold_dn),
        float(params.sigma_px), float(params.outlier_dn), _FIT_TOL_PX, _FIT_MAX_ITER,
        _FIT_MAX_ROUNDS, 0.5 * params.threshold_dn, float(params.max_residual),
        float(params.max_masked_fraction), _WIDTH_RANGE[0], _WIDTH_RANGE[1], se_core, se_near,
        se_flank)
    return (x, y) if found else None


@functools.lru_cache(maxsize=8)
def _structuring_elements(r: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The stripe mask's discs (bool): the marker core's (radius ``r``), the core grown by
    2 px, and the 5 x 5 square that covers the stripe's flanks (``marker_kernels.stripe_mask``)."""
    core = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2).astype(bool)
    near = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 5,) * 2).astype(bool)
    return core, near, np.ones((5, 5), bool)
