"""The closed loop: pick, scan, correct, place; the placed part against the truth, over
several realistic cells and parts, with the pose's sigmas against its errors.

In each realistic cell (every effect of ``simulator.effects``, a perturbed cell,
``--perturb-seed`` from `CELL_SEEDS`), calibrated as ``flyscan calibrate --sim`` calibrates it
(``benchmarks.calibrate._calibrate``: a simulated session fitted by
``scanner_core.calibration.session.calibrate_session``), every part (the reference four and the
procedural ones of ``benchmarks.parts.PROCEDURAL_PARTS``) is picked several times with a
random misplacement up to `MISPLACEMENT_UP_TO_MM` and `MISPLACEMENT_UP_TO_DEG` (in random
directions, magnitudes uniform; seeded). The scanner is told the simulated robot's
orientation accuracy as a cell's integrator reads it off the robot's datasheet
(``PoseParams.robot_rotation_std_deg``: the cell's ``tcp_rotation_error_deg``). Each pick:

1. **Scan**: one pass rendered in the true cell, frame by frame through the pipeline, on the
   *fitted* calibration, and finished by ``scanner_core.pipeline.finish.finish_pass`` (verdict,
   cross-check, pose, edges, report) as the service finishes it
   (``simulator.session.run_simulated_scan``).
2. **Act or not**: the report's pose entry judged by ``clients.placement.pose_actionable``
   (the pose's own ``act``), as a cell controller judges it.
3. **Correct**: the TCP place pose ``clients.placement.corrected_tcp_place``:
   ``taught_place @ nominal @ inv(pose)``, `TAUGHT_PLACE` a TCP pose in {B} at which a nominally
   held part lands right.
4. **Place**: the part lands at ``corrected @ true_grasp`` in {B} (the robot reaches the
   commanded TCP pose exactly; its own error is not the scanner's); its error against
   ``taught_place @ nominal``: the translation at the part's centroid (of the CAD mesh's
   volume, `reference_point`) and at the {P} origin, um, and the rotation angle, mdeg
   (`placed_error`).

Per part and per cell: picks, the act rate, the placed error of the picks acted on, the
picks acted on that landed outside the act tolerance, the pose's error per axis over its
reported sigma (``benchmarks.pose.trials.score``) and the terms of that sigma
(``pose.std_terms``), the reasons that blocked act, and the latency. Over all picks: the
errors' RMS in sigmas per axis and the share of the axis values of poses acted on or
observable beyond 3 sigmas (`sigma_calibration`), the reliability diagram (`reliability`), the
availability (the picks acted on among those the pose got right, `availability`), and the
act rate and placed error against the act tolerance (`against_tolerance`).

BLAS is held to one thread (``threadpoolctl``); the cells run on `jobs` processes.
``run(out_dir)`` writes ``place.json`` and ``place.png``.
"""
from __future__ import annotations

import pathlib
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from clients.placement import corrected_tcp_place, pose_actionable
from scanner_core.pose.registration import PoseParams
from scanner_core.pose.symmetry import nearest_equivalent
from benchmarks.calibrate import _calibrate
from benchmarks.parts import (AXES, DEMO_PART, PROCEDURAL_PARTS, REFERENCE_PARTS, bench_part,
                              random_misplacement)
from benchmarks.pose.trials import score
from benchmarks.results import pyplot, save_figure, write_json
from benchmarks.stats import fraction, judged, spread
from benchmarks.targets import SIGMA_BOUND
from simulator.cell import load_cell
from simulator.effects import EFFECTS, realistic_cell
from simulator.session import misplacement_matrix, run_simulated_scan

__all__ = ["run", "placed_error", "reference_point", "pick", "as_pose_result", "act_at",
           "sigma_calibration", "reliability", "availability", "against_tolerance", "TARGETS",
           "TAUGHT_PLACE", "PICKS_PER_PART", "QUICK_PICKS", "CELL_SEEDS", "PARTS"]

#: Picks per part in each cell in the full run, and in the quick one (the demo block only).
PICKS_PER_PART, QUICK_PICKS = 10, 4
#: The picks' misplacements: up to this far from the nominal grasp.
MISPLACEMENT_UP_TO_MM, MISPLACEMENT_UP_TO_DEG = 10.0, 20.0
#: The realistic cells' perturbations (``--perturb-seed``, also their effects' seeds): the
#: full run's, and the quick run's.
CELL_SEEDS, QUICK_CELL_SEEDS = (1, 2, 3, 4, 5), (1,)
#: The parts of the full run: the reference four and as many procedural ones.
PARTS = REFERENCE_PARTS + tuple(PROCEDURAL_PARTS)
#: The calibration session's LED and sphere positions (those of ``bench calibrate``'s runs).
SESSION_POSITIONS, QUICK_SESSION_POSITIONS = (200, 40), (100, 20)
#: Seed of the picks' misplacements: part ``i`` in cell ``c`` draws from
#: ``default_rng([PLACE_SEED, c, i])``.
PLACE_SEED = 20274
#: The taught place pose ^B X_T: the TCP pointing down (180 degrees about x_B) over a fixture
#: at (450, -150, 120) mm. The placed error does not depend on it (a rigid motion).
TAUGHT_PLACE = np.array([[1.0, 0.0, 0.0, 450.0],
                         [0.0, -1.0, 0.0, -150.0],
                         [0.0, 0.0, -1.0, 120.0],
                         [0.0, 0.0, 0.0, 1.0]])
