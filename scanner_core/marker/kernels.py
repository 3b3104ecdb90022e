"""The marker search's numba kernels: seeds in pooled boxes, the stripe mask, the fit.

``scanner_core.marker.finder`` runs the search (its module docstring gives the steps); these are its
per-candidate steps in compiled code, so that a tracked search (a window of each view, every
frame) costs few calls from Python: the blob-like full-resolution components of a pooled
block box (step 2), the mask of the stripe's pixels around a marker merged with it (step 3),
and the sub-pixel fit with its window that follows the estimate and its acceptance (step 4),
the brightest accepted fit kept (step 5). Written as ``marker`` did them in Python, result
for result: the same seeds, the same windows, the same fits.

Image convention: pixel centres at integer coordinates, (column, row) = (x, y).
"""
from __future__ import annotations

import math

import numba
import numpy as np

from scanner_core.numeric import pooling as _pooling
from scanner_core.numeric.linsolve import solve_in_place

__all__ = ["blob_seeds", "best_fit", "stripe_mask", "fit_window"]

# The sensor's saturation value: clipped pixels carry no amplitude information.
SATURATED_DN = 255
# Full-resolution margin around a pooled candidate's block bounding box (px).
REGION_PAD_PX = 2
# The fit's window follows its estimate at most this many times (recentred when the estimate
# drifts by more than half a pixel from the window's centre).
RECENTRE_TRIES = 3


@numba.njit(cache=True, nogil=True)
def region(bx, by, bw, bh, f, c0, c1, height):
    """Full-resolution (r0, r1, q0, q1) rows/columns of a pooled block box, padded, clipped."""
    q0 = max(c0, c0 + bx * f - REGION_PAD_PX)
    q1 = min(c1, c0 + (bx + bw) * f + REGION_PAD_PX)
    r0 = max(0, by * f - REGION_PAD_PX)
    r1 = min(height, (by + bh) * f + REGION_PAD_PX)
    return r0, r1, q0, q1


@numba.njit(cache=True, nogil=True)
def elongation(n, sx, sy, sxx, syy, sxy):
    """Ratio of principal axes of `n` pixels from their integer coordinate sums (each pixel a
    unit square: +1/12 variance). Central moments ``n * sxx - sx^2`` are exact integers."""
    n2 = n * n
    cxx = (n * sxx - sx * sx) / n2 + 1.0 / 12.0
    cyy = (n * syy - sy * sy) / n2 + 1.0 / 12.0
    cxy = (n * sxy - sx * sy) / n2
    half_trace = 0.5 * (cxx + cyy)
    root = math.sqrt(max(0.25 * (cxx - cyy) ** 2 + cxy * cxy, 0.0))
    return math.sqrt((half_trace + root) / (half_trace - root))


@numba.njit(cache=True, nogil=True)
def blob_seeds(image, c0, c1, boxes, f, thr, min_area, max_area, max_elongation,
               max_candidates):
    """Centroids (x, y) of the blob-like full-resolution components in pooled block boxes.

    For each box ``(bx, by, bw, bh)`` (blocks of ``f`` px, strip ``[c0, c1)``), the pixels above
    ``thr`` in its padded region are labelled (``_pooling.pool_components`` with blocks of 1)
    and the first ``max_candidates`` components kept when their area lies in
    ``[min_area, max_area]`` and their elongation is at most ``max_elongation``.

    Returns
    -------
    (K, 2) float64
        The seeds, box after box.
    """
    out = np.empty((boxes.shape[0] * max_candidates, 2))
    k = 0
    cols = np.empty((1, 2), np.int64)
    for b in range(boxes.shape[0]):
        r0, r1, q0, q1 = region(boxes[b, 0], boxes[b, 1], boxes[b, 2], boxes[b, 3], f, c0, c1,
                                image.shape[0])
        cols[0, 0] = q0
        cols[0, 1] = q1
        copy = np.empty((r1 - r0, q1 - q0), np.uint8)
        _, stats = _pooling.pool_components(image, r0, r1, cols, 1, thr, copy)
        for i in range(min(stats.shape[0], max_candidates)):
            area = stats[i, _pooling.STAT_AREA]
            if not (min_area <= area <= max_area):
                continue
            sx = stats[i, _pooling.STAT_SX]
            sy = stats[i, _pooling.STAT_SY]
            if elongation(area, sx, sy, stats[i, _pooling.STAT_SXX], stats[i, _pooling.STAT_SYY],
                          stats[i, _pooling.STAT_SXY]) > max_elongation:
                continue
            # Integer sums: the centroid is the correctly rounded mean.
            out[k, 0] = q0 + sx / area
            out[k, 1] = r0 + sy / area
            k += 1
    return out[:k]


