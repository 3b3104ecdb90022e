"""Edge points along one profile (paper section II): what `find_edges` takes and gives.

`find_edges` checks one frame's per-column stripe measurement, marks its dark and double
columns, and runs the compiled kernel over it (``scanner_core.edges.kernel``): drop-outs
evaluated by size, discontinuities by range, each edge point at half the relative step. It
gives the profile's `EdgePoints` in {B}; `EdgeParams` says how drop-outs and steps are told
from noise, `EdgeKind` names the kinds of point, and `profile_axes` the profile's in-plane
axes. The method is described in ``scanner_core.edges``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from scanner_core.edges.kernel import _edges_kernel
from scanner_core.geometry import PinholeCamera, Plane, triangulate_stripe
from scanner_core.geometry.model import NO_DISTORTION
from scanner_core.stripe.extractor import Reason

__all__ = ["EdgeKind", "EdgeParams", "EdgePoints", "find_edges", "profile_axes",
           "MIN_COLUMN_COMPONENT"]

#: The sheet must not be within about 0.06 degrees of perpendicular to the image columns (the
#: sine of that angle), or the stripe has no direction along the columns.
MIN_COLUMN_COMPONENT = 1e-3


class EdgeKind:
    """Codes of ``EdgePoints.kind`` and ``Scan.edge_kind`` (uint8): what a profile found; and
    of ``Scan.edges_aside.kind``: why the scan set an edge point aside
    (``scanner_core.edges.kinds``)."""

    DROPOUT = 0  # the stripe ends: the part's outline, a hole's rim, a shadow-casting edge
    STEP = 1  # the range jumps between neighbouring columns: a step in the part surface
    OCCLUDED = 2  # a drop-out where another part of the part hides the stripe (occluded_dropouts)
    GRAZING = 3  # on a surface the sheet grazes (grazing_edges)
    TURNED_AWAY = 4  # the surface may go on beyond, turned from the view or the light by a
    #                  soft crease (scanner_core.edges.kinds.turned_away)
    OFF_MODEL = 5  # off every edge of the registered CAD model (edge_kinds.reclassify_with_model)


@dataclass(frozen=True)
class EdgeParams:
    """How drop-outs and steps are told from noise (paper section II).

    Attributes
    ----------
    min_gap_px : int
        A gap is a drop-out when it holds at least this many dark columns (no stripe, or a
        stripe too faint to measure); narrower gaps are noise and are bridged. Default 3:
        one or two dark columns are specks or speckle; the smallest hole the reference cell
        should see (0.5 mm) spans 3 columns.
    max_bridge_px : int
        Longest run of invalid columns of any kind (dark, saturated, double, masked) across
        which the columns on either side still count as neighbours for the step test. Default
        10: saturation by speckle on bright surfaces spans up to about 7 columns.
    min_run_px : int
        A stretch of stripe with fewer valid columns than this, between drop-outs, is a speck
        (a noise pixel that passed for the stripe): it is removed before anything else.
    side_px : int
        Valid columns on each side of a drop-out or a step used for its line fits (row,
        range) and its levels; also the half-width of the window whose median jump gives the
        local slope of the surface (at least ``max_ramp_px``, so that a ramp does not
        set its own slope).
    min_step_mm : float
        Smallest step height (mm, along the range axis) that is an edge; smaller jumps are
        surface (texture, a fillet, calibration noise). Default 0.3 mm: over twenty times
        the point-to-point range scatter of the reference cell (about 13 um; 9 um per point),
        and below the smallest steps of machined parts that matter for their pose.
    noise_factor : float
        A step must also exceed this many times the profile's point-to-point range scatter
        (estimated per profile from second differences, robustly): noisy profiles (faint or
        speckled stripes) need larger steps.
    max_ramp_px : int
        Longest run of consecutive jumps of one sign taken as one step seen over a few
        columns; a longer run is a sloped surface.
    min_contrast : float
        A drop-out's side must be at least this many times as bright as the gap's columns
        (their background, or a stripe too faint to pass): a faint stripe ending in the noise
        gives no half step to place its edge by. Default 2: on the reference parts, drop-outs
        of stripes within 2x of their gap's level (a steep wall's, about 35 DN over 25 DN)
        landed 180 um RMS off their edges, against 20 um for the others.
    keep_far_side : bool
        Also keep the far side of a gap whose sides lie at different ranges (a shadow's or an
        occlusion's boundary on the farther surface, usually not an edge of the part).
    """

    min_gap_px: int = 3
    max_bridge_px: int = 10
    min_run_px: int = 3
    side_px: int = 6
    min_step_mm: float = 0.3
    noise_factor: float = 8.0
    max_ramp_px: int = 6
    min_contrast: float = 2.0
    keep_far_side: bool = False

    def __post_init__(self):
        for name in ("min_gap_px", "max_bridge_px", "min_run_px", "side_px", "max_ramp_px"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise ValueError(f"`{name}` must be a positive integer, got {value!r}")
        if self.side_px < 2 or self.side_px < self.max_ramp_px:
            raise ValueError(f"`side_px` must be >= 2 (a line fit) and >= `max_ramp_px` "
                             f"({self.max_ramp_px}), got {self.side_px}")
        if not (self.min_step_mm > 0 and math.isfinite(self.min_step_mm)):
            raise ValueError(f"`min_step_mm` must be > 0, got {self.min_step_mm}")
        if not (self.noise_factor >= 0 and math.isfinite(self.noise_factor)):
            raise ValueError(f"`noise_factor` must be >= 0, got {self.noise_factor}")
        if not (self.min_contrast >= 0 and math.isfinite(self.min_contrast)):
            raise ValueError(f"`min_contrast` must be >= 0, got {self.min_contrast}")


@dataclass(frozen=True)
class EdgePoints:
    """Edge points of one profile (or of a scan, concatenated), in the order found.

    Attributes
    ----------
    pixel : (M, 2) float64
        Where the edge lies in the image, px: the sub-pixel column where it was found, and
        the row of the side's stripe there (a drop-out: ``point_b`` projects to it) or half
        way between the two sides' rows (a step: the half-height point ``point_b``, off the
        sheet's surfaces, projects up to about a column away from it, by perspective).
    point_b : (M, 3) float64
        The edge point in {B}, mm, in the light plane.
    kind : (M,) uint8
        ``EdgeKind``: 0 drop-out, 1 step.
    size_mm : (M,) float64
        Drop-out: the gap's width in the sheet (distance between the two bounding stripe
        ends), mm; NaN where the stripe does not come back within the view. Step: the relative
        step height along the range axis, mm (positive).
    peak : (M,) float32
        Stripe peak intensity on the edge's side (drop-out) or the fainter side (step), DN:
        the point's quality.
    direction : (M,) int8
        +1 when the gap (drop-out) or the far side (step) lies towards higher columns, -1
        towards lower ones.
    along_b : (3,) float64
        The profile's axis along the stripe (towards higher columns) in {B}, unit: with
        ``direction`` it gives each point's direction across its edge (``across_b``).
    noise_mm : float
        The profile's point-to-point range scatter (one point's standard deviation), mm;
        NaN when too few points to tell.
    stripe_end : (M, 5) float32
        Drop-out: its last lit column's peak and the one before it over the image's
        background (``result.background_dn``), as fractions of the face's level 3 to 5
        columns in (the light each holds: a peak is its column's largest pixel), the
        distance from the point to the outer side of that column (px, outward), that
        column's row off the face's line (px), and 1 where the point was placed by a
        chamfer's own level (its rows turned short of the end), else 0: what
        :func:`chamfered_dropouts` places a chamfered outline by. NaN for a step; the levels
        and row NaN where the side is too short or broken for its face, or its face is no
        brighter than the background. A last column lit too faintly to pass the stripe's
        threshold is dark: the one before it is then the last, and the outline lies up to
        that faint share of a column beyond where the fit puts it.
    per_px_b : (M, 3) float64
        Drop-out: how the point moves in {B}, mm, when its column moves one px outward along
        its side's rows. NaN for a step.
    up_wall_b : (M, 3) float64
        Step on a wall the camera does not see: how far the point was moved from the near
        side's end to half the step's height, along the sheet's range axis, in {B}, mm (the
        wall is taken to run that way; ``scanner_core.pipeline.accumulate`` turns the move
        along the gripper's z_T). Zero for a step interpolated on a wall the camera sees,
        and for a drop-out.
    """

    pixel: np.ndarray
    point_b: np.ndarray
    kind: np.ndarray
    size_mm: np.ndarray
    peak: np.ndarray
    direction: np.ndarray
    along_b: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    noise_mm: float = float("nan")
    stripe_end: np.ndarray | None = None
    per_px_b: np.ndarray | None = None
    up_wall_b: np.ndarray | None = None

    def __post_init__(self):
        m = len(self.kind)
        if self.stripe_end is None:
            object.__setattr__(self, "stripe_end", np.full((m, 5), np.nan, np.float32))
        if self.per_px_b is None:
            object.__setattr__(self, "per_px_b", np.full((m, 3), np.nan))
        if self.up_wall_b is None:
            object.__setattr__(self, "up_wall_b", np.zeros((m, 3)))
        if (np.shape(self.stripe_end) != (m, 5) or np.shape(self.per_px_b) != (m, 3)
                or np.shape(self.up_wall_b) != (m, 3)):
            raise ValueError(f"`stripe_end`, `per_px_b` and `up_wall_b` must be ({m}, 5), "
                             f"({m}, 3) and ({m}, 3), got {np.shape(self.stripe_end)}, "
                             f"{np.shape(self.per_px_b)} and {np.shape(self.up_wall_b)}")

    def __len__(self) -> int:
        return len(self.kind)

    @property
    def across_b(self) -> np.ndarray:
        """(M, 3) float64: unit vectors in the sheet, in {B}, from each edge point's stripe
        side into its gap (drop-out) or from its near side to its far side (step)."""
        return self.direction[:, None].astype(np.float64) * self.along_b[None, :]

    @classmethod
    def empty(cls, along_b=None) -> "EdgePoints":
        along = np.full(3, np.nan) if along_b is None else np.asarray(along_b, np.float64)
        return cls(np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, np.uint8), np.zeros(0),
                   np.zeros(0, np.float32), np.zeros(0, np.int8), along)


def profile_axes(camera: PinholeCamera, light_plane_c: Plane) -> tuple[np.ndarray, np.ndarray]:
    """The in-plane axes of a profile, in {C}.

    Parameters
    ----------
    camera : PinholeCamera
        Unused beyond its convention ({C}: x along columns, z the optical axis); kept so that
        callers pass the geometry the way ``triangulate_stripe`` takes it.
    light_plane_c : Plane
        The light plane in {C} (Eq. 2).

    Returns
    -------
    e_a : (3,) float64
        Unit vector along the stripe: {C}'s x axis projected into the sheet.
    e_d : (3,) float64
        Unit range axis: in the sheet, perpendicular to ``e_a``, pointing away from the camera
        (``e_d . z_C > 0``).

    Raises
    ------
    ValueError
        When the sheet is perpendicular to the image columns (the stripe would run along a
        column: no profile along the columns).
    """
    del camera
    nx, ny, nz = (float(v) for v in light_plane_c.normal)  # scalars: no BLAS (docs/design.md)
    scale = math.sqrt(nx * nx + ny * ny + nz * nz)
    nx, ny, nz = nx / scale, ny / scale, nz / scale
    ax, ay, az = 1.0 - nx * nx, -nx * ny, -nx * nz  # x_C minus its component along n
    norm = math.sqrt(ax * ax + ay * ay + az * az)
    if norm < MIN_COLUMN_COMPONENT:
        raise ValueError("`light_plane_c` is perpendicular to the image columns: the stripe "
                         "does not run along the columns")
    ax, ay, az = ax / norm, ay / norm, az / norm
    dx, dy, dz = ny * az - nz * ay, nz * ax - nx * az, nx * ay - ny * ax  # n x e_a
    sign = -1.0 if dz < 0 else 1.0
    return np.array([ax, ay, az]), np.array([sign * dx, sign * dy, sign * dz])


def find_edges(result, valid, camera: PinholeCamera, light_plane_c: Plane, *,
               params: EdgeParams = EdgeParams(), masked=None) -> EdgePoints:
    """Drop-out and step edge points along one profile (paper section II).

    Parameters
    ----------
    result : StripeResult or any object with the same per-column arrays
        ``row`` (W,) float (sub-pixel row, px), ``peak`` (W,) float (DN, NaN outside the
        processed columns) and ``reason`` (W,) uint8 (``scanner_core.stripe.extractor.Reason``) of one
        frame.
    valid : (W,) bool
        Columns whose stripe is kept: typically ``result.valid & (result.peak >= min_peak)``
        with masked columns removed, as ``pipeline.process_frame`` computes it.
    camera : PinholeCamera
    light_plane_c : Plane
        Light plane in {C} (Eq. 2).
    params : EdgeParams
    masked : (W,) bool, optional
        Columns whose lack of a stripe says nothing (the LED marker masked out there): they
        are not dark, so they neither make nor widen a drop-out.

    Returns
    -------
    EdgePoints
        In {B}. Empty for a profile without stripe.

    Notes
    -----
    A column is *dark* when it is not valid and either holds no peak above the threshold
    (``Reason.NO_PEAK``), only noise (``Reason.TOO_NARROW``), or a stripe that ``valid``
    rejects although the extraction found it (``Reason.OK``: too faint), and is not
    ``masked``. Other invalid columns (saturated, double, too wide, fit failed, not processed)
    hold a stripe that could not be measured, or nothing known: a gap made of them is no
    drop-out (the stripe goes on), but steps are still measured across it when it is at most
    ``max_bridge_px`` wide. A drop-out needs its first gap column to be dark, so the end of
    the processed columns (the direct view's border) makes no edge.

    References
    ----------
    .. [1] "Fast visual part inspection for bin picking", section II:
       drop-outs by size, discontinuities by range, the edge at half the relative step.

    Examples
    --------
    In ``pipeline.process_frame``, with the marker's columns as it masks them::

        edges = find_edges(result, valid, calibration.camera, calibration.light_plane_c,
                           params=params.edges, masked=near & rows_near_marker)

    and placed in {T} as the profile's points, with the TCP at ``tcp`` and rotation ``R``::

        points_t = base_to_tcp(edges.point_b, tcp, R); across_t = edges.across_b @ R
    """
    row, peak, reason = _profile_arrays(result)
    w = row.shape[0]
    valid = _mask(valid, w, "valid")
    masked = np.zeros(w, dtype=bool) if masked is None else _mask(masked, w, "masked")
    e_a, e_d = profile_axes(camera, light_plane_c)
    along_b = np.einsum("ji,j->i", camera.rotation, e_a)  # {C} -> {B}; no BLAS (docs/design.md)
    if not valid.any():
        return EdgePoints.empty(along_b)
    dark = (~valid & ~masked
            & ((reason == Reason.NO_PEAK) | (reason == Reason.TOO_NARROW) | (reason == Reason.OK)))
    # 1: two stripes, rejected (Reason.DOUBLE); 2: measured on one of its two peaks (the
    # policies that choose a peak report no Reason.DOUBLE): ``_near_end``
    double = (~valid & (reason == Reason.DOUBLE)).astype(np.uint8)
    n_peaks = getattr(result, "n_peaks", None)
    if n_peaks is not None:
        double[_mask(np.asarray(n_peaks) >= 2, w, "result.n_peaks") & valid] = 2
    n = np.asarray(light_plane_c.normal, dtype=np.float64)
    p = params
    pixel, point_c, kind, size, pk, direction, end, move_c, noise = _edges_kernel(
        row, peak, valid, dark, double, float(camera.fx), float(camera.fy), float(camera.cx),
        float(camera.cy), n, float(light_plane_c.offset), e_a, e_d, int(p.min_gap_px),
        int(p.max_bridge_px), int(p.min_run_px), int(p.side_px), float(p.min_step_mm),
        float(p.noise_factor), int(p.max_ramp_px), float(p.min_contrast), bool(p.keep_far_side),
        _background(result))
    point_b = np.einsum("ij,jk->ik", point_c, camera.rotation) + camera.origin  # Eq. (3), no BLAS
    if camera.distorted and len(pixel):
        # The kernel's rays are the ideal pinhole's: a lens bends them by up to a few pixels at
        # the border. Each point moves by what the bending moves its pixel's point; the
        # kernel's own placement of a step's point (half the step back along the range, past
        # the pixel's ray) is kept. Taken from the pixel's point outright, every step of a
        # bracket's 5 mm step lay 55 um off in a cell with a real lens (its drop-outs, 18 um).
        pinhole = replace(camera, distortion=NO_DISTORTION)
        point_b = point_b + (triangulate_stripe(pixel, camera, light_plane_c)
                             - triangulate_stripe(pixel, pinhole, light_plane_c))
    per_px_b = np.einsum("ij,jk->ik", end[:, 5:8], camera.rotation)  # {C} -> {B}, no BLAS
    up_wall_b = np.einsum("ij,jk->ik", move_c, camera.rotation)
    stripe_end = end[:, :5].astype(np.float32)
    return EdgePoints(pixel, point_b, kind, size, pk.astype(np.float32), direction, along_b,
                      float(noise), stripe_end, per_px_b, up_wall_b)


# ---------------------------------------------------------------------------------------------
# input checks


def _profile_arrays(result) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    try:
        row, peak, reason = result.row, result.peak, result.reason
    except AttributeError:
        raise ValueError("`result` must have per-column arrays `row`, `peak` and `reason` "
                         f"(a StripeResult), got {type(result).__name__}") from None
    row = np.ascontiguousarray(row, dtype=np.float64)
    peak = np.ascontiguousarray(peak, dtype=np.float64)
    reason = np.ascontiguousarray(reason)
    if row.ndim != 1 or peak.shape != row.shape or reason.shape != row.shape:
        raise ValueError("`result.row`, `result.peak` and `result.reason` must be (W,) arrays "
                         f"of one length, got {row.shape}, {peak.shape}, {reason.shape}")
    if reason.dtype != np.uint8:
        raise ValueError(f"`result.reason` must be uint8 Reason codes, got {reason.dtype}")
    return row, peak, reason


def _background(result) -> float:
    """The frame's background level under the stripe, DN (0 when the result has none)."""
    value = float(getattr(result, "background_dn", 0.0))
    return value if math.isfinite(value) else 0.0


def _mask(mask, w: int, name: str) -> np.ndarray:
    arr = np.asarray(mask)
    if arr.shape != (w,) or arr.dtype != np.bool_:
        raise ValueError(f"`{name}` must be a ({w},) bool array, got {arr.shape} {arr.dtype}")
    return np.ascontiguousarray(arr)
