"""Edge points along one profile against analytic profiles with known edges (paper section II).

A profile here is built in the reference cell's light plane: a surface line at range ``d``
(``scanner_core.edges.profile_axes``) is projected into the image, which gives each column's
exact stripe row; peaks and Reason codes are set per column as the stripe extraction would.
"""
import time
from dataclasses import dataclass

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.special import ndtr

from scanner_core.edges import (CHAMFER_MIN_POINTS, EdgeKind, EdgeParams, EdgePoints,
                                chamfered_dropouts, find_edges, grazing_edges, occluded_dropouts,
                                profile_axes)
from scanner_core.stripe.extractor import Reason

WIDTH = 1920
#: The direct view of the reference cell (columns processed by the stripe extraction).
DIRECT = (384, 1536)
#: Ranges of the near and far surfaces in the sheet, mm (about the demo part's underside).
NEAR_MM, FAR_MM = 420.0, 425.0
#: Stripe amplitude above the background and the background, DN (the reference image model).
PEAK_DN, BACKGROUND_DN = 200.0, 10.0
#: The largest background pixel of a 1200-row column: about 10 + 3 sigma of the read noise.
DARK_PEAK_DN = 19.0
#: Extraction threshold and the pipeline's minimum peak, DN.
THRESHOLD_DN, MIN_PEAK_DN = 20.0, 40.0
#: The brief's tolerance for a drop-out edge's sub-pixel column, px.
SUBPIXEL_TOL_PX = 0.1
#: A stripe ending inside a column without blur lights that column in proportion to the share
#: it covers, which places the end exactly (float32 peaks). Half the relative step interpolated
#: linearly between column centres was off by up to 0.086 px, 0.118 px with the background
#: under the partial column, and by the same amount on every end at one phase.
BOX_RAMP_TOL_PX = 0.002
#: A double stripe (stripe.DOUBLE_PEAK_RATIO = 0.3) in the column holding a step's wall: both
#: sides cover at least 0.3 / 1.3 of it, so the wall lies within 0.27 px of its centre.
DOUBLE_COLUMN_TOL_PX = 0.27
#: Noise-free geometry: float32 rows (6e-5 px) and the projective round trip, mm.
EXACT_MM = 1e-3
#: With 0.03 px row noise (the centre of gravity's), a line fit over 6 columns extrapolated half
#: a column: about 0.02 px, times about 0.4 mm of range per row px.
NOISY_MM = 0.03
#: Row noise of the stripe centre, px: the reference centroid's 0.026 px, and a bad stripe's.
ROW_NOISE_PX = (0.03, 0.1)


@dataclass(frozen=True)
class Profile:
    """StripeResult-like arrays of one synthetic frame."""

    row: np.ndarray
    peak: np.ndarray
    reason: np.ndarray

    background_dn: float = BACKGROUND_DN

    @property
    def valid(self) -> np.ndarray:
        return (self.reason == Reason.OK) & (self.peak >= MIN_PEAK_DN)


@pytest.fixture(scope="module")
def geometry(cell):
    cal = cell.calibration
    e_a, e_d = profile_axes(cal.camera, cal.light_plane_c)
    return cal.camera, cal.light_plane_c, e_a, e_d


def surface_at(geometry, columns, d):
    """Where each column's line of sight meets the sheet's line at range ``d``: (a, rows)."""
    cam, plane, e_a, e_d = geometry
    base = plane.normal * plane.offset + d * e_d  # in {C}
    k = (np.asarray(columns, dtype=np.float64) - cam.cx) / cam.fx
    a = (k * base[2] - base[0]) / (e_a[0] - k * e_a[2])  # (u - cx) Z = fx X, linear in a
    p = base + a[:, None] * e_a
    return a, cam.fy * p[:, 1] / p[:, 2] + cam.cy


def sheet_point_b(geometry, a, d):
    cam, plane, e_a, e_d = geometry
    return cam.to_base(plane.normal * plane.offset + a * e_a + d * e_d)[0]


def blank_profile():
    """Nothing in the direct view: every processed column dark, the mirror strips unprocessed."""
    row = np.full(WIDTH, np.nan)
    peak = np.full(WIDTH, np.nan)
    reason = np.full(WIDTH, Reason.NOT_PROCESSED, np.uint8)
    peak[DIRECT[0]:DIRECT[1]] = DARK_PEAK_DN
    reason[DIRECT[0]:DIRECT[1]] = Reason.NO_PEAK
    return row, peak, reason


def set_stripe(profile, columns, rows, peaks=None):
    row, peak, reason = profile
    columns = np.asarray(columns)
    peaks = np.full(len(columns), PEAK_DN + BACKGROUND_DN) if peaks is None else peaks
    lit = peaks > THRESHOLD_DN
    row[columns] = np.where(lit, rows, np.nan)
    peak[columns] = peaks
    reason[columns] = np.where(lit, Reason.OK, Reason.NO_PEAK)


def make(profile, rng=None, row_noise_px=0.0):
    row, peak, reason = (a.copy() for a in profile)
    if row_noise_px:
        row = row + rng.normal(0.0, row_noise_px, row.shape)
    return Profile(row.astype(np.float32), peak.astype(np.float32), reason)


def edges_of(geometry, profile, **kwargs):
    cam, plane, _, _ = geometry
    return find_edges(profile, profile.valid, cam, plane, **kwargs)


def blurred_edge_peaks(columns, edge_col, blur_px, lit_below):
    """Peak DN of columns near a stripe's end at ``edge_col``, blurred by a Gaussian PSF along
    the stripe (sigma ``blur_px``): half the stripe's level exactly at the edge."""
    z = (edge_col - columns) / blur_px if lit_below else (columns - edge_col) / blur_px
    return BACKGROUND_DN + PEAK_DN * ndtr(z)


# ---------------------------------------------------------------------------------------------
# Drop-outs


@pytest.mark.parametrize("blur_px", [0.7, 1.0, 1.5])
@pytest.mark.parametrize("phase", [0.0, 0.25, 0.5, 0.8])
def test_dropout_edges_at_half_intensity_within_a_tenth_of_a_pixel(geometry, blur_px, phase):
    """A gap of known sub-pixel ends: one drop-out edge per side, at the half-intensity column,
    its row on the side's line, its point on the surface there."""
    left_end, right_end = 800.0 + phase, 900.0 - phase / 2  # the stripe's ends, px
    cols = np.arange(600, 1100)
    a, rows = surface_at(geometry, cols, NEAR_MM)
    peaks = np.where(cols < 850, blurred_edge_peaks(cols, left_end, blur_px, True),
                     blurred_edge_peaks(cols, right_end, blur_px, False))
    profile = blank_profile()
    set_stripe(profile, cols, rows, peaks)
    edges = edges_of(geometry, make(profile))
    assert len(edges) == 4 and np.all(edges.kind == EdgeKind.DROPOUT)  # the stripe's ends too
    order = np.argsort(edges.pixel[:, 0])
    assert_allclose(edges.pixel[order, 0], [599.5, left_end, right_end, 1099.5],
                    atol=SUBPIXEL_TOL_PX)
    assert_allclose(edges.direction[order], [-1, 1, -1, 1])
    order = order[1:3]
    for i, end in zip(order, (left_end, right_end)):
        a_end, row_end = surface_at(geometry, [edges.pixel[i, 0]], NEAR_MM)
        assert_allclose(edges.pixel[i, 1], row_end[0], atol=1e-3)
        assert_allclose(edges.point_b[i], sheet_point_b(geometry, a_end[0], NEAR_MM),
                        atol=EXACT_MM)
    # the gap's width in the sheet: between the two stripe ends
    assert_allclose(edges.size_mm[order], edges.size_mm[order[0]])
    assert 0 < edges.size_mm[order[0]] < (right_end - left_end) * 0.2


