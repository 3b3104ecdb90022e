"""Exposure control: the dynamic step, the split into time and gain, the
multiple-exposure merge, and convergence on a surface whose brightness changes mid-pass."""
from dataclasses import replace

import numpy as np
import pytest

from scanner_core.devices import ExposureControl
from scanner_core.pipeline.exposure import (ExposureController, ExposureParams, merge_exposure_pairs,
                                            next_brightness, split_brightness, stripe_brightness)
from scanner_core.stripe.extractor import Reason, extract
from simulator.imaging import ImageModel, render_image

NOMINAL_US = 1000.0
WIDTH, HEIGHT = 800, 160


class FakeCamera:
    """A stripe camera whose brightness follows exposure x gain x the surface's reflectance
    (the reference image model scaled, read noise scaled by the gain)."""

    exposure_range_us = (20.0, 20000.0)
    gain_range = (1.0, 16.0)

    def __init__(self, reflectance):
        self.reflectance = reflectance  # frame index -> factor on the model's 200 DN
        self.exposure_us, self.gain = NOMINAL_US, 1.0
        self.k = 0

    def set_exposure(self, exposure_us, gain=1.0):
        self.exposure_us, self.gain = exposure_us, gain

    def frame(self, rng):
        scale = self.reflectance(self.k) * self.exposure_us * self.gain / NOMINAL_US
        model = replace(ImageModel(), stripe_peak_dn=200.0 * scale,
                        read_noise_dn=3.0 * self.gain)
        cols = np.arange(100, 700)
        rows = 80.0 + 10.0 * np.sin(cols / 90.0)
        image = render_image(HEIGHT, WIDTH, model, rng, stripe_cols=cols, stripe_rows=rows,
                             stripe_gain=np.ones(len(cols)))
        taken = (self.exposure_us, self.gain)
        self.k += 1
        return image, taken


def _peaks(result):
    has = ~np.isin(result.reason, (Reason.NO_PEAK, Reason.NOT_PROCESSED))
    return result.peak[has]


def test_fake_camera_is_exposure_control():
    assert isinstance(FakeCamera(lambda k: 1.0), ExposureControl)


def test_dynamic_step_is_deadbeat_and_bounded():
    params = ExposureParams(mode="dynamic")
    # a stripe at 45 DN at 1000 us: 4x brighter gives 180 DN
    assert next_brightness(1000.0, 45.0, params) == pytest.approx(4000.0)
    # far too dark: at most max_step per update
    assert next_brightness(1000.0, 5.0, params) == pytest.approx(4000.0)
    # near full scale: by as much as allowed (how far it clips is unknown)
    assert next_brightness(1000.0, 235.0, params) == pytest.approx(1000.0 * 180.0 / 235.0)
    assert next_brightness(1000.0, 245.0, params) == pytest.approx(1000.0 / 4.0)
    # within the dead band, and without a stripe: left alone
    assert next_brightness(1000.0, 175.0, params) is None
    assert next_brightness(1000.0, float("nan"), params) is None


def test_stripe_brightness_needs_enough_columns():
    assert np.isnan(stripe_brightness(np.full(5, 100.0), 10.0, 75.0))
    peaks = np.concatenate([np.full(75, 50.0), np.full(25, 250.0)])
    assert stripe_brightness(peaks, 10.0, 75.0) == pytest.approx(40.0 + 0.25 * 200.0, abs=1e-9)


def test_split_prefers_time_then_gain():
    e, g = split_brightness(3000.0, (20.0, 20000.0), (1.0, 16.0), max_exposure_us=5000.0)
    assert (e, g) == (3000.0, 1.0)
    e, g = split_brightness(20000.0, (20.0, 20000.0), (1.0, 16.0), max_exposure_us=5000.0)
    assert e == 5000.0 and g == pytest.approx(4.0)
    e, g = split_brightness(1e9, (20.0, 20000.0), (1.0, 16.0), max_exposure_us=5000.0)
    assert (e, g) == (5000.0, 16.0)  # the camera's limits hold
    e, g = split_brightness(1.0, (20.0, 20000.0), (1.0, 16.0), max_exposure_us=5000.0)
    assert (e, g) == (20.0, 1.0)


def test_params_validated():
    with pytest.raises(ValueError, match="exposure mode"):
        ExposureParams(mode="hdr")
    with pytest.raises(ValueError, match="target_peak_dn"):
        ExposureParams(target_peak_dn=300.0)