#: The targets: the placed error of the picks acted on; none acted on outside the act
#: tolerance; the errors' RMS in sigmas within `Z_RMS_RANGE` on every axis and at most
#: `BEYOND_SHARE` of the axis values claimed (poses acted on or observable) beyond 3 sigmas;
#: at least `AVAILABILITY` of the picks the pose got right acted on.
TARGETS = {"placed_p99_um": 50.0, "placed_p99_mdeg": 50.0, "acted_outside_tolerance": 0,
           "z_rms_range": (0.7, 1.3), "beyond_3_sigma_share": 0.003, "availability": 0.95}
#: A pick the pose got right: its error within this share of the act tolerance on every axis
#: (and no axis free).
RIGHT_SHARE = 1.0 / 3.0
#: The act tolerances the chart runs over (mm, and the same number of degrees).
TOLERANCES = (0.05, 0.1, 0.2)
#: A part's pose is fixed by its scan when at least this share of its picks report no free
#: axis (ADIS16480, seen on its end, leaves the slide along the pass free in some).
FIXED_SHARE = 0.9
#: The misplacement bins of the act rate: the larger of |t| / 10 mm and |r| / 20 deg.
LEVEL_BINS = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)
#: Bins of the reliability diagram: predicted sigma, um or mdeg (log-spaced edges).
SIGMA_BINS = (0.3, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 1000.0)


def reference_point(part) -> np.ndarray:
    """The part's reference point in {P}, mm: the centroid of its CAD mesh (of the volume for a
    closed mesh, else of the surface: trimesh's ``center_mass`` / ``centroid``)."""
    mesh = part.mesh
    return np.asarray(mesh.center_mass if mesh.is_volume else mesh.centroid, dtype=np.float64)


def placed_error(taught_place, pose_matrix, nominal, truth, point_p) -> dict:
    """Where the part lands, placed with the corrected TCP pose, against where it should.

    The robot moves the TCP to ``corrected_tcp_place(taught_place, pose_matrix, nominal)``;
    the part, truly held at `truth` (^T X_P), lands at ``corrected @ truth`` in {B}; it should
    be at ``taught_place @ nominal``.

    Returns
    -------
    dict
        ``at_point_um`` (the error's norm at `point_p`, {P}, um), ``at_origin_um`` (at the {P}
        origin), ``angle_mdeg`` (the rotation between the two), and ``at_point_b_um`` (the
        error at `point_p` in {B}, um, signed).
    """
    corrected = corrected_tcp_place(taught_place, pose_matrix, nominal)
    placed = corrected @ np.asarray(truth, dtype=np.float64)
    target = np.asarray(taught_place, dtype=np.float64) @ np.asarray(nominal, dtype=np.float64)
    p = np.append(np.asarray(point_p, dtype=np.float64), 1.0)
    at_point = (placed @ p - target @ p)[:3] * 1e3
    at_origin = (placed[:3, 3] - target[:3, 3]) * 1e3
    turn = placed[:3, :3] @ target[:3, :3].T
    angle = np.degrees(np.linalg.norm(Rotation.from_matrix(turn).as_rotvec())) * 1e3
    return {"at_point_um": float(np.linalg.norm(at_point)),
            "at_origin_um": float(np.linalg.norm(at_origin)),
            "angle_mdeg": float(angle), "at_point_b_um": at_point.tolist()}


def as_pose_result(pose: dict) -> SimpleNamespace:
    """The report's pose entry read back as what ``benchmarks.pose.trials.score`` reads of a
    ``PoseResult`` (the entry is what the service hands out: the bench scores that)."""
    std = [np.nan if v is None else float(v) for v in pose["std"].values()]
    return SimpleNamespace(
        matrix=np.asarray(pose["matrix"], dtype=np.float64), std=np.asarray(std),
        time_ms=pose["time_ms"], coarse=pose["coarse"], iterations=pose["iterations"],
        flags=pose["flags"], observable=pose["observable"], free_axes=pose["free_axes"],
        inlier_fraction=pose["inlier_fraction"], rms_mm=pose["rms_mm"])


