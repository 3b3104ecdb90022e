"""The light plane from a sphere of known radius moved through the sheet (paper section II-A).

The stage carries a sphere of known radius (28.625 mm) to known centres; in each frame the
stripe on it is extracted, and each stripe pixel's ray (the calibrated direct view) meets the
sphere at a point of the light plane. All frames' points together fix the plane, fitted by
iteratively reweighted total least squares. Once the plane is known, the same stripes give the
sphere's centre the way the scanner would measure it (the circle in the plane and the known
radius), which is the accuracy figure the paper quotes (about 100 um).

References
----------
.. [1] "Fast visual part inspection for bin picking", section II-A, Eq. (2).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scanner_core.geometry import PinholeCamera, Plane, triangulate_stripe, unit
from scanner_core.geometry.calibration import PlaneUncertainty

#: Rays meeting the sphere more obliquely than this (cosine with its normal) are dropped: near
#: the silhouette a fraction of a pixel moves the point by millimetres.
MIN_INCIDENCE_COS = 0.35
#: Fewest stripe points a frame must give to count, and fewest frames for a plane.
MIN_POINTS_PER_FRAME = 20
MIN_FRAMES = 3
#: Fewest frames whose leave-one-out fits say how well they fix the plane (`plane_uncertainty`).
MIN_UNCERTAINTY_FRAMES = 4
#: Robust weights: Huber's scale in robust sigmas, and the reweighting rounds.
HUBER_K = 2.0
REWEIGHT_ROUNDS = 6
#: Frames whose circle lies closer to the sphere's equator than this (in share of the radius)
#: give no centre: there the circle's radius says nothing of which side the centre is.
MIN_CAP_HEIGHT = 0.15


#: A plane fit worse than this (RMS of its inliers, or share of the points that are) means the
#: sphere's stated centres or radius do not match its frames (a good session: 5 um, 95 %).
MAX_PLANE_RMS_MM = 0.05
MIN_INLIER_SHARE = 0.7


class PlaneCalibrationError(ValueError):
    """The sphere frames cannot determine the light plane."""


def plane_uncertainty(points_per_frame, plane: Plane) -> PlaneUncertainty:
    """The uncertainty of a plane fitted (`fit_plane`) to the stripe points of several
    frames: the delete-one-frame jackknife (Efron and Stein 1981),
    ``(G - 1) / G sum_f (theta_f - mean theta)(theta_f - mean theta)^T`` over the G frames,
    ``theta_f`` the plane fitted without frame f as ``PlaneUncertainty`` describes it. A
    frame's points share its errors (the stage's position of the sphere, the stripe's bias
    on it), so a frame counts as one observation; with a few dozen frames the jackknife
    holds where a cluster-robust sandwich falls short (docs/calibration.md).

    Parameters
    ----------
    points_per_frame : sequence of (N_f, 3) float
        The stripe points of each frame, mm in {B}; at least 4 frames.
    plane : Plane
        The plane fitted to all of them, in {B}.

    Returns
    -------
    PlaneUncertainty
        About the points' centroid, projected onto `plane`.
    """
    if len(points_per_frame) < MIN_UNCERTAINTY_FRAMES:
        raise ValueError(f"a plane's uncertainty needs at least {MIN_UNCERTAINTY_FRAMES} "
                         f"frames, got {len(points_per_frame)}")
    n = plane.normal
    centre = np.concatenate(points_per_frame).mean(axis=0)
    centre = centre - n * (n @ centre - plane.offset)  # onto the plane
    axes = np.stack(in_plane_axes(n))
    thetas = []
    for left_out in range(len(points_per_frame)):
        others = np.concatenate([p for i, p in enumerate(points_per_frame) if i != left_out])
        thetas.append(plane_parameters(fit_plane(others)[0], centre, axes))
    return PlaneUncertainty(centre, axes, jackknife_covariance(thetas))


def in_plane_axes(normal) -> tuple[np.ndarray, np.ndarray]:
    """Two orthonormal (3,) directions in the plane of unit `normal`, ``e_1 x e_2 = normal``:
    `normal` crossed with x_B (z_B when `normal` lies near x_B), then `normal` crossed with
    that."""
    e1 = unit(np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 0.0, 1.0]))
    return e1, np.cross(normal, e1)


def plane_parameters(plane: Plane, centre, axes) -> np.ndarray:
    """(3,): `plane` as a move of the plane through `centre` with normal ``axes[0] x
    axes[1]``: its tilts along the two `axes` (rad) and its shift along the normal at
    `centre` (mm), ``PlaneUncertainty``'s ``theta``."""
    normal = np.cross(axes[0], axes[1])
    sign = np.sign(plane.normal @ normal)
    n, offset = plane.normal * sign, plane.offset * sign
    return np.array([(n - normal) @ axes[0], (n - normal) @ axes[1], offset - n @ centre])


