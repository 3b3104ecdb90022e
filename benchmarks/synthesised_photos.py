"""The failures real photographs showed, synthesised, against the naive peak finder.

Each case is a ``simulator.line_photos.LinePhoto`` (a dim line over a quiet floor, a colour
camera's line through JPEG's 4:2:0 chroma, a printed checkerboard whose edges cut the line,
squares dimmer or brighter than the line, a narrow line, speckle), rendered with the seeds
given, and read by flyscan's ``extract`` as the pipeline reads such a frame (the colour excess
and ``shoulders`` for a colour frame) and by the naive peak finder of ``flyscan bench real``
(per column the argmax and a 3-point parabola, on the same colour excess). Both are scored
against the drawn line: unlike the photographs, the truth is known, so the RMS is about the
line itself, not a line fitted to the points.

``flyscan bench real`` reports these beside the photographs; the tests
(``tests/scanner_core/test_stripe_photos.py``) hold the same figures to their bounds.
"""
from __future__ import annotations

import numpy as np

from benchmarks.naive_peaks import BASELINE_DN, baseline_rows, naive_signal
from scanner_core.stripe.extractor import EXCESS_OFFSET_DN, extract, stripe_signal
from simulator.line_photos import LinePhoto, render_line_photo

__all__ = ["CASES", "SEEDS", "DIM", "against_naive", "run_cases"]

SEEDS = (0, 1, 2)
#: A dim line as the photographs showed it: peaks of 15-30 DN over 1 DN of noise.
DIM = dict(background_dn=4.0, read_noise_dn=1.0, sigma_px=(0.8, 1.6))
#: A printed checkerboard of 24 px squares, the dark ones at a fifth of the light ones.
_PRINT = dict(texture_px=24.0, black_reflectance=0.2)

#: The cases reported, by name.
CASES = {
    "mono, dim line 15 DN over 1 DN of noise": LinePhoto(peak_dn=15.0, **DIM),
    "mono, plain": LinePhoto(),
    "mono, plain, narrow (sigma 0.6-1.2 px)": LinePhoto(sigma_px=(0.6, 1.2)),
    "mono, speckled (sigma 0.5-6 px)": LinePhoto(sigma_px=(0.5, 6.0), speckle_contrast=0.3),
    "mono, print, lit squares (ambient 60 DN)": LinePhoto(peak_dn=100.0, ambient_dn=60.0,
                                                          sigma_px=(1.5, 3.0), **_PRINT),
    "mono, print, ambient 20 DN": LinePhoto(peak_dn=100.0, ambient_dn=20.0,
                                            sigma_px=(1.5, 3.0), **_PRINT),
    "mono, print, narrow line": LinePhoto(peak_dn=100.0, ambient_dn=60.0, sigma_px=(0.6, 1.2),
                                          **_PRINT),
    "mono, print, narrow line, ambient 20 DN": LinePhoto(peak_dn=100.0, ambient_dn=20.0,
                                                         sigma_px=(0.6, 1.2), **_PRINT),
    "mono, print, wide line (sigma 3-5 px), ambient 20 DN": LinePhoto(
        peak_dn=100.0, ambient_dn=20.0, sigma_px=(3.0, 5.0), **_PRINT),
    "mono, squares of 12 px dark at 0.3, line 60 DN": LinePhoto(
        peak_dn=60.0, ambient_dn=20.0, texture_px=12.0, black_reflectance=0.3,
        sigma_px=(1.0, 2.5)),
    "mono, squares of 30 px dark at 0.4, line dimmer than the lit squares": LinePhoto(
        peak_dn=100.0, ambient_dn=60.0, texture_px=30.0, black_reflectance=0.4,
        sigma_px=(2.5, 5.0)),
    "red, print, ambient 120 DN": LinePhoto(laser="red", peak_dn=100.0, background_dn=10.0,
                                            ambient_dn=120.0, read_noise_dn=2.0,
                                            sigma_px=(1.5, 3.0), **_PRINT),
    "red, print, through JPEG q85": LinePhoto(laser="red", peak_dn=100.0, background_dn=10.0,
                                              ambient_dn=120.0, read_noise_dn=2.0,
                                              sigma_px=(1.5, 3.0), jpeg_quality=85, **_PRINT),
    "green, print, through JPEG q85": LinePhoto(laser="green", peak_dn=160.0,
                                                background_dn=10.0, read_noise_dn=2.0,
                                                sigma_px=(1.0, 2.0), texture_px=24.0,
                                                black_reflectance=0.3, ambient_dn=60.0,
                                                jpeg_quality=85),
    "red overexposed (1500 DN), print, through JPEG q85": LinePhoto(
        laser="red", peak_dn=1500.0, background_dn=10.0, ambient_dn=120.0, read_noise_dn=2.0,
        sigma_px=(1.5, 3.0), jpeg_quality=85, **_PRINT),
}


