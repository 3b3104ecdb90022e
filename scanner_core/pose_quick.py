"""The search's quick refinement (``scanner_core.pose_search``): a few Gauss-Newton steps from
each of many starts at once.

The coarse grid refines 27 orientations and the probes up to 10 turns, each for a few
iterations on a few hundred points. Refined one at a time, each iteration of each start paid
numpy's per-call overhead for arrays of a few hundred rows (the coarse stage took 180-370 ms
of a pose's time, bench pose_time); refined together, each iteration is one look-up of every
start's points and one batch of 6 x 6 solves.

The step is the fine stage's (``scanner_core.pose_fine``: point-to-plane rows for surfaces,
rows across the edge in (x_T, y_T) for edges, a fixed correspondence gate, Tukey's biweight at
each start's own robust scale, the step solved where the information is not singular), on
rectangular (P, N) arrays: a row that has no match, or lies outside the gate, weighs 0. A
start stops moving once its step along the observable motions is within the tolerance or
creeps (``pose_fine._settled``), as a single fit does. Units: mm, radians.
"""
from __future__ import annotations

import numpy as np

from scanner_core.pose_fine import (_EDGE_SEARCH_MM, _MAD_TO_SIGMA, _MIN_EDGE_LEVEL,
                                    _MIN_SIGMA_MM, _SINGULAR, _TUKEY_C, _apply, _nearest,
                                    _settled, _spacing, _Terms)


def _quick_fits(surface: _Terms, edges: _Terms | None, starts, params, *, iterations: int,
                gate_mm: float) -> np.ndarray:
    """Each of the (P, 4, 4) `starts` refined for at most `iterations` Gauss-Newton steps.

    Parameters
    ----------
    surface, edges : _Terms
        The points to fit (the search's subsample, usually ``_Terms.rough``); `edges` may be
        None.
    starts : (P, 4, 4) float
        Poses ^T X_P, mm.
    params : PoseParams
        ``tol_mm``, ``tol_deg`` (when a start has settled), ``free_std_mm`` (what counts as
        observable), ``surface_noise_mm`` and ``edge_noise_mm`` (the rows' weights).
    iterations : int
    gate_mm : float
        Correspondences with a residual beyond this are left out, mm.

    Returns
    -------
    (P, 4, 4) float64
        The refined poses; a start with fewer than 6 rows stays where it is.
    """
    poses = np.array(starts, dtype=np.float64, copy=True).reshape(-1, 4, 4)
    centre = surface.points.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((surface.points - centre) ** 2, axis=1)))) or 1.0
    s = np.array([1.0, 1.0, 1.0, scale, scale, scale])
    step_tol = np.array([params.tol_mm] * 3 + [np.radians(params.tol_deg)] * 3)
    active = np.ones(len(poses), bool)
    sizes = [[] for _ in poses]
    for _ in range(int(iterations)):
        index = np.nonzero(active)[0]
        if not len(index):
            break
        current = poses[index]
        jac, res, w = _surface_rows(surface, current, centre, gate_mm, params.surface_noise_mm)
        if edges is not None and len(edges.points):
            e_jac, e_res, e_w = _edge_rows(edges, current, centre, gate_mm,
                                           params.edge_noise_mm)
            jac, res, w = (np.concatenate(pair, axis=1)
                           for pair in ((jac, e_jac), (res, e_res), (w, e_w)))
        enough = np.count_nonzero(w > 0, axis=1) >= 6
        delta, observed = _solve(jac / s, res, w, params.free_std_mm)
        for k, i in enumerate(index):
            if not enough[k]:
                active[i] = False  # too few rows: the start stays (as a single fit stops)
                continue
            poses[i] = _apply(delta[k] / s, centre) @ poses[i]
            if _settled(sizes[i], observed[k] / s, step_tol):
                active[i] = False
    return poses