@pytest.mark.parametrize("row_noise_px", ROW_NOISE_PX)
def test_blurred_dropout_with_row_noise(geometry, rng, row_noise_px):
    """Row noise on a blurred flank is no turn of the surface: the flank is still walked to
    its top (the turn needed grows with the profile's row scatter), and the ends stay within
    a tenth of a pixel."""
    left_end, right_end = 800.25, 812.6  # a hole's rims: the sides' ranges agree across it
    cols = np.arange(600, 1100)
    _, rows = surface_at(geometry, cols, NEAR_MM)
    peaks = np.where(cols < 806, blurred_edge_peaks(cols, left_end, 1.0, True),
                     blurred_edge_peaks(cols, right_end, 1.0, False))
    profile = blank_profile()
    set_stripe(profile, cols, rows, peaks)
    found = []
    for _ in range(40):
        edges = edges_of(geometry, make(profile, rng, row_noise_px))
        inner = np.sort(edges.pixel[(edges.pixel[:, 0] > 700) & (edges.pixel[:, 0] < 1000), 0])
        assert len(inner) == 2
        found.append(inner)
    assert_allclose(found, [[left_end, right_end]] * len(found), atol=SUBPIXEL_TOL_PX)

def test_wide_hole_with_row_noise_keeps_both_rims(geometry, rng):
    """A 100-column hole in one surface, rows noisy by 0.1 px: each side's line, extrapolated
    50 columns to the hole's middle, misses the other by its lever arm's error; only a far
    side beyond that error is a shadow's boundary. Taking the bare threshold, a quarter of the
    rims were lost as shadows; now a rim is lost only where noise this heavy passes for a
    curl (about 1 end in 800), and no edge is ever moved or doubled."""
    cols = np.r_[np.arange(600, 800), np.arange(900, 1100)]
    _, rows = surface_at(geometry, cols, NEAR_MM)
    profile = blank_profile()
    set_stripe(profile, cols, rows)
    ends = np.array([599.5, 799.5, 899.5, 1099.5])
    rims_found = 0
    trials = 200
    for _ in range(trials):
        found = edges_of(geometry, make(profile, rng, 0.1)).pixel[:, 0]
        nearest = np.abs(found[:, None] - ends)
        assert np.all(nearest.min(axis=1) < 0.2)  # every edge at one of the ends
        assert np.all(np.bincount(nearest.argmin(axis=1), minlength=4) <= 1)  # once at most
        rims_found += int(np.sum(nearest[:, 1:3].min(axis=0) < 0.2))
    assert rims_found >= 0.98 * 2 * trials


def test_dropout_of_a_point_sampled_edge_lies_half_way_between_columns(geometry):
    """A stripe that stops on the boundary between two columns at full intensity: half the
    relative step falls half way between them."""
    cols = np.arange(700, 1000)
    _, rows = surface_at(geometry, cols, NEAR_MM)
    profile = blank_profile()
    set_stripe(profile, cols, rows)
    edges = edges_of(geometry, make(profile))
    assert_allclose(np.sort(edges.pixel[:, 0]), [699.5, 999.5], atol=1e-6)
    assert np.all(np.isnan(edges.size_mm))  # the stripe does not come back within the view


@pytest.mark.parametrize("phase", [-0.45, -0.4, -0.3, -0.2, -0.1, 0.0, 0.1, 0.2, 0.3, 0.45])
def test_dropout_of_a_stripe_ending_inside_a_column(geometry, phase):
    """Each pixel integrates over its width: a stripe ending at ``c + phase`` lights column c
    in proportion to the part it covers (``0.5 + phase``), with no blur. That share places
    the end, at any phase: edges that the columns cross at one rate (parallel edges carried
    along the pass) keep their direction."""
    cols = np.arange(700, 1001)
    _, rows = surface_at(geometry, cols, NEAR_MM)
    left_end, right_end = 700.0 - phase, 1000.0 + phase
    coverage = np.ones(len(cols))
    coverage[[0, -1]] = 0.5 + phase
    profile = blank_profile()
    set_stripe(profile, cols, rows, BACKGROUND_DN + PEAK_DN * coverage)
    edges = edges_of(geometry, make(profile))
    assert len(edges) == 2 and np.all(edges.kind == EdgeKind.DROPOUT)
    assert_allclose(np.sort(edges.pixel[:, 0]), [left_end, right_end], atol=BOX_RAMP_TOL_PX)


def box_blurred_shares(columns, edge_col, blur_px, lit_below):
    """The lit share of each column (integrated over its width) of a stripe ending at
    ``edge_col``, blurred by a Gaussian PSF along the stripe (sigma ``blur_px``)."""
    def integral(t):  # of the normal CDF: t Phi(t) + phi(t)
        return t * ndtr(t) + np.exp(-0.5 * t * t) / np.sqrt(2.0 * np.pi)

    sign = 1.0 if lit_below else -1.0
    lo = sign * (edge_col - (np.asarray(columns) - 0.5 * sign)) / blur_px
    hi = sign * (edge_col - (np.asarray(columns) + 0.5 * sign)) / blur_px
    return (integral(lo) - integral(hi)) * blur_px


@pytest.mark.parametrize("blur_px", [0.3, 0.5, 1.0])
def test_dropout_of_a_slightly_blurred_stripe_ending_inside_a_column(geometry, blur_px):
    """Between a sharp end (its share placing it exactly) and a blurred one (placed at half
    the step): a little blur spreads the end over two or three columns, and every end, at
    any phase, stays within 0.06 px. Measured at 0.3, 0.5 and 1.0 px of blur: 0.048, 0.050
    and 0.016 px at most; half the relative step alone, 0.070, 0.043 and 0.016."""
    cols = np.arange(600, 1100)
    _, rows = surface_at(geometry, cols, NEAR_MM)
    found, truth = [], []
    for phase in np.linspace(-0.5, 0.5, 11)[:-1]:
        left_end, right_end = 800.0 + phase, 900.0 - phase / 2
        shares = np.where(cols < 850, box_blurred_shares(cols, left_end, blur_px, True),
                          box_blurred_shares(cols, right_end, blur_px, False))
        profile = blank_profile()
        set_stripe(profile, cols, rows, BACKGROUND_DN + PEAK_DN * shares)
        pixel = edges_of(geometry, make(profile)).pixel[:, 0]
        found.append(np.sort(pixel[(pixel > 700) & (pixel < 1000)]))
        truth.append([left_end, right_end])
    assert_allclose(found, truth, atol=0.06)


