"""Benchmark of the pose's coarse stage: flyscan's search seeded by the nominal grasp
(`scanner_core.pose.registration`) against OpenCV contrib's point-pair features
(``cv2.ppf_match_3d_PPF3DDetector``; Drost et al., "Model globally, match locally", CVPR 2010),
the candidate the pose's search names, on the same scans.

For each reference part (quick: the procedural block), PPF is trained once on the CAD surface
(the samples the fine stage registers against, `SurfaceModel.from_mesh`, subsampled to
``PPF_MODEL_POINTS``), and timed. On ``SCANS_PER_PART`` scans at misplacements up to 5 mm and
10 degrees (`bench pose`'s set (a), same seeds), each from a start displaced by the basin's
target level (10 mm and 20 degrees, random directions, as `bench pose` (b)):

- **flyscan**: its registration (`bench pose`'s default: mesh and edges) from the displaced
  start, its coarse stage as it is;
- **PPF + flyscan**: PPF's best pose on the scan's cloud with normals (PPF is global: the start
  plays no part), then flyscan's registration from it, coarse search included when the fit
  from PPF's pose looks poor (``coarse`` says when it ran; ``ppf_*`` is PPF's own error);
- **PPF top-k + flyscan**: the registration from each of PPF's ``TOP_K`` best poses, the one
  it trusts most kept (unflagged, then most points matched, then the tightest fit).

A trial succeeds as in `bench pose`: within 0.1 mm and 0.1 degree of the truth; a failure
without a flag is confidently wrong. Times are per scan: the registrations with the normals
they use, and for PPF the normals of the whole cloud and its match; PPF's training is reported
apart (once per part). The method kept has the fewest confidently wrong poses, then the most
successes, then the least time.
``run(out_dir)`` writes ``coarse.json`` and ``coarse.png``.
"""
from __future__ import annotations

import os
import pathlib
import sys
import time

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from scanner_core.io.scanfiles import scan_normals
from benchmarks.parts import (DEMO_PART, MISPLACEMENT_SEED, MISPLACEMENT_UP_TO_DEG,
                              MISPLACEMENT_UP_TO_MM, REFERENCE_PARTS, bench_part,
                              random_misplacement)
from benchmarks.pose import DIGITS
from benchmarks.pose.basin import BASIN_TARGET_LEVEL
from benchmarks.pose.scans import simulate_scan
from benchmarks.pose.trials import DEFAULT_CONFIG, register, score
from benchmarks.results import json_safe, pyplot, save_figure, write_json
from benchmarks.stats import fraction
from simulator.cell import load_cell
from simulator.session import misplacement_matrix

__all__ = ["run", "ppf_detector", "ppf_poses"]

SCANS_PER_PART, QUICK_SCANS_PER_PART = 4, 2
START_LEVEL = BASIN_TARGET_LEVEL  # mm, degrees
# PPF's sampling relative to the model's diameter (OpenCV's defaults) and the model size: its
# training grows quickly with both (idler_riser: 5k points 42 s, 20k points 112 s, at 0.04
# instead of 0.05 187 s; 2 cores).
PPF_RELATIVE_SAMPLING = 0.05
PPF_RELATIVE_DISTANCE = 0.05
PPF_SCENE_SAMPLE_STEP = 1.0 / 5.0
PPF_MODEL_POINTS, QUICK_PPF_MODEL_POINTS = 5000, 1000  # quick: 1.7 s of training, not 37
TOP_K = 5
METHODS = ("flyscan", "PPF + flyscan", f"PPF top-{TOP_K} + flyscan")


def ppf_detector(model, *, points: int = PPF_MODEL_POINTS, seed: int = 0):
    """A trained ``cv2.ppf_match_3d_PPF3DDetector`` for a `SurfaceModel` (in {P}), and its
    training time in seconds."""
    rng = np.random.default_rng(seed)
    keep = rng.choice(len(model.points), min(points, len(model.points)), replace=False)
    samples = np.hstack([model.points[keep], model.normals[keep]]).astype(np.float32)
    detector = cv2.ppf_match_3d_PPF3DDetector(PPF_RELATIVE_SAMPLING, PPF_RELATIVE_DISTANCE)
    t0 = time.perf_counter()
    detector.trainModel(samples)
    return detector, time.perf_counter() - t0


def ppf_poses(detector, points, normals, k: int = TOP_K) -> tuple[list[np.ndarray], float]:
    """PPF's `k` best poses ^T X_P (most votes first) for a cloud in {T} with its unit
    normals ((N, 3) each, mm), and the match's time in ms."""
    scene = np.hstack([points, normals]).astype(np.float32)
    t0 = time.perf_counter()
    results = detector.match(scene, PPF_SCENE_SAMPLE_STEP, PPF_RELATIVE_DISTANCE)
    elapsed = (time.perf_counter() - t0) * 1e3
    results = sorted(results, key=lambda r: -r.numVotes)[:k]
    return [np.asarray(r.pose, dtype=np.float64) for r in results], elapsed