def _outside(placed: dict, tolerance: tuple[float, float]) -> bool:
    """Landed outside the act tolerance (mm, deg): at the reference point, at the {P} origin or
    in the angle."""
    mm, deg = tolerance
    return (max(placed["at_point_um"], placed["at_origin_um"]) > mm * 1e3
            or placed["angle_mdeg"] > deg * 1e3)


def pick(part, cell, calibration, values, *, seed: int, point_p, tolerance,
         params: PoseParams = PoseParams()) -> dict:
    """One pick at misplacement `values` (mm, deg): scanned, judged, corrected and placed."""
    truth = misplacement_matrix(values) @ part.grasp
    level = max(np.linalg.norm(values[:3]) / MISPLACEMENT_UP_TO_MM,
                np.linalg.norm(values[3:]) / MISPLACEMENT_UP_TO_DEG)
    row = {"part": part.name, "seed": seed, "misplacement": list(values),
           "misplacement_mm": float(np.linalg.norm(values[:3])),
           "misplacement_deg": float(np.linalg.norm(values[3:])), "level": float(level)}
    t0 = time.perf_counter()
    try:
        _, report = run_simulated_scan(part, cell, calibration=calibration,
                                       misplacement=misplacement_matrix(values), seed=seed,
                                       evaluate=False, pose_params=params)
    except ValueError as exc:  # the part leaves the cell's volume: no pass
        return dict(row, scanned=False, act=False, act_reasons=[f"not scanned: {exc}"],
                    observable=False, points=0)
    row["pick_s"] = round(time.perf_counter() - t0, 3)
    pose = report["pose"]
    act, reasons = pose_actionable(pose)
    row.update(scanned=True, state=report.get("state"), points=int(report["points"]),
               act=bool(act), act_reasons=reasons,
               timings_ms={k: report["timings_ms"].get(k)
                           for k in ("processing", "cross_check", "pose")})
    if pose is None or "matrix" not in pose:
        return dict(row, observable=False, refused=(pose or {}).get("refused", report.get("reason")))
    # A part its own turns map onto itself sits the same at each: the truth is the one
    # nearest the pose.
    truth = truth @ nearest_equivalent(truth, pose["matrix"], part.surface_model.symmetries)
    scored = score(as_pose_result(pose), truth)
    row.update({k: scored[k] for k in ("translation_um", "rotation_mdeg", "translation_norm_um",
                                       "rotation_angle_mdeg", "std_um_mdeg", "z", "flags",
                                       "observable", "free_axes", "coarse")})
    row["std_terms"] = pose.get("std_terms")
    row["max_abs_z"] = _max_abs_z(scored["z"])
    row["pose_ms"] = float(pose["time_ms"]) + float(pose["normals_ms"])
    row["placed"] = placed_error(TAUGHT_PLACE, pose["matrix"], part.grasp, truth, point_p)
    row["outside_tolerance"] = _outside(row["placed"], tolerance)
    return row


def _max_abs_z(z) -> float | None:
    finite = [abs(v) for v in z if v is not None and np.isfinite(v)]
    return max(finite) if finite else None


