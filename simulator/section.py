"""The part cut by the light plane, and where the cut falls in the image's pixel columns.

:func:`slice_mesh` cuts the mesh with the sheet (an exact section, one segment per crossing
face); :func:`column_hits` splits the section at the boundaries of a view's pixel columns and
gives each piece a stripe sample at its exact sub-pixel row, with the share of the pixel it
covers (through a distorting lens, ``_column_hits_through_lens``). ``simulator.render`` makes
a frame's stripe samples from them.
"""
from __future__ import annotations

import numpy as np

from scanner_core.geometry import apply_transform

__all__ = ["slice_mesh", "column_hits", "LENS_PIECE_PX"]


def slice_mesh(vertices, faces, normal, offset) -> tuple[np.ndarray, np.ndarray]:
    """Cut a triangle mesh with the plane ``normal . x = offset``.

    Parameters
    ----------
    vertices : (V, 3) float64
    faces : (F, 3) int
    normal : (3,) float64
    offset : float

    Returns
    -------
    segments : (K, 2, 3) float64
        One segment per face that crosses the plane.
    face_index : (K,) int64
    """
    s = vertices @ normal - offset
    sf = s[faces]
    above = sf >= 0.0  # a vertex on the plane counts as above: no face yields a point-segment twice
    crossing = above.any(axis=1) & ~above.all(axis=1)
    index = np.nonzero(crossing)[0]
    if len(index) == 0:
        return np.zeros((0, 2, 3)), index
    v = vertices[faces[index]]
    sv = sf[index]
    av = above[index]
    points = np.empty((len(index), 3, 3))
    cuts = np.empty((len(index), 3), dtype=bool)
    for e, (a, b) in enumerate(((0, 1), (1, 2), (2, 0))):
        cuts[:, e] = av[:, a] != av[:, b]
        with np.errstate(divide="ignore", invalid="ignore"):  # uncut edges are discarded below
            t = sv[:, a] / (sv[:, a] - sv[:, b])
            points[:, e] = v[:, a] + t[:, None] * (v[:, b] - v[:, a])
    # Exactly two edges of a crossing face are cut; take them in edge order.
    order = np.argsort(~cuts, axis=1, kind="stable")[:, :2]
    segments = np.take_along_axis(points, order[:, :, None], axis=1)
    return segments, index


