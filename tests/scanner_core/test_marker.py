"""Tests for scanner_core.marker.finder on synthetic frames (seeded), built here with numpy."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from numpy.testing import assert_allclose

from scanner_core.numeric import pooling as _pooling
from scanner_core.marker import finder as marker_mod
from scanner_core.marker.finder import MarkerParams, find_marker, find_markers, marker_present
from simulator.imaging import ImageModel, render_image

# Reference image model (docs/design.md): background, read noise, marker and stripe.
BACKGROUND_DN = 10.0
NOISE_DN = 3.0
MARKER_PEAK_DN = 230.0
MARKER_SIGMA_PX = 2.5
STRIPE_PEAK_DN = 200.0
STRIPE_SIGMA_PX = 1.5

FRAME_SHAPE = (1200, 1920)
STRIPS = ((0, 384), (384, 1536), (1536, 1920))  # left mirror, direct, right mirror

# Tolerances. The Cramer-Rao bound per axis at the reference model is
# NOISE / (PEAK * sqrt(pi / 2)) = 0.0104 px; the fit measures 0.0105 px.
TOL_RMS_PX = 0.015
TOL_BIAS_PX = 0.003          # mean error over N_POSITIONS (its standard error is ~0.0006 px)
TOL_MAX_PX = 0.06            # worst single error at the reference model (about 5 sigma)
TOL_NEAR_STRIPE_PX = 0.1     # marker touching the end of the stripe (stripe pixels masked)
TOL_SATURATED_BIAS_PX = 0.005
# The tracked (windowed) search must give the whole-strip search's fit, bit for bit; this only
# leaves room for the comparison itself.
TOL_SAME_FIT_PX = 1e-9
N_POSITIONS = 300
SEARCH_PX = MarkerParams().search_px


def _blob(img: np.ndarray, x: float, y: float, peak: float = MARKER_PEAK_DN,
          sigma: float = MARKER_SIGMA_PX) -> None:
    """Add an isotropic Gaussian blob centred at (x, y) (column, row) to float image `img`."""
    yy, xx = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    r = int(6 * sigma) + 1
    sel = (np.abs(xx - x) <= r) & (np.abs(yy - y) <= r)
    img[sel] += peak * np.exp(-((xx[sel] - x) ** 2 + (yy[sel] - y) ** 2) / (2 * sigma**2))


def _stripe(img: np.ndarray, cols: np.ndarray, rows: np.ndarray,
            peak: float = STRIPE_PEAK_DN) -> None:
    """Add a stripe: in each column of `cols`, a Gaussian along the rows centred at `rows`."""
    yy = np.arange(img.shape[0])[:, None]
    img[:, cols] += peak * np.exp(-((yy - rows[None, :]) ** 2) / (2 * STRIPE_SIGMA_PX**2))


def _finish(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Background + read noise, rounded and clipped to uint8."""
    noisy = img + BACKGROUND_DN + rng.normal(0.0, NOISE_DN, img.shape)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def _curved_stripe(img: np.ndarray, rng: np.random.Generator, c0: int, c1: int,
                   row0: float, *, breaks: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """A long curved stripe over [c0, c1) with a step and (optionally) gaps."""
    cols = np.arange(c0, c1)
    rows = row0 + 40 * np.sin(cols / rng.uniform(40, 200))
    rows = rows + np.where(cols > rng.uniform(c0 + 50, c1 - 50), rng.uniform(-15, 15), 0.0)
    keep = np.ones(cols.size, bool)
    if breaks:
        for _ in range(4):
            a = rng.integers(0, cols.size)
            keep[a : a + rng.integers(1, 30)] = False
    _stripe(img, cols[keep], rows[keep])
    return cols[keep], rows[keep]


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20240611)


# --- accuracy ----------------------------------------------------------------------------------


def test_centre_accuracy_rms_and_bias(rng):
    shape, strip = (64, 64), (0, 64)
    truth = rng.uniform(31.0, 33.0, size=(N_POSITIONS, 2))
    errors = np.empty_like(truth)
    for k, (x, y) in enumerate(truth):
        img = np.zeros(shape)
        _blob(img, x, y)
        found = find_marker(_finish(img, rng), columns=strip)
        assert found is not None
        errors[k] = np.subtract(found, (x, y))
    assert_allclose(errors.mean(axis=0), 0.0, atol=TOL_BIAS_PX)
    assert np.all(np.sqrt((errors**2).mean(axis=0)) < TOL_RMS_PX)
    assert np.abs(errors).max() < TOL_MAX_PX


