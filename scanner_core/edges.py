"""Edge points along one profile: drop-outs evaluated by size, discontinuities by range.

Paper section II: "edges can be defined as discontinuities or drop-outs in the intensity of
the line. Drop-outs are evaluated by size, and discontinuities are evaluated by range in order
to certify whether the discontinuity represents a step in the part surface or an edge on the
part [...] The edge is defined as half the relative step height."

One profile is one frame's per-column stripe measurement (``scanner_core.stripe.extract``)
over the direct view. Its valid columns are triangulated into the light plane, where each
point gets two in-plane coordinates (mm, in {C} units):

- ``a``, along the stripe: the camera's x axis (image columns) projected into the sheet;
- ``d``, the *range*: in the sheet, perpendicular to ``a``, growing away from the camera.
  In the reference cell ``d`` runs along z_B = -z_T: the depth of the part's underside.

Along the profile (columns in order):

- **Drop-outs.** Runs of columns without a stripe are gaps. A gap with fewer than
  ``min_gap_px`` dark columns is noise (a speck, a dark column of speckle) and is bridged: the
  columns on either side stay neighbours. A larger gap bounded by stripe on one or both sides
  is a drop-out: the part's outline, a hole's rim, a shadow. Each bounding side gets one edge
  point where the stripe's peak intensity falls to half way between its level on that side
  and the level in the gap ("half the relative step", interpolated between columns), its row
  extrapolated from that side's rows, then triangulated. When the two sides of a gap lie at
  different ranges (by more than the step threshold and ``FAR_SIDE_SIGMAS`` standard errors
  of their lines extrapolated to the gap's middle), the far side is the boundary of a
  shadow or of an occlusion cast by the near side's edge, not an edge of the part: only the
  near side gives an edge point (``EdgeParams.keep_far_side``). A side's level is taken at the
  top of its falling flank, short of where its rows turn (a dimmer chamfer next to the gap
  keeps its own level); a side under ``min_contrast`` times its gap's level ends in the noise
  and gives no edge point.
- **Steps.** Between neighbouring valid columns (bridged gaps included) a jump in range,
  after removing the local slope of the surface, larger than the step threshold
  (``max(min_step_mm, noise_factor * point-to-point scatter)``) marks a step; a run of up to
  ``max_ramp_px`` such jumps of one sign is one step seen over a few columns (an inclined
  wall, a chamfer). Lines fitted to each side give the relative step height ``h`` at the
  step; the edge point lies at half of it. Where the step is resolved (its half-height level
  falls between two adjacent columns that hold less than half of it) the point is
  interpolated there; otherwise (a jump within one column, or across a bridged gap) the wall
  stands at the near side's boundary: where the near side's stripe falls to half its level, as
  a drop-out's (a pixel column holding the wall is lit in part by the near surface, in
  proportion to the share of the pixel it covers; a column holding both sides' stripes is
  taken as half lit by each when rejected as a double, and as lit by the near side at
  ``DOUBLE_SHARE`` of its peak when measured on one of two peaks, ``StripeResult.n_peaks``),
  and the point is that boundary on the near surface
  moved by ``h / 2`` along ``d``: walls are taken to run along the range axis (vertical walls
  in the reference cell), so in {T} the point projects onto the wall's top and bottom edges.
  A step with a side cut short by another edge must be ``SHORT_SIDE_STEP_FACTOR`` times the
  threshold high (a chamfer's slope at the rim of a larger step is no step of its own).
- **Surfaces curving away.** A side whose rows turn steadily up to its end, past their
  crest (:func:`_curls`), ends where the stripe is lost on a surface rounding off, not at an
  edge: neither a drop-out nor a step is placed there.

Drop-outs at the boundary of an occlusion by a feature outside the sheet look, in one profile,
like a rim: :func:`occluded_dropouts` finds them in the scan. A chamfer narrower than two
columns at an outline lights the stripe's last column or two at a level of its own, which one
profile cannot tell from where the outline lies in its last column: each drop-out reports its
stripe's end (``EdgePoints.stripe_end``), and :func:`chamfered_dropouts` fits the chamfer
along the edge's profiles and places their points at the outline.

Speed: one numba kernel over the profile: 0.05-0.1 ms per 1920-column frame with 1000 valid
columns, about 0.15 ms in a pass with the frame cold in the cache (2 cores, see
``tests/scanner_core/test_edges.py``). The first call loads the compiled kernel (10-20 ms; a
few seconds when it compiles): warm it up before a pass.

References
----------
.. [1] "Fast visual part inspection for bin picking", section II (../shared/paper.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from scanner_core.geometry import PARALLEL_COS, PinholeCamera, Plane, triangulate_stripe
from scanner_core.stripe import Reason

__all__ = ["EdgeKind", "EdgeParams", "EdgePoints", "find_edges", "occluded_dropouts",
           "grazing_edges", "chamfered_dropouts", "profile_axes"]

#: A step is resolved over adjacent columns (interpolated there) when the segment that holds
#: its half-height level spans at most this fraction of the step height; a larger share means
#: the jump happened within one column and the wall's position is only known to that column.
RESOLVED_STEP_FRACTION = 0.5
#: A drop-out's falling flank goes on inward while the next column is brighter by more than
#: this fraction: well above the speckle's column-to-column change (contrast 0.1 smoothed over
#: about 3 columns), well below a blurred edge's rise until its last few percent.
FLANK_RISE = 0.05
#: A drop-out side's intensity level is the median peak of this many columns from the top of
#: its flank inward: few enough to stay on a narrow face next to the gap (a 4-column chamfer).
LEVEL_PX = 3
#: A drop-out's flank stops where the stripe's row step changes by more than this between
#: neighbouring columns, px: a face turned against the one inward (a chamfer), whose dimmer
#: stripe keeps its own level. A blurred flank on one face keeps its rows' trend; the idler's
#: 45-degree chamfers turned them by 0.4 to 0.6 px, noise and partly lit end columns by up
#: to about 0.2 px.
ROW_BEND_PX = 0.25
#: ... and by more than this many times the turn's noise (sqrt(6) times the rows' scatter).
BEND_NOISE_FACTOR = 3.0
#: A step with a side cut short (fewer than side_px points before another edge or the end
#: of the stripe) must be this many times the step threshold high: a chamfer at the rim of a
#: larger step or of the outline reads as a step just over the threshold (the idler's 45
#: degree chamfers beside its 8.6 mm steps: 0.3 mm, about 100 um off every edge), while the
#: larger step beside it, cut short by the chamfer, stays.
SHORT_SIDE_STEP_FACTOR = 2.0
#: A side whose rows turn steadily over its last points before the end (by at least this
#: much in all, px, no one turn more than CURL_SHARE of it) ends on a surface curving away
#: from the camera or the sheet, not at an edge: cycloidal's rounded lobes turned the rows by
#: 0.2 to 0.45 px over 3 turns and ended 0.1 to 0.45 mm short of every CAD edge. A chamfer
#: turns them at one kink. CURL_MAX_TURNS turns are judged; a side too short for them (a
#: stretch of stripe 4 or 5 columns long across a lobe's crest) over the turns it has, at
#: least CURL_MIN_TURNS. Noisier profiles need CURL_NOISE_FACTOR times their rows' scatter
#: (2.5 sigma of the turn over 3 steps): on a level stripe with 0.1 px of row noise the test
#: took 10 of 8000 ends for curls (4 at 3 sigma, which kept two lobe ends 0.37 and 0.38 mm
#: off in the bench's cycloidal scans).
CURL_PX = 0.2
CURL_SHARE = 0.7
CURL_NOISE_FACTOR = 5.0
CURL_MAX_TURNS = 3
CURL_MIN_TURNS = 2
#: The far side of a gap (a shadow's or an occlusion's boundary) must lie beyond the near one
#: by the step threshold plus this many standard errors of the two sides' lines extrapolated
#: to the gap's middle: across a 100-column gap at 0.1 px of row noise, the bare threshold
#: took a quarter of the holes' rims for shadows.
FAR_SIDE_SIGMAS = 3.0
#: A drop-out's face level, for :func:`chamfered_dropouts`: the median peak of END_FACE_PX
#: columns from END_FACE_FROM columns in from the stripe's end (past a chamfer up to two
#: columns wide).
END_FACE_FROM = 3
END_FACE_PX = 3
#: A column holding a second peak (``StripeResult.n_peaks``) beside a step's near side holds
#: that side's stripe on part of it: its share is taken as this fraction of the column's
#: chosen peak (:func:`_near_end`). Measured at the 5 mm step of the bracket with two holes
#: (``simulator.parts.bracket_with_two_holes``), its wall leaning 2 to 6 degrees under its top
#: edge: the second peak held 0.28-0.6 of the chosen one (10th-90th percentiles, median 0.41
#: to 0.5); 0.47-1.1 (median 0.62) where both sides lit the column in part at the wall's end.
#: Taken as none (before issue 25), the steps landed 0.34 px inside the near side on average
#: (step RMS 76 um at a 6-degree lean); as half the near side's level, 0.35 px past it at the
#: wall's ends; as 0.65 of the chosen peak (the middle of DOUBLE_PEAK_RATIO..1), 0.27 px past.
DOUBLE_SHARE = 0.45
#: MAD of a normal sample times this is its standard deviation.
MAD_TO_SIGMA = 1.4826
#: The sheet must not be within about 0.06 degrees of perpendicular to the image columns (the
#: sine of that angle), or the stripe has no direction along the columns.
MIN_COLUMN_COMPONENT = 1e-3
#: Fewest second differences for a noise estimate; with fewer, the threshold is min_step_mm.
MIN_NOISE_SAMPLES = 8


class EdgeKind:
    """Codes of ``EdgePoints.kind`` and ``Scan.edge_kind`` (uint8): what a profile found; and
    of ``Scan.edges_aside.kind``: why the scan set an edge point aside
    (``scanner_core.edge_kinds``)."""

    DROPOUT = 0  # the stripe ends: the part's outline, a hole's rim, a shadow-casting edge
    STEP = 1  # the range jumps between neighbouring columns: a step in the part surface
    OCCLUDED = 2  # a drop-out where another part of the part hides the stripe (occluded_dropouts)
    GRAZING = 3  # on a surface the sheet grazes (grazing_edges)
    TURNED_AWAY = 4  # the surface may go on beyond, turned from the view or the light by a
    #                  soft crease (scanner_core.edge_kinds.turned_away)
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

    def __post_init__(self):
        m = len(self.kind)
        if self.stripe_end is None:
            object.__setattr__(self, "stripe_end", np.full((m, 5), np.nan, np.float32))
        if self.per_px_b is None:
            object.__setattr__(self, "per_px_b", np.full((m, 3), np.nan))
        if np.shape(self.stripe_end) != (m, 5) or np.shape(self.per_px_b) != (m, 3):
            raise ValueError(f"`stripe_end` and `per_px_b` must be ({m}, 5) and ({m}, 3), got "
                             f"{np.shape(self.stripe_end)} and {np.shape(self.per_px_b)}")

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
    nx, ny, nz = (float(v) for v in light_plane_c.normal)  # scalars: no BLAS (NOTES.md)
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
        processed columns) and ``reason`` (W,) uint8 (``scanner_core.stripe.Reason``) of one
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
    .. [1] "Fast visual part inspection for bin picking", section II (../shared/paper.md):
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
    along_b = np.einsum("ji,j->i", camera.rotation, e_a)  # {C} -> {B}; no BLAS (NOTES.md)
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
    pixel, point_c, kind, size, pk, direction, end, noise = _edges_kernel(
        row, peak, valid, dark, double, float(camera.fx), float(camera.fy), float(camera.cx),
        float(camera.cy), n, float(light_plane_c.offset), e_a, e_d, int(p.min_gap_px),
        int(p.max_bridge_px), int(p.min_run_px), int(p.side_px), float(p.min_step_mm),
        float(p.noise_factor), int(p.max_ramp_px), float(p.min_contrast), bool(p.keep_far_side),
        _background(result))
    point_b = np.einsum("ij,jk->ik", point_c, camera.rotation) + camera.origin  # Eq. (3), no BLAS
    if camera.distorted and len(pixel):
        # The kernel's rays are the ideal pinhole's: a lens bends them by up to a few pixels at
        # the border, which moves the edge's position but not the steps it found.
        point_b = triangulate_stripe(pixel, camera, light_plane_c)
    per_px_b = np.einsum("ij,jk->ik", end[:, 5:8], camera.rotation)  # {C} -> {B}, no BLAS
    stripe_end = end[:, :5].astype(np.float32)
    return EdgePoints(pixel, point_b, kind, size, pk.astype(np.float32), direction, along_b,
                      float(noise), stripe_end, per_px_b)


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


# ---------------------------------------------------------------------------------------------
# kernel: plain loops, compiled once (cache=True), no GIL held


@njit(nogil=True, cache=True)
def _fit_line(x, y, lo, hi):
    """Least-squares line through points lo..hi-1, centred: (x_mean, y_mean, slope, Sxx), Sxx
    the sum of squared deviations of x (a prediction at x0 has variance per unit variance of
    one point 1/n + (x0 - x_mean)^2 / Sxx)."""
    m = hi - lo
    xm = 0.0
    ym = 0.0
    for i in range(lo, hi):
        xm += x[i]
        ym += y[i]
    xm /= m
    ym /= m
    sxx = 0.0
    sxy = 0.0
    for i in range(lo, hi):
        dx = x[i] - xm
        sxx += dx * dx
        sxy += dx * (y[i] - ym)
    slope = sxy / sxx if sxx > 0.0 else 0.0
    return xm, ym, slope, sxx


@njit(nogil=True, cache=True)
def _median_small(buf, m):
    """Median of buf[:m] (m >= 1), sorting it in place: insertion sort for a dozen values."""
    for i in range(1, m):
        v = buf[i]
        j = i - 1
        while j >= 0 and buf[j] > v:
            buf[j + 1] = buf[j]
            j -= 1
        buf[j + 1] = v
    half = m // 2
    return buf[half] if m % 2 == 1 else 0.5 * (buf[half - 1] + buf[half])


@njit(nogil=True, cache=True)
def _median_of(values, lo, hi):
    return _median_small(values[lo:hi].copy(), hi - lo)


@njit(nogil=True, cache=True)
def _peak_at(peak, c):
    """The peak of column c, DN; 0 outside the image or the processed columns (NaN)."""
    if c < 0 or c >= peak.shape[0]:
        return 0.0
    v = peak[c]
    return v if v == v else 0.0


@njit(nogil=True, cache=True)
def _triangulate(u, v, fx, fy, cx, cy, n, offset, out):
    """Pixel ray x light plane in {C} (Eq. 2); False when parallel or behind the camera."""
    x = (u - cx) / fx
    y = (v - cy) / fy
    den = x * n[0] + y * n[1] + n[2]
    if abs(den) <= PARALLEL_COS:
        return False
    s = offset / den
    if not s > 0.0:
        return False
    out[0] = x * s
    out[1] = y * s
    out[2] = s
    return True


@njit(nogil=True, cache=True)
def _cumulative(mask):
    """(W + 1,) int64: the number of True in mask[:c] at c."""
    out = np.zeros(mask.shape[0] + 1, np.int64)
    for c in range(mask.shape[0]):
        out[c + 1] = out[c] + (1 if mask[c] else 0)
    return out


@njit(nogil=True, cache=True)
def _segments(cols, dark_cum, min_gap, max_bridge):
    """Split the valid columns where a gap is a drop-out or too wide to bridge: the first and
    last index (into cols) of each stretch of stripe."""
    nv = cols.shape[0]
    starts = np.empty(nv, np.int64)
    ends = np.empty(nv, np.int64)
    s = 0
    starts[0] = 0
    for k in range(nv - 1):
        c, c_next = cols[k], cols[k + 1]
        n_dark = dark_cum[c_next] - dark_cum[c + 1]
        if n_dark >= min_gap or c_next - c - 1 > max_bridge:
            ends[s] = k
            s += 1
            starts[s] = k + 1
    ends[s] = nv - 1
    return starts[: s + 1], ends[: s + 1]


@njit(nogil=True, cache=True)
def _remove_specks(valid, dark, min_gap, max_bridge, min_run):
    """Stretches of fewer than min_run valid columns between drop-outs become dark, in place
    (removing one can merge two gaps: a second pass settles it)."""
    for _ in range(2):
        cols = np.nonzero(valid)[0]
        if cols.shape[0] == 0:
            return
        starts, ends = _segments(cols, _cumulative(dark), min_gap, max_bridge)
        removed = False
        for s in range(starts.shape[0]):
            if ends[s] - starts[s] + 1 < min_run:
                for k in range(starts[s], ends[s] + 1):
                    valid[cols[k]] = False
                    dark[cols[k]] = True
                removed = True
        if not removed:
            return


@njit(nogil=True, cache=True)
def _range_noise(cols, d, seg):
    """One point's range scatter, mm, robustly from second differences over three adjacent
    columns (a smooth surface's curvature is far below the noise there); NaN when too few."""
    nv = cols.shape[0]
    d2 = np.empty(max(nv, 1))
    n2 = 0
    for k in range(1, nv - 1):
        if cols[k] - cols[k - 1] == 1 and cols[k + 1] - cols[k] == 1 and seg[k - 1] == seg[k + 1]:
            d2[n2] = abs(d[k + 1] - 2.0 * d[k] + d[k - 1])
            n2 += 1
    if n2 < MIN_NOISE_SAMPLES:
        return math.nan
    return MAD_TO_SIGMA * np.median(d2[:n2].copy()) / math.sqrt(6.0)  # var(d2) = 6 var(d)


@njit(nogil=True, cache=True)
def _step_candidates(cols, vcol, d, seg, side_px, cand_threshold):
    """Jumps in range beyond the local slope: jump k joins points k and k+1 of one segment;
    the slope per column is the median of the jumps within side_px on both sides.

    Returns the residual jumps (mm) and which exceed cand_threshold."""
    nj = max(cols.shape[0] - 1, 0)
    resid = np.zeros(nj)
    cand = np.zeros(nj, np.bool_)
    window = np.empty(2 * side_px)
    # A jump between adjacent columns whose window holds no jump above cand_threshold / 2 is
    # no candidate whatever the median (|jump - slope| <= cand_threshold): the median is
    # skipped there, which is most of a frame.
    big_cum = np.zeros(nj + 1, np.int64)
    for k in range(nj):
        big_cum[k + 1] = big_cum[k] + (1 if abs(d[k + 1] - d[k]) > 0.5 * cand_threshold else 0)
    for k in range(nj):
        if seg[k] != seg[k + 1]:
            continue
        if (cols[k + 1] - cols[k] == 1
                and big_cum[min(k + side_px + 1, nj)] == big_cum[max(k - side_px, 0)]):
            continue
        m = 0
        for j in range(max(k - side_px, 0), min(k + side_px + 1, nj)):
            if j != k and seg[j] == seg[k] and seg[j + 1] == seg[k]:
                window[m] = (d[j + 1] - d[j]) / (vcol[j + 1] - vcol[j])
                m += 1
        slope = _median_small(window, m) if m > 0 else 0.0
        resid[k] = d[k + 1] - d[k] - slope * (vcol[k + 1] - vcol[k])
        cand[k] = abs(resid[k]) > cand_threshold
    return resid, cand


@njit(nogil=True, cache=True)
def _dropout(sign, k_lo, k_hi, k_other, o_lo, o_hi, cols, a, d, pts, vcol, vrow, vpeak, peak,
             valid, dark, side_px, threshold, noise, curl, bend, min_contrast, keep_far,
             background, fx, fy, cx, cy, n, offset, out_pc, out):
    """The drop-out edge at one end of a stripe (sign -1: its first column, +1: its last),
    into out_pc (point in {C}) and out (u, v, size, level, then :func:`_stripe_end`'s
    fields). False when there is none: the far side of a gap across a range step, a side too
    faint for its gap, or a ray that misses the sheet.

    k_other is the other side's end point (-1: the stripe does not come back), o_lo..o_hi-1
    the other side's points next to the gap."""
    k_end = k_lo if sign < 0 else k_hi
    c_end = cols[k_end]
    # this side: its side_px points next to the gap
    if sign < 0:
        lo, hi = k_lo, min(k_lo + side_px, k_hi + 1)
    else:
        lo, hi = max(k_hi - side_px + 1, k_lo), k_hi + 1
    if _curls(vrow, vcol, k_end, sign, lo, hi, curl):
        return False  # the stripe fades on a surface curving away: no edge there
    size = math.nan
    if k_other >= 0:
        size = math.sqrt((pts[k_other, 0] - pts[k_end, 0]) ** 2
                         + (pts[k_other, 1] - pts[k_end, 1]) ** 2
                         + (pts[k_other, 2] - pts[k_end, 2]) ** 2)
        # "discontinuities are evaluated by range": both sides at the middle of the gap
        xm, ym, sl, sxx = _fit_line(a, d, lo, hi)
        oxm, oym, osl, osxx = _fit_line(a, d, o_lo, o_hi)
        a_mid = 0.5 * (a[k_other] + a[k_end])
        rise = (ym + sl * (a_mid - xm)) - (oym + osl * (a_mid - oxm))
        # each side's line extrapolated across the gap: its error grows with the lever arm
        lever = (1.0 / (hi - lo) + ((a_mid - xm) ** 2 / sxx if sxx > 0.0 else 0.0)
                 + 1.0 / (o_hi - o_lo) + ((a_mid - oxm) ** 2 / osxx if osxx > 0.0 else 0.0))
        spread = noise * math.sqrt(lever)
        if rise > threshold + FAR_SIDE_SIGMAS * spread and not keep_far:
            return False  # this side is farther: the boundary of a shadow or an occlusion
    # the side's level: at the top of the edge's falling flank (a blurred edge falls over a
    # few columns), found walking in while the stripe keeps brightening; a dimmer face next to
    # the gap (a chamfer) keeps its own level
    k_top = k_end
    bent = False
    while lo <= k_top - sign < hi and vpeak[k_top - sign] > (1.0 + FLANK_RISE) * vpeak[k_top]:
        if _bends(vrow, vcol, k_top - sign, sign, lo, hi, k_end, bend):
            bent = True
            break
        k_top -= sign
    if bent:  # the level of the face the edge is on: from its first column to the end
        if sign < 0:
            level = _median_of(vpeak, max(k_top - LEVEL_PX + 1, k_end), k_top + 1)
        else:
            level = _median_of(vpeak, k_top, min(k_top + LEVEL_PX, k_end + 1))
    elif sign < 0:
        level = _median_of(vpeak, k_top, min(k_top + LEVEL_PX, k_hi + 1))
    else:
        level = _median_of(vpeak, max(k_top - LEVEL_PX + 1, k_lo), k_top + 1)
    # the gap's level: its first columns
    gap = np.empty(side_px)
    m = 0
    c = c_end + sign
    while c >= 0 and c < peak.shape[0] and m < side_px and dark[c]:
        if peak[c] == peak[c]:
            gap[m] = peak[c]
            m += 1
        c += sign
    gap_level = _median_small(gap, m) if m > 0 else 0.0
    if level < min_contrast * gap_level:
        return False  # a faint stripe fading into the noise: no step to halve
    half = 0.5 * (level + gap_level)  # half the relative step
    # the outermost column at or above half, walking in from the end; then interpolate
    c_in = c_end
    steps = 0
    while _peak_at(peak, c_in) < half and steps < hi - lo - 1:
        c_in -= sign
        steps += 1
    p_in = _peak_at(peak, c_in)
    p_out = _peak_at(peak, c_in + sign)
    f = (p_in - half) / (p_in - p_out) if p_in > p_out else 0.5
    u = c_in + sign * min(max(f, 0.0), 1.0)
    cxm, cym, csl, _ = _fit_line(vcol, vrow, lo, hi)  # the side's rows, extrapolated
    v = cym + csl * (u - cxm)
    if not _triangulate(u, v, fx, fy, cx, cy, n, offset, out_pc):
        return False
    out[0], out[1], out[2], out[3] = u, v, size, level
    _stripe_end(k_end, sign, lo, hi, c_end, u, v, csl, vcol, vrow, vpeak, background, bent, fx,
                fy, cx, cy, n, offset, out_pc, out)
    return True


@njit(nogil=True, cache=True)
def _stripe_end(k_end, sign, lo, hi, c_end, u, v, row_slope, vcol, vrow, vpeak, background,
                bent, fx, fy, cx, cy, n, offset, point, out):
    """What :func:`chamfered_dropouts` needs of a drop-out, into out[4:12]: its last two lit
    columns' peaks over the background as fractions of the face's (the median of the
    END_FACE_PX columns from END_FACE_FROM in), the distance from the point to the outer
    side of its last lit column (px), the end column's row off the line of the face's
    columns 2 to 5 in (px), whether its flank walk found a chamfer (`bent`: it is placed by
    that chamfer's own level): ``EdgePoints.stripe_end``; then how the point moves in {C}
    per px outward along the side's rows (mm; by the ideal pinhole, as the kernel's rays):
    ``EdgePoints.per_px_b`` once rotated. No levels where the side is
    too short, broken by a bridged gap, or no brighter than the background where its face
    should be."""
    for i in range(4, 12):
        out[i] = math.nan
    out[6] = (c_end + 0.5 * sign - u) * sign
    out[8] = 1.0 if bent else 0.0
    k_in = k_end - (END_FACE_FROM + END_FACE_PX - 1) * sign
    if (lo <= k_in < hi
            and abs(vcol[k_end] - vcol[k_in]) == END_FACE_FROM + END_FACE_PX - 1):
        f_lo = min(k_in, k_end - END_FACE_FROM * sign)
        face = _median_of(vpeak, f_lo, f_lo + END_FACE_PX) - background
        if face > 0.0:
            out[4] = (vpeak[k_end] - background) / face
            out[5] = (vpeak[k_end - sign] - background) / face
            # the face's rows from columns 2 to 5 in: three columns' line, extrapolated,
            # turned idler_riser's blurred ends 0.5-1.6 px off; a chamfer reaching into the
            # second column shrinks the offset, which only makes the test stricter
            g_lo = min(k_in, k_end - 2 * sign)
            fxm, fym, fsl, _ = _fit_line(vcol, vrow, g_lo, g_lo + END_FACE_PX + 1)
            out[7] = vrow[k_end] - (fym + fsl * (vcol[k_end] - fxm))
    moved = out[9:12]  # a view: no allocation per drop-out
    if _triangulate(u + sign, v + sign * row_slope, fx, fy, cx, cy, n, offset, moved):
        for i in range(3):
            moved[i] -= point[i]


@njit(nogil=True, cache=True)
def _bends(vrow, vcol, k, sign, lo, hi, k_end, bend):
    """Whether the stripe's rows turn at point k (toward the gap: sign): another face begins
    there, not a blurred flank of the same one. A 45-degree chamfer at a level face's rim
    moved the rows 0.4 to 0.6 px per column against under 0.1 px on the face, and its stripe
    faded toward the gap; walked over, it took the face's level and the edge landed a column
    short of its end (0.2 mm). The end point k_end is lit in part and its row is off by up
    to about 0.2 px: no turn is judged on it."""
    if not (lo <= k - sign < hi and lo <= k + sign < hi) or k + sign == k_end:
        return False
    if abs(vcol[k + sign] - vcol[k - sign]) != 2.0:
        return False  # across a bridged gap: no neighbouring columns to compare
    inner = vrow[k] - vrow[k - sign]
    outer = vrow[k + sign] - vrow[k]
    return abs(outer - inner) > bend


@njit(nogil=True, cache=True)
def _curls(vrow, vcol, k_end, sign, lo, hi, curl):
    """Whether a side's rows turn steadily over the row steps before its end point k_end
    (the side runs toward the gap or the wall along sign; lo..hi-1 are its points, or for a
    step its whole stretch of stripe), and their last step runs the way they turn: a surface
    past its crest, curving away until the stripe is lost on it, whose end is no edge of the
    part. Rows still rising into a crest at the end are not judged curled (the crest's end of
    a short stretch is an edge); a stretch with its crest in the middle has no edge at
    either end (a cylinder seen across its top). Up to CURL_MAX_TURNS turns are judged (the
    6 points up to k_end); a shorter side over the turns it has, at least CURL_MIN_TURNS. The
    end point itself is left out: lit in part, its row is off by up to about 0.2 px."""
    if sign > 0:
        before = k_end - lo
    else:
        before = hi - 1 - k_end
    turns = min(CURL_MAX_TURNS, before - 2)
    if turns < CURL_MIN_TURNS:
        return False
    far = k_end - (turns + 2) * sign
    if abs(vcol[k_end - sign] - vcol[far]) != turns + 1:
        return False  # across a bridged gap: no neighbouring columns to compare
    t0 = vrow[k_end - sign] - vrow[k_end - 2 * sign]
    t_far = vrow[far + sign] - vrow[far]
    total = t0 - t_far
    if abs(total) < curl:
        return False
    if t0 * total <= 0.0:
        return False  # still rising into a crest at the end: not a surface turning away
    for j in range(1, turns + 1):
        turn = ((vrow[k_end - j * sign] - vrow[k_end - (j + 1) * sign])
                - (vrow[k_end - (j + 1) * sign] - vrow[k_end - (j + 2) * sign]))
        if turn * total <= 0.0 or abs(turn) > CURL_SHARE * abs(total):
            return False
    return True


@njit(nogil=True, cache=True)
def _near_end(near, toward, nlo, nhi, cols, vpeak, double, peak):
    """Column (sub-pixel) where the near side's stripe ends at a step within one column.

    The pixel column holding the wall is lit in part by each side's stripe (in proportion to
    the share of the pixel each surface covers); the near side's stripe is taken to end where
    its intensity falls to half its level, as a drop-out's: between its last column (bright
    in part when the wall lies within it) and the next one. The next column, when it holds
    the far side's stripe alone, holds too little of the near side's to show as a second peak
    (a share below ``DOUBLE_PEAK_RATIO`` of the far one's), and when it is dark (the wall or
    its shadow) it holds too little to pass the threshold: none is assumed. When it holds two
    stripes, the wall lies within it: rejected as a double (``double`` 1), whose two parts
    the extraction does not report, it is taken as half lit by each; measured on one of its
    two peaks (``double`` 2: the far side's, brighter or continuing its row), the near side's
    share is taken as ``DOUBLE_SHARE`` of the column's peak."""
    # the near side's points up to its end (which may lie inside a ramp of jumps)
    nlo, nhi = min(nlo, near), max(nhi, near + 1)
    # the near side's level, from the top of its flank inward (as a drop-out side's)
    k_top = near
    while (nlo <= k_top - toward < nhi
           and vpeak[k_top - toward] > (1.0 + FLANK_RISE) * vpeak[k_top]):
        k_top -= toward
    if toward > 0:
        lo, hi = max(k_top - LEVEL_PX + 1, nlo), k_top + 1
    else:
        lo, hi = k_top, min(k_top + LEVEL_PX, nhi)
    level = _median_of(vpeak, lo, hi)
    half = 0.5 * level
    c_near = cols[near]
    c_next = c_near + toward
    share = 0.0
    if 0 <= c_next < double.shape[0] and double[c_next] == 1:
        share = half
    elif 0 <= c_next < double.shape[0] and double[c_next] == 2:
        share = min(level, DOUBLE_SHARE * _peak_at(peak, c_next))
    if vpeak[near] < half:
        c_in, p_in, p_out = c_near - toward, level, vpeak[near]
    elif share >= half:
        c_in, p_in, p_out = c_next, share, 0.0
    else:
        c_in, p_in, p_out = c_near, vpeak[near], share
    f = (p_in - half) / (p_in - p_out) if p_in > p_out else 0.5
    return float(c_in) + toward * min(max(f, 0.0), 1.0)


@njit(nogil=True, cache=True)
def _step(k0, k1, llo, rhi, k_lo, k_hi, cols, a, d, pts, vcol, vrow, vpeak, peak, double,
          threshold, curl, fx, fy, cx, cy, n, offset, e_a, e_d, out_pc, out):
    """The step edge of the jumps k0..k1 (points k0..k1+1) with its sides llo..k0 and
    k1+1..rhi, in the stretch of stripe k_lo..k_hi, into out_pc (point in {C}) and out (u, v,
    height, level, direction). False when the step is below threshold, has no clean
    half-height crossing, or its near side curves away up to the run (:func:`_curls`)."""
    lxm, lym, lsl, _ = _fit_line(a, d, llo, k0 + 1)
    rxm, rym, rsl, _ = _fit_line(a, d, k1 + 1, rhi + 1)
    a_b = 0.5 * (a[k0] + a[k1 + 1])
    h = (rym + rsl * (a_b - rxm)) - (lym + lsl * (a_b - lxm))  # the relative step height
    if abs(h) < threshold:
        return False
    # where the profile crosses the mid-line of the two sides: half the relative step height
    p = -1
    e_p = 0.0
    e_q = 0.0
    for j in range(k0, k1 + 1):
        mid_p = 0.5 * ((lym + lsl * (a[j] - lxm)) + (rym + rsl * (a[j] - rxm)))
        mid_q = 0.5 * ((lym + lsl * (a[j + 1] - lxm)) + (rym + rsl * (a[j + 1] - rxm)))
        e_p = (d[j] - mid_p) * h
        e_q = (d[j + 1] - mid_q) * h
        if e_p <= 0.0 < e_q:
            p = j
            break
    if p < 0:
        return False  # noise larger than the step
    q = p + 1
    if cols[q] - cols[p] == 1 and abs(d[q] - d[p]) <= RESOLVED_STEP_FRACTION * abs(h):
        # resolved over adjacent columns: interpolate on the profile
        f = -e_p / (e_q - e_p)
        for i in range(3):
            out_pc[i] = pts[p, i] + f * (pts[q, i] - pts[p, i])
        u = vcol[p] + f
        v = vrow[p] + f * (vrow[q] - vrow[p])
    else:
        # the wall stands where the near side's stripe ends: at half its level
        if h > 0:
            near, toward, nlo, nhi, flo, fhi = p, 1, llo, k0 + 1, k1 + 1, rhi + 1
        else:
            near, toward, nlo, nhi, flo, fhi = q, -1, k1 + 1, rhi + 1, llo, k0 + 1
        if (_curls(vrow, vcol, k0, 1, k_lo, k0 + 1, curl) if h > 0
                else _curls(vrow, vcol, k1 + 1, -1, k1 + 1, k_hi + 1, curl)):
            return False  # the near side's stripe ends on a surface curving away, not at a rim
        u = _near_end(near, toward, nlo, nhi, cols, vpeak, double, peak)
        cxm, cym, csl, _ = _fit_line(vcol, vrow, nlo, nhi)
        v = cym + csl * (u - cxm) if nlo <= near < nhi else vrow[near] + csl * (u - vcol[near])
        if not _triangulate(u, v, fx, fy, cx, cy, n, offset, out_pc):
            return False
        a_n = out_pc[0] * e_a[0] + out_pc[1] * e_a[1] + out_pc[2] * e_a[2]
        d_n = out_pc[0] * e_d[0] + out_pc[1] * e_d[1] + out_pc[2] * e_d[2]
        mid = 0.5 * ((lym + lsl * (a_n - lxm)) + (rym + rsl * (a_n - rxm)))
        for i in range(3):
            out_pc[i] += (mid - d_n) * e_d[i]  # up the wall to half the step
        # in the image: half way between the two sides' rows at the wall's column
        fxm, fym, fsl, _ = _fit_line(vcol, vrow, flo, fhi)
        v = 0.5 * (v + fym + fsl * (u - fxm))
    out[0], out[1], out[2] = u, v, abs(h)
    out[3] = min(_median_of(vpeak, llo, k0 + 1), _median_of(vpeak, k1 + 1, rhi + 1))
    out[4] = 1.0 if h > 0 else -1.0
    return True


@njit(nogil=True, cache=True)
def _edges_kernel(row, peak, valid_in, dark_in, double, fx, fy, cx, cy, n, offset, e_a, e_d,
                  min_gap, max_bridge, min_run, side_px, min_step, noise_factor, max_ramp,
                  min_contrast, keep_far, background):
    w = row.shape[0]
    valid = valid_in.copy()
    dark = dark_in.copy()
    pc = np.empty(3)
    for c in range(w):  # a ray that misses the sheet (or a NaN row) is no stripe
        if valid[c] and not (row[c] == row[c]
                             and _triangulate(float(c), row[c], fx, fy, cx, cy, n, offset, pc)):
            valid[c] = False
    _remove_specks(valid, dark, min_gap, max_bridge, min_run)
    dark_cum = _cumulative(dark)
    cols = np.nonzero(valid)[0]
    nv = cols.shape[0]
    m_max = 3 * nv + 2  # two drop-outs per stretch of stripe, at most one step per jump
    out_px = np.empty((m_max, 2))
    out_pc = np.empty((m_max, 3))
    out_kind = np.empty(m_max, np.uint8)
    out_size = np.empty(m_max)
    out_peak = np.empty(m_max)
    out_dir = np.empty(m_max, np.int8)
    out_end = np.full((m_max, 8), np.nan)
    if nv == 0:
        return (out_px[:0], out_pc[:0], out_kind[:0], out_size[:0], out_peak[:0], out_dir[:0],
                out_end[:0], math.nan)
    starts, ends = _segments(cols, dark_cum, min_gap, max_bridge)
    n_seg = starts.shape[0]
    # the profile in the sheet: points in {C}, in-plane (a, d), columns, rows and peaks
    pts = np.empty((nv, 3))
    a = np.empty(nv)
    d = np.empty(nv)
    vrow = np.empty(nv)
    vcol = np.empty(nv)
    vpeak = np.empty(nv)
    for k in range(nv):
        c = cols[k]
        _triangulate(float(c), row[c], fx, fy, cx, cy, n, offset, pc)
        pts[k, 0], pts[k, 1], pts[k, 2] = pc[0], pc[1], pc[2]
        a[k] = pc[0] * e_a[0] + pc[1] * e_a[1] + pc[2] * e_a[2]
        d[k] = pc[0] * e_d[0] + pc[1] * e_d[1] + pc[2] * e_d[2]
        vrow[k] = row[c]
        vcol[k] = float(c)
        vpeak[k] = _peak_at(peak, c)
    seg = np.empty(nv, np.int64)
    for s in range(n_seg):
        seg[starts[s]:ends[s] + 1] = s
    noise = _range_noise(cols, d, seg)
    scatter = noise * math.sqrt(2.0) if noise == noise else 0.0  # point to point
    threshold = max(min_step, noise_factor * scatter)
    point_noise = noise if noise == noise else 0.0
    row_noise = _range_noise(cols, vrow, seg)  # the same estimate, on the rows (px)
    curl, bend = CURL_PX, ROW_BEND_PX
    if row_noise == row_noise:
        curl = max(CURL_PX, CURL_NOISE_FACTOR * row_noise)
        bend = max(ROW_BEND_PX, BEND_NOISE_FACTOR * math.sqrt(6.0) * row_noise)
    resid, cand = _step_candidates(cols, vcol, d, seg, side_px,
                                   max(noise_factor * scatter, min_step / max_ramp))
    res = np.empty(12)
    count = 0
    for s in range(n_seg):
        k_lo, k_hi = starts[s], ends[s]
        # -- drop-outs: the ends of the stretch, where a gap of min_gap dark columns begins
        for sign in (-1, 1):
            c_next = cols[k_lo] - 1 if sign < 0 else cols[k_hi] + 1
            if c_next < 0 or c_next >= w or not dark[c_next]:
                continue  # no gap, or one of columns that say nothing (the view's border)
            if sign < 0:
                k_other = k_lo - 1 if s > 0 else -1
                g_lo, g_hi = (cols[k_other] + 1 if k_other >= 0 else 0), cols[k_lo]
                o_lo = max(k_other - side_px + 1, starts[s - 1]) if s > 0 else 0
                o_hi = k_other + 1
            else:
                k_other = k_hi + 1 if s + 1 < n_seg else -1
                g_lo, g_hi = cols[k_hi] + 1, (cols[k_other] if k_other >= 0 else w)
                o_lo = k_other
                o_hi = min(k_other + side_px, ends[s + 1] + 1) if s + 1 < n_seg else 0
            if dark_cum[g_hi] - dark_cum[g_lo] < min_gap:
                continue  # "drop-outs are evaluated by size"
            if _dropout(sign, k_lo, k_hi, k_other, o_lo, o_hi, cols, a, d, pts, vcol, vrow,
                        vpeak, peak, valid, dark, side_px, threshold, point_noise, curl, bend,
                        min_contrast, keep_far, background, fx, fy, cx, cy, n, offset, pc, res):
                out_px[count, 0], out_px[count, 1] = res[0], res[1]
                out_pc[count, :] = pc
                out_kind[count] = 0
                out_size[count] = res[2]
                out_peak[count] = res[3]
                out_dir[count] = sign
                out_end[count, :] = res[4:12]
                count += 1
        # -- steps: runs of up to max_ramp candidate jumps of one sign
        k = k_lo
        while k < k_hi:
            if not cand[k]:
                k += 1
                continue
            k0 = k
            while k + 1 < k_hi and cand[k + 1] and (resid[k + 1] > 0) == (resid[k0] > 0):
                k += 1
            k1 = k
            k += 1
            if k1 - k0 + 1 > max_ramp:
                continue  # a sloped stretch of surface, not a step
            # the sides: up to side_px points beyond the run, short of other candidates
            llo = k0
            while llo > k_lo and k0 - llo + 1 < side_px and not cand[llo - 1]:
                llo -= 1
            rhi = k1 + 1
            while rhi < k_hi and rhi - k1 < side_px and not cand[rhi]:
                rhi += 1
            if k0 - llo + 1 < min_run or rhi - k1 < min_run:
                continue  # a step needs surface on both sides (a chamfer into a drop-out has not)
            cut_short = k0 - llo + 1 < side_px or rhi - k1 < side_px
            if _step(k0, k1, llo, rhi, k_lo, k_hi, cols, a, d, pts, vcol, vrow, vpeak, peak,
                     double, threshold, curl, fx, fy, cx, cy, n, offset, e_a, e_d, pc,
                     res) and not (
                         cut_short and res[2] < SHORT_SIDE_STEP_FACTOR * threshold):
                out_px[count, 0], out_px[count, 1] = res[0], res[1]
                out_pc[count, :] = pc
                out_kind[count] = 1
                out_size[count] = res[2]
                out_peak[count] = res[3]
                out_dir[count] = 1 if res[4] > 0 else -1
                count += 1
    return (out_px[:count].copy(), out_pc[:count].copy(), out_kind[:count].copy(),
            out_size[:count].copy(), out_peak[:count].copy(), out_dir[:count].copy(),
            out_end[:count].copy(), noise)


# ---------------------------------------------------------------------------------------------
# Per scan: drop-outs that are occlusions


def occluded_dropouts(points_t, across_t, sensors_t, cloud_t, *, probe_mm: float = 0.5,
                      radius_mm: float = 1.0, clearance_mm: float = 2.0) -> np.ndarray:
    """Drop-outs where the stripe vanished behind another part of the part, not at an edge.

    A profile cannot tell a rim from the boundary of an occlusion cast by a feature outside
    the sheet (a boss in front of the sheet hides the surface behind it from the camera,
    which views the sheet at an angle): both look like a gap between stripe ends at one
    range. The scan can: the surface just past a true rim is empty, so the camera's line of
    sight to a probe point ``probe_mm`` past the edge (in the sheet, into the gap) crosses
    nothing; past an occlusion's boundary that line of sight runs through the occluder, whose
    surface facing the camera other profiles have measured. A drop-out is occluded when some
    cloud point lies within ``radius_mm`` of that line of sight, farther than
    ``clearance_mm`` from the probe (the edge's own surface lies near its start).

    Costs about 0.05 ms per drop-out with a 30 k-point cloud (one k-d tree query per
    ``radius_mm`` along each line of sight).

    Parameters
    ----------
    points_t : (M, 3) float
        Drop-out edge points in {T}, mm.
    across_t : (M, 3) float
        Unit vectors from each point into its gap, in {T} (``EdgePoints.across_b`` rotated).
    sensors_t : (M, 3) float
        The camera centre in {T} when each point's frame was taken, mm
        (``Scan.sensor_positions_t`` of its frame).
    cloud_t : (N, 3) float
        The scan's cloud in {T}, mm.
    probe_mm : float
    radius_mm : float
        Must exceed half the spacing of the profiles (1.2 mm at 200 mm/s and 162 fps), so
        that a line of sight through a measured surface passes near one of its points.
    clearance_mm : float

    Returns
    -------
    (M,) bool
        True where the drop-out is the boundary of an occlusion.
    """
    from scipy.spatial import cKDTree  # scipy only for this scan-level check

    points = _points3(points_t, "points_t")
    across = _points3(across_t, "across_t")
    sensors = _points3(sensors_t, "sensors_t")
    cloud = _points3(cloud_t, "cloud_t")
    if across.shape != points.shape or sensors.shape != points.shape:
        raise ValueError(f"`across_t` and `sensors_t` must be {points.shape} like `points_t`, "
                         f"got {across.shape} and {sensors.shape}")
    out = np.zeros(len(points), dtype=bool)
    if len(points) == 0 or len(cloud) == 0:
        return out
    lo, hi = cloud.min(axis=0) - radius_mm, cloud.max(axis=0) + radius_mm
    tree = cKDTree(cloud)
    probes = points + probe_mm * across
    sight = sensors - probes
    length = np.sqrt(np.einsum("ij,ij->i", sight, sight))
    sight /= length[:, None]
    # the line of sight leaves the cloud's bounding box after t_exit
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - probes) / sight
        t2 = (hi - probes) / sight
    t_far = np.nan_to_num(np.maximum(t1, t2), nan=np.inf, posinf=np.inf, neginf=-np.inf)
    t_exit = t_far.min(axis=1)
    t_exit = np.minimum(t_exit, length)
    for i in range(len(points)):
        if not t_exit[i] > clearance_mm:
            continue
        t = np.arange(clearance_mm, t_exit[i] + radius_mm, radius_mm)
        samples = probes[i] + t[:, None] * sight[i]
        dist, _ = tree.query(samples, distance_upper_bound=radius_mm)
        out[i] = bool(np.isfinite(dist).any())
    return out