def test_stripe_cut_by_the_view_is_no_edge(geometry):
    """A stripe running into the border of the processed columns ends there, not at the part."""
    cols = np.arange(DIRECT[0], 1000)
    _, rows = surface_at(geometry, cols, NEAR_MM)
    profile = blank_profile()
    set_stripe(profile, cols, rows)
    edges = edges_of(geometry, make(profile))
    assert len(edges) == 1 and edges.pixel[0, 0] == pytest.approx(999.5)


def test_chamfer_at_the_outline_is_one_dropout_at_its_end(geometry):
    """A dimmer 45 degree chamfer over the last 4 columns before the gap: no step (no surface
    beyond it), and the drop-out at the chamfer's end, by the chamfer's own level."""
    cols = np.arange(800, 1004)
    d = NEAR_MM + np.clip(cols - 999, 0, None) * 0.16  # about a column's width per column
    rows = np.array([surface_at(geometry, [c], dd)[1][0] for c, dd in zip(cols, d)])
    peaks = np.where(cols > 999, BACKGROUND_DN + 0.65 * PEAK_DN, BACKGROUND_DN + PEAK_DN)
    profile = blank_profile()
    set_stripe(profile, cols, rows, peaks)
    edges = edges_of(geometry, make(profile))
    assert np.all(edges.kind == EdgeKind.DROPOUT)
    assert_allclose(np.sort(edges.pixel[:, 0]), [799.5, 1003.5], atol=1e-6)


@pytest.mark.parametrize("at_right", [True, False])
@pytest.mark.parametrize("chamfer_px", [2, 3])
def test_short_blurred_chamfer_keeps_its_own_level(geometry, chamfer_px, at_right):
    """A dimmer chamfer only a few columns wide, blurred with the face inward of it: the
    stripe brightens column by column from the gap up to the face, as a blurred flank of one
    face would. The rows turn where the chamfer begins, so the flank stops there and the
    drop-out is placed by the chamfer's level (walked up to the face's, the edge fell most of
    a pixel short of the chamfer's end). At either end of the stripe."""
    inward = np.arange(200)  # columns from the chamfer's end, inward
    level = np.where(inward < chamfer_px, 0.6, 1.0)
    depth = NEAR_MM + np.clip(chamfer_px - inward, 0, None) * 0.16
    blurred = np.convolve(np.r_[0.0, 0.0, level, 1.0], [0.25, 0.5, 0.25])[2:-2]  # gap, end, in
    end = 1000 if at_right else 800
    cols = end - inward if at_right else end + inward
    rows = np.array([surface_at(geometry, [c], dd)[1][0] for c, dd in zip(cols, depth)])
    profile = blank_profile()
    set_stripe(profile, cols, rows, BACKGROUND_DN + PEAK_DN * blurred[1:])
    _, peak, _ = profile
    peak[end + (1 if at_right else -1)] = BACKGROUND_DN + PEAK_DN * blurred[0]  # blur's tail
    edges = edges_of(geometry, make(profile))
    assert np.all(edges.kind == EdgeKind.DROPOUT)
    chamfer_end = end + (0.5 if at_right else -0.5)
    found = edges.pixel[np.argmin(np.abs(edges.pixel[:, 0] - chamfer_end)), 0]
    assert found == pytest.approx(chamfer_end, abs=0.1)


def chamfered_outline(geometry, wall, at_right, width_px=1.25, level=0.65, row_shift_px=0.4):
    """A stripe over columns 700..1000 that ends at the continuous column ``wall`` (a column
    c spans c - 0.5 .. c + 0.5) on its right or left, through a chamfer ``width_px`` wide lit
    at ``level`` of the face, its rows ``row_shift_px`` off the face's line in proportion to
    its light: the lit columns, rows and peaks, and each column's (of 650..1049) face and
    chamfer shares."""
    cols = np.arange(650, 1050)
    inward = wall - cols if at_right else cols - wall  # each column's centre, from the wall
    lo, hi = inward - 0.5, inward + 0.5
    chamfer = np.clip(np.minimum(hi, width_px) - np.maximum(lo, 0.0), 0.0, 1.0)
    face = np.clip(hi - np.maximum(lo, width_px), 0.0, 1.0)
    face[(cols < 700) if at_right else (cols > 1000)] = 0.0  # the stripe's other end
    light = face + level * chamfer
    _, rows = surface_at(geometry, cols, NEAR_MM)
    rows = rows + row_shift_px * np.divide(level * chamfer, light, out=np.zeros_like(light),
                                           where=light > 0)
    lit = light > 0.02
    return cols[lit], rows[lit], BACKGROUND_DN + PEAK_DN * light[lit], face, chamfer


@pytest.mark.parametrize("at_right", [True, False])
@pytest.mark.parametrize("phase", [0.1, 0.3, 0.6, 0.9])
def test_stripe_end_of_a_subpixel_chamfer(geometry, phase, at_right):
    """A chamfer 1.25 px wide lit at 0.65 of the face, its rows 0.4 px off: the drop-out
    reports its last two columns' light (over the background, of the face's), the distance
    to the outer side of its last column, that column's row off the face's line, whether
    its flank walk found the chamfer, and how the point moves per px outward
    (``chamfered_dropouts`` places the outline by them). At either end of the stripe."""
    sign = 1 if at_right else -1
    wall = (999.5 + phase) if at_right else (700.5 - phase)  # `phase` of the end column lit
    cols, rows, peaks, face, chamfer = chamfered_outline(geometry, wall, at_right)
    profile = blank_profile()
    set_stripe(profile, cols, rows, peaks)
    edges = edges_of(geometry, make(profile))
    i = int(np.argmax(edges.pixel[:, 0] * sign))
    assert edges.kind[i] == EdgeKind.DROPOUT and edges.direction[i] == sign
    lit = cols[peaks >= MIN_PEAK_DN]  # too faint below: dark
    end = lit.max() if at_right else lit.min()
    expected = (face + 0.65 * chamfer)[[end - 650, end - sign - 650]]  # over the background
    assert_allclose(edges.stripe_end[i, :2], expected, atol=1e-4)
    assert edges.stripe_end[i, 2] == pytest.approx((end + 0.5 * sign - edges.pixel[i, 0]) * sign,
                                                   abs=1e-5)
    assert abs(edges.stripe_end[i, 3]) == pytest.approx(0.4, abs=0.05)  # rows run either way
    # the chamfer fills column 999 (or 701) with its rows turned: the flank walk stops there
    assert edges.stripe_end[i, 4] == (1.0 if phase == 0.3 else 0.0)
    a, _ = surface_at(geometry, [edges.pixel[i, 0], edges.pixel[i, 0] + sign], NEAR_MM)
    outward = float(edges.per_px_b[i] @ edges.across_b[i])  # along the stripe, mm per px
    assert outward == pytest.approx(abs(a[1] - a[0]), rel=0.02)
    # steps carry none
    assert np.all(np.isnan(edges.stripe_end[edges.kind == EdgeKind.STEP]))


