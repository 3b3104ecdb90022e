"""The stripe on frames like the photographs where it once failed: a dim line over a quiet
floor, a colour camera's line through JPEG's 4:2:0 chroma, a printed checkerboard, a bright
surface; against the drawn line (``simulator.line_photos``) and beside the naive peak finder
of ``flyscan bench real`` (per column the argmax and a 3-point parabola)."""

import math

import numpy as np
import pytest

from benchmarks.synthesised_photos import DIM, SEEDS, against_naive
from scanner_core.stripe import estimators as est
from scanner_core.stripe.extractor import BAYER_PATTERNS, EXCESS_OFFSET_DN, extract, stripe_signal
from simulator.line_photos import LinePhoto, render_line_photo

# Share of the rows within 0.02 px of a whole pixel that an unbiased estimator leaves (4 %),
# with the sampling spread of ~1900 rows.
WHOLE_PIXEL_MAX = 0.055


@pytest.mark.parametrize("peak_dn", [15.0, 30.0])
def test_a_dim_line_over_a_quiet_floor_is_a_stripe(peak_dn):
    """15 and 30 DN over 1 DN of noise (what a dark part shows): with the defaults every
    column measured, none false, no pixel locking, better than the naive peak finder."""
    fly, base = against_naive(LinePhoto(peak_dn=peak_dn, **DIM))
    assert fly["measured"] >= 0.995
    assert fly["false"] == 0
    assert fly["whole_pixel"] <= WHOLE_PIXEL_MAX
    assert fly["rms"] < 0.8 * base["rms"]


def test_no_pixel_locking_under_a_fixed_threshold():
    """A fixed 20 DN threshold near a 30 DN line's top leaves one or two pixels above it:
    the centre still comes from the line's shape, not the brightest pixel's row (which 13 %
    of the rows sat within 0.02 px of when the threshold weighed the centroid)."""
    fly, _ = against_naive(LinePhoto(peak_dn=30.0, **DIM), threshold=20.0)
    assert fly["whole_pixel"] <= WHOLE_PIXEL_MAX


@pytest.mark.parametrize("photo", [
    LinePhoto(laser="green", peak_dn=30.0, jpeg_quality=90, **DIM),
    LinePhoto(laser="green", peak_dn=160.0, background_dn=10.0, read_noise_dn=2.0,
              sigma_px=(1.0, 2.0), texture_px=24.0, black_reflectance=0.3, ambient_dn=60.0,
              jpeg_quality=85),
    LinePhoto(laser="red", peak_dn=180.0, read_noise_dn=2.0, sigma_px=(1.5, 3.0),
              jpeg_quality=95, height=768, width=1152),
], ids=["dim-green-jpeg", "green-checkerboard-jpeg", "red-jpeg"])
def test_a_colour_line_through_jpeg(photo):
    """A colour camera's line through JPEG (4:2:0: the colour excess at half resolution),
    dim, over a printed checkerboard under ambient light, or bright and red, measured with
    ``shoulders`` as the pipeline does a colour frame: every column measured, and against the
    naive peak finder on the same colour excess a smaller RMS, fewer rows off by more than
    1 px, no fewer within 0.5 px."""
    fly, base = against_naive(photo)
    assert fly["measured"] >= 0.995
    assert fly["false"] == 0
    assert fly["rms"] < base["rms"]
    assert fly["beyond_1px"] <= base["beyond_1px"]
    assert fly["within_half"] >= base["within_half"]
    assert fly["whole_pixel"] <= WHOLE_PIXEL_MAX


def test_a_colour_line_whose_own_channel_clips():
    """A green line over a bright surface whose green channel clips over a few rows (the
    others barely rise): its excess is carried on over the clipped rows (and never under a
    pixel's own), and the line's centre holds."""
    photo = LinePhoto(laser="green", peak_dn=120.0, background_dn=10.0, ambient_dn=170.0,
                      read_noise_dn=1.5, sigma_px=(1.5, 2.5))
    errors = []
    for seed in SEEDS:
        frame, truth = render_line_photo(photo, np.random.default_rng(seed))
        clipped = (frame[..., 1] == 255).any(axis=0)
        assert clipped.mean() > 0.9
        res = extract(stripe_signal(frame), shoulders=True)
        assert res.valid[clipped].mean() >= 0.99
        errors.append((res.row - truth.row)[clipped & res.valid])
    assert np.sqrt(np.mean(np.concatenate(errors) ** 2)) < 0.1