def run(out_dir, quick: bool = False, *, picks: int | None = None, cells=None, parts=None,
        jobs: int = 2, progress=None) -> dict:
    """Run the closed loop; write ``place.json`` and ``place.png`` into `out_dir`.

    Parameters
    ----------
    quick : bool
        The demo block only, in one cell, `QUICK_PICKS` picks, a smaller calibration session.
    picks : int, optional
        Picks per part in each cell (default `PICKS_PER_PART`, or `QUICK_PICKS` with `quick`).
    cells : sequence of int, optional
        The cells' perturb seeds (default `CELL_SEEDS`; `QUICK_CELL_SEEDS` with `quick`).
    parts : sequence of str, optional
        Part names (``benchmarks.parts.bench_part``; default `PARTS`, the demo block with
        `quick`).
    jobs : int
        Cells run at once, each in a process of its own.
    progress : callable, optional
        Called with one line per part and cell; default: printed on stderr.
    """
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda line: print(line, file=sys.stderr, flush=True))
    t_start = time.perf_counter()
    names = tuple(parts) if parts else (DEMO_PART,) if quick else PARTS
    seeds = tuple(cells) if cells else QUICK_CELL_SEEDS if quick else CELL_SEEDS
    n_picks = picks if picks is not None else QUICK_PICKS if quick else PICKS_PER_PART
    positions = QUICK_SESSION_POSITIONS if quick else SESSION_POSITIONS
    tasks = [(seed, names, n_picks, positions) for seed in seeds]
    rows, cal_rows = [], {}
    if jobs > 1 and len(tasks) > 1:
        with ProcessPoolExecutor(max_workers=min(jobs, len(tasks))) as pool:
            results = pool.map(_cell_picks, tasks)
            for seed, (cell_rows, cal_row, lines) in zip(seeds, results):
                if progress is not None:  # the workers printed theirs on stderr as they went
                    for line in lines:
                        say(line)
                rows += cell_rows
                cal_rows[seed] = cal_row
    else:
        for task in tasks:
            cell_rows, cal_row, _ = _cell_picks(task, say)
            rows += cell_rows
            cal_rows[task[0]] = cal_row
    params = PoseParams()
    tolerance = (params.act_tolerance_mm, params.act_tolerance_deg)
    per_part = {name: _part_summary([r for r in rows if r["part"] == name]) for name in names}
    per_cell = {str(seed): _part_summary([r for r in rows if r["cell"] == seed])
                for seed in seeds}
    result = {
        "quick": quick,
        "settings": {
            "parts": list(names), "cells": list(seeds), "picks_per_part": n_picks,
            "misplacement_up_to": {"mm": MISPLACEMENT_UP_TO_MM, "deg": MISPLACEMENT_UP_TO_DEG},
            "effects": list(EFFECTS),
            "calibration": {"led_positions": positions[0], "sphere_positions": positions[1]},
            "calibrations": {str(k): v for k, v in cal_rows.items()},
            "act_tolerance": {"mm": tolerance[0], "deg": tolerance[1]},
            "taught_place": TAUGHT_PLACE,
            "placed_error": "the part at corrected @ true_grasp in {B} against taught_place @ "
                            "nominal_grasp: translation at the CAD mesh's centroid and at the "
                            "{P} origin, um; rotation angle, mdeg",
            "pose_error": "pose @ inv(true_grasp) in {T}: translation of the {T} origin (um), "
                          "rotation vector (mdeg); z = error / reported sigma per axis",
            "right": f"every axis's error within {RIGHT_SHARE:.3g} of the act tolerance, none "
                     "free",
            "fixed_share": FIXED_SHARE, "seed": PLACE_SEED, "blas_threads": 1, "jobs": jobs,
        },
        "picks": rows,
        "per_part": per_part,
        "per_cell": per_cell,
        "elapsed_s": round(time.perf_counter() - t_start, 1),
    }
    result["summary"] = _summary(rows, per_part, tolerance)
    result = write_json(out / "place.json", result, digits=6)
    _chart(result, out / "place.png")
    say(f"bench place done in {result['elapsed_s']:.0f} s: {out / 'place.json'}")
    return result


