"""``flyscan bench inspect``: does the inspection catch what the gripper should not hold, and
leave the good picks alone?

In one calibrated realistic cell (``--perturb-seed`` `CELL_SEED`, every effect of
``simulator.effects``, calibrated as ``flyscan calibrate --sim`` calibrates it), each part of
`PARTS` (half procedural, half the reference meshes) is scanned:

- `GOOD_PICKS` good picks in all, at random misplacements (up to `MISPLACEMENT_UP_TO_MM` and
  `MISPLACEMENT_UP_TO_DEG`): the false-reject rate, the picks whose pose fixes every axis and
  whose inspection fails (where the pose leaves an axis free, the model may sit off along it:
  those picks are counted apart, and never acted on either way);
- every fault of ``simulator.faults`` at each size of `SIZES_MM`, `TRIALS` times a part
  (`DOUBLE_TRIALS` double picks), each at its own random misplacement and fault draw: a fault
  is *detected* when the inspection fails.

The variant the other way about, ``filled``: the model registered is the part with a hole
drilled (as ``hole`` drills it), the gripper holds the part without it.

Each fault is also judged *seen* or not from the simulator's truth (``fault_seen``): whether
the scan's profiles crossed its difference from the model, where the true cell lights and
sees it, as much as the check's smallest region needs, at a pose that fixes every axis (where
an axis is loose the difference may slide along it: those picks, never acted on, are counted
apart). What the scan does not see no check can find; what it sees, the check must.

Per kind, the probability of detection (POD) against the fault's size is the hit/miss
logistic fit of non-destructive testing (MIL-HDBK-1823A): ``POD(a) = 1 / (1 + exp(-(b0 + b1
ln a)))`` by maximum likelihood, its lower 95 % confidence band from the fit's covariance
(the delta method), ``a90`` where the fit reaches 90 % and ``a90/95`` where its band does. A
double pick has no size: its detection rate. Also: picks acted on with a fault the check
detected (must be none), picks acted on with an undetected fault, and the time the check took
against the cloud's points (one core).
"""
from __future__ import annotations

import math
import pathlib
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np
import trimesh
from scipy.optimize import minimize
from threadpoolctl import threadpool_limits

from benchmarks.calibrate import _calibrate
from benchmarks.parts import DEMO_PART, bench_part, random_misplacement
from benchmarks.place import QUICK_SESSION_POSITIONS, SESSION_POSITIONS
from benchmarks.results import machine_info, pyplot, save_figure, write_json
from scanner_core.geometry import planes_moved
from scanner_core.inspection import point_deviations, point_spacing
from scanner_core.inspection.check import (LINK_SPACINGS, MIN_PROFILE_POINTS,
                                           MIN_REGION_PROFILES, MIN_REGION_SAMPLES,
                                           touching_groups, warm_up_inspection)
from scanner_core.inspection.coverage import COVER_STEPS, lit_and_seen, sheet_crossings
from scanner_core.pipeline.finish import inspect_pass
from scanner_core.pose.models import SurfaceModel
from scanner_core.pose.registration import PoseParams
from scanner_core.pose.warm import warm_up_pose
from simulator.cell import load_cell
from simulator.effects import realistic_cell
from simulator.faults import faulty_mesh
from simulator.parts import part_from_mesh
from simulator.session import misplacement_matrix, run_simulated_scan

__all__ = ["run", "pod_fit", "PARTS", "SIZES_MM", "GOOD_PICKS", "TRIALS", "CELL_SEED"]

#: The parts: half procedural, half the reference meshes (those that are closed: a chip is
#: cut from a volume, and cycloidal's mesh is open).
PARTS = (DEMO_PART, "bracket", "crowned_block", "idler_riser", "ADIS16480", "featuretype")
QUICK_PARTS = (DEMO_PART,)
#: The faults' sizes, mm: a debris blob's diameter, a chip's radius, a variant's extra length,
#: a drilled hole's diameter, a bend's deflection at the ends (``simulator.faults``); a double
#: pick has none. ``filled`` is the variant the other way about: the expected part (the model
#: registered) has the hole drilled, and the gripper holds the part without it.
SIZES_MM = {"debris": (1.0, 2.0, 3.0, 4.0, 6.0), "chip": (0.5, 1.0, 2.0, 3.0, 5.0),
            "variant": (0.25, 0.5, 1.0, 2.0, 4.0), "hole": (1.0, 2.0, 3.0, 4.0, 6.0),
            "filled": (1.0, 2.0, 3.0, 4.0, 6.0),
            "bend": (0.02, 0.05, 0.1, 0.2, 0.4), "double": (0.0,)}