@pytest.mark.parametrize("texture_px", [0.0, 24.0])
def test_an_overexposed_line_whose_core_turns_white(texture_px):
    """A red line 1500 DN bright through a colour camera and JPEG (q 85, 4:2:0): its red
    clips over a wide run and its core turns white as the other channels' crosstalk clips
    too, so the bare excess is hollow across the line (the photographs of two public sets).
    With its excess carried on over the clipped run, every column is measured, and better
    than by the naive peak finder on the bare excess: over a plain surface and over a
    printed checkerboard."""
    fly, base = against_naive(LinePhoto(laser="red", peak_dn=1500.0, background_dn=10.0,
                                   ambient_dn=120.0, read_noise_dn=2.0, sigma_px=(1.5, 3.0),
                                   texture_px=texture_px, black_reflectance=0.2,
                                   jpeg_quality=85))
    assert fly["measured"] >= 0.99
    assert fly["rms"] <= 0.9 * base["rms"]
    assert fly["beyond_1px"] <= base["beyond_1px"]
    assert fly["whole_pixel"] <= WHOLE_PIXEL_MAX


def test_shoulders_are_for_colour_frames():
    """Without ``shoulders`` the chroma spread to one side of a JPEG's narrow line (4:2:0: the
    colour at half resolution, on the blocks' grid) is weighed with it; with them on a mono
    camera's speckled line, its flanks are lost (worse than without): the trade the
    pipeline's choice by the frame makes."""
    jpeg = LinePhoto(laser="green", peak_dn=120.0, background_dn=10.0, read_noise_dn=2.0,
                     sigma_px=(0.7, 1.2), jpeg_quality=60)
    errors = {}
    for on in (False, True):
        e = []
        for seed in SEEDS:
            frame, truth = render_line_photo(jpeg, np.random.default_rng(seed))
            res = extract(stripe_signal(frame), shoulders=on)
            e.append((res.row - truth.row)[res.valid & truth.present])
        errors[on] = np.sqrt(np.mean(np.concatenate(e) ** 2))
    assert errors[True] < 0.9 * errors[False]
    speckled = LinePhoto(sigma_px=(0.5, 6.0), speckle_contrast=0.3)
    for on in (False, True):
        e = []
        for seed in SEEDS:
            frame, truth = render_line_photo(speckled, np.random.default_rng(seed))
            res = extract(frame, shoulders=on)
            ok = res.valid & truth.present
            e.append((res.row - truth.row)[ok] / truth.sigma[ok])
        errors[on] = np.sqrt(np.mean(np.concatenate(e) ** 2))
    assert errors[False] < 0.9 * errors[True]


@pytest.mark.parametrize("square_px, most", [(30.0, 0.03), (16.0, 0.06)])
def test_a_bright_printed_texture_is_not_a_stripe(square_px, most):
    """A printed checkerboard under bright ambient light (squares at 215 and 40 DN), no laser:
    its lit squares are the columns' maxima, each a plateau as wide on top as at half height,
    and few pass for a stripe (a square of 16 px or more; 80 % of the columns did before). Of
    squares of 8 px, four in five still do: a plateau that short cannot be told from a wide
    stripe in one column."""
    for seed in range(6):
        frame, _ = render_line_photo(LinePhoto(peak_dn=0.0, texture_px=square_px,
                                               ambient_dn=200.0, background_dn=10.0,
                                               black_reflectance=0.15),
                                     np.random.default_rng(seed))
        assert extract(frame).valid.mean() <= most