@numba.njit(cache=True, nogil=True)
def _erode(src, se):
    """Binary erosion by the structuring element ``se`` (odd square, anchored at its centre),
    pixels outside the image counting as on (OpenCV's default border for erosion)."""
    n, m = src.shape
    hy, hx = se.shape[0] // 2, se.shape[1] // 2
    out = np.zeros((n, m), np.bool_)
    for r in range(n):
        for c in range(m):
            on = True
            for dy in range(se.shape[0]):
                rr = r + dy - hy
                if rr < 0 or rr >= n:
                    continue
                for dx in range(se.shape[1]):
                    cc = c + dx - hx
                    if se[dy, dx] and 0 <= cc < m and not src[rr, cc]:
                        on = False
                        break
                if not on:
                    break
            out[r, c] = on
    return out


@numba.njit(cache=True, nogil=True)
def _dilate(src, se):
    """Binary dilation by the symmetric structuring element ``se``, pixels outside the image
    counting as off (OpenCV's default border for dilation)."""
    n, m = src.shape
    hy, hx = se.shape[0] // 2, se.shape[1] // 2
    out = np.zeros((n, m), np.bool_)
    for r in range(n):
        for c in range(m):
            if not src[r, c]:
                continue
            for dy in range(se.shape[0]):
                rr = r + dy - hy
                if rr < 0 or rr >= n:
                    continue
                for dx in range(se.shape[1]):
                    cc = c + dx - hx
                    if se[dy, dx] and 0 <= cc < m:
                        out[rr, cc] = True
    return out


@numba.njit(cache=True, nogil=True)
def stripe_mask(win, thr, se_core, se_near, se_flank):
    """(n, m) bool: above-threshold pixels of a window more than 2 px outside the marker core
    (what survives erosion by the core disc ``se_core``, grown back by ``se_near``: the disc +
    2 px), grown by ``se_flank`` (5 x 5) to cover the stripe's flanks below the threshold."""
    binary = win > thr
    near = _dilate(_erode(binary, se_core), se_near)
    return _dilate(binary & ~near, se_flank)


@numba.njit(cache=True, nogil=True)
def _window_origin(x, y, h, c0, c1, height):
    """Top-left (row, col) of the (2h+1)^2 window centred on round(x, y); (-1, -1) if it does
    not fit inside the strip and the image."""
    ix = int(round(x))
    iy = int(round(y))
    if ix - h < c0 or ix + h >= c1 or iy - h < 0 or iy + h >= height:
        return -1, -1
    return iy - h, ix - h


@numba.njit(cache=True, nogil=True)
def fit_window(image, c0, c1, x, y, merged, h, thr, sigma, outlier_dn, tol, max_iter,
               max_rounds, min_amp, max_residual, max_masked, width_lo, width_hi, se_core,
               se_near, se_flank):
    """Sub-pixel fit around a seed: ``(x, y, amplitude, accepted)`` in image coordinates.

    The window (``2 h + 1`` px square) follows the estimate if it drifts by more than half a
    pixel (at most ``RECENTRE_TRIES`` times); ``merged`` seeds come from a component shared
    with the stripe: the stripe's pixels away from the marker core are masked before the
    first fit (:func:`stripe_mask`), so that it starts unbiased. Accepted when the window
    fits the strip and the image, and the fit converged with an amplitude above ``min_amp``,
    a residual and a masked share within bounds, and a width within ``[width_lo, width_hi]``.
    """
    height = image.shape[0]
    amp = width = resid = masked = 0.0
    for _ in range(RECENTRE_TRIES):
        wr, wc = _window_origin(x, y, h, c0, c1, height)
        if wr < 0:
            return x, y, 0.0, False
        win = image[wr:wr + 2 * h + 1, wc:wc + 2 * h + 1]
        if merged:
            mask0 = stripe_mask(win, thr, se_core, se_near, se_flank)
        else:
            mask0 = np.zeros(win.shape, np.bool_)
        xr, yr, amp, _bg, width, resid, masked, status = fit_kernel(
            win, mask0, x - wc, y - wr, sigma, outlier_dn, tol, max_iter, max_rounds)
        if status != 0:
            return x, y, 0.0, False
        x_new, y_new = wc + xr, wr + yr
        recentred = round(x_new) == wc + h and round(y_new) == wr + h
        x, y = x_new, y_new
        if recentred:
            break
    if _window_origin(x, y, h, c0, c1, height)[0] < 0:
        return x, y, 0.0, False
    ok = (amp > min_amp and resid <= max_residual and masked <= max_masked
          and width_lo <= width / sigma <= width_hi)
    return x, y, amp, ok