def _chain(rng, n=12, level=0.65, width_px=1.25, row_off=0.4, noise=0.02, mm_per_px=0.16,
           phase=None):
    """Drop-outs along the edge x = 0 (gap toward +x) of a chamfer's chain, one per profile:
    their outline lies in their last lit column at lit fraction f (random, or `phase` in
    every profile); each point was placed 0.4 px inside it (as half the face's level places
    it)."""
    f = rng.uniform(0.05, 1.0, n) if phase is None else np.full(n, phase)
    last = level * f
    face_share = np.clip(f - width_px + 1.0, 0.0, 1.0)
    before = face_share + level * (1.0 - face_share)
    placed_px = -0.4  # where the point sits, px from the outline (inward)
    offset = (1.0 - f) - placed_px  # from the point to the outer side of its last column
    end = np.column_stack([last + rng.normal(0, noise, n), before + rng.normal(0, noise, n),
                           offset, np.full(n, row_off) + rng.normal(0, 0.05, n),
                           np.zeros(n)])
    points = np.column_stack([np.full(n, placed_px * mm_per_px), 1.2 * np.arange(n), np.zeros(n)])
    across = np.tile([1.0, 0.0, 0.0], (n, 1))
    per_px = np.tile([mm_per_px, 0.0, 0.0], (n, 1))
    return points, across, np.arange(n), end, per_px


def test_chamfered_dropouts_move_a_chamfers_chain_to_its_outline(rng):
    """12 profiles of a chamfer 1.25 px wide at 0.65 of the face, with 0.02 of level noise:
    the chain's fit finds the level, and its points move from 0.4 px (64 um) inside the
    outline to within 0.1 px of it."""
    points, across, frames, end, per_px = _chain(rng)
    moved, level = chamfered_dropouts(points, across, frames, end, per_px, 1.2)
    assert_allclose(level, 0.65, atol=0.05)
    assert np.sqrt(np.mean(moved[:, 0] ** 2)) < 0.1 * 0.16
    assert_allclose(moved[:, 1:], points[:, 1:])


def test_chamfered_dropouts_leave_what_is_no_narrow_chamfer(rng):
    """A sharp edge (its last column at the face's level times f), one crossed at the same
    phase by every profile (which fits a chamfer at that level as well as a sharp edge), a
    dim end whose rows do not turn (no face of its own), points placed by a chamfer's own
    level, and a chain too short to fit keep their places."""
    points, across, frames, end, per_px = _chain(rng, level=1.0)
    moved, level = chamfered_dropouts(points, across, frames, end, per_px, 1.2)
    assert np.all(level >= 0.95)
    assert_allclose(moved, points)
    points, across, frames, end, per_px = _chain(rng, level=1.0, phase=0.6)
    moved, _ = chamfered_dropouts(points, across, frames, end, per_px, 1.2)
    assert_allclose(moved, points)
    points, across, frames, end, per_px = _chain(rng, row_off=0.05)
    moved, level = chamfered_dropouts(points, across, frames, end, per_px, 1.2)
    assert np.all(level < 0.8)
    assert_allclose(moved, points)
    points, across, frames, end, per_px = _chain(rng)
    end[::2, 4] = 1.0  # every other one placed by the chamfer's level in its profile
    moved, _ = chamfered_dropouts(points, across, frames, end, per_px, 1.2)
    assert_allclose(moved[::2], points[::2])
    assert np.all(np.abs(moved[1::2, 0]) < 0.03)
    points, across, frames, end, per_px = _chain(rng, n=CHAMFER_MIN_POINTS - 1)
    moved, level = chamfered_dropouts(points, across, frames, end, per_px, 1.2)
    assert np.all(np.isnan(level))
    assert_allclose(moved, points)


def test_chamfered_dropouts_split_chains_by_direction_and_profile(rng):
    """A chamfer's chain beside a sharp edge's facing the other way (a slot's two sides
    0.5 mm apart) are two chains; a chain whose profiles lie 10 frames apart is none."""
    chamfer = _chain(rng)
    sharp = list(_chain(rng, level=1.0))
    sharp[0] = sharp[0] + [0.5, 0.0, 0.0]
    sharp[1] = -sharp[1]
    n = len(chamfer[0])
    both = [np.concatenate([a, b]) for a, b in zip(chamfer, sharp)]
    moved, level = chamfered_dropouts(*both, 1.2)
    assert_allclose(level[:n], 0.65, atol=0.05)
    assert np.all(level[n:] >= 0.95)
    assert np.sqrt(np.mean(moved[:n, 0] ** 2)) < 0.1 * 0.16
    assert_allclose(moved[n:], both[0][n:])
    points, across, frames, end, per_px = _chain(rng)
    moved, level = chamfered_dropouts(points, across, frames * 10, end, per_px, 1.2)
    assert np.all(np.isnan(level))
    assert_allclose(moved, points)


def test_chamfered_dropouts_check_their_inputs():
    with pytest.raises(ValueError, match="`stripe_end`"):
        chamfered_dropouts(np.zeros((3, 3)), np.zeros((3, 3)), np.arange(3), np.zeros((3, 4)),
                           np.zeros((3, 3)), 1.0)
    empty, level = chamfered_dropouts(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, int),
                                      np.zeros((0, 5)), np.zeros((0, 3)), float("nan"))
    assert empty.shape == (0, 3) and level.shape == (0,)


@pytest.mark.parametrize("stripe_dn, expected", [(60.0, 0), (80.0, 2)])
def test_faint_stripe_fading_into_its_gap_has_no_dropout(geometry, stripe_dn, expected):
    """A stripe under twice its gap's level (60 DN beside 35 DN of a faint stripe or noise
    under the threshold) ends in the noise: no half step to place an edge by, so no drop-out;
    at 80 DN it has two."""
    cols = np.arange(700, 1000)
    _, rows = surface_at(geometry, cols, NEAR_MM)
    profile = blank_profile()
    set_stripe(profile, cols, rows, np.full(len(cols), stripe_dn))
    _, peak, _ = profile
    peak[[*range(690, 700), *range(1000, 1010)]] = 35.0  # the gaps: faint, under MIN_PEAK_DN
    edges = edges_of(geometry, make(profile))
    assert len(edges) == expected


def test_stripe_fading_on_a_surface_curving_away_is_no_edge(geometry):
    """A surface that rounds off over its last 10 columns (its range growing with the square
    of the distance, as over a lobe's crest) until the stripe is lost: the rows turn steadily
    up to the end, which is no edge of the part; the straight end on the left is one."""
    cols = np.arange(800, 1001)
    d = NEAR_MM + 0.02 * np.clip(cols - 990, 0, None) ** 2  # the rows turn 0.1 px a column
    rows = np.array([surface_at(geometry, [c], dd)[1][0] for c, dd in zip(cols, d)])
    profile = blank_profile()
    set_stripe(profile, cols, rows)
    edges = edges_of(geometry, make(profile))
    assert len(edges) == 1 and edges.kind[0] == EdgeKind.DROPOUT
    assert edges.pixel[0, 0] == pytest.approx(799.5)