@pytest.mark.parametrize("photo", [
    LinePhoto(peak_dn=100.0, ambient_dn=60.0, texture_px=24.0, black_reflectance=0.2,
              sigma_px=(1.5, 3.0)),
    LinePhoto(peak_dn=100.0, ambient_dn=20.0, texture_px=24.0, black_reflectance=0.2,
              sigma_px=(1.5, 3.0)),
    LinePhoto(laser="red", peak_dn=100.0, background_dn=10.0, ambient_dn=120.0,
              read_noise_dn=2.0, texture_px=24.0, black_reflectance=0.2, sigma_px=(1.5, 3.0)),
], ids=["mono-lit-squares", "mono-dim-ambient", "red"])
def test_a_line_across_printed_squares(photo):
    """A line across a printed checkerboard (squares of 24 px, the dark ones at a fifth of
    the light ones' reflectance). On a mono frame with the ambient light at 60 DN the squares
    show (70 and 22 DN): where a lit square holds the line, the centroid's run followed it to
    its edge (1.125 px RMS before a run ending at a cliff was weighed above it); at 20 DN they
    barely do, and the edge shows only in the stripe; in a colour frame's red excess a grey
    print does not show at all. Where a square's edge cuts the line, its centre comes from
    the flank the edge leaves whole (before: 0.61, 0.60 and 0.29 px RMS, the naive peak
    finder 0.25, 0.24 and 0.22): now better than the peak finder, and on the mono frames with
    no more rows 1 px off than it (with the ambient light at 20 DN, 0.8 % of them were, cut
    stripes whose other flank read too narrow for the fall to stand out). On the dark
    squares, where the line is under 10 noise sigmas, fewer rows more than 1 px off than the
    peak finder gives, though most of the rows flyscan gives there are off (docs/stripe.md)."""
    fly, base = against_naive(photo)
    assert fly["measured"] >= 0.995
    assert fly["rms"] <= 0.9 * base["rms"]
    assert fly["within_half"] >= base["within_half"]
    assert fly["beyond_1px"] < 0.01
    if not photo.laser:  # a mono frame
        assert fly["beyond_1px"] <= base["beyond_1px"]
    assert fly["whole_pixel"] <= WHOLE_PIXEL_MAX
    assert fly["false_off_line"] < base["false_off_line"]


@pytest.mark.parametrize("ambient_dn, rms_ratio", [(60.0, 0.8), (20.0, 0.8)])
def test_a_narrow_line_over_a_print(ambient_dn, rms_ratio):
    """A narrow line (sigma 0.6-1.2 px) across squares of 24 px. Under 60 DN of ambient
    light its background, read 12 and 20 rows out, lies on the dark squares past the lit one
    it crosses, and a centroid over it weighed the lit pixels beside the stripe as far as the
    noise lifted each over the level (0.140 px RMS, the naive peak finder's three pixels
    0.140); over the window's ends it is better than the peak finder. Under 20 DN, where a
    square's edge lies within half a pixel of its centre, half the stripe is dark and both
    methods miss by 0.4-0.9 px; the fit's narrower margin where the two surfaces differ finds
    more of those cuts, and a stripe cut next to its argmax, two whole pixels left, takes the
    width of the uncut stripes beside it (0.91 -> 0.82 of the peak finder's RMS), and the two
    surfaces are told at 3 noise sigmas (0.72); no row more than 1 px off."""
    fly, base = against_naive(LinePhoto(peak_dn=100.0, ambient_dn=ambient_dn, texture_px=24.0,
                                        black_reflectance=0.2, sigma_px=(0.6, 1.2)))
    assert fly["measured"] >= 0.995
    assert fly["rms"] <= rms_ratio * base["rms"]
    assert fly["beyond_1px"] <= base["beyond_1px"]
    assert fly["whole_pixel"] <= WHOLE_PIXEL_MAX