def test_saturated_marker_unbiased(rng):
    # Peak 300 DN clips at 255: the clipped core is left out of the fit.
    shape, strip = (64, 64), (0, 64)
    truth = rng.uniform(31.0, 33.0, size=(N_POSITIONS, 2))
    errors = np.empty_like(truth)
    for k, (x, y) in enumerate(truth):
        img = np.zeros(shape)
        _blob(img, x, y, peak=300.0)
        image = _finish(img, rng)
        assert image.max() == 255
        found = find_marker(image, columns=strip)
        assert found is not None
        errors[k] = np.subtract(found, (x, y))
    assert_allclose(errors.mean(axis=0), 0.0, atol=TOL_SATURATED_BIAS_PX)
    assert np.all(np.sqrt((errors**2).mean(axis=0)) < TOL_RMS_PX)


def test_full_frame_three_views_with_stripe(rng):
    img = np.zeros(FRAME_SHAPE)
    truth = np.array([[200.3, 420.7], [900.6, 300.2], [1700.1, 950.9]])
    for x, y in truth:
        _blob(img, x, y)
    _curved_stripe(img, rng, 420, 1500, 700.0)
    image = _finish(img, rng)
    got = find_markers(image, strips=STRIPS)
    assert got.shape == (3, 2) and got.dtype == np.float64
    assert_allclose(got, truth, atol=TOL_MAX_PX)
    assert marker_present(image, strips=STRIPS)
    for k, strip in enumerate(STRIPS):
        assert_allclose(find_marker(image, columns=strip), truth[k], atol=TOL_MAX_PX)


# --- absence and the stripe ---------------------------------------------------------------------


def test_absent_marker(rng):
    image = _finish(np.zeros(FRAME_SHAPE), rng)
    assert find_marker(image, columns=STRIPS[1]) is None
    got = find_markers(image, strips=STRIPS)
    assert got.shape == (3, 2) and np.isnan(got).all()
    assert not marker_present(image, strips=STRIPS)


@pytest.mark.parametrize("seed", range(5))
def test_stripe_alone_is_not_a_marker(seed):
    rng = np.random.default_rng(seed)
    img = np.zeros(FRAME_SHAPE)
    _curved_stripe(img, rng, 400, 1520, rng.uniform(300, 900))
    # A short stripe fragment in a mirror view too.
    cols = np.arange(100, 140)
    _stripe(img, cols, 600 + 0.2 * (cols - 100))
    image = _finish(img, rng)
    assert np.isnan(find_markers(image, strips=STRIPS)).all()
    # The cheap test may pass a very short stripe piece in one view (documented), never two.
    assert not marker_present(image, strips=STRIPS)


@pytest.mark.parametrize("gap_px", [4.0, 6.0, 10.0])
@pytest.mark.parametrize("row_offset_px", [0.0, 3.0])
def test_marker_at_end_of_stripe(rng, gap_px, row_offset_px):
    # The stripe ends `gap_px` columns before the marker centre: its end touches the blob
    # (radius about 4.4 px at the threshold), so both form one thresholded component.
    for _ in range(10):
        img = np.zeros((300, 500))
        x_end = rng.uniform(240.0, 260.0)
        cols = np.arange(20, int(x_end) + 1)
        _stripe(img, cols, 150.0 + 0.1 * (cols - x_end))
        x, y = x_end + gap_px, 150.0 + row_offset_px + rng.uniform(-0.5, 0.5)
        _blob(img, x, y)
        found = find_marker(_finish(img, rng), columns=(0, 500))
        assert found is not None
        assert_allclose(found, (x, y), atol=TOL_NEAR_STRIPE_PX)


def test_stripe_through_marker_core_is_rejected_not_biased(rng):
    # The stripe runs into the marker's core: no trustworthy centre, so None.
    img = np.zeros((300, 500))
    cols = np.arange(20, 251)
    _stripe(img, cols, np.full(cols.size, 150.0))
    _blob(img, 250.0, 150.2)
    assert find_marker(_finish(img, rng), columns=(0, 500)) is None


def test_marker_next_to_stripe_in_mirror_view(rng):
    img = np.zeros(FRAME_SHAPE)
    cols = np.arange(1600, 1640)
    _stripe(img, cols, np.full(cols.size, 500.0))
    _blob(img, 1700.4, 520.6)
    found = find_marker(_finish(img, rng), columns=STRIPS[2])
    assert_allclose(found, (1700.4, 520.6), atol=TOL_MAX_PX)


