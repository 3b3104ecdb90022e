"""The fine stage of the registration (``scanner_core.pose.registration``): a robust point-to-plane fit
from a start near the answer.

Point-to-plane Gauss-Newton (Chen and Medioni 1992; Low 2004's linearisation), robust to
outliers (gripper fingers, reflections) through a correspondence gate, a normal agreement
test and Tukey's biweight on the residuals (IRLS, scale from the median absolute residual).
A surface point's residual is its distance to the plane of its model point; an edge point's,
its distance in (x_T, y_T) to the vertical plane through its model edge, a step's point
matched from half its step above and below it as well (`_nearest`). Motions the scan does
not constrain (a turn about a symmetry axis, a slide along a prism) are left at their
starting value instead of drifting: the update is solved in the observable subspace of the
information matrix only (`_directions`, `_solve`, `_hold_free_motions`).

The correspondences (`_Terms`, `_nearest`) serve the search's scores too
(``scanner_core.pose.search``), and the fit's information matrix the uncertainty
(``scanner_core.pose.confidence``). Units: mm, radians.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from scanner_core.pose.rows import across_a_crease, plane_rows
from scanner_core.pose.nearest_table import NearestMemo
from scanner_core.pose.models import EdgeModel, SurfaceModel

# Tukey's biweight constant: 95 % efficiency under Gaussian noise.
_TUKEY_C = 4.685
# The median absolute deviation of a Gaussian is 0.6745 sigma.
_MAD_TO_SIGMA = 1.0 / 0.6745
# The fine fit's first iterations use every _WARM_STRIDE-th surface point (of at least
# _WARM_MIN_POINTS) until its steps fall below _WARM_TOL_FACTOR times the tolerance, for
# _WARM_MAX_ITERATIONS at most (matches to few points can cycle short of that).
_WARM_STRIDE = 4
_WARM_MIN_POINTS = 2000
_WARM_TOL_FACTOR = 100.0
_WARM_MAX_ITERATIONS = 6
# A fit whose steps stay within this factor of the tolerance without halving over
# _CREEP_ITERATIONS iterations has settled: it creeps (correspondences moving with it, a
# constant 6.6e-5 mm an iteration on idler_riser) rather than converges, and would go on to
# ``max_iterations`` (a fifth of the poses of bench service's scans did, some 200 ms each).
_CREEP_FACTOR = 100.0
_CREEP_ITERATIONS = 3
# Accelerated ICP (Besl and McKay 1992, section IV.B): where two successive steps of a full
# fit point the same way (within this many degrees, in scaled units) and shrink by a ratio
# r, the fit converges linearly along that line (a weakly held turn: cycloidal's lobes,
# r = 0.68 over 30 iterations) and the rest of the way is about r / (1 - r) steps; the fit
# jumps there at once. Not where r exceeds _JUMP_RATIO: a step that hardly shrinks is a
# slide along a motion the scan barely holds (ADIS16480 seen on its end), which a jump
# would carry degrees away.
_JUMP_DEG = 5.0
_JUMP_RATIO = 0.95
# Information below this fraction of the strongest is no information (numerical zero).
_SINGULAR = 1e-10
# Floor of the robust scale, mm: no scan is better than this, and noise-free test data must
# not make the weights infinite.
_MIN_SIGMA_MM = 0.001
# An edge point at half a step's height lies this far from the step's edges in 3D (up to
# half the tallest step); the match searches that far, the residual is taken in the plane.
_EDGE_SEARCH_MM = 15.0
# |d x z_T| below this: the edge runs within 17 degrees of z_T.
_MIN_EDGE_LEVEL = 0.3


@dataclass
class _Terms:
    """One kind of correspondence: scan points (with normals for surfaces) and their model."""

    points: np.ndarray
    normals: np.ndarray | None
    frames: np.ndarray
    model: SurfaceModel | EdgeModel
    agreement: float = -1.0     # least cosine between `normals` and a match's normal
    steps_mm: np.ndarray | None = None  # edges: a step's height, 0 for a drop-out
    approximate: bool = False   # matched through the model's lookup table, not its grid
    # the grid's exact answers at one pose at a time, remembered between a fit's iterations
    memo: NearestMemo | None = field(default=None, init=False, repr=False, compare=False)

    def subset(self, index) -> "_Terms":
        # contiguous whatever the index (a slice is a strided view): the compiled rows take
        # one layout (``scanner_core.pose.warm`` compiles it)
        def take(values):
            return None if values is None else np.ascontiguousarray(values[index])
        return _Terms(take(self.points), take(self.normals), take(self.frames), self.model,
                      self.agreement, take(self.steps_mm), self.approximate)

    def rough(self) -> "_Terms":
        """The same points matched through the model's lookup table
        (``scanner_core.pose.nearest_table``) instead of its exact grid: what the search screens
        candidates with, whose points lie millimetres off the model."""
        return replace(self, approximate=True)


@dataclass
class _Fit:
    pose: np.ndarray
    rms: float
    inlier_fraction: float
    edge_fraction: float        # of the edge points, matched (1.0 without edges)
    iterations: int
    jacobian: np.ndarray        # (K, 6) of the inliers, about `centre`
    residuals: np.ndarray       # (K,)
    weights: np.ndarray         # (K,)
    frames: np.ndarray          # (K,) frame of each inlier
    curves: np.ndarray          # (K,) model edge curve of each edge row, -1 for surfaces
    faces: np.ndarray           # (K,) model face of each surface row, -1 for edges or none
    points: np.ndarray          # (K, 3) the scan point of each row, {T}
    centre: np.ndarray          # (3,)
    scale_mm: float             # radius that makes rotations comparable with translations


def _fine(surface: _Terms, edges: _Terms | None, start, params, *, warm: bool = True,
          wander: bool = False) -> _Fit:
    """The fit from `start` ((4, 4) ^T X_P, mm) to convergence; the search's quick
    refinements of many starts are ``scanner_core.pose.quick``. Without `warm`, every
    iteration uses all the points (a start already at a minimum of some of them). With
    `wander`, a fit whose steps are still ``_WANDER_STEP`` or more after
    ``_WANDER_ITERATIONS`` iterations stops there: it roams between minima, and the caller
    has the coarse search to turn to."""
    pose = start.copy()
    centre = surface.points.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((surface.points - centre) ** 2, axis=1)))) or 1.0
    gates = [params.gate_mm] * 2
    step_tol = np.array([params.tol_mm] * 3 + [np.radians(params.tol_deg)] * 3)
    # Far from the minimum, a quarter of the points steers as well as all of them.
    sparse = (surface.subset(slice(None, None, _WARM_STRIDE))
              if warm and len(surface.points) >= _WARM_MIN_POINTS else None)
    it = 0
    sizes, previous, visited = [], None, []
    for it in range(1, params.max_iterations + 1):
        terms = surface if sparse is None else sparse
        rows, sigmas = _linearise(terms, edges, pose, centre, gates, params)
        jac, res, w = rows[:3]
        if len(res) < 6:
            break
        delta, observed = _solve(jac, res, w, scale, params.free_std_mm)
        step = delta
        if sparse is None:
            step = delta + observed * _jump(previous, observed, scale)
            previous = observed
        pose = _apply(step, centre) @ pose
        gates = [max(params.min_gate_mm, min(g, 6.0 * sg)) for g, sg in zip(gates, sigmas)]
        if sparse is not None and (it >= _WARM_MAX_ITERATIONS
                                   or np.all(np.abs(observed) < _WARM_TOL_FACTOR * step_tol)):
            sparse = None
            continue
        if sparse is None and (_settled(sizes, observed, step_tol)
                               or _revisited(visited, pose, step_tol)):
            break
        if (wander and it >= _WANDER_ITERATIONS
                and np.any(np.abs(observed) >= _WANDER_STEP)):
            break
    pose, rows = _hold_free_motions(surface, edges, start, pose, centre, scale, gates, params)
    if rows is None:
        rows, _ = _linearise(surface, edges, pose, centre, gates, params)
    jac, res, w, frames, matched, curves, faces, points = rows
    inlier_fraction = matched / max(len(surface.points), 1)
    edge_fraction = ((len(res) - matched) / len(edges.points)) if edges is not None else 1.0
    rms = float(np.sqrt(np.sum(w * res**2) / np.sum(w))) if len(res) else np.inf
    return _Fit(pose, rms, inlier_fraction, edge_fraction, it, jac, res, w, frames, curves,
                faces, points, centre, scale)


# A fit that places a minimum (the search's, a probe's on a share of the points) stops at
# this many times the tolerance: a fit on every point settles it from there, and the fits on
# a subsample agree with it no closer than their own scatter. The settling fit itself stops
# there too (at 0.1 um and 0.1 mdeg by default): steps below that are tenths of the noise's
# effect, and took the fits on every point 2 to 8 more iterations (docs/pose.md).
_SEEK_TOL_FACTOR = 10.0


def _seeking(params):
    """`params` with the tolerance of a fit that places a minimum for another to settle."""
    return replace(params, tol_mm=params.tol_mm * _SEEK_TOL_FACTOR,
                   tol_deg=params.tol_deg * _SEEK_TOL_FACTOR)


def _settling(params, points: int):
    """`params` for a pose's fits of its `points` surface points: the search's on its
    subsample, and those on every point that settle what it placed (`_seeking`), when there
    are more than ``params.search_points``; `params` itself when the search ran on them all."""
    return _seeking(params) if points > params.search_points else params


def _hold_free_motions(surface, edges, start, pose, centre, scale, gates, params):
    """Take back what the fit moved along free motions, and settle the rest with them held.

    A free motion is one the scan does not pin down (`_observable`); a weak constraint (the
    facets of a turned cylinder) or the noise would otherwise leave it anywhere, and with it
    the {T} origin of a part turned about an axis that misses the origin.

    Returns the pose and, when it is the pose given (nothing free), its linearisation
    (`_linearise`'s first value), else None: the caller need not linearise there again.
    """
    rows, _ = _linearise(surface, edges, pose, centre, gates, params)
    jac, res, w, frames = rows[:4]
    if len(res) < 6:
        return pose, rows
    _, vectors, strong = _directions(jac, w, frames, scale, params)
    free = vectors[:, ~strong]
    if free.shape[1] == 0:
        return pose, rows
    s = np.array([1.0, 1.0, 1.0, scale, scale, scale])
    moved = pose @ np.linalg.inv(start)
    twist = np.concatenate([moved[:3, :3] @ centre + moved[:3, 3] - centre,
                            Rotation.from_matrix(moved[:3, :3]).as_rotvec()]) * s
    twist -= free @ (free.T @ twist)
    pose = _apply(twist / s, centre) @ start
    step_tol = np.array([params.tol_mm] * 3 + [np.radians(params.tol_deg)] * 3)
    sizes, visited = [], []
    for _ in range(params.max_iterations):
        (jac, res, w, *_), _ = _linearise(surface, edges, pose, centre, gates, params)
        if len(res) < 6:
            break
        _, observed = _solve(jac, res, w, scale, params.free_std_mm)
        pose = _apply(observed, centre) @ pose
        if _settled(sizes, observed, step_tol) or _revisited(visited, pose, step_tol):
            break
    return pose, None


# Poses a fit remembers to tell a cycle (a few iterations in cycloidal's polish).
_CYCLE_MEMORY = 16


def _revisited(visited: list, pose, step_tol) -> bool:
    """Whether `pose` is one of the fit's earlier poses (`visited`, which grows; within the
    tolerance): a fit whose correspondences flip between a few sets goes round a cycle of
    steps of several micrometres that neither settles nor creeps, to ``max_iterations``
    (cycloidal's steps of 0.3 to 9.8 um, every 6 iterations the same, measured in bench
    pose_time's scans)."""
    translation, rotation = pose[:3, 3], pose[:3, :3]
    cycled = any(np.all(np.abs(translation - t) < step_tol[:3])
                 and np.linalg.norm(Rotation.from_matrix(rotation @ r.T).as_rotvec())
                 < step_tol[3] for t, r in visited)
    visited.append((translation.copy(), rotation.copy()))
    del visited[:-_CYCLE_MEMORY]
    return cycled


def _jump(previous, delta, scale) -> float:
    """How many more steps of `delta` (the observable part of a step) the fit may take at
    once after `previous`: r / (1 - r) where the two point the same way and shrink by r
    (`_JUMP_DEG`, `_JUMP_RATIO`), else 0."""
    if previous is None:
        return 0.0
    s = np.array([1.0, 1.0, 1.0, scale, scale, scale])
    a, b = previous * s, delta * s
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0.0 or nb == 0.0 or a @ b < na * nb * np.cos(np.radians(_JUMP_DEG)):
        return 0.0
    ratio = nb / na
    return ratio / (1.0 - ratio) if ratio <= _JUMP_RATIO else 0.0


#: A fit from the nominal grasp still stepping this much (mm along, radians about x, y, z)
#: after this many iterations roams (`_fine`'s `wander`).
_WANDER_ITERATIONS = 20
_WANDER_STEP = np.array([0.01] * 3 + [np.radians(0.01)] * 3)


def _settled(sizes: list, step, step_tol) -> bool:
    """Whether a fit whose last step was `step` has settled: within the tolerance, or
    creeping (`_CREEP_FACTOR`). `sizes` holds the steps so far (in tolerances) and grows."""
    size = float(np.max(np.abs(step) / step_tol))
    sizes.append(size)
    return size < 1.0 or (len(sizes) > _CREEP_ITERATIONS and size < _CREEP_FACTOR
                          and size > 0.5 * sizes[-1 - _CREEP_ITERATIONS])


def _linearise(surface, edges, pose, centre, gates, params):
    """Residuals, Jacobian rows, robust weights and frames of all correspondences at `pose`
    (the rows of weight 0 left out).

    Returns ``(jacobian, residuals, weights, frames, surface_inliers, curves, faces,
    points)`` (``curves``: the model edge curve each row matched, ``EdgeModel.curves``, -1
    for a surface row; ``faces``: the model face each surface row matched,
    ``SurfaceModel.faces``, -1 for an edge row or a model without faces; ``points``: each
    row's scan point) and the robust scale of each kind (surface, edges).
    """
    parts, sigmas = [], []
    for terms, rows, gate, noise_mm in ((surface, _surface_rows, gates[0], params.surface_noise_mm),
                                        (edges, _edge_rows, gates[1], params.edge_noise_mm)):
        if terms is None:
            sigmas.append(np.inf)
            continue
        jac, res, w, sigma, nearest = rows(terms, pose[None], centre, gate, noise_mm)
        keep = w[0] > 0
        matched = nearest[0][keep]
        none = np.full(len(matched), -1, np.int64)
        if terms is edges:  # the model sample each row matched: its edge curve, its face
            curves, faces = terms.model.curves[matched], none
        else:
            model_faces = getattr(terms.model, "faces", None)
            curves, faces = none, (none if model_faces is None else model_faces[matched])
        parts.append((jac[0][keep], res[0][keep], w[0][keep], terms.frames[keep], curves,
                      faces, terms.points[keep]))
        sigmas.append(float(sigma[0]))
    jac, res, w, frames, curves, faces, points = (np.concatenate(x) for x in zip(*parts))
    return (jac, res, w, frames, len(parts[0][1]), curves, faces, points), sigmas


def _nearest(terms: _Terms, local, up, bound):
    """Distance to and index of the nearest model point within `bound` mm (inf and the
    model's size beyond it) of each point of `local` ((..., N, 3), the scan in {P}).

    A step's edge point lies half the step's height from the edge it was found at, up or
    down the wall (paper section II), and as far from the wall's other edge: matched from
    where it lies, it finds either, or another edge near the wall's middle. It is matched
    from half its step above and below it along z_T (`up`, z_T in {P}, (..., 3)) as well,
    and keeps the nearest of the three matches: the edge it came from.
    """
    shape = local.shape[:-1]
    if terms.approximate:
        def query(points):
            return terms.model.lookup.query(points, bound)
    else:
        def query(points):
            return terms.model.grid.query(points, k=1, distance_upper_bound=bound)
    if not terms.approximate and len(shape) == 2 and shape[0] == 1:
        # one pose: the fit's iterations ask again only where the answer may have changed
        if terms.memo is None:
            terms.memo = NearestMemo(terms.model.grid)
        dist, nearest = terms.memo.query(local.reshape(-1, 3), bound)
    else:
        dist, nearest = query(local.reshape(-1, 3))
    dist, nearest = dist.reshape(shape), nearest.reshape(shape)
    if terms.steps_mm is None:
        return dist, nearest
    stepped = np.nonzero(terms.steps_mm > 0)[0]
    if not len(stepped):
        return dist, nearest
    half = 0.5 * terms.steps_mm[stepped, None]
    for sign in (1.0, -1.0):
        moved = local[..., stepped, :] + sign * half * up[..., None, :]
        d, n = query(moved.reshape(-1, 3))
        d, n = d.reshape(moved.shape[:-1]), n.reshape(moved.shape[:-1])
        nearer = d < dist[..., stepped]
        dist[..., stepped] = np.where(nearer, d, dist[..., stepped])
        nearest[..., stepped] = np.where(nearer, n, nearest[..., stepped])
    return dist, nearest


def _surface_rows(terms: _Terms, poses, centre, gate, noise_mm):
    """Point-to-plane rows of the N surface points at each of the (P, 4, 4) `poses`: the
    residual of scan point s matched to model point q (normal n) is ``n . (s - X q)`` in
    {T}; a motion (t, w) about `centre` changes it by ``-[n, (s - centre) x n] . (t, w)``.
    Returns (P, N, 6) rows, (P, N) residuals and weights (0 for a point with no match,
    whose normal disagrees or beyond the gate), (P,) robust scales
    (``scanner_core.pose.rows.plane_rows``) and the model sample each point matched, (P, N)."""
    rotation, translation = poses[:, :3, :3], poses[:, :3, 3]
    local = (terms.points[None] - translation[:, None]) @ rotation  # (P, N, 3) in {P}
    dist, nearest = _nearest(terms, local, rotation[:, 2], gate + 2.0 * _spacing(terms.model))
    normals = terms.normals if terms.normals is not None else np.full(terms.points.shape, np.nan)
    valid = np.isfinite(dist)
    if not terms.approximate:
        valid &= ~_across_a_crease(terms.model, local, valid, nearest)
    # Scan normals point to the sensor, model normals out of the part: the same way up.
    rows = plane_rows(terms.points, normals, terms.model.points, terms.model.normals,
                      nearest, valid, rotation, translation, centre, gate,
                      noise_mm, terms.agreement, False, _MIN_EDGE_LEVEL, _MAD_TO_SIGMA,
                      _TUKEY_C, _MIN_SIGMA_MM)
    return (*rows, nearest)


def _across_a_crease(model: SurfaceModel, local, found, nearest) -> np.ndarray:
    """(P, N) bool: the points `found` a match whose sample lies beside a crease
    (``SurfaceModel.crease_planes``) and which lie nearer the crease's other face's plane
    than their sample's: a point of one face matched to a sample of the other, a spacing
    away, which would read its distance across to that face's plane (a rim's top-face point
    measured to the wall below it). They are left unmatched: the face they lie on has its
    own points."""
    return across_a_crease(local.reshape(-1, 3), found.reshape(-1),
                           np.asarray(nearest.reshape(-1), dtype=np.int64), model.crease_planes,
                           model.points, model.normals).reshape(found.shape)


def _edge_rows(terms: _Terms, poses, centre, gate, noise_mm):
    """Edge rows, as :func:`_surface_rows`: the distance in (x_T, y_T) from the edge point
    to the model's edge line, i.e. to the vertical plane through it (normal ``d x z_T`` for
    edge direction d); an edge within 17 degrees of z_T is no line in that plane. Returns
    the model sample each point matched, (P, N), as well."""
    rotation, translation = poses[:, :3, :3], poses[:, :3, 3]
    local = (terms.points[None] - translation[:, None]) @ rotation
    bound = gate + _spacing(terms.model) + _EDGE_SEARCH_MM
    dist, nearest = _nearest(terms, local, rotation[:, 2], bound)
    rows = plane_rows(terms.points, terms.points, terms.model.points, terms.model.directions,
                      nearest, np.isfinite(dist), rotation, translation, centre, gate,
                      noise_mm, -1.0, True, _MIN_EDGE_LEVEL, _MAD_TO_SIGMA, _TUKEY_C,
                      _MIN_SIGMA_MM)
    return (*rows, nearest)


def _spacing(model) -> float:
    """Typical distance between a model's points, mm (for the match radius)."""
    return float(getattr(model, "spacing_mm", 0.5))


def _information(jac, w, scale):
    """J^T W J with rotations scaled to arc length at `scale` mm (comparable units)."""
    js = jac / np.array([1.0, 1.0, 1.0, scale, scale, scale])
    return js.T @ (js * w[:, None])


def _observable(values, free_std_mm):
    """Which eigen-directions of the information the scan pins down better than the limit
    (`values` ascending along the last axis, one row per pose)."""
    return values > np.maximum(1.0 / free_std_mm**2, _SINGULAR * values[..., -1:])


def _directions(jac, w, frames, scale, params):
    """Eigen-decomposition of the information and which directions are observable: pinned
    down better than ``free_std_mm`` at the expected scatter, by at least ``min_frames``
    profiles' worth of information (two points at a part's far end, in one profile, pin
    nothing one can trust: that profile's placement error moves them together)."""
    s = np.array([1.0, 1.0, 1.0, scale, scale, scale])
    values, vectors = np.linalg.eigh(_information(jac, w, scale))
    strong = _observable(values, params.free_std_mm)
    projected = ((jac / s) @ vectors) ** 2 * w[:, None]  # (K, 6) information per row
    _, inverse = np.unique(frames, return_inverse=True)
    per_frame = np.zeros((inverse.max() + 1, 6))
    np.add.at(per_frame, inverse, projected)
    total = per_frame.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        effective = total**2 / np.sum(per_frame**2, axis=0)  # participation ratio
    strong &= np.nan_to_num(effective) >= params.min_frames
    return values, vectors, strong


def _solve(jac, res, w, scale, free_std_mm):
    """Gauss-Newton step, and its size along the observable motions only.

    Every direction with information moves (early in a fit a motion may look free only for
    want of matches); the step's size for convergence leaves out the free motions, which a
    weak constraint (the facets of a turned cylinder) would otherwise creep along for ever.
    """
    s = np.array([1.0, 1.0, 1.0, scale, scale, scale])
    step, observed = _steps((jac / s)[None], res[None], w[None], free_std_mm)
    return step[0] / s, observed[0] / s


def _steps(scaled_jac, res, w, free_std_mm):
    """:func:`_solve` for P poses at once, on (P, N, 6) rows already scaled to arc length
    (rows of weight 0 count for nothing): each pose's step and its part along the observable
    motions, both (P, 6) in scaled units."""
    weighted = scaled_jac.transpose(0, 2, 1) * w[:, None]  # (P, 6, N)
    info = weighted @ scaled_jac
    rhs = (weighted @ res[..., None])[..., 0]
    values, vectors = np.linalg.eigh(info)
    top = values[:, -1:]
    projected = np.einsum("pji,pj->pi", vectors, rhs)
    with np.errstate(all="ignore"):
        moving = values > _SINGULAR * top
        along = np.where(moving, projected / np.where(moving, values, 1.0), 0.0)
        strong = _observable(values, free_std_mm)
    step = np.einsum("pij,pj->pi", vectors, along)
    observed = np.einsum("pij,pj->pi", vectors, np.where(strong, along, 0.0))
    return step, observed


def _apply(delta, centre) -> np.ndarray:
    """4x4 in {T}: rotate by ``delta[3:]`` about `centre`, then translate by ``delta[:3]``;
    (P, 4, 4) for (P, 6) `delta`."""
    delta = np.asarray(delta, dtype=np.float64)
    if delta.ndim == 2:
        m = np.tile(np.eye(4), (len(delta), 1, 1))
        rotation = Rotation.from_rotvec(delta[:, 3:]).as_matrix()
        m[:, :3, :3] = rotation
        m[:, :3, 3] = centre + delta[:, :3] - rotation @ centre
        return m
    m = np.eye(4)
    rotation = Rotation.from_rotvec(delta[3:]).as_matrix()
    m[:3, :3] = rotation
    m[:3, 3] = centre + delta[:3] - rotation @ centre
    return m


def _evenly(n: int, limit: int) -> np.ndarray:
    """At most `limit` indices spread evenly over ``range(n)``."""
    return np.unique(np.linspace(0, n - 1, min(n, limit)).astype(np.int64)) if n else np.arange(0)


def _subsample(n: int, limit: int, rng) -> np.ndarray:
    if n <= limit:
        return np.arange(n)
    return np.sort(rng.choice(n, size=limit, replace=False))