def test_a_print_finer_than_the_line():
    """Squares of 12 px, dark at 0.3, under a line of sigma 1-2.5 px at 60 DN: an edge cuts
    the stripe in most columns. The cut stripe's whole flank is fitted over its own foot, no
    further than three of its widths out (the walk had run on into the next dark square, and
    the fit widened toward the cut: 0.282 px RMS and 1.84 % of the rows more than 1 px off,
    the naive peak finder 0.261 px and none); a stripe cut near its centre is still cut where
    the dark square's share of it goes on falling past the edge. The lit and dark squares'
    feet, 14 DN apart over 3.6 DN of noise, are two surfaces at 3 noise sigmas (not at 4),
    and the fit's narrower margin finds more of the cuts: 0.81 -> 0.73 of the peak finder's
    RMS, 0.61 -> 0.31 % of the rows more than 1 px off."""
    fly, base = against_naive(LinePhoto(peak_dn=60.0, ambient_dn=20.0, texture_px=12.0,
                                        black_reflectance=0.3, sigma_px=(1.0, 2.5)))
    assert fly["measured"] >= 0.995
    assert fly["rms"] <= 0.8 * base["rms"]
    assert fly["beyond_1px"] < 0.005
    assert fly["whole_pixel"] <= WHOLE_PIXEL_MAX


def test_a_stripe_dimmer_than_the_lit_squares_it_crosses():
    """A wide line (sigma 2.5-5 px) across squares of 30 px, the dark ones at 0.4 under 60 DN
    of ambient light: on a dark square the stripe (40 DN over 34) is dimmer than the lit
    squares (70 DN) its column crosses too, so the column's brightest pixel is no stripe.
    Where the stripe beside it goes on, the row that stands highest over its surround is
    (72 % of the columns measured before), looked for near the neighbour's row first (a lit
    square's corner farther off stood higher and hid it in runs of 20-30 columns: 94.4 %).
    A lit square's last row on the stripe's flank, brighter than the stripe, had passed for
    it and stopped those runs: the stripe past that edge is looked for (96.12 -> 99.75 % over
    twelve frames)."""
    fly, base = against_naive(LinePhoto(peak_dn=100.0, ambient_dn=60.0, texture_px=30.0,
                                   black_reflectance=0.4, sigma_px=(2.5, 5.0)))
    assert fly["measured"] >= 0.99
    assert fly["within_half"] >= base["within_half"] + 0.25
    assert fly["beyond_1px"] <= 0.5 * base["beyond_1px"]
    assert fly["rms"] <= 0.7 * base["rms"]
    assert fly["whole_pixel"] <= WHOLE_PIXEL_MAX


def _past_edge_frame(rng, edge_offsets, flip=False, plain=180, rows=160, noise=3.0):
    """A mono frame (rows, plain + len(edge_offsets)) uint8 and its stripe's rows: a line of
    sigma 2.5-4 px (100 DN) under 60 DN of ambient light across a surface dark at 0.4 (10 DN
    black level). In the first ``plain`` columns the line lies on the dark surface alone; in
    the others, a lit surface ends ``edge_offsets`` of the line's sigmas before its centre
    (above it, or below with ``flip``), so that its last row holds the line's flank, brighter
    than the line's centre (the column's brightest pixel). Rendered at 8 sub-samples per
    pixel, with Gaussian ``noise`` (DN)."""
    w = plain + len(edge_offsets)
    sigma = np.linspace(2.5, 4.0, w)
    centre = 80.0 + np.linspace(-6.0, 6.0, w) + rng.uniform(-0.5, 0.5, w)
    past = np.concatenate([np.full(plain, np.inf), np.asarray(edge_offsets) * sigma[plain:]])
    sub = (np.arange(rows * 8) + 0.5)[:, None] / 8.0 - 0.5
    lit = (sub - centre > past) if flip else (centre - sub > past)
    light = 60.0 + 100.0 * np.exp(-0.5 * ((sub - centre) / sigma) ** 2)
    v = 10.0 + (np.where(lit, 1.0, 0.4) * light).reshape(rows, 8, w).mean(axis=1)
    v += rng.normal(0.0, noise, v.shape)
    return np.clip(np.round(v), 0, 255).astype(np.uint8), centre


