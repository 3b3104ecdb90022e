"""One simulated pass of ``bench pose_limits`` at one level of a factor: the trials, the parts,
the pass, and its row of ``pose_limits.json`` with its verdict."""
from __future__ import annotations

import sys
import time

import numpy as np

from benchmarks import parts
from benchmarks.pose_limits.conditions import condition
from benchmarks.pose_limits.verdicts import edge_verdict, finite_or_none, pose_figures, pose_verdict
from benchmarks.targets import EDGE_OUTLIER_MM
from simulator.cell import Cell
from simulator.evaluate import edge_accuracy
from simulator.parts import Part
from simulator.session import misplacement_matrix, run_simulated_scan

__all__ = ["DEMO_PART", "TRIALS", "QUICK_TRIALS", "demo_part", "run_level",
           "progress"]

#: The demo block's name in these figures.
DEMO_PART = "demo"

#: Misplacements (tx, ty, tz mm, rotation vector deg) and camera seeds of the trials. No tilt
#: about x_T or y_T: each curve varies one cause, and a tilt changes which walls the camera
#: sees (bench pose's trials tilt up to 10 degrees).
TRIALS = (
    {"misplacement": (1.5, -1.0, 0.5, 0.0, 0.0, 2.0), "seed": 0},
    {"misplacement": (-2.5, 2.0, -0.5, 0.0, 0.0, -4.0), "seed": 1},
)
QUICK_TRIALS = TRIALS[:1]


def demo_part() -> Part:
    """The demo block (``benchmarks.parts.demo_part``), named `DEMO_PART`."""
    return parts.demo_part(DEMO_PART)


def _cli_refusal(part: Part, cell: Cell) -> str | None:
    """What ``flyscan scan`` says of this pass before running it (too few profiles), or None."""
    from scanner_core.scanplan import too_few_profiles

    return too_few_profiles(part, cell.pass_profile.speed_mm_s, cell.pass_profile.fps)


def _verdict(row: dict) -> str:
    """The verdict (``benchmarks.pose_limits``); the command line's refusal comes first."""
    if row["cli_refusal"]:
        return "refused"
    return pose_verdict(row["pose"])


def run_level(factor: str, level: float, part: Part, cell: Cell, *, misplacement, seed: int,
              evaluate: bool = True) -> dict:
    """One simulated pass at one level of a factor: the row of ``pose_limits.json``.

    Parameters
    ----------
    factor : str
        A name of `FACTORS`.
    level : float
    part : Part
        The part scanned (the symmetry factor builds its own).
    cell : Cell
        The reference cell: the scanner's calibration, and the truth before the factor.
    misplacement : (6,) float
        tx, ty, tz mm and a rotation vector in degrees, on top of the nominal grasp.
    seed : int
        Seed of the simulated camera.
    evaluate : bool
        Also score the cloud against the true surface (``cloud_rms_um``).
    """
    part, truth = condition(factor, level, part, cell)
    t0 = time.perf_counter()
    scan, report = run_simulated_scan(part, truth, calibration=cell.calibration,
                                      misplacement=misplacement_matrix(misplacement), seed=seed,
                                      evaluate=evaluate)
    wall_s = time.perf_counter() - t0
    grasp = np.asarray(report["ground_truth"]["grasp"])
    edges = {"count": 0}
    if len(scan.edges):
        acc = edge_accuracy(scan.edges, part.mesh, grasp, kinds=scan.edge_kind,
                            outlier_mm=EDGE_OUTLIER_MM)
        edges = {k: finite_or_none(acc[k]) for k in ("rms_um", "median_um", "p99_um",
                                                      "outlier_fraction", "rms_inliers_um")}
        edges["count"] = int(len(scan.edges))
        edges["by_kind"] = {kind: {"count": v["count"], "rms_um": finite_or_none(v.get("rms_um"))}
                            for kind, v in acc["by_kind"].items()}
    edges_ok, edges_why = edge_verdict(edges)
    cloud = report["ground_truth"].get("accuracy", {})
    p = truth.pass_profile
    row = {
        "factor": factor, "level": level, "part": part.name, "seed": seed,
        "misplacement": list(misplacement),
        "spacing_mm": round(p.speed_mm_s / p.fps, 4),
        "profiles_on_part": round(float(part.extents_t[1]) / (p.speed_mm_s / p.fps), 2),
        "cli_refusal": _cli_refusal(part, truth) if factor == "speed" else None,
        "frames": int(report["frames"]),
        "frames_unplaced": int(report["frames_unplaced"]),
        "points": int(report["points"]),
        "edge_points": int(report["edge_points"]),
        "end_reason": report.get("end_reason"),
        "cross_check_flagged": report["cross_check"].get("flagged"),
        "cloud_rms_um": finite_or_none(cloud.get("rms_um")),
        "edges": edges,
        "edges_within_target": edges_ok,
        "edges_miss": edges_why,
        "pose": pose_figures(report),
        "wall_s": round(wall_s, 2),
    }
    if factor == "marker":
        row["mirror_columns_truth"] = [list(m.columns) for m in truth.calibration.mirrors]
    row["verdict"] = _verdict(row)
    # What the library's pose says when nothing refuses the pass first.
    row["pose_verdict"] = pose_verdict(row["pose"])
    return row


def progress(row: dict) -> None:
    """One row, in one line on stderr."""
    pose, edges = row["pose"], row["edges"]

    def f(x, fmt):
        return format(x, fmt) if x is not None else "   -"

    print(f"bench pose limits: {row['factor']:10s} {row['level']:>7g} {row['part']:22s} "
          f"seed {row['seed']} {row['frames']:4d} frames {row['points']:6d} pts "
          f"{row['edge_points']:4d} edges  edge RMS {f(edges.get('rms_um'), '6.1f')} um  "
          f"pose {f(pose['translation_um'], '7.1f')} um {f(pose['rotation_mdeg'], '7.1f')} mdeg "
          f"max {f(pose['max_sigmas'], '5.1f')} sigma  {row['verdict']}  ({row['wall_s']:.1f} s)",
          file=sys.stderr, flush=True)
