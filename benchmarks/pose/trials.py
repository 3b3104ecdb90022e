"""The pose bench's (a): one registration per scan and configuration, scored against the truth,
and the summaries per configuration, with the model to keep (the CAD mesh or the predicted
cloud)."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from scanner_core.pose.registration import PoseParams, PoseResult, SurfaceModel, scan_pose
from benchmarks.pose.calibration import calibration
from benchmarks.stats import fraction, judged, spread
from benchmarks.targets import TARGET_ROTATION_MDEG, TARGET_TRANSLATION_UM
from simulator.parts import Part

__all__ = ["CONFIGS", "DEFAULT_CONFIG", "QUICK_CONFIGS", "SUCCESS_MM", "SUCCESS_DEG",
           "register", "score", "trial", "trial_line", "config_summary", "accuracy_summary",
           "recommend", "fmt"]

# Configurations: name -> (model, with the edge cloud, max_points or None for the default,
# PoseParams().max_points: 6000 at the time of writing; the scans have 2.6k to 30k points).
CONFIGS = {
    "mesh+edges": ("mesh", True, None),
    "mesh": ("mesh", False, None),
    "predicted+edges": ("predicted", True, None),
    "predicted": ("predicted", False, None),
    "mesh+edges 20k": ("mesh", True, 20000),
    "mesh+edges 2k": ("mesh", True, 2000),
}
DEFAULT_CONFIG = "mesh+edges"
QUICK_CONFIGS = tuple(CONFIGS)
#: A registration succeeds (converges) within this of the truth, mm and degrees.
SUCCESS_MM, SUCCESS_DEG = 0.1, 0.1


def register(part: Part, scan, start, config: str, predicted: SurfaceModel) -> PoseResult:
    """`scan_pose` from `start` in configuration `config` (`predicted`: the predicted cloud's
    model, for the configurations that use it)."""
    model, edges, max_points = CONFIGS[config]
    params = PoseParams() if max_points is None else PoseParams(max_points=max_points)
    return scan_pose(scan, part.surface_model if model == "mesh" else predicted, start,
                     edge_model=part.edge_model if edges else None, params=params)


def score(result: PoseResult, truth: np.ndarray) -> dict:
    """The error of a registered pose against the truth: per axis (um, mdeg; signed, of
    ``result.matrix @ inv(truth)`` in {T}), its norms, and per axis in reported sigmas."""
    e = result.matrix @ np.linalg.inv(truth)
    rotvec = Rotation.from_matrix(e[:3, :3]).as_rotvec(degrees=True) * 1e3
    values = np.concatenate([e[:3, 3] * 1e3, rotvec])
    std = np.asarray(result.std, dtype=np.float64) * 1e3  # mm -> um, deg -> mdeg
    with np.errstate(invalid="ignore", divide="ignore"):
        z = values / std
    t_norm, r_norm = float(np.linalg.norm(values[:3])), float(np.linalg.norm(rotvec))
    return {
        "translation_um": values[:3].tolist(), "rotation_mdeg": values[3:].tolist(),
        "translation_norm_um": t_norm, "rotation_angle_mdeg": r_norm,
        "std_um_mdeg": std.tolist(), "z": z.tolist(),
        "success": bool(t_norm < SUCCESS_MM * 1e3 and r_norm < SUCCESS_DEG * 1e3),
        "within_target": bool(t_norm <= TARGET_TRANSLATION_UM
                              and r_norm <= TARGET_ROTATION_MDEG),
        "time_ms": float(result.time_ms), "coarse": bool(result.coarse),
        "iterations": int(result.iterations), "flags": list(result.flags),
        "observable": bool(result.observable),
        "free_axes": [a["label"] for a in result.free_axes],
        "inlier_fraction": float(result.inlier_fraction), "rms_um": float(result.rms_mm) * 1e3,
    }


def trial(part, scan, truth, config, predicted, info) -> dict:
    """One registration from the nominal grasp, scored: a row of ``trials``."""
    row = {"part": part.name, "scan": info["scan"], "config": config,
           "misplacement": info["misplacement"], "points": info["points"]}
    try:
        row.update(score(register(part, scan, part.grasp, config, predicted), truth))
        row["refused"] = None
    except ValueError as exc:  # too few points: the registration refuses, with its reason
        row["refused"] = str(exc)
    return row


def trial_line(info: dict, rows: list[dict]) -> str:
    """One scan's trials, in one progress line."""
    parts = [f"{info['part']} scan {info['scan']}: {info['points']} points, "
             f"{info['edge_points']} edge points"]
    for r in rows:
        if r["refused"]:
            parts.append(f"{r['config']} refused")
        else:
            parts.append(f"{r['config']} {r['translation_norm_um']:.1f} um "
                         f"{r['rotation_angle_mdeg']:.1f} mdeg {r['time_ms']:.0f} ms"
                         + (" coarse" if r["coarse"] else "") + (" flagged" if r["flags"] else ""))
    return "; ".join(parts)