def _error(matrix, truth) -> tuple[float, float]:
    """PPF's own pose against the truth: um, mdeg."""
    e = np.asarray(matrix) @ np.linalg.inv(truth)
    return (float(np.linalg.norm(e[:3, 3]) * 1e3),
            float(np.degrees(Rotation.from_matrix(e[:3, :3]).magnitude()) * 1e3))


def _registration(part, scan, start):
    """`bench pose`'s default registration from `start`, and its time with the normals of the
    points it uses (ms)."""
    result = register(part, scan, start, DEFAULT_CONFIG, None)
    return result, result.time_ms + result.normals_ms


def _row(method, result, truth, register_ms, extra=None) -> dict:
    row = {"method": method, **score(result, truth), "register_ms": register_ms,
           **(extra or {})}
    row["time_ms"] = register_ms + row.get("normals_ms", 0.0) + row.get("match_ms", 0.0)
    row["confident_wrong"] = not row["success"] and not row["flags"]
    return row


def _trials(part, scan, truth, start, detector, normals_ms) -> list[dict]:
    """One row per method for one scan and start. PPF's rows count the normals of the whole
    cloud (`normals_ms`, which it needs and flyscan does not), its match and the
    registrations; flyscan's registration, its coarse search included, runs from PPF's
    poses as from any start (``coarse`` says whether it ran)."""
    try:
        ours, ours_ms = _registration(part, scan, start)
    except ValueError as exc:  # too few points: every method refuses alike
        return [{"method": m, "success": False, "confident_wrong": False, "time_ms": None,
                 "refused": str(exc)} for m in METHODS]
    rows = [_row(METHODS[0], ours, truth, ours_ms)]
    poses, match_ms = ppf_poses(detector, scan.cloud, scan_normals(scan))
    if not poses:
        return rows + [{"method": m, "success": False, "confident_wrong": False,
                        "time_ms": normals_ms + match_ms, "match_ms": match_ms,
                        "refused": "PPF found no pose"} for m in METHODS[1:]]
    ppf_um, ppf_mdeg = _error(poses[0], truth)
    fits = [_registration(part, scan, p) for p in poses]
    shared = {"normals_ms": normals_ms, "match_ms": match_ms}
    rows.append(_row(METHODS[1], fits[0][0], truth, fits[0][1],
                     {**shared, "ppf_translation_um": ppf_um, "ppf_rotation_mdeg": ppf_mdeg}))
    # the candidate the registration itself would trust most: unflagged, then most points
    # matched, then the tightest fit
    best, _ = max(fits, key=lambda f: (not f[0].flags, f[0].inlier_fraction, -f[0].rms_mm))
    rows.append(_row(METHODS[2], best, truth, sum(ms for _, ms in fits),
                     {**shared, "candidates": len(poses)}))
    return rows


def run(out_dir, quick: bool = False, *, progress=None) -> dict:
    """Run the benchmark; write ``coarse.json`` and ``coarse.png`` into `out_dir`."""
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda line: print(line, file=sys.stderr, flush=True))
    t_start = time.perf_counter()
    cell = load_cell()
    names = (DEMO_PART,) if quick else REFERENCE_PARTS
    n_scans = QUICK_SCANS_PER_PART if quick else SCANS_PER_PART
    parts, trials = {}, []
    with threadpool_limits(limits=1, user_api="blas"):
        for p_index, name in enumerate(names):
            part = bench_part(name)
            model_points = min(QUICK_PPF_MODEL_POINTS if quick else PPF_MODEL_POINTS,
                               len(part.surface_model.points))
            detector, train_s = ppf_detector(part.surface_model, points=model_points)
            parts[name] = {"ppf_train_s": round(train_s, 2), "model_points": model_points}
            say(f"{name}: PPF trained in {train_s:.1f} s")
            rng = np.random.default_rng([MISPLACEMENT_SEED, p_index])
            start_rng = np.random.default_rng([MISPLACEMENT_SEED, p_index, 1])
            for i in range(n_scans):
                values = random_misplacement(rng, MISPLACEMENT_UP_TO_MM, MISPLACEMENT_UP_TO_DEG,
                                             up_to=True)
                scan, truth, info = simulate_scan(part, cell, values, seed=i)
                offset = random_misplacement(start_rng, *START_LEVEL, up_to=False)
                start = np.linalg.inv(misplacement_matrix(offset)) @ truth
                rows = _trials(part, scan, truth, start, detector, info["normals_ms"])
                for r in rows:
                    r.update(part=name, scan=i, misplacement=values, start_offset=offset)
                trials += rows
                say(f"{name} scan {i}: " + "; ".join(
                    f"{r['method']} " + (f"refused ({r['refused']})" if r.get("refused") else
                                         f"{'ok' if r['success'] else 'FAILED'} "
                                         f"{r['time_ms']:.0f} ms") for r in rows))
    result = {"quick": quick,
              "settings": {"parts": list(names), "scans_per_part": n_scans,
                           "start_offset": list(START_LEVEL), "top_k": TOP_K,
                           "ppf": {"relative_sampling": PPF_RELATIVE_SAMPLING,
                                   "relative_distance": PPF_RELATIVE_DISTANCE,
                                   "scene_sample_step": PPF_SCENE_SAMPLE_STEP,
                                   "model_points": QUICK_PPF_MODEL_POINTS if quick
                                   else PPF_MODEL_POINTS},
                           "blas_threads": 1, "cpu_count": os.cpu_count()},
              "parts": parts, "trials": trials,
              "elapsed_s": round(time.perf_counter() - t_start, 1)}
    result = json_safe(result, digits=DIGITS)  # a free axis's sigma is NaN: None in JSON
    result["summary"] = _summary(result)
    result = write_json(out_dir / "coarse.json", result)
    _plot(result, out_dir / "coarse.png")
    say(f"coarse bench done in {result['elapsed_s']:.0f} s: {out_dir / 'coarse.json'}")
    return result


