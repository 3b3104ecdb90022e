"""The global search of the registration (``scanner_core.pose.registration``): where to start the fine
stage when the nominal grasp is no good start, and which other minima fit as well.

- **agreement** (`_agreement`, `_agreements`): a pose scored at fixed tolerances, the
  fraction of the surface points and of the edge points it matches, not by a fit's own
  robust scale, which favours a loose, unsettled fit. It ranks the candidates, and
  compares converged fits (`_final_score`).
- **coarse** (`_coarse`): used when the fine stage from the nominal grasp does not settle on
  a good fit; a grid of orientations around the nominal grasp, each with its translation
  seeded from the scan's extent, is refined briefly on a subsample; around the best few, a
  finer sweep about the rotation their fit pins down least (a flat part's turn in its plane,
  held by its edges alone) finds the basin a many-lobed outline leaves a degree or two wide.
  The same sweep checks a fit from the nominal grasp that looks good (`_better_turn`): one a
  lobe off matches every edge point but a keyway's.
- **probes** (`_probe_turns`): a converged fit whose weakest turn is held loosely is refitted
  from turns near it and from the best turns of a sweep all the way round it
  (`_round_seeds`): a round part picked from a bin can sit any turn off its nominal. A
  minimum that fits clearly better is taken; one that fits as well (`_rival_margin`) is a
  rival, which the uncertainty then covers (``scanner_core.pose.confidence``).

The quick refinements of the coarse grid and of the probes, the probes' sweep all the way
round, and the scores that only place a seed (the coarse sweep's turns, a probe peak's best
turn) match their points through the models' lookup tables (``_Terms.rough``,
``scanner_core.pose.nearest_table``): their points lie millimetres off the model, where an
exact query is slow (an edge point searches 15 mm), and a seed is refined before anything is
decided on it. The scores that rank refined candidates and decide (the better turn, the final
scores, the rival margins), and every full fit, use the exact search (the models' grids).
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import maximum_filter1d
from scipy.spatial.transform import Rotation

from scanner_core.pose.rows import matched_within
from scanner_core.pose.fine import (_EDGE_SEARCH_MM, _MIN_EDGE_LEVEL, _evenly, _Fit, _fine,
                                    _information, _linearise, _nearest, _seeking, _settling,
                                    _spacing, _subsample, _Terms)
from scanner_core.pose.quick import _quick_fits

# Model points that seed a coarse candidate's translation.
_SEED_POINTS = 5000
# Poses whose seeds a model remembers (the coarse grid's 27 around each grasp it is held by).
_SEED_CACHE = 1024
# A converged fit is scored at this many times the expected scatter.
_FINAL_TOL = 5.0


def _turn_deg(pose, other) -> float:
    """The angle between two poses' rotations, degrees."""
    relative = np.asarray(pose)[:3, :3] @ np.asarray(other)[:3, :3].T
    return float(np.degrees(Rotation.from_matrix(relative).magnitude()))


def _final_score(surface, edges, fit: _Fit, params) -> float:
    """A converged fit's agreement at ``_FINAL_TOL`` times the expected scatter."""
    return _agreement(surface, edges, fit.pose, _FINAL_TOL * params.surface_noise_mm,
                      _FINAL_TOL * params.edge_noise_mm)


def _agreement(surface: _Terms, edges: _Terms | None, pose, tol_surface: float,
               tol_edge: float) -> float:
    """How well `pose` explains the scan at fixed tolerances: the fraction of the surface
    points within `tol_surface` mm of the model's plane (normals agreeing) plus the fraction
    of the edge points within `tol_edge` mm of a model edge (in the (x_T, y_T) plane).

    Unlike a fit's own inlier fractions, which count within a multiple of the fit's own
    robust scale, this does not reward a loose, unsettled fit: it ranks the
    candidates of the coarse search, which are refined only briefly.
    """
    return float(_agreements(surface, edges, pose[None], tol_surface, tol_edge)[0])


