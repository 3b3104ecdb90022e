"""Benchmark of the part's pose in the gripper (`scanner_core.pose`): accuracy against time,
basin of convergence, calibration of the reported sigma, and Open3D and small_gicp side by side.

On the reference cell and the four reference parts (the quick set: the procedural demo block
only), with one simulated pass per (part, misplacement, seed) and several registrations on each:

a. **Accuracy against time per configuration.** Scans of every part at random misplacements up
   to 5 mm and 10 degrees (the issue's target set; seeded), each registered from the nominal
   grasp against the CAD mesh (`SurfaceModel.from_mesh`) and against the simulator's
   predicted cloud of the same pass (`simulator.virtual_setup.predict_cloud` at the nominal
   grasp, mapped back to {P}: the paper's conclusion), with and without the edge cloud (the
   CAD's sharp edges, `EdgeModel.from_mesh`, either way), and with fewer points
   (`PoseParams.max_points`). Per configuration: translation error (um, norm of the {T}
   origin's error) and rotation error (mdeg, angle) median / p95 / max, and the registration
   time (``PoseResult.time_ms``; the scan's normals are computed once per scan and reported
   apart). The mesh is the default; the summary says which model to keep.
b. **Basin of convergence.** Success (error below 0.1 mm and 0.1 degrees) against the initial
   misplacement, up to 15 mm and 30 degrees, in random directions (seeded), with the coarse
   stage as it is. Most trials reuse the scans of (a): the start is the true pose displaced by
   the trial's misplacement (the registration sees only the start relative to the truth); in
   the full set a few scans are also rendered at the large misplacements themselves. The
   target is scored on the scans that constrain every axis: each scan is registered once
   from its true pose, and a scan whose pose there reports a free axis (ADIS16480 seen on its
   end: nothing in it fixes the slide along the pass) cannot converge along that axis from any
   start, whatever the method. Those trials are scored apart, along the axes their pose
   reports, and the rate over every trial is given beside the target's.
c. **Calibration of the uncertainty.** For every trial of (a), the signed error over the
   reported standard deviation per axis (free axes, with no sigma, left out): the fraction of
   trials with every axis within 3 sigma, and the factor by which the sigmas would have to be
   inflated to reach the target, over all trials and over the converged ones.
d. **Side by side** on one ~50k-point scan (a denser pass: 50 mm/s) of one part, from the same
   start (the nominal grasp) against the same target (the CAD sampled as points with normals,
   `SurfaceModel.from_mesh`): flyscan's `register` (with the scan's normals,
   ``scanner_core.scanio.scan_normals``; the models' building reported apart, since it is
   once per part), Open3D's point-to-plane ICP (building its clouds; its KD-tree is built in
   the call) and small_gicp (its preprocessing: downsampling, normals or covariances, KD-trees;
   then its plane ICP and its GICP). Each timed with its preprocessing, several runs in turn,
   medians. Open3D and small_gicp are optional benchmark-only extras
   (``pip install 'flyscan[bench]'``); a missing one is skipped with a note.

BLAS is held to one thread (``threadpoolctl``); the KD-tree queries and the other libraries
use both cores as they do by default. ``run(out_dir)`` writes ``pose.json``, ``pose.png`` and
``pose_calibration.png`` into ``out_dir`` and returns the dict.
"""
from __future__ import annotations

import importlib.util
import json
import os
import pathlib
import sys
import time

import numpy as np
from scipy import stats
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from scanner_core.fileio import save_json_atomic
from scanner_core.pose import PoseParams, PoseResult, SurfaceModel, register, scan_pose
from scanner_core.scanio import scan_normals
from benchmarks.machine import machine_info
from simulator.cell import Cell, load_cell
from simulator.evaluate import edge_accuracy
from simulator.parts import Part, block_with_holes_and_steps, load_reference_part, part_from_mesh
from simulator.session import misplacement_matrix, run_simulated_scan
from simulator.virtual_setup import predict_cloud, reference_setup

__all__ = ["run", "side_by_side", "CONFIGS"]

REFERENCE_PARTS = ("idler_riser", "featuretype", "ADIS16480", "cycloidal")
BLOCK_PART = "block"

# (a) The target set: misplacements up to this far from the nominal grasp.
ACCURACY_MAX_MM, ACCURACY_MAX_DEG = 5.0, 10.0
SCANS_PER_PART, QUICK_SCANS_PER_PART = 8, 3
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

# (b) Initial misplacements (mm, degrees), in random directions; the target holds up to
# BASIN_TARGET_LEVEL.
BASIN_LEVELS = ((2.5, 5.0), (5.0, 10.0), (7.5, 15.0), (10.0, 20.0), (12.5, 25.0), (15.0, 30.0))
BASIN_TRIALS = 10         # per part and level, on the scans of (a), beyond the target's range
# Within it (up to BASIN_TARGET_LEVEL): enough trials that a rate of 99 % can be shown, not
# only measured (with none failed, the one-sided 95 % lower bound passes 99 % at 299).
BASIN_TRIALS_IN_TARGET = 25
BASIN_RENDERED_LEVELS = ((10.0, 20.0), (15.0, 30.0))  # one scan per part rendered at each
QUICK_BASIN_LEVELS = ((2.5, 5.0), (10.0, 20.0))
QUICK_BASIN_TRIALS = 2
BASIN_TARGET_LEVEL = (10.0, 20.0)
SUCCESS_MM, SUCCESS_DEG = 0.1, 0.1

# (c) Every axis within this many reported sigma in at least TARGET_CALIBRATED of the trials.
SIGMA_BOUND = 3.0

# (d) One part, a denser pass (about 50k points), misplacements about 1 mm / 1 degree and
# about 2 mm / 4 degrees; each method run this often, in turn.
SIDE_PART = "idler_riser"
SIDE_SPEED_MM_S = 50.0
SIDE_MISPLACEMENTS = ((0.6, -0.5, 0.4, 0.5, -0.6, 0.5), (1.5, -1.0, 0.8, 2.0, -3.0, 2.5))
SIDE_RUNS, QUICK_SIDE_RUNS = 7, 1
# Open3D and small_gicp: correspondences up to this far (mm; the misplacements above move no
# point of the part farther), at most this many iterations. small_gicp stops when an update
# is below 0.1 degree by default, more than the 0.02 degree target: its tolerances here are
# tight (SIDE_TOL_*). Open3D stops on the relative change of its fit: its default (1e-6)
# already lands within a few um and mdeg; 1e-9 bought less than 0.5 um for 50 % more time.
SIDE_GATE_MM = 2.0
SIDE_MAX_ITERATIONS = 60
SIDE_TOL_MM, SIDE_TOL_DEG = 1e-4, 1e-3
OPEN3D_RELATIVE_TOL = 1e-6
SMALL_GICP_DOWNSAMPLING_MM = 0.25  # its default; about the scan's own spacing
SIDE_THREADS = 2

# The targets.
TARGET_TRANSLATION_UM = 20.0
TARGET_ROTATION_MDEG = 20.0
TARGET_BASIN = 0.99
TARGET_CALIBRATED = 0.99
TARGET_EDGE_RMS_UM = 30.0   # edge points against the CAD's sharp edges, in (x_T, y_T)
TARGET_EDGE_OUTLIERS = 0.05  # of them farther than 0.5 mm from every edge
TARGET_SPEED_RATIO = 1.0  # flyscan's time over each other library's, on the same input

_SEED = 20261
_PERCENTILE = 95


# --------------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------------

