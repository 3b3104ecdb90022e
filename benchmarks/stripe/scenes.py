"""The stripe extractor on scenes beyond the reference model, for ``bench stripe``.

1. Lines as photographs show them (``simulator.line_photos``): sigma from 0.5 to 6 px, a width
   varying along the line, 2-D speckle, a printed checkerboard under it (with and without
   ambient light on it), a colour camera's red channel through a Bayer mosaic and JPEG. Per
   scene: the share of the columns holding a stripe that are measured (a row within the line's
   own extent), the false columns (a row outside it), the RMS error in the line's sigmas, and
   the frame's width gate, with the fixed (20 DN) and the noise-derived threshold.
2. Frames of the reference cell (the demo block's pass, rendered by the simulator): the time of
   the pipeline's stripe call on each frame that holds a stripe (its settings: noise floors,
   continuity, the saturation fit, the direct view's columns, the geometric window of the
   frame's TCP) against a copy of the frame, timed frame by frame in the same run.

`scenes_target` holds the first to its target; `demo_cell_frames` times the second on
the demo block's pass.
"""
from __future__ import annotations

import time

import numpy as np

from scanner_core.stripe import extractor as stripe
from scanner_core.pipeline import PipelineParams, camera_frames
from scanner_core.stripe.window import volume_rows
from benchmarks.parts import demo_pass
from simulator.line_photos import LinePhoto, render_line_photo

__all__ = ["SCENES", "photographed", "cell_frames", "demo_cell_frames", "scenes_target",
           "TARGET_MEASURED", "TARGET_CELL_RATIO"]

#: at least this share of the columns holding a stripe measured, none false ...
TARGET_MEASURED = 0.99
#: ... and the stripe on a frame of the reference cell within this many copies of the frame.
TARGET_CELL_RATIO = 2.5
#: A row farther than this plus two of the line's sigmas from its centre is not on the line.
FALSE_PX = 2.0
#: The scenes; those marked False are reported but not held to the target (ambient light on a
#: white surface above the fixed 20 DN threshold outshines a stripe dimmed on the black squares:
#: no single-frame extractor with a threshold below the background can tell them apart).
SCENES = {
    "sigma 0.5": (LinePhoto(sigma_px=(0.5, 0.5)), True),
    "sigma 1": (LinePhoto(sigma_px=(1.0, 1.0)), True),
    "sigma 3": (LinePhoto(sigma_px=(3.0, 3.0)), True),
    "sigma 6": (LinePhoto(sigma_px=(6.0, 6.0)), True),
    "sigma 0.7-4.7": (LinePhoto(sigma_px=(0.7, 4.7)), True),
    "sigma 1.5 widening to 7": (LinePhoto(sigma_px=(1.5, 7.0), sigma_profile="ramp"), True),
    "sigma 0.5-6, speckle 0.3": (LinePhoto(sigma_px=(0.5, 6.0), speckle_contrast=0.3), True),
    "checkerboard 8 px, speckle": (LinePhoto(texture_px=8.0, speckle_contrast=0.2), True),
    "checkerboard 3 px, speckle": (LinePhoto(texture_px=3.0, speckle_contrast=0.2), True),
    "Bayer red channel, speckle": (LinePhoto(bayer=True, speckle_contrast=0.2), True),
    "Bayer red, checkerboard, JPEG 90": (LinePhoto(bayer=True, texture_px=10.0,
                                                   speckle_contrast=0.2, jpeg_quality=90), True),
    "checkerboard under ambient light": (LinePhoto(texture_px=8.0, speckle_contrast=0.2,
                                                   ambient_dn=40.0), False),
}