#: The quick run's sizes: each kind's smallest and largest.
QUICK_SIZES_MM = {kind: tuple(sorted({sizes[0], sizes[-1]})) for kind, sizes in SIZES_MM.items()}
#: Trials of each fault size on each part; good picks in all (spread over the parts).
TRIALS, QUICK_TRIALS = 3, 1
#: Double picks of each part: a rate to near 99 % needs more than a size's trials.
DOUBLE_TRIALS = 10
GOOD_PICKS, QUICK_GOOD_PICKS = 300, 4
CELL_SEED = 34
MISPLACEMENT_UP_TO_MM, MISPLACEMENT_UP_TO_DEG = 5.0, 10.0
INSPECT_SEED = 44
#: A finer pass: the paper's slow speed at the camera's full rate puts the profiles about
#: 0.3 mm apart (1.2 mm at the default pass, where a 1 mm chip is crossed by one profile at
#: most): chips, and good picks for the false rejects there.
FINE_PASS_SPEED_MM_S = 50.0
FINE_SIZES_MM = {"chip": (0.5, 1.0, 2.0)}
FINE_GOOD_PICKS = 5
#: Good picks of each part the check is timed on apart, on one idle core.
TIMED_PICKS = 5
#: Good picks of each part ``bench inspect --timing`` times.
TIMING_PICKS = 10
#: Checks more of each timed pick's scan (``bench inspect --timing``): the least is its cost.
TIMING_REPEATS = 3
#: Whether the scan saw a fault (the evaluation's, from the simulator's truth): the model's
#: and the held mesh's surfaces sampled this finely (``fault_seen``).
SEEN_SPACING_MM = 0.2
#: ... a sample's difference from the other's samples within this many of their spacings of
#: the threshold is checked against the other mesh itself.
SEEN_UNSURE_SPACINGS = 4.0