def _cell_picks(task, say=None):
    """One cell's picks (a process of its own with `jobs`): the cell calibrated, then every
    part picked. Returns the rows, the calibration's figures and the progress lines."""
    seed, names, n_picks, positions = task
    lines = []

    def tell(line):
        lines.append(line)
        if say is not None:
            say(line)
        else:
            print(line, file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    rows = []
    with threadpool_limits(limits=1, user_api="blas"):
        cell = realistic_cell(load_cell(perturb_seed=seed), seed=seed)
        calibration, cal_row = _calibrate(cell, seed, *positions)
        # the simulated robot's datasheet: how far off it reports its orientation
        params = replace(PoseParams(),
                         robot_rotation_std_deg=cell.effects.tcp_rotation_error_deg)
        tolerance = (params.act_tolerance_mm, params.act_tolerance_deg)
        tell(f"bench place: cell {seed} ({', '.join(EFFECTS)}) calibrated from {positions[0]} "
             f"LED / {positions[1]} sphere positions in {cal_row['time_s']:.0f} s")
        for index, name in enumerate(names):
            part = bench_part(name)
            point = reference_point(part)
            rng = np.random.default_rng([PLACE_SEED, seed, index])
            mine = []
            for i in range(n_picks):
                values = random_misplacement(rng, MISPLACEMENT_UP_TO_MM, MISPLACEMENT_UP_TO_DEG,
                                             up_to=True)
                row = pick(part, cell, calibration, values, seed=i, point_p=point,
                           tolerance=tolerance, params=params)
                mine.append(dict(row, cell=seed))
            tell(_progress_line(f"cell {seed} {name}", mine, time.perf_counter() - t0))
            rows += mine
    return rows, cal_row, lines


def _progress_line(name, rows, elapsed_s) -> str:
    acted = [r for r in rows if r["act"]]
    worst = max((r["placed"]["at_point_um"] for r in acted), default=None)
    return (f"bench place: {name} {len(rows)} picks, {len(acted)} acted on"
            + (f" (worst placed {worst:.1f} um)" if worst is not None else "")
            + f", {sum(bool(r.get('outside_tolerance')) and r['act'] for r in rows)} acted on "
              f"outside the tolerance; {elapsed_s:.0f} s")


def _percentiles(values) -> dict:
    """`benchmarks.stats.spread` (n, median, p95, max) with the p99."""
    out = spread(values)
    v = [x for x in values if x is not None and np.isfinite(x)]
    out["p99"] = float(np.percentile(v, 99)) if v else None
    return out


def _mean(values) -> float | None:
    return float(np.mean(values)) if values else None


def _z_max(rows) -> dict:
    """The largest |z| per axis (None: no finite z) over `rows`."""
    out = {}
    for i, axis in enumerate(AXES):
        zs = [abs(r["z"][i]) for r in rows if r.get("z") and r["z"][i] is not None
              and np.isfinite(r["z"][i])]
        out[axis] = max(zs) if zs else None
    return out


def _beyond(rows) -> list[dict]:
    """The picks among `rows` with an axis's error beyond `SIGMA_BOUND` reported sigmas."""
    return [{"cell": r.get("cell"), "seed": r["seed"], "max_abs_z": r["max_abs_z"],
             "act": r["act"], "observable": r["observable"]}
            for r in rows if r.get("max_abs_z") is not None and r["max_abs_z"] > SIGMA_BOUND]


def _by_level(rows) -> list[dict]:
    out = []
    for lo, hi in zip(LEVEL_BINS[:-1], LEVEL_BINS[1:]):
        sel = [r for r in rows if lo <= r["level"] < hi or (hi == LEVEL_BINS[-1]
                                                            and r["level"] == hi)]
        out.append({"level": [lo, hi], "picks": len(sel), "act_rate": fraction(r["act"]
                                                                                for r in sel)})
    return out


def _reason_kind(reason: str) -> str:
    """A reason that blocked act, without its figures: the words before its colon ("poor
    fit", "partial scan", "not observable"), an axis's 3 sigma as "3 sigma beyond the act
    tolerance"."""
    kind = reason.split(":")[0]
    return "3 sigma beyond the act tolerance" if kind in AXES else kind


def _part_summary(rows) -> dict:
    acted = [r for r in rows if r["act"]]
    observable = [r for r in rows if r.get("observable")]
    outside = [r for r in acted if r.get("outside_tolerance")]
    return {
        "picks": len(rows),
        "scanned": sum(r["scanned"] for r in rows),
        "acted_on": len(acted),
        "act_rate": fraction(r["act"] for r in rows),
        "observable": len(observable),
        "observable_share": fraction(bool(r.get("observable")) for r in rows),
        "placed_um": _percentiles([r["placed"]["at_point_um"] for r in acted]),
        "placed_origin_um": _percentiles([r["placed"]["at_origin_um"] for r in acted]),
        "placed_mdeg": _percentiles([r["placed"]["angle_mdeg"] for r in acted]),
        "placed_um_all_with_pose": _percentiles([r["placed"]["at_point_um"] for r in rows
                                                 if "placed" in r]),
        "acted_outside_tolerance": len(outside),
        "acted_outside_tolerance_picks": [
            {"seed": r["seed"], "misplacement": r["misplacement"], "placed": r["placed"]}
            for r in outside],
        # The pose's error in {T} of the picks acted on, signed, per axis (um, mdeg): a bias
        # common to the picks (the calibration's) shows here.
        "pose_error_mean_acted": {axis: _mean([(r["translation_um"] + r["rotation_mdeg"])[i]
                                               for r in acted])
                                  for i, axis in enumerate(AXES)},
        "max_abs_z_acted": _z_max(acted),
        "max_abs_z_observable": _z_max(observable),
        "beyond_3_sigma_acted_or_observable": _beyond([r for r in rows
                                                       if r["act"] or r.get("observable")]),
        "act_by_level": _by_level(rows),
        "act_blocked_by": _blocked(r for r in rows if not r["act"]),
        "sigma_calibration": sigma_calibration(rows),
        "pose_ms": spread([r.get("pose_ms") for r in rows]),
        "finish_pose_ms": spread([(r.get("timings_ms") or {}).get("pose") for r in rows]),
        "pick_s": spread([r.get("pick_s") for r in rows]),
        "points": spread([r["points"] for r in rows if r["scanned"]]),
    }


def fixed_parts(per_part: dict) -> list[str]:
    """The parts whose pose the scan fixes: at least `FIXED_SHARE` of their picks report no
    free axis."""
    return [name for name, p in per_part.items()
            if p["observable_share"] is not None and p["observable_share"] >= FIXED_SHARE]


def _errors(row) -> np.ndarray:
    """(6,) the pose's error, um and mdeg."""
    return np.asarray(row["translation_um"] + row["rotation_mdeg"], dtype=np.float64)


def _sigmas(row) -> np.ndarray:
    """(6,) the reported sigmas, um and mdeg, NaN where free."""
    return np.array([np.nan if v is None else v for v in row["std_um_mdeg"]], dtype=np.float64)


def _tolerance_dependent(reason: str) -> bool:
    """Whether a reason against acting depends on the act tolerance: an axis's 3 sigma
    beyond it, a rival minimum beyond it, the near symmetry that names them."""
    return reason.split(":")[0] in AXES + ("ambiguous", "near symmetry")


def act_at(row, tolerance_mm: float, tolerance_deg: float) -> bool:
    """Whether a pick's pose would be acted on at another act tolerance: nothing free, no
    reason against it but the tolerance's, no rival minimum (kept against it whatever the
    tolerance: the report does not say how far its rivals lie), and every axis's 3 sigma
    within the tolerance."""
    if not row.get("scanned") or "std_um_mdeg" not in row or row.get("free_axes"):
        return False
    reasons = row.get("act_reasons") or []
    if any(not _tolerance_dependent(r) or r.startswith("ambiguous") for r in reasons):
        return False
    sigma = _sigmas(row) / 1e3
    limit = np.array([tolerance_mm] * 3 + [tolerance_deg] * 3)
    return bool(np.all(np.isfinite(sigma)) and np.all(SIGMA_BOUND * sigma <= limit))


def sigma_calibration(rows) -> dict:
    """The reported sigmas against the errors: per axis, the errors' RMS in sigmas over every
    pose (an honest sigma gives 1; below, it is too large), and the share of the axis values
    of the poses acted on or observable beyond `SIGMA_BOUND` sigmas."""
    with_pose = [r for r in rows if "std_um_mdeg" in r]
    z = np.array([[np.nan if v is None else v for v in r["z"]] for r in with_pose]
                 ).reshape(-1, 6)
    rms = {axis: (float(np.sqrt(np.nanmean(z[:, i] ** 2))) if np.isfinite(z[:, i]).any()
                  else None) for i, axis in enumerate(AXES)}
    claimed = np.array([bool(r["act"] or r.get("observable")) for r in with_pose], bool)
    values = np.abs(z[claimed])
    finite = np.isfinite(values)
    beyond = int(np.sum(values[finite] > SIGMA_BOUND))
    return {"z_rms": rms, "axis_values_claimed": int(finite.sum()), "beyond": beyond,
            "beyond_share": beyond / finite.sum() if finite.sum() else None,
            "poses": len(with_pose)}


def reliability(rows) -> dict:
    """The reliability diagram per axis: the poses binned by their reported sigma
    (`SIGMA_BINS`, um or mdeg), each bin's median sigma against the RMS of its errors."""
    with_pose = [r for r in rows if "std_um_mdeg" in r]
    out = {}
    for i, axis in enumerate(AXES):
        sigma = np.array([_sigmas(r)[i] for r in with_pose])
        error = np.array([_errors(r)[i] for r in with_pose])
        bins = []
        for lo, hi in zip(SIGMA_BINS[:-1], SIGMA_BINS[1:]):
            sel = np.isfinite(sigma) & (sigma >= lo) & (sigma < hi)
            if sel.sum():
                bins.append({"sigma": [lo, hi], "n": int(sel.sum()),
                             "median_sigma": float(np.median(sigma[sel])),
                             "rms_error": float(np.sqrt(np.mean(error[sel] ** 2)))})
        out[axis] = bins
    return out


def _right(row, tolerance) -> bool:
    """The pose got the pick right: every axis's error within `RIGHT_SHARE` of `tolerance`
    (mm, deg), no axis free."""
    if "std_um_mdeg" not in row or row.get("free_axes"):
        return False
    limit = RIGHT_SHARE * np.array([tolerance[0]] * 3 + [tolerance[1]] * 3) * 1e3
    return bool(np.all(np.abs(_errors(row)) <= limit))


def availability(rows, tolerance) -> dict:
    """The picks acted on among those the pose got right (`_right`)."""
    right = [r for r in rows if _right(r, tolerance)]
    return {"right": len(right), "acted_on": sum(r["act"] for r in right),
            "share": fraction(r["act"] for r in right),
            "refused_for": _blocked(r for r in right if not r["act"])}


def _blocked(rows) -> dict:
    counts: dict[str, int] = {}
    for r in rows:
        for reason in r["act_reasons"]:
            counts[_reason_kind(reason)] = counts.get(_reason_kind(reason), 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: -kv[1]))