def jackknife_covariance(replicates) -> np.ndarray:
    """(P, P): the delete-a-group jackknife's covariance of G `replicates` ((G, P)),
    ``(G - 1) / G sum_g (x_g - mean x)(x_g - mean x)^T``."""
    x = np.asarray(replicates, dtype=np.float64)
    spread = x - x.mean(axis=0)
    return spread.T @ spread * (len(x) - 1) / len(x)


@dataclass(frozen=True)
class PlaneCalibration:
    """The fitted light plane and how well the sphere frames agree with it.

    Attributes
    ----------
    plane_b : Plane
        The light plane in {B}, mm.
    rms_mm : float
        RMS distance of the inliers to it.
    points : int
        Stripe points used.
    frames : int
        Sphere frames that gave points.
    centre_errors_mm : (F,) float64
        Per frame, the distance between the sphere centre measured through the fitted plane
        and the stage's (NaN where the circle is too near the equator).
    uncertainty : PlaneUncertainty
        How well the frames fix the plane (`plane_uncertainty`).
    """

    plane_b: Plane
    rms_mm: float
    points: int
    frames: int
    centre_errors_mm: np.ndarray
    uncertainty: PlaneUncertainty | None = None

    @property
    def centre_rms_mm(self) -> float:
        e = self.centre_errors_mm[np.isfinite(self.centre_errors_mm)]
        return float(np.sqrt(np.mean(e**2))) if len(e) else float("nan")


def sphere_points(pixels, camera: PinholeCamera, centre_b, radius_mm: float) -> np.ndarray:
    """Where the pixels' rays first meet a sphere: (N, 3) mm in {B}, NaN for rays that miss
    it or graze it (``MIN_INCIDENCE_COS``).

    Parameters
    ----------
    pixels : (N, 2) float
        Stripe pixels (u, v), px.
    camera : PinholeCamera
    centre_b : (3,) float
        The sphere's centre in {B}, mm.
    radius_mm : float
    """
    d = camera.rays(pixels)
    o = camera.origin
    oc = o - np.asarray(centre_b, dtype=np.float64)
    b = d @ oc
    disc = b * b - (oc @ oc - radius_mm**2)
    with np.errstate(invalid="ignore"):
        s = -b - np.sqrt(disc)  # the near intersection: the side the camera sees
    points = o + s[:, None] * d
    normal = (points - centre_b) / radius_mm
    cos = -np.einsum("ij,ij->i", normal, d)
    points[~(disc > 0) | ~(cos >= MIN_INCIDENCE_COS)] = np.nan
    return points


def fit_plane(points, *, weights=None) -> tuple[Plane, np.ndarray]:
    """Robust total least squares plane through (N, 3) points: the plane and the final weights."""
    p = np.asarray(points, dtype=np.float64)
    w = np.ones(len(p)) if weights is None else np.asarray(weights, dtype=np.float64)
    for _ in range(REWEIGHT_ROUNDS):
        centre = (w[:, None] * p).sum(axis=0) / w.sum()
        q = (p - centre) * np.sqrt(w)[:, None]
        _, _, vt = np.linalg.svd(q, full_matrices=False)
        n = vt[-1]
        r = (p - centre) @ n
        sigma = 1.4826 * np.median(np.abs(r)) + 1e-12
        a = np.abs(r) / (HUBER_K * sigma)
        w = np.where(a <= 1.0, 1.0, 1.0 / np.maximum(a, 1e-12))
    if n[1] < 0:
        n = -n  # a fixed sign: the sheet's normal along the pass (+y in the reference cell)
    return Plane(unit(n), float(n @ centre)), w


def circle_centre(points, plane: Plane, radius_mm: float, side_point) -> np.ndarray:
    """The sphere's centre from the stripe's points in the plane: the circle's centre (least
    squares, Kasa) moved off the plane by ``sqrt(R^2 - r^2)`` towards ``side_point`` (the
    stage's centre says which side). NaN near the equator (``MIN_CAP_HEIGHT``)."""
    n = plane.normal
    e1, e2 = in_plane_axes(n)
    origin = n * plane.offset
    x, y = (points - origin) @ e1, (points - origin) @ e2
    a = np.column_stack([2 * x, 2 * y, np.ones(len(x))])
    (cx, cy, c), *_ = np.linalg.lstsq(a, x * x + y * y, rcond=None)
    r2 = c + cx * cx + cy * cy
    h2 = radius_mm**2 - r2
    if not h2 > (MIN_CAP_HEIGHT * radius_mm) ** 2:
        return np.full(3, np.nan)
    side = np.sign((np.asarray(side_point, dtype=np.float64) - origin) @ n)
    return origin + cx * e1 + cy * e2 + side * np.sqrt(h2) * n


