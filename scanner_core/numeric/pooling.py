"""Max-pooling and sparse connected components in one row-major pass, for numba-fast searches.

The marker search (``scanner_core.marker.finder``) looks for bright blobs on a max-pooled copy of each
view strip. Done with numpy (strided maxima) and OpenCV (connected components of the whole pooled
strip) it cost about 15 times a copy of the frame; here one kernel reads each pixel once, row
after row (the order the frame lies in memory, docs/design.md "Frame processing"), writes the block
maxima and labels the above-threshold blocks as runs, so that the labelling costs in proportion to
the bright blocks, not to the strip. Several strips side by side are pooled in the same pass: one
pass per strip reads each image row in pieces, which costs three times as much on frames not in
cache (1920 x 1200, three views: 0.39 ms one by one, 0.12 ms in one pass; a copy 0.11 ms).
With a block size of 1 the same kernel labels a full-resolution window and gives each
component's pixel moments.
"""
from __future__ import annotations

import numpy as np
from numba import njit

#: Columns of the ``stats`` array returned by :func:`pool_components`: bounding box in blocks
#: (x, y, width, height), area in blocks, largest block value (DN), the integer moments of the
#: component's block coordinates (sums of x, y, x^2, y^2, x*y), all relative to the component's
#: window, and the index of that window.
STAT_X, STAT_Y, STAT_W, STAT_H, STAT_AREA, STAT_PEAK = 0, 1, 2, 3, 4, 5
STAT_SX, STAT_SY, STAT_SXX, STAT_SYY, STAT_SXY, STAT_WINDOW = 6, 7, 8, 9, 10, 11
N_STATS = 12

# Initial capacity of the run table (runs of consecutive above-threshold blocks in a row); it
# doubles when full. A marker is a few runs, the stripe one or two per block row.
_RUN_CAPACITY = 256


