"""Stripe extraction against analytic ground truth rendered by the reference image model."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from scanner_core.stripe.extractor import METHODS, Reason, StripeResult, extract
from simulator.imaging import ImageModel, cramer_rao_bound_px, render_image

HEIGHT = 64
N_COLUMNS = 4000
# RMS error bounds (px) per method at the reference model (noise 3 DN, speckle 0.1); measured
# 0.026 / 0.038 / 0.042 / 0.023 / 0.020 on the reference frames, with ~10 % margin.
RMS_TOL_PX = {"cog": 0.035, "gaussian3": 0.045, "parabola": 0.05, "blais_rioux": 0.03}
# The least-squares Gaussian fit must approach the Cramer-Rao bound.
LSQ_CRB_FACTOR = 1.3
# No estimator may be biased by more than this (px); the standard error of the mean here is
# about 0.0007 px.
BIAS_TOL_PX = 0.01
# Every column of a clean single stripe must be found, except the ~0.7 % that the reference
# speckle (+20 % amplitude, 2 sigma) pushes into saturation.
MIN_VALID_FRACTION = 0.98
MIN_VALID_FRACTION_NO_SPECKLE = 0.999


@pytest.fixture(scope="module")
def reference_frame():
    rng = np.random.default_rng(20240601)
    cols = np.arange(N_COLUMNS)
    rows = rng.uniform(16.0, HEIGHT - 16.0, N_COLUMNS)  # uniform sub-pixel phase
    img = render_image(HEIGHT, N_COLUMNS, ImageModel(), rng, stripe_cols=cols, stripe_rows=rows)
    return img, rows


@pytest.mark.parametrize("method", METHODS)
def test_accuracy_against_ground_truth(reference_frame, method):
    img, truth = reference_frame
    res = extract(img, method=method)
    assert res.valid.mean() >= MIN_VALID_FRACTION
    assert np.all(res.reason[~res.valid] == Reason.SATURATED)
    err = (res.row - truth)[res.valid]
    rms = float(np.sqrt(np.mean(err**2)))
    tol = LSQ_CRB_FACTOR * cramer_rao_bound_px(ImageModel()) if method == "lsq_gauss" else RMS_TOL_PX[method]
    assert rms < tol, f"{method}: RMS {rms:.4f} px >= {tol:.4f} px"
    assert abs(float(np.mean(err))) < BIAS_TOL_PX


@pytest.mark.parametrize("method", METHODS)
def test_result_contract(reference_frame, method):
    img, _ = reference_frame
    res = extract(img, method=method)
    assert isinstance(res, StripeResult)
    for name, dtype in (("row", np.float32), ("peak", np.float32), ("width", np.float32),
                        ("valid", np.bool_), ("reason", np.uint8)):
        arr = getattr(res, name)
        assert arr.shape == (N_COLUMNS,) and arr.dtype == dtype, name
    assert np.array_equal(res.valid, res.reason == Reason.OK)
    assert np.all(np.isnan(res.row) == ~res.valid)
    assert_allclose(res.peak, img.max(axis=0))
    # sigma-like width of the 1.5 px stripe
    assert 1.2 < float(np.median(res.width[res.valid])) < 1.8


def _render_columns(rows_per_col, gains_per_col, seed=0, height=HEIGHT, model=ImageModel()):
    cols, rows, gains = [], [], []
    for c, (rr, gg) in enumerate(zip(rows_per_col, gains_per_col)):
        cols += [c] * len(rr)
        rows += list(rr)
        gains += list(gg)
    return render_image(height, len(rows_per_col), model, np.random.default_rng(seed),
                        stripe_cols=np.array(cols, int), stripe_rows=np.array(rows, float),
                        stripe_gain=np.array(gains, float))


@pytest.mark.parametrize("method", METHODS)
def test_saturated_columns_invalid(method):
    # the historical behaviour, kept as an option (saturated plateaus are measured by default:
    # test_stripe_surfaces.py)
    n = 200
    img = _render_columns([[30.3]] * n, [[2.0]] * n)
    assert (img == 255).any(axis=0).all()
    res = extract(img, method=method, saturation="reject")
    assert not res.valid.any()
    assert np.all(res.reason == Reason.SATURATED)
    assert np.all(np.isnan(res.row))


@pytest.mark.parametrize("method", METHODS)
def test_empty_columns_invalid(method):
    # background and read noise only: noise pixels above the threshold must not pass as stripes
    img = render_image(HEIGHT, 5000, ImageModel(), np.random.default_rng(1))
    res = extract(img, method=method)
    assert not res.valid.any()
    assert np.all(np.isnan(res.row))
    assert set(np.unique(res.reason)) <= {Reason.NO_PEAK, Reason.TOO_NARROW}


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("main_first", [True, False])
def test_double_peaked_columns_invalid(method, main_first):
    n = 300
    main, second = (15.2, 45.7) if main_first else (45.7, 15.2)
    img = _render_columns([[main, second]] * n, [[1.0, 0.5]] * n, model=ImageModel(speckle_contrast=0.0))
    # the historical behaviour, kept as policy="reject" (the default picks a peak:
    # test_stripe_surfaces.py)
    res = extract(img, method=method, policy="reject")
    assert not res.valid.any()
    assert np.all(res.reason == Reason.DOUBLE)


@pytest.mark.parametrize("method", METHODS)
def test_weak_second_peak_tolerated(method):
    # a reflection at 10 % of the stripe stays below DOUBLE_PEAK_RATIO: the column is kept
    n = 300
    img = _render_columns([[15.2, 45.7]] * n, [[1.0, 0.1]] * n, model=ImageModel(speckle_contrast=0.0))
    res = extract(img, method=method)
    assert res.valid.mean() >= MIN_VALID_FRACTION_NO_SPECKLE
    assert np.all(np.abs(res.row[res.valid] - 15.2) < 0.2)


@pytest.mark.parametrize("method", METHODS)
def test_too_wide_invalid(method):
    n = 100
    model = ImageModel(stripe_sigma_px=6.0, speckle_contrast=0.0)
    img = _render_columns([[32.0]] * n, [[1.0]] * n, model=model)
    res = extract(img, method=method, max_width=4.0)
    assert not res.valid.any()
    assert np.all(res.reason == Reason.TOO_WIDE)


@pytest.mark.parametrize("method", METHODS)
def test_columns_slice(reference_frame, method):
    img, truth = reference_frame
    c0, c1 = 100, 350
    res = extract(img, method=method, columns=(c0, c1))
    full = extract(img, method=method)
    inside = np.zeros(img.shape[1], bool)
    inside[c0:c1] = True
    assert not res.valid[~inside].any()
    assert np.all(res.reason[~inside] == Reason.NOT_PROCESSED)
    assert np.all(np.isnan(res.row[~inside]))
    assert_allclose(res.row[inside], full.row[inside], equal_nan=True)


@pytest.mark.parametrize(
    "bad",
    [np.zeros((8, 8, 3), np.uint8), np.zeros((8, 8), np.float32), np.zeros(8, np.uint8),
     np.zeros((8, 8), np.uint16), [[0, 1], [2, 3]]],
)
def test_bad_image_raises(bad):
    with pytest.raises(ValueError, match="`image` must be 2-D uint8"):
        extract(bad)


def test_bad_options_raise():
    img = np.zeros((16, 16), np.uint8)
    with pytest.raises(ValueError, match="`method`"):
        extract(img, method="nope")
    with pytest.raises(ValueError, match="`columns`"):
        extract(img, columns=(5, 40))
    with pytest.raises(ValueError, match="`window`"):
        extract(img, window=1)
    with pytest.raises(ValueError, match="`window` must be 2 to 127"):
        extract(img, window=128)
    with pytest.raises(ValueError, match="unknown parameter"):
        extract(img, thresh=3)


def test_non_contiguous_image(reference_frame):
    img, _ = reference_frame
    view = img[:, ::2]
    assert_allclose(extract(view).row, extract(np.ascontiguousarray(view)).row, equal_nan=True)


def _walks(img, am, threshold, t_cog, window, max_walk):
    """Per column (width, count, centre) by the separate estimators and by the single walks
    the kernel calls (``within_window``, else ``width_count_cog``)."""
    from scanner_core.stripe import estimators as est

    h = img.shape[0]
    apart, single = [], []
    out = np.empty(4)
    for c in range(img.shape[1]):
        a = int(am[c])
        level = 0.5 * (float(img[a, c]) + threshold)
        apart.append((est.fwhm_width(img, c, a, h, level, max_walk),
                      est.count_above(img, c, a, h, threshold, window),
                      est.cog(img, c, a, h, t_cog, window, np.nan, max_walk)))
        if not est.within_window(img, c, a, h, level, max_walk, threshold, window, t_cog,
                                 np.nan, out):
            est.width_count_cog(img, c, a, h, level, max_walk, threshold, window, t_cog,
                                np.nan, max_walk, out)
        single.append(tuple(out[:3]))
    return np.array(apart), np.array(single)


def test_single_walks_equal_the_separate_estimators():
    # 200 frames of random stripes (sigma 0.3-8 px, peaks 5-300 DN, noise 0-8 DN, stripes at
    # the frame's edges), levels and windows: the walks that read each pixel once give what
    # the three estimators give one by one
    rng = np.random.default_rng(7)
    for _ in range(200):
        h, w = 60, 120
        r = np.arange(h)[:, None]
        row = rng.uniform(-5, h + 5) + rng.normal(0, 3, w).cumsum() * 0.1
        img = np.clip(np.round(rng.uniform(0, 40) + rng.uniform(5, 300)
                               * np.exp(-0.5 * ((r - row) / rng.uniform(0.3, 8)) ** 2)
                               + rng.normal(0, rng.uniform(0, 8), (h, w))), 0, 255).astype(np.uint8)
        am = img.argmax(axis=0)
        threshold = float(rng.uniform(0, 0.9) * img.max(axis=0).min())
        t_cog = float(rng.uniform(0, 1) * threshold)
        window, max_walk = int(rng.integers(2, 8)), int(rng.integers(3, 40))
        apart, single = _walks(img, am, threshold, t_cog, window, max_walk)
        assert_allclose(single, apart, rtol=0, atol=1e-9, equal_nan=True)


def _column_max_by_definition(img, r0, r1, c0, c1, sep):
    """Per column, row by row: the maximum, its first row, and the largest value seen more
    than `sep` rows from the running maximum's row when it was seen (the old maximum demoted
    into it when a new one appears far away)."""
    n = c1 - c0
    mx, am, sec = np.zeros(n, np.uint8), np.zeros(n, np.uint16), np.zeros(n, np.uint8)
    for j in range(n):
        m, a, s = 0, 0, 0
        for r in range(r0, r1):
            v = int(img[r, c0 + j])
            if r - a > sep:
                s = max(s, min(m, v))
            if v > m:
                m, a = v, r
        mx[j], am[j], sec[j] = m, a, s
    return mx, am, sec


@pytest.mark.parametrize("kind", ["noise", "ties", "stripes", "ramp"])
@pytest.mark.parametrize("sep", [0, 8, 40, 254])
def test_column_maxima_in_byte_blocks_follow_their_definition(kind, sep):
    """The column maxima read in blocks of rows coded as bytes (``passes.column_max``) give
    exactly the running maximum, its row and the far second maximum, over frames taller than
    a byte's 256 rows and at either end of ``sep``."""
    from scanner_core.stripe import passes

    rng = np.random.default_rng(sep)
    h, w = 700, 37
    if kind == "noise":
        img = rng.integers(0, 256, (h, w), dtype=np.uint8)
    elif kind == "ties":
        img = rng.integers(0, 3, (h, w), dtype=np.uint8)
    elif kind == "stripes":
        img = rng.normal(12.0, 4.0, (h, w)).clip(0, 255).astype(np.uint8)
        for c in range(w):
            for r in rng.integers(0, h, 3):
                img[max(r - 2, 0):r + 3, c] = rng.integers(20, 256)
    else:
        img = np.sort(rng.integers(0, 256, (h, w), dtype=np.uint8), axis=0)
    for r0, r1, c0, c1 in ((0, h, 0, w), (3, 611, 5, 30), (290, 300, 0, 1), (0, 9, 2, 37)):
        mx, am, sec = (np.zeros(c1 - c0, t) for t in (np.uint8, np.uint16, np.uint8))
        passes.column_max(img, r0, r1, c0, c1, sep, mx, am, sec)
        expected = _column_max_by_definition(img, r0, r1, c0, c1, sep)
        for got, want in zip((mx, am, sec), expected):
            np.testing.assert_array_equal(got, want)