@pytest.mark.parametrize("change", ["step", "ramp"])
def test_dynamic_converges_when_the_surface_darkens(change):
    """A matte surface for 20 frames, then a dark one (0.12 of it: 24 DN at the nominal
    exposure), by a step or a ramp over 20 frames: the controller brings the stripe back to
    its target within a few frames each time, and the dark stretch is measured as well as the
    bright one."""
    if change == "step":
        reflectance = lambda k: 1.0 if k < 20 else 0.12  # noqa: E731
    else:
        reflectance = lambda k: float(np.interp(k, [20, 40], [1.0, 0.12]))  # noqa: E731
    camera = FakeCamera(reflectance)
    params = ExposureParams(mode="dynamic")
    control = ExposureController(camera, params, fps=162.0)
    rng = np.random.default_rng(3)
    brightness, valid = [], []
    for _ in range(70):
        image, (exposure, gain) = camera.frame(rng)
        result = extract(image, threshold="auto")
        brightness.append(stripe_brightness(_peaks(result), result.background_dn, 75.0))
        valid.append(result.valid[100:700].mean())
        control.profile_measured(exposure, gain, _peaks(result), result.background_dn)
    brightness = np.array(brightness)
    target = params.target_peak_dn
    settle = 5 if change == "step" else 3
    # after the first frames and once settled after the change, within 15 % of the target
    bright_settled = brightness[settle:20]
    dark_settled = brightness[(20 if change == "step" else 40) + settle:]
    assert np.all(np.abs(bright_settled / target - 1) < 0.15), bright_settled
    assert np.all(np.abs(dark_settled / target - 1) < 0.15), dark_settled
    assert min(valid[45:]) > 0.99
    # the dark stretch needs 1 / 0.12 = 8.3x the brightness: 5.6 ms at most in the frame
    # period (0.9 / 162 fps), the rest as gain
    assert camera.exposure_us == pytest.approx(0.9e6 / 162.0, rel=0.01)
    assert camera.gain == pytest.approx(180.0 / 200.0 / 0.12 * NOMINAL_US / camera.exposure_us,
                                        rel=0.15)


def test_fixed_and_unsupported_cameras_are_left_alone():
    camera = FakeCamera(lambda k: 0.1)
    control = ExposureController(camera, ExposureParams(mode="fixed"), fps=162.0)
    control.profile_measured(1000.0, 1.0, np.full(100, 30.0), 10.0)
    control.frame_grabbed(1000.0, 1.0)
    assert (camera.exposure_us, camera.gain, control.updates) == (NOMINAL_US, 1.0, 0)
    plain = object()  # a camera without set_exposure
    assert not ExposureController(plain, ExposureParams(mode="dynamic"), fps=162.0).active


def test_multiple_alternates():
    camera = FakeCamera(lambda k: 1.0)
    control = ExposureController(camera, ExposureParams(mode="multiple", multiple_ratio=8.0),
                                 fps=162.0)
    taken = []
    for _ in range(6):
        taken.append(camera.exposure_us)
        control.frame_grabbed(camera.exposure_us, camera.gain)
    assert taken == [1000.0, 125.0, 1000.0, 125.0, 1000.0, 125.0]


def test_merge_keeps_the_better_exposed_column():
    # frames 10 (long) and 11 (short) pair; 12 (long) has no partner (13 was dropped)
    frame_ids = [10, 11, 12]
    levels = [1000.0, 125.0, 1000.0]
    columns = [np.array([1, 2, 3, 4]), np.array([2, 3, 4, 5]), np.array([1, 2])]
    peaks = [np.array([200.0, 255.0, 255.0, 60.0]), np.array([40.0, 180.0, 200.0, 20.0]),
             np.array([255.0, 255.0])]
    saturated = [np.array([False, True, True, False]), np.array([False, False, True, False]),
                 np.array([True, True])]
    keep = merge_exposure_pairs(frame_ids, levels, columns, peaks, saturated)
    # col 1 and 5: one frame only, kept; col 2: the long one clips (scores 128 DN), the short
    # one is dim (40 DN): the clipped one; col 3: clipped against 180 DN unclipped: the
    # unclipped; col 4: 60 DN unclipped against a clipped one: the clipped
    assert keep[0].tolist() == [True, True, False, False]
    assert keep[1].tolist() == [False, True, True, True]
    assert keep[2].tolist() == [True, True]


def test_a_clipped_peak_beats_a_dim_unclipped_one():
    """The flanks of a clipped stripe measure it better than a stripe at 40 DN does."""
    keep = merge_exposure_pairs([0, 1], [1000.0, 125.0], [np.array([7]), np.array([7])],
                                [np.array([255.0]), np.array([40.0])],
                                [np.array([True]), np.array([False])])
    assert [k.tolist() for k in keep] == [[True], [False]]