@numba.njit(cache=True, nogil=True)
def best_fit(image, c0, c1, seeds, merged, max_candidates, h, thr, sigma, outlier_dn, tol,
             max_iter, max_rounds, min_amp, max_residual, max_masked, width_lo, width_hi,
             se_core, se_near, se_flank):
    """Fit the first ``max_candidates`` seeds (:func:`fit_window`); the accepted fit with the
    largest amplitude: ``(x, y, found)``."""
    best_x = best_y = math.nan
    best_amp = -math.inf
    found = False
    for k in range(min(seeds.shape[0], max_candidates)):
        x, y, amp, ok = fit_window(image, c0, c1, seeds[k, 0], seeds[k, 1], merged, h, thr,
                                   sigma, outlier_dn, tol, max_iter, max_rounds, min_amp,
                                   max_residual, max_masked, width_lo, width_hi, se_core,
                                   se_near, se_flank)
        if ok and amp > best_amp:
            best_x, best_y, best_amp, found = x, y, amp, True
    return best_x, best_y, found


@numba.njit(cache=True, nogil=True)
def gauss_factors(p, inv2s2, ex, ey):
    """The isotropic Gaussian is separable: ``exp(-((c - xc)^2 + (r - yc)^2) * inv2s2)`` is
    ``ey[r] * ex[c]``, so a window needs n + m exponentials instead of n * m (the fit's main
    cost). Fills ``ex`` (m,) and ``ey`` (n,) float64 for the centre ``p[0], p[1]``."""
    for c in range(ex.size):
        ex[c] = math.exp(-((c - p[0]) ** 2) * inv2s2)
    for r in range(ey.size):
        ey[r] = math.exp(-((r - p[1]) ** 2) * inv2s2)


@numba.njit(cache=True, nogil=True)
def gauss_cost(img, use, p, ex, ey):
    """Sum of squared residuals over the `use` pixels; ``ex``, ``ey`` are scratch."""
    ss = 0.0
    gauss_factors(p, 0.5 / (p[4] * p[4]), ex, ey)
    for r in range(img.shape[0]):
        for c in range(img.shape[1]):
            if use[r, c]:
                d = img[r, c] - p[3] - p[2] * (ey[r] * ex[c])
                ss += d * d
    return ss


