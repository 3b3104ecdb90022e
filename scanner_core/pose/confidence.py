"""How far to trust a registered pose (``scanner_core.pose.registration``): its covariance, the motions
the scan leaves free, and the flags.

- **covariance** (`_uncertainty`): the cluster-robust sandwich ``H^-1 (sum_f g_f g_f^T)
  H^-1`` over the frames f (Liang and Zeger 1986): the points of one profile share that
  frame's placement error (the marker's triangulation), so they are not independent, and
  the sandwich takes that from the residuals themselves. The edge points along one edge of
  the model share an error too: their offsets are pooled over the scan's edge curves and
  added (`_two_way_meat`, `_shared_offsets`). Those two are scaled by
  ``PoseParams.sigma_inflation`` (1 by default). An axis that few profiles hold has its
  profiles' variance measured from few independent draws: it is widened to Student's t's on
  their degrees of freedom (`_profile_freedom`). The surface points of one model face share
  an offset across the profiles too, measured face by face and added (`_face_offsets`). The
  whole is taken about the {T} origin, and widened by each rival minimum the search found
  (``scanner_core.pose.search._probe_turns``) and by the light plane's uncertainty carried
  through the fit (`_sheet_response`); ``pose_inputs.add_placement_error`` adds the marker's
  and the robot's. Each term is kept (``COVARIANCE_TERMS``, `term_stds`).
- **free motions** (`_free_motions`): the directions the scan does not pin down, in words
  (turns first, then slides along the {T} axes where they can be); the axes they move are
  not reported.
- **flags** (`_flags`, `_coverage_flags`, `_rival_words`): why not to act on a pose as it
  stands: a poor fit, large residuals, free motions, profiles too far apart, a partial scan,
  a rival that fits as well.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import bdtr

from scanner_core.pose.fine import _directions, _Fit
from scanner_core.pose.inputs import ScanPoseInputs
from scanner_core.pose.models import SurfaceModel

if TYPE_CHECKING:
    from scanner_core.pose.registration import PoseParams

_AXIS_LABELS = ("x_T", "y_T", "z_T")
# A free motion moves the axes whose component in its unit direction exceeds this.
_TOUCHED = 0.2
# A fit whose residuals exceed this many times the expected scatter is flagged.
_RMS_FLAG = 5.0
# A variance measured from few independent draws (the edges' shared offsets, `_shared_offsets`;
# the profiles' scatter along an axis few of them hold, `_profile_freedom`) is widened to
# Student's t's, nu / (nu - 2) times (`_t_variance_factor`); with this many degrees of freedom
# or fewer, this many times: the factor at nu = 3 (at 2 and below t has no variance).
_MIN_FREEDOM = 3
_FEW_FREEDOM_FACTOR = 3.0
# A face whose offset the fit takes up by more than this is not measured (`_face_offsets`):
# the fit holds a motion on it more than on all the others together, and what its rows
# show of its offset, given back, is mostly their noise.
_MAX_FACE_LEVERAGE = 0.5
# A cluster's leverage is capped at 1 minus this (`_leverage_corrected`).
_MIN_SLACK = 0.05
# A free motion's turn part (scaled, of a unit motion) below this is round-off: it slides.
_FREE_TURN = 1e-8

#: A flag that informs and does not stop a robot acting on the pose (``judge``).
EDGES_NOTE = "edges: "
#: A scan covering less of the part's length along the pass than this is partial.
MIN_COVERAGE = 0.9
#: Edge points matched fewer than a right pose's share (``PoseParams.good_edge_fraction``)
#: refute the pose only when a right pose would match so few this rarely (a binomial tail):
#: one unmatched edge point of a smooth part's scan tells nothing; the first significance
#: sends the fit to the coarse search, the second makes it a poor fit.
EDGES_SEARCH_SIGNIFICANCE, EDGES_POOR_SIGNIFICANCE = 0.05, 0.01


#: The terms of a pose's covariance, in the order ``PoseResult.std_terms`` lists them.
#: ``profiles``: the measurement noise through the fit, the points of a profile clustered (each
#: frame's placement error); ``few_profiles``: what that variance, measured from the scatter of
#: the few profiles that hold an axis, leaves open (Student's t, `_profile_freedom`); ``edges``:
#: the offsets the edge points along one model edge share, pooled over the scan's edges;
#: ``faces``: the offsets the surface points of one model face share across the profiles,
#: measured on each face the fit does not take up (`_face_offsets`); ``inflation``: what
#: ``PoseParams.sigma_inflation`` adds to the profiles' and the edges' terms; ``free``: the
#: slack of the motions the scan leaves free; ``rivals``: the other minima that fit as well;
#: ``light_plane``: the calibration's light plane, on which every profile was triangulated;
#: ``marker``: the calibration's marker offset; ``robot``: the robot's orientation report.
COVARIANCE_TERMS = ("profiles", "few_profiles", "edges", "faces", "inflation", "free", "rivals",
                    "light_plane", "marker", "robot")


def _uncertainty(fit: _Fit, params, rivals=(), sheet=None) -> tuple[np.ndarray, np.ndarray, list,
                                                                    dict]:
    """Covariance (cluster-robust over frames), per-axis std, the free axes and the
    covariance's terms (``COVARIANCE_TERMS`` but the marker's and the robot's, which
    ``pose_inputs.add_placement_error`` adds), about the {T} origin. Each rival minimum
    (``_probe_turns``) adds its difference's outer product: the scan cannot tell the fit from
    it, so the spread between them is uncertainty too. `sheet` (``(frames, table,
    covariance)`` of ``ScanPoseInputs``' ``sheet_*``, or None) adds the light plane's
    (`_sheet_response`)."""
    nan6 = np.full(6, np.nan)
    if len(fit.residuals) < 6:
        return np.full((6, 6), np.nan), nan6, [{"kind": "all", "axis": None,
                                                 "label": "too few matched points"}], {}
    s = np.array([1.0, 1.0, 1.0, fit.scale_mm, fit.scale_mm, fit.scale_mm])
    js = fit.jacobian / s
    values, vectors, strong = _directions(fit.jacobian, fit.weights, fit.frames, fit.scale_mm,
                                          params)
    info_inv = vectors[:, strong] @ np.diag(1.0 / values[strong]) @ vectors[:, strong].T
    by_profile, two_way = _two_way_meat(js, fit.weights, fit.residuals, fit.frames, fit.curves,
                                        info_inv)
    unscale = 1.0 / np.outer(s, s)
    profiles = info_inv @ by_profile @ info_inv * unscale
    sandwich = info_inv @ two_way @ info_inv * unscale
    # About the {T} origin: t_o = t_c + c x w.
    c = fit.centre
    cross = np.array([[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]], [-c[1], c[0], 0.0]])
    to_origin = np.eye(6)
    to_origin[:3, 3:] = cross
    terms = {"profiles": profiles, "edges": sandwich - profiles,
             "faces": info_inv @ _face_offsets(js, fit.weights, fit.residuals, fit.frames,
                                               fit.faces, info_inv) @ info_inv * unscale,
             "inflation": sandwich * (params.sigma_inflation**2 - 1.0),
             "free": _free_prior(vectors[:, ~strong], s, params)}
    if sheet is not None:
        response = _sheet_response(fit, js, info_inv, s, sheet[0], sheet[1])
        terms["light_plane"] = response @ sheet[2] @ response.T
    terms = {name: to_origin @ term @ to_origin.T for name, term in terms.items()}
    freedom = _profile_freedom(js * np.sqrt(fit.weights)[:, None], fit.frames, info_inv,
                               to_origin / s[None, :])
    spread = np.sqrt(_t_variance_factor(freedom) - 1.0)
    terms["few_profiles"] = terms["profiles"] * np.outer(spread, spread)
    terms["rivals"] = np.zeros((6, 6))
    for rival in rivals:
        m = _rival_motion(fit.pose, rival)
        terms["rivals"] = terms["rivals"] + np.outer(m, m)
    covariance = sum(terms.values())
    free_scaled = vectors[:, ~strong]
    free_axes = _free_motions(free_scaled, s, c)
    std = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    std[3:] = np.degrees(std[3:])
    if free_axes:
        # Along a free motion the scan says nothing: the axes it moves are not reported. A
        # free turn about an axis that misses the {T} origin carries the origin round with it:
        # those translation axes are not reported either.
        touched = np.zeros(6, bool)
        for axis in free_axes:
            direction = np.asarray(axis["axis"])
            if axis["kind"] == "translation":
                touched[:3] |= np.abs(direction) > _TOUCHED
                continue
            touched[3:] |= np.abs(direction) > _TOUCHED
            through = np.asarray(axis["through_mm"])
            swing = np.zeros(3)
            for angle in (np.pi / 2, np.pi, -np.pi / 2):
                turn = Rotation.from_rotvec(angle * direction).as_matrix()
                swing = np.maximum(swing, np.abs(turn @ -through + through))
            touched[:3] |= swing > 3.0 * np.nan_to_num(std[:3], nan=np.inf)
        std[touched] = np.nan
        for term in (covariance, *terms.values()):
            term[touched, :] = np.nan
            term[:, touched] = np.nan
    return covariance, std, free_axes, terms


def _sheet_response(fit: _Fit, js, info_inv, s, frames, table) -> np.ndarray:
    """(6, 3): how the fit's motion (mm, rad, about its centre) moves with the light plane's
    tilts and shift ``theta`` (``scanner_core.calibration.plane.PlaneUncertainty``).

    A point triangulated on the plane lies where its camera ray ``x = C + lambda u`` meets
    it; the plane moved by ``theta`` moves it along the ray by
    ``delta x = u (delta - alpha a_1 . (x - c) - beta a_2 . (x - c)) / (n . u)`` (to first
    order). Its row's residual moves by ``-J_t . delta x`` (``J_t`` the row's translation
    part: a residual moves with the point as against the model), and the Gauss-Newton step
    answers ``-H^+ sum_i w_i J_i delta r_i`` in the observable motions. `frames` (F,) and
    `table` ((F, 5, 3), ``pose_inputs.sheet_in_tcp``) give each row's plane and camera in
    {T}; a row whose frame is not listed does not move.
    """
    order = np.argsort(frames, kind="stable")
    slot = np.clip(np.searchsorted(frames[order], fit.frames), 0, len(frames) - 1)
    known = frames[order][slot] == fit.frames
    rows = table[order[slot]]                               # (K, 5, 3)
    normal, a1, a2, centre, camera = (rows[:, i] for i in range(5))
    ray = fit.points - camera
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    along = np.einsum("ki,ki->k", normal, ray)
    lever = fit.points - centre
    shift = np.column_stack([-np.einsum("ki,ki->k", a1, lever),
                             -np.einsum("ki,ki->k", a2, lever),
                             np.ones(len(lever))]) / along[:, None]
    moved = -np.einsum("ki,ki->k", fit.jacobian[:, :3], ray)[:, None] * shift    # (K, 3)
    moved[~known] = 0.0
    step = -info_inv @ (js.T @ (fit.weights[:, None] * moved))                 # scaled
    return step / s[:, None]


def term_stds(terms: dict) -> dict:
    """Per term of a pose's covariance (``COVARIANCE_TERMS``: (6, 6), mm and rad), the
    standard deviation it alone gives each axis (``tx_mm`` ... ``rz_deg``): the square root
    of its diagonal, signed as it (a term that took variance away would be negative), NaN
    along a free motion. The squares, signed, add up to the reported variances."""
    out = {}
    for name in COVARIANCE_TERMS:
        if name not in terms:
            continue
        diag = np.diag(terms[name]).copy()
        diag[3:] *= np.degrees(1.0) ** 2
        out[name] = np.sign(diag) * np.sqrt(np.abs(diag))
    return out


def _two_way_meat(js, weights, residuals, frames, curves, info_inv):
    """Two (6, 6) cluster-robust "meats" of the weighted scores: clustered by profile
    (`frames`, (K,)), each cluster's residuals corrected for its leverage
    (`_leverage_corrected`, the jackknife's approximation); and the same plus the offsets the
    edge rows of one model edge curve share (`curves`, (K,), -1 for a surface row:
    `_shared_offsets`, and what one edge's own residuals hold beyond them), which add to the
    profiles' scatter and never take from it. `js`
    ((K, 6)) are the rows in scaled units, `info_inv` ((6, 6)) the inverse of their
    information.

    The edge points along one edge share an error that their scatter does not show (a
    rounded edge, the stripe fading as the surface turns away), and a few edge points hold a
    flat part's slides and turn in its plane, so the fit takes up much of their residuals:
    both are measured in docs/pose.md ("What every edge shares").
    """
    root = np.sqrt(weights)
    x, e = js * root[:, None], residuals * root
    by_profile = _leverage_corrected(x, e, frames, info_inv)
    edge = curves >= 0
    if not edge.any():
        return by_profile, by_profile
    shared = _shared_offsets(x[edge], e[edge], weights[edge], curves[edge], info_inv)
    # The pooled variance spreads one edge's offset over all of them: an edge far out of the
    # others' spread (matched to the CAD's wrong edge, say) shows in its own residuals. What
    # the edge rows clustered by edge (CR3) hold beyond the same rows by profile and the
    # pooled term is added where it exceeds them.
    by_curve = _leverage_corrected(x[edge], e[edge], curves[edge], info_inv)
    by_frame = _leverage_corrected(x[edge], e[edge], frames[edge], info_inv)
    return by_profile, by_profile + shared + _positive_part(by_curve - by_frame - shared)


def _profile_freedom(x, frames, info_inv, readout) -> np.ndarray:
    """(A,): the degrees of freedom of each reported axis's profile-clustered variance (the
    CR3 sandwich of `_two_way_meat` clustered by `frames`, (K,)), Satterthwaite's ``nu = (tr
    G)^2 / tr G^2`` under the working model of independent rows of equal variance (Bell and
    McCaffrey 2002).

    An axis's variance is ``sum_g u_g^2``, ``u_g = l^T X_g^T A_g e_g`` over the profiles g,
    ``l = H^-1 R^T a`` its contrast (`readout` R, (A, 6), maps the scaled motion to the
    reported axes), ``A_g = (I - H_gg)^-1``. With ``e = M eps``, ``M = I - X H^-1 X^T``, the
    ``u_g`` are correlated normals, ``Cov(u_g, u_h) = G_gh = a_g^T M_gh a_h``, ``a_g = A_g X_g
    l = X_g m_g``, ``m_g = (I - H^-1 B_g)^-1 l`` (``B_g = X_g^T X_g``; push-through), so
    ``G = diag(m_g^T B_g m_g) - b H^-1 b^T``, ``b_g = B_g m_g``: all in the motion's six
    dimensions. An axis that few profiles hold (the turn about the pass's axis on a small
    part, seen at its two ends) has few degrees of freedom however many profiles the scan
    has, and its variance, measured from their scatter, is as uncertain as a variance from as
    many draws. `x` ((K, 6)) are the weighted rows in scaled units, `info_inv` ((6, 6)) the
    inverse of their information; leverages capped as in `_leave_out_moves`.
    """
    _, inverse = np.unique(frames, return_inverse=True)
    _, _, gram = _cluster_grams(x, inverse.reshape(-1))                        # B_g
    root, basis, slack = _leverage_basis(gram, info_inv)
    contrasts = info_inv @ readout.T                                          # (6, A): l
    # (I - H^-1 B)^-1 l = l + L U diag(1 / slack) U^T L^T B l
    along = np.einsum("gji,jk,gka->gia", basis, root.T, gram @ contrasts) / slack[:, :, None]
    m = contrasts[None] + np.einsum("ij,gjk,gka->gia", root, basis, along)   # (G, 6, A)
    b = gram @ m
    own = np.einsum("gia,gia->ga", m, b)                                      # m_g^T B_g m_g
    spread = b.transpose(2, 0, 1) @ info_inv                                  # (A, G, 6)
    cross = np.einsum("agi,gia->ga", spread, b)                               # b_g^T H^-1 b_g
    gram_b = np.einsum("gia,gja->aij", b, b)                                  # sum_g b_g b_g^T
    both = info_inv[None] @ gram_b
    trace = own.sum(axis=0) - np.einsum("aii->a", both)
    square = (np.sum(own**2, axis=0) - 2.0 * np.sum(own * cross, axis=0)
              + np.einsum("aij,aji->a", both, both))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(square > 0.0, trace**2 / square, np.inf)


def _t_variance_factor(freedom) -> np.ndarray:
    """Student's t's variance over its scale's, ``nu / (nu - 2)``, for `freedom` nu (any
    shape); ``_FEW_FREEDOM_FACTOR`` at ``_MIN_FREEDOM`` or fewer (at 2 and below it has
    none); 1 where nu is infinite."""
    nu = np.asarray(freedom, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        factor = np.where(nu > _MIN_FREEDOM, nu / (nu - 2.0), _FEW_FREEDOM_FACTOR)
    return np.where(np.isinf(nu), 1.0, factor)


def _face_offsets(js, weights, residuals, frames, faces, info_inv) -> np.ndarray:
    """(6, 6) "meat" of the offsets the surface rows of one model face share across profiles
    (`faces`, (K,), -1 for a row of no face): a face off by ``o_c`` along its normal as a
    whole (a chamfer the exposure's blur smears, a face the sensor sees at a slant) pulls the
    motion by ``o_c g_c``, ``g_c = sum_{i in c} w_i J_i``, which the profiles' clusters take
    as independent draws frame by frame: ``sum_f g_cf g_cf^T`` where the face's offset gives
    ``g_c g_c^T``. What is added is the difference, ``o_c^2 (g_c g_c^T - sum_f g_cf
    g_cf^T)``, summed over the faces and its negative eigenvalues dropped.

    ``o_c^2`` is measured on each face: the weighted mean ``m_c`` of its rows' residuals,
    each given back what the fit took up of the face's (`_cluster_residuals`), less the
    mean's own variance over the face's profiles (cluster-robust, ``F_c / (F_c - 1) sum_f
    (sum_{i in c, f} w_i (r_i - m_c))^2 / (sum_{i in c} w_i)^2``): ``m_c^2 - v_c``. It is
    not unbiased: the given-back mean also carries the error of the fit without the face,
    which ``v_c`` leaves out (a face with no offset reads a little), and ``v_c`` counts the
    profiles' own placement errors, which the other faces take up from ``m_c`` (an offset
    reads a little small); docs/place.md gives their size. Only faces seen in two profiles
    or more whose offset the fit takes up by at most half
    (``h_c = g_c^T H^-1 g_c / sum_{i in c} w_i``, at most ``_MAX_FACE_LEVERAGE``): a face
    that holds a motion alone (the top face, the height) reads as no offset whatever it is,
    the same as the profiles' own clusters see it. `js` ((K, 6)) are the rows in scaled units, `info_inv` ((6, 6)) the
    inverse of their information."""
    dims = js.shape[1]
    on_face = faces >= 0
    if not on_face.any():
        return np.zeros((dims, dims))
    x = js[on_face] * weights[on_face, None]          # w_i J_i
    w, r = weights[on_face], residuals[on_face]
    root = np.sqrt(w)
    _, face = np.unique(faces[on_face], return_inverse=True)
    face = face.reshape(-1)
    given_back = _cluster_residuals(js[on_face] * root[:, None], r * root, face, info_inv) / root
    count = face.max() + 1
    mass = np.bincount(face, weights=w, minlength=count)
    mean = np.bincount(face, weights=w * given_back, minlength=count) / mass
    pull = _sums(face, x, count)
    leverage = np.einsum("gi,ij,gj->g", pull, info_inv, pull) / mass
    # per face and profile: the spread of the mean and the pulls frame by frame
    profile = frames[on_face] - frames[on_face].min()
    _, cell = np.unique(face * (profile.max() + 1) + profile, return_inverse=True)
    cell = cell.reshape(-1)
    cell_face = np.zeros(cell.max() + 1, np.int64)
    cell_face[cell] = face
    spread = np.bincount(cell, weights=w * (given_back - mean[face]))
    profiles = np.bincount(cell_face, minlength=count)
    variance = np.bincount(cell_face, weights=spread**2, minlength=count) / mass**2
    variance *= profiles / np.maximum(profiles - 1, 1)
    cell_pull = _sums(cell, x, len(cell_face))
    within = _sums(cell_face, np.einsum("ci,cj->cij", cell_pull, cell_pull).reshape(-1, dims**2),
                   count).reshape(count, dims, dims)
    offset2 = np.where((profiles >= 2) & (leverage <= _MAX_FACE_LEVERAGE),
                       mean**2 - variance, 0.0)
    meat = np.einsum("c,cij->ij", offset2, pull[:, :, None] * pull[:, None, :] - within)
    return _positive_part(meat)


def _sums(group, values, count) -> np.ndarray:
    """(count, D): the rows of `values` ((K, D)) summed by `group` ((K,) in 0..count-1)."""
    return np.stack([np.bincount(group, weights=column, minlength=count)
                     for column in values.T], axis=1)


def _positive_part(matrix) -> np.ndarray:
    """The symmetric `matrix` with its negative eigenvalues set to 0."""
    values, vectors = np.linalg.eigh((matrix + matrix.T) / 2.0)
    return (vectors * np.clip(values, 0.0, None)) @ vectors.T


def _shared_offsets(x, e, weights, curves, info_inv) -> np.ndarray:
    """(6, 6) "meat" of the offsets the edge rows of one model edge curve share: each curve
    c off by its own ``o_c``, drawn with one variance ``tau^2`` for the scan, gives
    ``tau^2 sum_c g_c g_c^T``, ``g_c = sum_{i in c} w_i J_i`` the curve's pull on the motion.

    ``tau^2`` is pooled over the curves of two or more rows (a random-effects model, method
    of moments): the mean of ``m_c^2 - s_c^2 / n_c``, ``m_c`` the mean of curve c's residuals
    corrected for what the fit took up of them (`_cluster_residuals`), ``s_c^2`` their
    scatter about it; zero when the curves agree within their scatter. Pooled, the variance
    rests on every curve at once, not on each curve's own residuals, which a part of few
    edges makes a poor estimate. It rests on ``nu = sum_c (1 - h_c)`` degrees of freedom, ``h_c`` the leverage of curve c's
    offset in the fit: an error over few of them spreads as Student's t, whose variance is
    ``nu / (nu - 2)`` of its scale's (``_FEW_FREEDOM_FACTOR`` for ``nu`` up to
    ``_MIN_FREEDOM``). `x` ((K, 6)) and `e` ((K,)) are the weighted rows and residuals,
    `weights` (K,) the rows' weights.
    """
    _, inverse, sizes = np.unique(curves, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    root = np.sqrt(weights)
    corrected = _cluster_residuals(x, e, inverse, info_inv) / root
    pull = _sums(inverse, x * root[:, None], len(sizes))
    total = np.bincount(inverse, weights=corrected, minlength=len(sizes))
    squares = np.bincount(inverse, weights=corrected**2, minlength=len(sizes))
    many = sizes >= 2
    if not many.any():
        return np.zeros((x.shape[1], x.shape[1]))
    mean = total[many] / sizes[many]
    scatter = (squares[many] - sizes[many] * mean**2) / (sizes[many] - 1)
    tau2 = max(0.0, float(np.mean(mean**2 - scatter / sizes[many])))
    mass = np.bincount(inverse, weights=weights, minlength=len(sizes))
    leverage = np.einsum("gi,ij,gj->g", pull, info_inv, pull) / mass
    freedom = float(np.sum(1.0 - np.clip(leverage[many], 0.0, 1.0)))
    tau2 *= float(_t_variance_factor(freedom))
    return tau2 * pull.T @ pull


def _cluster_residuals(x, e, inverse, info_inv) -> np.ndarray:
    """(K,): each row's residual with what the fit took up of its cluster's given back,
    ``(I - H_gg)^-1 e_g`` per cluster g (`inverse`, (K,) cluster index, sorted or not), its
    leverages capped at 1 - ``_MIN_SLACK`` (`_leave_out_moves`)."""
    order, starts, moves, _ = _leave_out_moves(x, e, inverse, info_inv)
    cluster = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(e)]))
    out = np.empty_like(e)
    out[order] = e[order] + np.einsum("ki,ki->k", x[order], moves[cluster])
    return out


def _leverage_corrected(x, e, keys, info_inv) -> np.ndarray:
    """(6, 6): ``sum_g X_g^T A_g e_g e_g^T A_g X_g`` over the clusters g (rows of `keys`
    alike) of the weighted rows `x` ((K, 6)) and residuals `e` ((K,)), with ``A_g = (I -
    H_gg)^-1``, ``H_gg = X_g info_inv X_g^T`` (Bell and McCaffrey 2002's CR3, the jackknife's
    approximation): a cluster whose residuals the fit took up is scaled back up. A leverage
    near 1 (one cluster alone holding a motion) is capped at 1 - ``_MIN_SLACK``
    (`_leave_out_moves`)."""
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    _, _, moves, (scores, gram) = _leave_out_moves(x, e, inverse.reshape(-1), info_inv)
    corrected = scores + np.einsum("gij,gj->gi", gram, moves)
    return corrected.T @ corrected


def _leave_out_moves(x, e, inverse, info_inv):
    """Per cluster g of the rows (`inverse`, (K,) cluster index), ``v_g = L (I - L^T B_g
    L)^-1 L^T s_g`` (6,): with ``s_g = X_g^T e_g``, ``B_g = X_g^T X_g`` and ``L L^T =
    info_inv``, ``(I - H_gg)^-1 e_g = e_g + X_g v_g`` (Woodbury), computed in the motion's six
    dimensions whatever the cluster's size. The eigenvalues of ``L^T B_g L`` are the
    cluster's leverages, capped at 1 - ``_MIN_SLACK``.

    Returns the rows' order by cluster, each cluster's first row in it, the (G, 6) moves and
    the (G, 6) scores ``s_g`` with the (G, 6, 6) ``B_g``.
    """
    order, starts, gram = _cluster_grams(x, inverse)
    scores = np.add.reduceat(x[order] * e[order, None], starts, axis=0)
    root, basis, slack = _leverage_basis(gram, info_inv)
    along = np.einsum("gji,gj->gi", basis, scores @ root) / slack
    moves = np.einsum("gij,gj->gi", basis, along) @ root.T
    return order, starts, moves, (scores, gram)


def _cluster_grams(x, inverse):
    """The rows' order by cluster (`inverse`, (K,) cluster index), each cluster's first row
    in it, and the (G, 6, 6) ``B_g = X_g^T X_g`` of the rows `x` ((K, 6))."""
    order = np.argsort(inverse, kind="stable")
    starts = np.r_[0, np.nonzero(np.diff(inverse[order]))[0] + 1]
    xs = x[order]
    return order, starts, np.add.reduceat(xs[:, :, None] * xs[:, None, :], starts, axis=0)


def _leverage_basis(gram, info_inv):
    """``L`` ((6, 6), ``L L^T = info_inv``), and per cluster the eigenvectors ``U_g`` ((G, 6,
    6)) of ``L^T B_g L`` (`gram`) and one minus its eigenvalues, the cluster's leverages,
    capped below at ``_MIN_SLACK`` ((G, 6))."""
    values, vectors = np.linalg.eigh(info_inv)
    root = vectors * np.sqrt(np.clip(values, 0.0, None))
    leverages, basis = np.linalg.eigh(root.T @ gram @ root)
    return root, basis, np.maximum(1.0 - leverages, _MIN_SLACK)


def _free_prior(free_scaled, s, params) -> np.ndarray:
    """(6, 6) covariance (mm, rad, about the fit's centre) of the motions the scan leaves
    free: along each, the pose keeps its start, so its error is the misplacement along it,
    bounded only by what a pick can leave (``PoseParams.prior_mm``, ``prior_deg``).

    A free slide along a prism's length tilted 0.5 degrees from y_T moves x_T by 9 um per mm
    it slides: an L-block 5 mm off along its free axis, came out 44 um off in
    x_T and 26 um in z_T with sigmas of 3 and 0.5 um. With this prior those axes' sigmas are
    87 and 52 um: they bound their errors, and the pose is not acted on.
    """
    covariance = np.zeros((6, 6))
    for v in free_scaled.T:
        motion = v / s
        turn, slide = np.linalg.norm(motion[3:]), np.linalg.norm(motion[:3])
        size = (np.radians(params.prior_deg) / turn if turn * s[3] > slide
                else params.prior_mm / max(slide, 1e-12))
        covariance += size**2 * np.outer(motion, motion)
    return covariance


def _free_motions(free_scaled, s, centre) -> list[dict]:
    """The free motions (orthonormal columns of `free_scaled`, scaled parameters) in words,
    turns first, then slides along the {T} axes where they can be: a free subspace that
    holds a turn and a slide can come out of the eigen-decomposition as two mixed motions
    (ADIS16480 with y_T and its turn free read "about z_T, about z_T")."""
    k = free_scaled.shape[1]
    if k > 1:
        _, sv, vt = np.linalg.svd(free_scaled[3:])  # singular values in descending order
        rank = int(np.sum(sv > _FREE_TURN))  # unit columns: an absolute floor
        basis = free_scaled @ vt.T  # the first `rank` turn; the rest only slide
        basis[3:, rank:] = 0.0
        if k - rank > 1:
            basis[:3, rank:] = _axis_aligned(basis[:3, rank:])
        free_scaled = basis
    return [_describe(v / np.linalg.norm(v), s, centre) for v in free_scaled.T]


def _axis_aligned(slides) -> np.ndarray:
    """An orthonormal basis of the span of `slides` ((3, m), orthonormal columns) whose
    vectors lie as close to the {T} axes as the span allows, nearest first."""
    projector = slides @ slides.T
    out = []
    for _ in range(slides.shape[1]):
        candidates = projector - sum((np.outer(b, b) for b in out), np.zeros((3, 3)))
        axis = int(np.argmax(np.linalg.norm(candidates, axis=0)))
        vector = candidates[:, axis]
        out.append(vector / np.linalg.norm(vector))
    return np.column_stack(out)


def _describe(vector_scaled, s, centre) -> dict:
    """A free motion (unit vector in scaled parameters) in words."""
    motion = vector_scaled / s
    t, w = motion[:3], motion[3:]
    if np.linalg.norm(w) * s[3] > np.linalg.norm(t):
        axis = w / np.linalg.norm(w)
        kind = "rotation"
        # The rotation's axis passes through the point where the motion leaves no translation.
        through = centre + np.cross(axis, t) / np.linalg.norm(w)
    else:
        axis = t / np.linalg.norm(t)
        kind = "translation"
        through = None
    axis = axis * np.sign(axis[np.argmax(np.abs(axis))])
    main = int(np.argmax(np.abs(axis)))
    label = (f"{'about' if kind == 'rotation' else 'along'} {_AXIS_LABELS[main]}"
             if abs(axis[main]) > 0.9 else f"{kind} {np.round(axis, 3).tolist()}")
    entry = {"kind": kind, "axis": np.round(axis, 6).tolist(), "label": label}
    if through is not None:
        entry["through_mm"] = np.round(through, 3).tolist()
    return entry


def _rival_motion(pose, rival) -> np.ndarray:
    """(6,): the rival's difference from `pose` as translation of the {T} origin (mm) and
    rotation vector (rad), the covariance's parameters."""
    d = rival @ np.linalg.inv(pose)
    return np.concatenate([d[:3, 3], Rotation.from_matrix(d[:3, :3]).as_rotvec()])


def _rival_words(pose, rival) -> str:
    m = _rival_motion(pose, rival)
    return (f"a pose {np.degrees(np.linalg.norm(m[3:])) * 1e3:.0f} mdeg and "
            f"{np.linalg.norm(m[:3]) * 1e3:.0f} um away")


def edges_refute(fraction: float, count: int, share: float, significance: float) -> bool:
    """Whether `count` edge points of which `fraction` matched the model refute a pose
    whose right share is `share`: fewer matched than that, and a right pose matching so few
    or fewer has a probability below `significance` (the binomial's lower tail,
    ``P(X <= k) = sum_{i<=k} C(n, i) share^i (1 - share)^(n - i)``)."""
    if count == 0 or fraction >= share:
        return False
    matched = int(round(fraction * count))
    return bool(bdtr(matched, count, share) < significance)


def _flags(fit: _Fit, free_axes, edge_count: int, params: PoseParams) -> list[str]:
    flags = []
    if fit.inlier_fraction < params.good_inlier_fraction:
        flags.append(f"poor fit: {fit.inlier_fraction:.0%} of the points match the model")
    poor = (fit.edge_fraction < params.act_edge_fraction
            and edges_refute(fit.edge_fraction, edge_count, params.good_edge_fraction,
                             EDGES_POOR_SIGNIFICANCE))
    if poor:
        flags.append(f"poor fit: {fit.edge_fraction:.0%} of the {edge_count} edge points match "
                     "the model's edges")
    elif edge_count and fit.edge_fraction < params.good_edge_fraction:
        flags.append(f"{EDGES_NOTE}{fit.edge_fraction:.0%} of the {edge_count} edge points "
                     "match the model's edges")
    if fit.rms > _RMS_FLAG * params.surface_noise_mm:
        flags.append(f"large residuals: {fit.rms * 1e3:.0f} um RMS")
    if free_axes:
        flags.append("not observable: " + ", ".join(a["label"] for a in free_axes))
    return flags


def _coverage_flags(inputs: ScanPoseInputs, pose, surface_model: SurfaceModel) -> list[str]:
    """Flags a pose cannot raise from its fit alone: profiles too far apart, and a pass that
    saw only part of the part: it began or ended with the part in the sheet (the trigger came
    late, the pass stopped early: ``ScanPoseInputs.in_sheet_at``) and covers less than
    ``MIN_COVERAGE`` of the length the part's downward faces span along the pass. Faces the
    camera cannot see from any frame of a whole pass leave its coverage short as well, and
    say nothing against the pose."""
    flags = [] if inputs.sparse is None else [inputs.sparse]
    began, ended = inputs.in_sheet_at
    if not (began or ended):
        return flags
    normals_t = surface_model.normals @ pose[:3, :3].T
    facing = normals_t[:, 2] > 0.3  # the sensor looks up at the part along -z_T
    if facing.any():
        along = (surface_model.points[facing] @ pose[:3, :3].T + pose[:3, 3])[:, 1]
        seen = inputs.cloud[:, 1]
        length = float(along.max() - along.min())
        overlap = min(along.max(), seen.max()) - max(along.min(), seen.min())
        coverage = max(0.0, float(overlap)) / length if length > 0 else 1.0
        if coverage < MIN_COVERAGE:
            when = " and ".join(w for w, cut in (("began", began), ("ended", ended)) if cut)
            flags.append(f"partial scan: {coverage:.0%} of the part's length along the pass "
                         f"(the pass {when} with the part in the sheet)")
    return flags


_AXIS_WORDS = ("tx", "ty", "tz", "rx", "ry", "rz")


def judge(result, model: SurfaceModel | None, params: PoseParams) -> None:
    """The verdict a robot acts on, set on `result` (a ``PoseResult``): ``observable``,
    ``act``, ``act_reasons`` and ``symmetry``.

    Observable: no free motion, every axis's 3 sigma within the act tolerance
    (``PoseParams.act_tolerance_mm`` for translations of the {T} origin,
    ``act_tolerance_deg`` for rotations), and no rival minimum beyond it that fits as well.
    Act: observable, and no other flag (a poor fit, large residuals, profiles too sparse, a
    partial scan, an implausible turn). A rotation left loose (free, beyond the tolerance, or
    with a rival beyond it) has its near symmetry named (``scanner_core.pose.symmetry``).

    The tolerance bounds 3 sigma, not 1: a pose acted on then lands within the tolerance
    unless its error exceeds 3 of its sigmas, which ``flyscan bench pose`` and ``flyscan
    bench place`` count (never, over their trials, on the reference parts).
    """
    from scanner_core.pose.symmetry import name_symmetry

    tolerance = np.array([params.act_tolerance_mm] * 3 + [params.act_tolerance_deg] * 3)
    reasons = []
    if result.free_axes:
        reasons.append("not observable: " + ", ".join(a["label"] for a in result.free_axes))
    loose = [i for i in range(6)
             if np.isfinite(result.std[i]) and 3.0 * result.std[i] > tolerance[i]]
    for i in loose:
        unit = "mm" if i < 3 else "degrees"
        reasons.append(f"{_AXIS_WORDS[i]}: 3 sigma {3.0 * result.std[i]:.3g} {unit}, beyond the "
                       f"act tolerance {tolerance[i]:g} {unit}")
    far = []
    for rival in result.rivals:
        m = _rival_motion(result.matrix, rival)
        if (np.linalg.norm(m[:3]) > params.act_tolerance_mm
                or np.degrees(np.linalg.norm(m[3:])) > params.act_tolerance_deg):
            far.append(rival)
    if far:
        reasons.append(f"ambiguous: {len(far)} other minim{'um' if len(far) == 1 else 'a'} "
                       "beyond the act tolerance fit the scan as well ("
                       + "; ".join(_rival_words(result.matrix, r) for r in far[:4])
                       + ("; ..." if len(far) > 4 else "") + ")")
    result.symmetry = None
    if model is not None and (far or any(i >= 3 for i in loose)
                              or any(a["kind"] == "rotation" for a in result.free_axes)):
        result.symmetry = name_symmetry(result.matrix, result.covariance, far,
                                        result.free_axes, model, params)
        if result.symmetry is not None:
            reasons.insert(0, "near symmetry: " + result.symmetry["label"])
    result.observable = not (result.free_axes or loose or far)
    others = [f for f in result.flags
              if not f.startswith(("not observable: ", "ambiguous: ", EDGES_NOTE))]
    result.act_reasons = reasons + others
    result.act = result.observable and not others