def _agreements(surface: _Terms, edges: _Terms | None, poses, tol_surface: float,
                tol_edge: float, edge_search_mm: float = _EDGE_SEARCH_MM) -> np.ndarray:
    """(P,) :func:`_agreement` of each of the (P, 4, 4) `poses`, in one query of each model's
    tree (a sweep of 355 turns took 56 ms, as many single calls 123 ms). An edge point
    finds its model edge within `edge_search_mm` beyond `tol_edge` (a step's point of
    unknown height lies up to half the tallest step from its edge; a query that far costs
    six times one within a millimetre)."""
    scores = _matched_fraction(surface, poses, _surface_bound(surface, tol_surface),
                               tol_surface, planes=True)
    if edges is None or not len(edges.points):
        return scores + 1.0
    return scores + _matched_fraction(edges, poses, _edge_bound(edges, tol_edge, edge_search_mm),
                                      tol_edge, planes=False)


def _surface_bound(surface: _Terms, tol: float) -> float:
    """How far (mm) a surface point's model sample may lie for a match within `tol`."""
    return tol + 2.0 * _spacing(surface.model)


def _edge_bound(edges: _Terms, tol: float, search_mm: float = _EDGE_SEARCH_MM) -> float:
    return tol + _spacing(edges.model) + search_mm


def _matched_fraction(terms: _Terms, poses, bound, tol, *, planes: bool) -> np.ndarray:
    """(P,) fraction of `terms`' points :func:`_matched` at each pose."""
    matched = _matched(terms, poses, bound, tol, planes=planes)
    return matched.sum(axis=1) / max(len(terms.points), 1)


def _matched(terms: _Terms, poses, bound, tol, *, planes: bool) -> np.ndarray:
    """(P, N) bool: whether each of `terms`' points lies within `tol` of its model at each
    pose: of its plane (normals agreeing) for surfaces, of its edge across it in (x_T, y_T)
    for edges.
    Residuals are taken in {P}, where the model lies (a distance does not change with the
    frame), so each pose's rotation is applied once per point, not per match."""
    n = len(terms.points)
    rotation, translation = poses[:, :3, :3], poses[:, :3, 3]
    local = (terms.points[None] - translation[:, None]) @ rotation  # (P, N, 3) in {P}
    dist, nearest = _nearest(terms, local, rotation[:, 2], bound)
    if planes:
        vectors = terms.model.normals
        normals = terms.normals if terms.normals is not None else np.full((n, 3), np.nan)
    else:
        vectors, normals = terms.model.directions, terms.points
    return matched_within(local, nearest, np.isfinite(dist), terms.model.points, vectors,
                          normals, rotation, terms.agreement, tol, planes, _MIN_EDGE_LEVEL)


# The coarse candidates are ranked at these tolerances (mm, surface and edges): wide enough
# for a fit refined only briefly, narrow enough that a wrong turn (a feature a lobe off)
# does not pass.
_COARSE_TOL_MM = (0.1, 0.25)
# Distinct coarse candidates kept from the grid, each swept about its weakest rotation.
_COARSE_KEEP = 3
# Seeds from the sweeps refined and compared.
_SWEEP_SEEDS = 4
# Two candidates closer than this (degrees, and mm) are the same.
_SAME_DEG, _SAME_MM = 1.0, 0.5


