"""The fine stage's rows (``scanner_core.pose.fine``: point-to-plane residuals, Jacobian rows
and Tukey weights of matched scan points) and the search's agreement test
(``scanner_core.pose.search._matched``), each in one compiled pass at P poses at once.

Done with numpy, one row set took some 30 array operations (gathers, the turn into {T}, the
normal test, the gate, two masked medians, the weights): 2.9 ms for 6 000 points of which the
KD-tree's query took 2.3 ms, 0.58 ms for 1 300 points of which 0.38 ms (one core). Once the
queries are remembered between iterations (``scanner_core.pose.nearest_table.NearestMemo``) those
overheads were what was left. Here each point is read once.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(nogil=True, cache=True)
def plane_rows(scan_points, scan_normals, model_points, model_vectors, nearest, valid, rotation,
               translation, centre, gate, noise_mm, agreement, edges, min_level, mad_to_sigma,
               tukey_c, min_sigma):
    """Robust point-to-plane rows of N scan points matched to model points at P poses.

    For pose p (``X = [R | t]``, {P} to {T}) and scan point s (mm, {T}) matched to model
    point q with vector v (both {P}):

    - a surface's plane normal is ``n = R v`` (v the model normal); the match counts only
      where n agrees with the scan normal (``n . s_n >= agreement``, a NaN normal agrees);
    - an edge's is ``n = (d_y, -d_x, 0) / |.|`` for ``d = R v`` (v the edge direction): the
      vertical plane through the edge, no plane where ``|.| <= min_level``;
    - the residual is ``r = n . (s - (R q + t))``, the Jacobian row ``[n, (s - centre) x n]``.

    Residuals within `gate` are weighted by Tukey's biweight at the pose's robust scale
    ``sigma = max(mad_to_sigma * MAD, min_sigma)`` (MAD: the median absolute deviation
    from their median), ``w = (1 - (r / (tukey_c sigma))^2)^2 / noise_mm^2``; a pose with
    fewer than 3 such residuals has none (weights 0, scale inf).

    Parameters
    ----------
    scan_points : (N, 3) float64
    scan_normals : (N, 3) float64
        Surfaces only (NaN: unknown); edges: any array.
    model_points, model_vectors : (M, 3) float64
    nearest : (P, N) int64
        Each point's model point at each pose; read only where `valid`.
    valid : (P, N) bool
        A match within the query's bound.
    rotation : (P, 3, 3) float64
    translation : (P, 3) float64
    centre : (3,) float64
        The point the rotations turn about.
    gate, noise_mm, agreement, min_level, mad_to_sigma, tukey_c, min_sigma : float
    edges : bool

    Returns
    -------
    jacobian : (P, N, 6) float64
        0 outside the gate.
    residuals, weights : (P, N) float64
        0 outside the gate.
    scale : (P,) float64
        sigma, mm; inf for a pose with fewer than 3 residuals within the gate.
    """
    count, n = nearest.shape
    jacobian = np.zeros((count, n, 6))
    residuals = np.zeros((count, n))
    weights = np.zeros((count, n))
    scale = np.full(count, np.inf)
    inside = np.zeros(n, np.bool_)
    kept = np.empty(n)
    for p in range(count):
        r, t = rotation[p], translation[p]
        k = 0
        for i in range(n):
            inside[i] = False
            if not valid[p, i]:
                continue
            j = nearest[p, i]
            v0, v1, v2 = model_vectors[j, 0], model_vectors[j, 1], model_vectors[j, 2]
            nx = r[0, 0] * v0 + r[0, 1] * v1 + r[0, 2] * v2
            ny = r[1, 0] * v0 + r[1, 1] * v1 + r[1, 2] * v2
            nz = r[2, 0] * v0 + r[2, 1] * v1 + r[2, 2] * v2
            if edges:
                length = np.sqrt(ny * ny + nx * nx)
                if not length > min_level:
                    continue
                nx, ny, nz = ny / length, -nx / length, 0.0
            elif np.isfinite(scan_normals[i, 0]):
                if (nx * scan_normals[i, 0] + ny * scan_normals[i, 1]
                        + nz * scan_normals[i, 2]) < agreement:
                    continue
            q0, q1, q2 = model_points[j, 0], model_points[j, 1], model_points[j, 2]
            dx = scan_points[i, 0] - (r[0, 0] * q0 + r[0, 1] * q1 + r[0, 2] * q2 + t[0])
            dy = scan_points[i, 1] - (r[1, 0] * q0 + r[1, 1] * q1 + r[1, 2] * q2 + t[1])
            dz = scan_points[i, 2] - (r[2, 0] * q0 + r[2, 1] * q1 + r[2, 2] * q2 + t[2])
            res = nx * dx + ny * dy + nz * dz
            if not abs(res) <= gate:
                continue
            inside[i] = True
            residuals[p, i] = res
            cx = scan_points[i, 0] - centre[0]
            cy = scan_points[i, 1] - centre[1]
            cz = scan_points[i, 2] - centre[2]
            jacobian[p, i, 0], jacobian[p, i, 1], jacobian[p, i, 2] = nx, ny, nz
            jacobian[p, i, 3] = cy * nz - cz * ny
            jacobian[p, i, 4] = cz * nx - cx * nz
            jacobian[p, i, 5] = cx * ny - cy * nx
            kept[k] = res
            k += 1
        if k < 3:
            for i in range(n):
                residuals[p, i] = 0.0
                for c in range(6):
                    jacobian[p, i, c] = 0.0
            continue
        middle = np.median(kept[:k])
        for m in range(k):
            kept[m] = abs(kept[m] - middle)
        sigma = max(mad_to_sigma * np.median(kept[:k]), min_sigma)
        scale[p] = sigma
        for i in range(n):
            if inside[i]:
                u = residuals[p, i] / (tukey_c * sigma)
                if abs(u) < 1.0:
                    weights[p, i] = (1.0 - u * u) ** 2 / noise_mm**2
    return jacobian, residuals, weights, scale


@njit(nogil=True, cache=True)
def matched_within(local, nearest, valid, model_points, model_vectors, scan_normals,
                   rotation, agreement, tol, planes, min_level):
    """(P, N) bool: whether each scan point lies within `tol` (mm) of its model match at
    each of P poses, the residual taken in {P} (``offset = local - q``):

    - surfaces (`planes`): ``|v . offset| <= tol`` for the model normal v, and the scan
      normal turned into {P} (``R^T s_n``; a NaN normal agrees) at least `agreement` (a
      cosine) along v;
    - edges: across the edge in (x_T, y_T), ``|z . (v x offset)| <= tol * level`` for the
      edge direction v and z_T in {P} (``z``, the third row of R), where
      ``level = sqrt(1 - (z . v)^2)`` must exceed `min_level`.

    Parameters
    ----------
    local : (P, N, 3) float64
        The scan points in {P} at each pose, mm.
    nearest : (P, N) int64
    valid : (P, N) bool
    model_points, model_vectors : (M, 3) float64
    scan_normals : (N, 3) float64
        Surfaces only; edges: any array.
    rotation : (P, 3, 3) float64
    agreement, tol, min_level : float
    planes : bool
    """
    count, n = nearest.shape
    matched = np.zeros((count, n), np.bool_)
    for p in range(count):
        r = rotation[p]
        for i in range(n):
            if not valid[p, i]:
                continue
            j = nearest[p, i]
            ox = local[p, i, 0] - model_points[j, 0]
            oy = local[p, i, 1] - model_points[j, 1]
            oz = local[p, i, 2] - model_points[j, 2]
            vx, vy, vz = model_vectors[j, 0], model_vectors[j, 1], model_vectors[j, 2]
            if planes:
                if not abs(vx * ox + vy * oy + vz * oz) <= tol:
                    continue
                sx, sy, sz = scan_normals[i, 0], scan_normals[i, 1], scan_normals[i, 2]
                if np.isfinite(sx):
                    # the scan normal in {P}: R^T s_n
                    px = r[0, 0] * sx + r[1, 0] * sy + r[2, 0] * sz
                    py = r[0, 1] * sx + r[1, 1] * sy + r[2, 1] * sz
                    pz = r[0, 2] * sx + r[1, 2] * sy + r[2, 2] * sz
                    if vx * px + vy * py + vz * pz < agreement:
                        continue
                matched[p, i] = True
            else:
                zx, zy, zz = r[2, 0], r[2, 1], r[2, 2]
                along = zx * vx + zy * vy + zz * vz
                level = np.sqrt(max(1.0 - along * along, 0.0))
                across = abs(zx * (vy * oz - vz * oy) + zy * (vz * ox - vx * oz)
                             + zz * (vx * oy - vy * ox))
                matched[p, i] = level > min_level and across <= tol * level
    return matched


@njit(nogil=True, cache=True)
def across_a_crease(points, found, nearest, crease_planes, model_points, model_normals):
    """(K,) bool: the `points` ((K, 3) mm, in {P}) `found` a match (their `nearest` model
    sample, (K,) int64) whose sample lies beside a crease (a finite row of `crease_planes`,
    (M, 4): the plane ``n . x = c`` of its crease neighbour's face) and which lie nearer that
    plane than their sample's own (``|n_q . (x - q)|``)."""
    out = np.zeros(len(points), np.bool_)
    for i in range(len(points)):
        if not found[i]:
            continue
        j = nearest[i]
        if not np.isfinite(crease_planes[j, 0]):
            continue
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        own = abs(model_normals[j, 0] * (x - model_points[j, 0])
                  + model_normals[j, 1] * (y - model_points[j, 1])
                  + model_normals[j, 2] * (z - model_points[j, 2]))
        across = abs(crease_planes[j, 0] * x + crease_planes[j, 1] * y
                     + crease_planes[j, 2] * z - crease_planes[j, 3])
        out[i] = across < own
    return out