def against_tolerance(rows) -> list[dict]:
    """Availability against safety: at each act tolerance of `TOLERANCES` (mm, and as many
    degrees), the share of picks acted on (`act_at`), of the right ones (`_right` at that
    tolerance), the placed error's p99 of those acted on, and those placed outside it."""
    out = []
    for tol in TOLERANCES:
        acted = [r for r in rows if act_at(r, tol, tol)]
        right = [r for r in rows if _right(r, (tol, tol))]
        out.append({
            "tolerance": {"mm": tol, "deg": tol},
            "act_rate": fraction(act_at(r, tol, tol) for r in rows),
            "availability": fraction(act_at(r, tol, tol) for r in right),
            "placed_p99_um": _percentiles([r["placed"]["at_point_um"] for r in acted])["p99"],
            "placed_p99_mdeg": _percentiles([r["placed"]["angle_mdeg"] for r in acted])["p99"],
            "acted_outside": sum(_outside(r["placed"], (tol, tol)) for r in acted),
            "acted_on": len(acted)})
    return out


def _term_shares(rows) -> dict:
    """Per term of the sigma (``pose.std_terms``), its median standard deviation per axis over
    the poses (um, mdeg), and its mean share of the variance (the shares of a pose add up
    to 1)."""
    terms = [r["std_terms"] for r in rows if r.get("std_terms")]
    if not terms:
        return {}
    keys = list(terms[0][next(iter(terms[0]))])
    out = {}
    for name in terms[0]:
        values = np.array([[np.nan if t[name][k] is None else t[name][k] for k in keys]
                           for t in terms]) * 1e3
        totals = np.array([[sum((t[n][k] or 0.0) ** 2 * np.sign(t[n][k] or 0.0) for n in t)
                            for k in keys] for t in terms]) * 1e6
        with np.errstate(invalid="ignore", divide="ignore"):
            share = np.sign(values) * values**2 / totals
        out[name] = {"median_std": dict(zip(AXES, np.nanmedian(np.abs(values), axis=0)
                                            .tolist())),
                     "mean_share": dict(zip(AXES, np.nanmean(share, axis=0).tolist()))}
    return out