def run(out_dir, quick: bool = False, *, progress=None) -> dict:
    """Run the benchmark; write ``pose.json``, ``pose.png`` and ``pose_calibration.png``.

    Parameters
    ----------
    out_dir : path
        Created when missing.
    quick : bool
        The CI set: the procedural block only, few scans and trials, the side by side on one
        of its default-pass scans (about 10k points) once.
    progress : callable, optional
        Called with one line per step; default: printed on stderr.

    Returns
    -------
    dict
        What ``pose.json`` holds; ``summary`` has the targets and whether each is met.
    """
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda line: print(line, file=sys.stderr, flush=True))
    t_start = time.perf_counter()
    load_before = os.getloadavg()
    cell = load_cell()
    names = (BLOCK_PART,) if quick else REFERENCE_PARTS
    n_scans = QUICK_SCANS_PER_PART if quick else SCANS_PER_PART
    levels = QUICK_BASIN_LEVELS if quick else BASIN_LEVELS
    n_basin = [QUICK_BASIN_TRIALS if quick else
               BASIN_TRIALS_IN_TARGET if _in_target(level) else BASIN_TRIALS for level in levels]
    with threadpool_limits(limits=1, user_api="blas"):
        trials, basin, models, scans_info = [], [], {}, []
        first_scan = None
        for p_index, name in enumerate(names):
            part = _part(name)
            models[name], predicted = _build_models(part, cell)
            say(f"{name}: models built (mesh {models[name]['mesh_surface_ms']:.0f} ms, edges "
                f"{models[name]['edge_model_ms']:.0f} ms, predicted cloud "
                f"{models[name]['predicted_ms']:.0f} ms, {models[name]['predicted_points']} "
                f"points)")
            rng = np.random.default_rng([_SEED, p_index])
            scans = []
            for i in range(n_scans):
                values = _random_misplacement(rng, ACCURACY_MAX_MM, ACCURACY_MAX_DEG, up_to=True)
                scan, truth, info = _scan(part, cell, values, seed=i)
                info.update(_at_truth(part, scan, truth))
                scans.append((scan, truth))
                scans_info.append(info)
                if first_scan is None:
                    first_scan = (part, scan, truth, values)
                for config in QUICK_CONFIGS if quick else CONFIGS:
                    trials.append(_trial(part, scan, truth, config, predicted,
                                         dict(info, misplacement=values)))
                say(_trial_line(info, [t for t in trials if t["part"] == name
                                       and t["scan"] == i]))
            from_nominal = {t["scan"]: t.get("success", False) for t in trials
                            if t["part"] == name and t["config"] == DEFAULT_CONFIG}
            observable = {i["scan"]: i["observable_at_truth"] for i in scans_info
                          if i["part"] == name}
            basin += _basin_displaced(part, scans, from_nominal, observable, levels, n_basin,
                                      rng, say)
            if not quick:
                basin += _basin_rendered(part, cell, BASIN_RENDERED_LEVELS, rng, say)
        if quick:
            part, scan, truth, values = first_scan
            side = side_by_side(part, [(scan, truth, values)], runs=QUICK_SIDE_RUNS,
                                progress=say, dense=False)
        else:
            side = side_by_side(_part(SIDE_PART), None, cell=cell, runs=SIDE_RUNS,
                                progress=say)
    result = {
        "machine": dict(machine_info(), load_average_before=[round(v, 2) for v in load_before],
                        load_average_after=[round(v, 2) for v in os.getloadavg()]),
        "quick": quick,
        "settings": _settings(quick, names, n_scans, levels, n_basin),
        "models": models,
        "scans": scans_info,
        "trials": trials,
        "basin": {"trials": basin},
        "side_by_side": side,
        "elapsed_s": round(time.perf_counter() - t_start, 1),
    }
    result = _finish(_clean(result), out_dir)
    say(f"pose bench done in {result['elapsed_s']:.0f} s: {out_dir / 'pose.json'}")
    return result


def rebuild(out_dir) -> dict:
    """Recompute the summaries and redraw the charts from the trials in ``pose.json``."""
    out_dir = pathlib.Path(out_dir)
    return _finish(json.loads((out_dir / "pose.json").read_text()), out_dir)


def _finish(result: dict, out_dir: pathlib.Path) -> dict:
    """Everything that follows from the trials: per configuration, per basin level, the
    calibration, the summary; then ``pose.json`` and the charts written."""
    trials, settings = result["trials"], result["settings"]
    result["configs"] = [
        _config_summary(name, settings["configs"][name],
                        [t for t in trials if t["config"] == name])
        for name in dict.fromkeys(t["config"] for t in trials)]
    result["basin"]["levels"] = _basin_levels(result["basin"]["trials"],
                                              [tuple(lv) for lv in settings["basin_levels"]])
    # The per-trial z values once, here; the configurations keep the figures.
    result["calibration"] = {c["config"]: c.pop("calibration") for c in result["configs"]}
    for c in result["configs"]:
        c["calibration"] = {k: result["calibration"][c["config"]][k]
                            for k in ("all", "converged")}
    result["summary"] = _summary(result)
    result = _clean(result)
    save_json_atomic(out_dir / "pose.json", result)
    _plot(result, out_dir / "pose.png")
    _plot_calibration(result, out_dir / "pose_calibration.png")
    return result


def _settings(quick, names, n_scans, levels, n_basin) -> dict:
    return {
        "parts": list(names), "scans_per_part": n_scans,
        "accuracy_misplacement_up_to": {"mm": ACCURACY_MAX_MM, "deg": ACCURACY_MAX_DEG},
        "configs": {name: {"model": m, "edges": e,
                           "max_points": mp if mp is not None else PoseParams().max_points}
                    for name, (m, e, mp) in CONFIGS.items()},
        "default_config": DEFAULT_CONFIG,
        "basin_levels": [list(level) for level in levels],
        "basin_trials_per_part_and_level": n_basin,  # one count per level
        "basin_rendered_levels": [] if quick else [list(lv) for lv in BASIN_RENDERED_LEVELS],
        "success": {"mm": SUCCESS_MM, "deg": SUCCESS_DEG},
        "sigma_bound": SIGMA_BOUND,
        "predicted_cloud": "predict_cloud(part, reference_setup(cell), pose=part.grasp), "
                           "mapped to {P} by inv(grasp); the CAD's edge model with it",
        "blas_threads": 1,
        "seed": _SEED,
    }


# --------------------------------------------------------------------------------------------
# Parts, models, scans
# --------------------------------------------------------------------------------------------

def _part(name: str) -> Part:
    if name == BLOCK_PART:
        return part_from_mesh(block_with_holes_and_steps(), name=BLOCK_PART,
                              source="procedural:block_with_holes_and_steps")
    return load_reference_part(name)


def _build_models(part: Part, cell: Cell) -> tuple[dict, SurfaceModel]:
    """The part's registration models, each timed with its KD-tree (once per part)."""
    t0 = time.perf_counter()
    surface = part.surface_model
    surface.tree  # noqa: B018 - built here, timed here
    t1 = time.perf_counter()
    edges = part.edge_model
    edges.tree  # noqa: B018
    t2 = time.perf_counter()
    cloud = predict_cloud(part, reference_setup(cell), pose=part.grasp)
    back = np.linalg.inv(part.grasp)
    predicted = SurfaceModel.from_points(cloud.points @ back[:3, :3].T + back[:3, 3],
                                         cloud.normals @ back[:3, :3].T)
    predicted.tree  # noqa: B018
    t3 = time.perf_counter()
    return {"faces": int(len(part.faces)), "mesh_surface_points": int(len(surface.points)),
            "mesh_surface_ms": (t1 - t0) * 1e3, "edge_points": int(len(edges.points)),
            "edge_model_ms": (t2 - t1) * 1e3, "predicted_points": int(len(predicted.points)),
            "predicted_ms": (t3 - t2) * 1e3,
            "predicted_sweep_ms": cloud.elapsed_s * 1e3}, predicted