def test_brightest_of_two_blobs_wins(rng):
    img = np.zeros((100, 200))
    _blob(img, 50.3, 50.2, peak=120.0)
    _blob(img, 150.7, 40.4, peak=230.0)
    found = find_marker(_finish(img, rng), columns=(0, 200))
    assert_allclose(found, (150.7, 40.4), atol=TOL_MAX_PX)


# --- edges --------------------------------------------------------------------------------------


@pytest.mark.parametrize("x", [386.0, 390.0, 1533.0, 1529.0])
def test_marker_cut_by_strip_edge_is_none(rng, x):
    # Choice: a marker whose fit window (half-size ceil(3 * 2.5) = 8 px) leaves the strip is
    # reported absent, since a truncated blob would bias the centre.
    img = np.zeros(FRAME_SHAPE)
    _blob(img, x, 600.3)
    assert find_marker(_finish(img, rng), columns=STRIPS[1]) is None


@pytest.mark.parametrize("x", [392.3, 1527.4])
def test_marker_just_inside_strip_edge_is_found(rng, x):
    img = np.zeros(FRAME_SHAPE)
    _blob(img, x, 600.3)
    found = find_marker(_finish(img, rng), columns=STRIPS[1])
    assert_allclose(found, (x, 600.3), atol=TOL_MAX_PX)


@pytest.mark.parametrize("y", [3.0, 1196.0])
def test_marker_cut_by_image_border_is_none(rng, y):
    img = np.zeros(FRAME_SHAPE)
    _blob(img, 900.0, y)
    assert find_marker(_finish(img, rng), columns=STRIPS[1]) is None


# --- trigger ------------------------------------------------------------------------------------


@pytest.mark.parametrize("views, min_views, expected",
                         [((0, 1, 2), 2, True), ((0, 2), 2, True), ((2,), 2, False),
                          ((2,), 1, True), ((0, 1, 2), 3, True), ((0, 1), 3, False)])
def test_marker_present_counts_views(rng, views, min_views, expected):
    centres = [(200.5, 600.0), (960.2, 400.0), (1750.7, 700.0)]
    img = np.zeros(FRAME_SHAPE)
    for v in views:
        _blob(img, *centres[v])
    _curved_stripe(img, rng, 420, 1500, 800.0)
    assert marker_present(_finish(img, rng), strips=STRIPS, min_views=min_views) is expected


# --- input checks -------------------------------------------------------------------------------


@pytest.mark.parametrize("image", [np.zeros((10, 10), np.float32), np.zeros((10, 10, 3), np.uint8),
                                   np.zeros(10, np.uint8), [[0, 1], [2, 3]]])
def test_bad_image(image):
    with pytest.raises(ValueError, match="`image`"):
        find_marker(image, columns=(0, 2))
    with pytest.raises(ValueError, match="`image`"):
        find_markers(image, strips=[(0, 2)])
    with pytest.raises(ValueError, match="`image`"):
        marker_present(image, strips=[(0, 2)])


@pytest.mark.parametrize("columns", [(0, 21), (-1, 5), (5, 5), (6, 2), (0.5, 4), (1,), "ab", None])
def test_bad_columns(columns):
    image = np.zeros((10, 20), np.uint8)
    with pytest.raises(ValueError, match="`columns`"):
        find_marker(image, columns=columns)


def test_bad_strips():
    image = np.zeros((10, 20), np.uint8)
    with pytest.raises(ValueError, match=r"`strips\[1\]`"):
        find_markers(image, strips=[(0, 10), (10, 30)])
    with pytest.raises(ValueError, match="`strips`"):
        find_markers(image, strips=[])
    with pytest.raises(ValueError, match="`strips`"):
        marker_present(image, strips=5)
    with pytest.raises(ValueError, match="`min_views`"):
        marker_present(image, strips=[(0, 10)], min_views=0)


@pytest.mark.parametrize("kwargs", [{"threshold_dn": 300.0}, {"min_area_px": 0},
                                    {"min_area_px": 50, "max_area_px": 10},
                                    {"sigma_px": 0.0}, {"decimation": 0}, {"search_px": 0}])
def test_bad_params(kwargs):
    with pytest.raises(ValueError):
        MarkerParams(**kwargs)