def _surface_rows(terms: _Terms, poses, centre, gate, noise_mm):
    """(P, N, 6) Jacobian rows, (P, N) residuals and weights of the surface points at each
    pose: ``n . (s - X q)`` for scan point s matched to model point q of normal n."""
    rotation, translation = poses[:, :3, :3], poses[:, :3, 3]
    local = (terms.points[None] - translation[:, None]) @ rotation  # (P, N, 3) in {P}
    dist, nearest = _nearest(terms, local, rotation[:, 2], gate + 2.0 * _spacing(terms.model))
    valid = np.isfinite(dist)
    nearest = np.where(valid, nearest, 0)
    turn = rotation.transpose(0, 2, 1)  # row vectors in {P} to {T}
    n_t = terms.model.normals[nearest] @ turn
    if terms.normals is not None:
        # Scan normals point to the sensor, model normals out of the part: the same way up.
        agree = np.einsum("pnj,nj->pn", n_t, np.nan_to_num(terms.normals, nan=0.0))
        valid &= (agree >= terms.agreement) | ~np.isfinite(terms.normals[:, 0])
    q_t = terms.model.points[nearest] @ turn + translation[:, None]
    return _robust_rows(terms.points, n_t, q_t, valid, centre, gate, noise_mm)


def _edge_rows(terms: _Terms, poses, centre, gate, noise_mm):
    """As :func:`_surface_rows` for edge points: the distance in (x_T, y_T) to the vertical
    plane through the matched model edge (normal ``d x z_T`` for edge direction d)."""
    rotation, translation = poses[:, :3, :3], poses[:, :3, 3]
    local = (terms.points[None] - translation[:, None]) @ rotation
    bound = gate + _spacing(terms.model) + _EDGE_SEARCH_MM
    dist, nearest = _nearest(terms, local, rotation[:, 2], bound)
    valid = np.isfinite(dist)
    nearest = np.where(valid, nearest, 0)
    turn = rotation.transpose(0, 2, 1)
    d_t = terms.model.directions[nearest] @ turn
    m = np.stack([d_t[..., 1], -d_t[..., 0], np.zeros(d_t.shape[:-1])], axis=-1)
    length = np.linalg.norm(m, axis=-1)
    valid &= length > _MIN_EDGE_LEVEL  # an edge along z_T is no line in (x_T, y_T)
    m = m / np.maximum(length, 1e-12)[..., None]
    q_t = terms.model.points[nearest] @ turn + translation[:, None]
    return _robust_rows(terms.points, m, q_t, valid, centre, gate, noise_mm)


def _robust_rows(s_t, n_t, q_t, valid, centre, gate, noise_mm):
    """Rows within `gate` weighted by Tukey's biweight at each pose's own robust scale (the
    median absolute deviation of its rows within the gate) and by ``1 / noise_mm**2``; a
    pose with fewer than 3 such rows gets none (``pose_fine._robust_rows``)."""
    res = np.sum(n_t * (s_t[None] - q_t), axis=-1)
    inside = valid & (np.abs(res) <= gate)
    counted = np.count_nonzero(inside, axis=1)
    inside &= (counted >= 3)[:, None]
    # a pose without rows gets zeros (no all-NaN median); its weights are 0 regardless
    masked = np.where(inside | ~inside.any(axis=1, keepdims=True), np.where(inside, res, 0.0),
                      np.nan)
    middle = np.nanmedian(masked, axis=1, keepdims=True)
    spread = np.nanmedian(np.abs(masked - middle), axis=1, keepdims=True)
    sigma = np.maximum(_MAD_TO_SIGMA * spread, _MIN_SIGMA_MM)
    u = np.where(inside, res, 0.0) / (_TUKEY_C * sigma)
    w = np.where(inside & (np.abs(u) < 1.0), (1.0 - u**2) ** 2, 0.0) / noise_mm**2
    jac = np.concatenate([n_t, np.cross(s_t[None] - centre, n_t)], axis=-1)
    return jac, np.where(inside, res, 0.0), w


def _solve(scaled_jac, res, w, free_std_mm):
    """Batched ``pose_fine._solve`` on rows already scaled to arc length: each pose's
    Gauss-Newton step (every direction with information) and its part along the observable
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
        strong = values > np.maximum(1.0 / free_std_mm**2, _SINGULAR * top)
    step = np.einsum("pij,pj->pi", vectors, along)
    observed = np.einsum("pij,pj->pi", vectors, np.where(strong, along, 0.0))
    return step, observed