@pytest.mark.parametrize("flip", [False, True])
def test_a_stripe_past_a_lit_surfaces_edge(flip):
    """A line whose centre lies on a dark surface 0.9-1.7 of its sigmas past a lit surface's
    edge: the lit surface's last row holds the line's flank, brighter than the line's centre,
    and is the column's brightest pixel, a peak a fraction of a pixel wide that was taken
    for the stripe (1-8 px off, or none, in every such column). Over ten frames of noise:
    the stripe past the edge in at least three quarters of those columns, within 0.3 px RMS,
    and in 85 % where the edge lies 1.2 sigmas or more from the centre (the stripe nearer to
    it barely dips between its centre and the edge); where no edge is near, as before."""
    rng = np.random.default_rng(3)
    offsets = np.linspace(0.9, 1.7, 60)
    plain, past = [], []
    for _ in range(10):
        img, centre = _past_edge_frame(rng, offsets, flip)
        res = extract(img)
        err = np.where(res.valid, res.row - centre, np.inf)
        plain.append(err[:-60])
        past.append(err[-60:])
    plain, past = np.concatenate(plain), np.array(past)
    assert np.all(np.abs(plain) < 1.0)
    assert np.sqrt(np.mean(plain ** 2)) < 0.25
    near = np.abs(past) < 1.0
    assert near.mean() >= 0.75
    assert near[:, offsets >= 1.2].mean() >= 0.85
    assert np.sqrt(np.mean(past[near] ** 2)) < 0.3


def _cut_column(centre, sigma, edge, dark_below=True, rows=120, ambient=60.0, noise=0.0,
                rng=None):
    """One column (rows, 1) uint8: a stripe of ``sigma`` px at ``centre`` over a surface whose
    reflectance falls to 0.2 past the row ``edge`` (10 DN dark level, ``ambient`` DN, 100 DN
    stripe), rendered at 8 sub-samples per pixel, with Gaussian ``noise`` (DN) from ``rng``."""
    sub = (np.arange(rows * 8) + 0.5) / 8.0 - 0.5
    past = sub > edge if dark_below else sub < edge
    reflectance = np.where(past, 0.2, 1.0)
    light = ambient + 100.0 * np.exp(-0.5 * ((sub - centre) / sigma) ** 2)
    v = 10.0 + (reflectance * light).reshape(rows, 8).mean(axis=1)
    if noise:
        v = v + rng.normal(0.0, noise, rows)
    return np.clip(np.round(v), 0, 255).astype(np.uint8)[:, None]


@pytest.mark.parametrize("centre, sigma, edge, dark_below", [
    (50.3, 2.0, 51.5, True), (50.3, 2.0, 49.5, False), (60.0, 2.8, 60.5, True),
    (40.3, 1.5, 40.5, True), (40.2, 1.5, 40.6, True)])
def test_a_cut_flank_is_found_and_the_whole_one_fitted(centre, sigma, edge, dark_below):
    """A dark square's edge across the stripe (between two pixels, or a tenth into one):
    ``cut_flank`` finds the flank it cuts and the last lit row, and ``uncut_centre`` fits the
    other flank to within 0.1 px, where the centroid of the whole stripe is pulled toward the
    lit side."""
    img = _cut_column(centre, sigma, edge, dark_below)
    h = img.shape[0]
    a = int(np.argmax(img[:, 0]))
    bg = float(np.median(img[:, 0]))
    step, r_cut = est.cut_flank(img, 0, a, h, bg, 1.0, 40)
    assert step == (1 if dark_below else -1)
    assert r_cut == (round(edge - 0.5) if dark_below else round(edge + 0.5))
    y = est.uncut_centre(img, 0, a, h, step, r_cut, 1.0, 40, math.nan, False)
    assert abs(y - centre) < 0.1
    whole = est.cog(img, 0, a, h, bg + 0.15 * (float(img[a, 0]) - bg), 4, math.nan, 40)
    assert abs(whole - centre) > 0.2


@pytest.mark.parametrize("centre, sigma, edge, dark_below, ambient, cut, share", [
    (50.27, 1.6, 50.5, True, 20.0, True, 0.98), (50.73, 1.6, 50.5, False, 20.0, True, 0.98),
    (49.8, 0.9, 49.5, False, 20.0, True, 0.25),
    (50.2, 0.65, 52.5, True, 60.0, False, 0.0), (50.2, 0.65, 47.5, False, 60.0, False, 0.02),
    (50.4, 1.0, 200.0, True, 60.0, False, 0.0)])