def _random_misplacement(rng, t_mm: float, r_deg: float, *, up_to: bool) -> list[float]:
    """A translation and a rotation vector in random directions: of exactly `t_mm` and `r_deg`
    or, with `up_to`, of magnitudes uniform in ``[0, t_mm]`` and ``[0, r_deg]``."""
    direction = rng.normal(size=3)
    axis = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    axis /= np.linalg.norm(axis)
    t, r = (rng.uniform(0.0, t_mm), rng.uniform(0.0, r_deg)) if up_to else (t_mm, r_deg)
    return [round(float(v), 6) for v in np.concatenate([direction * t, axis * r])]


def _scan(part: Part, cell: Cell, values, *, seed: int):
    """One simulated pass (no registration of its own, no cloud scoring) and its normals."""
    truth = misplacement_matrix(values) @ part.grasp
    t0 = time.perf_counter()
    scan, report = run_simulated_scan(part, cell, misplacement=misplacement_matrix(values),
                                      seed=seed, evaluate=False, pose=False)
    t1 = time.perf_counter()
    scan_normals(scan)
    info = {"part": part.name, "scan": seed, "seed": seed, "points": int(len(scan.cloud)),
            "edge_points": int(len(scan.edges)), "frames": int(report["frames"]),
            "render_and_process_s": round(t1 - t0, 3),
            "normals_ms": round((time.perf_counter() - t1) * 1e3, 3)}
    t2 = time.perf_counter()
    if len(scan.edges):
        accuracy = edge_accuracy(scan.edges, part.mesh, truth, kinds=scan.edge_kind)
        info["edges"] = {k: accuracy[k] for k in ("count", "rms_um", "median_um",
                                                  "outlier_fraction", "rms_inliers_um",
                                                  "dropouts_off_sharp_edges")}
    info["edge_scoring_ms"] = round((time.perf_counter() - t2) * 1e3, 3)
    return scan, truth, info


# --------------------------------------------------------------------------------------------
# One registration, scored
# --------------------------------------------------------------------------------------------

def _register(part: Part, scan, start, config: str, predicted: SurfaceModel) -> PoseResult:
    model, edges, max_points = CONFIGS[config]
    params = PoseParams() if max_points is None else PoseParams(max_points=max_points)
    return scan_pose(scan, part.surface_model if model == "mesh" else predicted, start,
                     edge_model=part.edge_model if edges else None, params=params)


def _score(result: PoseResult, truth: np.ndarray) -> dict:
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


def _trial(part, scan, truth, config, predicted, info) -> dict:
    row = {"part": part.name, "scan": info["scan"], "config": config,
           "misplacement": info["misplacement"], "points": info["points"]}
    try:
        row.update(_score(_register(part, scan, part.grasp, config, predicted), truth))
        row["refused"] = None
    except ValueError as exc:  # too few points: the registration refuses, with its reason
        row["refused"] = str(exc)
    return row


def _trial_line(info: dict, rows: list[dict]) -> str:
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


# --------------------------------------------------------------------------------------------
# (b) Basin of convergence
# --------------------------------------------------------------------------------------------

def _basin_displaced(part, scans, from_nominal, observable, levels, n_trials, rng,
                     say) -> list[dict]:
    """Trials on the scans of (a) (`n_trials`: a count per level), taken in turn: the start
    is the true pose displaced by the trial's misplacement (``truth = D @ start``), the
    default configuration, the coarse stage as is. Each row says whether the same scan
    converged from the nominal grasp in (a) (`from_nominal`: scan index -> bool), which
    tells a narrow basin from a hard scan, and whether it constrains every axis at its true
    pose (`observable`: scan index -> bool, from `_at_truth`)."""
    rows, turn = [], 0
    for level_index, (t_mm, r_deg) in enumerate(levels):
        for _ in range(n_trials[level_index]):
            index = turn % len(scans)  # the scans taken in turn, across the levels
            turn += 1
            scan, truth = scans[index]
            values = _random_misplacement(rng, t_mm, r_deg, up_to=False)
            start = np.linalg.inv(misplacement_matrix(values)) @ truth
            rows.append(_basin_row(part, scan, truth, start, values, t_mm, r_deg,
                                   "displaced start", index))
            rows[-1]["scan_converged_from_nominal"] = bool(from_nominal.get(index, False))
            rows[-1]["scan_observable"] = bool(observable[index])
        done = [r for r in rows if r["level"] == [t_mm, r_deg]]
        say(f"{part.name} basin {t_mm:g} mm / {r_deg:g} deg: "
            f"{sum(r['success'] for r in done)}/{len(done)} converged, median "
            f"{np.median([r['time_ms'] or 0.0 for r in done]):.0f} ms, "
            f"{sum(bool(r['coarse']) for r in done)} with the coarse stage")
    return rows


def _basin_rendered(part, cell, levels, rng, say) -> list[dict]:
    """One pass rendered at each large misplacement itself, registered from the nominal."""
    rows = []
    for t_mm, r_deg in levels:
        values = _random_misplacement(rng, t_mm, r_deg, up_to=False)
        seed = 100 + len(rows)
        try:
            scan, truth, _ = _scan(part, cell, values, seed=seed)
        except ValueError as exc:  # the part leaves the cell's volume: no pass to register
            rows.append({"part": part.name, "level": [t_mm, r_deg], "kind": "rendered",
                         "misplacement": values, "success": False, "time_ms": None,
                         "coarse": None, "refused": f"not scanned: {exc}"})
            continue
        rows.append(_basin_row(part, scan, truth, part.grasp, values, t_mm, r_deg, "rendered",
                               seed))
        rows[-1]["scan_observable"] = _at_truth(part, scan, truth)["observable_at_truth"]
        r = rows[-1]
        say(f"{part.name} basin, rendered at {t_mm:g} mm / {r_deg:g} deg: "
            + ("refused" if r["refused"] else
               f"{r['translation_norm_um']:.1f} um {r['rotation_angle_mdeg']:.1f} mdeg "
               f"{r['time_ms']:.0f} ms" + (" coarse" if r["coarse"] else "")))
    return rows


def _in_target(level) -> bool:
    """Whether a basin level (mm, degrees) lies within the target's range."""
    return level[0] <= BASIN_TARGET_LEVEL[0] and level[1] <= BASIN_TARGET_LEVEL[1]


def _at_truth(part: Part, scan, truth) -> dict:
    """Whether the scan constrains every axis of the part's pose: registered once from its
    true pose (default configuration), what the pose reports there. This decides the basin
    target's scope by the scan, not by what a trial's own pose claims: an axis the scan
    leaves free at the truth has no right answer to converge to. (From another start a pose
    can land where its curvature claims a little more: ADIS16480 scan 6, free about z_T at
    its truth, came out 142 mdeg off with no free axis and a sigma of 156 mdeg, flagged
    ambiguous; the summary's ``own_report`` counts such trials.)"""
    try:
        result = _register(part, scan, truth, DEFAULT_CONFIG, None)
    except ValueError as exc:
        return {"observable_at_truth": False, "free_axes_at_truth": [f"refused: {exc}"]}
    return {"observable_at_truth": bool(result.observable),
            "free_axes_at_truth": [a["label"] for a in result.free_axes]}


def _basin_row(part, scan, truth, start, values, t_mm, r_deg, kind, index) -> dict:
    row = {"part": part.name, "level": [t_mm, r_deg], "kind": kind, "scan": index,
           "misplacement": values}
    try:
        row.update(_score(_register(part, scan, start, DEFAULT_CONFIG, None), truth))
        row["refused"] = None
    except ValueError as exc:
        row.update(success=False, time_ms=None, coarse=None, refused=str(exc))
    return row