@pytest.mark.parametrize("near", [np.zeros((2, 2)), np.zeros(3), np.zeros((3, 3)), "ab",
                                  [[1.0, 2.0], [3.0, 4.0], [5.0, "x"]]])
def test_bad_near(near):
    image = np.zeros((50, 60), np.uint8)
    with pytest.raises(ValueError, match="`near`"):
        find_markers(image, strips=[(0, 20), (20, 40), (40, 60)], near=near)


def test_bad_near_single_strip():
    image = np.zeros((50, 60), np.uint8)
    with pytest.raises(ValueError, match="`near`"):
        find_marker(image, columns=(0, 60), near=(1.0, 2.0, 3.0))


@pytest.mark.parametrize("search_px", [0, -5.0, np.nan, np.inf, "x"])
def test_bad_search_px(search_px):
    image = np.zeros((50, 60), np.uint8)
    with pytest.raises(ValueError, match="`search_px`"):
        find_markers(image, strips=[(0, 60)], near=[[10.0, 10.0]], search_px=search_px)


# --- tracked search (near a prediction) ---------------------------------------------------------


def _three_view_frame(rng, truth, *, stripe_row=700.0):
    img = np.zeros(FRAME_SHAPE)
    for x, y in truth:
        _blob(img, x, y)
    _curved_stripe(img, rng, 420, 1500, stripe_row)
    return _finish(img, rng)


TRUTH_3 = np.array([[200.3, 420.7], [900.6, 300.2], [1700.1, 950.9]])
# Prediction errors, px: none, small, and just inside the default window (+-48 px).
OFFSETS = [(0.0, 0.0), (7.5, -3.2), (-30.0, 25.0), (40.0, -40.0)]


@pytest.mark.parametrize("offset", OFFSETS)
@pytest.mark.parametrize("view", range(3))
def test_windowed_search_equals_full_search(rng, view, offset):
    image = _three_view_frame(rng, TRUTH_3)
    full = find_markers(image, strips=STRIPS)
    assert np.isfinite(full).all()
    near = np.full((3, 2), np.nan)
    near[view] = TRUTH_3[view] + offset
    got = find_markers(image, strips=STRIPS, near=near)
    assert_allclose(got, full, rtol=0, atol=TOL_SAME_FIT_PX)
    assert_allclose(find_marker(image, columns=STRIPS[view], near=tuple(near[view])),
                    full[view], rtol=0, atol=TOL_SAME_FIT_PX)


def test_windowed_search_in_all_views_at_once(rng):
    image = _three_view_frame(rng, TRUTH_3)
    near = TRUTH_3 + rng.uniform(-20.0, 20.0, TRUTH_3.shape)
    assert_allclose(find_markers(image, strips=STRIPS, near=near),
                    find_markers(image, strips=STRIPS), rtol=0, atol=TOL_SAME_FIT_PX)


def test_windowed_search_uses_only_the_window(rng, monkeypatch):
    # With a good prediction the whole strip is never searched.
    image = _three_view_frame(rng, TRUTH_3)
    windows = []
    search = marker_mod._search

    def spy(image, rows, spans, params):
        windows.extend((*rows, w0, w1) for _, _, w0, w1 in spans)
        return search(image, rows, spans, params)

    monkeypatch.setattr(marker_mod, "_search", spy)
    find_markers(image, strips=STRIPS, near=TRUTH_3)
    assert len(windows) == 3
    for (r0, r1, w0, w1), (x, y) in zip(windows, TRUTH_3):
        assert r1 - r0 <= 2 * SEARCH_PX + 2 * MarkerParams().decimation
        assert w1 - w0 <= 2 * SEARCH_PX + 2 * MarkerParams().decimation
        assert w0 <= x < w1 and r0 <= y < r1


def test_nan_prediction_is_no_prediction(rng):
    image = _three_view_frame(rng, TRUTH_3)
    near = np.array([[np.nan, np.nan], [np.nan, 5.0], [np.inf, 3.0]])
    assert_allclose(find_markers(image, strips=STRIPS, near=near),
                    find_markers(image, strips=STRIPS), rtol=0, atol=TOL_SAME_FIT_PX)


