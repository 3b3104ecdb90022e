"""Benchmark of the pose's own time: ``scan_pose`` on simulated scans of every part, by part
and point count, stage by stage, on one core and by the thread's CPU clock.

``flyscan bench service`` measures what the robot waits for (the pass's last frame to the
pose on ZeroMQ) through the running service, wall clock, as other work shares the machine.
This one isolates the registration (normals, fine stage, coarse stage, turn check, probes)
so that two versions of it can be compared on the same scans, and its CPU time does not
depend on what else runs: each scan's pose is computed twice and the faster kept
(``time.thread_time``; BLAS held to one thread, the KD-tree queries on one worker).

The scans: the procedural parts (the demo block among them), the four reference parts and
the parts kept for checks (``benchmarks.parts.VALIDATION_PARTS``: other procedural shapes,
a faceted dome, public meshes) at 400, 200 and 100 mm/s (the point count goes as the
inverse), three random misplacements each up to 5 mm and 10 degrees (seeded). The quick set: the demo block at 200 mm/s, two scans.

``run(out_dir)`` writes ``pose_time.json`` (per scan: part, speed, points, time, stages,
act, error against the truth; summaries by part and for the scans of up to
`TARGET_POSE_POINTS` points) and ``pose_time.png``.
"""
from __future__ import annotations

import pathlib
import time

import numpy as np
from threadpoolctl import threadpool_limits

from benchmarks.parts import (DEMO_PART, MISPLACEMENT_SEED, MISPLACEMENT_UP_TO_DEG,
                              MISPLACEMENT_UP_TO_MM, PROCEDURAL_PARTS, REFERENCE_PARTS,
                              VALIDATION_PARTS, bench_part, random_misplacement)
from benchmarks.stats import spread
from benchmarks.results import machine_info, write_json
from benchmarks.service import TARGET_POSE_P95_MS, TARGET_POSE_POINTS, pose_stages
from scanner_core.pose.registration import PoseParams, scan_pose
from simulator.cell import load_cell
from simulator.session import misplacement_matrix, run_simulated_scan

__all__ = ["run", "SPEEDS_MM_S", "SCANS_PER_SPEED"]

#: Pass speeds (mm/s) and scans per part and speed.
SPEEDS_MM_S, SCANS_PER_SPEED = (400.0, 200.0, 100.0), 3
QUICK_SPEEDS_MM_S, QUICK_SCANS_PER_SPEED = (200.0,), 2
#: Each pose is computed this many times; the fastest is kept.
REPEATS = 2


def run(out_dir, quick: bool = False, *, progress=print) -> dict:
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = (DEMO_PART,) if quick else (tuple(PROCEDURAL_PARTS) + REFERENCE_PARTS
                                        + tuple(VALIDATION_PARTS))
    speeds = QUICK_SPEEDS_MM_S if quick else SPEEDS_MM_S
    count = QUICK_SCANS_PER_SPEED if quick else SCANS_PER_SPEED
    cell = load_cell()
    rows = []
    with threadpool_limits(1):
        for p_index, name in enumerate(names):
            part = bench_part(name)
            prepare_ms = part.prepare()  # once per part, as the service does at arming
            for speed in speeds:
                for k in range(count):
                    rng = np.random.default_rng([MISPLACEMENT_SEED, p_index, int(speed), k])
                    values = random_misplacement(rng, MISPLACEMENT_UP_TO_MM,
                                                 MISPLACEMENT_UP_TO_DEG, up_to=True)
                    row = _timed(part, cell.with_pass(speed_mm_s=speed), values, seed=k)
                    row.update(part=name, speed_mm_s=speed, prepare_ms=round(prepare_ms, 1))
                    rows.append(row)
                    progress(f"bench pose_time: {name} {speed:g} mm/s #{k}: {row['points']} "
                             f"points, {row['ms']:.0f} ms {row['stages_ms']}")
    result = {"machine": machine_info(), "quick": quick, "repeats": REPEATS,
              "clock": "time.thread_time, fastest of the repeats", "rows": rows,
              "summary": _summary(rows)}
    write_json(out / "pose_time.json", result, digits=3)
    _plot(result, out / "pose_time.png")
    return result