def _prominence_by_definition(v, r0, r1, s0, s1, reach):
    """``kernel.prominent_peak``'s row, background and prominence, pixel by pixel."""
    best, row, back = -np.inf, None, None
    for r in range(max(s0, r0 + 1), min(s1, r1 - 1)):
        b = max(v[max(r - reach, r0):r].min(), v[r + 1:min(r + reach, r1 - 1) + 1].min())
        if v[r] - b > best:
            best, row, back = v[r] - b, r, b
    return best, row, back


def test_prominent_peak_follows_its_definition():
    """The row standing highest over the lower pixels within ``reach`` on each side, from
    blocks' running minima (``kernel.prominent_peak``), is the one its definition gives: any
    reach, bands cut anywhere, the search band inside or beside them."""
    from scanner_core.stripe.kernel import prominent_peak

    rng = np.random.default_rng(5)
    out = np.zeros(2)
    for _ in range(2000):
        h = int(rng.integers(3, 80))
        img = rng.integers(0, 256, (h, 3)).astype(np.uint8)
        reach = int(rng.integers(1, 20))
        r0 = int(rng.integers(0, h - 2))
        r1 = int(rng.integers(r0 + 1, h + 1))
        s0 = int(rng.integers(r0, r1))
        s1 = int(rng.integers(s0, r1 + 1))
        got = prominent_peak(img, 1, r0, r1, s0, s1, reach, out)
        best, row, back = _prominence_by_definition(img[:, 1].astype(int), r0, r1, s0, s1,
                                                    reach)
        assert got == best
        if row is not None:
            assert (out[0], out[1]) == (row, back)


def test_a_step_is_not_prominent_and_a_bump_is():
    """A texture's step stands over neither side's lowest pixel; a stripe on the dark side of
    it, dimmer than the lit side, stands over both."""
    from scanner_core.stripe.kernel import prominent_peak

    col = np.full(60, 70, np.uint8)
    col[30:] = 30  # a lit square above row 30, a dark one below
    out = np.zeros(2)
    img = col[:, None]
    assert prominent_peak(img, 0, 0, 60, 0, 60, 8, out) <= 0.0
    stripe = (30 + 30 * np.exp(-0.5 * ((np.arange(60) - 44.0) / 2.0) ** 2)).astype(np.uint8)
    col[30:] = stripe[30:]
    assert prominent_peak(col[:, None], 0, 0, 60, 0, 60, 8, out) == 30.0
    assert (out[0], out[1]) == (44, 30)