def test_a_cut_is_told_from_a_whole_stripe_through_noise(centre, sigma, edge, dark_below,
                                                         ambient, cut, share):
    """Over 200 draws of 3 DN noise: a stripe of sigma 1.6 px cut at its centre on a dim
    surface (whose other flank, read from the argmax, looks too narrow for the fall to stand
    out of it: the width test alone found 69 % of them) is found cut every time, by the fall
    against that flank's own fit; a narrow one (sigma 0.9 px) cut 0.3 px past its centre, its
    whole flank two or three pixels, at least a quarter of the time (a twelfth before the fit's
    margin narrowed where the two surfaces differ). A narrow whole stripe with a square's edge
    two pixels past its gentle flank, and one on a plain surface, never; with the edge 2.7 px
    past its steep flank, at most one draw in fifty (1.25 % of 2000)."""
    rng = np.random.default_rng(0)
    steps = []
    for _ in range(200):
        img = _cut_column(centre, sigma, edge, dark_below, ambient=ambient, noise=3.0, rng=rng)
        a = int(np.argmax(img[:, 0]))
        steps.append(est.cut_flank(img, 0, a, img.shape[0], float(np.median(img[:, 0])), 3.0,
                                   40)[0])
    steps = np.array(steps)
    if cut:
        assert np.mean(steps == (1 if dark_below else -1)) >= share
    else:
        assert np.mean(steps != 0) <= share


def test_a_core_on_a_shoulder_is_not_cut_in_a_colour_excess():
    """A bright core on a shoulder of its own, cut off sharply on the other side (an
    overexposed red line's excess through JPEG): ``cut_flank`` may take it for a cut stripe,
    but its whole flank stands on the shoulder, 40 DN above the cut side's foot, where a grey
    print's squares have the same excess; with ``same_foot`` no centre comes of it."""
    v = np.full(120, 20.0)
    v[40:50] = [30.0, 45.0, 60.0, 60.0, 62.0, 60.0, 110.0, 150.0, 160.0, 150.0]
    v[50:54] = [24.0, 22.0, 21.0, 20.0]
    img = v.astype(np.uint8)[:, None]
    a = int(np.argmax(v))
    step, r_cut = est.cut_flank(img, 0, a, 120, 20.0, 1.0, 40)
    assert step == 1
    assert math.isfinite(est.uncut_centre(img, 0, a, 120, step, r_cut, 1.0, 40, math.nan, False))
    assert math.isnan(est.uncut_centre(img, 0, a, 120, step, r_cut, 1.0, 40, math.nan, True))


def test_a_centre_past_the_edge_is_put_at_it():
    """The stripe's centre 0.8 px past a dark square's edge: its lit flank still rises where
    the edge cuts it, and the centre is put at the edge, half a pixel past the last lit row,
    not extrapolated into the dark."""
    img = _cut_column(50.3, 2.0, 49.5, True)
    a = int(np.argmax(img[:, 0]))
    step, r_cut = est.cut_flank(img, 0, a, img.shape[0], float(np.median(img[:, 0])), 1.0, 40)
    assert (step, r_cut) == (1, 49)
    assert est.uncut_centre(img, 0, a, img.shape[0], step, r_cut, 1.0, 40, math.nan, False) == 49.5


@pytest.mark.parametrize("centre, sigma, edge, dark_below, share", [
    (50.45, 0.87, 50.5, True, 0.75), (50.26, 0.88, 50.5, True, 0.85),
    (50.1, 0.6, 50.5, True, 0.95), (50.74, 0.88, 50.5, False, 0.9)])
