"""The registration's nearest-point queries: a lookup table of a point set's nearest point
(O(1), approximate) for the search (``scanner_core.pose.search``), an exact grid search for
the fits and the scores that decide, and a memo of a fit's exact queries.

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

The fine fit's own queries are exact (`NearestGrid`), and mostly unchanged from one
iteration to the next: `NearestMemo` remembers them and asks again only about the points
whose nearest may have changed.

`NearestGrid` answers exactly what ``cKDTree.query(points, k, distance_upper_bound)`` does
(k of 1 or 2) from a uniform grid of cells, each listing its points: a query visits the
cells in shells of growing Chebyshev radius around its own and stops once the nearest found
lies within the shells' box (nothing outside it can be nearer). The model's samples lie on
a surface or along edges at a fixed spacing, so a cell sized to hold about a dozen of them
answers a point near the model from the 27 cells about it: on the pose's queries two to three
times faster than the KD-tree, which walks its nodes down and back for each point.
"""
from __future__ import annotations

import numpy as np
from numba import njit
from scipy.ndimage import distance_transform_edt

__all__ = ["NearestTable", "NearestMemo", "NearestGrid"]


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
    """An exact search's nearest point of one set of moving points (a fit's scan points at each of
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
    tree : NearestGrid or scipy.spatial.cKDTree
        Over the set, mm: anything with ``query(points, k=2, distance_upper_bound=...)``,
        ``n`` (the set's size) and ``data`` (its (M, 3) points).
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


class NearestGrid:
    """Exact nearest points of a set from a grid of cells: ``cKDTree.query``'s answer for
    k of 1 or 2 within a bound (the same distances; of samples equally near, perhaps another).

    Parameters
    ----------
    points : (M, 3) float64
        The set, mm; M >= 1.
    points_per_cell : float
        The cell's side is chosen so that a cell holding points holds about this many on
        average (a dozen: fewer and a query visits more empty cells, more and it measures
        more points).
    max_cells : int
        The grid's size bound (8 bytes a cell); the cell grows beyond it.
    far : callable(points (K, 3), k, bound) -> (dist, index), optional
        What answers the points whose k-th nearest lies beyond ``FAR_SHELLS`` shells of cells
        (the set's KD-tree: a grid visits every cell within the distance, a tree skips the
        empty space at once). Without it the grid searches on, as far as it takes.

    Attributes
    ----------
    n : int
        The set's size (what a query returns as the index of no match).
    data : (M, 3) float64
        The set.
    cell_mm : float
    """

    def __init__(self, points, points_per_cell: float = 12.0, *, max_cells: int = 2_000_000,
                 far=None):
        self.far = far
        self.data = np.ascontiguousarray(points, dtype=np.float64)
        if self.data.ndim != 2 or self.data.shape[1] != 3 or not len(self.data):
            raise ValueError(f"a grid needs (M >= 1, 3) points, got {self.data.shape}")
        if not np.isfinite(self.data).all():
            raise ValueError("a grid's points must be finite")
        self.n = len(self.data)
        self.origin = self.data.min(axis=0)
        extent = self.data.max(axis=0) - self.origin
        if not extent.max() < _MAX_EXTENT_MM:
            raise ValueError(f"a grid's points span {extent.max():.3g} mm, more than "
                             f"{_MAX_EXTENT_MM:g} (a unit's mistake?)")
        # The samples' spacing and dimension (a surface, a line) are not known here: the
        # side is found from the set's own occupancy, a secant in log-log (a cell holds
        # ~ side^d points), from the side an even spread over the box would take.
        def per_cell(side):
            cells = self._flat(self._cells(self.data, side, extent), side, extent)
            return self.n / np.unique(cells).size

        sides = [self._bounded(max(float(np.cbrt(np.prod(extent + 1e-6) / self.n)), 1e-3),
                               extent, max_cells)]
        sides.append(self._bounded(2.0 * sides[0], extent, max_cells))
        occupancy = [per_cell(side) for side in sides]
        for _ in range(6):
            if abs(np.log(occupancy[-1] / points_per_cell)) < np.log(1.25):
                break
            slope = np.log(occupancy[-1] / occupancy[-2]) / np.log(sides[-1] / sides[-2])
            step = np.log(points_per_cell / occupancy[-1]) / np.clip(slope, 0.5, 3.0) \
                if np.isfinite(slope) else np.log(2.0)
            sides.append(self._bounded(sides[-1] * float(np.exp(np.clip(step, -3.0, 3.0))),
                                       extent, max_cells))
            if sides[-1] == sides[-2]:  # held at the grid's size bound
                break
            occupancy.append(per_cell(sides[-1]))
        self.cell_mm = sides[len(occupancy) - 1]  # the last side measured (each is bounded)
        self.shape = self._shape(self.cell_mm, extent)
        flat = self._flat(self._cells(self.data, self.cell_mm, extent), self.cell_mm, extent)
        self.order = np.argsort(flat, kind="stable").astype(np.int64)
        self.sorted = np.ascontiguousarray(self.data[self.order])
        counts = np.bincount(flat, minlength=int(np.prod(self.shape)))
        self.start = np.zeros(len(counts) + 1, np.int64)
        np.cumsum(counts, out=self.start[1:])

    @staticmethod
    def _shape(cell, extent) -> np.ndarray:
        return np.floor(extent / cell).astype(np.int64) + 1

    def _bounded(self, cell, extent, max_cells) -> float:
        while np.prod(self._shape(cell, extent)) > max_cells:
            cell *= 1.05
        return float(cell)

    def _cells(self, points, cell, extent) -> np.ndarray:
        shape = self._shape(cell, extent)
        return np.clip(np.floor((points - self.origin) / cell).astype(np.int64), 0, shape - 1)

    def _flat(self, cells, cell, extent) -> np.ndarray:
        shape = self._shape(cell, extent)
        return (cells[:, 0] * shape[1] + cells[:, 1]) * shape[2] + cells[:, 2]

    def query(self, points, k: int = 1, distance_upper_bound: float = np.inf):
        """As ``cKDTree.query``: for each of `points` ((K, 3) mm), its `k` (1 or 2) nearest
        within `distance_upper_bound` (strictly nearer), nearest first.

        Returns
        -------
        dist : (K,) float64 for k = 1, (K, 2) for k = 2
            inf where there is none.
        index : (K,) or (K, 2) int64
            ``n`` where there is none.
        """
        if k not in (1, 2):
            raise ValueError(f"k must be 1 or 2, got {k}")
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        shells = FAR_SHELLS if self.far is not None else np.iinfo(np.int64).max
        dist, index, unresolved = _grid_nearest(points, self.sorted, self.order, self.start,
                                                self.origin, self.cell_mm, self.shape, k,
                                                float(distance_upper_bound), shells)
        if unresolved.any() and not np.isfinite(points[unresolved]).all():
            raise ValueError("a grid's query points must be finite")  # as cKDTree's
        if self.far is not None and unresolved.any():
            far_dist, far_index = self.far(points[unresolved], k, distance_upper_bound)
            dist[unresolved] = np.reshape(far_dist, (-1, k))
            index[unresolved] = np.reshape(far_index, (-1, k))
        return (dist[:, 0], index[:, 0]) if k == 1 else (dist, index)


#: Shells of cells a grid query searches before it hands the point to `NearestGrid.far`.
FAR_SHELLS = 4
# A grid spans at most this (mm): beyond, its cells' indices would overflow.
_MAX_EXTENT_MM = 1e9


@njit(nogil=True, cache=True)
def _slab_gap(x, low):
    """Distance from coordinate `x` to the interval [low, low + 1] (0 inside), in cells."""
    return max(low - x, 0.0, x - low - 1.0)


@njit(nogil=True, cache=True)
def _grid_nearest(points, cell_points, order, start, origin, cell_mm, shape, k, bound,
                  max_shells):
    """`NearestGrid.query`: each point's cells visited in shells of growing radius about
    its own cell (clamped to the grid); a shell's cells nearer than the k-th nearest found so
    far are measured; the search ends when the box of shells so far holds the k-th nearest
    (every cell outside it lies at least the box's gap away) or covers the grid; after
    `max_shells` shells the point is left unresolved (the third output). Squared distances
    in mm^2, compared as the KD-tree compares them (strictly under the bound's)."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    m = len(cell_points)
    dist = np.full((len(points), k), np.inf)
    index = np.full((len(points), k), m, np.int64)
    unresolved = np.zeros(len(points), np.bool_)
    bound_sq = bound * bound
    for i in range(len(points)):
        qx, qy, qz = points[i, 0], points[i, 1], points[i, 2]
        px = (qx - origin[0]) / cell_mm
        py = (qy - origin[1]) / cell_mm
        pz = (qz - origin[2]) / cell_mm
        if not (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz)):
            unresolved[i] = True  # the caller refuses it
            continue
        cx = min(max(int(np.floor(px)), 0), nx - 1)
        cy = min(max(int(np.floor(py)), 0), ny - 1)
        cz = min(max(int(np.floor(pz)), 0), nz - 1)
        first, second, j1, j2 = bound_sq, bound_sq, m, m
        radius = 0
        while True:
            limit = second if k == 2 else first
            for x in range(max(cx - radius, 0), min(cx + radius, nx - 1) + 1):
                gx = _slab_gap(px, x) * cell_mm
                if gx * gx >= limit:
                    continue
                for y in range(max(cy - radius, 0), min(cy + radius, ny - 1) + 1):
                    gy = _slab_gap(py, y) * cell_mm
                    gxy = gx * gx + gy * gy
                    if gxy >= limit:
                        continue
                    on_shell = abs(x - cx) == radius or abs(y - cy) == radius
                    # inside the shell's x and y faces only its two z faces are new
                    z_step = 1 if on_shell else max(2 * radius, 1)
                    z = cz - radius
                    while z <= cz + radius:
                        if 0 <= z < nz:
                            gz = _slab_gap(pz, z) * cell_mm
                            if gxy + gz * gz < limit:
                                c = (x * ny + y) * nz + z
                                for j in range(start[c], start[c + 1]):
                                    ax = qx - cell_points[j, 0]
                                    ay = qy - cell_points[j, 1]
                                    az = qz - cell_points[j, 2]
                                    d = ax * ax + ay * ay + az * az
                                    if d < first:
                                        second, j2 = first, j1
                                        first, j1 = d, j
                                    elif k == 2 and d < second:
                                        second, j2 = d, j
                                    limit = second if k == 2 else first
                        z += z_step
            # the gap from the point to the outside of the box of shells so far, mm
            gap = np.inf
            if cx - radius > 0:
                gap = min(gap, px - (cx - radius))
            if cx + radius < nx - 1:
                gap = min(gap, cx + radius + 1 - px)
            if cy - radius > 0:
                gap = min(gap, py - (cy - radius))
            if cy + radius < ny - 1:
                gap = min(gap, cy + radius + 1 - py)
            if cz - radius > 0:
                gap = min(gap, pz - (cz - radius))
            if cz + radius < nz - 1:
                gap = min(gap, cz + radius + 1 - pz)
            gap *= cell_mm
            if gap == np.inf or (gap > 0 and gap * gap >= (second if k == 2 else first)):
                break
            if radius == max_shells:
                unresolved[i] = True
                break
            radius += 1
        if j1 < m:
            dist[i, 0], index[i, 0] = np.sqrt(first), order[j1]
        if k == 2 and j2 < m:
            dist[i, 1], index[i, 1] = np.sqrt(second), order[j2]
    return dist, index, unresolved
