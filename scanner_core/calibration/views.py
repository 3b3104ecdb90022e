"""The three views from the LED marker at known stage positions (paper section II-A, Eq. 1).

The stage (or robot) moves the LED to many known positions in {B}; its centroid is found in
the direct view and in each mirror view. A model per view mapping {B} to the image is fitted by
least squares, from a ladder of models:

- ``affine``: the paper's Eq. (1) taken literally, pixels an affine function of the position
  (``[u, v] = A [P, 1]``, 8 numbers, linear least squares "in matrix form");
- ``projective``: a pinhole projection, ``[u, v, 1] ~ P [P, 1]`` (DLT, 11 numbers, Hartley's
  normalised DLT refined on the reprojection error);
- ``pinhole+distortion``: one physical camera for all views (intrinsics, the lens's radial and
  tangential distortion, its pose in {B}), each mirror view the same camera looking at the
  scene reflected in its mirror plane; fitted jointly (bundle adjustment from the DLTs).

Each view keeps the simplest model whose reprojection error on held-out positions is not worse
than the next model's by more than ``SELECTION_MARGIN`` (model no more than the scene needs),
and all of them are reported. The scanner's geometry (``Calibration``) is the physical model:
with distortion when any view needs it, else the same camera with an ideal lens.

References
----------
.. [1] "Fast visual part inspection for bin picking", section II-A.
.. [2] R. Hartley and A. Zisserman, "Multiple View Geometry", 2nd ed., algorithm 7.1 (DLT).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scanner_core.geometry import (NO_DISTORTION, Mirror, PinholeCamera, Plane, apply_transform,
                                   reflection_matrix, unit)

MODELS = ("affine", "projective", "pinhole+distortion")
#: A richer model is kept only when it lowers the held-out error by more than this share, and
#: by more than SELECTION_MARGIN_PX.
SELECTION_MARGIN = 0.05
SELECTION_MARGIN_PX = 0.002
#: Share of the positions held out to choose between the models.
HOLDOUT_FRACTION = 0.25
#: Fewest positions a view needs (the DLT has 11 unknowns; the margin is for the hold-out).
MIN_POSITIONS = 16
#: The positions must span a volume: the smallest principal spread, mm, below which they lie on
#: a plane or a line and the projection is not determined.
MIN_SPREAD_MM = 1.0
#: Robust loss scale of the joint fit, px (observations farther off count less: a wrong blob).
ROBUST_SCALE_PX = 0.5
#: Observations off by more than this many robust sigmas after the fit are dropped, and the fit
#: repeated once.
OUTLIER_SIGMAS = 5.0


class ViewCalibrationError(ValueError):
    """The observations cannot determine the views (too few, degenerate or inconsistent)."""


@dataclass(frozen=True)
class ViewReport:
    """How each model of the ladder did on one view."""

    view: str
    observations: int
    train_rms_px: dict
    heldout_rms_px: dict
    chosen: str

    def to_dict(self) -> dict:
        return {"view": self.view, "observations": self.observations,
                "train_rms_px": self.train_rms_px, "heldout_rms_px": self.heldout_rms_px,
                "chosen": self.chosen}


@dataclass(frozen=True)
class ViewCalibration:
    """The fitted views: the physical camera and mirror planes, and the ladder's report."""

    camera: PinholeCamera
    mirror_planes: tuple[Plane, ...]
    reports: tuple[ViewReport, ...]
    model: str
    rms_px: float
    outliers: int = 0
    per_view_rms_px: list = field(default_factory=list)


# ---------------------------------------------------------------------------------------------
# the affine and projective models, per view


def fit_affine(points_b, pixels) -> np.ndarray:
    """Eq. (1) as an affine map: the (2, 4) matrix A with ``[u, v] = A [P, 1]``, by linear least
    squares. points_b (N, 3) mm, pixels (N, 2) px."""
    p = np.asarray(points_b, dtype=np.float64)
    a = np.column_stack([p, np.ones(len(p))])
    sol, *_ = np.linalg.lstsq(a, np.asarray(pixels, dtype=np.float64), rcond=None)
    return sol.T


def project_affine(matrix, points_b) -> np.ndarray:
    p = np.asarray(points_b, dtype=np.float64)
    return p @ matrix[:, :3].T + matrix[:, 3]