def test_a_narrow_stripe_cut_next_to_its_argmax(centre, sigma, edge, dark_below, share):
    """A narrow stripe (sigma 0.6-0.9 px) on a dim print (20 DN of ambient light, 2 DN of
    noise) whose edge lies between its argmax and the next pixel keeps two pixels of whole
    flank, too few for ``uncut_centre``'s fit (the centroid of the two was up to 0.6 px off):
    ``narrow_cut`` finds the side in most of 200 draws, and ``narrow_cut_centre`` with the
    stripe's width puts the centre within 0.15 px RMS, never 0.3 px off."""
    rng = np.random.default_rng(0)
    sides, errors = [], []
    for _ in range(200):
        img = _cut_column(centre, sigma, edge, dark_below, ambient=20.0, noise=2.0, rng=rng)
        h = img.shape[0]
        a = int(np.argmax(img[:, 0]))
        side = est.narrow_cut(img, 0, a, h, float(np.median(img[:, 0])), 2.0, 40, 0.5)
        sides.append(side)
        if side:
            errors.append(est.narrow_cut_centre(img, 0, a, h, side, sigma, 2.0, 40) - centre)
    assert set(sides) <= {0, 1 if dark_below else -1}
    assert np.mean(np.array(sides) != 0) >= share
    assert np.sqrt(np.mean(np.square(errors))) <= 0.15
    assert np.max(np.abs(errors)) < 0.3


@pytest.mark.parametrize("centre, sigma, edge, dark_below, ambient", [
    (50.0, 0.6, 200.0, True, 20.0), (50.5, 0.6, 200.0, True, 20.0),
    (50.3, 1.2, 200.0, True, 20.0), (50.4, 0.6, 51.5, True, 20.0),
    (50.2, 0.65, 52.5, True, 60.0), (50.2, 0.65, 47.5, False, 20.0)])
def test_a_narrow_whole_stripe_is_not_taken_for_cut(centre, sigma, edge, dark_below, ambient):
    """A narrow whole stripe on a plain surface, or with a dark square's edge past its first
    pixel on either side, is never taken for one cut next to its argmax in 200 draws of 2 DN
    noise."""
    rng = np.random.default_rng(1)
    for _ in range(200):
        img = _cut_column(centre, sigma, edge, dark_below, ambient=ambient, noise=2.0, rng=rng)
        a = int(np.argmax(img[:, 0]))
        assert est.narrow_cut(img, 0, a, img.shape[0], float(np.median(img[:, 0])), 2.0, 40,
                              0.5) == 0


@pytest.mark.parametrize("profile", ["whole", "narrow", "flat top"])
def test_a_whole_stripe_is_not_cut(profile):
    """No edge: a Gaussian of sigma 2 px, one of 0.6 px (its one-pixel fall is most of its
    height), and a flat top between two cliffs (a colour line's clipped core): none is cut."""
    if profile == "flat top":
        v = np.full(120, 20.0)
        v[48:53] = [120.0, 124.0, 122.0, 125.0, 121.0]
        v[47], v[53] = 70.0, 72.0
        img = v.astype(np.uint8)[:, None]
    else:
        img = _cut_column(50.4, 2.0 if profile == "whole" else 0.6, 200.0)
    a = int(np.argmax(img[:, 0]))
    step, _ = est.cut_flank(img, 0, a, img.shape[0], float(np.median(img[:, 0])), 1.0, 40)
    assert step == 0


def test_a_stripe_on_a_bright_surface():
    """A line 50 DN over a surface at 190 DN (a white part under ambient light): it stands
    clear of its own background, not of a fixed level, and is measured whole."""
    fly, _ = against_naive(LinePhoto(peak_dn=50.0, background_dn=10.0, ambient_dn=180.0,
                                sigma_px=(1.0, 2.0)))
    assert fly["measured"] >= 0.995
    assert fly["false"] == 0
    assert fly["rms"] < 0.1