def _summary(result: dict) -> dict:
    """Per method: success, confident wrong poses (wrong and unflagged: the worst outcome),
    time per scan; PPF's own error and match time; the method to keep: fewest confident wrong
    poses, then most successes, then least time."""
    out = {"ppf_train_s": {name: p["ppf_train_s"] for name, p in result["parts"].items()}}
    for method in METHODS:
        rows = [r for r in result["trials"] if r["method"] == method]
        times = [r["time_ms"] for r in rows if r.get("time_ms") is not None]
        out[method] = {
            "trials": len(rows),
            "success_rate": fraction([r["success"] for r in rows]),
            "confident_wrong": sum(r["confident_wrong"] for r in rows),
            "per_part": {name: fraction([r["success"] for r in rows if r["part"] == name])
                         for name in result["parts"]},
            "time_ms_median": float(np.median(times)) if times else None}
    ppf = [r for r in result["trials"] if r["method"] == METHODS[1] and "match_ms" in r]
    out["ppf_match_ms_median"] = float(np.median([r["match_ms"] for r in ppf])) if ppf else None
    own = [r for r in ppf if "ppf_translation_um" in r]
    out["ppf_own_error_median"] = {
        "translation_mm": float(np.median([r["ppf_translation_um"] for r in own])) / 1e3,
        "rotation_deg": float(np.median([r["ppf_rotation_mdeg"] for r in own])) / 1e3,
    } if own else None
    out["keep"] = min(METHODS, key=lambda m: (out[m]["confident_wrong"],
                                              -(out[m]["success_rate"] or 0.0),
                                              out[m]["time_ms_median"] or np.inf))
    return out


def _plot(result: dict, path: pathlib.Path) -> None:
    plt = pyplot()

    s = result["summary"]
    names = list(result["parts"])
    fig, (ax_ok, ax_time) = plt.subplots(1, 2, figsize=(12, 4.5))
    width = 0.8 / len(METHODS)
    for k, method in enumerate(METHODS):
        x = np.arange(len(names)) + (k - (len(METHODS) - 1) / 2) * width
        ax_ok.bar(x, [(s[method]["per_part"][n] or 0.0) * 100 for n in names], width,
                  label=method)
        rows = [r for r in result["trials"] if r["method"] == method]
        ax_time.bar(x, [np.median([r["time_ms"] for r in rows if r["part"] == n
                                   and r.get("time_ms") is not None] or [np.nan])
                        for n in names], width, label=method)
    for ax in (ax_ok, ax_time):
        ax.set_xticks(np.arange(len(names)), names)
    start = result["settings"]["start_offset"]
    ax_ok.set_ylabel("success, % (within 0.1 mm and 0.1 deg)")
    ax_ok.set_title(f"From starts {start[0]:g} mm / {start[1]:g} deg off")
    ax_ok.set_ylim(0, 105)
    ax_ok.legend(fontsize=8, loc="lower right")
    ax_time.set_yscale("log")
    ax_time.set_ylabel("time per scan, ms (median)")
    ax_time.set_title("PPF's training, once per part (not included):\n" + ", ".join(
        f"{n} {t:.0f} s" for n, t in s["ppf_train_s"].items()), fontsize=9)
    save_figure(fig, path, dpi=110)