def _basin_levels(rows, levels) -> list[dict]:
    out = []
    for t_mm, r_deg in levels:
        level = {"mm": t_mm, "deg": r_deg}
        for kind in ("displaced start", "rendered"):
            sel = [r for r in rows if r["level"] == [t_mm, r_deg] and r["kind"] == kind]
            if not sel:
                continue
            ok = sum(r["success"] for r in sel)
            good = [r for r in sel if r.get("scan_converged_from_nominal", True)]
            observable = [r for r in sel if r.get("scan_observable", True)]
            level[kind] = {
                "trials": len(sel), "converged": ok, "success_rate": ok / len(sel),
                # The target's scope: the scans that constrain every axis (`_at_truth`).
                "trials_on_observable_scans": len(observable),
                "success_rate_on_observable_scans": _fraction([r["success"]
                                                               for r in observable]),
                # Only the scans that converge from the nominal grasp in (a): the basin
                # itself, without the scans that fail whatever the start.
                "trials_on_good_scans": len(good),
                "success_rate_on_good_scans": _fraction([r["success"] for r in good]),
                "coarse": sum(bool(r.get("coarse")) for r in sel),
                "flagged_failures": sum(1 for r in sel if not r["success"]
                                        and (r.get("refused") or r.get("flags"))),
                "confident_failures": sum(1 for r in sel if not r["success"]
                                          and not r.get("refused") and not r.get("flags")),
                "time_ms": _stats([r["time_ms"] for r in sel if r.get("time_ms") is not None]),
            }
        out.append(level)
    return out


# --------------------------------------------------------------------------------------------
# (a), (c) Summaries per configuration
# --------------------------------------------------------------------------------------------

def _stats(values) -> dict:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=np.float64)
    if len(v) == 0:
        return {"n": 0, "median": None, "p95": None, "max": None}
    return {"n": int(len(v)), "median": float(np.median(v)),
            "p95": float(np.percentile(v, _PERCENTILE)), "max": float(v.max())}


def _config_summary(name: str, spec: dict, rows: list[dict]) -> dict:
    done = [r for r in rows if not r["refused"]]
    observable = [r for r in done if r["observable"]]
    acted_on = [r for r in done if not r["flags"]]
    per_part = {}
    for part in dict.fromkeys(r["part"] for r in rows):
        sel = [r for r in done if r["part"] == part]
        per_part[part] = {
            "trials": len(sel),
            "translation_um": _stats([r["translation_norm_um"] for r in sel]),
            "rotation_mdeg": _stats([r["rotation_angle_mdeg"] for r in sel]),
            "time_ms_median": _stats([r["time_ms"] for r in sel])["median"],
            "within_target": _fraction([r["within_target"] for r in sel]),
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
        "translation_um": _stats([r["translation_norm_um"] for r in observable]),
        "rotation_mdeg": _stats([r["rotation_angle_mdeg"] for r in observable]),
        "all_trials": {"translation_um": _stats([r["translation_norm_um"] for r in done]),
                       "rotation_mdeg": _stats([r["rotation_angle_mdeg"] for r in done])},
        # The poses to act on: no flag at all.
        "unflagged": {"trials": len(acted_on),
                      "translation_um": _stats([r["translation_norm_um"] for r in acted_on]),
                      "rotation_mdeg": _stats([r["rotation_angle_mdeg"] for r in acted_on]),
                      "within_target": _fraction([r["within_target"] for r in acted_on])},
        "within_target": _fraction([r["within_target"] for r in done]),
        "converged": _fraction([r["success"] for r in done]),
        # The worst outcome: a pose with no flag that is wrong by more than 0.1 mm / 0.1 deg.
        "confident_wrong": sum(1 for r in acted_on if not r["success"]),
        "time_ms": _stats([r["time_ms"] for r in done]),
        "per_part": per_part,
        "calibration": _calibration(done),
    }


def _fraction(flags) -> float | None:
    flags = list(flags)
    return sum(bool(f) for f in flags) / len(flags) if flags else None


def _calibration(rows: list[dict]) -> dict:
    """|error| / reported sigma per axis over trials (free axes left out): the fraction of
    trials with every axis within SIGMA_BOUND, and the inflation the sigmas would need."""

    def worst(sel):
        out = []
        for r in sel:
            z = np.abs(np.asarray([np.nan if v is None else v for v in r["z"]], dtype=float))
            z = z[np.isfinite(z)]
            if len(z):
                out.append(float(z.max()))
        return np.asarray(out)

    def block(sel) -> dict:
        w = worst(sel)
        if len(w) == 0:
            return {"trials": 0, "within": None, "inflation_needed": None}
        q = float(np.quantile(w, TARGET_CALIBRATED))
        z = np.array([[np.nan if v is None else v for v in r["z"]] for r in sel], dtype=float)
        per_axis = {}
        for i, axis in enumerate(("tx", "ty", "tz", "rx", "ry", "rz")):
            col = z[:, i][np.isfinite(z[:, i])]
            per_axis[axis] = {
                "n": int(len(col)),
                "within": float(np.mean(np.abs(col) <= SIGMA_BOUND)) if len(col) else None,
                "rms_z": float(np.sqrt(np.mean(col**2))) if len(col) else None,
                "max_abs_z": float(np.abs(col).max()) if len(col) else None}
        return {"trials": int(len(w)), "within": float(np.mean(w <= SIGMA_BOUND)),
                "worst_axis_z_q99": q, "worst_axis_z_max": float(w.max()),
                # Multiply every sigma by this for TARGET_CALIBRATED of the trials to have
                # every axis within SIGMA_BOUND sigma (1.0: none needed).
                "inflation_needed": max(1.0, q / SIGMA_BOUND), "per_axis": per_axis}

    converged = [r for r in rows if r["success"]]
    return {"all": block(rows), "converged": block(converged),
            "z": [r["z"] for r in rows], "z_converged": [r["z"] for r in converged]}


# --------------------------------------------------------------------------------------------
# (d) Side by side with Open3D and small_gicp
# --------------------------------------------------------------------------------------------