def config_summary(name: str, spec: dict, rows: list[dict]) -> dict:
    """One configuration's trials: accuracy, time, flags, per part, and the calibration of
    their sigmas (`benchmarks.pose.calibration.calibration`)."""
    done = [r for r in rows if not r["refused"]]
    observable = [r for r in done if r["observable"]]
    acted_on = [r for r in done if not r["flags"]]
    per_part = {}
    for part in dict.fromkeys(r["part"] for r in rows):
        sel = [r for r in done if r["part"] == part]
        per_part[part] = {
            "trials": len(sel),
            "translation_um": spread([r["translation_norm_um"] for r in sel]),
            "rotation_mdeg": spread([r["rotation_angle_mdeg"] for r in sel]),
            "time_ms_median": spread([r["time_ms"] for r in sel])["median"],
            "within_target": fraction([r["within_target"] for r in sel]),
            "not_observable": sum(not r["observable"] for r in sel),
            "flagged": sum(bool(r["flags"]) for r in sel),
        }
    return {
        "config": name, "model": spec["model"], "edges": spec["edges"],
        "max_points": spec["max_points"],
        "trials": len(rows), "refused": len(rows) - len(done),
        "not_observable": len(done) - len(observable),
        "flagged": len(done) - len(acted_on),
        "coarse": sum(r["coarse"] for r in done),
        # The target is for observable parts: the trials the registration reports observable.
        "translation_um": spread([r["translation_norm_um"] for r in observable]),
        "rotation_mdeg": spread([r["rotation_angle_mdeg"] for r in observable]),
        "all_trials": {"translation_um": spread([r["translation_norm_um"] for r in done]),
                       "rotation_mdeg": spread([r["rotation_angle_mdeg"] for r in done])},
        # The poses to act on: no flag at all.
        "unflagged": {"trials": len(acted_on),
                      "translation_um": spread([r["translation_norm_um"] for r in acted_on]),
                      "rotation_mdeg": spread([r["rotation_angle_mdeg"] for r in acted_on]),
                      "within_target": fraction([r["within_target"] for r in acted_on])},
        "within_target": fraction([r["within_target"] for r in done]),
        "converged": fraction([r["success"] for r in done]),
        # The worst outcome: a pose with no flag that is wrong by more than 0.1 mm / 0.1 deg.
        "confident_wrong": sum(1 for r in acted_on if not r["success"]),
        "time_ms": spread([r["time_ms"] for r in done]),
        "per_part": per_part,
        "calibration": calibration(done),
    }