def run(out_dir, quick: bool = False, *, jobs: int = 2, progress=None) -> dict:
    """Run the bench; write ``inspect.json`` and ``inspect.png`` into `out_dir`."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda line: print(line, file=sys.stderr, flush=True))
    t_start = time.perf_counter()
    names = QUICK_PARTS if quick else PARTS
    trials = QUICK_TRIALS if quick else TRIALS
    sizes = QUICK_SIZES_MM if quick else SIZES_MM
    trials_by_kind = {kind: DOUBLE_TRIALS if kind == "double" and not quick else trials
                      for kind in sizes}
    good = QUICK_GOOD_PICKS if quick else GOOD_PICKS
    cell, calibration, cal_row = _calibrated_cell(quick)
    say(f"bench inspect: cell {CELL_SEED} calibrated in {cal_row['time_s']:.0f} s")
    tasks = []
    for index, name in enumerate(names):
        per_part = good // len(names) + (index < good % len(names))
        tasks.append((name, index, per_part, trials_by_kind, sizes, cell, calibration))
    timing_tasks = list(tasks)
    if not quick:  # the finer pass, its own draws
        fine = cell.with_pass(speed_mm_s=FINE_PASS_SPEED_MM_S)
        tasks += [(name, (index, 1), FINE_GOOD_PICKS, {kind: trials for kind in FINE_SIZES_MM},
                   FINE_SIZES_MM, fine, calibration) for index, name in enumerate(names)]
    rows = []
    if jobs > 1 and len(tasks) > 1:
        with ProcessPoolExecutor(max_workers=min(jobs, len(tasks))) as pool:
            for part_rows in pool.map(_part_rows, tasks):
                rows += part_rows
                say(_progress_line(part_rows, time.perf_counter() - t_start))
    else:
        for task in tasks:
            part_rows = _part_rows(task)
            rows += part_rows
            say(_progress_line(part_rows, time.perf_counter() - t_start))
    # the check's time apart, on one idle core: the pool's two processes share the machine
    say("bench inspect: timing the check on one idle core")
    timed = [_timed_check(task, TIMED_PICKS if not quick else 1) for task in timing_tasks]
    result = {"quick": quick,
              "settings": {"parts": list(names), "cell": CELL_SEED, "trials": trials,
                           "trials_by_kind": trials_by_kind,
                           "good_picks": good,
                           "sizes_mm": {k: list(v) for k, v in sizes.items()},
                           "misplacement_up_to": {"mm": MISPLACEMENT_UP_TO_MM,
                                                  "deg": MISPLACEMENT_UP_TO_DEG},
                           "fine_pass": None if quick else {
                               "speed_mm_s": FINE_PASS_SPEED_MM_S,
                               "fps": cell.pass_profile.fps, "good_picks_per_part":
                                   FINE_GOOD_PICKS,
                               "sizes_mm": {k: list(v) for k, v in FINE_SIZES_MM.items()}},
                           "calibration": cal_row, "blas_threads": 1, "jobs": jobs},
              "rows": rows, "timed": [t for part in timed for t in part],
              "summary": _summary([r for r in rows if r.get("pass") != "fine"],
                                  [t for part in timed for t in part]),
              "elapsed_s": round(time.perf_counter() - t_start, 1)}
    fine_rows = [r for r in rows if r.get("pass") == "fine"]
    if fine_rows:
        result["summary"]["fine_pass"] = _summary(fine_rows)
    result = write_json(out / "inspect.json", result, digits=6)
    _chart(result, out / "inspect.png")
    say(f"bench inspect done in {result['elapsed_s']:.0f} s: {out / 'inspect.json'}")
    return result


def _calibrated_cell(quick: bool):
    """The bench's realistic cell, and its calibration by the robot (``bench calibrate``'s
    session, fewer positions when `quick`): ``(cell, calibration, its row)``."""
    positions = QUICK_SESSION_POSITIONS if quick else SESSION_POSITIONS
    with threadpool_limits(limits=1, user_api="blas"):
        cell = realistic_cell(load_cell(perturb_seed=CELL_SEED), seed=CELL_SEED)
        calibration, cal_row = _calibrate(cell, CELL_SEED, *positions)
    return cell, calibration, cal_row


def run_timing(out_dir, quick: bool = False, *, progress=None) -> dict:
    """The check's time alone (``flyscan bench inspect --timing``): `TIMING_PICKS` good picks
    of each part in the bench's calibrated cell, in this process, on one core, its kernels
    warmed up first; per pick its points, the check's ms in the pass, and the least of it
    and `TIMING_REPEATS` checks more of the same scan. Writes ``inspect_timing.json`` and
    ``inspect_timing.png`` into `out_dir`: a machine's answer to "how long does the check add
    to a scan", in minutes where the whole bench takes an hour.

    The budget a pick is held to is 20 ms for a scan of up to 20 000 points and 20 ms per
    20 000 for a larger one; ``*_per_budget_20000`` is the check's ms scaled so
    (``ms * 20 000 / max(points, 20 000)``), ``*_per_20000_points`` scaled by its points
    whatever their number (a small scan's fixed cost, the model's samples, then reads large).
    """
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda line: print(line, file=sys.stderr, flush=True))
    t_start = time.perf_counter()
    names = QUICK_PARTS if quick else PARTS
    cell, calibration, cal_row = _calibrated_cell(quick)
    say(f"bench inspect --timing: cell {CELL_SEED} calibrated in {cal_row['time_s']:.0f} s")
    timed = []
    for index, name in enumerate(names):
        part_times = _timed_check((name, index, 0, 0, {}, cell, calibration),
                                  1 if quick else TIMING_PICKS, TIMING_REPEATS)
        timed += part_times
        say(f"  {name}: " + ", ".join(f"{t['check_ms']:.1f} (least {t['check_ms_least']:.1f}) "
                                      f"ms, {t['points']} points" for t in part_times))
    points = np.array([t["points"] for t in timed], dtype=np.float64)
    checks = np.array([t["check_ms"] for t in timed])
    least = np.array([t["check_ms_least"] for t in timed])

    def spread(values, key):
        return {f"{key}_median": float(np.median(values)),
                f"{key}_p95": float(np.percentile(values, 95))}

    by_part = {}
    for name in names:
        mine = [t for t in timed if t["part"] == name]
        if mine:
            by_part[name] = {"points_median": float(np.median([t["points"] for t in mine])),
                             "check_ms_median": float(np.median([t["check_ms"] for t in mine])),
                             "check_ms_max": float(np.max([t["check_ms"] for t in mine])),
                             "least_ms_median": float(np.median([t["check_ms_least"]
                                                                 for t in mine])),
                             "least_ms_max": float(np.max([t["check_ms_least"] for t in mine]))}
    result = {"quick": quick,
              "settings": {"parts": list(names), "cell": CELL_SEED, "blas_threads": 1,
                           "picks_per_part": 1 if quick else TIMING_PICKS,
                           "repeats": TIMING_REPEATS, "calibration": cal_row},
              "timed": timed,
              "summary": {"picks": len(timed),
                          **spread(checks, "check_ms"),
                          **spread(checks * 20_000.0 / points, "per_20000_points"),
                          **spread(least, "least_ms"),
                          **spread(least * 20_000.0 / points, "least_per_20000_points"),
                          **spread(per_budget_20000(checks, points), "per_budget_20000"),
                          **spread(per_budget_20000(least, points), "least_per_budget_20000"),
                          # a straight line through the least times: a scan of 20 000 points
                          # of a part like these
                          "least_fit_ms_at_20000": (float(np.polyval(
                              np.polyfit(points, least, 1), 20_000.0))
                              if len(set(points.tolist())) > 1 else None),
                          "by_part": by_part},
              "machine": machine_info(),
              "elapsed_s": round(time.perf_counter() - t_start, 1)}
    result = write_json(out / "inspect_timing.json", result, digits=6)
    _timing_chart(result, out / "inspect_timing.png")
    say(f"bench inspect --timing done in {result['elapsed_s']:.0f} s: "
        f"{out / 'inspect_timing.json'}")
    return result


def per_budget_20000(ms, points) -> np.ndarray:
    """The check's ms held to its budget, as ms per 20 000 points: ``ms * 20 000 / max(points,
    20 000)``, the budget being 20 ms for a scan of up to 20 000 points and 20 ms per 20 000
    points above (a small scan's fixed cost, the model's samples, is not scaled up)."""
    return (np.asarray(ms, dtype=np.float64) * 20_000.0
            / np.maximum(np.asarray(points, dtype=np.float64), 20_000.0))


BUDGET_LABEL = "budget: 20 ms, 20 ms per 20 000 points above"


def _timing_chart(result, path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for k, name in enumerate(result["settings"]["parts"]):
        mine = [t for t in result["timed"] if t["part"] == name]
        colour = f"C{k % 10}"
        ax.plot([t["points"] for t in mine], [t["check_ms_least"] for t in mine], "o",
                color=colour, alpha=0.8, label=name)
        ax.plot([t["points"] for t in mine], [t["check_ms"] for t in mine], "o", mfc="none",
                color=colour, alpha=0.6)
    top = max([t["points"] for t in result["timed"]] + [20_000]) * 1.05
    grid = np.linspace(0, top, 100)
    ax.plot(grid, 20.0 / per_budget_20000(1.0, grid), color="tab:red", ls=":", lw=0.8,
            label=BUDGET_LABEL)
    summary = result["summary"]
    ax.set_title(f"the check on one core (filled: least of {1 + result['settings']['repeats']}"
                 f" runs; hollow: the pass's own)\nof the budget, p95: least "
                 f"{summary['least_per_budget_20000_p95']:.1f} ms, the pass's "
                 f"{summary['per_budget_20000_p95']:.1f} ms per 20 000", fontsize=8)
    ax.set_xlabel("cloud points")
    ax.set_ylabel("check, ms")
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    save_figure(fig, path)


def _part_rows(task) -> list[dict]:
    """One part's good picks and faulty ones (a process of its own with ``jobs``)."""
    name, index, good, trials, sizes_mm, cell, calibration = task
    # a finer pass's task names its part's index with the series: (index, 1)
    series = "fine" if isinstance(index, tuple) else "default"
    rows = []
    with threadpool_limits(limits=1, user_api="blas"):
        part = bench_part(name)
        params = replace(PoseParams(), robot_rotation_std_deg=cell.effects.tcp_rotation_error_deg)
        rng = np.random.default_rng([INSPECT_SEED, *np.atleast_1d(index)])
        toward = part.grasp[2, :3]
        cases = [("good", 0.0)] * good + [(kind, size) for kind, sizes in sizes_mm.items()
                                          for size in sizes for _ in range(trials[kind])]
        for i, (kind, size) in enumerate(cases):
            values = random_misplacement(rng, MISPLACEMENT_UP_TO_MM, MISPLACEMENT_UP_TO_DEG,
                                         up_to=True)
            held, model = None, part
            try:
                if kind == "filled":
                    mesh = faulty_mesh(part.mesh, "hole", size, toward, rng)
                    model = part_from_mesh(mesh, name=f"{name} drilled", grasp=part.grasp)
                    held = part
                elif kind != "good":
                    mesh = faulty_mesh(part.mesh, kind, size, toward, rng)
                    held = part_from_mesh(mesh, name=f"{name} {kind}", grasp=part.grasp)
                scan, report = run_simulated_scan(model, cell, calibration=calibration,
                                                  misplacement=misplacement_matrix(values),
                                                  seed=i, evaluate=False, pose_params=params,
                                                  held=held)
            except Exception as exc:  # a chip of an open mesh, a fault that leaves nothing, say
                rows.append({"part": name, "kind": kind, "size_mm": size, "pass": series,
                             "error": repr(exc)})
                continue
            row = _row(name, kind, size, report)
            row["pass"] = series
            row["profile_spacing_mm"] = round(float(scan.profile_spacing_mm), 4)
            thresholds = (report.get("inspection") or {}).get("thresholds")
            if held is not None and thresholds:
                limit = thresholds["deform_mm" if kind == "bend" else "extra_mm"]
                row.update(fault_seen(scan, model.mesh, held.mesh,
                                      misplacement_matrix(values) @ part.grasp, cell, limit,
                                      point_spacing(scan.cloud, scan.frame_ids),
                                      np.array(report["pose"]["matrix"])))
            rows.append(row)
    return rows


