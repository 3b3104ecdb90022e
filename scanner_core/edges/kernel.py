"""The compiled kernel of the per-profile edge detection (``scanner_core.edges.profile
.find_edges``): plain loops over one profile, compiled once (``cache=True``), no GIL held.

`_edges_kernel` walks the profile's stretches of stripe: it removes specks, estimates the
range noise, places a drop-out's point at each end of a stretch that a gap of dark columns
follows (`_dropout`, with its side's level, flank, bends and curls and the stripe's end for
``scanner_core.edges.filters.chamfered_dropouts``) and a step's at each run of jumps in range
(`_step`, resolved between columns or at the near side's end, `_near_end`). The method is
described in ``scanner_core.edges``; the constants below are its tuning, measured where
their comments say.

One concern that reads best whole, and one module by necessity: numba's cache checks only
the file of the function it compiled, so a helper or a constant of this kernel kept in
another module could change without the cached kernel being compiled again.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from scanner_core.geometry import PARALLEL_COS

#: A step is resolved over adjacent columns (interpolated there) when the segment that holds
#: its half-height level spans at most this fraction of the step height; a larger share means
#: the jump happened within one column and the wall's position is only known to that column.
RESOLVED_STEP_FRACTION = 0.5
#: A drop-out's falling flank goes on inward while the next column is brighter by more than
#: this fraction: well above the speckle's column-to-column change (contrast 0.1 smoothed over
#: about 3 columns), well below a blurred edge's rise until its last few percent.
FLANK_RISE = 0.05
#: A drop-out side's intensity level is the median peak of this many columns from the top of
#: its flank inward: few enough to stay on a narrow face next to the gap (a 4-column chamfer).
LEVEL_PX = 3
#: A drop-out's flank stops where the stripe's row step changes by more than this between
#: neighbouring columns, px: a face turned against the one inward (a chamfer), whose dimmer
#: stripe keeps its own level. A blurred flank on one face keeps its rows' trend; the idler's
#: 45-degree chamfers turned them by 0.4 to 0.6 px, noise and partly lit end columns by up
#: to about 0.2 px.
ROW_BEND_PX = 0.25
#: ... and by more than this many times the turn's noise (sqrt(6) times the rows' scatter).
BEND_NOISE_FACTOR = 3.0
#: A step with a side cut short (fewer than side_px points before another edge or the end
#: of the stripe) must be this many times the step threshold high: a chamfer at the rim of a
#: larger step or of the outline reads as a step just over the threshold (the idler's 45
#: degree chamfers beside its 8.6 mm steps: 0.3 mm, about 100 um off every edge), while the
#: larger step beside it, cut short by the chamfer, stays.
SHORT_SIDE_STEP_FACTOR = 2.0
#: A side whose rows turn steadily over its last points before the end (by at least this
#: much in all, px, no one turn more than CURL_SHARE of it) ends on a surface curving away
#: from the camera or the sheet, not at an edge: cycloidal's rounded lobes turned the rows by
#: 0.2 to 0.45 px over 3 turns and ended 0.1 to 0.45 mm short of every CAD edge. A chamfer
#: turns them at one kink. CURL_MAX_TURNS turns are judged; a side too short for them (a
#: stretch of stripe 4 or 5 columns long across a lobe's crest) over the turns it has, at
#: least CURL_MIN_TURNS. Noisier profiles need CURL_NOISE_FACTOR times their rows' scatter
#: (2.5 sigma of the turn over 3 steps): on a level stripe with 0.1 px of row noise the test
#: took 10 of 8000 ends for curls (4 at 3 sigma, which kept two lobe ends 0.37 and 0.38 mm
#: off in the bench's cycloidal scans).
CURL_PX = 0.2
CURL_SHARE = 0.7
CURL_NOISE_FACTOR = 5.0
CURL_MAX_TURNS = 3
CURL_MIN_TURNS = 2
#: The far side of a gap (a shadow's or an occlusion's boundary) must lie beyond the near one
#: by the step threshold plus this many standard errors of the two sides' lines extrapolated
#: to the gap's middle: across a 100-column gap at 0.1 px of row noise, the bare threshold
#: took a quarter of the holes' rims for shadows.
FAR_SIDE_SIGMAS = 3.0
#: A drop-out's face level, for :func:`chamfered_dropouts`: the median peak of END_FACE_PX
#: columns from END_FACE_FROM columns in from the stripe's end (past a chamfer up to two
#: columns wide).
END_FACE_FROM = 3
END_FACE_PX = 3
#: A column holding a second peak (``StripeResult.n_peaks``) beside a step's near side holds
#: that side's stripe on part of it: its share is taken as this fraction of the column's
#: chosen peak (:func:`_near_end`). Measured at the 5 mm step of the bracket with two holes
#: (``simulator.parts.bracket_with_two_holes``), its wall leaning 2 to 6 degrees under its top
#: edge: the second peak held 0.28-0.6 of the chosen one (10th-90th percentiles, median 0.41
#: to 0.5); 0.47-1.1 (median 0.62) where both sides lit the column in part at the wall's end.
#: Taken as none (the earlier default), the steps landed 0.34 px inside the near side on average
#: (step RMS 76 um at a 6-degree lean); as half the near side's level, 0.35 px past it at the
#: wall's ends; as 0.65 of the chosen peak (the middle of DOUBLE_PEAK_RATIO..1), 0.27 px past.
DOUBLE_SHARE = 0.45
#: MAD of a normal sample times this is its standard deviation.
MAD_TO_SIGMA = 1.4826
#: Fewest second differences for a noise estimate; with fewer, the threshold is min_step_mm.
MIN_NOISE_SAMPLES = 8


@njit(nogil=True, cache=True)
def _fit_line(x, y, lo, hi):
    """Least-squares line through points lo..hi-1, centred: (x_mean, y_mean, slope, Sxx), Sxx
    the sum of squared deviations of x (a prediction at x0 has variance per unit variance of
    one point 1/n + (x0 - x_mean)^2 / Sxx)."""
    m = hi - lo
    xm = 0.0
    ym = 0.0
    for i in range(lo, hi):
        xm += x[i]
        ym += y[i]
    xm /= m
    ym /= m
    sxx = 0.0
    sxy = 0.0
    for i in range(lo, hi):
        dx = x[i] - xm
        sxx += dx * dx
        sxy += dx * (y[i] - ym)
    slope = sxy / sxx if sxx > 0.0 else 0.0
    return xm, ym, slope, sxx


@njit(nogil=True, cache=True)
def _median_small(buf, m):
    """Median of buf[:m] (m >= 1), sorting it in place: insertion sort for a dozen values."""
    for i in range(1, m):
        v = buf[i]
        j = i - 1
        while j >= 0 and buf[j] > v:
            buf[j + 1] = buf[j]
            j -= 1
        buf[j + 1] = v
    half = m // 2
    return buf[half] if m % 2 == 1 else 0.5 * (buf[half - 1] + buf[half])


@njit(nogil=True, cache=True)
def _median_of(values, lo, hi):
    return _median_small(values[lo:hi].copy(), hi - lo)


@njit(nogil=True, cache=True)
def _peak_at(peak, c):
    """The peak of column c, DN; 0 outside the image or the processed columns (NaN)."""
    if c < 0 or c >= peak.shape[0]:
        return 0.0
    v = peak[c]
    return v if v == v else 0.0


@njit(nogil=True, cache=True)
def _triangulate(u, v, fx, fy, cx, cy, n, offset, out):
    """Pixel ray x light plane in {C} (Eq. 2); False when parallel or behind the camera."""
    x = (u - cx) / fx
    y = (v - cy) / fy
    den = x * n[0] + y * n[1] + n[2]
    if abs(den) <= PARALLEL_COS:
        return False
    s = offset / den
    if not s > 0.0:
        return False
    out[0] = x * s
    out[1] = y * s
    out[2] = s
    return True


@njit(nogil=True, cache=True)
def _cumulative(mask):
    """(W + 1,) int64: the number of True in mask[:c] at c."""
    out = np.zeros(mask.shape[0] + 1, np.int64)
    for c in range(mask.shape[0]):
        out[c + 1] = out[c] + (1 if mask[c] else 0)
    return out


@njit(nogil=True, cache=True)
def _segments(cols, dark_cum, min_gap, max_bridge):
    """Split the valid columns where a gap is a drop-out or too wide to bridge: the first and
    last index (into cols) of each stretch of stripe."""
    nv = cols.shape[0]
    starts = np.empty(nv, np.int64)
    ends = np.empty(nv, np.int64)
    s = 0
    starts[0] = 0
    for k in range(nv - 1):
        c, c_next = cols[k], cols[k + 1]
        n_dark = dark_cum[c_next] - dark_cum[c + 1]
        if n_dark >= min_gap or c_next - c - 1 > max_bridge:
            ends[s] = k
            s += 1
            starts[s] = k + 1
    ends[s] = nv - 1
    return starts[: s + 1], ends[: s + 1]


@njit(nogil=True, cache=True)
def _remove_specks(valid, dark, min_gap, max_bridge, min_run):
    """Stretches of fewer than min_run valid columns between drop-outs become dark, in place
    (removing one can merge two gaps: a second pass settles it)."""
    for _ in range(2):
        cols = np.nonzero(valid)[0]
        if cols.shape[0] == 0:
            return
        starts, ends = _segments(cols, _cumulative(dark), min_gap, max_bridge)
        removed = False
        for s in range(starts.shape[0]):
            if ends[s] - starts[s] + 1 < min_run:
                for k in range(starts[s], ends[s] + 1):
                    valid[cols[k]] = False
                    dark[cols[k]] = True
                removed = True
        if not removed:
            return


@njit(nogil=True, cache=True)
def _range_noise(cols, d, seg):
    """One point's range scatter, mm, robustly from second differences over three adjacent
    columns (a smooth surface's curvature is far below the noise there); NaN when too few."""
    nv = cols.shape[0]
    d2 = np.empty(max(nv, 1))
    n2 = 0
    for k in range(1, nv - 1):
        if cols[k] - cols[k - 1] == 1 and cols[k + 1] - cols[k] == 1 and seg[k - 1] == seg[k + 1]:
            d2[n2] = abs(d[k + 1] - 2.0 * d[k] + d[k - 1])
            n2 += 1
    if n2 < MIN_NOISE_SAMPLES:
        return math.nan
    return MAD_TO_SIGMA * np.median(d2[:n2].copy()) / math.sqrt(6.0)  # var(d2) = 6 var(d)


@njit(nogil=True, cache=True)
def _step_candidates(cols, vcol, d, seg, side_px, cand_threshold):
    """Jumps in range beyond the local slope: jump k joins points k and k+1 of one segment;
    the slope per column is the median of the jumps within side_px on both sides.

    Returns the residual jumps (mm) and which exceed cand_threshold."""
    nj = max(cols.shape[0] - 1, 0)
    resid = np.zeros(nj)
    cand = np.zeros(nj, np.bool_)
    window = np.empty(2 * side_px)
    # A jump between adjacent columns whose window holds no jump above cand_threshold / 2 is
    # no candidate whatever the median (|jump - slope| <= cand_threshold): the median is
    # skipped there, which is most of a frame.
    big_cum = np.zeros(nj + 1, np.int64)
    for k in range(nj):
        big_cum[k + 1] = big_cum[k] + (1 if abs(d[k + 1] - d[k]) > 0.5 * cand_threshold else 0)
    for k in range(nj):
        if seg[k] != seg[k + 1]:
            continue
        if (cols[k + 1] - cols[k] == 1
                and big_cum[min(k + side_px + 1, nj)] == big_cum[max(k - side_px, 0)]):
            continue
        m = 0
        for j in range(max(k - side_px, 0), min(k + side_px + 1, nj)):
            if j != k and seg[j] == seg[k] and seg[j + 1] == seg[k]:
                window[m] = (d[j + 1] - d[j]) / (vcol[j + 1] - vcol[j])
                m += 1
        slope = _median_small(window, m) if m > 0 else 0.0
        resid[k] = d[k + 1] - d[k] - slope * (vcol[k + 1] - vcol[k])
        cand[k] = abs(resid[k]) > cand_threshold
    return resid, cand


@njit(nogil=True, cache=True)
def _dropout(sign, k_lo, k_hi, k_other, o_lo, o_hi, cols, a, d, pts, vcol, vrow, vpeak, peak,
             valid, dark, side_px, threshold, noise, curl, bend, min_contrast, keep_far,
             background, fx, fy, cx, cy, n, offset, out_pc, out):
    """The drop-out edge at one end of a stripe (sign -1: its first column, +1: its last),
    into out_pc (point in {C}) and out (u, v, size, level, then :func:`_stripe_end`'s
    fields). False when there is none: the far side of a gap across a range step, a side too
    faint for its gap, or a ray that misses the sheet.

    k_other is the other side's end point (-1: the stripe does not come back), o_lo..o_hi-1
    the other side's points next to the gap."""
    k_end = k_lo if sign < 0 else k_hi
    c_end = cols[k_end]
    # this side: its side_px points next to the gap
    if sign < 0:
        lo, hi = k_lo, min(k_lo + side_px, k_hi + 1)
    else:
        lo, hi = max(k_hi - side_px + 1, k_lo), k_hi + 1
    if _curls(vrow, vcol, k_end, sign, lo, hi, curl):
        return False  # the stripe fades on a surface curving away: no edge there
    size = math.nan
    if k_other >= 0:
        size = math.sqrt((pts[k_other, 0] - pts[k_end, 0]) ** 2
                         + (pts[k_other, 1] - pts[k_end, 1]) ** 2
                         + (pts[k_other, 2] - pts[k_end, 2]) ** 2)
        # "discontinuities are evaluated by range": both sides at the middle of the gap
        xm, ym, sl, sxx = _fit_line(a, d, lo, hi)
        oxm, oym, osl, osxx = _fit_line(a, d, o_lo, o_hi)
        a_mid = 0.5 * (a[k_other] + a[k_end])
        rise = (ym + sl * (a_mid - xm)) - (oym + osl * (a_mid - oxm))
        # each side's line extrapolated across the gap: its error grows with the lever arm
        lever = (1.0 / (hi - lo) + ((a_mid - xm) ** 2 / sxx if sxx > 0.0 else 0.0)
                 + 1.0 / (o_hi - o_lo) + ((a_mid - oxm) ** 2 / osxx if osxx > 0.0 else 0.0))
        spread = noise * math.sqrt(lever)
        if rise > threshold + FAR_SIDE_SIGMAS * spread and not keep_far:
            return False  # this side is farther: the boundary of a shadow or an occlusion
    # the side's level: at the top of the edge's falling flank (a blurred edge falls over a
    # few columns), found walking in while the stripe keeps brightening; a dimmer face next to
    # the gap (a chamfer) keeps its own level
    k_top = k_end
    bent = False
    while lo <= k_top - sign < hi and vpeak[k_top - sign] > (1.0 + FLANK_RISE) * vpeak[k_top]:
        if _bends(vrow, vcol, k_top - sign, sign, lo, hi, k_end, bend):
            bent = True
            break
        k_top -= sign
    if bent:  # the level of the face the edge is on: from its first column to the end
        if sign < 0:
            level = _median_of(vpeak, max(k_top - LEVEL_PX + 1, k_end), k_top + 1)
        else:
            level = _median_of(vpeak, k_top, min(k_top + LEVEL_PX, k_end + 1))
    elif sign < 0:
        level = _median_of(vpeak, k_top, min(k_top + LEVEL_PX, k_hi + 1))
    else:
        level = _median_of(vpeak, max(k_top - LEVEL_PX + 1, k_lo), k_top + 1)
    # the gap's level: its first columns
    gap = np.empty(side_px)
    m = 0
    c = c_end + sign
    while c >= 0 and c < peak.shape[0] and m < side_px and dark[c]:
        if peak[c] == peak[c]:
            gap[m] = peak[c]
            m += 1
        c += sign
    gap_level = _median_small(gap, m) if m > 0 else 0.0
    if level < min_contrast * gap_level:
        return False  # a faint stripe fading into the noise: no step to halve
    if abs(c_end - cols[k_top]) <= 1.0:
        # a sharp end: no column but the last (and the gap's first) lit in part
        u = _sharp_end(peak, dark, c_end, sign, level, gap_level, background)
    else:
        half = 0.5 * (level + gap_level)  # half the relative step
        # the outermost column at or above half, walking in from the end; then interpolate
        c_in = c_end
        steps = 0
        while _peak_at(peak, c_in) < half and steps < hi - lo - 1:
            c_in -= sign
            steps += 1
        p_in = _peak_at(peak, c_in)
        p_out = _peak_at(peak, c_in + sign)
        f = (p_in - half) / (p_in - p_out) if p_in > p_out else 0.5
        u = c_in + sign * min(max(f, 0.0), 1.0)
    cxm, cym, csl, _ = _fit_line(vcol, vrow, lo, hi)  # the side's rows, extrapolated
    v = cym + csl * (u - cxm)
    if not _triangulate(u, v, fx, fy, cx, cy, n, offset, out_pc):
        return False
    out[0], out[1], out[2], out[3] = u, v, size, level
    _stripe_end(k_end, sign, lo, hi, c_end, u, v, csl, vcol, vrow, vpeak, background, bent, fx,
                fy, cx, cy, n, offset, out_pc, out)
    return True


@njit(nogil=True, cache=True)
def _sharp_end(peak, dark, c_end, sign, level, gap_level, background):
    """Where a sharp drop-out's face ends, px: the inner side of its last lit column `c_end`
    moved outward by that column's lit width and the first gap column's, each its peak's
    share of the face's over the background, ``(p - b) / (level - b)`` (DN); a peak no
    brighter than the gap's (`gap_level`: the noise's highest pixel, or a stripe too faint
    to be one) holds none.

    A column integrates the light over its width, so the share of a column lit in part is
    where the edge lies in it, at any place in the column. Where the flank crosses half the
    step, interpolated between two columns, is exact only at a column's sides and middle:
    off by up to 0.08 px in between, the same way on every edge that the columns cross at
    the same rate, as a part's parallel edges carried along the pass do, which turns them
    together. A blurred end (a flank over more columns) has no such bias to remove, and
    summing its columns' shares would add their speckle: it is left to the half step."""
    step = level - background
    if not step > 0.0:
        return c_end + 0.5 * sign
    width = 0.0
    for c in (c_end, c_end + sign):
        p = _peak_at(peak, c)
        if c != c_end and not (0 <= c < peak.shape[0] and dark[c]):
            break
        if p > gap_level:
            width += (p - background) / step
    return c_end - 0.5 * sign + sign * min(max(width, 0.0), 2.0)


@njit(nogil=True, cache=True)
def _stripe_end(k_end, sign, lo, hi, c_end, u, v, row_slope, vcol, vrow, vpeak, background,
                bent, fx, fy, cx, cy, n, offset, point, out):
    """What :func:`chamfered_dropouts` needs of a drop-out, into out[4:12]: its last two lit
    columns' peaks over the background as fractions of the face's (the median of the
    END_FACE_PX columns from END_FACE_FROM in), the distance from the point to the outer
    side of its last lit column (px), the end column's row off the line of the face's
    columns 2 to 5 in (px), whether its flank walk found a chamfer (`bent`: it is placed by
    that chamfer's own level): ``EdgePoints.stripe_end``; then how the point moves in {C}
    per px outward along the side's rows (mm; by the ideal pinhole, as the kernel's rays):
    ``EdgePoints.per_px_b`` once rotated. No levels where the side is
    too short, broken by a bridged gap, or no brighter than the background where its face
    should be."""
    for i in range(4, 12):
        out[i] = math.nan
    out[6] = (c_end + 0.5 * sign - u) * sign
    out[8] = 1.0 if bent else 0.0
    k_in = k_end - (END_FACE_FROM + END_FACE_PX - 1) * sign
    if (lo <= k_in < hi
            and abs(vcol[k_end] - vcol[k_in]) == END_FACE_FROM + END_FACE_PX - 1):
        f_lo = min(k_in, k_end - END_FACE_FROM * sign)
        face = _median_of(vpeak, f_lo, f_lo + END_FACE_PX) - background
        if face > 0.0:
            out[4] = (vpeak[k_end] - background) / face
            out[5] = (vpeak[k_end - sign] - background) / face
            # the face's rows from columns 2 to 5 in: three columns' line, extrapolated,
            # turned idler_riser's blurred ends 0.5-1.6 px off; a chamfer reaching into the
            # second column shrinks the offset, which only makes the test stricter
            g_lo = min(k_in, k_end - 2 * sign)
            fxm, fym, fsl, _ = _fit_line(vcol, vrow, g_lo, g_lo + END_FACE_PX + 1)
            out[7] = vrow[k_end] - (fym + fsl * (vcol[k_end] - fxm))
    moved = out[9:12]  # a view: no allocation per drop-out
    if _triangulate(u + sign, v + sign * row_slope, fx, fy, cx, cy, n, offset, moved):
        for i in range(3):
            moved[i] -= point[i]


@njit(nogil=True, cache=True)
def _bends(vrow, vcol, k, sign, lo, hi, k_end, bend):
    """Whether the stripe's rows turn at point k (toward the gap: sign): another face begins
    there, not a blurred flank of the same one. A 45-degree chamfer at a level face's rim
    moved the rows 0.4 to 0.6 px per column against under 0.1 px on the face, and its stripe
    faded toward the gap; walked over, it took the face's level and the edge landed a column
    short of its end (0.2 mm). The end point k_end is lit in part and its row is off by up
    to about 0.2 px: no turn is judged on it."""
    if not (lo <= k - sign < hi and lo <= k + sign < hi) or k + sign == k_end:
        return False
    if abs(vcol[k + sign] - vcol[k - sign]) != 2.0:
        return False  # across a bridged gap: no neighbouring columns to compare
    inner = vrow[k] - vrow[k - sign]
    outer = vrow[k + sign] - vrow[k]
    return abs(outer - inner) > bend


@njit(nogil=True, cache=True)
def _curls(vrow, vcol, k_end, sign, lo, hi, curl):
    """Whether a side's rows turn steadily over the row steps before its end point k_end
    (the side runs toward the gap or the wall along sign; lo..hi-1 are its points, or for a
    step its whole stretch of stripe), and their last step runs the way they turn: a surface
    past its crest, curving away until the stripe is lost on it, whose end is no edge of the
    part. Rows still rising into a crest at the end are not judged curled (the crest's end of
    a short stretch is an edge); a stretch with its crest in the middle has no edge at
    either end (a cylinder seen across its top). Up to CURL_MAX_TURNS turns are judged (the
    6 points up to k_end); a shorter side over the turns it has, at least CURL_MIN_TURNS. The
    end point itself is left out: lit in part, its row is off by up to about 0.2 px."""
    if sign > 0:
        before = k_end - lo
    else:
        before = hi - 1 - k_end
    turns = min(CURL_MAX_TURNS, before - 2)
    if turns < CURL_MIN_TURNS:
        return False
    far = k_end - (turns + 2) * sign
    if abs(vcol[k_end - sign] - vcol[far]) != turns + 1:
        return False  # across a bridged gap: no neighbouring columns to compare
    t0 = vrow[k_end - sign] - vrow[k_end - 2 * sign]
    t_far = vrow[far + sign] - vrow[far]
    total = t0 - t_far
    if abs(total) < curl:
        return False
    if t0 * total <= 0.0:
        return False  # still rising into a crest at the end: not a surface turning away
    for j in range(1, turns + 1):
        turn = ((vrow[k_end - j * sign] - vrow[k_end - (j + 1) * sign])
                - (vrow[k_end - (j + 1) * sign] - vrow[k_end - (j + 2) * sign]))
        if turn * total <= 0.0 or abs(turn) > CURL_SHARE * abs(total):
            return False
    return True


@njit(nogil=True, cache=True)
def _near_end(near, toward, nlo, nhi, cols, vpeak, double, peak):
    """Column (sub-pixel) where the near side's stripe ends at a step within one column.

    The pixel column holding the wall is lit in part by each side's stripe (in proportion to
    the share of the pixel each surface covers); the near side's stripe is taken to end where
    its intensity falls to half its level, as a drop-out's: between its last column (bright
    in part when the wall lies within it) and the next one. The next column, when it holds
    the far side's stripe alone, holds too little of the near side's to show as a second peak
    (a share below ``DOUBLE_PEAK_RATIO`` of the far one's), and when it is dark (the wall or
    its shadow) it holds too little to pass the threshold: none is assumed. When it holds two
    stripes, the wall lies within it: rejected as a double (``double`` 1), whose two parts
    the extraction does not report, it is taken as half lit by each; measured on one of its
    two peaks (``double`` 2: the far side's, brighter or continuing its row), the near side's
    share is taken as ``DOUBLE_SHARE`` of the column's peak."""
    # the near side's points up to its end (which may lie inside a ramp of jumps)
    nlo, nhi = min(nlo, near), max(nhi, near + 1)
    # the near side's level, from the top of its flank inward (as a drop-out side's)
    k_top = near
    while (nlo <= k_top - toward < nhi
           and vpeak[k_top - toward] > (1.0 + FLANK_RISE) * vpeak[k_top]):
        k_top -= toward
    if toward > 0:
        lo, hi = max(k_top - LEVEL_PX + 1, nlo), k_top + 1
    else:
        lo, hi = k_top, min(k_top + LEVEL_PX, nhi)
    level = _median_of(vpeak, lo, hi)
    half = 0.5 * level
    c_near = cols[near]
    c_next = c_near + toward
    share = 0.0
    if 0 <= c_next < double.shape[0] and double[c_next] == 1:
        share = half
    elif 0 <= c_next < double.shape[0] and double[c_next] == 2:
        share = min(level, DOUBLE_SHARE * _peak_at(peak, c_next))
    if vpeak[near] < half:
        c_in, p_in, p_out = c_near - toward, level, vpeak[near]
    elif share >= half:
        c_in, p_in, p_out = c_next, share, 0.0
    else:
        c_in, p_in, p_out = c_near, vpeak[near], share
    f = (p_in - half) / (p_in - p_out) if p_in > p_out else 0.5
    return float(c_in) + toward * min(max(f, 0.0), 1.0)


@njit(nogil=True, cache=True)
def _step(k0, k1, llo, rhi, k_lo, k_hi, cols, a, d, pts, vcol, vrow, vpeak, peak, double,
          threshold, curl, fx, fy, cx, cy, n, offset, e_a, e_d, out_pc, out_move, out):
    """The step edge of the jumps k0..k1 (points k0..k1+1) with its sides llo..k0 and
    k1+1..rhi, in the stretch of stripe k_lo..k_hi, into out_pc (point in {C}), out_move
    (how far it was moved from the near side's end up the wall, {C}, mm: zero where it was
    interpolated on the profile) and out (u, v, height, level, direction). False when the
    step is below threshold, has no clean half-height crossing, or its near side curves away
    up to the run (:func:`_curls`)."""
    lxm, lym, lsl, _ = _fit_line(a, d, llo, k0 + 1)
    rxm, rym, rsl, _ = _fit_line(a, d, k1 + 1, rhi + 1)
    a_b = 0.5 * (a[k0] + a[k1 + 1])
    h = (rym + rsl * (a_b - rxm)) - (lym + lsl * (a_b - lxm))  # the relative step height
    if abs(h) < threshold:
        return False
    # where the profile crosses the mid-line of the two sides: half the relative step height
    p = -1
    e_p = 0.0
    e_q = 0.0
    for j in range(k0, k1 + 1):
        mid_p = 0.5 * ((lym + lsl * (a[j] - lxm)) + (rym + rsl * (a[j] - rxm)))
        mid_q = 0.5 * ((lym + lsl * (a[j + 1] - lxm)) + (rym + rsl * (a[j + 1] - rxm)))
        e_p = (d[j] - mid_p) * h
        e_q = (d[j + 1] - mid_q) * h
        if e_p <= 0.0 < e_q:
            p = j
            break
    if p < 0:
        return False  # noise larger than the step
    q = p + 1
    for i in range(3):
        out_move[i] = 0.0
    if cols[q] - cols[p] == 1 and abs(d[q] - d[p]) <= RESOLVED_STEP_FRACTION * abs(h):
        # resolved over adjacent columns: interpolate on the profile
        f = -e_p / (e_q - e_p)
        for i in range(3):
            out_pc[i] = pts[p, i] + f * (pts[q, i] - pts[p, i])
        u = vcol[p] + f
        v = vrow[p] + f * (vrow[q] - vrow[p])
    else:
        # the wall stands where the near side's stripe ends: at half its level
        if h > 0:
            near, toward, nlo, nhi, flo, fhi = p, 1, llo, k0 + 1, k1 + 1, rhi + 1
        else:
            near, toward, nlo, nhi, flo, fhi = q, -1, k1 + 1, rhi + 1, llo, k0 + 1
        if (_curls(vrow, vcol, k0, 1, k_lo, k0 + 1, curl) if h > 0
                else _curls(vrow, vcol, k1 + 1, -1, k1 + 1, k_hi + 1, curl)):
            return False  # the near side's stripe ends on a surface curving away, not at a rim
        u = _near_end(near, toward, nlo, nhi, cols, vpeak, double, peak)
        cxm, cym, csl, _ = _fit_line(vcol, vrow, nlo, nhi)
        v = cym + csl * (u - cxm) if nlo <= near < nhi else vrow[near] + csl * (u - vcol[near])
        if not _triangulate(u, v, fx, fy, cx, cy, n, offset, out_pc):
            return False
        a_n = out_pc[0] * e_a[0] + out_pc[1] * e_a[1] + out_pc[2] * e_a[2]
        d_n = out_pc[0] * e_d[0] + out_pc[1] * e_d[1] + out_pc[2] * e_d[2]
        mid = 0.5 * ((lym + lsl * (a_n - lxm)) + (rym + rsl * (a_n - rxm)))
        for i in range(3):
            out_move[i] = (mid - d_n) * e_d[i]  # up the wall to half the step
            out_pc[i] += out_move[i]
        # in the image: half way between the two sides' rows at the wall's column
        fxm, fym, fsl, _ = _fit_line(vcol, vrow, flo, fhi)
        v = 0.5 * (v + fym + fsl * (u - fxm))
    out[0], out[1], out[2] = u, v, abs(h)
    out[3] = min(_median_of(vpeak, llo, k0 + 1), _median_of(vpeak, k1 + 1, rhi + 1))
    out[4] = 1.0 if h > 0 else -1.0
    return True


@njit(nogil=True, cache=True)
def _edges_kernel(row, peak, valid_in, dark_in, double, fx, fy, cx, cy, n, offset, e_a, e_d,
                  min_gap, max_bridge, min_run, side_px, min_step, noise_factor, max_ramp,
                  min_contrast, keep_far, background):
    w = row.shape[0]
    valid = valid_in.copy()
    dark = dark_in.copy()
    pc = np.empty(3)
    move = np.zeros(3)
    for c in range(w):  # a ray that misses the sheet (or a NaN row) is no stripe
        if valid[c] and not (row[c] == row[c]
                             and _triangulate(float(c), row[c], fx, fy, cx, cy, n, offset, pc)):
            valid[c] = False
    _remove_specks(valid, dark, min_gap, max_bridge, min_run)
    dark_cum = _cumulative(dark)
    cols = np.nonzero(valid)[0]
    nv = cols.shape[0]
    m_max = 3 * nv + 2  # two drop-outs per stretch of stripe, at most one step per jump
    out_px = np.empty((m_max, 2))
    out_pc = np.empty((m_max, 3))
    out_kind = np.empty(m_max, np.uint8)
    out_size = np.empty(m_max)
    out_peak = np.empty(m_max)
    out_dir = np.empty(m_max, np.int8)
    out_end = np.full((m_max, 8), np.nan)
    out_move = np.zeros((m_max, 3))
    if nv == 0:
        return (out_px[:0], out_pc[:0], out_kind[:0], out_size[:0], out_peak[:0], out_dir[:0],
                out_end[:0], out_move[:0], math.nan)
    starts, ends = _segments(cols, dark_cum, min_gap, max_bridge)
    n_seg = starts.shape[0]
    # the profile in the sheet: points in {C}, in-plane (a, d), columns, rows and peaks
    pts = np.empty((nv, 3))
    a = np.empty(nv)
    d = np.empty(nv)
    vrow = np.empty(nv)
    vcol = np.empty(nv)
    vpeak = np.empty(nv)
    for k in range(nv):
        c = cols[k]
        _triangulate(float(c), row[c], fx, fy, cx, cy, n, offset, pc)
        pts[k, 0], pts[k, 1], pts[k, 2] = pc[0], pc[1], pc[2]
        a[k] = pc[0] * e_a[0] + pc[1] * e_a[1] + pc[2] * e_a[2]
        d[k] = pc[0] * e_d[0] + pc[1] * e_d[1] + pc[2] * e_d[2]
        vrow[k] = row[c]
        vcol[k] = float(c)
        vpeak[k] = _peak_at(peak, c)
    seg = np.empty(nv, np.int64)
    for s in range(n_seg):
        seg[starts[s]:ends[s] + 1] = s
    noise = _range_noise(cols, d, seg)
    scatter = noise * math.sqrt(2.0) if noise == noise else 0.0  # point to point
    threshold = max(min_step, noise_factor * scatter)
    point_noise = noise if noise == noise else 0.0
    row_noise = _range_noise(cols, vrow, seg)  # the same estimate, on the rows (px)
    curl, bend = CURL_PX, ROW_BEND_PX
    if row_noise == row_noise:
        curl = max(CURL_PX, CURL_NOISE_FACTOR * row_noise)
        bend = max(ROW_BEND_PX, BEND_NOISE_FACTOR * math.sqrt(6.0) * row_noise)
    resid, cand = _step_candidates(cols, vcol, d, seg, side_px,
                                   max(noise_factor * scatter, min_step / max_ramp))
    res = np.empty(12)
    count = 0
    for s in range(n_seg):
        k_lo, k_hi = starts[s], ends[s]
        # -- drop-outs: the ends of the stretch, where a gap of min_gap dark columns begins
        for sign in (-1, 1):
            c_next = cols[k_lo] - 1 if sign < 0 else cols[k_hi] + 1
            if c_next < 0 or c_next >= w or not dark[c_next]:
                continue  # no gap, or one of columns that say nothing (the view's border)
            if sign < 0:
                k_other = k_lo - 1 if s > 0 else -1
                g_lo, g_hi = (cols[k_other] + 1 if k_other >= 0 else 0), cols[k_lo]
                o_lo = max(k_other - side_px + 1, starts[s - 1]) if s > 0 else 0
                o_hi = k_other + 1
            else:
                k_other = k_hi + 1 if s + 1 < n_seg else -1
                g_lo, g_hi = cols[k_hi] + 1, (cols[k_other] if k_other >= 0 else w)
                o_lo = k_other
                o_hi = min(k_other + side_px, ends[s + 1] + 1) if s + 1 < n_seg else 0
            if dark_cum[g_hi] - dark_cum[g_lo] < min_gap:
                continue  # "drop-outs are evaluated by size"
            if _dropout(sign, k_lo, k_hi, k_other, o_lo, o_hi, cols, a, d, pts, vcol, vrow,
                        vpeak, peak, valid, dark, side_px, threshold, point_noise, curl, bend,
                        min_contrast, keep_far, background, fx, fy, cx, cy, n, offset, pc, res):
                out_px[count, 0], out_px[count, 1] = res[0], res[1]
                out_pc[count, :] = pc
                out_kind[count] = 0
                out_size[count] = res[2]
                out_peak[count] = res[3]
                out_dir[count] = sign
                out_end[count, :] = res[4:12]
                count += 1
        # -- steps: runs of up to max_ramp candidate jumps of one sign
        k = k_lo
        while k < k_hi:
            if not cand[k]:
                k += 1
                continue
            k0 = k
            while k + 1 < k_hi and cand[k + 1] and (resid[k + 1] > 0) == (resid[k0] > 0):
                k += 1
            k1 = k
            k += 1
            if k1 - k0 + 1 > max_ramp:
                continue  # a sloped stretch of surface, not a step
            # the sides: up to side_px points beyond the run, short of other candidates
            llo = k0
            while llo > k_lo and k0 - llo + 1 < side_px and not cand[llo - 1]:
                llo -= 1
            rhi = k1 + 1
            while rhi < k_hi and rhi - k1 < side_px and not cand[rhi]:
                rhi += 1
            if k0 - llo + 1 < min_run or rhi - k1 < min_run:
                continue  # a step needs surface on both sides (a chamfer into a drop-out has not)
            cut_short = k0 - llo + 1 < side_px or rhi - k1 < side_px
            if _step(k0, k1, llo, rhi, k_lo, k_hi, cols, a, d, pts, vcol, vrow, vpeak, peak,
                     double, threshold, curl, fx, fy, cx, cy, n, offset, e_a, e_d, pc,
                     move, res) and not (
                         cut_short and res[2] < SHORT_SIDE_STEP_FACTOR * threshold):
                out_px[count, 0], out_px[count, 1] = res[0], res[1]
                out_pc[count, :] = pc
                out_kind[count] = 1
                out_move[count, :] = move
                out_size[count] = res[2]
                out_peak[count] = res[3]
                out_dir[count] = 1 if res[4] > 0 else -1
                count += 1
    return (out_px[:count].copy(), out_pc[:count].copy(), out_kind[:count].copy(),
            out_size[:count].copy(), out_peak[:count].copy(), out_dir[:count].copy(),
            out_end[:count].copy(), out_move[:count].copy(), noise)
