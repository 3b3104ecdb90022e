"""The search's quick refinement (``scanner_core.pose.search``): a few Gauss-Newton steps from
each of many starts at once.

The coarse grid refines 27 orientations and the probes up to 10 turns, each for a few
iterations on a few hundred points. Refined one at a time, each iteration of each start paid
numpy's per-call overhead for arrays of a few hundred rows (the coarse stage took 180-370 ms
of a pose's time, bench pose_time); refined together, each iteration is one look-up of every
start's points and one batch of 6 x 6 solves.

The rows and the step are the fine stage's own (``scanner_core.pose.fine``: `_surface_rows`,
`_edge_rows` and `_steps` take P poses at once; a single fit passes one): point-to-plane rows
for surfaces, rows across the edge in (x_T, y_T) for edges, Tukey's biweight at each start's
own robust scale, on rectangular (P, N) arrays where a row without a match, or outside the
gate, weighs 0. Unlike the fine stage, the gate stays fixed. A start stops moving once its
step along the observable motions is within the tolerance or creeps (``pose_fine._settled``),
as a single fit does. Units: mm, radians.
"""
from __future__ import annotations

import numpy as np

from scanner_core.pose.fine import _apply, _edge_rows, _settled, _steps, _surface_rows, _Terms


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
        jac, res, w, *_ = _surface_rows(surface, current, centre, gate_mm,
                                        params.surface_noise_mm)
        if edges is not None and len(edges.points):
            e_jac, e_res, e_w, *_ = _edge_rows(edges, current, centre, gate_mm,
                                               params.edge_noise_mm)
            jac, res, w = (np.concatenate(pair, axis=1)
                           for pair in ((jac, e_jac), (res, e_res), (w, e_w)))
        enough = np.count_nonzero(w > 0, axis=1) >= 6
        delta, observed = _steps(jac / s, res, w, params.free_std_mm)
        moved = index[enough]
        poses[moved] = _apply(delta[enough] / s, centre) @ poses[moved]
        active[index[~enough]] = False  # too few rows: the start stays (as a single fit stops)
        for k in np.nonzero(enough)[0]:
            if _settled(sizes[index[k]], observed[k] / s, step_tol):
                active[index[k]] = False
    return poses