@pytest.mark.parametrize("turn_mm, expected", [(0.0, [899.5, 904.5]), (0.03, [904.5])])
def test_short_stretch_across_a_crest_ends_on_its_steep_side_in_no_edge(geometry, turn_mm,
                                                                         expected):
    """Five columns of stripe across a rounded crest (cycloidal's lobes), its range growing
    with the square of the distance from the crest at the right end: too short a side for
    three turns, its steep end is judged over two, and is no edge; the crest's end is one.
    Level, both ends are edges."""
    cols = np.arange(900, 905)
    d = NEAR_MM + turn_mm * (904 - cols) ** 2
    rows = np.array([surface_at(geometry, [c], dd)[1][0] for c, dd in zip(cols, d)])
    profile = blank_profile()
    set_stripe(profile, cols, rows)
    edges = edges_of(geometry, make(profile))
    assert np.all(edges.kind == EdgeKind.DROPOUT)
    assert_allclose(np.sort(edges.pixel[:, 0]), expected, atol=1e-6)


def test_masked_columns_make_no_dropout(geometry):
    cols = np.arange(DIRECT[0], DIRECT[1])
    _, rows = surface_at(geometry, cols, NEAR_MM)
    profile = blank_profile()
    set_stripe(profile, cols, rows)
    p = make(profile)
    masked = np.zeros(WIDTH, bool)
    masked[1000:1025] = True  # the LED marker's columns, taken out by the pipeline
    p.peak[masked] = DARK_PEAK_DN  # no stripe seen there (as dark as a gap: no contrast test)
    cam, plane, _, _ = geometry
    assert len(find_edges(p, p.valid & ~masked, cam, plane, masked=masked)) == 0
    # without telling, the masked columns look like a gap: two drop-outs
    assert len(find_edges(p, p.valid & ~masked, cam, plane)) == 2


def test_shadow_side_of_a_gap_across_a_step_is_dropped(geometry):
    """A gap between a near and a far surface: the near side's end is the edge that casts the
    shadow; the far side's end is the shadow's boundary (kept only on request)."""
    near_cols, far_cols = np.arange(700, 900), np.arange(920, 1100)
    _, near_rows = surface_at(geometry, near_cols, NEAR_MM)
    _, far_rows = surface_at(geometry, far_cols, FAR_MM)
    profile = blank_profile()
    set_stripe(profile, near_cols, near_rows)
    set_stripe(profile, far_cols, far_rows)
    edges = edges_of(geometry, make(profile))
    assert_allclose(np.sort(edges.pixel[:, 0]), [699.5, 899.5, 1099.5], atol=1e-6)
    kept = edges_of(geometry, make(profile), params=EdgeParams(keep_far_side=True))
    assert_allclose(np.sort(kept.pixel[:, 0]), [699.5, 899.5, 919.5, 1099.5], atol=1e-6)


# ---------------------------------------------------------------------------------------------
# Steps


def step_profile(geometry, wall_col, near_left=True, lo=700, hi=1100):
    """A step whose wall stands half a column beyond the near side's last column ``wall_col``.

    Each column sees the near surface while it meets it before the wall, the far surface
    when it meets it beyond the wall, and else the unlit wall (dark). Returns the profile and
    the wall's position ``a`` in the sheet."""
    cols = np.arange(lo, hi)
    toward = 0.5 if near_left else -0.5
    a_wall = surface_at(geometry, [wall_col + toward], NEAR_MM)[0][0]
    a_near, r_near = surface_at(geometry, cols, NEAR_MM)
    a_far, r_far = surface_at(geometry, cols, FAR_MM)
    sees_near = a_near < a_wall if near_left else a_near > a_wall
    sees_far = ~sees_near & (a_far > a_wall if near_left else a_far < a_wall)
    profile = blank_profile()
    set_stripe(profile, cols[sees_near], r_near[sees_near])
    set_stripe(profile, cols[sees_far], r_far[sees_far])
    return profile, a_wall


@pytest.mark.parametrize("near_left", [True, False])
@pytest.mark.parametrize("wall_col", [900, 1203])
def test_step_edge_at_half_height_on_the_wall(geometry, wall_col, near_left):
    profile, a_wall = step_profile(geometry, wall_col, near_left, lo=wall_col - 150,
                                   hi=wall_col + 150)
    edges = edges_of(geometry, make(profile))
    steps = edges.kind == EdgeKind.STEP
    assert steps.sum() == 1 and (~steps).sum() == 2  # and the two ends of the stripe
    i = np.nonzero(steps)[0][0]
    assert_allclose(edges.point_b[i], sheet_point_b(geometry, a_wall, 0.5 * (NEAR_MM + FAR_MM)),
                    atol=EXACT_MM)
    assert_allclose(edges.size_mm[i], FAR_MM - NEAR_MM, atol=EXACT_MM)
    assert edges.direction[i] == (1 if near_left else -1)
    # in the image: at the wall's column, half way between the two sides' rows
    col = wall_col + (0.5 if near_left else -0.5)
    rows = [surface_at(geometry, [col], r)[1][0] for r in (NEAR_MM, FAR_MM)]
    assert_allclose(edges.pixel[i], [col, np.mean(rows)], atol=1e-3)


def test_chamfer_at_a_steps_rim_is_no_step_of_its_own(geometry):
    """A near face whose rim falls 0.4 mm over 4 columns (a chamfer) and then runs on for 3
    before a 5 mm step: one step, the wall's. The chamfer's slope, with the wall's jump 3
    columns away, has no surface of its own on that side."""
    near_cols, far_cols = np.arange(700, 900), np.arange(901, 1100)
    d = NEAR_MM + np.clip(near_cols - 892, 0, 4) * 0.1 + np.clip(near_cols - 896, 0, None) * 0.02
    near_rows = np.array([surface_at(geometry, [c], dd)[1][0] for c, dd in zip(near_cols, d)])
    _, far_rows = surface_at(geometry, far_cols, FAR_MM)
    profile = blank_profile()
    set_stripe(profile, near_cols, near_rows)
    set_stripe(profile, far_cols, far_rows)
    edges = edges_of(geometry, make(profile))
    steps = edges.kind == EdgeKind.STEP
    assert steps.sum() == 1
    assert edges.size_mm[steps][0] == pytest.approx(FAR_MM - NEAR_MM, abs=0.5)