def _normaliser(x: np.ndarray) -> np.ndarray:
    """Hartley's similarity: centroid to the origin, mean distance sqrt(dim)."""
    dim = x.shape[1]
    centre = x.mean(axis=0)
    scale = np.sqrt(dim) / np.mean(np.linalg.norm(x - centre, axis=1))
    t = np.eye(dim + 1)
    t[:dim, :dim] *= scale
    t[:dim, dim] = -scale * centre
    return t


def fit_dlt(points_b, pixels, *, refine: bool = True) -> np.ndarray:
    """A pinhole projection, the (3, 4) matrix P with ``[u, v, 1] ~ P [X, 1]`` ([2]_, normalised
    DLT), refined by least squares on the reprojection error."""
    x = np.asarray(points_b, dtype=np.float64)
    u = np.asarray(pixels, dtype=np.float64)
    tx, tu = _normaliser(x), _normaliser(u)
    xn = np.column_stack([x, np.ones(len(x))]) @ tx.T
    un = np.column_stack([u, np.ones(len(u))]) @ tu.T
    rows = []
    for X, (a, b, _) in zip(xn, un):
        rows.append(np.concatenate([np.zeros(4), -X, b * X]))
        rows.append(np.concatenate([X, np.zeros(4), -a * X]))
    _, _, vt = np.linalg.svd(np.array(rows))
    p = np.linalg.inv(tu) @ vt[-1].reshape(3, 4) @ tx
    p /= np.linalg.norm(p[2, :3])
    if (p[2, :3] @ x.mean(axis=0) + p[2, 3]) < 0:
        p = -p  # the points in front of the camera: positive depth
    if refine:
        from scipy.optimize import least_squares

        sol = least_squares(lambda q: (project_dlt(q.reshape(3, 4), x) - u).ravel(), p.ravel(),
                            method="lm")
        p = sol.x.reshape(3, 4)
        p /= np.linalg.norm(p[2, :3]) * np.sign(p[2, :3] @ x.mean(axis=0) + p[2, 3])
    return p


def project_dlt(matrix, points_b) -> np.ndarray:
    p = np.asarray(points_b, dtype=np.float64)
    h = p @ matrix[:, :3].T + matrix[:, 3]
    return h[:, :2] / h[:, 2:3]


def decompose_dlt(matrix) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K (3, 3, K[2,2] = 1), R (3, 3) and the centre C (3,) of ``P ~ K R [I | -C]``; R may be
    improper (a mirror view). ``P``'s sign must give the scene a positive depth (``fit_dlt``
    returns it so)."""
    import scipy.linalg

    m = matrix[:, :3]
    centre = -np.linalg.solve(m, matrix[:, 3])
    k, r = scipy.linalg.rq(m)
    signs = np.diag(np.sign(np.diag(k)))  # positive focal lengths
    k, r = k @ signs, signs @ r
    return k / k[2, 2], r, centre


# ---------------------------------------------------------------------------------------------
# the physical model, all views at once


def _unpack(x: np.ndarray, n_mirrors: int, distortion: bool, template: PinholeCamera):
    from scipy.spatial.transform import Rotation

    fx, fy, cx, cy = x[:4]
    i = 4
    dist = tuple(x[i:i + 5]) if distortion else NO_DISTORTION
    i += 5 if distortion else 0
    rotation = Rotation.from_rotvec(x[i:i + 3]).as_matrix()
    origin = x[i + 3:i + 6]
    i += 6
    camera = PinholeCamera(fx, fy, cx, cy, template.width, template.height, rotation, origin,
                           tuple(float(v) for v in dist))
    planes = []
    for _ in range(n_mirrors):
        theta, phi, d = x[i:i + 3]
        n = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
        planes.append(Plane(n, float(d)))
        i += 3
    return camera, planes


def _pack(camera: PinholeCamera, planes, distortion: bool) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    parts = [[camera.fx, camera.fy, camera.cx, camera.cy]]
    if distortion:
        parts.append(list(camera.distortion))
    parts.append(Rotation.from_matrix(camera.rotation).as_rotvec())
    parts.append(camera.origin)
    for plane in planes:
        n = plane.normal
        parts.append([np.arctan2(np.hypot(n[0], n[1]), n[2]), np.arctan2(n[1], n[0]), plane.offset])
    return np.concatenate([np.asarray(p, dtype=np.float64) for p in parts])


def project_views(camera: PinholeCamera, planes, points_b) -> np.ndarray:
    """(N, 1 + M, 2) pixels of {B} points in the direct view and each mirror's view."""
    p = np.asarray(points_b, dtype=np.float64)
    views = [camera.project(p)] + [camera.project(apply_transform(
        reflection_matrix(pl.normal, pl.offset), p)) for pl in planes]
    return np.stack(views, axis=1)


