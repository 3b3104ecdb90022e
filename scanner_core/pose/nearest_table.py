"""A lookup table of a point set's nearest point: O(1) approximate nearest-neighbour queries
for the registration's search (``scanner_core.pose.search``).

The search screens candidate poses whose points lie millimetres off the model, where a
KD-tree's query visits every sample within that distance (2-4 us a point at 0.25 mm spacing,
0.7-2 us on the sparse models): most of a pose's time on the scans the coarse stage or the
probes run on. The table answers in a few array operations whatever the distance: a grid of
voxels of side ``h`` over the points' bounding box grown by ``band_mm``, each holding the
point nearest its centre (through the Euclidean distance transform of the occupied voxels,
Maurer et al. 2003, ``scipy.ndimage.distance_transform_edt``), or -1 beyond the band. A query
reads its voxel's point and measures its true distance to it.

What it returns is *a* point near the nearest: off by at most about ``h * sqrt(3)`` in
position (the voxel's half diagonal twice), which moves a point-to-plane residual not at all on
a planar face and by ``d^2 / 2R`` on a surface of radius R. It serves the screening of
candidates, never the fine fit, whose correspondences come from the KD-tree. Points off the
table (beyond the band, or a band narrower than the query's bound) are answered by the
KD-tree, so a bound is honoured exactly either way.

Built once per part (``scanner_core.cad.PartModel`` arms it); its size is bounded by
``max_voxels`` (int32, 4 bytes each), the voxel growing on large parts.

The fine fit's own queries are exact, and mostly unchanged from one iteration to the next:
`NearestMemo` remembers them and asks the KD-tree again only about the points whose nearest
may have changed.
"""
from __future__ import annotations

import numpy as np
from numba import njit
from scipy.ndimage import distance_transform_edt

__all__ = ["NearestTable", "NearestMemo"]


