"""``bench stripe`` on real surfaces: the valid fraction and RMS error of every
estimator against the stripe's peak from 5 DN to 10 times full scale (dark parts to clipped
specular ones), with the fixed and the noise-derived ("auto") floors and the historical handling
of saturation (rejected), the break points of each marked; and the share of the columns on the
true stripe under a reflection at half its brightness 20-40 rows away, per selection policy."""
from __future__ import annotations

import numpy as np

from scanner_core.stripe import extractor as stripe
from benchmarks.stripe.full_frames import FRAME_WIDTH, REFERENCE_NOISE_DN
from simulator.imaging import ImageModel, render_image

__all__ = ["PEAKS_DN", "SWEEP_HEIGHT", "BREAK_MIN_VALID", "BREAK_MAX_RMS_PX",
           "REFLECTION_RATIO", "REFLECTION_OFFSETS_PX", "GLINT_PERIOD", "GLINT_RATIO",
           "TARGET_REFLECTION_ON_STRIPE", "dynamic_range", "reflections", "surface_targets"]

# Dynamic range sweep: stripe peak above the background, DN (5 DN to 10x full scale).
PEAKS_DN = (5.0, 8.0, 12.0, 18.0, 25.0, 30.0, 40.0, 60.0, 100.0, 150.0, 200.0, 245.0, 300.0,
            450.0, 700.0, 1000.0, 1530.0, 2000.0, 2550.0)
# Frames of the sweep and of the reflection panel: short (the stripe stays within
# SWEEP_ROW_RANGE), full width; rows drawn per column at random (uniform sub-pixel phase).
SWEEP_HEIGHT = 256
SWEEP_ROW_RANGE = (40.0, 216.0)
# Where a method breaks: valid fraction below this or RMS error above that.
BREAK_MIN_VALID = 0.9
BREAK_MAX_RMS_PX = 0.1
# The targets on the sweep.
TARGET_SAT_PEAK_DN = 1530.0  # 6x full scale
TARGET_SAT_MIN_VALID = 0.98
TARGET_SAT_MAX_RMS_PX = 0.08
TARGET_DIM_PEAK_DN = 30.0
TARGET_DIM_MIN_VALID = 0.9
TARGET_DIM_MAX_RMS_PX = 0.15
# Reflection panel: a second stripe at REFLECTION_RATIO of the stripe's brightness,
# REFLECTION_OFFSETS_PX rows above or below it; glints: every GLINT_PERIOD-th column the
# reflection is GLINT_RATIO times the stripe.
REFLECTION_RATIO = 0.5
REFLECTION_OFFSETS_PX = (20.0, 40.0)
GLINT_PERIOD = 5
GLINT_RATIO = 1.5
TARGET_REFLECTION_ON_STRIPE = 0.98
# A column is on the true stripe when its row is within this of the truth, px.
ON_STRIPE_PX = 1.0


def _sweep_frame(peak_dn: float, rng: np.random.Generator):
    """A SWEEP_HEIGHT x FRAME_WIDTH reference-model frame with a stripe of ``peak_dn``."""
    model = ImageModel(read_noise_dn=REFERENCE_NOISE_DN)
    rows = rng.uniform(*SWEEP_ROW_RANGE, FRAME_WIDTH)
    img = render_image(SWEEP_HEIGHT, FRAME_WIDTH, model, rng, stripe_cols=np.arange(FRAME_WIDTH),
                       stripe_rows=rows,
                       stripe_gain=np.full(FRAME_WIDTH, peak_dn / model.stripe_peak_dn))
    return img, rows


def _breaks(peaks, valid, rms) -> dict:
    """Working range of one series: the lowest working peak and the first failing one above it."""
    ok = [v >= BREAK_MIN_VALID and r is not None and r <= BREAK_MAX_RMS_PX
          for v, r in zip(valid, rms)]
    if not any(ok):
        return {"low_dn": None, "high_dn": None}
    i0 = ok.index(True)
    i1 = next((i for i in range(i0, len(ok)) if not ok[i]), None)
    return {"low_dn": peaks[i0], "high_dn": None if i1 is None else peaks[i1]}


# series of the dynamic-range sweep: name -> (method, extract options)
def _sweep_series() -> dict:
    series = {m: (m, {}) for m in stripe.METHODS}
    series.update({f"{m} auto": (m, {"threshold": "auto"}) for m in stripe.METHODS})
    series["cog, saturation rejected (the earlier default)"] = ("cog", {"saturation": "reject"})
    return series