def _coarse(surface: _Terms, edges: _Terms | None, nominal, params, rng) -> list[np.ndarray]:
    """Starts for the fine stage, best first, from a grid of orientations around the nominal
    grasp and, around the best of them, a finer sweep about the rotation their fit pins down
    least (a flat part's turn in its plane: the edges alone hold it, and the basin of a part
    with a many-lobed outline is a degree or two wide)."""
    few = surface.subset(_subsample(len(surface.points), params.coarse_points, rng))
    few_edges = None if edges is None else edges.subset(
        _subsample(len(edges.points), params.coarse_points, rng))
    angles = np.arange(-params.coarse_extent_deg, params.coarse_extent_deg + 1e-9,
                       params.coarse_step_deg)
    grid = np.array(np.meshgrid(angles, angles, angles, indexing="ij")).reshape(3, -1).T
    grid = grid[np.argsort(np.linalg.norm(grid, axis=1))]
    rough, rough_edges = few.rough(), _rough(few_edges)

    def refine(starts) -> list:
        poses = _quick_fits(rough, rough_edges, starts, params,
                            iterations=params.coarse_iterations, gate_mm=params.gate_mm * 2)
        return list(zip(poses, _agreements(few, few_edges, poses, *_COARSE_TOL_MM)))

    turns = np.tile(np.eye(4), (len(grid), 1, 1))
    turns[:, :3, :3] = Rotation.from_rotvec(np.radians(grid)).as_matrix()
    kept = _distinct(refine(_seed_translations(few.points, surface.model, turns @ nominal)),
                     _COARSE_KEEP)
    # The sweep: about the weakest rotation of the best candidate's fit, through the scan's
    # centre, across the grid's step, without refinement (cheap); the best distinct seeds
    # are then refined like the grid's candidates.
    step = max(params.coarse_sweep_deg, 1e-3)
    half = params.coarse_step_deg / 2.0 + step
    offsets = np.arange(-half, half + 1e-9, step)
    centre = few.points.mean(axis=0)
    seeds = []
    for pose, _ in kept:
        axis = _weakest_rotation(few, few_edges, pose, centre, params)
        moved = _turned(pose, axis, centre, offsets)
        seeds.extend(zip(moved, _agreements(rough, rough_edges, moved, *_COARSE_TOL_MM)))
    refined = refine(np.stack([pose for pose, _ in
                               _distinct(seeds, _SWEEP_SEEDS, same_deg=step * 1.5)]))
    return [pose for pose, _ in _distinct(refined + kept, _SWEEP_SEEDS)]


# A turn whose agreement beats the fit's by this much (fractions of the surface points plus
# of the edge points) sends a fit that looked good to the coarse search.
_BETTER_TURN = 0.02
# The turns of the check scored through the lookup tables, the best this many of them again
# through the exact search, which decides.
_TURN_CHECK_EXACT = 3


def _better_turn(surface: _Terms, edges: _Terms | None, pose, params) -> np.ndarray | None:
    """The turn of `pose` about its weakest rotation, within one step of the coarse grid,
    that fits the scan better than `pose` itself, or None: a fit that matches most of its points
    can still sit a lobe or a tooth off (every edge but a keyway's matches), the many-lobed
    outline then pins the wrong turn as tightly as the right one; and a fit from a start
    far off can stop a few degrees short of the truth however firmly its weakest rotation
    is held. The turns are screened through the lookup tables (some 2 ms for 30 turns of
    800 points, against 20 through the KD-trees) and the best few decide through the
    exact search. The turn found is a start for the fine stage (a fit a lobe off then lands on
    the right one without the whole coarse search)."""
    rng = np.random.default_rng(params.seed + 1)
    few = surface.subset(_subsample(len(surface.points), params.coarse_points, rng))
    few_edges = None if edges is None else edges.subset(
        _subsample(len(edges.points), params.coarse_points, rng))
    centre = few.points.mean(axis=0)
    axis = _weakest_rotation(few, few_edges, pose, centre, params)
    step = max(params.coarse_sweep_deg, 1e-3)
    angles = np.arange(step, params.coarse_step_deg + 1e-9, step)
    turned = _turned(pose, axis, centre, np.concatenate([angles, -angles]))
    rough = _agreements(few.rough(), _rough(few_edges), turned, *_COARSE_TOL_MM)
    best = turned[np.argsort(-rough, kind="stable")[:_TURN_CHECK_EXACT]]
    own = _agreement(few, few_edges, pose, *_COARSE_TOL_MM)
    exact = _agreements(few, few_edges, best, *_COARSE_TOL_MM)
    winner = int(np.argmax(exact))
    return best[winner] if exact[winner] > own + _BETTER_TURN else None