def _timed_check(task, picks: int, repeats: int = 0) -> list[dict]:
    """The check's time on `picks` good picks of one part, scanned in this process alone
    (the first of the part's random misplacements), its kernels warmed up first as the
    service's are; with `repeats`, the check run that many times more on each pick's scan
    (``repeats_ms``) and the least of all (``check_ms_least``)."""
    name, index, _, _, _, cell, calibration = task
    out = []
    with threadpool_limits(limits=1, user_api="blas"):
        warm_up_pose()  # as the service does before it streams (``service.engine``)
        warm_up_inspection()
        part = bench_part(name)
        part.prepare()
        params = replace(PoseParams(), robot_rotation_std_deg=cell.effects.tcp_rotation_error_deg)
        rng = np.random.default_rng([INSPECT_SEED, index])
        for i in range(picks):
            values = random_misplacement(rng, MISPLACEMENT_UP_TO_MM, MISPLACEMENT_UP_TO_DEG,
                                         up_to=True)
            scan, report = run_simulated_scan(part, cell, calibration=calibration,
                                              misplacement=misplacement_matrix(values), seed=i,
                                              evaluate=False, pose_params=params)
            inspection = report.get("inspection") or {}
            if inspection.get("time_ms") is None or not report.get("points"):
                continue
            row = {"part": name, "points": report["points"], "check_ms": inspection["time_ms"]}
            if repeats:
                # the same check again on the same scan: the least of them is its cost, the
                # rest what the machine added (timeit's reading)
                matrix = np.asarray(report["pose"]["matrix"], dtype=np.float64)
                again = [inspect_pass(scan, part, matrix).time_ms for _ in range(repeats)]
                row["repeats_ms"] = again
                row["check_ms_least"] = min([row["check_ms"], *again])
            out.append(row)
    return out