class NearestTable:
    """Nearest point of a set by lookup.

    Parameters
    ----------
    points : (M, 3) float64
        The set, mm.
    band_mm : float
        How far from the set the table answers (beyond: ``fallback``).
    voxel_mm : float
        The smallest voxel side; it grows so that the table has at most `max_voxels`.
    max_voxels : int
    fallback : callable(points (K, 3), bound) -> (dist (K,), index (K,)), optional
        What answers the points off the table (the set's KD-tree); None: they have no match.
    """

    def __init__(self, points, band_mm: float, voxel_mm: float = 0.5, *,
                 max_voxels: int = 4_000_000, fallback=None):
        self.points = np.asarray(points, dtype=np.float64)
        self.band_mm = float(band_mm)
        self.fallback = fallback
        if not len(self.points):
            self.origin, self.voxel_mm = np.zeros(3), 1.0
            self.table = np.full((1, 1, 1), -1, np.int32)
            return
        low = self.points.min(axis=0) - band_mm
        extent = self.points.max(axis=0) + band_mm - low
        voxel = max(voxel_mm, float(np.cbrt(np.prod(extent) / max_voxels)))
        shape = np.maximum(np.ceil(extent / voxel).astype(np.int64) + 1, 1)
        while np.prod(shape) > max_voxels:  # rounding up can overshoot by a few percent
            voxel *= 1.02
            shape = np.maximum(np.ceil(extent / voxel).astype(np.int64) + 1, 1)
        self.origin, self.voxel_mm = low, voxel
        cells = self._cells(self.points, shape)
        owner = np.full(tuple(shape), -1, np.int32)
        owner[tuple(cells.T)] = np.arange(len(self.points), dtype=np.int32)
        distance, nearest = distance_transform_edt(owner < 0, sampling=voxel,
                                                   return_indices=True)
        table = owner[tuple(nearest)]
        del nearest
        # a voxel's own point lies up to half a diagonal from its centre
        table[distance > band_mm + voxel * np.sqrt(3.0) / 2] = -1
        self.table = table

    def _cells(self, points, shape=None) -> np.ndarray:
        """(K, 3) int64 voxel of each point (rounded to the nearest centre)."""
        shape = self.table.shape if shape is None else shape
        cells = np.rint((points - self.origin) / self.voxel_mm).astype(np.int64)
        return np.clip(cells, 0, np.asarray(shape) - 1)

    def query(self, points, bound: float):
        """The distance to and index of a point of the set near each of `points`.

        Parameters
        ----------
        points : (K, 3) float
            mm.
        bound : float
            Farther than this (mm) is no match.

        Returns
        -------
        dist : (K,) float64
            inf where there is no match.
        index : (K,) int64
            ``M`` (the set's size) where there is no match, as ``cKDTree.query`` gives.
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        size = len(self.points)
        if not size or not len(points):
            return np.full(len(points), np.inf), np.full(len(points), size, np.int64)
        dist, index = _look_up(points, self.origin, float(self.voxel_mm), self.table,
                               self.points, float(bound))
        # Off the table is beyond the band: no match within a bound inside it; a bound beyond
        # it, the KD-tree knows.
        off = np.isinf(dist) if bound > self.band_mm else np.zeros(len(points), bool)
        if self.fallback is not None and np.any(off):
            dist[off], index[off] = self.fallback(points[off], bound)
        return dist, index


class NearestMemo:
    """A KD-tree's nearest point of one set of moving points (a fit's scan points at each of
    its iterations), remembered between queries and asked again only where it may have
    changed: exactly what a fresh query returns.

    Each query keeps, for every point, its nearest (at distance ``d1``) and a lower bound
    ``d2`` on the distance to every other point of the set (the second nearest's, or the
    query's bound when there is none within it). A point that has since moved by ``delta``
    keeps its nearest while ``d1 + delta < d2 - delta`` (the triangle inequality), and has
    still none within a bound ``b`` while ``b <= bound - delta``. Late in a fit the points
    move by micrometres against samples a quarter of a millimetre apart: over a pose's fits
    15-24 % of them were asked again, and the fits' queries took 2-3 times less time (three
    of bench pose_time's scans).

    Parameters
    ----------
    tree : scipy.spatial.cKDTree
        Over the set, mm.
    """

    def __init__(self, tree):
        self.tree = tree
        self.where = None  # (K, 3) where each point was last asked

    def query(self, points, bound: float):
        """As ``cKDTree.query(points, k=1, distance_upper_bound=bound)``: (K,) distances (inf
        beyond `bound`) and (K,) indices (the set's size beyond it) of `points` ((K, 3) mm,
        the same K points at every call)."""
        points = np.asarray(points, dtype=np.float64)
        if self.where is None or len(self.where) != len(points):
            self.where = points.copy()
            self.index = np.full(len(points), self.tree.n, np.int64)
            self.first = np.full(len(points), np.inf)
            self.others = np.zeros(len(points))
            self.bound = np.zeros(len(points))
            ask = np.ones(len(points), bool)
        else:
            ask = _to_ask(points, self.where, self.first, self.others, self.bound, bound)
        if np.any(ask):
            dist, index = self.tree.query(points[ask], k=2, distance_upper_bound=bound)
            self.where[ask] = points[ask]
            self.index[ask] = index[:, 0]
            self.first[ask] = dist[:, 0]
            self.others[ask] = np.minimum(dist[:, 1], bound)
            self.bound[ask] = bound
        return _within(points, np.where(np.isfinite(self.first), self.index, -1),
                       self.tree.data, bound)


@njit(nogil=True, cache=True)
def _to_ask(points, where, first, others, asked_bound, bound):
    """Which points `NearestMemo` must ask the tree about again (see there)."""
    ask = np.empty(len(points), np.bool_)
    for i in range(len(points)):
        dx = points[i, 0] - where[i, 0]
        dy = points[i, 1] - where[i, 1]
        dz = points[i, 2] - where[i, 2]
        moved = np.sqrt(dx * dx + dy * dy + dz * dz)
        if np.isfinite(first[i]):
            ask[i] = not (first[i] + moved < others[i] - moved)
        else:
            ask[i] = not (bound <= asked_bound[i] - moved)
    return ask


@njit(nogil=True, cache=True)
def _within(points, candidate, set_points, bound):
    """Each point's distance to its `candidate` of the set (-1: none) and the candidate's
    index, where within `bound`; inf and the set's size elsewhere."""
    dist = np.full(len(points), np.inf)
    index = np.full(len(points), len(set_points), np.int64)
    for i in range(len(points)):
        j = candidate[i]
        if j < 0:
            continue
        dx = points[i, 0] - set_points[j, 0]
        dy = points[i, 1] - set_points[j, 1]
        dz = points[i, 2] - set_points[j, 2]
        d = np.sqrt(dx * dx + dy * dy + dz * dz)
        if d <= bound:
            dist[i], index[i] = d, j
    return dist, index


@njit(nogil=True, cache=True)
def _look_up(points, origin, voxel_mm, table, set_points, bound):
    """`NearestTable.query` on the table alone, in one pass: each point's voxel (the nearest
    centre; none outside the grid), its point and its true distance, within `bound`."""
    nx, ny, nz = table.shape
    candidate = np.full(len(points), -1, np.int64)
    cell = np.empty(3, np.int64)
    for i in range(len(points)):
        outside = False
        for a, extent in enumerate((nx, ny, nz)):
            x = points[i, a]
            if not (x >= origin[a] - voxel_mm / 2 and x <= origin[a] + (extent - 0.5) * voxel_mm):
                outside = True
                break
            c = int(np.rint((x - origin[a]) / voxel_mm))
            cell[a] = min(max(c, 0), extent - 1)
        if not outside:
            candidate[i] = table[cell[0], cell[1], cell[2]]
    return _within(points, candidate, set_points, bound)