@pytest.mark.parametrize("offset", [(0.0, 200.0), (0.0, -200.0), (200.0, 0.0), (-200.0, 150.0)])
def test_wrong_prediction_falls_back_to_whole_strip(rng, offset):
    image = _three_view_frame(rng, TRUTH_3)
    full = find_markers(image, strips=STRIPS)
    got = find_markers(image, strips=STRIPS, near=TRUTH_3 + offset)
    assert_allclose(got, full, rtol=0, atol=TOL_SAME_FIT_PX)
    assert_allclose(got, TRUTH_3, atol=TOL_MAX_PX)


def test_prediction_on_the_window_edge_falls_back(rng):
    # The blob (about 4.4 px radius at the threshold) straddles the window's side: its pooled
    # component touches that side and is left out of the window; the whole strip finds it.
    image = _three_view_frame(rng, TRUTH_3)
    full = find_markers(image, strips=STRIPS)
    for dx in (SEARCH_PX - 1.0, SEARCH_PX + 2.0, -SEARCH_PX - 1.5):
        got = find_markers(image, strips=STRIPS, near=TRUTH_3 + (dx, 0.0))
        assert_allclose(got, full, rtol=0, atol=TOL_SAME_FIT_PX)


@pytest.mark.parametrize("gap_px", [6.0, 10.0])
def test_marker_merged_with_stripe_tracked_equals_full(rng, gap_px):
    # The stripe runs out of the window with the marker on its end: one component crossing the
    # window's side, left to the whole-strip search (merged-core seeds, stripe masked).
    img = np.zeros((300, 500))
    x_end = 250.3
    cols = np.arange(20, int(x_end) + 1)
    _stripe(img, cols, 150.0 + 0.1 * (cols - x_end))
    _blob(img, x_end + gap_px, 150.4)
    image = _finish(img, rng)
    full = find_marker(image, columns=(0, 500))
    assert_allclose(full, (x_end + gap_px, 150.4), atol=TOL_NEAR_STRIPE_PX)
    got = find_marker(image, columns=(0, 500), near=(x_end + gap_px - 2.0, 152.0))
    assert_allclose(got, full, rtol=0, atol=TOL_SAME_FIT_PX)


def test_prediction_near_second_blob_returns_that_blob(rng):
    # Documented: the window's blob wins even when a brighter one is elsewhere in the strip.
    img = np.zeros(FRAME_SHAPE)
    _blob(img, 600.4, 300.3, peak=150.0)
    _blob(img, 1200.2, 800.6, peak=230.0)
    image = _finish(img, rng)
    assert_allclose(find_marker(image, columns=STRIPS[1]), (1200.2, 800.6), atol=TOL_MAX_PX)
    assert_allclose(find_marker(image, columns=STRIPS[1], near=(610.0, 290.0)), (600.4, 300.3),
                    atol=TOL_MAX_PX)


@pytest.mark.parametrize("x, near_x, strip", [
    (392.3, 380.0, 1),     # just inside the direct view's left edge, predicted left of it
    (1527.4, 1545.0, 1),   # right edge of the direct view, predicted in the mirror strip
    (10.6, 2.0, 0),        # left image border
    (1908.8, 1919.0, 2),   # right image border
    (396.0, 384.0 - SEARCH_PX - 10.0, 1),  # window entirely outside the strip: whole strip
])
def test_prediction_near_strip_edge_is_clipped(rng, x, near_x, strip):
    img = np.zeros(FRAME_SHAPE)
    _blob(img, x, 600.3)
    image = _finish(img, rng)
    full = find_marker(image, columns=STRIPS[strip])
    assert_allclose(full, (x, 600.3), atol=TOL_MAX_PX)
    got = find_marker(image, columns=STRIPS[strip], near=(near_x, 604.0))
    assert_allclose(got, full, rtol=0, atol=TOL_SAME_FIT_PX)


@pytest.mark.parametrize("y, near_y", [(10.4, 1.0), (1189.7, 1199.0), (600.2, -20.0)])
def test_prediction_near_image_border_is_clipped(rng, y, near_y):
    img = np.zeros(FRAME_SHAPE)
    _blob(img, 900.3, y)
    image = _finish(img, rng)
    full = find_marker(image, columns=STRIPS[1])
    assert_allclose(full, (900.3, y), atol=TOL_MAX_PX)
    got = find_marker(image, columns=STRIPS[1], near=(905.0, near_y))
    assert_allclose(got, full, rtol=0, atol=TOL_SAME_FIT_PX)


@pytest.mark.parametrize("near, half", [((400.0, 600.0), 48.0), ((383.9, 0.0), 48.0),
                                        ((1535.2, 1199.9), 48.0), ((900.0, 600.0), 3.0),
                                        ((910.7, 37.3), 100.5)])