def side_by_side(part: Part, inputs=None, *, cell: Cell | None = None, runs: int = SIDE_RUNS,
                 progress=None, dense: bool = True) -> dict:
    """flyscan's registration against Open3D's point-to-plane ICP and small_gicp, on the same
    scans from the same start (the nominal grasp), each timed with its preprocessing.

    Parameters
    ----------
    part : Part
    inputs : list of (Scan, (4, 4) truth, misplacement values), optional
        The scans; default: passes of `part` in `cell` at `SIDE_SPEED_MM_S` (about 50k
        points), at each of `SIDE_MISPLACEMENTS`.
    cell : Cell, optional
        For rendering the default inputs (default: the reference cell).
    runs : int
        Runs of every method on every scan, in turn (the order rotates from run to run).

    Returns
    -------
    dict
        Per scan and method: medians of the times (total, preprocessing, registration),
        errors and ratios (flyscan over each); the flyscan model building (once per part);
        ``skipped`` notes for libraries that are not installed.
    """
    say = progress or (lambda line: None)
    if inputs is None:
        cell = (cell or load_cell()).with_pass(speed_mm_s=SIDE_SPEED_MM_S)
        inputs = []
        for i, values in enumerate(SIDE_MISPLACEMENTS):
            scan, truth, info = _scan(part, cell, list(values), seed=200 + i)
            say(f"side by side: {part.name} at {SIDE_SPEED_MM_S:g} mm/s, {info['points']} points")
            inputs.append((scan, truth, list(values)))
    t0 = time.perf_counter()
    model = SurfaceModel.from_mesh(part.mesh)
    model.tree  # noqa: B018
    t1 = time.perf_counter()
    edge_model = part.edge_model
    edge_model.tree  # noqa: B018
    t2 = time.perf_counter()
    methods, skipped = _side_methods(part, model, edge_model)
    cases = []
    for scan, truth, values in inputs:
        timings = {name: [] for name in methods}
        for r in range(runs):
            order = list(methods)
            order = order[r % len(order):] + order[:r % len(order)]
            for name in order:
                timings[name].append(methods[name](scan, part.grasp))
        case = {"points": int(len(scan.cloud)), "edge_points": int(len(scan.edges)),
                "misplacement": values, "runs": runs, "methods": {}}
        for name, results in timings.items():
            pose = results[-1]["pose"]
            e = pose @ np.linalg.inv(truth)
            case["methods"][name] = {
                "total_ms": float(np.median([x["total_ms"] for x in results])),
                "total_ms_fastest": float(min(x["total_ms"] for x in results)),
                "preprocess_ms": float(np.median([x["preprocess_ms"] for x in results])),
                "register_ms": float(np.median([x["register_ms"] for x in results])),
                "total_ms_runs": [round(x["total_ms"], 2) for x in results],
                "translation_um": float(np.linalg.norm(e[:3, 3]) * 1e3),
                "rotation_mdeg": float(np.degrees(Rotation.from_matrix(e[:3, :3]).magnitude())
                                       * 1e3),
                **results[-1].get("extra", {})}
        fly = case["methods"]["flyscan"]
        others = {name: m for name, m in case["methods"].items() if not name.startswith("flyscan")}
        # Medians of the runs; on a shared machine the fastest runs are the steadier figure.
        case["ratios"] = {f"flyscan/{name}": fly["total_ms"] / m["total_ms"]
                          for name, m in others.items()}
        case["ratios_fastest"] = {f"flyscan/{name}": fly["total_ms_fastest"]
                                  / m["total_ms_fastest"] for name, m in others.items()}
        case["ratios_register_alone"] = {
            f"flyscan/{name}": fly["register_ms"] / m["total_ms"] for name, m in others.items()}
        cases.append(case)
        say("side by side, " + f"{case['points']} points: " + ", ".join(
            f"{name} {m['total_ms']:.0f} ms ({m['translation_um']:.1f} um, "
            f"{m['rotation_mdeg']:.1f} mdeg)" for name, m in case["methods"].items()))
    return {
        "part": part.name, "dense_pass": dense,
        "speed_mm_s": SIDE_SPEED_MM_S if dense else None,
        "target": {"points": int(len(model.points)), "spacing_mm": model.spacing_mm,
                   "what": "SurfaceModel.from_mesh: the CAD sampled as points with face normals"},
        "flyscan_models_ms": {"surface": (t1 - t0) * 1e3, "edges": (t2 - t1) * 1e3},
        "settings": {"gate_mm": SIDE_GATE_MM, "max_iterations": SIDE_MAX_ITERATIONS,
                     "small_gicp_tol_mm": SIDE_TOL_MM, "small_gicp_tol_deg": SIDE_TOL_DEG,
                     "open3d_relative_tol": OPEN3D_RELATIVE_TOL,
                     "small_gicp_downsampling_mm": SMALL_GICP_DOWNSAMPLING_MM,
                     "threads": SIDE_THREADS,
                     "flyscan": "as scan_pose: normals of the fitted subsample, register "
                                "with the CAD mesh and the edge cloud, default PoseParams: "
                                "what ships",
                     "flyscan surfaces, all points": "scan_normals + register with the CAD "
                                                     "mesh, every point, no edges: the very "
                                                     "input the others get"},
        "versions": _versions(),
        "skipped": skipped,
        "cases": cases,
    }


def _side_methods(part: Part, model: SurfaceModel, edge_model) -> tuple[dict, dict]:
    """name -> callable(scan, start) returning times (ms) and ^T X_P; notes for skipped ones."""

    def flyscan(scan, start, *, edges=True, all_points=False):
        scan.normals = None  # computed again: part of the cost
        t0 = time.perf_counter()
        if not all_points:  # what ships: normals of the fitted subsample only
            params = PoseParams()
            result = scan_pose(scan, model, start, edge_model=edge_model if edges else None,
                               params=params)
            t1 = t0 + result.normals_ms / 1e3
        else:
            normals = scan_normals(scan)
            t1 = time.perf_counter()
            params = PoseParams(max_points=len(scan.cloud))
            result = register(scan.cloud, normals, model, start, frame_ids=scan.frame_ids,
                              params=params)
        t2 = time.perf_counter()
        return {"total_ms": (t2 - t0) * 1e3, "preprocess_ms": (t1 - t0) * 1e3,
                "register_ms": (t2 - t1) * 1e3, "pose": result.matrix,
                "extra": {"iterations": result.iterations, "flags": list(result.flags),
                          "points_used": min(len(scan.cloud), params.max_points)}}

    methods = {"flyscan": flyscan,
               "flyscan surfaces, all points": lambda s, x: flyscan(s, x, edges=False,
                                                                    all_points=True)}
    skipped = {}
    if importlib.util.find_spec("open3d") is None:
        skipped["open3d"] = ("open3d is not installed (pip install 'flyscan[bench]'): no "
                             "comparison")
    else:
        methods["open3d point-to-plane"] = _open3d_method(model)
    if importlib.util.find_spec("small_gicp") is None:
        skipped["small_gicp"] = ("small_gicp is not installed (pip install 'flyscan[bench]'): "
                                 "no comparison")
    else:
        methods["small_gicp plane ICP"] = _small_gicp_method(model, "PLANE_ICP")
        methods["small_gicp GICP"] = _small_gicp_method(model, "GICP")
    return methods, skipped


def _open3d_method(model: SurfaceModel):
    import open3d as o3d

    reg = o3d.pipelines.registration

    def method(scan, start):
        t0 = time.perf_counter()
        source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
            np.asarray(scan.cloud, dtype=np.float64)))
        target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model.points))
        target.normals = o3d.utility.Vector3dVector(model.normals)
        t1 = time.perf_counter()
        # The source (the scan, {T}) onto the target (the CAD, {P}): the inverse of ^T X_P.
        # Its KD-tree over the target is built inside the call, every call.
        result = reg.registration_icp(
            source, target, SIDE_GATE_MM, np.linalg.inv(start),
            reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(relative_fitness=OPEN3D_RELATIVE_TOL,
                                       relative_rmse=OPEN3D_RELATIVE_TOL,
                                       max_iteration=SIDE_MAX_ITERATIONS))
        t2 = time.perf_counter()
        return {"total_ms": (t2 - t0) * 1e3, "preprocess_ms": (t1 - t0) * 1e3,
                "register_ms": (t2 - t1) * 1e3,
                "pose": np.linalg.inv(np.asarray(result.transformation)),
                "extra": {"fitness": float(result.fitness),
                          "inlier_rmse_um": float(result.inlier_rmse) * 1e3}}

    return method


def _small_gicp_method(model: SurfaceModel, kind: str):
    import small_gicp

    def method(scan, start):
        t0 = time.perf_counter()
        # Its preprocessing: voxel downsampling, normals (plane ICP) or covariances (GICP)
        # from the neighbours, KD-trees; then the registration. As ``small_gicp.align`` on the
        # raw arrays does, in two calls so that the two are timed apart.
        target, target_tree = small_gicp.preprocess_points(
            model.points, downsampling_resolution=SMALL_GICP_DOWNSAMPLING_MM,
            num_threads=SIDE_THREADS)
        source, _ = small_gicp.preprocess_points(
            np.asarray(scan.cloud, dtype=np.float64),
            downsampling_resolution=SMALL_GICP_DOWNSAMPLING_MM, num_threads=SIDE_THREADS)
        t1 = time.perf_counter()
        result = small_gicp.align(
            target, source, target_tree, init_T_target_source=np.linalg.inv(start),
            registration_type=kind, max_correspondence_distance=SIDE_GATE_MM,
            num_threads=SIDE_THREADS, max_iterations=SIDE_MAX_ITERATIONS,
            rotation_epsilon=np.radians(SIDE_TOL_DEG), translation_epsilon=SIDE_TOL_MM)
        t2 = time.perf_counter()
        return {"total_ms": (t2 - t0) * 1e3, "preprocess_ms": (t1 - t0) * 1e3,
                "register_ms": (t2 - t1) * 1e3,
                "pose": np.linalg.inv(np.asarray(result.T_target_source)),
                "extra": {"iterations": int(result.iterations),
                          "converged": bool(result.converged),
                          "source_points": int(source.size()),
                          "target_points": int(target.size())}}

    return method