# The turns about the weakest rotation a converged fit is probed with, degrees: a part held by
# little but a few small features (ADIS16480, whose large faces lie parallel to the sheet) has
# minima a degree apart whose own curvature claims a few hundredths of a degree.
_PROBE_DEG = (-2.0, -1.0, 1.0, 2.0)
# And all the way round, for a part with a near symmetry about that rotation: cycloidal's
# lobes fit 90, 180 and 270 degrees off with 91 % of the points matched against 96 % at the
# truth, unflagged, for a start that far off (a round part picked from a bin); a 38-lobed
# disc's any whole number of lobes off. The sweep (:func:`_round_seeds`) turns the fit in
# steps of ``coarse_sweep_deg`` from beyond the near probes, scores each turn unrefined at
# loose tolerances (mm, surface and edges: lobes 0.4 mm high blur, a keyway does not, and a
# turn about a slightly wrong line still scores), with this many points of each kind, and
# keeps the best turn of each of its peaks (maxima this far either side, degrees) for the
# quick refinement: the 6 best peaks, at 60-80 ms a sweep.
_ROUND_FROM_DEG = 3.0
_ROUND_TOL_MM = (0.5, 1.0)
_ROUND_POINTS = 150
_ROUND_APART_DEG = 5.0
_ROUND_SEEDS = 6
_ROUND_FINE_DEG = 0.2
# A rotation the surfaces hold less than this (their weakest rotation's information over their
# strongest's) rests mostly on the edges, where an outline that repeats (lobes, teeth) can fit
# a turn off. Measured at the bench's fits: a disc seen on its flat face 1e-17, featuretype
# up to 6e-6, cycloidal 4.5e-4 to 4.4e-3 (its fits' weakness with the edges, 0.016-0.032,
# is above ``probe_weakness``), ADIS16480 1.6e-3 to 0.026, idler_riser 0.011-0.023.
_EDGES_ALONE = 7e-3
# Not about a rotation the scan leaves free (a cylinder's: weakness 2e-6, against 0.004 to
# 0.023 for the reference parts' weakest): every turn about it fits, and it is reported free.
_HELD_WEAKNESS = 1e-4
# A probe whose quick refinement scores within this of the fit's (coarse tolerances) is
# refined fully; one whose full fit then scores within _RIVAL_SCORE of the best is a rival.
_PROBE_MARGIN = 0.01
# The quick refinement of a probe: points and iterations (a tenth of the fit's cost).
_PROBE_POINTS, _PROBE_ITERATIONS = 400, 4
_RIVAL_SCORE = 0.002
# ... or within this many standard errors of the paired difference of the two agreements
# (McNemar 1947, per profile: of the points one pose matches and the other does not, as many
# each way when the scan cannot tell them apart). ADIS16480 seen on its 44 x 14 mm end in 12
# profiles has two minima 0.15 degree apart about z_T that differ by 8 of 2 600 surface
# points: the one 0.003 better was reported with a sigma of 20 mdeg.
_RIVAL_Z = 2.0
# A rival this close to the fit (degrees, mm) is the same minimum.
_RIVAL_SAME_DEG, _RIVAL_SAME_MM = 0.02, 0.02
# A probe is fitted first on 1/_MID_SHARE of the search's points. It settles within
# _MID_SAME times that of the minimum it shares with a fit on every point (the subsample's
# own scatter), and its score on every point lies within ``_PROBE_MARGIN`` of that fit's:
# one below the best by more than `_MID_MARGIN` can be neither better nor a rival
# (``_rival_margin`` is at most ``_PROBE_MARGIN``).
_MID_SHARE = 2
_MID_SAME = 2.0
_MID_MARGIN = 2.0 * _PROBE_MARGIN


