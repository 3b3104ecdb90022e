"""Surface normals of a scanned cloud, oriented toward the sensor that saw each point.

A scan is a stack of stripe profiles, one per camera frame: along a profile the points lie a
fraction of a millimetre apart (about 0.16 mm in the reference cell), between profiles a
millimetre or more (the pass speed over the frame rate). Plain k-nearest neighbours would pick
most neighbours from the point's own profile, a line, on which no plane can be fitted. So
:func:`estimate_normals` takes the ``k`` nearest points in the point's own profile *and* the
``k`` nearest in each adjacent profile (the previous and the next frame that has points),
within a radius, and fits a plane to them by principal component analysis (Hoppe et al.
[1]_): the normal is the eigenvector of the smallest eigenvalue of the neighbours' covariance.
A point whose neighbourhood holds no point of another profile gets no plane: a profile lies
in the light sheet, so a plane through one profile alone is the sheet, not the surface. The
sign is chosen so that the normal points toward the sensor (the camera's optical centre at that
point's frame), the viewpoint orientation of [2]_; the sensor being known, Hoppe et al.'s
orientation by propagation is not needed.

The neighbour search runs profile by profile: each profile's points sorted along the
profiles' main direction, searched outward from the query's place and stopped where the gap
along that direction (a lower bound on the distance) passes the k-th nearest so far. It
answers what a k-d tree over the points with the profile's rank as a fourth coordinate, scaled
far beyond the cloud's size, answers, in less time. The planes are fitted point
by point in compiled code, the 3 x 3 eigenproblem in closed form. An unstructured cloud (no
frame ids) is searched with a k-d tree (``scipy.spatial.cKDTree``).

References
----------
.. [1] H. Hoppe, T. DeRose, T. Duchamp, J. McDonald, W. Stuetzle, "Surface reconstruction from
   unorganized points", SIGGRAPH 1992, Computer Graphics 26(2), 71-78.
.. [2] R. B. Rusu, "Semantic 3D object maps for everyday manipulation in human living
   environments", PhD thesis, TU Munich, 2009 (PCA normals flipped toward the viewpoint, as
   PCL's ``flipNormalTowardsViewpoint``).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from scanner_core.geometry import unit

__all__ = ["estimate_normals", "FALLBACKS"]

#: Nearest points taken from the point's own profile (itself included) and from each adjacent
#: profile: about +-0.65 mm along a reference-cell profile, enough to average the stripe's
#: ~20 um noise. Odd, so that the set is symmetric about the point (and about its twin in a
#: neighbouring profile): an even count tilts the plane on a curved surface.
DEFAULT_K = 9
#: The automatic neighbourhood radius, in multiples of the cloud's typical spacing (the larger
#: of the median distance to the next profile and the median reach of ``k`` neighbours in a
#: profile): wide enough for every regular neighbour, narrow enough not to bridge gaps and steps.
RADIUS_FACTOR = 3.0
#: A plane needs three points; five (the point and four neighbours) give it some redundancy.
DEFAULT_MIN_NEIGHBOURS = 5
#: Points of the neighbouring profiles (both together) a plane needs besides the point's own
#: profile: fewer, and the plane is the light sheet's or hangs on a point or two.
MIN_ACROSS = 3
#: A neighbourhood whose second principal spread (standard deviation) is below this fraction
#: of its first is a line: its normal is undetermined. 0.05 sits between a ridge seen as one
#: point per profile with the stripe's noise (about 0.02 mm over 1.2 mm: 0.017) and a profile
#: stack at 1 m/s (9 points over +-0.65 mm along a profile, profiles 6 mm apart: about 0.08).
MIN_SPREAD_RATIO = 0.05
#: What a point without a fitted plane gets.
FALLBACKS = ("view", "nan")


def estimate_normals(points, *, sensors, frame_ids=None, k: int = DEFAULT_K,
                     radius: float | None = None,
                     min_neighbours: int = DEFAULT_MIN_NEIGHBOURS,
                     fallback: str = "view", workers: int = 1, index=None) -> np.ndarray:
    """Unit surface normals by PCA over each point's neighbours, oriented toward the sensor.

    Parameters
    ----------
    points : (N, 3) float
        The cloud, mm (any frame; the scanner's is {T}).
    sensors : (N, 3) or (3,) float
        Where the sensor that saw each point was, mm, in the frame of `points`: the camera's
        optical centre at the point's frame. A row with NaN (sensor unknown) gives a NaN
        normal: the sign cannot be chosen.
    frame_ids : (N,) int, optional
        The profile (camera frame) of each point. With it, the neighbours are the `k` nearest
        points of the point's own profile (itself included) and the `k` nearest of the
        previous and of the next profile (by rank of frame id, so a dropped frame is
        bridged). Without it, the cloud is unstructured and the neighbours are its ``3 k``
        nearest points (plain Hoppe et al.).
    k : int
        Points per profile, >= 3.
    radius : float, optional
        Neighbours farther than this, mm, are left out (no plane across a gap or a step).
        Default: ``RADIUS_FACTOR`` times the cloud's typical spacing.
    min_neighbours : int
        Fewer neighbours than this within `radius`, the point included, and the point gets
        the `fallback` (>= 3).
    fallback : {"view", "nan"}
        What a point gets when its neighbourhood fixes no plane (too few neighbours; fewer
        than ``MIN_ACROSS`` from the neighbouring profiles, e.g. a feature that one profile
        alone saw; or all on one line): ``"view"`` the unit vector
        from the point to its sensor (still a normal facing the sensor, the best guess a
        single view gives), ``"nan"`` NaN, so that the caller can tell.
    workers : int
        Threads of the unstructured cloud's neighbour search (``cKDTree.query``; -1: all
        cores; a profile stack's is one thread). One by default:
        the service runs this beside its acquisition.
    index : (M,) int, optional
        Estimate the normals of these points only (their neighbours still come from the
        whole cloud): the registration needs a subsample's.

    Returns
    -------
    normals : (N, 3) float32 (or (M, 3) with `index`)
        Unit vectors, ``dot(normal, sensor - point) >= 0``; NaN where the sensor is unknown,
        and with ``fallback="nan"`` where no plane could be fitted.

    Raises
    ------
    ValueError
        When an argument has the wrong shape, type or value; the message names it.

    References
    ----------
    .. [1] Hoppe et al. 1992, see the module's docstring.
    """
    pts = _check_points(points)
    n = len(pts)
    sens = _check_sensors(sensors, n)
    ranks = _check_frame_ids(frame_ids, n)
    k = _check_int(k, "k", 3)
    min_neighbours = _check_int(min_neighbours, "min_neighbours", 3)
    workers = -1 if workers == -1 else _check_int(workers, "workers", 1, "or -1")
    if radius is not None:
        radius = _check_radius(radius)
    if fallback not in FALLBACKS:
        raise ValueError(f"`fallback` must be one of {FALLBACKS}, got {fallback!r}")
    query = np.arange(n) if index is None else _check_index(index, n)
    normals = np.full((len(query), 3), np.nan)
    if len(query):
        neighbours, distance, own = _neighbours(pts, ranks, k, radius, workers, query)
        normals, planar = _pca_normals(pts, neighbours, distance, min_neighbours, query)
        if own < neighbours.shape[1]:  # a profile stack: a plane needs the neighbouring profiles
            planar &= np.isfinite(distance[:, own:]).sum(axis=1) >= MIN_ACROSS
        to_sensor = sens[query] - pts[query]
        if fallback == "view":
            with np.errstate(invalid="ignore", divide="ignore"):  # a sensor on its point: NaN
                normals[~planar] = unit(to_sensor[~planar])
        else:
            normals[~planar] = np.nan
        normals = _orient(normals, to_sensor)
    return normals.astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Helpers


def _check_points(points) -> np.ndarray:
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.dtype.kind not in "fiu":
        raise ValueError(f"`points` must be (N, 3) float, got {arr.shape} {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError("`points` must be finite")
    return arr


def _check_sensors(sensors, n: int) -> np.ndarray:
    arr = np.asarray(sensors)
    if arr.dtype.kind not in "fiu" or arr.shape not in ((3,), (n, 3)):
        raise ValueError(f"`sensors` must be (3,) or ({n}, 3) float like `points`, got "
                         f"{arr.shape} {arr.dtype}")
    return np.broadcast_to(arr.astype(np.float64), (n, 3))


def _check_int(value, name: str, minimum: int, also: str = "") -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"`{name}` must be an integer >= {minimum}{' ' + also if also else ''}, "
                         f"got {value!r}")
    return int(value)


def _check_radius(radius) -> float:
    try:
        value = float(radius)
    except (TypeError, ValueError):
        value = float("nan")
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"`radius` must be a positive number of mm or None, got {radius!r}")
    return value


def _check_frame_ids(frame_ids, n: int) -> np.ndarray | None:
    """Each point's profile rank: 0, 1, ... in frame-id order (None without frame ids)."""
    if frame_ids is None:
        return None
    arr = np.asarray(frame_ids)
    if arr.shape != (n,) or arr.dtype.kind not in "iu":
        raise ValueError(f"`frame_ids` must be ({n},) int like `points`, got {arr.shape} {arr.dtype}")
    return np.unique(arr, return_inverse=True)[1].reshape(n)


def _check_index(index, n: int) -> np.ndarray:
    arr = np.asarray(index)
    if arr.ndim != 1 or arr.dtype.kind not in "iu" or (len(arr) and (arr.min() < 0 or arr.max() >= n)):
        raise ValueError(f"`index` must be a 1-D array of point indices in [0, {n}), got "
                         f"{arr.shape} {arr.dtype}")
    return arr.astype(np.int64)


def _neighbours(pts: np.ndarray, ranks: np.ndarray | None, k: int, radius: float | None,
                workers: int, query_index: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Neighbour indices (M, K) of the query points (N where none), distances (M, K) (inf
    where none), and how many of the K columns come first from the point's own profile."""
    centred = pts - pts.mean(axis=0)
    bound = np.inf if radius is None else float(radius)
    structured = ranks is not None
    m = len(query_index)
    if structured:
        index, distance = _profile_neighbours(centred, ranks, k, bound, query_index)
        own_k = k
    else:
        # Sliding-midpoint splits (not balanced): built and queried faster on these clouds.
        tree = cKDTree(centred, balanced_tree=False)
        own_k = 3 * k  # the point itself included
        d, i = tree.query(centred[query_index], k=own_k, distance_upper_bound=bound,
                          workers=workers)
        index, distance = [i.reshape(m, -1)], [d.reshape(m, -1)]
    if radius is None:
        reach = distance[0][:, -1]
        spacing = [np.median(reach[np.isfinite(reach)])] if np.isfinite(reach).any() else []
        if structured:
            gap = distance[2][:, 0]
            spacing += [np.median(gap[np.isfinite(gap)])] if np.isfinite(gap).any() else []
        radius = RADIUS_FACTOR * max(spacing) if spacing else np.inf
    index, distance = np.concatenate(index, axis=1), np.concatenate(distance, axis=1)
    far = ~(distance <= radius)
    index[far], distance[far] = len(pts), np.inf
    return index, distance, own_k


def _profile_neighbours(centred, ranks, k, bound, query_index):
    """The `k` nearest points of each query point's own profile (itself included), of the
    previous and of the next (by rank), within `bound`: ``([own, previous, next] indices,
    [...] distances)``, each (M, k), sorted by distance, N and inf where fewer.

    Exactly what a KD-tree over the points, each profile apart from the others, answers, and
    faster on a scan (docs/pose.md): each profile's points sorted along the profiles'
    main direction ``u`` (the main axis of the points about their profile's mean), and the
    search run outward from the query's place in that order (`_profile_knn`), stopped where
    ``|t - t_q|`` along ``u``, a lower bound on the distance, passes the k-th nearest so far.
    """
    n_ranks = int(ranks.max()) + 1 if len(ranks) else 0
    counts = np.bincount(ranks, minlength=n_ranks)
    means = np.zeros((n_ranks, 3))
    np.add.at(means, ranks, centred)
    about = centred - (means / np.maximum(counts, 1)[:, None])[ranks]
    u = np.linalg.eigh(np.einsum("ni,nj->ij", about, about))[1][:, -1]
    along = np.ascontiguousarray(centred @ u)
    order = np.lexsort((along, ranks))
    stop = np.cumsum(counts)
    index, distance = [], []
    for offset in (0, -1, 1):
        d, i = _profile_knn(centred, along, order, stop - counts, stop, ranks,
                            np.ascontiguousarray(query_index), offset, k, bound)
        distance.append(d)
        index.append(i)
    return index, distance


@njit(nogil=True, cache=True)
def _profile_knn(centred, along, order, start, stop, ranks, query, offset, k, bound):
    """For each of `query`, the `k` nearest points (closer than `bound`) of the profile of
    rank ``ranks[q] + offset``, whose points ``order[start[r]:stop[r]]`` are sorted by
    `along`: (M, k) distances (inf where fewer) and indices (N there), by distance, ties by
    index."""
    n = len(centred)
    dist = np.full((len(query), k), np.inf)
    index = np.full((len(query), k), n, np.int64)
    for qi in range(len(query)):
        q = query[qi]
        r = ranks[q] + offset
        if r < 0 or r >= len(start) or stop[r] <= start[r]:
            continue
        lo, hi = start[r], stop[r]
        t = along[q]
        a, b = lo, hi  # the first of the profile at or past t
        while a < b:
            mid = (a + b) // 2
            if along[order[mid]] < t:
                a = mid + 1
            else:
                b = mid
        left, right, count = a - 1, a, 0
        while left >= lo or right < hi:
            gap_left = t - along[order[left]] if left >= lo else np.inf
            gap_right = along[order[right]] - t if right < hi else np.inf
            if gap_left <= gap_right:
                j, gap = order[left], gap_left
                left -= 1
            else:
                j, gap = order[right], gap_right
                right += 1
            if gap >= bound or (count == k and gap > dist[qi, k - 1]):
                break  # every point farther along lies farther away
            dx = centred[j, 0] - centred[q, 0]
            dy = centred[j, 1] - centred[q, 1]
            dz = centred[j, 2] - centred[q, 2]
            d = np.sqrt(dx * dx + dy * dy + dz * dz)
            if d < bound:
                count = _keep_nearest(dist[qi], index[qi], count, d, j)
    return dist, index


@njit(nogil=True, cache=True)
def _keep_nearest(dist, index, count, d, j):
    """Insert (d, j) into the `count` nearest so far (sorted by distance, then index; at most
    ``len(dist)``); the new count."""
    k = len(dist)
    if count == k and (d > dist[k - 1] or (d == dist[k - 1] and j > index[k - 1])):
        return count
    pos = min(count, k - 1)
    while pos > 0 and (dist[pos - 1] > d or (dist[pos - 1] == d and index[pos - 1] > j)):
        dist[pos] = dist[pos - 1]
        index[pos] = index[pos - 1]
        pos -= 1
    dist[pos] = d
    index[pos] = j
    return min(count + 1, k)


def _pca_normals(pts: np.ndarray, index: np.ndarray, distance: np.ndarray,
                 min_neighbours: int, query_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest-eigenvalue eigenvectors of the neighbours' covariance (Hoppe et al. [1]_),
    unoriented, and whether the neighbourhood fixed a plane, for the query points."""
    normals = np.empty((len(query_index), 3))
    planar = np.zeros(len(query_index), bool)
    _plane_fits(pts, index, np.isfinite(distance), query_index, min_neighbours,
                MIN_SPREAD_RATIO, normals, planar)
    return normals, planar


@njit(nogil=True, cache=True)
def _plane_fits(pts, index, found, query_index, min_neighbours, min_spread_ratio, normals,
                planar):
    """:func:`_pca_normals` point by point: the covariance of the found neighbours' offsets
    from the query point (translation-invariant; small offsets keep it exact wherever the
    cloud sits), its eigenvalues in closed form (:func:`_symmetric_eigenvalues`) and the
    smallest one's eigenvector as the largest cross product of two rows of ``C - l_min I``
    (they span the plane it is normal to): no LAPACK call per point (timings in
    docs/pose.md)."""
    for i in range(len(query_index)):
        q = query_index[i]
        m = 0
        sx = sy = sz = sxx = syy = szz = sxy = sxz = syz = 0.0
        for k in range(index.shape[1]):
            if not found[i, k]:
                continue
            j = index[i, k]
            dx = pts[j, 0] - pts[q, 0]
            dy = pts[j, 1] - pts[q, 1]
            dz = pts[j, 2] - pts[q, 2]
            sx += dx
            sy += dy
            sz += dz
            sxx += dx * dx
            syy += dy * dy
            szz += dz * dz
            sxy += dx * dy
            sxz += dx * dz
            syz += dy * dz
            m += 1
        normals[i, 0], normals[i, 1], normals[i, 2] = 1.0, 0.0, 0.0
        if m < min_neighbours:
            continue  # these get the fallback
        mx, my, mz = sx / m, sy / m, sz / m
        a00, a11, a22 = sxx / m - mx * mx, syy / m - my * my, szz / m - mz * mz
        a01, a02, a12 = sxy / m - mx * my, sxz / m - mx * mz, syz / m - my * mz
        low, mid, high = _symmetric_eigenvalues(a00, a11, a22, a01, a02, a12)
        planar[i] = math.sqrt(max(mid, 0.0)) > min_spread_ratio * math.sqrt(max(high, 0.0))
        # rows of C - low I; the eigenvector is normal to all three
        r0 = (a00 - low, a01, a02)
        r1 = (a01, a11 - low, a12)
        r2 = (a02, a12, a22 - low)
        best = 0.0
        for u, v in ((r0, r1), (r0, r2), (r1, r2)):
            cx = u[1] * v[2] - u[2] * v[1]
            cy = u[2] * v[0] - u[0] * v[2]
            cz = u[0] * v[1] - u[1] * v[0]
            size = cx * cx + cy * cy + cz * cz
            if size > best:
                best = size
                norm = math.sqrt(size)
                normals[i, 0], normals[i, 1], normals[i, 2] = cx / norm, cy / norm, cz / norm


@njit(nogil=True, cache=True)
def _symmetric_eigenvalues(a00, a11, a22, a01, a02, a12):
    """Ascending eigenvalues of a symmetric 3 x 3 matrix: the trigonometric solution of its
    characteristic cubic (Smith 1961), ``q + 2 p cos(phi + 2 pi k / 3)`` with ``q`` the mean
    of the diagonal, ``p`` the deviation's scale and ``3 phi = acos(det((A - q I) / p) / 2)``."""
    off = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = math.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * off) / 6.0)
    if p == 0.0:
        return q, q, q
    b00, b11, b22, b01, b02, b12 = b00 / p, b11 / p, b22 / p, a01 / p, a02 / p, a12 / p
    half_det = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02)
                      + b02 * (b01 * b12 - b11 * b02))
    phi = math.acos(min(max(half_det, -1.0), 1.0)) / 3.0
    high = q + 2.0 * p * math.cos(phi)
    low = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    return low, 3.0 * q - high - low, high


def _orient(normals: np.ndarray, to_sensor: np.ndarray) -> np.ndarray:
    """Flip each normal to the side of its sensor (viewpoint orientation, [2]_); NaN where
    the sensor is unknown."""
    facing = np.einsum("ij,ij->i", normals, to_sensor)
    sign = np.where(facing < 0, -1.0, 1.0)
    sign[~np.isfinite(to_sensor).all(axis=1)] = np.nan
    return normals * sign[:, None]