def column_hits(segments_p, pose_b, camera, columns):
    """Where the section segments fall in each image column, weighted by pixel coverage.

    A camera integrates over each pixel's area: pixel column ``c`` covers ``u`` in
    ``[c - 0.5, c + 0.5]``. A segment projecting to ``[u_min, u_max]`` gives one sample to
    every column it overlaps, taken at the middle of the overlap (where that column plane,
    through the camera centre, cuts the segment), with the overlap's share of the pixel as its
    coverage: the last column of a stripe that ends inside it is lit in proportion to the
    part it covers, and two segments meeting inside a column give two partial samples whose
    coverages add up to 1 (for a straight section, their coverage-weighted row is the row at
    the column's centre). Overlaps of zero length (a segment along a line of sight) give no
    sample.

    Parameters
    ----------
    segments_p : (K, 2, 3) float64
        Section segments in {P}, mm.
    pose_b : (4, 4) float64
        ^B X_P.
    camera : PinholeCamera
    columns : (2,) int
        The view's columns, half-open ``[c0, c1)``: coverage is counted within
        ``[c0 - 0.5, c1 - 0.5]``.

    Returns
    -------
    cols : (N,) int64
    rows : (N,) float64
        Exact sub-pixel row at the middle of the overlap.
    points_p : (N, 3) float64
        The 3-D point there, in {P}.
    segment : (N,) int64
        Which segment it came from.
    coverage : (N,) float64
        Share of the pixel column the segment covers, in (0, 1].
    """
    if len(segments_p) == 0:
        return (np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64),
                np.zeros(0))
    if camera.distorted:
        return _column_hits_through_lens(segments_p, pose_b, camera, columns)
    seg_b = apply_transform(pose_b, segments_p.reshape(-1, 3))
    q = camera.to_camera(seg_b).reshape(-1, 2, 3)
    qa, qb = q[:, 0], q[:, 1]
    front = (qa[:, 2] > 0) & (qb[:, 2] > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ua = camera.fx * qa[:, 0] / qa[:, 2] + camera.cx
        ub = camera.fx * qb[:, 0] / qb[:, 2] + camera.cx
    umin = np.clip(np.minimum(ua, ub), columns[0] - 0.5, columns[1] - 0.5)
    umax = np.clip(np.maximum(ua, ub), columns[0] - 0.5, columns[1] - 0.5)
    # Columns whose pixel [c - 0.5, c + 0.5] overlaps [umin, umax] (a span ending on a pixel
    # boundary does not reach into the next pixel).
    first = np.floor(umin + 0.5)
    last = np.ceil(umax + 0.5) - 1.0
    spans = front & (umax > umin)
    counts = np.where(spans, last - first + 1.0, 0.0).astype(np.int64)
    segment = np.repeat(np.arange(len(q)), counts)
    starts = np.repeat(np.where(spans, first, 0.0).astype(np.int64), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    cols = starts + offsets
    lo = np.maximum(umin[segment], cols - 0.5)
    hi = np.minimum(umax[segment], cols + 0.5)
    coverage = hi - lo
    keep = coverage > 0.0
    cols, segment, coverage = cols[keep], segment[keep], coverage[keep]
    u = 0.5 * (lo[keep] + hi[keep])  # the middle of the overlap
    k = (u - camera.cx) / camera.fx
    a, b = qa[segment], qb[segment]
    d = b - a
    t = (k * a[:, 2] - a[:, 0]) / (d[:, 0] - k * d[:, 2])
    t = np.clip(t, 0.0, 1.0)
    x = a + t[:, None] * d
    rows = camera.fy * x[:, 1] / x[:, 2] + camera.cy
    points_p = segments_p[segment, 0] + t[:, None] * (segments_p[segment, 1] - segments_p[segment, 0])
    return cols, rows, points_p, segment, coverage


#: Through a distorting lens, section segments are cut into pieces at most this long in the
#: image (px) and each piece taken as straight there: the lens bends a 100 px stripe by pixels,
#: a 0.5 px piece by less than 1e-4 px.
LENS_PIECE_PX = 0.5


def _column_hits_through_lens(segments_p, pose_b, camera, columns):
    """:func:`column_hits` for a camera whose lens distorts: a pixel column is no longer a
    plane through the camera centre, so the segments are cut into short pieces, each piece's
    ends projected through the lens and the piece taken as straight in the image."""
    seg_b = apply_transform(pose_b, segments_p.reshape(-1, 3)).reshape(-1, 2, 3)
    ideal = camera.without_distortion()
    ends = ideal.project(seg_b.reshape(-1, 3)).reshape(-1, 2, 2)
    span = np.abs(ends[:, 1] - ends[:, 0]).max(axis=1)
    ok = np.isfinite(span)
    pieces = np.where(ok, np.ceil(np.where(ok, span, 0.0) / LENS_PIECE_PX), 0).astype(np.int64)
    pieces = np.maximum(pieces, ok.astype(np.int64))
    segment = np.repeat(np.arange(len(seg_b)), pieces)
    k = np.arange(pieces.sum()) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    t0 = k / pieces[segment]
    t1 = (k + 1) / pieces[segment]
    a, d = segments_p[segment, 0], segments_p[segment, 1] - segments_p[segment, 0]
    pa, pb = a + t0[:, None] * d, a + t1[:, None] * d
    px = camera.project(apply_transform(pose_b, np.concatenate([pa, pb]))).reshape(2, -1, 2)
    ua, va, ub, vb = px[0, :, 0], px[0, :, 1], px[1, :, 0], px[1, :, 1]
    umin = np.clip(np.minimum(ua, ub), columns[0] - 0.5, columns[1] - 0.5)
    umax = np.clip(np.maximum(ua, ub), columns[0] - 0.5, columns[1] - 0.5)
    first = np.floor(umin + 0.5)
    last = np.ceil(umax + 0.5) - 1.0
    spans = np.isfinite(ua) & np.isfinite(ub) & (umax > umin)
    counts = np.where(spans, last - first + 1.0, 0.0).astype(np.int64)
    piece = np.repeat(np.arange(len(ua)), counts)
    starts = np.repeat(np.where(spans, first, 0.0).astype(np.int64), counts)
    cols = starts + np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    lo = np.maximum(umin[piece], cols - 0.5)
    hi = np.minimum(umax[piece], cols + 0.5)
    coverage = hi - lo
    keep = coverage > 0.0
    cols, piece, coverage = cols[keep], piece[keep], coverage[keep]
    u = 0.5 * (lo[keep] + hi[keep])
    t = np.clip((u - ua[piece]) / (ub[piece] - ua[piece]), 0.0, 1.0)
    rows = va[piece] + t * (vb[piece] - va[piece])
    points_p = pa[piece] + t[:, None] * (pb[piece] - pa[piece])
    # One sample per segment and column, as without a lens: the pieces' coverage-weighted mean.
    seg = segment[piece]
    key, first, group = np.unique(seg * (int(columns[1]) + 1) + cols, return_index=True,
                                  return_inverse=True)
    weight = np.bincount(group, coverage)
    rows = np.bincount(group, coverage * rows) / weight
    points_p = np.stack([np.bincount(group, coverage * points_p[:, i]) for i in range(3)], 1)
    return cols[first], rows, points_p / weight[:, None], seg[first], weight