def split_column_step(geometry, column, phase, near_left):
    """A step whose wall stands inside pixel column ``column``, at ``column + phase``: that
    column is lit in part by each side, in proportion to the share of the pixel each surface
    covers (the wall unlit). As the stripe extraction sees it, the column holds the brighter
    side's stripe, or a double stripe (not valid) when the fainter one reaches 0.3 of it.
    Returns the profile and whether that column holds a double stripe."""
    cols = np.arange(column - 150, column + 151)
    near_share = (0.5 + phase) if near_left else (0.5 - phase)
    far_share = 1.0 - near_share
    near = cols < column if near_left else cols > column
    far = ~near & (cols != column)
    profile = blank_profile()
    set_stripe(profile, cols[near], surface_at(geometry, cols[near], NEAR_MM)[1])
    set_stripe(profile, cols[far], surface_at(geometry, cols[far], FAR_MM)[1])
    bright, faint = max(near_share, far_share), min(near_share, far_share)
    peak = BACKGROUND_DN + PEAK_DN * bright
    if faint >= 0.3 * bright:  # stripe.DOUBLE_PEAK_RATIO
        row, peaks, reason = profile
        row[column], peaks[column], reason[column] = np.nan, peak, Reason.DOUBLE
        return profile, True
    side_mm = NEAR_MM if near_share > far_share else FAR_MM
    set_stripe(profile, [column], surface_at(geometry, [column], side_mm)[1], np.array([peak]))
    return profile, False


@pytest.mark.parametrize("near_left", [True, False])
@pytest.mark.parametrize("phase", [-0.45, -0.1, 0.0, 0.15, 0.45])
def test_step_with_its_wall_inside_a_column(geometry, phase, near_left):
    """The wall within one column, that column lit in part by each side: the near side's
    stripe ends where its intensity falls to half its level, as a drop-out's: within a tenth
    of a pixel of the wall when the column holds one side's stripe (the near side's share of
    a column holding the far side's, below 0.23, is taken as none: at 0.05 here); at the
    column's centre when it holds both (a double stripe, whose two parts the extraction does
    not report)."""
    column = 1000
    profile, double = split_column_step(geometry, column, phase, near_left)
    edges = edges_of(geometry, make(profile))
    steps = edges.kind == EdgeKind.STEP
    assert steps.sum() == 1
    i = np.nonzero(steps)[0][0]
    if double:
        assert_allclose(edges.pixel[i, 0], column, atol=1e-9)
        assert abs(phase) <= DOUBLE_COLUMN_TOL_PX
    else:
        assert_allclose(edges.pixel[i, 0], column + phase, atol=SUBPIXEL_TOL_PX)
    # the point: the near surface's end at that column, moved up the wall to half the step
    a_found = surface_at(geometry, [edges.pixel[i, 0]], NEAR_MM)[0][0]
    assert_allclose(edges.point_b[i], sheet_point_b(geometry, a_found, 0.5 * (NEAR_MM + FAR_MM)),
                    atol=EXACT_MM)
    assert edges.direction[i] == (1 if near_left else -1)


@dataclass(frozen=True)
class TwoPeakProfile(Profile):
    """A profile whose extraction measured some columns on one of two peaks
    (``StripeResult.n_peaks``, the default "continuity" policy)."""

    n_peaks: np.ndarray = None


#: The near side's share of a column measured on the far side's peak, beside it: from the
#: least a second peak holds (stripe.DOUBLE_PEAK_RATIO) to 0.6 of the far side's (the bracket's
#: leaning wall, edges.DOUBLE_SHARE); taking it as DOUBLE_SHARE of that peak puts the near end
#: within 0.19 of a column of the truth over that range (as none, 0.3 to 0.6 off).
TWO_PEAK_TOL_PX = 0.2


@pytest.mark.parametrize("share", [0.3, 0.45, 0.6])
@pytest.mark.parametrize("near_left", [True, False])
def test_step_beside_a_column_of_two_peaks(geometry, share, near_left):
    """A wall leaning under its top edge: the column beyond the near side's last one holds
    all of the far side's stripe and `share` of the near side's, and the extraction measures
    it on the far side's (brighter) peak, with a second one. The near side ends `share` into
    that column; the step's column lies within TWO_PEAK_TOL_PX of it. Without the second peak
    the near side's share is taken as none and the step lands at the column's border."""
    column = 1000
    cols = np.arange(column - 150, column + 151)
    near = cols < column if near_left else cols > column
    profile = blank_profile()
    set_stripe(profile, cols[near], surface_at(geometry, cols[near], NEAR_MM)[1])
    set_stripe(profile, cols[~near], surface_at(geometry, cols[~near], FAR_MM)[1])
    n_peaks = np.zeros(WIDTH, np.uint8)
    n_peaks[cols] = 1
    n_peaks[column] = 2
    base = make(profile)
    row, peak, reason = base.row, base.peak, base.reason
    expected = column + (share - 0.5 if near_left else 0.5 - share)
    for peaks, tol in ((n_peaks, TWO_PEAK_TOL_PX), (None, None)):
        two = TwoPeakProfile(row, peak, reason, n_peaks=peaks)
        edges = edges_of(geometry, two)
        steps = np.nonzero(edges.kind == EdgeKind.STEP)[0]
        assert len(steps) == 1
        u = edges.pixel[steps[0], 0]
        if tol is not None:
            assert abs(u - expected) <= tol
        else:  # as the earlier default: at the border of the near side's last column
            assert_allclose(u, column + (-0.5 if near_left else 0.5), atol=1e-9)


@pytest.mark.parametrize("row_noise_px", ROW_NOISE_PX)
def test_step_with_stripe_noise(geometry, rng, row_noise_px):
    profile, a_wall = step_profile(geometry, 1000)
    for _ in range(20):
        edges = edges_of(geometry, make(profile, rng, row_noise_px))
        steps = edges.kind == EdgeKind.STEP
        assert steps.sum() == 1
        expected = sheet_point_b(geometry, a_wall, 0.5 * (NEAR_MM + FAR_MM))
        assert np.linalg.norm(edges.point_b[steps][0] - expected) < NOISY_MM * row_noise_px / 0.03


def test_resolved_ramp_is_interpolated_at_half_height(geometry):
    """A step seen over a few columns (an inclined wall): the edge point lies on the ramp where
    it crosses half the step height."""
    cols = np.arange(800, 1100)
    a_n, _ = surface_at(geometry, cols, NEAR_MM)
    # range along the profile: near, a linear ramp over 4 columns, far
    t = np.clip((cols - 950) / 4.0, 0.0, 1.0)
    d = NEAR_MM + t * (FAR_MM - NEAR_MM)
    cam, plane, e_a, e_d = geometry
    # each column's line of sight meets the sheet where the range is d: solve per column
    rows = np.array([surface_at(geometry, [c], dd)[1][0] for c, dd in zip(cols, d)])
    a_cols = np.array([surface_at(geometry, [c], dd)[0][0] for c, dd in zip(cols, d)])
    profile = blank_profile()
    set_stripe(profile, cols, rows)
    edges = edges_of(geometry, make(profile))
    i = np.nonzero(edges.kind == EdgeKind.STEP)[0]
    assert len(i) == 1
    mid = 0.5 * (NEAR_MM + FAR_MM)
    a_mid = np.interp(mid, d[148:156], a_cols[148:156])  # half height: column 952
    assert_allclose(edges.point_b[i[0]], sheet_point_b(geometry, a_mid, mid), atol=EXACT_MM)
    assert_allclose(edges.pixel[i[0], 0], 952.0, atol=0.05)