def _summary(rows, per_part, tolerance) -> dict:
    acted = [r for r in rows if r["act"]]
    fixed = fixed_parts(per_part)
    placed_um = _percentiles([r["placed"]["at_point_um"] for r in acted])
    placed_mdeg = _percentiles([r["placed"]["angle_mdeg"] for r in acted])
    beyond = [dict(b, part=name) for name, p in per_part.items()
              for b in p["beyond_3_sigma_acted_or_observable"]]
    outside = sum(p["acted_outside_tolerance"] for p in per_part.values())
    calibration = sigma_calibration(rows)
    rms = [v for v in calibration["z_rms"].values() if v is not None]
    available = availability(rows, tolerance)
    low, high = TARGETS["z_rms_range"]
    return {
        "picks": len(rows), "acted_on": len(acted),
        "act_rate": fraction(r["act"] for r in rows),
        "placed_um": placed_um, "placed_mdeg": placed_mdeg,
        "fixed_parts": fixed,
        "act_rate_per_part": {n: p["act_rate"] for n, p in per_part.items()},
        "sigma_calibration": calibration,
        "availability": available,
        "against_tolerance": against_tolerance(rows),
        "reliability": reliability(rows),
        "std_terms": _term_shares(rows),
        "beyond_3_sigma": {"acted_on": sum(b["act"] for b in beyond),
                           "observable": sum(bool(b["observable"]) for b in beyond),
                           "picks": beyond},
        "act_blocked_by": _blocked(r for r in rows if not r["act"]),
        "targets": {
            "placed_p99_um": judged(placed_um["p99"], TARGETS["placed_p99_um"], "<="),
            "placed_p99_mdeg": judged(placed_mdeg["p99"], TARGETS["placed_p99_mdeg"], "<="),
            "acted_outside_tolerance": judged(outside, TARGETS["acted_outside_tolerance"], "<="),
            "z_rms_lowest": judged(min(rms) if rms else None, low, ">="),
            "z_rms_highest": judged(max(rms) if rms else None, high, "<="),
            "beyond_3_sigma_share": judged(calibration["beyond_share"],
                                           TARGETS["beyond_3_sigma_share"], "<="),
            "availability": judged(available["share"], TARGETS["availability"], ">="),
        },
    }