@numba.njit(cache=True, nogil=True)
def fit_kernel(win, mask0, x0, y0, sigma, outlier_dn, tol, max_iter, max_rounds):
    """Least-squares fit of b + A exp(-((x-xc)^2 + (y-yc)^2) / (2 s^2)) to a window.

    Levenberg-Marquardt over (xc, yc, A, b, s) on the valid pixels: not saturated (censored,
    their true value is unknown) and not masked. After convergence, pixels brighter than the
    model by more than `outlier_dn` (a stripe touching the marker) are masked with their
    8-neighbours and the fit repeated until the mask stops growing.

    win : (n, m) uint8 window; mask0 : (n, m) bool, pixels known not to be the marker (the
    stripe); x0, y0 : seed in window coordinates, px; sigma : seed width, px.
    Each round runs at most `max_iter` iterations; only the last round (mask settled) must
    converge. Returns (xc, yc, A, b, s, rel_rms_residual, masked_fraction, status); status
    0 = ok, 1 = singular system, 2 = no convergence (or mask still growing), 3 = left the window.

    The Gaussian is evaluated as a product of row and column factors (`gauss_factors`) and the
    normal equations are summed in scalars: 4.5 times faster than one exponential per pixel
    (3000 synthetic windows, with and without a stripe), with the same status on every window
    and centres within 4e-15 px of the per-pixel version.
    """
    n, m = win.shape
    img = win.astype(np.float64)
    sat = img >= 255.0
    mask = mask0.copy()
    use = ~(sat | mask)
    # Seed: background from the window border, amplitude from the seed pixel.
    border = np.concatenate((img[0, :], img[n - 1, :], img[:, 0], img[:, m - 1]))
    p = np.empty(5)
    p[0] = x0
    p[1] = y0
    p[3] = np.median(border)
    p[2] = max(img[min(max(int(round(y0)), 0), n - 1), min(max(int(round(x0)), 0), m - 1)]
               - p[3], 1.0)
    p[4] = sigma
    jtj = np.empty((5, 5))
    jtr = np.empty(5)
    ex = np.empty(m)
    ey = np.empty(n)
    converged = False
    for _round in range(max_rounds):
        lam = 1e-3
        cost = gauss_cost(img, use, p, ex, ey)
        converged = False
        for _it in range(max_iter):
            xc, yc, amp, bg, s = p[0], p[1], p[2], p[3], p[4]
            inv_s2 = 1.0 / (s * s)
            gauss_factors(p, 0.5 * inv_s2, ex, ey)
            # Normal equations J^T J, J^T r accumulated in scalars (upper triangle), which
            # stay in registers; the Jacobian per pixel is (g0, ..., g4).
            a00 = a01 = a02 = a03 = a04 = a11 = a12 = a13 = a14 = 0.0
            a22 = a23 = a24 = a33 = a34 = a44 = 0.0
            b0 = b1 = b2 = b3 = b4 = 0.0
            for r in range(n):
                for c in range(m):
                    if not use[r, c]:
                        continue
                    dx = c - xc
                    dy = r - yc
                    d2 = dx * dx + dy * dy
                    e = ey[r] * ex[c]
                    ae = amp * e
                    res = img[r, c] - bg - ae
                    g0 = ae * dx * inv_s2
                    g1 = ae * dy * inv_s2
                    g2 = e
                    g4 = ae * d2 * inv_s2 / s
                    # g3 = 1 (background)
                    b0 += g0 * res
                    b1 += g1 * res
                    b2 += g2 * res
                    b3 += res
                    b4 += g4 * res
                    a00 += g0 * g0
                    a01 += g0 * g1
                    a02 += g0 * g2
                    a03 += g0
                    a04 += g0 * g4
                    a11 += g1 * g1
                    a12 += g1 * g2
                    a13 += g1
                    a14 += g1 * g4
                    a22 += g2 * g2
                    a23 += g2
                    a24 += g2 * g4
                    a33 += 1.0
                    a34 += g4
                    a44 += g4 * g4
            jtr[0], jtr[1], jtr[2], jtr[3], jtr[4] = b0, b1, b2, b3, b4
            jtj[0, 0], jtj[0, 1], jtj[0, 2], jtj[0, 3], jtj[0, 4] = a00, a01, a02, a03, a04
            jtj[1, 1], jtj[1, 2], jtj[1, 3], jtj[1, 4] = a11, a12, a13, a14
            jtj[2, 2], jtj[2, 3], jtj[2, 4] = a22, a23, a24
            jtj[3, 3], jtj[3, 4] = a33, a34
            jtj[4, 4] = a44
            for i in range(5):
                for j in range(i):
                    jtj[i, j] = jtj[j, i]
            improved = False
            step = np.zeros(5)
            for _try in range(12):
                a = jtj.copy()
                for i in range(5):
                    a[i, i] *= 1.0 + lam
                step = jtr.copy()
                if not solve_in_place(a, step):
                    return p[0], p[1], p[2], p[3], p[4], np.inf, 1.0, 1
                trial = p + step
                if trial[4] > 0.0:
                    new_cost = gauss_cost(img, use, trial, ex, ey)
                    if new_cost <= cost:
                        p = trial
                        cost = new_cost
                        lam = max(lam * 0.1, 1e-9)
                        improved = True
                        break
                lam *= 10.0
            if p[0] < 0.0 or p[0] > m - 1.0 or p[1] < 0.0 or p[1] > n - 1.0:
                return p[0], p[1], p[2], p[3], p[4], np.inf, 1.0, 3
            if not improved or (abs(step[0]) < tol and abs(step[1]) < tol):
                # No cost decrease possible any more is convergence at a minimum too.
                converged = True
                break
        # Outliers: far above the model, with their 8-neighbours. The mask only
        # grows (rounds are bounded by max_rounds); masking costs precision, not bias.
        grown = False
        gauss_factors(p, 0.5 / (p[4] * p[4]), ex, ey)
        for r in range(n):
            for c in range(m):
                model = p[3] + p[2] * (ey[r] * ex[c])
                # A saturated pixel that the blob alone would not saturate is an outlier too.
                if img[r, c] - model > outlier_dn:
                    for rr in range(max(r - 1, 0), min(r + 2, n)):
                        for cc in range(max(c - 1, 0), min(c + 2, m)):
                            if not mask[rr, cc]:
                                mask[rr, cc] = True
                                grown = True
        if not grown:
            break
        use = ~(sat | mask)
        converged = False
    if not converged:
        # Either the last fit did not converge or the mask was still growing.
        return p[0], p[1], p[2], p[3], p[4], np.inf, 1.0, 2
    # Fit quality inside 2 s of the centre.
    ss = 0.0
    cnt = 0
    n_core = 0
    n_masked = 0
    gauss_factors(p, 0.5 / (p[4] * p[4]), ex, ey)
    for r in range(n):
        for c in range(m):
            d2 = (c - p[0]) ** 2 + (r - p[1]) ** 2
            if d2 <= 4.0 * p[4] * p[4]:
                n_core += 1
                if mask[r, c]:
                    n_masked += 1
                elif not sat[r, c]:
                    res = img[r, c] - p[3] - p[2] * (ey[r] * ex[c])
                    ss += res * res
                    cnt += 1
    if cnt == 0 or p[2] <= 0.0:
        return p[0], p[1], p[2], p[3], p[4], np.inf, 1.0, 1
    return p[0], p[1], p[2], p[3], p[4], math.sqrt(ss / cnt) / p[2], n_masked / max(n_core, 1), 0