def test_merge_leaves_equal_exposures_alone():
    keep = merge_exposure_pairs([0, 1], [1000.0, 1000.0], [np.array([1]), np.array([1])],
                                [np.array([100.0]), np.array([90.0])],
                                [np.array([False]), np.array([False])])
    assert [k.tolist() for k in keep] == [[True], [True]]


def test_a_surface_lit_for_part_of_the_exposure_is_not_kept():
    """A flat face seen in six profiles 1.2 mm apart: its first profile, lit for a quarter of
    the exposure (the face reached the sheet late in it), is dropped; a dim column in the middle
    (its neighbours on both sides see it) and a profile taken at half the light with half the
    peak are kept; so is a step's first profile when it is as bright as the next."""
    from scanner_core.pipeline.exposure import partly_lit

    x = np.linspace(-10.0, 10.0, 101)
    frames, cloud, quality, light = [], [], [], []
    for k in range(6):
        frames += [k] * len(x)
        cloud += [np.column_stack([x, np.full_like(x, 1.2 * k), np.full_like(x, 5.0)])]
        q = np.full(len(x), 200.0)
        if k == 0:
            q[:] = 50.0  # lit a quarter of the exposure
        if k == 3:
            q[40] = 30.0  # a dim column inside the face: not an end
        if k == 2:
            q /= 2.0
        quality.append(q)
        light += [0.5 if k == 2 else 1.0] * len(x)
    # A step: a second face 3 mm higher seen from profile 4 on, as bright as its next profile.
    for k in (4, 5):
        frames += [k] * 10
        cloud += [np.column_stack([np.linspace(20.5, 22.0, 10), np.full(10, 1.2 * k),
                                   np.full(10, 8.0)])]
        quality.append(np.full(10, 190.0))
        light += [1.0] * 10
    frames, cloud, quality = np.array(frames), np.vstack(cloud), np.concatenate(quality)
    drop = partly_lit(frames, cloud, quality, np.array(light), 0.5)
    assert drop[frames == 0].all()
    assert not drop[frames != 0].any()
    assert not partly_lit(frames, cloud, quality, np.array(light), 0.0).any()


def test_partly_lit_points_are_the_ones_a_profile_by_profile_search_finds(rng):
    """All profiles at once (sorted under one key) against each profile's own KD-tree of x_T,
    as the scan's end first did: the same points, over profiles with gaps between them,
    surfaces that step, and dim points at either side."""
    from scipy.spatial import cKDTree

    from scanner_core.pipeline.exposure import PARTLY_LIT_MATCH_MM, partly_lit

    def profile_by_profile(frame_ids, cloud, level, ratio):
        out = np.zeros(len(cloud), bool)
        members = {f: np.nonzero(frame_ids == f)[0] for f in np.unique(frame_ids)}
        trees = {f: cKDTree(cloud[m][:, :1]) for f, m in members.items()}
        for f, idx in members.items():
            seen, reference = [], []
            for g in (f - 1, f + 1):
                if g not in members:
                    seen.append(np.zeros(len(idx), bool))
                    reference.append(np.zeros(len(idx)))
                    continue
                dist, j = trees[g].query(cloud[idx, :1], distance_upper_bound=PARTLY_LIT_MATCH_MM)
                found = np.isfinite(dist)
                other = members[g][np.where(found, j, 0)]
                dz = np.abs(cloud[other, 2] - cloud[idx, 2])
                dy = np.abs(cloud[other, 1] - cloud[idx, 1])
                same = found & (dz <= np.maximum(0.5, 1.5 * dy))
                seen.append(same)
                reference.append(np.where(same, level[other], 0.0))
            one_side = seen[0] ^ seen[1]
            out[idx] = one_side & (level[idx] < ratio * np.where(seen[0], reference[0],
                                                                 reference[1]))
        return out

    frames = np.repeat(np.r_[np.arange(0, 30), np.arange(32, 40)], 60)
    n = len(frames)
    x = rng.uniform(-20.0, 20.0, n)
    cloud = np.column_stack([x, frames * 1.2, np.where(x > 5.0, 3.0, 0.0) + rng.normal(0, 0.2, n)])
    quality = rng.uniform(50.0, 250.0, n)
    light = np.where(rng.random(n) < 0.1, np.nan, rng.uniform(0.5, 2.0, n))
    got = partly_lit(frames, cloud, quality, light, 0.6)
    level = quality / np.where(np.isfinite(light) & (light > 0), light, 1.0)
    want = profile_by_profile(frames, cloud, level, 0.6)
    assert got.tolist() == want.tolist() and 0 < got.sum() < n // 4