#: A chain's face next to the gap is a chamfer when its fitted level is below this fraction
#: of the face further in.
CHAMFER_MAX_LEVEL = 0.85
#: Fewest drop-outs along one edge to fit its chamfer by.
CHAMFER_MIN_POINTS = 6
#: A chamfer must explain its chain's levels better than a sharp edge by this much per
#: profile (mean squared residual, squared fractions of the face's level: 0.07 of it RMS).
#: An edge the profiles cross at one phase fits a sharp edge as well (the chamfer's level
#: and the lit fraction cannot be told apart): nothing is moved then. Noise alone gained
#: at most 0.002 on 800 synthetic sharp chains (6-30 profiles, 0.03-0.05 of level noise,
#: the phase varying or fixed); ADIS16480's chamfer chains gained 0.011 to 0.076.
CHAMFER_MIN_GAIN = 0.005
#: Drop-outs along one edge: within this many profiles of each other, their directions into
#: the gap within CHAIN_DEG, and within CHAIN_SPACINGS profile spacings (at least
#: CHAIN_MIN_MM) of each other.
CHAIN_FRAMES = 3
CHAIN_DEG = 30.0
CHAIN_SPACINGS = 2.5
CHAIN_MIN_MM = 2.0
_CHAMFER_LEVELS = np.linspace(0.2, 1.0, 81)
_CHAMFER_WIDTHS_PX = np.linspace(1.0, 2.0, 41)