def pooled_shape(rows: int, cols: int, f: int) -> tuple[int, int]:
    """Shape ``(ceil(rows / f), ceil(cols / f))`` of a window pooled in ``f x f`` blocks."""
    return -(-rows // f), -(-cols // f)


def pooled_layout(cols: np.ndarray, f: int) -> np.ndarray:
    """(K + 1,) int64 first block column of each window in the joint pooled array, then its width.

    ``cols`` is (K, 2) int64, the windows' column ranges ``[start, stop)``.
    """
    widths = -(-(cols[:, 1] - cols[:, 0]) // f)
    return np.concatenate(([0], np.cumsum(widths))).astype(np.int64)


@njit(nogil=True, cache=True)
def _find(parent, k):
    """Root of run ``k`` (path halving)."""
    while parent[k] != k:
        parent[k] = parent[parent[k]]
        k = parent[k]
    return k


@njit(nogil=True, cache=True)
def _grow(runs, parent):
    """Twice the capacity, contents kept."""
    n = runs.shape[0]
    new_runs = np.empty((2 * n, runs.shape[1]), np.int64)
    new_runs[:n] = runs
    new_parent = np.empty(2 * n, np.int64)
    new_parent[:n] = parent
    return new_runs, new_parent


@njit(nogil=True, cache=True)
def _block_max(tmp, start, w, f, out):
    """``out[k] = max(tmp[start + k * f : start + min((k + 1) * f, w)])`` for each block of a
    window ``w`` columns wide (the last block holds what is left).

    The usual block size 4 has its own loop: with a literal stride LLVM vectorises the strided
    loads (about 40 times faster than the loop over a run-time ``f``). The window is indexed
    from 0 through a view: an offset added to the index (``start + 4 * k``) stops the
    vectorisation (10 times slower).
    """
    t = tmp[start : start + w]
    full = w // f
    if f == 4:
        for k in range(full):
            a = 4 * k
            out[k] = max(max(t[a], t[a + 1]), max(t[a + 2], t[a + 3]))
    elif f == 1:
        for k in range(full):
            out[k] = t[k]
    else:
        for k in range(full):
            a = k * f
            m = t[a]
            for j in range(a + 1, a + f):
                m = max(m, t[j])
            out[k] = m
    if full * f < w:
        a = full * f
        m = t[a]
        for j in range(a + 1, w):
            m = max(m, t[j])
        out[full] = m


@njit(nogil=True, cache=True)
def pool_components(img, r0, r1, cols, f, thr, pooled):
    """Max-pool windows in ``f x f`` blocks and label their 8-connected above-threshold blocks.

    Parameters
    ----------
    img : (H, W) uint8, C-contiguous
        The full image.
    r0, r1 : int
        Rows ``[r0, r1)`` of every window; blocks start at row ``r0`` and the last block row
        holds what is left (``(r1 - r0) % f`` rows).
    cols : (K, 2) int64
        Column range ``[start, stop)`` of each window (they may overlap: each is labelled on
        its own); blocks start at ``start`` and the last block column of a window holds what is
        left. The pass reads the columns from the smallest start to the largest stop.
    f : int
        Block size, >= 1 (1: no pooling, the windows themselves are labelled).
    thr : int
        Blocks whose maximum is strictly above ``thr`` (DN) are "on".
    pooled : (ceil((r1 - r0) / f), B) uint8
        Output: the block maxima, window ``k`` in columns ``layout[k]:layout[k + 1]`` of
        ``layout = pooled_layout(cols, f)``.

    Returns
    -------
    peak : (K,) int64
        Largest pixel value in each window, DN.
    stats : (n, N_STATS) int64
        One row per 8-connected component of on blocks (components never span two windows), in
        raster order of each component's first block within its window (columns ``STAT_*``).
    """
    n_win = cols.shape[0]
    layout = np.empty(n_win + 1, np.int64)
    layout[0] = 0
    lo = cols[0, 0]
    hi = cols[0, 1]
    for k in range(n_win):
        layout[k + 1] = layout[k] + (cols[k, 1] - cols[k, 0] + f - 1) // f
        lo = min(lo, cols[k, 0])
        hi = max(hi, cols[k, 1])
    w = hi - lo
    nbr = pooled.shape[0]
    # Column maxima of one block row over the span of all windows.
    tmp = np.empty(w, np.uint8)
    # Runs: block row, first and last block column, largest value, window; union-find parents.
    runs = np.empty((_RUN_CAPACITY, 5), np.int64)
    parent = np.empty(_RUN_CAPACITY, np.int64)
    n_runs = 0
    # Runs of the previous block row, per window: [prev_start, prev_stop).
    prev_start = np.zeros(n_win, np.int64)
    prev_stop = np.zeros(n_win, np.int64)
    peak = np.zeros(n_win, np.int64)
    for br in range(nbr):
        ra = r0 + br * f
        rb = min(ra + f, r1)
        # Column maxima over the block's rows: contiguous uint8 rows, so the loop vectorises.
        first = img[ra, lo:hi]
        for j in range(w):
            tmp[j] = first[j]
        for r in range(ra + 1, rb):
            row = img[r, lo:hi]
            for j in range(w):
                tmp[j] = max(tmp[j], row[j])
        for win in range(n_win):
            out = pooled[br, layout[win] : layout[win + 1]]
            nbc = out.size
            _block_max(tmp, cols[win, 0] - lo, cols[win, 1] - cols[win, 0], f, out)
            row_max = np.uint8(0)
            for bc in range(nbc):
                row_max = max(row_max, out[bc])
            peak[win] = max(peak[win], np.int64(row_max))
            row_start = n_runs
            if row_max <= thr:
                # Nothing on in this block row (the usual case): no runs to label.
                prev_start[win] = prev_stop[win] = n_runs
                continue
            # Runs of on blocks, each joined to the runs of the previous row it touches (8-conn.).
            p = prev_start[win]
            p_stop = prev_stop[win]
            bc = 0
            while bc < nbc:
                if out[bc] <= thr:
                    bc += 1
                    continue
                a = bc
                m = out[bc]
                while bc < nbc and out[bc] > thr:
                    m = max(m, out[bc])
                    bc += 1
                b = bc - 1
                if n_runs == runs.shape[0]:
                    runs, parent = _grow(runs, parent)
                k = n_runs
                n_runs += 1
                runs[k, 0] = br
                runs[k, 1] = a
                runs[k, 2] = b
                runs[k, 3] = m
                runs[k, 4] = win
                parent[k] = k
                # Previous-row runs ending left of a - 1 touch neither this run nor later ones.
                while p < p_stop and runs[p, 2] < a - 1:
                    p += 1
                q = p
                while q < p_stop and runs[q, 1] <= b + 1:
                    # Union, the older run (raster order) as the root.
                    rq = _find(parent, q)
                    rk = _find(parent, k)
                    if rq < rk:
                        parent[rk] = rq
                    elif rk < rq:
                        parent[rq] = rk
                    q += 1
            prev_start[win] = row_start
            prev_stop[win] = n_runs
    return peak, _run_stats(runs, parent, n_runs)


@njit(nogil=True, cache=True)
def _run_stats(runs, parent, n_runs):
    """Per-component statistics (``STAT_*`` columns) from the labelled runs, components in the
    order of their oldest run (the root: unions keep the smaller index)."""
    label = np.empty(n_runs, np.int64)
    n = 0
    for k in range(n_runs):
        root = _find(parent, k)
        if root == k:
            label[k] = n
            n += 1
        else:
            label[k] = label[root]
    stats = np.zeros((n, N_STATS), np.int64)
    x1 = np.empty(n, np.int64)
    y1 = np.empty(n, np.int64)
    for k in range(n_runs):
        lab = label[k]
        y = runs[k, 0]
        a = runs[k, 1]
        b = runs[k, 2]
        cnt = b - a + 1
        s = stats[lab]
        if s[STAT_AREA] == 0:
            s[STAT_X] = a
            s[STAT_Y] = y
            s[STAT_WINDOW] = runs[k, 4]
            x1[lab] = b
            y1[lab] = y
        else:
            s[STAT_X] = min(s[STAT_X], a)
            x1[lab] = max(x1[lab], b)
            y1[lab] = max(y1[lab], y)
        s[STAT_AREA] += cnt
        s[STAT_PEAK] = max(s[STAT_PEAK], runs[k, 3])
        sx = (a + b) * cnt // 2
        # Sum of x^2 for x = a..b, from the closed form of sum_{x<=k} x^2 = k(k+1)(2k+1)/6.
        sxx = (b * (b + 1) * (2 * b + 1) - (a - 1) * a * (2 * a - 1)) // 6
        s[STAT_SX] += sx
        s[STAT_SY] += y * cnt
        s[STAT_SXX] += sxx
        s[STAT_SYY] += y * y * cnt
        s[STAT_SXY] += y * sx
    for lab in range(n):
        stats[lab, STAT_W] = x1[lab] - stats[lab, STAT_X] + 1
        stats[lab, STAT_H] = y1[lab] - stats[lab, STAT_Y] + 1
    return stats
