"""``bench stripe`` on full frames of the reference image model: every estimator's time per
1920 x 1200 frame on one thread against ``image.copy()`` of the same frames (the memory floor),
its RMS error and bias against the exact stripe rows at several read-noise levels beside the
Cramer-Rao bound, and the options that cost time (the pipeline's own call among them)."""
from __future__ import annotations

import dataclasses
import sys
import time

import numpy as np

from scanner_core.stripe import extractor as stripe
from simulator.imaging import ImageModel, cramer_rao_bound_px, render_image

__all__ = ["FRAME_HEIGHT", "FRAME_WIDTH", "NOISE_LEVELS_DN", "REFERENCE_NOISE_DN",
           "TIMING_PASSES", "PIPELINE_VARIANT", "frames", "noise_sweep", "median_ms",
           "method_figures", "variant_times"]

FRAME_HEIGHT = 1200
FRAME_WIDTH = 1920
NOISE_LEVELS_DN = (1.0, 2.0, 3.0, 5.0, 8.0)
REFERENCE_NOISE_DN = 3.0
# Stripe rows stay inside this band (px), away from the frame edges.
ROW_RANGE = (200.0, 1000.0)
# Passes over the frame set per timed operation; the set (20 frames = 46 MB) exceeds the
# last-level cache, so every call sees a frame that is not in cache.
TIMING_PASSES = 3
#: The stripe call of the pipeline's defaults, timed beside the plain ``cog``.
PIPELINE_VARIANT = "pipeline: auto floors, continuity, fit, window"
#: Its geometric window spans this many rows per column about the stripe: the median span of
#: ``scanner_core.stripe.window.volume_rows`` over the demo block's pass in the reference cell (the
#: inspection volume's section of the sheet seen from the camera: 343 rows).
REFERENCE_WINDOW_ROWS = 344.0


def _stripe_rows(rng: np.random.Generator, width: int) -> np.ndarray:
    """Smooth random stripe row per column: slope plus a few sinusoids, within ROW_RANGE."""
    x = np.arange(width, dtype=float)
    lo, hi = ROW_RANGE
    rows = rng.uniform(lo + 250.0, hi - 250.0) + rng.uniform(-0.1, 0.1) * (x - width / 2)
    for amp, period in ((80.0, 2000.0), (25.0, 300.0), (4.0, 40.0)):
        rows += amp * np.sin(2 * np.pi * x / (period * rng.uniform(0.7, 1.3)) + rng.uniform(0, 2 * np.pi))
    return np.clip(rows, lo, hi)


def frames(model: ImageModel, n: int, rng: np.random.Generator):
    """`n` full frames of `model` with a smooth random stripe each, and its exact rows."""
    cols = np.arange(FRAME_WIDTH)
    frames, truth = [], []
    for _ in range(n):
        rows = _stripe_rows(rng, FRAME_WIDTH)
        frames.append(render_image(FRAME_HEIGHT, FRAME_WIDTH, model, rng, stripe_cols=cols,
                                   stripe_rows=rows))
        truth.append(rows)
    return frames, truth


def _errors(method: str, frames, truth) -> dict:
    errs, valid = [], 0
    for img, rows in zip(frames, truth):
        res = stripe.extract(img, method=method)
        errs.append(res.row[res.valid].astype(float) - rows[res.valid])
        valid += int(res.valid.sum())
    e = np.concatenate(errs)
    return {
        "rms_px": float(np.sqrt(np.mean(e**2))) if e.size else None,
        "bias_px": float(np.mean(e)) if e.size else None,
        "p99_abs_px": float(np.percentile(np.abs(e), 99)) if e.size else None,
        "valid_fraction": valid / (len(frames) * FRAME_WIDTH),
    }


def median_ms(fn, frames) -> float:
    """The median time of `fn` on each of `frames`, ms (`TIMING_PASSES` passes; the first
    call excluded: JIT, first touch)."""
    fn(frames[0])  # JIT / first-touch, excluded
    times = []
    for _ in range(TIMING_PASSES):
        for img in frames:
            t0 = time.perf_counter_ns()
            fn(img)
            times.append(time.perf_counter_ns() - t0)
    return float(np.median(times)) * 1e-6