def _versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for dist in ("open3d-cpu", "open3d", "small-gicp"):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:
            pass
    return out


# --------------------------------------------------------------------------------------------
# Summary
# --------------------------------------------------------------------------------------------

def _target(value, limit, op) -> dict:
    if value is None:
        return {"value": None, "limit": limit, "op": op, "met": False}
    met = {">=": value >= limit, "<=": value <= limit, "<": value < limit}[op]
    return {"value": round(float(value), 4), "limit": limit, "op": op, "met": bool(met)}


def _summary(result: dict) -> dict:
    configs = {c["config"]: c for c in result["configs"]}
    default = configs[DEFAULT_CONFIG]
    summary = {
        "accuracy": {
            "config": DEFAULT_CONFIG,
            "observable_trials": default["translation_um"]["n"],
            "trials": default["trials"],
            "translation_um_max": _target(default["translation_um"]["max"],
                                          TARGET_TRANSLATION_UM, "<="),
            "rotation_mdeg_max": _target(default["rotation_mdeg"]["max"],
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
        "model": _recommend(configs, result["trials"]),
    }
    summary["edges"] = _edge_summary(result["scans"])
    # (b) every trial up to the target level, whichever way it was made; the target on the
    # scans that constrain every axis, the rest scored along the axes their pose reports.
    limit_mm, limit_deg = BASIN_TARGET_LEVEL
    sel = [r for r in result["basin"]["trials"] if _in_target(r["level"])]
    scoped = [r for r in sel if r.get("scan_observable", True)]
    unobservable = [r for r in sel if not r.get("scan_observable", True)]
    own = [r for r in sel if not r.get("refused") and not r.get("free_axes")]
    ok = sum(r["success"] for r in scoped)
    summary["basin"] = {
        "up_to": {"mm": limit_mm, "deg": limit_deg},
        "scope": ("trials on scans that constrain every axis at their true pose"
                  if any("scan_observable" in r for r in sel)
                  else "every trial (these trials carry no observability at the truth)"),
        "success_rate": _target(ok / len(scoped) if scoped else None, TARGET_BASIN, ">="),
        "trials": len(scoped), "converged": ok,
        # One-sided 95 % Clopper-Pearson lower bound: what this many trials can show.
        "success_rate_lower_95": _lower_95(ok, len(scoped)),
        "per_part": {part: _fraction([r["success"] for r in scoped if r["part"] == part])
                     for part in dict.fromkeys(r["part"] for r in sel)},
        # Scoped by each trial's own pose instead: every trial whose pose reports no free
        # axis, and the misses among them (a rival minimum the scan cannot tell apart lands
        # here when its curvature claims the turn).
        "own_report": {
            "trials": len(own), "converged": sum(r["success"] for r in own),
            "success_rate": _fraction([r["success"] for r in own]),
            "misses": [{"part": r["part"], "scan": r["scan"], "level": r["level"],
                        "translation_um": r.get("translation_norm_um"),
                        "rotation_mdeg": r.get("rotation_angle_mdeg"),
                        "max_abs_z": _max_abs_z(r), "flags": r.get("flags")}
                       for r in own if not r["success"]]},
        "all_trials": {"trials": len(sel), "converged": sum(r["success"] for r in sel),
                       "success_rate": _fraction([r["success"] for r in sel]),
                       "success_rate_lower_95": _lower_95(sum(r["success"] for r in sel),
                                                          len(sel))},
        # A free axis keeps whatever the minimum lets it: these trials are scored along the
        # axes their pose reports, and a pose off the truth must say so (a flag: free axes,
        # a rival minimum); none may be confidently wrong.
        "unobservable_scans": {
            "trials": len(unobservable),
            "converged_known_axes": sum(_success_known_axes(r) for r in unobservable),
            "flagged": sum(1 for r in unobservable if r.get("refused") or r.get("flags")),
            "confident_wrong": sum(1 for r in unobservable if not r["success"]
                                   and not r.get("refused") and not r.get("flags")),
            "scans": sorted({f"{r['part']} scan {r['scan']}" for r in unobservable})},
        "success_rate_on_good_scans": _fraction(
            [r["success"] for r in sel if r.get("scan_converged_from_nominal", True)]),
        # Within 0.1 mm / 0.1 degree along the axes the pose reports a sigma for (a free
        # axis, reported as free, keeps its start): not the target, what it adds up to.
        "success_rate_known_axes": _fraction([_success_known_axes(r) for r in sel]),
        "per_part_known_axes": {part: _fraction([_success_known_axes(r)
                                                 for r in sel if r["part"] == part])
                                for part in dict.fromkeys(r["part"] for r in sel)},
        "trials_on_good_scans": sum(1 for r in sel if r.get("scan_converged_from_nominal", True)),
        "per_level": [{"mm": lv["mm"], "deg": lv["deg"],
                       **{kind: lv[kind]["success_rate"] for kind in ("displaced start",
                                                                      "rendered") if kind in lv},
                       "displaced start, good scans":
                           lv.get("displaced start", {}).get("success_rate_on_good_scans"),
                       "displaced start, observable scans":
                           lv.get("displaced start", {}).get(
                               "success_rate_on_observable_scans")}
                      for lv in result["basin"]["levels"]],
    }
    cal = default["calibration"]
    summary["calibration"] = {
        "config": DEFAULT_CONFIG,
        "within_3_sigma": _target(cal["all"]["within"], TARGET_CALIBRATED, ">="),
        "trials": cal["all"]["trials"],
        "inflation_needed": cal["all"]["inflation_needed"],
        "within_3_sigma_converged": cal["converged"]["within"],
        "inflation_needed_converged": cal["converged"]["inflation_needed"],
        "rms_z_per_axis_converged": {axis: v["rms_z"] for axis, v in
                                     cal["converged"].get("per_axis", {}).items()},
    }
    # The basin's registrations carry sigmas too, each its own. They are not independent
    # trials: the starts on one scan mostly land on the same minimum, with the same error
    # and sigma. Their distinct results are counted, and no confidence bound is drawn.
    done = [r for r in result["basin"]["trials"] if not r.get("refused")]
    basin_cal = _calibration(done)
    distinct = list({_result_key(r): r for r in done}.values())
    summary["calibration"]["basin_registrations"] = {
        **{k: basin_cal["all"][k] for k in ("trials", "within", "worst_axis_z_max")
           if k in basin_cal["all"]},
        "distinct_results": len(distinct),
        "distinct_results_within": _fraction([_max_abs_z(r) <= SIGMA_BOUND for r in distinct]),
        # The poses a robot would act on: those without any flag.
        "unflagged_distinct_results_within": _fraction(
            [_max_abs_z(r) <= SIGMA_BOUND for r in distinct if not r.get("flags")]),
    }
    side = result["side_by_side"]
    ratios = {}
    for case in side["cases"]:
        for key, value in case["ratios"].items():
            ratios.setdefault(key, []).append(value)
    worst = {k: max(v) for k, v in ratios.items()}  # over the scans: flyscan's worst case

    def worst_of(key):
        out = {}
        for case in side["cases"]:
            for k, v in case[key].items():
                out[k] = max(out.get(k, v), v)
        return out

    summary["side_by_side"] = {
        "part": side["part"], "points": [c["points"] for c in side["cases"]],
        "flyscan_ms": [c["methods"]["flyscan"]["total_ms"] for c in side["cases"]],
        "ratios_worst_case": worst,
        "ratios_fastest_runs_worst_case": worst_of("ratios_fastest"),
        # flyscan's registration alone (the scan's normals are computed for cloud.ply anyway)
        # against the others' totals.
        "ratios_register_alone_worst_case": worst_of("ratios_register_alone"),
        # flyscan (what ships) against the fastest of the others, on every scan: strictly less.
        "faster_than_each": _target(max(worst.values()) if worst else None,
                                    TARGET_SPEED_RATIO, "<="),
        "skipped": side["skipped"],
    }
    if worst:
        summary["side_by_side"]["faster_than_each"]["met"] = bool(
            max(worst.values()) < TARGET_SPEED_RATIO)
    return summary


def _edge_summary(scans: list[dict]) -> dict:
    """The edge cloud of every scan of (a) against the CAD's sharp edges (drop-outs also
    against the outline: ``simulator.evaluate.edge_accuracy``), per part: the
    issue's target is an RMS within 30 um and fewer than 5 % beyond 0.5 mm. The RMS is of
    the points within 0.5 mm (one stray point 1 mm off among a hundred would make it 100 um
    alone: the outliers are the other half of the target); that of all points beside it."""
    per_part = {}
    for part in dict.fromkeys(s["part"] for s in scans):
        sel = [s["edges"] for s in scans if s["part"] == part and s.get("edges")]
        if not sel:
            continue
        per_part[part] = {
            "scans": len(sel), "edge_points_median": float(np.median([e["count"] for e in sel])),
            "rms_inliers_um_worst": max(e["rms_inliers_um"] for e in sel),
            "rms_inliers_um_median": float(np.median([e["rms_inliers_um"] for e in sel])),
            "outlier_fraction_worst": max(e["outlier_fraction"] for e in sel),
            "rms_all_um_worst": max(e["rms_um"] for e in sel),
            # drop-outs where a rounded or drafted rim turns away: on the outline, off the
            # sharp edges
            "dropouts_off_sharp_edges": int(sum(e.get("dropouts_off_sharp_edges", 0)
                                                for e in sel)),
            "within_target": _fraction([e["rms_inliers_um"] <= TARGET_EDGE_RMS_UM
                                        and e["outlier_fraction"] < TARGET_EDGE_OUTLIERS
                                        for e in sel]),
        }
    if not per_part:
        return {}
    return {"per_part": per_part,
            "rms_inliers_um_worst": _target(
                max(p["rms_inliers_um_worst"] for p in per_part.values()),
                TARGET_EDGE_RMS_UM, "<="),
            "outlier_fraction_worst": _target(
                max(p["outlier_fraction_worst"] for p in per_part.values()),
                TARGET_EDGE_OUTLIERS, "<")}


def _max_abs_z(row: dict) -> float:
    """The largest |error| / reported sigma over a trial's axes with a sigma (0 if none)."""
    z = [abs(v) for v in row.get("z") or () if v is not None and np.isfinite(v)]
    return float(max(z)) if z else 0.0


def _result_key(row: dict) -> tuple:
    """A registration's result to 0.1 um / 0.1 mdeg on its scan: starts that land on the
    same minimum share it."""
    error = [*row["translation_um"], *row["rotation_mdeg"]]
    return (row["part"], row["scan"], row["kind"], *np.round(error, 1).tolist())


def _lower_95(successes: int, trials: int) -> float:
    """One-sided 95 % Clopper-Pearson lower bound of a success rate."""
    return float(stats.beta.ppf(0.05, successes, trials - successes + 1)) if successes else 0.0


def _success_known_axes(row: dict) -> bool:
    """Within the success limits along the axes the pose reports a sigma for. A free axis
    keeps its start, and the pose says so: what it claims to know, it should have found."""
    if row.get("refused") or row.get("std_um_mdeg") is None:
        return False
    std = np.array([np.nan if v is None else v for v in row["std_um_mdeg"]], dtype=float)
    error = np.array([*row["translation_um"], *row["rotation_mdeg"]], dtype=float)
    known = np.isfinite(std)
    return bool(np.linalg.norm(error[:3][known[:3]]) < SUCCESS_MM * 1e3
                and np.linalg.norm(error[3:][known[3:]]) < SUCCESS_DEG * 1e3)


def _recommend(configs: dict, trials: list[dict]) -> dict:
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
                f"{_fmt(c['translation_um']['p95'])} um / {_fmt(c['rotation_mdeg']['p95'])} mdeg"
                f", {c['confident_wrong']} confident wrong, median "
                f"{_fmt(c['time_ms']['median'])} ms")

    return {"keep": keep,
            "time_ratio_predicted_to_mesh": None if ratio is None else round(ratio, 3),
            "reason": describe("mesh", mesh) + "; " + describe("predicted", pred)
            + "; predicted/mesh time on the same scans "
            + ("n/a" if ratio is None else f"{ratio:.2f}") + " (median). The predicted "
              "cloud also has to be swept again for every cell setup and nominal grasp."}


def _fmt(v) -> str:
    return "n/a" if v is None else f"{v:.1f}"


def _clean(obj):
    """JSON-safe: numpy scalars and arrays to Python, NaN and infinities to None."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _clean(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return round(v, 6) if np.isfinite(v) else None
    return obj


# --------------------------------------------------------------------------------------------
# Charts
# --------------------------------------------------------------------------------------------

def _plot(result: dict, path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(20, 11))
    _plot_accuracy(axes[0, 0], result, "translation_um", "translation error (um)",
                   TARGET_TRANSLATION_UM)
    _plot_accuracy(axes[0, 1], result, "rotation_mdeg", "rotation error (mdeg)",
                   TARGET_ROTATION_MDEG)
    _plot_basin(axes[0, 2], result)
    cal = result["calibration"].get(DEFAULT_CONFIG)
    _plot_histogram(axes[1, 0], cal, "all axes pooled, " + DEFAULT_CONFIG)
    _plot_qq(axes[1, 1], cal)
    _plot_side(axes[1, 2], result["side_by_side"])
    fig.suptitle("flyscan bench pose" + (" (quick set)" if result["quick"] else ""))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_accuracy(ax, result, key, label, target) -> None:
    """Median error against median time per configuration; the bar reaches p95, the cross
    the maximum (observable trials)."""
    for i, c in enumerate(result["configs"]):
        s, t = c[key], c["time_ms"]["median"]
        if s["median"] is None or t is None:  # no trial reported observable
            ax.plot([], [], "o", color=f"C{i}", label=f"{c['config']}: never observable")
            continue
        ax.errorbar([t], [max(s["median"], 1e-2)],
                    yerr=[[0.0], [max(s["p95"] - s["median"], 0.0)]], fmt="o", color=f"C{i}",
                    capsize=4, label=f"{c['config']} ({c['within_target'] or 0:.0%} in target)")
        ax.plot([t], [max(s["max"], 1e-2)], "x", color=f"C{i}")
    ax.axhline(target, color="k", ls=":", lw=1, label=f"target {target:g}")
    ax.set_yscale("log")
    ax.set_xlabel("registration time, median (ms)")
    ax.set_ylabel(label + ": median, bar to p95, x max")
    ax.set_title(f"{label.split(' (')[0]} against time per configuration\n"
                 f"misplacements up to {ACCURACY_MAX_MM:g} mm / {ACCURACY_MAX_DEG:g} deg")
    ax.legend(fontsize=7)


def _plot_basin(ax, result) -> None:
    levels = result["basin"]["levels"]
    x = np.arange(len(levels))
    counts = {"success_rate": "trials",
              "success_rate_on_observable_scans": "trials_on_observable_scans"}
    for kind, key, style, label in (
            ("displaced start", "success_rate_on_observable_scans", "o-",
             "displaced start, scans observable at their truth (target's scope)"),
            ("displaced start", "success_rate", "^:",
             "displaced start, every scan of (a)"),
            ("rendered", "success_rate", "s--", "rendered at the misplacement")):
        count = counts[key]
        pts = [(i, lv[kind][key], lv[kind][count]) for i, lv in enumerate(levels)
               if kind in lv and lv[kind][key] is not None]
        if pts:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], style, label=label)
            for i, rate, n in pts:
                ax.annotate(f"n={n}", (i, rate), textcoords="offset points", xytext=(0, 6),
                            fontsize=7, ha="center")
    ax.axhline(TARGET_BASIN, color="k", ls=":", lw=1, label=f"target {TARGET_BASIN:.0%} "
               f"up to {BASIN_TARGET_LEVEL[0]:g} mm / {BASIN_TARGET_LEVEL[1]:g} deg")
    ax.set_xticks(x, [f"{lv['mm']:g} mm\n{lv['deg']:g} deg" for lv in levels], fontsize=8)
    ax.set_ylim(-0.05, 1.1)
    ax.set_xlabel("initial misplacement (random directions)")
    ax.set_ylabel(f"success rate (error < {SUCCESS_MM:g} mm and {SUCCESS_DEG:g} deg)")
    ax.set_title("basin of convergence (" + DEFAULT_CONFIG + ", coarse stage as is)")
    ax.legend(fontsize=7)


def _z_values(cal, key="z") -> np.ndarray:
    if not cal:
        return np.zeros(0)
    z = np.array([[np.nan if v is None else v for v in row] for row in cal[key]], dtype=float)
    return z[np.isfinite(z)] if z.size else np.zeros(0)


def _plot_histogram(ax, cal, title) -> None:
    z = _z_values(cal)
    zc = _z_values(cal, "z_converged")
    grid = np.linspace(-5, 5, 201)
    bins = np.linspace(-6, 6, 49)
    ax.hist(np.clip(z, -6, 6), bins=bins, density=True, alpha=0.45, label=f"all ({len(z)})")
    ax.hist(np.clip(zc, -6, 6), bins=bins, density=True, histtype="step", lw=1.5,
            label=f"converged ({len(zc)})")
    ax.plot(grid, stats.norm.pdf(grid), "k-", lw=1, label="unit Gaussian")
    for s in (-SIGMA_BOUND, SIGMA_BOUND):
        ax.axvline(s, color="r", ls=":", lw=1)
    ax.set_xlabel("signed error / reported sigma (clipped to +-6)")
    ax.set_ylabel("density")
    within = cal["all"]["within"] if cal else None
    ax.set_title(f"calibration: {title}\ntrials with every axis within 3 sigma: "
                 f"{'n/a' if within is None else f'{within:.0%}'}")
    ax.legend(fontsize=7)


def _plot_qq(ax, cal) -> None:
    for key, style, label in (("z", "o", "all"), ("z_converged", "+", "converged")):
        z = np.sort(_z_values(cal, key))
        if len(z) == 0:
            continue
        q = stats.norm.ppf((np.arange(1, len(z) + 1) - 0.5) / len(z))
        ax.plot(q, z, style, ms=4, mfc="none", alpha=0.8, label=label)
    line = np.linspace(-3.5, 3.5, 71)
    ax.plot(line, line, "k-", lw=1, label="calibrated")
    ax.axhspan(-SIGMA_BOUND, SIGMA_BOUND, color="g", alpha=0.08)
    ax.set_xlabel("unit Gaussian quantile")
    ax.set_ylabel("signed error / reported sigma")
    ax.set_title("QQ plot of error / sigma, all axes pooled\n(steeper than the line: sigma "
                 "too small)")
    ax.set_yscale("symlog", linthresh=3)
    ticks = [-1000, -100, -10, -3, 0, 3, 10, 100, 1000]
    ax.set_yticks(ticks, [str(t) for t in ticks])
    ax.legend(fontsize=7)


def _plot_side(ax, side) -> None:
    cases = side["cases"]
    if not cases:
        ax.set_axis_off()
        return
    names = list(cases[0]["methods"])
    width = 0.8 / len(cases)
    y = np.arange(len(names))
    for k, case in enumerate(cases):
        pre = [case["methods"][n]["preprocess_ms"] for n in names]
        reg = [case["methods"][n]["register_ms"] for n in names]
        offset = (k - (len(cases) - 1) / 2) * width
        ax.barh(y + offset, pre, width, color="C7", alpha=0.7,
                label="preprocessing" if k == 0 else None)
        ax.barh(y + offset, reg, width, left=pre, color=f"C{k}", alpha=0.8,
                label=f"registration, {case['points']} points, misplacement "
                      f"{np.linalg.norm(case['misplacement'][:3]):.1f} mm / "
                      f"{np.linalg.norm(case['misplacement'][3:]):.1f} deg")
        for j, n in enumerate(names):
            m = case["methods"][n]
            ax.text(m["total_ms"] * 1.01, y[j] + offset,
                    f"{m['total_ms']:.0f} ms, {m['translation_um']:.1f} um, "
                    f"{m['rotation_mdeg']:.1f} mdeg", va="center", fontsize=7)
    ax.set_yticks(y, names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("time, median of runs in turn (ms)")
    note = ("; skipped: " + ", ".join(side["skipped"])) if side["skipped"] else ""
    ax.set_title(f"side by side on {side['part']}, from the nominal grasp{note}")
    ax.legend(fontsize=7, loc="lower right")
    ax.set_xlim(0, max(c["methods"][n]["total_ms"] for c in cases for n in names) * 1.6)


def _plot_calibration(result: dict, path: pathlib.Path) -> None:
    """Per configuration and per axis: |error| / sigma of every trial."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(result["calibration"])
    fig, axes = plt.subplots(1, len(names), figsize=(3.6 * len(names), 4.2), sharey=True,
                             squeeze=False)
    for ax, name in zip(axes[0], names):
        cal = result["calibration"][name]
        z = np.array([[np.nan if v is None else v for v in row] for row in cal["z"]],
                     dtype=float).reshape(-1, 6)
        for i in range(6):
            col = np.abs(z[:, i][np.isfinite(z[:, i])])
            ax.plot(np.full(len(col), i) + np.linspace(-0.2, 0.2, len(col)),
                    np.maximum(col, 1e-3), ".", ms=4, color=f"C{i}")
        ax.axhline(SIGMA_BOUND, color="r", ls=":", lw=1)
        ax.set_yscale("log")
        ax.set_xticks(range(6), ["tx", "ty", "tz", "rx", "ry", "rz"])
        within = cal["all"]["within"]
        ax.set_title(f"{name}\nall axes within 3 sigma: "
                     f"{'n/a' if within is None else f'{within:.0%}'}, inflate x"
                     f"{_fmt(cal['all']['inflation_needed'])}", fontsize=9)
    axes[0, 0].set_ylabel("|error| / reported sigma per trial (free axes left out)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":  # python -m benchmarks.pose OUT_DIR [--quick]
    args = [a for a in sys.argv[1:] if a != "--quick"]
    out = run(pathlib.Path(args[0] if args else "out/bench/pose"), quick="--quick" in sys.argv)
    print(json.dumps(out["summary"], indent=2))