def _initial_physical(points_b, pixels, width, height) -> tuple[PinholeCamera, list[Plane]]:
    """The camera from the direct view's DLT, each mirror from its view's DLT (a reflected
    camera: ``P_m ~ K R H``, H the mirror's reflection)."""
    seen = np.isfinite(pixels[:, 0, 0])
    k, r, centre = decompose_dlt(fit_dlt(points_b[seen], pixels[seen, 0]))
    if np.linalg.det(r) < 0:
        raise ViewCalibrationError("the direct view's projection looks mirrored: are the view "
                                   "strips in the right order?")
    camera = PinholeCamera(k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height, r, centre)
    planes = []
    for v in range(1, pixels.shape[1]):
        seen = np.isfinite(pixels[:, v, 0])
        pm = fit_dlt(points_b[seen], pixels[seen, v])
        m = np.linalg.inv(camera.matrix) @ pm
        h3 = r.T @ m[:, :3]
        scale = -np.cbrt(np.linalg.det(h3))  # a reflection has determinant -1
        h3, t = h3 / scale, m[:, 3] / scale
        w, vecs = np.linalg.eigh(0.5 * (np.eye(3) - 0.5 * (h3 + h3.T)))
        n = vecs[:, np.argmax(w)]
        h = r.T @ t + centre  # the reflection's translation, 2 d n
        planes.append(Plane(n, float(n @ h / 2.0)))
    return camera, planes


def fit_physical(points_b, pixels, width: int, height: int, *, distortion: bool,
                 initial: tuple | None = None) -> tuple[PinholeCamera, list[Plane], np.ndarray]:
    """The joint camera and mirror model by robust least squares on all views' reprojection.

    Returns the camera, the mirror planes and a (N, V) bool mask of the observations kept.
    """
    from scipy.optimize import least_squares

    points_b = np.asarray(points_b, dtype=np.float64)
    pixels = np.asarray(pixels, dtype=np.float64)
    camera, planes = initial if initial is not None else _initial_physical(
        points_b, pixels, width, height)
    if distortion and not camera.distorted:
        camera = PinholeCamera(camera.fx, camera.fy, camera.cx, camera.cy, width, height,
                               camera.rotation, camera.origin, NO_DISTORTION)
    use = np.isfinite(pixels[..., 0])
    n_mirrors = pixels.shape[1] - 1

    def residual(x):
        cam, pls = _unpack(x, n_mirrors, distortion, camera)
        return (project_views(cam, pls, points_b) - pixels)[use].ravel()

    x0 = _pack(camera, planes, distortion)
    for _ in range(2):
        sol = least_squares(residual, x0, loss="soft_l1", f_scale=ROBUST_SCALE_PX, x_scale="jac")
        err = np.linalg.norm((project_views(*_unpack(sol.x, n_mirrors, distortion, camera),
                                            points_b) - pixels), axis=2)
        sigma = 1.4826 * np.median(err[use]) + 1e-9
        keep = use & (err < OUTLIER_SIGMAS * max(sigma, 0.01))
        if keep.sum() == use.sum():
            break
        use, x0 = keep, sol.x
    cam, pls = _unpack(sol.x, n_mirrors, distortion, camera)
    return cam, pls, use


# ---------------------------------------------------------------------------------------------
# the ladder


def _rms(err: np.ndarray) -> float:
    err = err[np.isfinite(err).all(axis=-1)]
    return float(np.sqrt(np.mean(np.sum(err**2, axis=-1)))) if len(err) else float("nan")


def check_positions(points_b, pixels) -> None:
    """ViewCalibrationError when the positions cannot determine every view."""
    points_b = np.asarray(points_b, dtype=np.float64)
    if points_b.ndim != 2 or points_b.shape[1] != 3 or len(points_b) != len(pixels):
        raise ViewCalibrationError(f"need (N, 3) positions and (N, V, 2) pixels, got "
                                   f"{points_b.shape} and {np.shape(pixels)}")
    for v in range(pixels.shape[1]):
        seen = np.isfinite(pixels[:, v, 0])
        name = _view_name(v)
        if seen.sum() < MIN_POSITIONS:
            raise ViewCalibrationError(f"the {name} view saw the LED at {int(seen.sum())} "
                                       f"positions; it needs at least {MIN_POSITIONS}")
        spread = np.linalg.svd(points_b[seen] - points_b[seen].mean(axis=0), compute_uv=False)
        spread /= np.sqrt(seen.sum())
        if spread[-1] < MIN_SPREAD_MM:
            shape = "a line" if spread[1] < MIN_SPREAD_MM else "a plane"
            raise ViewCalibrationError(
                f"the positions the {name} view saw lie on {shape} (spread {spread[-1]:.3f} mm "
                f"across it): move the LED through a volume")