def _row(name, kind, size, report) -> dict:
    pose = report.get("pose") or {}
    inspection = report.get("inspection") or {}
    return {"part": name, "kind": kind, "size_mm": size, "state": report.get("state"),
            "posed": "matrix" in pose, "observable": bool(pose.get("observable")),
            "act": bool(pose.get("act")),
            "conforms": inspection.get("conforms"), "failing": inspection.get("failing"),
            "sigma_um": inspection.get("sigma_um"), "points": report.get("points"),
            "check_ms": inspection.get("time_ms"),
            "reasons": [r for r in pose.get("act_reasons", []) if not r.startswith("inspection")],
            **({"failure": report["failure"]} if report.get("failure") else {})}


def fault_seen(scan, good_mesh, held_mesh, true_pose, cell, threshold_mm: float,
               point_step_mm: float, registered_pose=None) -> dict:
    """Whether the scan's profiles crossed the fault where the true cell lights and sees it,
    as much as the check needs to call a region.

    The difference between the model and the held mesh, at the true pose ``true_pose``
    (^T X_P) and the model at ``registered_pose`` (the scan's; default the true one: what the
    registration absorbed of a bend or a longer part, no check at that pose can see): the
    held mesh's surface samples farther than `threshold_mm` from the model's (material added
    or moved, where the scan's points lie off the model), and the model's samples farther
    than that and than the scan's cover radius (``COVER_STEPS`` point steps) from the held
    mesh's surface (material taken away, where the scan has no point: a surface moved by
    less lends the scan points near the model's); lit by the cell's true laser source and
    seen by its true camera (the scan's placed frames, the true cell's sheet), with nothing
    of the mesh in the way.
    A profile's chord across it is the samples within half their spacing of its sheet times
    that spacing, each weighted by ``sqrt(1 - (n . m)^2)`` (a face turned by ``n . m`` to the
    sheet's normal ``m`` lays a strip that much wider within the slab). Seen: one piece of the
    difference (its samples on the sheets grouped as the check groups a region's points,
    ``touching_groups`` at ``LINK_SPACINGS`` of the scan's larger sampling step) crossed by
    ``MIN_REGION_PROFILES`` profiles with a chord of at least ``MIN_PROFILE_POINTS`` + 1 point
    steps (a chord's ends lie at the threshold itself, where the scan's noise takes about
    half the points below it), and ``MIN_REGION_SAMPLES`` point steps of chord in all: no
    fewer points than the check's smallest region holds. Two profiles each across another
    piece (a plug through a stepped part, one face a profile) are two regions of one profile.
    Returns ``{"seen": bool, "seen_profiles": int, "seen_chord_mm": float}``, the last two of
    the piece crossed most."""
    rotations = np.asarray(scan.tcp_rotations_b, dtype=np.float64).reshape(-1, 3, 3)
    positions = np.asarray(scan.tcp_positions_b, dtype=np.float64).reshape(-1, 3)
    if len(rotations) < 2:
        return {"seen": False, "seen_profiles": 0}
    truth = cell.calibration
    sheet = truth.light_plane_b
    to_t = lambda points_b: np.einsum("fji,fj->fi", rotations, points_b - positions)  # noqa: E731
    inverse = rotations.transpose(0, 2, 1)
    planes_t = planes_moved(np.tile(np.r_[sheet.normal, sheet.offset], (len(inverse), 1)),
                            inverse, -np.einsum("fij,fj->fi", inverse, positions))
    model_pose = np.asarray(true_pose if registered_pose is None else registered_pose,
                            dtype=np.float64)
    held_mesh = held_mesh.copy()
    held_mesh.apply_transform(np.linalg.inv(model_pose) @ np.asarray(true_pose))
    rotation, translation = model_pose[:3, :3], model_pose[:3, 3]
    planes_p = planes_moved(planes_t, rotation.T, -rotation.T @ translation)
    sensors_p = (to_t(truth.camera.origin) - translation) @ rotation
    lasers_p = (to_t(cell.laser_origin_b) - translation) @ rotation
    good = SurfaceModel.from_mesh(good_mesh, spacing_mm=SEEN_SPACING_MM, seed=2)
    held = SurfaceModel.from_mesh(held_mesh, spacing_mm=SEEN_SPACING_MM, seed=3)
    on_sheets, on_frames, weights = [], [], []
    no_points = max(threshold_mm, COVER_STEPS * point_step_mm)
    for samples, other, mesh, other_mesh, threshold_mm in (
            (good, held, good_mesh, held_mesh, no_points),
            (held, good, held_mesh, good_mesh, threshold_mm)):
        # off the other's samples, then off its mesh itself (the samples' own spacing puts
        # points near an edge off by a little)
        deviation = np.abs(point_deviations(samples.points, other))
        index = np.nonzero(deviation > threshold_mm)[0]
        # those near the threshold asked of the mesh itself, a few at a time (a point far
        # from it would weigh every face); those far beyond it are off it surely
        unsure = index[deviation[index] <= threshold_mm + SEEN_UNSURE_SPACINGS * other.spacing_mm]
        off = np.ones(len(samples.points), bool)
        for chunk in np.array_split(unsure, max(1, len(unsure) // 2000 + 1)):
            if len(chunk):
                _, exact, _ = trimesh.proximity.closest_point(other_mesh, samples.points[chunk])
                off[chunk] = exact > threshold_mm
        index = index[off[index]]
        frame, _, _ = sheet_crossings(samples.points[index], planes_p)
        index, frame = index[frame >= 0], frame[frame >= 0]
        lit = lit_and_seen(samples.points[index], samples.normals[index], sensors_p[frame],
                           planes_p[frame], lambda o, d, m=mesh: m.ray.intersects_any(o, d),
                           sources_p=lasers_p[frame])
        index, frame = index[lit], frame[lit]
        off_sheet = np.abs(np.einsum("ij,ij->i", planes_p[frame, :3], samples.points[index])
                           - planes_p[frame, 3])
        # a face inclined to the sheet lays a wider strip of samples within the slab about
        # it: each counts for the slab's width across the face, sqrt(1 - (n . m)^2)
        on = off_sheet <= 0.5 * samples.spacing_mm
        width = np.sqrt(np.clip(1.0 - np.einsum("ij,ij->i", planes_p[frame[on], :3],
                                                samples.normals[index[on]]) ** 2, 0.0, 1.0))
        on_sheets.append(samples.points[index[on]])
        on_frames.append(frame[on])
        weights.append(width)
    step = float(scan.profile_spacing_mm)
    return seen_piece(*(np.concatenate(x) for x in (on_sheets, on_frames, weights)),
                      max(step, point_step_mm) if math.isfinite(step) else point_step_mm,
                      point_step_mm)


def seen_piece(points, frames, width, sampling_mm: float, point_step_mm: float) -> dict:
    """``fault_seen``'s verdict from the difference's samples on the sheets: `points` (K, 3)
    mm, the frame of each (K,), the width each counts for (K,); grouped at ``LINK_SPACINGS``
    of `sampling_mm` (the scan's larger sampling step), the piece crossed most."""
    best = {"seen": False, "seen_profiles": 0, "seen_chord_mm": 0.0}
    if not len(points):
        return best
    for group in touching_groups(points, LINK_SPACINGS * sampling_mm):
        ids, inverse = np.unique(frames[group], return_inverse=True)
        chords = np.bincount(inverse, weights=width[group]) * SEEN_SPACING_MM
        crossing = chords[chords >= (MIN_PROFILE_POINTS + 1) * point_step_mm]
        seen = (len(crossing) >= MIN_REGION_PROFILES
                and crossing.sum() >= MIN_REGION_SAMPLES * point_step_mm)
        piece = {"seen": bool(seen), "seen_profiles": int(len(crossing)),
                 "seen_chord_mm": round(float(crossing.sum()), 3)}
        if (piece["seen"], piece["seen_chord_mm"]) > (best["seen"], best["seen_chord_mm"]):
            best = piece
    return best


def pod_fit(sizes, hits) -> dict:
    """The hit/miss POD curve ``1 / (1 + exp(-(b0 + b1 ln a)))`` of sizes (mm, > 0) and hits
    (bool), by maximum likelihood; ``a90`` and ``a90_95`` (where the lower 95 % band reaches
    90 %) in mm, None where the data cannot say (all hits or all misses: no slope)."""
    a = np.asarray(sizes, dtype=np.float64)
    y = np.asarray(hits, dtype=np.float64)
    out = {"trials": int(len(a)), "hits": int(y.sum()), "b0": None, "b1": None, "a90": None,
           "a90_95": None}
    if len(a) < 4 or y.all() or not y.any():
        return out
    x = np.log(a)

    def nll(b):
        z = b[0] + b[1] * x
        return float(np.sum(np.logaddexp(0.0, z) - y * z))

    fit = minimize(nll, np.array([0.0, 1.0]), method="BFGS")
    b0, b1 = fit.x
    if not (np.isfinite(b1) and b1 > 0):
        return out
    p = 1.0 / (1.0 + np.exp(-(b0 + b1 * x)))
    info = np.array([[np.sum(p * (1 - p)), np.sum(p * (1 - p) * x)],
                     [np.sum(p * (1 - p) * x), np.sum(p * (1 - p) * x * x)]])
    cov = np.linalg.pinv(info)
    logit90 = math.log(9.0)
    out.update(b0=float(b0), b1=float(b1), a90=float(math.exp((logit90 - b0) / b1)))
    grid = np.linspace(x.min() - 1.0, x.max() + 3.0, 2001)
    se = np.sqrt(np.maximum(cov[0, 0] + 2 * grid * cov[0, 1] + grid**2 * cov[1, 1], 0.0))
    lower = b0 + b1 * grid - 1.645 * se
    reached = np.nonzero(lower >= logit90)[0]
    out["a90_95"] = float(math.exp(grid[reached[0]])) if len(reached) else None
    return out


def _summary(rows, timed=()) -> dict:
    ok = [r for r in rows if "error" not in r]
    # a false reject is a good pick whose pose fixes every axis and whose check fails; where
    # the pose leaves an axis free the model may sit off along it (never acted on either way)
    good = [r for r in ok if r["kind"] == "good" and r["posed"] and r["observable"]]
    loose = [r for r in ok if r["kind"] == "good" and r["posed"] and not r["observable"]]
    faults = [r for r in ok if r["kind"] != "good"]
    per_kind = {}
    for kind in SIZES_MM:
        mine = [r for r in faults if r["kind"] == kind]
        if not mine and faults:  # a series without this kind (the finer pass's)
            continue
        sizes = sorted({r["size_mm"] for r in mine})
        hit = [r["conforms"] is False for r in mine]
        by_size = {str(s): {"trials": sum(r["size_mm"] == s for r in mine),
                            "detected": sum(h for r, h in zip(mine, hit) if r["size_mm"] == s),
                            "seen": sum(_seen(r) for r in mine if r["size_mm"] == s),
                            "detected_of_seen": sum(h for r, h in zip(mine, hit)
                                                    if r["size_mm"] == s and _seen(r)),
                            "acted_on": sum(r["act"] for r in mine if r["size_mm"] == s)}
                   for s in sizes}
        seen = [r for r in mine if _seen(r)]
        seen_loose = [r for r in mine if r.get("seen") and not r["observable"]]
        entry = {"trials": len(mine), "detected": int(sum(hit)),
                 # the faults the scan's profiles crossed as much as the check's smallest
                 # region needs (``fault_seen``, from the simulator's truth), at a pose that
                 # fixes every axis (``_seen``)
                 "seen": len(seen), "detected_of_seen": sum(r["conforms"] is False for r in seen),
                 # ... and at a pose that leaves an axis loose: never acted on either way
                 "seen_pose_loose": len(seen_loose),
                 "detected_of_seen_pose_loose": sum(r["conforms"] is False for r in seen_loose),
                 "seen_missed": [{"part": r["part"], "size_mm": r["size_mm"],
                                  "seen_profiles": r["seen_profiles"],
                                  "seen_chord_mm": r["seen_chord_mm"]}
                                 for r in seen if r["conforms"] is not False],
                 # a scan that failed (the second part hid the marker, say), or a pose refused:
                 # never acted on, though the check never ran
                 "scan_failed_or_refused": sum(not r["posed"] for r in mine),
                 "acted_on": sum(r["act"] for r in mine), "by_size": by_size}
        if kind != "double":
            entry["pod"] = pod_fit([r["size_mm"] for r in mine], hit)
        per_kind[kind] = entry
    # the check's time on good picks, scaled to 20 000 points (its queries grow with the
    # points): timed apart on one idle core where given, else as the pool's processes ran it
    timed = list(timed) or [r for r in good if r.get("check_ms") is not None and r.get("points")]
    checks = np.array([r["check_ms"] for r in timed])
    per_20k = np.array([r["check_ms"] * 20_000.0 / r["points"] for r in timed])
    budget = per_budget_20000(checks, [r["points"] for r in timed])
    loaded = np.array([r["check_ms"] * 20_000.0 / r["points"] for r in good
                       if r.get("check_ms") is not None and r.get("points")])
    return {
        "good_picks": len(good),
        "good_picks_not_observable": len(loose),
        "not_observable_failing_the_check": sum(r["conforms"] is False for r in loose),
        "false_rejects": sum(r["conforms"] is False for r in good),
        "false_reject_share": (sum(r["conforms"] is False for r in good) / len(good)
                               if good else None),
        "false_rejects_by_part": {p: sum(r["conforms"] is False for r in good if r["part"] == p)
                                  for p in sorted({r["part"] for r in good})},
        "faults": per_kind,
        "acted_on_detected": sum(r["act"] and r["conforms"] is False for r in faults),
        "acted_on_undetected": sum(r["act"] and r["conforms"] is not False for r in faults),
        "check_ms": {"median": float(np.median(checks)) if len(checks) else None,
                     "p95": float(np.percentile(checks, 95)) if len(checks) else None,
                     "per_20000_points_median": (float(np.median(per_20k)) if len(per_20k)
                                                 else None),
                     "per_20000_points_p95": (float(np.percentile(per_20k, 95)) if len(per_20k)
                                              else None),
                     "per_budget_20000_p95": (float(np.percentile(budget, 95)) if len(budget)
                                              else None),
                     "timed_picks": len(timed),
                     "per_20000_points_median_in_the_pool": (float(np.median(loaded))
                                                             if len(loaded) else None)},
        "errors": [r for r in rows if "error" in r],
    }


def _seen(row) -> bool:
    """Whether the scan saw a fault's difference from the model: its profiles crossed it
    (``fault_seen``) and the pose fixes every axis. Where an axis is loose (free, or 3 sigma
    beyond the act tolerance) the model may sit anywhere along it within its sigmas, and so
    may the difference: a longer part slid along its length fits as a good one. Such picks
    are never acted on, and are counted apart, as the good picks are."""
    return bool(row.get("seen")) and bool(row["observable"])


def _progress_line(rows, elapsed_s) -> str:
    name = rows[0]["part"] if rows else "?"
    if rows and rows[0].get("pass") == "fine":
        name += " (finer pass)"
    good = [r for r in rows if r.get("kind") == "good" and r.get("observable")]
    faults = [r for r in rows if r.get("kind") not in ("good", None) and "error" not in r]
    return (f"bench inspect: {name}: {sum(r['conforms'] is False for r in good)} of {len(good)} "
            f"good picks with every axis fixed rejected, "
            f"{sum(r['conforms'] is False for r in faults)} of {len(faults)} faults detected "
            f"({elapsed_s:.0f} s)")


def _chart(result, path) -> None:
    plt = pyplot()
    kinds = [k for k in SIZES_MM if k != "double"]
    fig, axes = plt.subplots(1, len(kinds) + 1, figsize=(4.0 * (len(kinds) + 1), 3.6))
    rows = [r for r in result["rows"] if "error" not in r and r.get("pass") != "fine"]
    summary = result["summary"]
    for ax, kind in zip(axes, kinds):
        mine = [r for r in rows if r["kind"] == kind]
        sizes = np.array([r["size_mm"] for r in mine])
        hits = np.array([r["conforms"] is False for r in mine], dtype=float)
        jitter = np.random.default_rng(0).uniform(-0.03, 0.03, len(hits))
        ax.semilogx(sizes, hits + jitter, "o", alpha=0.35, color="tab:blue", label="hit / miss")
        pod = summary["faults"][kind].get("pod") or {}
        if pod.get("b1"):
            grid = np.geomspace(min(SIZES_MM[kind]) * 0.5, max(SIZES_MM[kind]) * 2.0, 200)
            curve = 1.0 / (1.0 + np.exp(-(pod["b0"] + pod["b1"] * np.log(grid))))
            ax.semilogx(grid, curve, color="tab:red", label="POD fit")
            if pod.get("a90"):
                ax.axvline(pod["a90"], color="tab:red", ls=":",
                           label=f"a90 {pod['a90']:.2f} mm"
                                 + (f", a90/95 {pod['a90_95']:.2f}" if pod.get("a90_95") else ""))
        fine = (summary.get("fine_pass") or {}).get("faults", {}).get(kind)
        if fine:
            fine_rows = [r for r in result["rows"] if "error" not in r and r["kind"] == kind
                         and r.get("pass") == "fine"]
            ax.semilogx([r["size_mm"] * 1.04 for r in fine_rows],
                        [float(r["conforms"] is False) - 0.06 for r in fine_rows], "^",
                        alpha=0.35, color="tab:purple",
                        label=f"finer pass: {fine['detected_of_seen']} of {fine['seen']} seen "
                              "detected")
        by_size = summary["faults"][kind]["by_size"]
        seen_sizes = [float(k) for k, v in by_size.items() if v.get("seen")]
        if seen_sizes:
            ax.semilogx(seen_sizes, [by_size[str(k) if str(k) in by_size else k]
                                     ["detected_of_seen"] / by_size[str(k)]["seen"]
                                     for k in seen_sizes], "s", color="tab:green", ms=6,
                        mfc="none", label="detected of those seen")
        ax.axhline(0.9, color="gray", lw=0.5)
        ax.set_title(f"{kind}: {summary['faults'][kind]['detected_of_seen']} of "
                     f"{summary['faults'][kind]['seen']} seen detected", fontsize=9)
        ax.set_xlabel("size, mm")
        ax.set_xticks(SIZES_MM[kind], [f"{v:g}" for v in SIZES_MM[kind]])
        ax.minorticks_off()
        ax.set_ylim(-0.1, 1.1)
        ax.legend(fontsize=7, loc="lower right")
    axes[0].set_ylabel("detected (POD)")
    ax = axes[-1]
    points = [r["points"] for r in rows if r.get("check_ms") is not None]
    checks = [r["check_ms"] for r in rows if r.get("check_ms") is not None]
    ax.plot(points, checks, ".", alpha=0.3, color="tab:gray", label="in the pool (2 processes)")
    timed = result.get("timed") or []
    ax.plot([t["points"] for t in timed], [t["check_ms"] for t in timed], "o", color="tab:blue",
            label="apart, one idle core")
    grid = np.linspace(0, max(points + [t["points"] for t in timed] + [20_000]), 100)
    ax.plot(grid, 20.0 / per_budget_20000(1.0, grid), color="tab:red", ls=":", lw=0.8,
            label=BUDGET_LABEL)
    ax.set_xlabel("cloud points")
    ax.set_ylabel("check, ms")
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title(f"false rejects {summary['false_rejects']} of {summary['good_picks']} good; "
                 f"double picks {summary['faults']['double']['detected']} of "
                 f"{summary['faults']['double']['trials']}", fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
