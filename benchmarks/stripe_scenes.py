"""The stripe extractor on scenes beyond the reference model (issue 25), for ``bench stripe``.

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
"""
from __future__ import annotations

import time

import numpy as np

from scanner_core import stripe
from scanner_core.pipeline import PipelineParams, camera_frames
from scanner_core.window import volume_rows
from simulator.line_photos import LinePhoto, render_line_photo

__all__ = ["SCENES", "photographed", "cell_frames", "TARGET_MEASURED", "TARGET_CELL_RATIO"]

#: Issue 25: at least this share of the columns holding a stripe measured, none false ...
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


def _score(photo: LinePhoto, threshold, seeds) -> dict:
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
    """Per scene and threshold (``"20"``, ``"auto"``), the figures of ``_score``."""
    out = {}
    for name, (photo, held) in SCENES.items():
        out[name] = {"held_to_target": held,
                     "fixed_20dn": _score(photo, 20.0, seeds),
                     "auto": _score(photo, "auto", seeds)}
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


def plot_scenes(scenes: dict, ax_measured, ax_rms) -> None:
    """Measured share and RMS error per scene, fixed and noise-derived thresholds."""
    names = list(scenes)
    y = np.arange(len(names))
    for i, (key, label) in enumerate((("fixed_20dn", "threshold 20 DN"), ("auto", "auto"))):
        m = [scenes[n][key]["measured_fraction"] for n in names]
        r = [scenes[n][key]["rms_in_sigmas"] or np.nan for n in names]
        ax_measured.barh(y + (i - 0.5) * 0.38, m, 0.38, color=f"C{i}", label=label)
        ax_rms.barh(y + (i - 0.5) * 0.38, r, 0.38, color=f"C{i}", label=label)
        for k, n in enumerate(names):
            f = scenes[n][key]["false_columns"]
            if f:
                ax_measured.text(1.005, k + (i - 0.5) * 0.38, f"{f} false", va="center",
                                 fontsize=7, color=f"C{i}")
    labels = [n + ("" if scenes[n]["held_to_target"] else " (not held)") for n in names]
    for ax in (ax_measured, ax_rms):
        ax.set_yticks(y)
        ax.set_yticklabels(labels, fontsize=8)
        ax.invert_yaxis()
        ax.legend(fontsize=7, loc="lower left")
    ax_measured.axvline(TARGET_MEASURED, color="k", ls=":", label="target 99 %")
    ax_measured.set_xlim(0.0, 1.12)
    ax_measured.set_xlabel("share of the columns holding a stripe measured")
    ax_measured.set_title("lines as photographs show them (640 x 480, 3 frames each)")
    ax_rms.set_xscale("log")
    ax_rms.set_xlabel("RMS error, in the line's own sigmas")
    ax_rms.set_title("error of the measured columns")