def noise_sweep(reference: ImageModel, n: int, rng: np.random.Generator):
    """Per read-noise level: the model (speckle off: the bound ignores speckle), its frames and
    their true rows; and the Cramer-Rao bound of each level."""
    sweep = {}
    for noise in NOISE_LEVELS_DN:
        model = dataclasses.replace(reference, read_noise_dn=noise, speckle_contrast=0.0)
        sweep[noise] = (model, *frames(model, n, rng))
    crb = {noise: cramer_rao_bound_px(sweep[noise][0]) for noise in NOISE_LEVELS_DN}
    return sweep, crb


def method_figures(ref_frames, ref_truth, sweep, crb, copy_ms) -> dict:
    """Per method of ``scanner_core.stripe.extractor``: its time per frame (and over a copy's), its
    error on the reference frames (speckle on) and at every noise level of `sweep`."""
    methods = {}
    for method in stripe.METHODS:
        t_ms = median_ms(lambda img, m=method: stripe.extract(img, method=m), ref_frames)
        entry = {
            "time_ms": t_ms,
            "ratio_to_copy": t_ms / copy_ms,
            "reference_speckle": _errors(method, ref_frames, ref_truth),
            "noise_sweep": [],
        }
        for noise in NOISE_LEVELS_DN:
            _, fr, tr = sweep[noise]
            e = _errors(method, fr, tr)
            e["read_noise_dn"] = noise
            e["crb_px"] = crb[noise]
            e["rms_over_crb"] = e["rms_px"] / crb[noise] if e["rms_px"] is not None else None
            entry["noise_sweep"].append(e)
        entry["at_reference_noise"] = next(e for e in entry["noise_sweep"]
                                           if e["read_noise_dn"] == REFERENCE_NOISE_DN)
        methods[method] = entry
        ref = entry["at_reference_noise"]
        print(f"bench stripe: {method:12s} {t_ms:7.3f} ms/frame ({t_ms / copy_ms:5.1f} x copy)  "
              f"RMS {ref['rms_px']:.4f} px  bias {ref['bias_px']:+.4f} px  @ {REFERENCE_NOISE_DN:g} DN",
              file=sys.stderr)
    return methods


def variant_times(ref_frames, ref_truth, copy_ms) -> dict:
    """The options that cost time (the defaults are timed by `method_figures`):
    name -> ms per frame."""
    bounds = (np.full(FRAME_WIDTH, ROW_RANGE[0] - 20.0), np.full(FRAME_WIDTH, ROW_RANGE[1] + 20.0))
    windows = {id(img): (rows - REFERENCE_WINDOW_ROWS / 2, rows + REFERENCE_WINDOW_ROWS / 2)
               for img, rows in zip(ref_frames, ref_truth)}
    variants = {
        "cog, threshold auto": lambda img: stripe.extract(img, threshold="auto"),
        "cog, geometric window": lambda img: stripe.extract(img, row_min=bounds[0],
                                                            row_max=bounds[1]),
        "cog, policy strongest": lambda img: stripe.extract(img, policy="strongest"),
        # what the pipeline runs (scanner_core.pipeline.frame_stripe): floors from the noise,
        # continuity, the saturation fit and the geometric window
        PIPELINE_VARIANT: lambda img: stripe.extract(img, threshold="auto",
                                                     row_min=windows[id(img)][0],
                                                     row_max=windows[id(img)][1]),
    }
    variants_ms = {}
    for name, fn in variants.items():
        variants_ms[name] = median_ms(fn, ref_frames)
        print(f"bench stripe: {name:22s} {variants_ms[name]:7.3f} ms/frame "
              f"({variants_ms[name] / copy_ms:5.1f} x copy)", file=sys.stderr)
    return variants_ms