def accuracy_summary(configs: dict, trials: list[dict]) -> dict:
    """The summary's ``accuracy`` (the default configuration against the targets),
    ``configs`` (each in a few figures) and ``model`` (`recommend`)."""
    default = configs[DEFAULT_CONFIG]
    return {
        "accuracy": {
            "config": DEFAULT_CONFIG,
            "observable_trials": default["translation_um"]["n"],
            "trials": default["trials"],
            "translation_um_max": judged(default["translation_um"]["max"],
                                         TARGET_TRANSLATION_UM, "<="),
            "rotation_mdeg_max": judged(default["rotation_mdeg"]["max"],
                                        TARGET_ROTATION_MDEG, "<="),
            "translation_um_p95": default["translation_um"]["p95"],
            "rotation_mdeg_p95": default["rotation_mdeg"]["p95"],
            "within_target": default["within_target"],
            "confident_wrong": default["confident_wrong"],
            "flagged": default["flagged"],
            "unflagged_trials": default["unflagged"]["trials"],
            "unflagged_translation_um_max": default["unflagged"]["translation_um"]["max"],
            "unflagged_rotation_mdeg_max": default["unflagged"]["rotation_mdeg"]["max"],
        },
        "configs": {name: {"translation_um_median": c["translation_um"]["median"],
                           "translation_um_p95": c["translation_um"]["p95"],
                           "rotation_mdeg_median": c["rotation_mdeg"]["median"],
                           "rotation_mdeg_p95": c["rotation_mdeg"]["p95"],
                           "within_target": c["within_target"],
                           "not_observable": c["not_observable"], "flagged": c["flagged"],
                           "confident_wrong": c["confident_wrong"],
                           "unflagged_within_target": c["unflagged"]["within_target"],
                           "time_ms_median": c["time_ms"]["median"]}
                    for name, c in configs.items()},
        "model": recommend(configs, trials),
    }


def recommend(configs: dict, trials: list[dict]) -> dict:
    """Mesh or predicted cloud, both with edges at the default size: the one with fewer
    confident wrong poses (the worst outcome), then more trials within the accuracy target;
    on a tie, the predicted cloud only if clearly faster on the same scans (the median of the
    per-scan time ratios: the times of different parts differ tenfold, and a median over all
    of them falls between the parts). The mesh stays unless the predicted cloud is better."""
    mesh, pred = configs.get("mesh+edges"), configs.get("predicted+edges")
    if not mesh or not pred:
        return {"keep": "mesh", "reason": "only the mesh was measured"}
    times = {(t["config"], t["part"], t["scan"]): t["time_ms"] for t in trials
             if not t["refused"]}
    ratios = [times[("predicted+edges", p, i)] / times[("mesh+edges", p, i)]
              for (c, p, i) in times if c == "mesh+edges" and ("predicted+edges", p, i) in times]
    ratio = float(np.median(ratios)) if ratios else None  # None: no scan registered by both

    def key(c):
        return (c["confident_wrong"], -(c["within_target"] or 0.0))

    if key(pred) < key(mesh):
        keep = "predicted"
    elif key(pred) == key(mesh) and ratio is not None and ratio < 0.8:
        keep = "predicted"
    else:
        keep = "mesh"

    def describe(label, c):
        return (f"{label}: {100 * (c['within_target'] or 0):.0f} % of trials within "
                f"{TARGET_TRANSLATION_UM:g} um / {TARGET_ROTATION_MDEG:g} mdeg, p95 "
                f"{fmt(c['translation_um']['p95'])} um / {fmt(c['rotation_mdeg']['p95'])} mdeg"
                f", {c['confident_wrong']} confident wrong, median "
                f"{fmt(c['time_ms']['median'])} ms")

    return {"keep": keep,
            "time_ratio_predicted_to_mesh": None if ratio is None else round(ratio, 3),
            "reason": describe("mesh", mesh) + "; " + describe("predicted", pred)
            + "; predicted/mesh time on the same scans "
            + ("n/a" if ratio is None else f"{ratio:.2f}") + " (median). The predicted "
              "cloud also has to be swept again for every cell setup and nominal grasp."}


def fmt(v) -> str:
    """A figure to one decimal, or n/a."""
    return "n/a" if v is None else f"{v:.1f}"