def _chart(result: dict, path) -> None:
    plt = pyplot()
    rows, names = result["picks"], result["settings"]["parts"]
    summary = result["summary"]
    fig, ax = plt.subplots(2, 3, figsize=(18, 10))
    # the placed error of the picks acted on, per part
    a = ax[0, 0]
    data = [[r["placed"]["at_point_um"] for r in rows if r["part"] == n and r["act"]]
            for n in names]
    a.boxplot([d or [np.nan] for d in data], whis=(1, 99), showfliers=False)
    for i, d in enumerate(data):
        a.plot(np.full(len(d), i + 1) + np.random.default_rng(i).uniform(-0.15, 0.15, len(d)),
               d, ".", alpha=0.4)
        a.text(i + 1, 0, f"n={len(d)}", ha="center", va="bottom", fontsize=7)
    a.axhline(TARGETS["placed_p99_um"], ls=":", color="grey")
    a.set_xticks(range(1, len(names) + 1), names, rotation=30, fontsize=8)
    a.set_ylim(bottom=0)
    a.set_ylabel("placed error at the centroid, um")
    a.set_title(f"picks acted on ({summary['acted_on']} of {summary['picks']}), "
                f"{len(result['settings']['cells'])} cells")
    # availability against safety
    a = ax[0, 1]
    levels = summary["against_tolerance"]
    x = [lv["tolerance"]["mm"] for lv in levels]
    a.plot(x, [100 * (lv["act_rate"] or 0) for lv in levels], "o-", label="all picks acted on")
    a.plot(x, [100 * (lv["availability"] or 0) for lv in levels], "s-",
           label="right picks acted on (availability)")
    a.axhline(100 * TARGETS["availability"], ls=":", color="grey")
    a.set_xscale("log")
    a.minorticks_off()
    a.set_xticks(x, [f"{v:g} mm\n{v:g} deg" for v in x])
    a.set_ylim(-5, 105)
    a.set_ylabel("%")
    a.set_xlabel("act tolerance")
    b = a.twinx()
    b.plot(x, [lv["placed_p99_um"] or np.nan for lv in levels], "^--", color="C3",
           label="placed p99 of those acted on, um")
    b.plot(x, [1e3 * v for v in x], ":", color="C3", alpha=0.6, label="the tolerance, um")
    b.set_ylabel("placed error p99, um", color="C3")
    b.set_ylim(bottom=0)
    handles = a.get_legend_handles_labels()[0] + b.get_legend_handles_labels()[0]
    a.legend(handles, [h.get_label() for h in handles], fontsize=7, loc="lower right")
    outside = sum(lv["acted_outside"] for lv in levels)
    a.set_title(f"availability against safety ({outside} acted on outside their tolerance "
                f"over the {len(levels)} tolerances)")
    # errors in sigmas per axis and cell
    a = ax[0, 2]
    cells = result["settings"]["cells"]
    for k, cell in enumerate(cells):
        rms = result["per_cell"][str(cell)]["sigma_calibration"]["z_rms"]
        a.plot(np.arange(6) + 0.08 * (k - len(cells) / 2), [rms[axis] or np.nan for axis in AXES],
               "o", alpha=0.7, label=f"cell {cell}")
    total = summary["sigma_calibration"]["z_rms"]
    a.plot(range(6), [total[axis] or np.nan for axis in AXES], "k_", markersize=25, mew=2,
           label="all")
    low, high = TARGETS["z_rms_range"]
    a.axhspan(low, high, color="green", alpha=0.08)
    a.axhline(1.0, color="green", lw=0.8)
    a.set_xticks(range(6), AXES)
    a.set_ylabel("RMS of error / reported sigma")
    share = summary["sigma_calibration"]["beyond_share"]
    a.set_title("errors in sigmas" + ("" if share is None else
                                     f"; {100 * share:.2f} % of claimed beyond {SIGMA_BOUND:g}"))
    a.legend(fontsize=7, ncol=2)
    # reliability diagrams
    for k, (axes, unit) in enumerate(((AXES[:3], "um"), (AXES[3:], "mdeg"))):
        a = ax[1, k]
        top = 1.0
        for axis in axes:
            bins = summary["reliability"][axis]
            sx = [b["median_sigma"] for b in bins]
            sy = [b["rms_error"] for b in bins]
            a.plot(sx, sy, "o-", label=axis)
            for bx, by, b in zip(sx, sy, bins):
                a.text(bx, by, f" {b['n']}", fontsize=6)
            top = max([top] + sx + sy)
        line = np.array([0.1, top * 1.5])
        a.plot(line, line, "k-", lw=0.8, label="honest")
        a.fill_between(line, line * low, line * high, color="green", alpha=0.08)
        a.set_xscale("log")
        a.set_yscale("log")
        a.set_xlabel(f"reported sigma, {unit} (median of the bin)")
        a.set_ylabel(f"RMS error, {unit}")
        a.set_title(f"reliability: {'translations' if k == 0 else 'rotations'}")
        a.legend(fontsize=7)
    # the terms of the sigma
    a = ax[1, 2]
    terms = summary["std_terms"]
    bottom = np.zeros(6)
    for name, entry in terms.items():
        values = np.array([max(entry["mean_share"][axis] or 0.0, 0.0) for axis in AXES])
        if values.max() < 0.01:
            continue
        a.bar(range(6), 100 * values, bottom=100 * bottom, label=name)
        bottom += values
    a.set_xticks(range(6), AXES)
    a.set_ylabel("share of the variance, %, mean over the poses")
    a.set_title("where each axis's sigma comes from (pose.std_terms)")
    a.legend(fontsize=7)
    save_figure(fig, path, dpi=90)