def test_uneven_ramp_is_one_step_with_row_noise(geometry, rng):
    """A 5 mm step seen over 4 columns whose jumps grow (0.2, 0.5, 1.0, 3.3 mm: a wall
    leaning into view): one step every time. Its near side is judged for curling at its own
    end, not over the ramp's jumps (which turn the rows by far more than noise)."""
    cols = np.arange(800, 1100)
    d = NEAR_MM + np.interp(cols, [950, 951, 952, 953, 954], [0.0, 0.2, 0.7, 1.7, 5.0])
    rows = np.array([surface_at(geometry, [c], dd)[1][0] for c, dd in zip(cols, d)])
    profile = blank_profile()
    set_stripe(profile, cols, rows)
    for _ in range(40):
        edges = edges_of(geometry, make(profile, rng, 0.03))
        assert (edges.kind == EdgeKind.STEP).sum() == 1


@pytest.mark.parametrize("row_noise_px", ROW_NOISE_PX)
def test_noise_slopes_and_small_jumps_are_surface(geometry, rng, row_noise_px):
    """Stripe noise on a flat, a sloped and a curved surface, and a jump below min_step_mm:
    no step, and only the stripe's two ends as drop-outs."""
    cols = np.arange(600, 1300)
    x = (cols - 950) / 350.0
    for d in (np.full(len(cols), NEAR_MM),
              NEAR_MM + 8.0 * x,  # 8 mm over 110 mm: a 4 degree slope
              NEAR_MM + 6.0 * x**2,  # a gentle bulge
              NEAR_MM + 0.2 * (cols > 950)):  # a 0.2 mm step: below min_step_mm
        rows = np.array([surface_at(geometry, [c], dd)[1][0] for c, dd in zip(cols, d)])
        profile = blank_profile()
        set_stripe(profile, cols, rows)
        for _ in range(5):
            edges = edges_of(geometry, make(profile, rng, row_noise_px))
            assert np.all(edges.kind == EdgeKind.DROPOUT)
            assert_allclose(np.sort(edges.pixel[:, 0]), [599.5, 1299.5], atol=SUBPIXEL_TOL_PX)


def test_noise_estimate(geometry, rng):
    cols = np.arange(600, 1300)
    _, rows = surface_at(geometry, cols, NEAR_MM)
    profile = blank_profile()
    set_stripe(profile, cols, rows)
    quiet = edges_of(geometry, make(profile, rng, 0.03)).noise_mm
    loud = edges_of(geometry, make(profile, rng, 0.3)).noise_mm
    assert 0.003 < quiet < 0.03  # about 0.4 mm of range per row px
    assert loud == pytest.approx(10 * quiet, rel=0.2)


# ---------------------------------------------------------------------------------------------
# Contract


def test_result_contract(geometry):
    profile, _ = step_profile(geometry, 1000)
    edges = edges_of(geometry, make(profile))
    assert isinstance(edges, EdgePoints)
    m = len(edges)
    for name, shape, dtype in (("pixel", (m, 2), np.float64), ("point_b", (m, 3), np.float64),
                               ("kind", (m,), np.uint8), ("size_mm", (m,), np.float64),
                               ("peak", (m,), np.float32), ("direction", (m,), np.int8),
                               ("across_b", (m, 3), np.float64)):
        arr = getattr(edges, name)
        assert arr.shape == shape and arr.dtype == dtype, name
    assert_allclose(np.linalg.norm(edges.across_b, axis=1), 1.0)
    # a drop-out's pixel is the projection of its point
    cam, dropout = geometry[0], edges.kind == EdgeKind.DROPOUT
    assert_allclose(cam.project(edges.point_b[dropout]), edges.pixel[dropout], atol=1e-6)
    # the peak is the stripe's level
    assert_allclose(edges.peak, PEAK_DN + BACKGROUND_DN)


def test_empty_profiles(geometry):
    empty = edges_of(geometry, make(blank_profile()))
    assert len(empty) == 0 and empty.point_b.shape == (0, 3) and empty.across_b.shape == (0, 3)
    assert np.all(np.isfinite(empty.along_b))


def test_inputs_are_checked(geometry):
    cam, plane, _, _ = geometry
    p = make(blank_profile())
    with pytest.raises(ValueError, match="`valid` must be a \\(1920,\\) bool"):
        find_edges(p, p.valid[:10], cam, plane)
    with pytest.raises(ValueError, match="`masked`"):
        find_edges(p, p.valid, cam, plane, masked=np.zeros(WIDTH))
    with pytest.raises(ValueError, match="`result` must have"):
        find_edges(np.zeros(WIDTH), p.valid, cam, plane)
    with pytest.raises(ValueError, match="`min_step_mm`"):
        EdgeParams(min_step_mm=0.0)
    with pytest.raises(ValueError, match="`min_gap_px`"):
        EdgeParams(min_gap_px=1.5)


# ---------------------------------------------------------------------------------------------
# Occlusions (per scan)


def test_occluded_dropouts():
    """A plate (the cloud) between the camera and the probe past one drop-out hides it; the
    other drop-out's line of sight is clear."""
    g = np.mgrid[-10:10:0.5, -10:10:0.5].reshape(2, -1).T
    plate = np.column_stack([g[:, 0], g[:, 1] + 20.0, np.full(len(g), 10.0)])  # z = 10 mm
    points = np.array([[0.0, 0.0, 0.0], [0.0, -40.0, 0.0]])
    across = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    sensors = np.array([[0.0, 200.0, 100.0], [0.0, 160.0, 100.0]])  # through the plate, past it
    assert occluded_dropouts(points, across, sensors, plate).tolist() == [True, False]
    assert occluded_dropouts(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)),
                             plate).shape == (0,)
    with pytest.raises(ValueError, match="`across_t`"):
        occluded_dropouts(points, across[:1], sensors, plate)


# ---------------------------------------------------------------------------------------------
# Speed: a printout, not an assertion


def test_speed_printout(geometry, capsys):
    profile, _ = step_profile(geometry, 1000, lo=DIRECT[0] + 50, hi=DIRECT[1] - 50)
    p = make(profile, np.random.default_rng(0), 0.03)
    edges_of(geometry, p)  # compiled (or loaded from the cache) before timing
    n = 200
    t0 = time.perf_counter()
    for _ in range(n):
        edges_of(geometry, p)
    per_frame_ms = (time.perf_counter() - t0) / n * 1e3
    with capsys.disabled():
        print(f"\nfind_edges: {per_frame_ms:.3f} ms per 1920-column frame "
              f"({int(p.valid.sum())} valid columns)")


