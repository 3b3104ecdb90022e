"""Reference image model: statistics of the rendered frames against the model."""

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from simulator.imaging import (RENDER_HALF_WIDTH_SIGMAS, ImageModel, cramer_rao_bound_px,
                               render_image)

# Background statistics over 0.5 Mpx: standard error of the mean ~0.004 DN; the 256-level noise
# table quantises the distribution (see simulator.imaging), allowing ~1 % on the std.
MEAN_TOL_DN = 0.03
STD_REL_TOL = 0.02
# Centroid of the stripe in a column vs. its exact row (mean over many columns), px.
CENTROID_BIAS_TOL_PX = 0.005
CENTROID_RMS_TOL_PX = 0.05


def test_background_statistics():
    model = ImageModel()
    img = render_image(512, 1024, model, np.random.default_rng(0))
    assert img.dtype == np.uint8 and img.shape == (512, 1024)
    assert_allclose(img.mean(), model.background_dn, atol=MEAN_TOL_DN)
    # rounding adds 1/12 DN^2 of variance
    expected_std = math.sqrt(model.read_noise_dn**2 + 1.0 / 12.0)
    assert_allclose(img.std(), expected_std, rtol=STD_REL_TOL)


def test_ambient_gradient():
    model = ImageModel(ambient_dn=40.0)
    img = render_image(400, 600, model, np.random.default_rng(0)).astype(float)
    assert_allclose(img[:20, :20].mean(), model.background_dn + 40.0 * 0.02, atol=0.5)
    assert_allclose(img[-20:, -20:].mean(), model.background_dn + 40.0 * 0.98, atol=0.5)
    assert_allclose(img.mean(), model.background_dn + 20.0, atol=0.1)
    # noise on top of the gradient: pixel differences along a row (gradient 0.03 DN/px) carry
    # twice the variance of one pixel
    noise_std = np.diff(img[150:250], axis=1).std() / math.sqrt(2.0)
    assert_allclose(noise_std, math.sqrt(model.read_noise_dn**2 + 1.0 / 12.0), rtol=STD_REL_TOL)


@pytest.mark.parametrize("speckle", [0.0, 0.1])
def test_stripe_centroid(speckle):
    model = ImageModel(speckle_contrast=speckle)
    rng = np.random.default_rng(3)
    n = 3000
    rows = rng.uniform(20.0, 44.0, n)
    img = render_image(64, n, model, rng, stripe_cols=np.arange(n), stripe_rows=rows)
    r = np.arange(64)[:, None]
    near = np.abs(r - rows[None, :]) <= 6
    w = np.where(near, img.astype(float) - model.background_dn, 0.0)
    centroid = (w * r).sum(axis=0) / w.sum(axis=0)
    err = centroid - rows
    assert abs(err.mean()) < CENTROID_BIAS_TOL_PX
    assert np.sqrt(np.mean(err**2)) < CENTROID_RMS_TOL_PX
    peak = img.max(axis=0).astype(float) - model.background_dn
    assert_allclose(np.median(peak), model.stripe_peak_dn, rtol=0.03)
    if speckle:
        # amplitude modulation of the stripe: std of the per-column peak ~ the speckle contrast
        assert 0.07 < np.std(peak) / np.mean(peak) < 0.13


def test_double_stripes_add():
    model = ImageModel(read_noise_dn=0.0, speckle_contrast=0.0)
    img = render_image(40, 1, model, np.random.default_rng(0), stripe_cols=[0, 0],
                       stripe_rows=[20.0, 20.0], stripe_gain=[0.25, 0.25])
    assert img[20, 0] == 110


def test_saturation_clips():
    model = ImageModel()
    img = render_image(64, 100, model, np.random.default_rng(0), stripe_cols=np.arange(100),
                       stripe_rows=np.full(100, 30.0), stripe_gain=3.0)
    assert img.max() == 255
    assert np.all(img[30] == 255)
    low = render_image(64, 100, ImageModel(saturation_dn=100.0), np.random.default_rng(0),
                       stripe_cols=np.arange(100), stripe_rows=np.full(100, 30.0))
    assert low.max() == 100