def _timed(part, cell, values, *, seed: int) -> dict:
    misplacement = misplacement_matrix(values)
    scan, _ = run_simulated_scan(part, cell, misplacement=misplacement, seed=seed,
                                 evaluate=False, pose=False)
    truth = misplacement @ part.grasp
    best = None
    for _ in range(REPEATS):
        with pose_stages(clock=time.thread_time) as spent:
            t0 = time.thread_time()
            result = scan_pose(scan, part.surface_model, part.grasp, edge_model=part.edge_model,
                               params=PoseParams())
            ms = (time.thread_time() - t0) * 1e3
        if best is None or ms < best[0]:
            best = (ms, dict(spent), result)
    ms, spent, result = best
    error = np.linalg.inv(truth) @ result.matrix
    angle = np.degrees(np.arccos(np.clip((np.trace(error[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    return {"points": int(len(scan.cloud)), "edge_points": int(len(scan.edges)),
            "misplacement": [round(v, 4) for v in values], "ms": ms,
            "stages_ms": {k: round(v, 1) for k, v in spent.items()},
            "normals_ms": result.normals_ms, "coarse": result.coarse, "act": result.act,
            "rivals": len(result.rivals), "free_axes": [a["label"] for a in result.free_axes],
            "error_um": float(np.linalg.norm(truth[:3, 3] - result.matrix[:3, 3]) * 1e3),
            "error_mdeg": float(angle * 1e3)}


def _summary(rows: list[dict]) -> dict:
    small = [r["ms"] for r in rows if r["points"] <= TARGET_POSE_POINTS]
    by_part = {name: spread([r["ms"] for r in rows if r["part"] == name])
               for name in dict.fromkeys(r["part"] for r in rows)}
    searched = [r["ms"] for r in rows if r["points"] <= TARGET_POSE_POINTS
                and (r["coarse"] or r["stages_ms"].get("probes", 0.0) > 10.0)]
    return {"up_to_target_points": spread(small), "by_part": by_part,
            "searched_up_to_target_points": spread(searched),
            "target_p95_ms": TARGET_POSE_P95_MS, "target_points": TARGET_POSE_POINTS,
            "over_target": int(sum(ms > TARGET_POSE_P95_MS for ms in small)),
            "note": "the pose alone; the service adds the pass's end, the scan's assembly and "
                    "the publishing (bench service)"}


def _plot(result: dict, path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["rows"]
    fig, (ax_points, ax_stages) = plt.subplots(1, 2, figsize=(13, 5))
    colours = plt.get_cmap("tab20").colors
    for k, name in enumerate(dict.fromkeys(r["part"] for r in rows)):
        mine = [r for r in rows if r["part"] == name]
        ax_points.scatter([r["points"] for r in mine], [r["ms"] for r in mine], label=name, s=18,
                          color=colours[k % len(colours)], marker="os^D"[k // 10 % 4])
    ax_points.axhline(TARGET_POSE_P95_MS, color="k", ls="--", lw=1, label="target p95")
    ax_points.axvline(TARGET_POSE_POINTS, color="grey", ls=":", lw=1)
    ax_points.set(xscale="log", xlabel="scan points", ylabel="pose, ms (thread CPU)",
                  title="the pose's time by part and point count")
    ax_points.legend(fontsize=7, ncol=2)
    stages = ["fine", "coarse", "turn_check", "probes"]
    order = sorted(range(len(rows)), key=lambda i: rows[i]["ms"])
    bottom = np.zeros(len(rows))
    for stage in stages:
        values = np.array([rows[i]["stages_ms"].get(stage, 0.0) for i in order])
        ax_stages.bar(np.arange(len(rows)), values, bottom=bottom, label=stage)
        bottom += values
    other = np.array([rows[i]["ms"] for i in order]) - bottom
    ax_stages.bar(np.arange(len(rows)), np.maximum(other, 0.0), bottom=bottom,
                  label="normals, uncertainty, flags", color="lightgrey")
    ax_stages.set(xlabel="scans, by time", ylabel="ms", title="where the time goes")
    ax_stages.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
