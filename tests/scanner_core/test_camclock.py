"""A camera's clock mapped to the host's: the mapping against the true exposure times, and the
drift measured, on a synthetic camera whose clock runs 30 ppm slow, with transfer latency."""
import numpy as np
import pytest

from scanner_core.pipeline.camclock import CameraClock

FPS = 162.0
DRIFT_PPM = 30.0
#: The least transfer latency (read-out and transfer of a frame), s; the mapping includes it.
LATENCY_MIN_S = 2e-3
#: Mapped times against the truth plus the least latency, s, once the window has filled:
#: the bucket minima sit within a few microseconds of the envelope.
MAP_TOL_S = 50e-6
#: The drift measured against the truth, ppm.
DRIFT_TOL_PPM = 2.0


def _stream(rng, seconds):
    """(camera_s, host_received_s, host_exposure_s) of a camera booted 1000 s before."""
    camera = 1000.0 + np.arange(int(seconds * FPS)) / FPS
    exposure = 52_000.0 + camera * (1 + DRIFT_PPM * 1e-6)  # the host's clock at the exposure
    latency = LATENCY_MIN_S + rng.exponential(0.4e-3, camera.size)  # positive, varying
    latency[rng.random(camera.size) < 0.02] += 0.03  # a stalled transfer now and then
    return camera, exposure + latency, exposure


def test_mapped_times_follow_the_host_clock_and_the_drift_is_measured():
    camera, received, exposure = _stream(np.random.default_rng(3), 30.0)
    clock = CameraClock()
    mapped = np.array([clock.map(c, h) for c, h in zip(camera, received)])
    settled = camera > camera[0] + 10.0  # the 10 s window filled
    np.testing.assert_allclose(mapped[settled], exposure[settled] + LATENCY_MIN_S, atol=MAP_TOL_S)
    assert np.all(mapped <= received)  # never later than it arrived
    assert np.all(np.diff(mapped[settled]) > 0)  # in order
    estimate = clock.estimate()
    assert estimate.drift_ppm == pytest.approx(DRIFT_PPM, abs=DRIFT_TOL_PPM)
    assert estimate.frames == camera.size


def test_early_frames_are_mapped_without_a_drift():
    camera, received, exposure = _stream(np.random.default_rng(4), 0.4)
    clock = CameraClock()
    mapped = [clock.map(c, h) for c, h in zip(camera, received)]
    assert np.isnan(clock.estimate().drift_ppm)  # not one bucket complete yet
    # the offset is the least one seen so far: within the latency's spread of the truth
    assert np.max(np.abs(np.array(mapped[20:]) - exposure[20:] - LATENCY_MIN_S)) < 1e-3


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="bucket_s"):
        CameraClock(bucket_s=0.0)
    with pytest.raises(ValueError, match="window_buckets"):
        CameraClock(window_buckets=1)
    with pytest.raises(ValueError, match="finite"):
        CameraClock().map(float("nan"), 1.0)