def test_marker_blob():
    model = ImageModel(read_noise_dn=0.0)
    img = render_image(100, 120, model, np.random.default_rng(0),
                       marker_xy=[[40.3, 60.7], [np.nan, 5.0]])
    w = img.astype(float) - model.background_dn
    rr, cc = np.mgrid[:100, :120]
    assert_allclose((w * cc).sum() / w.sum(), 40.3, atol=0.01)
    assert_allclose((w * rr).sum() / w.sum(), 60.7, atol=0.01)
    assert_allclose(w.max(), model.marker_peak_dn, rtol=0.05)


def test_same_seed_same_image():
    kw = dict(stripe_cols=np.arange(300), stripe_rows=np.linspace(10, 50, 300),
              marker_xy=[[100.0, 30.0]])
    a = render_image(64, 300, ImageModel(), np.random.default_rng(7), **kw)
    b = render_image(64, 300, ImageModel(), np.random.default_rng(7), **kw)
    c = render_image(64, 300, ImageModel(), np.random.default_rng(8), **kw)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_stripe_over_a_background_frame():
    """Drawn over a background frame, a stripe is the same stripe and the background is that
    frame's, pixel for pixel; a frame drawn next shows nothing of the one before."""
    model = ImageModel()
    rng = np.random.default_rng(4)
    n = 3000
    background = render_image(64, n, model, rng)
    rows = rng.uniform(20.0, 44.0, n)
    img = render_image(64, n, model, rng, stripe_cols=np.arange(n), stripe_rows=rows,
                       background=background)
    r = np.arange(64)[:, None]
    reach = math.ceil(RENDER_HALF_WIDTH_SIGMAS * model.stripe_sigma_px) + 1  # drawn afresh
    support = np.abs(r - rows[None, :]) <= reach
    assert np.array_equal(img[~support], background[~support])
    assert not np.array_equal(img[support], background[support])
    w = np.where(np.abs(r - rows[None, :]) <= 6, img.astype(float) - model.background_dn, 0.0)
    err = (w * r).sum(axis=0) / w.sum(axis=0) - rows
    assert abs(err.mean()) < CENTROID_BIAS_TOL_PX
    assert np.sqrt(np.mean(err**2)) < CENTROID_RMS_TOL_PX
    # the same scene drawn whole: the same peak level
    whole = render_image(64, n, model, rng, stripe_cols=np.arange(n), stripe_rows=rows)
    assert_allclose(np.median(img.max(axis=0)), np.median(whole.max(axis=0)), atol=2.0)
    elsewhere = render_image(64, n, model, rng, stripe_cols=np.arange(n),
                             stripe_rows=np.full(n, 5.0), background=background)
    far = np.broadcast_to(np.abs(r - 5.0) > reach, img.shape)
    assert np.array_equal(elsewhere[far], background[far])
    again = render_image(64, n, model, rng, stripe_cols=np.arange(n), stripe_rows=rows,
                         background=background)
    assert_allclose(np.median(again.max(axis=0)), np.median(img.max(axis=0)), atol=2.0)
    with pytest.raises(ValueError, match="background"):
        render_image(64, n, model, rng, background=background[:, :10])


def test_cramer_rao_bound_reference():
    assert_allclose(cramer_rao_bound_px(ImageModel()), 0.0195, atol=5e-5)
    assert_allclose(cramer_rao_bound_px(ImageModel(read_noise_dn=6.0)), 0.039, atol=1e-4)


def test_bad_model_raises():
    with pytest.raises(ValueError, match="saturation_dn"):
        render_image(8, 8, ImageModel(saturation_dn=300.0), np.random.default_rng(0))