def chamfered_dropouts(points_t, across_t, frame_ids, stripe_end, per_px_t, spacing_mm):
    """Drop-outs of a chamfered outline, placed at the outline.

    A chamfer between one and two columns wide (ADIS16480's 0.2 mm, 1.25 px in the
    reference cell) lights the stripe's last column or two at a level of its own, below the
    face's: the half-level crossing of the face's level falls on the chamfer, about 0.4 px
    inside the outline. One profile cannot tell the chamfer's width and level from where the
    outline lies in its last column. An edge's profiles can: along it the chamfer keeps its
    width ``w`` (px) and level ``c`` (of the face's), while the outline's place in the last
    lit column, the fraction ``f`` of it lit, changes from profile to profile. Pixels
    integrate the light they receive, so the last column holds ``c f`` of the face's level,
    and the one before ``c`` when the chamfer covers it, or ``c`` on its chamfered share
    ``w - f`` and the face's level on the rest (``"a pixel column holding the wall is lit
    in part by the near surface, in proportion to the share of the pixel it covers"``, as
    at steps). ``c`` and ``w`` are fitted to the chain's levels by least squares (a grid:
    ``c`` from 0.2 to 1, ``w`` from 1 to 2 px), each profile's ``f`` with them in closed
    form. Where ``c`` is below ``CHAMFER_MAX_LEVEL``, explains the levels better than a
    sharp edge by ``CHAMFER_MIN_GAIN``, and the chain's last columns lie off
    their faces' lines by ``ROW_BEND_PX`` or more (median: a face turned against the one
    inward puts its stripe on a line of its own, as :func:`_bends` judges a wider chamfer;
    one partly lit column's row is too noisy to judge alone), its points move to the
    outline, ``1 - f`` px in from the outer side of their last lit column, but for those
    whose profile found the chamfer's own level (``stripe_end``'s last field), which the
    half-level crossing of that level places already. Elsewhere the
    half-level placement stands: a sharp edge's last column holds the face's level times
    ``f``, a blurred edge dims over a few columns without turning its rows, and a chamfer
    two columns wide or more has been placed by its own level in the profile.

    ADIS16480's 16 outline chains in the bench's 8 scans fitted ``c`` 0.42 to 0.79 with their
    rows 0.31 to 0.50 px off; their points moved from 26-75 um RMS to 13-35 um. Costs 1.5 ms
    for a scan's 28 drop-outs, 6 ms for 220 (bench pose's scans, 2 cores); memory, one
    (widths, points) array at a time.

    Parameters
    ----------
    points_t : (M, 3) float
        Drop-out points in {T}, mm.
    across_t : (M, 3) float
        Unit vectors from each point into its gap, in {T}.
    frame_ids : (M,) int
        The profile of each point.
    stripe_end : (M, 5) float
        ``EdgePoints.stripe_end`` of each point.
    per_px_t : (M, 3) float
        ``EdgePoints.per_px_b`` of each point, rotated into {T}.
    spacing_mm : float
        The profiles' spacing along the pass, mm (NaN: CHAIN_MIN_MM is the reach).

    Returns
    -------
    points : (M, 3) float64
        The points, those of chamfered chains moved.
    chamfer_level : (M,) float64
        The fitted chamfer level of each point's chain (of the face's); NaN where no chain
        was fitted (fewer than CHAMFER_MIN_POINTS with levels).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    points = _points3(points_t, "points_t")
    across = _points3(across_t, "across_t")
    per_px = _points3(per_px_t, "per_px_t")
    end = np.asarray(stripe_end, dtype=np.float64)
    frames = np.asarray(frame_ids).reshape(-1).astype(np.int64)  # unsigned ids would wrap
    m = len(points)
    if across.shape != points.shape or per_px.shape != points.shape or end.shape != (m, 5) \
            or frames.shape != (m,):
        raise ValueError(f"`across_t`, `per_px_t` must be ({m}, 3), `stripe_end` ({m}, 5) and "
                         f"`frame_ids` ({m},), got {across.shape}, {per_px.shape}, "
                         f"{end.shape}, {frames.shape}")
    out = points.copy()
    level = np.full(m, np.nan)
    usable = np.nonzero(np.isfinite(end[:, :3]).all(axis=1) & np.isfinite(per_px).all(axis=1))[0]
    if len(usable) < CHAMFER_MIN_POINTS:
        return out, level
    reach = max(CHAIN_MIN_MM, CHAIN_SPACINGS * spacing_mm) if np.isfinite(spacing_mm) \
        else CHAIN_MIN_MM
    pairs = cKDTree(points[usable]).query_pairs(reach, output_type="ndarray")
    i, j = usable[pairs[:, 0]], usable[pairs[:, 1]]
    apart = np.abs(frames[i] - frames[j])
    linked = ((apart >= 1) & (apart <= CHAIN_FRAMES)
              & (np.einsum("ij,ij->i", across[i], across[j]) > math.cos(math.radians(CHAIN_DEG))))
    graph = coo_matrix((np.ones(int(linked.sum())), (i[linked], j[linked])), shape=(m, m))
    _, label = connected_components(graph, directed=False)
    for chain in np.unique(label[usable]):
        members = usable[label[usable] == chain]
        if len(members) < CHAMFER_MIN_POINTS:
            continue
        c, _, fill, gain = _fit_chamfer(end[members, 0], end[members, 1])
        level[members] = c
        if (c < CHAMFER_MAX_LEVEL and gain >= CHAMFER_MIN_GAIN
                and abs(np.median(end[members, 3])) >= ROW_BEND_PX):
            shift_px = np.where(end[members, 4] > 0, 0.0, end[members, 2] - (1.0 - fill))
            out[members] += shift_px[:, None] * per_px[members]
    return out, level


def _fit_chamfer(last, before):
    """The chamfer level c and width w (px) that best explain one chain's last two column
    levels (:func:`chamfered_dropouts`), each profile's lit fraction f of its last column
    under them, and how much better per profile than a sharp edge (c = 1) they explain
    them (mean squared residual, in squared fractions of the face's level): c, w, the
    fractions and the gain. Levels are tried from 1 down, a tie keeping the higher (a
    sharp edge crossed at one phase fits c = f, f = 1 as well as c = 1). Memory: one
    (widths, points) array at a time."""
    w = _CHAMFER_WIDTHS_PX[:, None]
    best_cost, best = np.inf, None
    sharp_cost = np.inf
    for c in _CHAMFER_LEVELS[::-1]:
        # f <= w - 1: the column before is all chamfer
        f_a = np.clip(last / c, 0.0, w - 1.0)
        cost_a = (last - c * f_a) ** 2 + (before - c) ** 2
        # f >= w - 1: the column before holds face on f - w + 1 of it
        rest = before - c + (1.0 - c) * (w - 1.0)
        f_b = np.clip((c * last + (1.0 - c) * rest) / (c**2 + (1.0 - c) ** 2), w - 1.0, 1.0)
        cost_b = (last - c * f_b) ** 2 + (before - c - (1.0 - c) * (f_b - w + 1.0)) ** 2
        first = cost_a <= cost_b
        totals = np.where(first, cost_a, cost_b).sum(axis=1)
        k = int(np.argmin(totals))
        if c == _CHAMFER_LEVELS[-1]:
            sharp_cost = float(totals[k])
        if totals[k] < best_cost:
            best_cost = float(totals[k])
            best = (float(c), float(_CHAMFER_WIDTHS_PX[k]), np.where(first[k], f_a[k], f_b[k]))
    c, width, fill = best
    return c, width, fill, (sharp_cost - best_cost) / len(last)


def _on_own_profile(points, frame_ids, cloud, cloud_frames, tree, k: int = 32):
    """Each point moved to the nearest cloud point of its own profile (among its `k` nearest
    cloud points; kept where none is)."""
    if len(frame_ids) != len(points):
        raise ValueError(f"`frame_ids` must be ({len(points)},), got {frame_ids.shape}")
    k = min(k, len(cloud))
    _, nearest = tree.query(points, k=k)
    nearest = nearest.reshape(len(points), k)
    same = cloud_frames[nearest] == frame_ids[:, None]
    first = np.argmax(same, axis=1)
    found = same[np.arange(len(points)), first]
    out = points.copy()
    out[found] = cloud[nearest[found, first[found]]]
    return out


def _points3(points, name: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"`{name}` must be (N, 3), got {arr.shape}")
    return arr


#: A surface turned closer than this to the light sheet (degrees between their normals) is
#: grazed by it: the sheet, some 0.1 mm thick, lights a band many times wider on it, and the
#: stripe there breaks into gaps and jumps that are no edge of the part.
GRAZING_DEG = 25.0
#: The grazing test's neighbourhood spans at least this many profile spacings.
LONE_PROFILE_REACH = 2.1


def grazing_edges(points_t, sheet_normals_t, cloud_t, cloud_frame_ids, spacing_mm: float, *,
                  frame_ids=None, radius_mm: float = 2.5, grazing_deg: float = GRAZING_DEG,
                  min_points: int = 8) -> np.ndarray:
    """Edge points on a surface the light sheet grazes.

    A profile alone cannot tell: the sheet cuts a wall turned a few degrees from it along a
    curve that looks like any other. The scan can. Where the cloud around the edge point
    holds two profiles or more, their plane's normal (principal axis of least spread) lies
    within ``grazing_deg`` of the sheet's. Where it holds the point's own profile only,
    although the profiles lie closer than half ``radius_mm`` apart, the surface climbs
    between them by more than about 60 degrees from level: the next profile landed out of
    reach, and the sheet grazes the surface as well. A wall tilted 7 degrees toward the
    camera (the demo block misplaced by a rotation) gave 16 % of its edge points more than
    0.5 mm from any edge of the part, all on the three profiles that cut that wall; 0.8 %
    with this filter.

    Parameters
    ----------
    points_t : (M, 3) float
        Edge points in {T}, mm.
    sheet_normals_t : (M, 3) float
        Unit normal of the light sheet in {T} at each point's frame.
    cloud_t : (N, 3) float
        The scan's cloud in {T}, mm.
    cloud_frame_ids : (N,) int
        The profile of each cloud point.
    spacing_mm : float
        The profiles' spacing along the pass (median): at more than half ``radius_mm``, a
        lone profile says nothing, and only the plane test applies.
    frame_ids : (M,) int, optional
        The profile of each edge point: its neighbourhood is then centred on the nearest
        cloud point of that profile. A step's point lies half the step's height off the
        surface (2.5 mm on a 5 mm step), where a neighbourhood about it reaches its own
        profile's points only and the test would take it for a grazed wall.
    radius_mm : float
        Neighbourhood of each edge point: about twice the profiles' spacing at the default
        pass (1.2 mm at 200 mm/s and 162 fps); widened to ``LONE_PROFILE_REACH`` spacings
        (up to twice itself) on a faster pass. A misplaced part's pass spaced its profiles
        1.28 mm apart: with the neighbourhood fixed, walls 7 degrees from the sheet kept
        edge points up to 0.5 mm off (idler_riser, 96 um RMS, now 54 um).
    grazing_deg : float
    min_points : int
        Fewer cloud points than this within the radius: nothing to judge by, the point is kept.

    Returns
    -------
    (M,) bool
        The edge points on a grazed surface.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points_t, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(sheet_normals_t, dtype=np.float64).reshape(-1, 3)
    cloud = np.asarray(cloud_t, dtype=np.float64).reshape(-1, 3)
    frames = np.asarray(cloud_frame_ids).reshape(-1)
    out = np.zeros(len(points), bool)
    if len(points) == 0 or len(cloud) < min_points:
        return out
    if np.isfinite(spacing_mm):
        # Reach a level surface's next profiles even on a fast pass: a lone profile then
        # means a surface climbing past 60 degrees, not one the pass left sparse.
        # (up to twice the radius: a wider neighbourhood would mix surfaces)
        radius_mm = max(radius_mm, min(LONE_PROFILE_REACH * spacing_mm, 2.0 * radius_mm))
    dense = np.isfinite(spacing_mm) and spacing_mm < radius_mm / 2
    cos_limit = math.cos(math.radians(grazing_deg))
    tree = cKDTree(cloud)
    if frame_ids is not None:
        points = _on_own_profile(points, np.asarray(frame_ids).reshape(-1), cloud, frames, tree)
    for i, near in enumerate(tree.query_ball_point(points, radius_mm)):
        if len(near) < min_points:
            continue
        if np.all(frames[near] == frames[near[0]]):
            out[i] = dense
            continue
        local = cloud[near] - cloud[near].mean(axis=0)
        _, axes = np.linalg.eigh(local.T @ local)
        out[i] = abs(float(axes[:, 0] @ normals[i])) > cos_limit
    return out