def test_colour_excess():
    """``v_k - (v_i + v_j) / 2`` rounded half up, kept EXCESS_OFFSET_DN above zero (a grey
    pixel's excess there), clipped to [0, 255]; a clipped channel with nothing unclipped in
    its column to carry on from keeps its own excess."""
    rgb = np.array([[[10, 50, 11], [100, 100, 100], [0, 0, 255], [255, 240, 250],
                     [255, 0, 0]]], np.uint8)
    assert stripe_signal(rgb, "green_excess").tolist() == [[56, 16, 0, 4, 0]]
    assert stripe_signal(rgb, "red_excess").tolist() == [[0, 16, 0, 26, 255]]
    assert stripe_signal(rgb, "blue_excess").tolist() == [[0, 16, 255, 19, 0]]
    # auto on a colour frame: the largest excess
    assert stripe_signal(rgb).tolist() == [[56, 16, 255, 26, 255]]
    assert stripe_signal(rgb, "green").tolist() == [[50, 100, 0, 240, 0]]
    mono = np.arange(12, dtype=np.uint8).reshape(3, 4)
    assert stripe_signal(mono) is mono


def test_a_clipped_run_is_carried_on_from_its_edges():
    """Down a column, a red line whose red clips while green and blue rise to white: the bare
    excess falls to zero at the white core (hollow), the carried-on one peaks there; a white
    surface (every channel clipped, none rising over its edges) stays near zero; JPEG's one
    pixel under full scale inside a clipped run joins its two halves."""
    line = np.array([[200, 100, 100], [220, 110, 110], [240, 120, 120], [255, 140, 140],
                     [255, 200, 200], [250, 250, 250], [255, 200, 200], [255, 140, 140],
                     [240, 120, 120], [220, 110, 110], [200, 100, 100]], np.uint8)[:, None]
    bare = (2 * line[:, 0, 0].astype(int) - line[:, 0, 1] - line[:, 0, 2] + 1) // 2 + 16
    assert bare[5] == 16 and bare.argmax() != 5
    carried = stripe_signal(line, "red_excess")[:, 0].astype(int)
    assert carried.argmax() == 5
    assert np.all(np.diff(carried[:6]) > 0) and np.all(np.diff(carried[5:]) < 0)
    assert np.array_equal(carried, carried[::-1])
    assert np.array_equal(stripe_signal(line)[:, 0], carried)
    wall = np.array([[230, 240, 235], [250, 250, 250], [255, 255, 255], [255, 255, 255],
                     [252, 250, 255], [231, 240, 236]], np.uint8)[:, None]
    assert stripe_signal(wall, "red_excess").max() < 16 + 15
    holed = line.copy()
    holed[5] = (244, 250, 250)  # under the clipped level: the run goes on through it
    assert stripe_signal(holed, "red_excess")[:, 0].argmax() == 5


@pytest.mark.parametrize("pattern", sorted(BAYER_PATTERNS))
def test_a_bayer_mosaic_is_demosaiced_before_its_excess(pattern):
    """A red patch on grey through each mosaic: its red excess stands out where it is."""
    h, w = 32, 32
    rgb = np.full((h, w, 3), 60, np.uint8)
    rgb[8:24, 8:24] = (200, 40, 40)
    raw = np.empty((h, w), np.uint8)
    channel = {"R": 0, "G": 1, "B": 2}
    for i, (dr, dc) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        raw[dr::2, dc::2] = rgb[dr::2, dc::2, channel[pattern[i]]]
    red = stripe_signal(raw, "red_excess", bayer=pattern).astype(int)
    assert red[12:20, 12:20].min() > 140 + EXCESS_OFFSET_DN
    assert np.abs(red[:4, :4] - EXCESS_OFFSET_DN).max() <= 2


def test_stripe_signal_refuses_what_it_cannot_read():
    rgb = np.zeros((4, 4, 3), np.uint8)
    with pytest.raises(ValueError, match="signal"):
        stripe_signal(rgb, "infrared")
    with pytest.raises(ValueError, match="mono"):
        stripe_signal(rgb, "mono")
    with pytest.raises(ValueError, match="colour frame"):
        stripe_signal(np.zeros((4, 4), np.uint8), "green_excess")
    with pytest.raises(ValueError, match="uint8"):
        stripe_signal(rgb.astype(np.uint16))
    with pytest.raises(ValueError, match="bayer"):
        stripe_signal(np.zeros((4, 4), np.uint8), bayer="RGBG")
    with pytest.raises(ValueError, match="Bayer mosaic is"):
        stripe_signal(rgb, bayer="RGGB")