def _profiles_on_plane(normal, *, spacing_mm=1.2, profiles=7, seed=0):
    """Points of `profiles` parallel profiles (the sheets y = k * spacing) on the plane
    through the origin with `normal`, and their profile ids: what the scan holds around an
    edge point there."""
    rng = np.random.default_rng(seed)
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    out, ids = [], []
    for k in range(-(profiles // 2), profiles // 2 + 1):
        x = np.linspace(-5.0, 5.0, 60)
        y = np.full_like(x, k * spacing_mm)
        z = -(normal[0] * x + normal[1] * y) / normal[2]  # on the plane
        out.append(np.c_[x, y, z])
        ids.append(np.full(len(x), k))
    cloud = np.concatenate(out)
    return cloud + rng.normal(0.0, 0.01, cloud.shape), np.concatenate(ids)


@pytest.mark.parametrize("tilt_deg, spacing_mm, grazed", [
    (7.0, 1.2, True),     # the next profile lands 9.8 mm up the wall: out of reach
    (7.0, 1.3, True),     # a pass a little faster (the reference cell's, misplaced parts)
    (20.0, 1.2, True),    # 3.3 mm up: out of reach too
    (20.0, 0.3, True),    # a dense pass: the neighbours' plane is the wall's
    (40.0, 1.2, False),   # steep, but the neighbours span it: its normal is 50 deg off
    (90.0, 1.2, False),   # a level face
    (7.0, 6.0, False),    # a sparse pass (1 m/s): a lone profile says nothing
])
def test_an_edge_on_a_wall_the_sheet_grazes_is_found(tilt_deg, spacing_mm, grazed):
    """The sheet's normal is y; a wall turned `tilt_deg` from the sheet (90: a level face)."""
    t = np.radians(tilt_deg)
    normal = np.array([0.0, np.cos(t), np.sin(t)])
    cloud, ids = _profiles_on_plane(normal, spacing_mm=spacing_mm)
    edge = np.array([[1.0, 0.0, 0.0]])
    found = grazing_edges(edge, [[0.0, 1.0, 0.0]], cloud, ids, spacing_mm)
    assert found.tolist() == [grazed]


def test_a_step_point_in_mid_air_is_judged_by_its_own_surface():
    """A 5 mm step across level faces, profiles 1.28 mm apart (a misplaced part's pass): the
    step's point, half way up, is 2.5 mm from every cloud point. Centred on it, the
    neighbourhood holds its own profile only and reads as a grazed wall; centred on its
    profile's nearest point, it holds the neighbouring profiles' level face."""
    spacing = 1.28
    cloud, ids = [], []
    for k in range(-3, 4):
        x = np.linspace(10.0, 24.0, 80)
        z = np.where(x < 17.0, 20.5, 15.5)
        cloud.append(np.c_[x, np.full_like(x, k * spacing), z])
        ids.append(np.full(len(x), k))
    cloud, ids = np.concatenate(cloud), np.concatenate(ids)
    step = np.array([[17.0, 0.0, 18.0]])
    sheet = [[0.0, 1.0, 0.0]]
    assert grazing_edges(step, sheet, cloud, ids, spacing).tolist() == [True]
    assert grazing_edges(step, sheet, cloud, ids, spacing, frame_ids=[0]).tolist() == [False]
    with pytest.raises(ValueError, match="`frame_ids`"):
        grazing_edges(step, sheet, cloud, ids, spacing, frame_ids=[0, 1])


def test_the_scan_s_filters_judge_many_points_at_once_as_one_at_a_time(rng):
    """grazing_edges and occluded_dropouts take every point's neighbourhood or line of sight
    in one batch (segments of one array): each point's verdict is the one it gets alone,
    with their own KD-tree or a shared one."""
    from scipy.spatial import cKDTree

    tilted, ids = _profiles_on_plane([0.0, np.cos(0.12), np.sin(0.12)], profiles=9)
    level, level_ids = _profiles_on_plane([0.0, 0.0, 1.0], profiles=9, seed=1)
    cloud = np.concatenate([tilted, level + [30.0, 0.0, 0.0]])
    frames = np.concatenate([ids, level_ids])
    edges = np.concatenate([rng.uniform([-4, -3, -1], [4, 3, 1], (40, 3)),
                            rng.uniform([26, -3, -1], [34, 3, 1], (40, 3)),
                            [[100.0, 0.0, 0.0]]])  # nothing near
    sheets = np.tile([0.0, 1.0, 0.0], (len(edges), 1))
    batch = grazing_edges(edges, sheets, cloud, frames, 1.2,
                          cloud_tree=cKDTree(cloud))
    alone = [grazing_edges(e[None], s[None], cloud, frames, 1.2)[0] for e, s in zip(edges, sheets)]
    assert batch.tolist() == alone and 0 < batch.sum() < len(edges)

    across = np.tile([1.0, 0.0, 0.0], (len(edges), 1))
    sensors = edges + rng.uniform([-20, -20, 40], [20, 20, 120], (len(edges), 3))
    batch = occluded_dropouts(edges, across, sensors, cloud + [0.0, 0.0, 8.0],
                              cloud_tree=cKDTree(cloud + [0.0, 0.0, 8.0]))
    alone = [occluded_dropouts(e[None], a[None], s[None], cloud + [0.0, 0.0, 8.0])[0]
             for e, a, s in zip(edges, across, sensors)]
    assert batch.tolist() == alone and 0 < batch.sum() < len(edges)


def test_the_chamfer_fit_over_all_levels_is_the_fit_level_by_level(rng, monkeypatch):
    """The chamfer's levels go through in blocks; the fit is the one a level at a time finds
    (the first width at its least, the highest level on a tie), whatever the block."""
    from scanner_core.edges import filters as edge_filters
    from scanner_core.edges.filters import _CHAMFER_LEVELS, _CHAMFER_WIDTHS_PX, _fit_chamfer

    def one_level_at_a_time(last, before):
        w = _CHAMFER_WIDTHS_PX[:, None]
        best_cost, best, sharp = np.inf, None, np.inf
        for c in _CHAMFER_LEVELS[::-1]:
            f_a = np.clip(last / c, 0.0, w - 1.0)
            cost_a = (last - c * f_a) ** 2 + (before - c) ** 2
            rest = before - c + (1.0 - c) * (w - 1.0)
            f_b = np.clip((c * last + (1.0 - c) * rest) / (c**2 + (1.0 - c) ** 2), w - 1.0, 1.0)
            cost_b = (last - c * f_b) ** 2 + (before - c - (1.0 - c) * (f_b - w + 1.0)) ** 2
            first = cost_a <= cost_b
            totals = np.where(first, cost_a, cost_b).sum(axis=1)
            k = int(np.argmin(totals))
            if c == _CHAMFER_LEVELS[-1]:
                sharp = float(totals[k])
            if totals[k] < best_cost:
                best_cost = float(totals[k])
                best = (float(c), float(_CHAMFER_WIDTHS_PX[k]),
                        np.where(first[k], f_a[k], f_b[k]))
        return (*best, (sharp - best_cost) / len(last))

    for block in (edge_filters._CHAMFER_BLOCK, 41 * 30 * 7):
        monkeypatch.setattr(edge_filters, "_CHAMFER_BLOCK", block)
        for n in (6, 30):
            level = rng.uniform(0.3, 1.0)
            fill = rng.uniform(0.0, 1.0, n)
            last, before = level * fill + rng.normal(0, 0.03, n), level + rng.normal(0, 0.03, n)
            got, want = _fit_chamfer(last, before), one_level_at_a_time(last, before)
            assert got[:2] == want[:2] and got[3] == want[3]
            assert_allclose(got[2], want[2], rtol=0, atol=0)