def dynamic_range(n_frames: int, rng: np.random.Generator) -> dict:
    """Per series (`_sweep_series`): valid fraction, RMS error and saturated share at every
    peak of `PEAKS_DN`, and where it breaks."""
    frames = {p: [_sweep_frame(p, rng) for _ in range(n_frames)] for p in PEAKS_DN}
    out = {}
    for name, (method, opts) in _sweep_series().items():
        valid, rms, sat = [], [], []
        for p in PEAKS_DN:
            errs, nv, ns = [], 0, 0
            for img, rows in frames[p]:
                res = stripe.extract(img, method=method, **opts)
                errs.append(res.row[res.valid].astype(float) - rows[res.valid])
                nv += int(res.valid.sum())
                ns += int(res.saturated[res.valid].sum())
            e = np.concatenate(errs)
            valid.append(nv / (n_frames * FRAME_WIDTH))
            rms.append(float(np.sqrt(np.mean(e**2))) if e.size else None)
            sat.append(ns / max(nv, 1))
        out[name] = {"method": method, "options": opts, "valid_fraction": valid, "rms_px": rms,
                     "saturated_fraction": sat, "breaks": _breaks(PEAKS_DN, valid, rms)}
    return out


def _reflection_frame(kind: str, rng: np.random.Generator):
    """Stripe + reflection: ``kind`` "smooth" (continuous stripe and reflection), "random"
    (rows and offsets at random per column) or "glints" (smooth, every GLINT_PERIOD-th column
    the reflection outshines the stripe)."""
    model = ImageModel(read_noise_dn=REFERENCE_NOISE_DN)
    c = np.arange(FRAME_WIDTH)
    lo, hi = SWEEP_ROW_RANGE
    if kind == "random":
        rows = rng.uniform(lo + 45.0, hi - 45.0, FRAME_WIDTH)
        off = (rng.uniform(*REFLECTION_OFFSETS_PX, FRAME_WIDTH)
               * rng.choice([-1.0, 1.0], FRAME_WIDTH))
    else:
        mid = 0.5 * (lo + hi)
        phase = rng.uniform(0, 2 * np.pi)
        rows = mid + 25.0 * np.sin(2 * np.pi * c / rng.uniform(500, 900) + phase)
        a, b = REFLECTION_OFFSETS_PX
        off = ((0.5 * (a + b) + 0.5 * (b - a) * np.sin(2 * np.pi * c / 1100.0))
               * rng.choice([-1.0, 1.0]))
    ratio = np.full(FRAME_WIDTH, REFLECTION_RATIO)
    if kind == "glints":
        ratio[c % GLINT_PERIOD == 0] = GLINT_RATIO
    img = render_image(SWEEP_HEIGHT, FRAME_WIDTH, model, rng, stripe_cols=np.concatenate([c, c]),
                       stripe_rows=np.concatenate([rows, rows + off]),
                       stripe_gain=np.concatenate([np.ones(FRAME_WIDTH), ratio]))
    return img, rows


def reflections(n_frames: int, rng: np.random.Generator) -> dict:
    """Per reflection scene and selection policy: the share of the columns on the true stripe."""
    out = {}
    for kind in ("smooth", "random", "glints"):
        frames = [_reflection_frame(kind, rng) for _ in range(n_frames)]
        out[kind] = {}
        for policy in stripe.POLICIES:
            on = 0
            for img, rows in frames:
                res = stripe.extract(img, policy=policy)
                on += int((res.valid & (np.abs(res.row - rows) < ON_STRIPE_PX)).sum())
            out[kind][policy] = on / (n_frames * FRAME_WIDTH)
    return out


def surface_targets(dynamic: dict, reflections: dict) -> dict:
    """The targets on the sweep and the reflections."""
    def at(name, peak):
        i = PEAKS_DN.index(peak)
        d = dynamic[name]
        return d["valid_fraction"][i], d["rms_px"][i]

    out = {}
    v, r = at("cog", TARGET_SAT_PEAK_DN)
    out["saturated_6x_cog"] = {
        "valid_fraction": v, "rms_px": r, "target_min_valid": TARGET_SAT_MIN_VALID,
        "target_max_rms_px": TARGET_SAT_MAX_RMS_PX,
        "met": v >= TARGET_SAT_MIN_VALID and r is not None and r <= TARGET_SAT_MAX_RMS_PX}
    for method in stripe.METHODS:
        v, r = at(f"{method} auto", TARGET_DIM_PEAK_DN)
        out[f"dim_30dn_{method}_auto"] = {
            "valid_fraction": v, "rms_px": r, "target_min_valid": TARGET_DIM_MIN_VALID,
            "target_max_rms_px": TARGET_DIM_MAX_RMS_PX,
            "met": v >= TARGET_DIM_MIN_VALID and r is not None and r <= TARGET_DIM_MAX_RMS_PX}
    default = "continuity"
    worst = min(reflections[k][default] for k in ("smooth", "random"))
    out["reflection_half_default_policy"] = {"policy": default, "value": worst,
                                             "target_min": TARGET_REFLECTION_ON_STRIPE,
                                             "met": worst >= TARGET_REFLECTION_ON_STRIPE}
    return out