def sphere_plane(frames, camera: PinholeCamera,
                 radius_mm: float) -> tuple[Plane, list[np.ndarray], np.ndarray]:
    """The light plane through the sphere frames' stripe points, robustly (`fit_plane`).

    Parameters
    ----------
    frames : sequence of (pixels (N, 2), centre_b (3,))
        Each frame's stripe pixels on the sphere and the stage's sphere centre in {B}, mm.
    camera : PinholeCamera
        The calibrated direct view.
    radius_mm : float

    Returns
    -------
    plane_b : Plane
        In {B}, mm.
    points_per_frame : list of (N_f, 3) float64
        The stripe points of each frame that gave enough of them, mm in {B}.
    weights : (sum N_f,) float64
        The fit's robust weights, in the order of those points.

    Raises
    ------
    PlaneCalibrationError
        Fewer than ``MIN_FRAMES`` frames with a stripe on the sphere (the sheet never cuts it),
        or all centres on one line (the plane would turn about it).
    """
    per_frame = []
    for pixels, centre in frames:
        pts = sphere_points(pixels, camera, centre, radius_mm)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if len(pts) >= MIN_POINTS_PER_FRAME:
            per_frame.append(pts)
    if len(per_frame) < MIN_FRAMES:
        raise PlaneCalibrationError(
            f"only {len(per_frame)} sphere frame(s) show a stripe on the sphere; at least "
            f"{MIN_FRAMES} are needed: does the sheet cut the sphere at those positions?")
    allpts = np.concatenate(per_frame)
    spread = np.linalg.svd(allpts - allpts.mean(axis=0), compute_uv=False) / np.sqrt(len(allpts))
    if spread[1] < 1.0:
        raise PlaneCalibrationError("the stripe points lie on a line: move the sphere across "
                                    "the sheet, not along one line in it")
    plane, w = fit_plane(allpts)
    return plane, per_frame, w


def calibrate_plane(frames, camera: PinholeCamera, radius_mm: float) -> PlaneCalibration:
    """The light plane from sphere frames (`sphere_plane`), how well they agree with it, and
    how well they fix it (`plane_uncertainty`; None from fewer than
    ``MIN_UNCERTAINTY_FRAMES`` frames).

    Parameters
    ----------
    frames : sequence of (pixels (N, 2), centre_b (3,))
        Each frame's stripe pixels on the sphere and the stage's sphere centre in {B}, mm.
    camera : PinholeCamera
        The calibrated direct view.
    radius_mm : float

    Raises
    ------
    PlaneCalibrationError
        As `sphere_plane`, or when the points do not lie on one plane (``MAX_PLANE_RMS_MM``,
        ``MIN_INLIER_SHARE``).
    """
    plane, per_frame, w = sphere_plane(frames, camera, radius_mm)
    allpts = np.concatenate(per_frame)
    inlier = w >= 1.0
    rms = float(np.sqrt(np.mean(plane.signed_distance(allpts[inlier]) ** 2)))
    if rms > MAX_PLANE_RMS_MM or inlier.mean() < MIN_INLIER_SHARE:
        raise PlaneCalibrationError(
            f"the stripe points on the spheres do not lie on one plane ({rms * 1e3:.0f} um RMS, "
            f"{inlier.mean():.0%} of them near it): do the stage's sphere centres belong to "
            f"these frames, and is the radius right?")
    plane_c = plane.transformed(camera.rotation, -camera.rotation @ camera.origin)
    errors = []
    for (pixels, centre) in frames:
        pts = triangulate_stripe(pixels, camera, plane_c)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if len(pts) < MIN_POINTS_PER_FRAME:
            errors.append(np.nan)
            continue
        errors.append(float(np.linalg.norm(circle_centre(pts, plane, radius_mm, centre)
                                           - centre)))
    uncertainty = (plane_uncertainty(per_frame, plane)
                   if len(per_frame) >= MIN_UNCERTAINTY_FRAMES else None)
    return PlaneCalibration(plane, rms, int(inlier.sum()), len(per_frame), np.array(errors),
                            uncertainty)