def score_photo(photo: LinePhoto, threshold, seeds) -> dict:
    """How ``scanner_core.stripe.extractor.extract`` at `threshold` reads `photo` rendered with each of
    `seeds`: the share of the columns holding a stripe measured on the line (within
    ``FALSE_PX`` plus two of the line's sigmas), the false columns, the RMS error of those
    measured in the line's sigmas, and the median width gate (px)."""
    measured = present = false = 0
    errors, gates = [], []
    for seed in seeds:
        img, truth = render_line_photo(photo, np.random.default_rng(seed))
        res = stripe.extract(img, threshold=threshold)
        err = np.abs(res.row - truth.row)
        on_line = err <= FALSE_PX + 2.0 * truth.sigma
        measured += int((res.valid & on_line)[truth.present].sum())
        present += int(truth.present.sum())
        false += int((res.valid & ~on_line).sum())
        kept = res.valid & on_line & truth.present
        errors.append(err[kept] / truth.sigma[kept])
        gates.append(getattr(res, "width_gate_px", np.nan))
    e = np.concatenate(errors)
    return {"measured_fraction": measured / max(present, 1), "columns_with_stripe": present,
            "false_columns": false,
            "rms_in_sigmas": float(np.sqrt(np.mean(e**2))) if e.size else None,
            "width_gate_px": float(np.median(gates))}


def photographed(seeds=(0, 1, 2)) -> dict:
    """Per scene and threshold (``"20"``, ``"auto"``), the figures of `score_photo`."""
    out = {}
    for name, (photo, held) in SCENES.items():
        out[name] = {"held_to_target": held,
                     "fixed_20dn": score_photo(photo, 20.0, seeds),
                     "auto": score_photo(photo, "auto", seeds)}
    return out


def cell_frames(sim, params: PipelineParams, repeats: int = 3) -> dict:
    """The pipeline's stripe call on the frames of a simulated pass that hold a stripe, against
    a copy of each frame, one thread; ``sim`` is a ``simulator.session.SimulatedCell``."""
    cal = sim.cell.calibration
    sim.camera.open()
    sim.robot.connect()
    try:
        frames = list(camera_frames(sim.camera))
    finally:
        sim.camera.close()
        sim.robot.disconnect()
    rotation = sim.cell.gripper_rotation_b
    calls = []
    for frame in frames:
        truth = sim.camera.truths.get(frame.frame_id)
        if truth is None or len(truth.stripe_columns) < 100:
            continue
        lo, hi = volume_rows(cal, truth.tcp_b, rotation, params.inspection_volume_mm,
                             margin_mm=params.window_margin_mm)
        calls.append((frame.image, lo, hi))

    def call(image, lo, hi):
        return stripe.extract(image, method=params.stripe_method, threshold="auto",
                              columns=cal.direct_columns, policy=params.stripe_policy,
                              saturation=params.stripe_saturation, row_min=lo, row_max=hi)

    call(*calls[0])  # JIT / first touch, excluded
    copy_ms, stripe_ms = [], []
    for _ in range(repeats):
        for image, lo, hi in calls:
            t0 = time.perf_counter_ns()
            image.copy()
            t1 = time.perf_counter_ns()
            call(image, lo, hi)
            t2 = time.perf_counter_ns()
            copy_ms.append((t1 - t0) * 1e-6)
            stripe_ms.append((t2 - t1) * 1e-6)
    copy, strip = float(np.median(copy_ms)), float(np.median(stripe_ms))
    return {"frames": len(calls), "repeats": repeats, "copy_ms": copy, "stripe_ms": strip,
            "stripe_ms_p90": float(np.percentile(stripe_ms, 90)), "ratio_to_copy": strip / copy,
            "call": "threshold auto, direct view, continuity, saturation fit, geometric window"}


def demo_cell_frames(repeats: int) -> dict:
    """`cell_frames` on the demo block's pass through the reference cell
    (``benchmarks.parts.demo_pass``), the pipeline's default settings."""
    return cell_frames(demo_pass(), PipelineParams(), repeats=repeats)


def scenes_target(scenes: dict) -> dict:
    """The worst measured share and the false columns over the scenes held to the target,
    with either threshold."""
    held = [d[k] for d in scenes.values() if d["held_to_target"] for k in ("fixed_20dn", "auto")]
    worst = min(h["measured_fraction"] for h in held)
    false = sum(h["false_columns"] for h in held)
    return {"worst_measured_fraction": worst, "false_columns": false,
            "target_min_measured": TARGET_MEASURED, "target_false": 0,
            "met": worst >= TARGET_MEASURED and false == 0}