def against_naive(photo: LinePhoto, seeds=SEEDS, threshold="auto",
                  signal="auto") -> tuple[dict, dict]:
    """flyscan's ``extract`` and the naive peak finder on ``photo`` rendered with each seed.

    Returns
    -------
    flyscan, baseline : dict
        Over the seeds' frames: ``measured``, the share of the columns holding a stripe that
        are measured; ``rms`` (px), the RMS error over the columns both methods measure within
        3 px of the line; ``beyond_1px``, the share of its measured columns more than 1 px
        off; ``within_half``, the share of the columns holding a stripe it gets within
        0.5 px; ``whole_pixel``, the share of its rows within 0.02 px of a whole pixel (4 %
        unbiased); ``false``, its columns measured where no stripe is visible (under
        ``simulator.line_photos.PRESENT_SNR`` noise sigmas: on a dark square, say), and
        ``false_off_line``, those of them more than 1 px off the line: outliers the other
        figures leave out.
    """
    rows = {"flyscan": [], "baseline": []}
    truths = []
    for seed in seeds:
        frame, truth = render_line_photo(photo, np.random.default_rng(seed))
        image = frame if frame.ndim == 2 else stripe_signal(frame, signal)
        res = extract(image, threshold=threshold, shoulders=frame.ndim == 3)
        gate = BASELINE_DN + (EXCESS_OFFSET_DN if frame.ndim == 3 else 0.0)
        naive = frame if frame.ndim == 2 else naive_signal(frame, f"{photo.laser}_excess")
        rows["flyscan"].append(np.where(res.valid, res.row, np.nan).astype(np.float64))
        rows["baseline"].append(baseline_rows(naive, gate))
        truths.append(truth)
    line = np.concatenate([t.row for t in truths])
    present = np.concatenate([t.present for t in truths])
    r = {k: np.concatenate(v) for k, v in rows.items()}
    err = {k: v - line for k, v in r.items()}
    common = present & np.all([np.abs(e) <= 3.0 for e in err.values()], axis=0)
    figures = []
    for name in ("flyscan", "baseline"):
        ok = np.isfinite(r[name]) & present
        e = err[name]
        figures.append({"measured": float(ok.sum() / present.sum()),
                        "rms": float(np.sqrt(np.mean(e[common] ** 2))),
                        "beyond_1px": float(np.mean(np.abs(e[ok]) > 1.0)),
                        "within_half": float(np.mean(np.abs(e[present]) <= 0.5)),
                        "whole_pixel": float(np.mean(np.abs(r[name][ok]
                                                            - np.round(r[name][ok])) < 0.02)),
                        "false": int((np.isfinite(r[name]) & ~present).sum()),
                        "false_off_line": int((np.abs(e[~present]) > 1.0).sum())})
    return figures[0], figures[1]


def run_cases(cases=None, seeds=SEEDS, progress=None) -> dict:
    """``against_naive`` on every case of ``cases`` (default ``CASES``): per name, both
    methods' figures and flyscan's RMS as a share of the baseline's."""
    out = {}
    for name, photo in (cases or CASES).items():
        fly, base = against_naive(photo, seeds)
        out[name] = {"flyscan": fly, "baseline": base,
                     "rms_ratio": fly["rms"] / base["rms"] if base["rms"] > 0 else None}
        if progress:
            progress(f"bench real: {name}: {fly['rms']:.3f} px against {base['rms']:.3f}, "
                     f"{100 * fly['beyond_1px']:.2f} % against {100 * base['beyond_1px']:.2f} % "
                     "more than 1 px off")
    return out