def _probe_turns(surface: _Terms, edges: _Terms | None, fit: _Fit, params):
    """The converged fit checked against refits from turns of it about its weakest rotation.

    Returns the fit (or a probe's, when it scores clearly better: ``_BETTER_TURN``) and the
    others that score as well (within :func:`_rival_margin`, or better) but lie elsewhere:
    distinct minima the scan cannot tell apart, which the uncertainty must then cover.
    Every fit is probed from turns of ``_PROBE_DEG`` about its weakest rotation: the fine
    stage from a start far off can stop a degree or two short of a better minimum however
    firmly the scan holds that rotation, and how firmly it holds it, measured on a few
    hundred points, varies by a factor of two between subsamples. The sweep all the way
    round is for a fit whose weakest rotation is held less than ``probe_weakness``, or by
    its edges alone (its surfaces hold it less than ``_EDGES_ALONE``: a flat part turning in
    its plane, whose outline may repeat). A quick refinement (the coarse stage's) screens the
    turns; those that pass are fitted on a share of the points, and on every point only
    when they settle on a minimum not yet fitted that may score as well (docs/pose.md,
    "Speed").
    """
    rng = np.random.default_rng(params.seed + 2)
    few = surface.subset(_subsample(len(surface.points), _PROBE_POINTS, rng))
    few_edges = None if edges is None else edges.subset(
        _subsample(len(edges.points), _PROBE_POINTS, rng))
    centre = few.points.mean(axis=0)
    axis, weakness = _weakest_rotation(few, few_edges, fit.pose, centre, params, weakness=True)
    weakly_held = weakness <= params.probe_weakness or (
        few_edges is not None
        and _weakest_rotation(few, None, fit.pose, centre, params, weakness=True)[1]
        <= _EDGES_ALONE)
    rough, rough_edges = few.rough(), _rough(few_edges)
    own = _agreement(few, few_edges, fit.pose, *_COARSE_TOL_MM)
    starts = list(_turned(fit.pose, axis, centre, _PROBE_DEG))
    if weakly_held and weakness > _HELD_WEAKNESS:
        starts += _round_seeds(few, few_edges, fit.pose, axis, params)
    quick = _quick_fits(rough, rough_edges, np.stack(starts), params,
                        iterations=_PROBE_ITERATIONS, gate_mm=params.gate_mm * 2)
    scores = _agreements(few, few_edges, quick, *_COARSE_TOL_MM)
    # Each probe that passes is fitted on a share of the points first: many settle on a
    # minimum already found, or on one that scores clearly below the best, and only the
    # others are fitted again on every point.
    share = max(params.search_points // _MID_SHARE, _PROBE_POINTS)
    mid = (surface.subset(_subsample(len(surface.points), share, rng))
           if len(surface.points) > share else surface)
    settled = []
    for pose, score in zip(quick, scores):
        if (score >= own - _PROBE_MARGIN
                and all(not _same(pose, other, _RIVAL_SAME_DEG * 10, _RIVAL_SAME_MM * 10)
                        for other in [fit.pose] + [f.pose for f in settled])):
            probe = _fine(mid, edges, pose, _seeking(params) if mid is not surface else params)
            if all(not _same(probe.pose, other, _RIVAL_SAME_DEG * _MID_SAME,
                             _RIVAL_SAME_MM * _MID_SAME)
                   for other in [fit.pose] + [f.pose for f in settled]):
                settled.append(probe)
    if not settled:
        return fit, []
    own_final = _final_score(surface, edges, fit, params)
    fits = [fit]
    if mid is surface:
        fits += settled
    else:
        tolerances = (_FINAL_TOL * params.surface_noise_mm, _FINAL_TOL * params.edge_noise_mm)
        on_all = _agreements(surface, edges, np.stack([f.pose for f in settled]), *tolerances)
        best = max(float(np.max(on_all)), own_final)
        # settled on every point as the search's own minimum was
        settle = _settling(params, len(surface.points))
        fits += [_fine(surface, edges, f.pose, settle) for f, sc in zip(settled, on_all)
                 if sc >= best - _MID_MARGIN]
    if len(fits) == 1:
        return fit, []
    scores = [own_final] + [_final_score(surface, edges, f, params) for f in fits[1:]]
    # Move to a probe's minimum only when it is clearly better (as the coarse stage would);
    # one barely better is a rival, not an answer.
    best = int(np.argmax(scores))
    keep = best if scores[best] > scores[0] + _BETTER_TURN else 0
    rivals = []
    for f, sc in zip(fits, scores):
        if (f is not fits[keep]
                and scores[keep] - sc <= _rival_margin(surface, edges, fits[keep].pose, f.pose,
                                                        params)
                and all(not _same(f.pose, other, _RIVAL_SAME_DEG, _RIVAL_SAME_MM)
                        for other in [fits[keep].pose] + rivals)):
            rivals.append(f.pose)
    return fits[keep], rivals


def _rival_margin(surface: _Terms, edges: _Terms | None, pose, other, params) -> float:
    """How much lower than `pose`'s final score `other`'s may be and still fit as well:
    ``_RIVAL_SCORE``, or ``_RIVAL_Z`` standard errors of the difference, counted on the
    points that only one of the two matches (each kind of point over its own number, as
    in :func:`_agreement`), but never more than ``_PROBE_MARGIN``. The points of one
    profile, surface and edge alike, share its placement, so they count as one cluster (as
    in :func:`_uncertainty`): its net share squared, never less than its discordant points'
    (McNemar's variance for independent points). The cap keeps a minimum that misses a
    whole profile or two from passing: with the differences in a few clusters, the
    difference is never more than a few standard errors, however large."""
    tol_surface, tol_edge = _FINAL_TOL * params.surface_noise_mm, _FINAL_TOL * params.edge_noise_mm
    kinds = [(surface, _surface_bound(surface, tol_surface), tol_surface, True)]
    if edges is not None and len(edges.points):
        kinds.append((edges, _edge_bound(edges, tol_edge), tol_edge, False))
    frames = np.concatenate([terms.frames for terms, *_ in kinds])
    _, cluster = np.unique(frames, return_inverse=True)
    net = np.zeros(cluster.max() + 1 if len(cluster) else 0)
    independent = np.zeros_like(net)
    start = 0
    for terms, bound, tol, planes in kinds:
        n = len(terms.points)
        first, second = _matched(terms, np.stack([pose, other]), bound, tol, planes=planes)
        mine = cluster[start:start + n]
        start += n
        net += np.bincount(mine, first.astype(float) - second, minlength=len(net)) / max(n, 1)
        independent += np.bincount(mine, (first != second).astype(float),
                                   minlength=len(net)) / max(n, 1) ** 2
    standard_error = float(np.sqrt(np.sum(np.maximum(net**2, independent))))
    return min(max(_RIVAL_SCORE, _RIVAL_Z * standard_error), _PROBE_MARGIN)


def _round_seeds(few: _Terms, few_edges: _Terms | None, pose, axis, params) -> list:
    """Starts all the way round the weakest rotation: `pose` turned about `axis` through the
    model's centre (on the axis of a part near-symmetric about it; the scan's own centre is
    not, when the scan sees one side) in steps of ``coarse_sweep_deg``, scored without
    refinement in one batch (:func:`_agreements`); the best turns of the ``_ROUND_SEEDS``
    best peaks of that score (maxima ``_ROUND_APART_DEG`` either side), as (4, 4) poses in
    {T}."""
    step = max(params.coarse_sweep_deg, 0.1)
    pivot = pose[:3, :3] @ few.model.points.mean(axis=0) + pose[:3, 3]
    few = few.subset(_evenly(len(few.points), _ROUND_POINTS))
    if few_edges is not None:
        few_edges = few_edges.subset(_evenly(len(few_edges.points), _ROUND_POINTS))
    moved = _turned(pose, axis, pivot, np.arange(_ROUND_FROM_DEG, 360.0 - _ROUND_FROM_DEG + 1e-9,
                                                 step))
    # an edge point matched near its edge (drop-outs, steps of known height), through the
    # lookup tables, is all a rough ranking at these tolerances needs
    scores = _agreements(few.rough(), _rough(few_edges), moved, *_ROUND_TOL_MM,
                         edge_search_mm=_ROUND_TOL_MM[1])
    # the best turn of each peak of the score (a broad lobe's shoulders outscore a narrower
    # lobe's top): maxima within _ROUND_APART_DEG either side, best first
    reach = max(1, int(round(_ROUND_APART_DEG / step)))
    peaks = np.nonzero(scores >= maximum_filter1d(scores, 2 * reach + 1, mode="nearest"))[0]
    chosen = []
    for i in peaks[np.argsort(-scores[peaks], kind="stable")]:
        if all(abs(i - j) > reach for j in chosen):
            chosen.append(i)
            if len(chosen) == _ROUND_SEEDS:
                break
    # Each peak placed within a fraction of a degree, at the tight tolerances (through the
    # lookup tables: the seed is refined before it is scored for a decision): a minimum
    # about a weakly held rotation can be narrower than the sweep's step (cycloidal's true
    # turn: a start 2 degrees off settles in a minimum 1.6 degrees off it).
    fine = np.arange(-step, step + 1e-9, _ROUND_FINE_DEG)
    local = np.concatenate([_turned(moved[i], axis, pivot, fine) for i in chosen]) if chosen \
        else np.zeros((0, 4, 4))
    tight = _agreements(few.rough(), _rough(few_edges), local,
                        *_COARSE_TOL_MM).reshape(len(chosen), len(fine))
    return [local[k * len(fine) + int(np.argmax(row))] for k, row in enumerate(tight)]


def _rough(terms: _Terms | None) -> _Terms | None:
    return None if terms is None else terms.rough()


def _turned(pose, axis, pivot, angles_deg) -> np.ndarray:
    """(K, 4, 4): `pose` turned by each of the (K,) `angles_deg` about the line through
    `pivot` (mm, {T}) along the unit `axis`."""
    turns = np.tile(np.eye(4), (len(angles_deg), 1, 1))
    turns[:, :3, :3] = Rotation.from_rotvec(
        np.radians(np.asarray(angles_deg, dtype=np.float64))[:, None] * axis).as_matrix()
    turns[:, :3, 3] = pivot - turns[:, :3, :3] @ pivot
    return turns @ pose


def _distinct(candidates, count, *, same_deg=_SAME_DEG, same_mm=_SAME_MM):
    """Up to `count` of `(pose, score)` pairs, best first, no two closer than `same_deg`
    and `same_mm` (one basin's candidates count once)."""
    chosen = []
    for pose, score in sorted(candidates, key=lambda c: -c[1]):
        if all(not _same(pose, other, same_deg, same_mm) for other, _ in chosen):
            chosen.append((pose, score))
            if len(chosen) == count:
                break
    return chosen


def _same(a, b, same_deg=_SAME_DEG, same_mm=_SAME_MM) -> bool:
    return _turn_deg(a, b) < same_deg and np.linalg.norm(a[:3, 3] - b[:3, 3]) < same_mm


def _weakest_rotation(surface, edges, pose, centre, params, *, weakness: bool = False):
    """Unit axis in {T} of the rotation the fit at `pose` pins down least (translations
    free to follow: the Schur complement of the information); z_T when it cannot tell.
    With `weakness`, also the ratio of its information to the strongest rotation's."""
    (jac, _, w, *_), _ = _linearise(surface, edges, pose, centre,
                                      [params.gate_mm * 2] * 2, params)
    if len(w) < 6:
        axis, ratio = np.array([0.0, 0.0, 1.0]), 0.0
    else:
        info = _information(jac, w, 1.0)
        tt, tr, rr = info[:3, :3], info[:3, 3:], info[3:, 3:]
        values, vectors = np.linalg.eigh(rr - tr.T @ np.linalg.pinv(tt) @ tr)
        axis = vectors[:, 0] * np.sign(vectors[np.argmax(np.abs(vectors[:, 0])), 0])
        ratio = float(values[0] / values[-1]) if values[-1] > 0 else 0.0
    return (axis, ratio) if weakness else axis


def _seed_translations(pts, model, poses) -> np.ndarray:
    """Shift each of the (P, 4, 4) `poses` so that the model's sensor-facing side meets the
    scan: centres in x, y, the nearest surfaces to the sensor (largest z_T) in z."""
    scan_xy = np.median(pts[:, :2], axis=0)
    scan_z = np.percentile(pts[:, 2], 95)
    moved = np.array(poses, dtype=np.float64, copy=True)
    for pose in moved:
        model_xy, model_z = _model_seed(model, pose)
        pose[:2, 3] += scan_xy - model_xy
        pose[2, 3] += scan_z - model_z
    return moved


def _model_seed(model, pose) -> tuple[np.ndarray, float]:
    """The median (x, y) and the 95th percentile z_T of the model's sensor-facing samples
    at `pose`, remembered per pose (``SurfaceModel.seed_cache``)."""
    cache = getattr(model, "seed_cache", None)
    key = np.asarray(pose, dtype=np.float64).tobytes()
    if cache is not None and key in cache:
        return cache[key]
    few = slice(None, None, max(1, len(model.points) // _SEED_POINTS))
    model_t = model.points[few] @ pose[:3, :3].T + pose[:3, 3]
    facing = (model.normals[few] @ pose[:3, :3].T)[:, 2] > 0.3
    if facing.sum() < 10:
        facing = np.ones(len(model_t), bool)
    seed = (np.median(model_t[facing, :2], axis=0), np.percentile(model_t[facing, 2], 95))
    if cache is not None:
        if len(cache) >= _SEED_CACHE:
            cache.clear()
        cache[key] = seed
    return seed