def test_search_window_on_block_grid_and_clipped(near, half):
    f = MarkerParams().decimation
    c0, c1 = STRIPS[1]
    height = FRAME_SHAPE[0]
    r0, r1, w0, w1 = marker_mod._search_window(near, half, c0, c1, height, f)
    assert c0 <= w0 < w1 <= c1 and 0 <= r0 < r1 <= height
    assert (w0 - c0) % f == 0 and r0 % f == 0
    assert w1 == c1 or (w1 - c0) % f == 0
    assert r1 == height or r1 % f == 0
    # Holds every pixel centre within near +- half that lies inside the strip and the image.
    x, y = near
    assert w0 <= max(c0, np.ceil(x - half)) and min(c1, np.floor(x + half) + 1) <= w1
    assert r0 <= max(0, np.ceil(y - half)) and min(height, np.floor(y + half) + 1) <= r1


def test_search_window_none_when_outside_or_whole():
    c0, c1 = STRIPS[1]
    h = FRAME_SHAPE[0]
    assert marker_mod._search_window((c0 - 60.0, 500.0), 48.0, c0, c1, h, 4) is None
    assert marker_mod._search_window((900.0, -60.0), 48.0, c0, c1, h, 4) is None
    assert marker_mod._search_window((np.nan, 500.0), 48.0, c0, c1, h, 4) is None
    assert marker_mod._search_window((900.0, 600.0), 5000.0, c0, c1, h, 4) is None


def test_tracking_a_moving_marker_equals_full_search():
    # Rendered frames (simulator.imaging) of a marker moving ~5 px per frame in all three views,
    # with a stripe; the prediction is the previous frame's result, as in the live service.
    rng = np.random.default_rng(77)
    model = ImageModel()
    cols = np.arange(430, 1490)
    previous = None
    for k in range(12):
        truth = np.array([[900.0 + 2.1 * k, 200.0 + 5.3 * k], [150.0 - 1.7 * k, 190.0 + 5.1 * k],
                          [1720.0 + 1.3 * k, 205.0 + 5.2 * k]])
        image = render_image(*FRAME_SHAPE, model, rng, stripe_cols=cols,
                             stripe_rows=700.0 + 30.0 * np.sin(cols / 90.0), marker_xy=truth)
        full = find_markers(image, strips=((384, 1536), (0, 384), (1536, 1920)))
        assert_allclose(full, truth, atol=TOL_MAX_PX)
        got = find_markers(image, strips=((384, 1536), (0, 384), (1536, 1920)), near=previous)
        assert_allclose(got, full, rtol=0, atol=TOL_SAME_FIT_PX)
        previous = got


# --- pooled candidates kernel -------------------------------------------------------------------


def _max_pool_reference(sub: np.ndarray, f: int) -> np.ndarray:
    """(ceil(H/f), ceil(W/f)) block maxima with numpy (the module's former implementation)."""
    h, w = sub.shape
    hc, wc = h - h % f, w - w % f
    rows = sub[0:hc:f]
    for k in range(1, f):
        rows = np.maximum(rows, sub[k:hc:f])
    if hc < h:
        rows = np.vstack([rows, sub[hc:].max(axis=0, keepdims=True)])
    out = rows[:, 0:wc:f]
    for k in range(1, f):
        out = np.maximum(out, rows[:, k:wc:f])
    if wc < w:
        out = np.hstack([out, rows[:, wc:].max(axis=1, keepdims=True)])
    return out