def _view_name(v: int) -> str:
    return ["direct", "left mirror", "right mirror"][v] if v < 3 else f"mirror {v}"


def calibrate_views(points_b, pixels, width: int, height: int, *, seed: int = 0,
                    holdout: float = HOLDOUT_FRACTION) -> ViewCalibration:
    """Fit the ladder of view models and choose per view (module docstring).

    Parameters
    ----------
    points_b : (N, 3) float
        Stage positions of the LED in {B}, mm.
    pixels : (N, V, 2) float
        Its centroid in the direct view then each mirror view, px; NaN where not seen.
    width, height : int
        Image size, px.
    seed : int
        Chooses the held-out positions.

    Returns
    -------
    ViewCalibration
    """
    points_b = np.asarray(points_b, dtype=np.float64)
    pixels = np.asarray(pixels, dtype=np.float64)
    check_positions(points_b, pixels)
    rng = np.random.default_rng(seed)
    test = np.zeros(len(points_b), bool)
    test[rng.permutation(len(points_b))[:max(1, int(round(holdout * len(points_b))))]] = True
    train = ~test
    views = pixels.shape[1]
    train_rms = {m: [np.nan] * views for m in MODELS}
    test_rms = {m: [np.nan] * views for m in MODELS}
    for v in range(views):
        seen = np.isfinite(pixels[:, v, 0])
        tr, te = seen & train, seen & test
        a = fit_affine(points_b[tr], pixels[tr, v])
        train_rms["affine"][v] = _rms(project_affine(a, points_b[tr]) - pixels[tr, v])
        test_rms["affine"][v] = _rms(project_affine(a, points_b[te]) - pixels[te, v])
        p = fit_dlt(points_b[tr], pixels[tr, v])
        train_rms["projective"][v] = _rms(project_dlt(p, points_b[tr]) - pixels[tr, v])
        test_rms["projective"][v] = _rms(project_dlt(p, points_b[te]) - pixels[te, v])
    cam, planes, _ = fit_physical(points_b[train], pixels[train], width, height, distortion=True)
    predicted = project_views(cam, planes, points_b)
    for v in range(views):
        train_rms["pinhole+distortion"][v] = _rms(predicted[train, v] - pixels[train, v])
        test_rms["pinhole+distortion"][v] = _rms(predicted[test, v] - pixels[test, v])
    reports = []
    for v in range(views):
        chosen = MODELS[-1]
        for i, model in enumerate(MODELS[:-1]):
            richer = min(test_rms[m][v] for m in MODELS[i + 1:])
            if test_rms[model][v] <= richer * (1 + SELECTION_MARGIN) + SELECTION_MARGIN_PX:
                chosen = model
                break
        reports.append(ViewReport(_view_name(v), int(np.isfinite(pixels[:, v, 0]).sum()),
                                  {m: train_rms[m][v] for m in MODELS},
                                  {m: test_rms[m][v] for m in MODELS}, chosen))
    # The scanner triangulates through one physical camera: with the lens model when any view
    # needs it. An affine view would not triangulate the stripe of a perspective camera; it is
    # reported, and the projective (ideal pinhole) camera stands in for it.
    distortion = any(r.chosen == "pinhole+distortion" for r in reports)
    model = "pinhole+distortion" if distortion else "projective"
    cam, planes, kept = fit_physical(points_b, pixels, width, height, distortion=distortion)
    err = project_views(cam, planes, points_b) - pixels
    per_view = [_rms(np.where(kept[:, v, None], err[:, v], np.nan)) for v in range(views)]
    return ViewCalibration(cam, tuple(planes), tuple(reports), model,
                           _rms(np.where(kept[..., None], err, np.nan)),
                           int(np.isfinite(pixels[..., 0]).sum() - kept.sum()), per_view)


def views_as_mirrors(planes, columns) -> tuple[Mirror, ...]:
    """The fitted mirror planes with their views' column strips."""
    return tuple(Mirror(Plane(unit(p.normal), p.offset), tuple(c)) for p, c in zip(planes, columns))
