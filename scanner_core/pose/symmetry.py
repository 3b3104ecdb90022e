"""The near symmetry behind a rotation the scan holds loosely, named for the report.

A pose not acted on because a rotation is loose (free, its sigma beyond the act tolerance,
or another minimum that fits as well: ``scanner_core.pose.confidence.judge``) says why in
the part's terms: "6-fold about z_T" (a hexagonal prism), "87-fold about z_T" (a ring
tessellated into 87 facets), "round about x_T" (a shaft whose flat the pass does not see).

- **axis**: the screw axis of each rival's difference from the fit (a near symmetry maps
  the part onto itself), else the free rotation's line, else the covariance's loosest
  rotation with the axis of a surface of revolution fitted to the model's normals (every
  normal meets it: ``a . (p x n) + m . n = 0`` in Plucker coordinates).
- **self-match** (`self_match`): the fraction of the model's samples that, turned by an
  angle about the axis, land on the model's surface (within a tolerance of a sample's plane,
  normals agreeing).
- **fold**: among the n whose period 360/n puts every rival's turn near a whole number of
  periods, the one the model matches itself best at (tight tolerance: the expected scatter),
  the smallest on a tie; kept when at least ``NEAR`` of the model matches, and clearly more
  than at half the period (else it is a round part's tessellation).
- **round**: the model matches itself, on average over three unrelated turns, within the
  final agreement tolerance (``_FINAL_TOL`` times the scatter): any turn fits nearly as well.

The part's *exact* symmetries (`exact_symmetries`) are another matter: turns that map the
CAD onto itself (``EXACT_FRACTION`` of its surface within ``EXACT_TOL_MM``), tried about the
principal axes of its surface (any n-fold turn about an axis whose two perpendicular second
moments are equal, a half turn about each), closed into a group. Poses that differ by one of
them place the part the same: the pose reported is the one nearest the nominal grasp
(`nearest_equivalent`), and a rival that is the pose turned by one is no rival.

Units: mm, degrees in the report.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["name_symmetry", "self_match", "NEAR", "exact_symmetries", "nearest_equivalent",
           "equivalent_to", "surface_moments", "EXACT_TOL_MM", "EXACT_FRACTION"]

#: At least this fraction of the model's surface matching itself turned is a near symmetry
#: (it only names why a rotation the scan holds loosely is loose: a shaft whose flat, 13 % of
#: its surface, the pass does not see).
NEAR = 0.75
# A principal axis of the surface within this (degrees) of the loose rotation is its axis.
_SNAP_DEG = 10.0
# Samples of the model used for the self-match.
_SAMPLES = 3000
# Turns that share no period with each other or with a small fold (degrees): a model that
# matches itself at all three is round about the axis.
_ROUND_TURNS_DEG = (13.7, 67.3, 151.9)
# A fold is the part's own when the model matches itself this much better at it than at half
# its period (tight tolerance).
_FOLD_MARGIN = 0.05
# Folds tried when no rival suggests a period.
_SMALL_FOLDS = tuple(range(2, 13))
# A rival's turn within this of a whole number of periods (degrees, or this fraction of the
# period if larger) suggests that period.
_PERIOD_SLACK_DEG, _PERIOD_SLACK = 0.5, 0.1
# Periods shorter than 2 degrees (the slack a quarter of them) tell nothing apart.
_MAX_FOLD = 180
_AXIS_LABELS = ("x_T", "y_T", "z_T")
#: A turn maps the part onto itself when this fraction of its samples land within
#: ``EXACT_TOL_MM`` of its surface: the rest are samples whose neighbours sit on the next
#: facet. A feature that tells the turns apart (a key, a notch) is more of the surface than
#: the fraction leaves out, unless smaller than about half a percent of it.
EXACT_TOL_MM, EXACT_FRACTION = 0.01, 0.995
# Two second moments of the surface within this relative difference are equal: the axis
# of the third can carry an n-fold symmetry (n >= 3).
_EQUAL_MOMENTS = 1e-3
# The exact symmetry's folds tried about such an axis (periods of 2 degrees and more, as
# for the near ones), screened on this many samples, and the largest group kept.
_EXACT_FOLDS = tuple(range(2, _MAX_FOLD + 1))
_SCREEN_SAMPLES = 500
# A fold whose screened match is within this of the best screened one is matched on all.
_SCREEN_SLACK = 0.05
_MAX_GROUP = 2 * _MAX_FOLD


def name_symmetry(pose, covariance, rivals, free_axes, model, params) -> dict | None:
    """The near symmetry about the loose rotation of a pose, or None when there is none.

    Parameters
    ----------
    pose : (4, 4) float
        ^T X_P, mm.
    covariance : (6, 6) float
        The pose's (tx, ty, tz mm, rx, ry, rz rad); NaN rows along free motions.
    rivals : list of (4, 4) float
        Other minima that fit as well (beyond the act tolerance).
    free_axes : list of dict
        ``PoseResult.free_axes``.
    model : scanner_core.pose.models.SurfaceModel
    params : scanner_core.pose.registration.PoseParams

    Returns
    -------
    dict or None
        ``{"label", "axis" (unit, {T}), "through_mm" ({T}), "fold" (int or None),
        "period_deg" (float or None), "round" (bool), "matched_fraction"}``.
    """
    pose = np.asarray(pose, dtype=np.float64)
    axis_t, through_t, turns = _loose_axis(pose, covariance, rivals, free_axes)
    if axis_t is None:
        return None
    rotation = pose[:3, :3]
    if through_t is None:
        axis_p, pivot_p = _fit_line(model, rotation.T @ axis_t)
        axis_t = rotation @ axis_p
    else:
        axis_p, pivot_p = rotation.T @ axis_t, rotation.T @ (through_t - pose[:3, 3])
    tight = params.surface_noise_mm
    loose = 5.0 * params.surface_noise_mm  # pose_search._FINAL_TOL times the scatter
    folds = _candidate_folds(turns)
    fold, matched = None, 0.0
    screen = {n: self_match(model, axis_p, pivot_p, 360.0 / n, tight, _SCREEN_SAMPLES)
              for n in folds}
    # screened on a few samples, the best few matched on all (none when even the best
    # screened is too far below a near symmetry for its samples' scatter to hide one)
    top = max(screen.values(), default=0.0)
    if top >= NEAR - _SCREEN_SLACK:
        scores = {n: self_match(model, axis_p, pivot_p, 360.0 / n, tight)
                  for n, f in screen.items() if f >= top - _SCREEN_SLACK}
        best = max(scores.values())
        if best >= NEAR:
            # of the folds that match as well, the one the rivals' turns fit best (a 4.1 degree
            # turn of a faceted surface slides along its facets whether it is 86- or 87-fold),
            # then the smallest
            fold = min((n for n, f in scores.items() if f >= best - 0.01),
                       key=lambda n: (round(_period_misfit(turns, n), 2), n))
            matched = scores[fold]
            # A fold the model matches no better than half its period is no symmetry of its
            # own: a round part's tessellation (a 128-sided shaft), or a near-round one.
            half = self_match(model, axis_p, pivot_p, 180.0 / fold, tight)
            if matched < half + _FOLD_MARGIN:
                fold = None
    # a mean over three turns: a few samples each tell 75 % from not
    round_match = float(np.mean([self_match(model, axis_p, pivot_p, t, loose, _SCREEN_SAMPLES)
                                 for t in _ROUND_TURNS_DEG]))
    is_round = round_match >= NEAR
    if fold is None and not is_round:
        return None
    axis_t = axis_t * np.sign(axis_t[np.argmax(np.abs(axis_t))])
    where = _axis_words(axis_t)
    if fold is not None:
        label = f"{fold}-fold about {where}"
    else:
        label = f"round about {where}"
        matched = round_match
    if matched < 0.995:
        label += f" ({1.0 - matched:.0%} of the surface breaks it)"
    return {"label": label,
            "axis": np.round(axis_t, 6).tolist(),
            "through_mm": np.round(rotation @ pivot_p + pose[:3, 3], 3).tolist(),
            "fold": fold,
            "period_deg": None if fold is None else round(360.0 / fold, 6),
            "round": bool(is_round),
            "matched_fraction": round(float(matched), 4)}


def self_match(model, axis_p, pivot_p, turn_deg: float, tol_mm: float,
               samples: int = _SAMPLES) -> float:
    """Fraction of (up to `samples` of) the model's samples that, turned by `turn_deg`
    about the line through `pivot_p` along the unit `axis_p` (both in {P}), lie within
    `tol_mm` of a nearby sample's plane with normals within 30 degrees."""
    step = max(1, len(model.points) // samples)
    points, normals = model.points[::step], model.normals[::step]
    turn = Rotation.from_rotvec(np.radians(turn_deg) * np.asarray(axis_p)).as_matrix()
    moved = (points - pivot_p) @ turn.T + pivot_p
    moved_normals = normals @ turn.T
    reach = tol_mm + 2.0 * model.spacing_mm
    _, nearest = model.tree.query(moved, k=4, distance_upper_bound=reach)
    found = nearest < len(model.points)
    safe = np.where(found, nearest, 0)
    offset = moved[:, None, :] - model.points[safe]
    plane = np.abs(np.einsum("nkj,nkj->nk", offset, model.normals[safe]))
    agree = np.einsum("nkj,nj->nk", model.normals[safe], moved_normals) > np.cos(np.radians(30))
    return float(np.mean(np.any(found & agree & (plane <= tol_mm), axis=1)))


def _loose_axis(pose, covariance, rivals, free_axes):
    """The loose rotation's line in {T} (unit axis, a point on it, mm) and the rivals' turns
    about it (degrees, in (0, 360)); None for the line when there is none.

    From rivals: the screw axis of each rival's difference from the fit (a near symmetry
    maps the part onto itself, so the difference turns it about the symmetry's axis), signs
    aligned, the axes summed and the points averaged across it. From a free rotation: its
    axis and point. Else the covariance's loosest rotation, its line fitted to the model's
    normals (`_fit_line`)."""
    if rivals:
        motions = [r @ np.linalg.inv(pose) for r in rivals]
        vectors = np.array([Rotation.from_matrix(m[:3, :3]).as_rotvec() for m in motions])
        lead = vectors[np.argmax(np.linalg.norm(vectors, axis=1))]
        signs = np.where(vectors @ lead < 0, -1.0, 1.0)
        axis = (vectors * signs[:, None]).sum(axis=0)
        axis /= np.linalg.norm(axis)
        across = np.eye(3) - np.outer(axis, axis)
        points = []
        for m, v in zip(motions, vectors):
            # on the motion's own screw axis c: R c + t = c + (t . a) a
            own = v / np.linalg.norm(v)
            c = np.linalg.lstsq(np.eye(3) - m[:3, :3], m[:3, 3] - (m[:3, 3] @ own) * own,
                                rcond=1e-9)[0]
            points.append(across @ c)
        turns = np.degrees(vectors @ axis) % 360.0
        return axis, np.mean(points, axis=0), [t for t in turns if 1e-6 < t < 360.0 - 1e-6]
    for free in free_axes:
        if free.get("kind") == "rotation" and free.get("through_mm") is not None:
            return (np.asarray(free["axis"], dtype=np.float64),
                    np.asarray(free["through_mm"], dtype=np.float64), [])
    block = np.asarray(covariance, dtype=np.float64)[3:, 3:]
    if not np.isfinite(block).all():
        return None, None, []
    _, vectors = np.linalg.eigh(block)
    return vectors[:, -1], None, []


def _fit_line(model, axis_p):
    """The axis of the model's surface of revolution nearest `axis_p` ({P}): every normal
    of such a surface meets its axis, ``a . (p x n) + m . n = 0`` in the axis' Plucker
    coordinates (a, m), solved as the least singular vector over the samples; the unit axis
    and a point on it, or `axis_p` through the samples' centre when the fit turns more than
    ``_SNAP_DEG`` from it."""
    axis_p = np.asarray(axis_p, dtype=np.float64) / np.linalg.norm(axis_p)
    step = max(1, len(model.points) // _SAMPLES)
    points, normals = model.points[::step], model.normals[::step]
    centre = points.mean(axis=0)
    rows = np.hstack([np.cross(points - centre, normals), normals])
    vector = np.linalg.svd(rows, full_matrices=False)[2][-1]
    a, m = vector[:3], vector[3:]
    size = np.linalg.norm(a)
    if size < 1e-9 or abs(a @ axis_p) / size < np.cos(np.radians(_SNAP_DEG)):
        return axis_p, centre
    a, m = a / size, m / size
    # the point of the line (a, m) nearest the samples' centre: a x m, from it
    point = centre + np.cross(a, m)
    return a * np.sign(a @ axis_p), point


def _candidate_folds(turns) -> list[int]:
    """The n (2..``_MAX_FOLD``) whose period 360/n puts every turn in `turns` (degrees)
    within ``_PERIOD_SLACK`` of a whole, non-zero number of periods; ``_SMALL_FOLDS``
    without turns."""
    if not len(turns):
        return list(_SMALL_FOLDS)
    turns = np.asarray(turns, dtype=np.float64)
    folds = []
    for n in range(2, _MAX_FOLD + 1):
        period = 360.0 / n
        whole = np.round(turns / period)
        slack = max(_PERIOD_SLACK_DEG, _PERIOD_SLACK * period)
        if np.all(whole >= 1) and np.all(np.abs(turns - whole * period) <= slack):
            folds.append(n)
    return folds


def _period_misfit(turns, fold: int) -> float:
    """RMS (degrees) of the `turns` from their nearest whole numbers of periods 360/`fold`;
    0 without turns."""
    if not len(turns):
        return 0.0
    turns = np.asarray(turns, dtype=np.float64)
    period = 360.0 / fold
    return float(np.sqrt(np.mean((turns - np.round(turns / period) * period) ** 2)))


def _axis_words(axis) -> str:
    main = int(np.argmax(np.abs(axis)))
    if abs(axis[main]) > 0.9:
        return _AXIS_LABELS[main]
    return str(np.round(axis * np.sign(axis[main]), 3).tolist())


def surface_moments(mesh) -> tuple[np.ndarray, np.ndarray]:
    """The centroid (3,) and the principal axes (3, 3), columns, of a mesh's surface (its
    area's second moments about the centroid, exact over each triangle:
    ``A/12 (9 m m^T + sum_k d_k d_k^T)`` for a triangle of area A, centroid m and corners
    d_k, all about the surface's centroid), with the moments (3,) ascending, mm^2."""
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    area = np.asarray(mesh.area_faces, dtype=np.float64)
    total = float(area.sum())
    if not total > 0.0:  # no area: no axes to speak of
        return tri.reshape(-1, 3).mean(axis=0), np.eye(3), np.zeros(3)
    centroid = (area[:, None] * tri.mean(axis=1)).sum(axis=0) / total
    d = tri - centroid
    m = d.mean(axis=1)
    second = (9.0 * np.einsum("f,fi,fj->ij", area, m, m)
              + np.einsum("f,fki,fkj->ij", area, d, d)) / (12.0 * total)
    moments, axes = np.linalg.eigh(second)
    return centroid, axes, moments


def exact_symmetries(model, centroid, axes, moments) -> np.ndarray:
    """The turns that map the part onto itself, as (K, 4, 4) float64 transforms in {P}
    (the identity first; K = 1 for a part without symmetry).

    Tried about each principal axis through the centroid (`surface_moments`): every fold
    of ``_EXACT_FOLDS`` about an axis whose perpendicular moments are equal, a half turn
    about the others; the largest fold that matches (`self_match` at ``EXACT_TOL_MM``, at
    least ``EXACT_FRACTION``) generates that axis's turns. A part round about an axis (it
    matches a turn that is no period: ``_ROUND_TURNS_DEG``) has no discrete symmetry there;
    its free turn is the fit's to hold (``PoseResult.free_axes``).
    """
    def turn(axis, angle_deg):
        t = np.eye(4)
        t[:3, :3] = Rotation.from_rotvec(np.radians(angle_deg) * axis).as_matrix()
        t[:3, 3] = centroid - t[:3, :3] @ centroid
        return t

    def matches(axis, angle_deg):
        # a turn that maps the part onto itself matches on any subset of the samples
        return (self_match(model, axis, centroid, angle_deg, EXACT_TOL_MM, _SCREEN_SAMPLES)
                >= EXACT_FRACTION - 0.01
                and self_match(model, axis, centroid, angle_deg, EXACT_TOL_MM)
                >= EXACT_FRACTION)

    generators = []
    scale = max(float(np.max(moments)), 1e-12)
    for k in range(3):
        axis = axes[:, k]
        others = [moments[j] for j in range(3) if j != k]
        if abs(others[0] - others[1]) <= _EQUAL_MOMENTS * scale:
            if matches(axis, _ROUND_TURNS_DEG[0]):
                continue
            folds = [n for n in _EXACT_FOLDS if matches(axis, 360.0 / n)]
        else:
            folds = [2] if matches(axis, 180.0) else []
        if folds:
            generators.append(turn(axis, 360.0 / max(folds)))
    group = np.eye(4)[None]
    if not generators:
        return group
    generators = np.stack(generators)
    frontier = group
    while len(frontier) and len(group) < _MAX_GROUP:
        new = []
        for product in (frontier[:, None] @ generators[None]).reshape(-1, 4, 4):
            known = np.concatenate([group, *(p[None] for p in new)])
            if not np.any(np.all(np.isclose(product, known, atol=1e-6), axis=(1, 2))):
                new.append(product)
        frontier = np.array(new).reshape(-1, 4, 4)
        group = np.concatenate([group, frontier])
    return group


def nearest_equivalent(pose, nominal, group) -> np.ndarray:
    """(4, 4) float64: of the turns `g` in `group` (`exact_symmetries`), whose poses
    ``pose @ g`` place the part the same, the one that brings the pose's rotation nearest
    `nominal`'s (the identity when that is `pose` itself)."""
    pose = np.asarray(pose, dtype=np.float64)
    if len(group) < 2:
        return np.eye(4)
    relative = (pose @ group)[:, :3, :3] @ np.asarray(nominal, dtype=np.float64)[:3, :3].T
    cos = (np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0
    return np.array(group[int(np.argmax(cos))])


def equivalent_to(pose, other, group, tol_mm: float, tol_deg: float) -> bool:
    """Whether `other` is `pose` turned by one of the part's symmetries other than the
    identity, within `tol_mm` (the {T} origin) and `tol_deg`."""
    for g in group[1:]:
        d = np.asarray(other) @ np.linalg.inv(np.asarray(pose) @ g)
        if (np.linalg.norm(d[:3, 3]) <= tol_mm
                and np.degrees(Rotation.from_matrix(d[:3, :3]).magnitude()) <= tol_deg):
            return True
    return False