@pytest.mark.parametrize("f", [1, 2, 3, 4, 5, 8])
@pytest.mark.parametrize("seed", range(8))
def test_pool_components_equals_numpy_and_opencv(f, seed):
    rng = np.random.default_rng(seed)
    height, width = (int(v) for v in rng.integers(1, 140, 2) * 2 + 1)  # odd sizes
    full = rng.integers(0, 256, (height + 7, width + 9), dtype=np.uint8)
    # Sparse bright pixels (blobs, lines) on a dark background, as in a frame.
    full[rng.random(full.shape) > rng.uniform(0.005, 0.2)] //= 8
    r0, c0 = int(rng.integers(0, 8)), int(rng.integers(0, 10))
    r1, c1 = r0 + height, c0 + width
    thr = int(rng.integers(20, 120))
    pooled = np.empty(_pooling.pooled_shape(height, width, f), np.uint8)
    peak, stats = _pooling.pool_components(full, r0, r1, np.array([[c0, c1]]), f, thr, pooled)

    ref = _max_pool_reference(full[r0:r1, c0:c1], f)
    np.testing.assert_array_equal(pooled, ref)
    assert peak.tolist() == [ref.max()]
    assert (stats[:, _pooling.STAT_WINDOW] == 0).all()
    n, labels, cv_stats, _ = cv2.connectedComponentsWithStats((ref > thr).view(np.uint8),
                                                              connectivity=8)
    assert len(stats) == n - 1
    # OpenCV's components, put in raster order of their first block (the kernel's order).
    flat = labels.ravel()
    _, first = np.unique(flat, return_index=True)  # label 0 (background) first
    order = 1 + np.argsort(first[1:])
    np.testing.assert_array_equal(stats[:, :5], cv_stats[order])
    ys, xs = np.divmod(np.arange(flat.size), ref.shape[1])
    peak_ref = np.zeros(n, np.int64)
    np.maximum.at(peak_ref, flat, ref.ravel())
    np.testing.assert_array_equal(stats[:, _pooling.STAT_PEAK], peak_ref[order])
    moments = {_pooling.STAT_SX: xs, _pooling.STAT_SY: ys, _pooling.STAT_SXX: xs * xs,
               _pooling.STAT_SYY: ys * ys, _pooling.STAT_SXY: xs * ys}
    for col, values in moments.items():
        sums = np.zeros(n, np.int64)
        np.add.at(sums, flat, values)
        np.testing.assert_array_equal(stats[:, col], sums[order])


@pytest.mark.parametrize("f", [1, 3, 4])
@pytest.mark.parametrize("seed", range(4))
def test_pool_components_several_windows_in_one_pass(f, seed):
    # Windows side by side (the three views), apart, and overlapping: each as if pooled alone.
    rng = np.random.default_rng(100 + seed)
    image = rng.integers(0, 256, (int(rng.integers(20, 90)) * 2 + 1, 301), dtype=np.uint8)
    image[rng.random(image.shape) > 0.05] //= 8
    cols = np.array([[61, 240], [0, 61], [240, 301], [17, 18], [100, 203]])
    r0, r1, thr = 3, image.shape[0] - 2, 90
    layout = _pooling.pooled_layout(cols, f)
    pooled = np.empty((_pooling.pooled_shape(r1 - r0, 1, f)[0], layout[-1]), np.uint8)
    peak, stats = _pooling.pool_components(image, r0, r1, cols, f, thr, pooled)
    for k, (c0, c1) in enumerate(cols):
        alone = np.empty(_pooling.pooled_shape(r1 - r0, c1 - c0, f), np.uint8)
        peak_k, stats_k = _pooling.pool_components(image, r0, r1, cols[k : k + 1], f, thr, alone)
        np.testing.assert_array_equal(pooled[:, layout[k] : layout[k + 1]], alone)
        assert peak[k] == peak_k[0]
        mine = stats[stats[:, _pooling.STAT_WINDOW] == k]
        np.testing.assert_array_equal(mine[:, : _pooling.STAT_WINDOW],
                                      stats_k[:, : _pooling.STAT_WINDOW])


def test_pool_components_nothing_above_threshold():
    image = np.full((37, 53), 60, np.uint8)
    pooled = np.empty(_pooling.pooled_shape(37, 53, 4), np.uint8)
    peak, stats = _pooling.pool_components(image, 0, 37, np.array([[0, 53]]), 4, 60, pooled)
    assert peak.tolist() == [60] and stats.shape == (0, _pooling.N_STATS)
    assert (pooled == 60).all()


# --- trigger speed-up keeps its answers ----------------------------------------------------------


def test_marker_present_with_and_without_marker_rendered():
    rng = np.random.default_rng(5)
    model = ImageModel()
    cols = np.arange(430, 1490)
    rows = 600.0 + 40.0 * np.sin(cols / 70.0)
    with_marker = render_image(*FRAME_SHAPE, model, rng, stripe_cols=cols, stripe_rows=rows,
                               marker_xy=[[900.2, 300.7], [200.4, 310.1], [1700.9, 305.3]])
    without = render_image(*FRAME_SHAPE, model, rng, stripe_cols=cols, stripe_rows=rows)
    assert marker_present(with_marker, strips=STRIPS)
    assert not marker_present(without, strips=STRIPS)
