"""``flyscan bench planning``: the scan planner (``planning``) measured.

Phases, each writing ``OUT/<phase>.json`` (``phase(out)`` runs one alone), gathered by
`combine` into ``OUT/bench_planning.json`` and ``OUT/bench_planning.png``:

- ``reference``: the four reference parts planned (``flyscan plan``'s defaults) on a local
  cluster of two workers: the time, each part's chosen grasp, turn and preset, whether it
  fixes every axis; the per-task cost and memory of its candidates.
- ``rerun``: the same plan again on its cache: what it computes, its time against the first's.
- ``measured``: each reference part scanned by ``flyscan scan --plan`` at other noise seeds,
  at the nominal grasp and at random misplacements (up to 5 mm and 10 degrees, the pose
  bench's set): the sigmas it reports against those the plan predicted (target: within a
  factor 2).
- ``fastpath``: for every grasp and turn of the reference parts at the default preset, the
  verdict of the fast ray-cast path (``predict_cloud`` at the pass's profile spacing,
  registered without edges: it has none) against the rendered pass's: which axes are free.
- ``catalogue``: a procedural catalogue of 100 parts of varied shapes generated in OUT and
  planned with the defaults on two workers: the time, the parts with every axis fixed, the
  per-task cost and memory.
- ``throughput``: one fixed set of candidates computed on 1 then 2 workers (each warmed up,
  a fresh cache each time): candidates per second, and the ratio (target 1.7). Run it with
  the cores free: the load average before and after is recorded.
"""
from __future__ import annotations

import io
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.parts import (MISPLACEMENT_UP_TO_DEG, MISPLACEMENT_UP_TO_MM, REFERENCE_PARTS,
                              random_misplacement)
from benchmarks.results import pyplot, save_figure, write_json

__all__ = ["run", "PHASES", "combine"]

#: A catalogue of this many procedural parts is planned by the ``catalogue`` phase.
CATALOGUE_PARTS = 100
#: Seeds of ``flyscan scan --plan`` in the ``measured`` phase (the plan's own is 0).
MEASURED_SEEDS = (1, 2, 3)
#: The throughput's fixed set: this many procedural parts, default preset, turns of 90
#: degrees, one resting face.
THROUGHPUT_PARTS = 8
TARGET_RATIO = 1.7
TARGET_SIGMA_FACTOR = 2.0


def run(out, *, quick: bool = False) -> dict:
    """Every phase (``quick``: 10 catalogue parts, 3 throughput parts), then `combine`."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    reference(out)
    rerun(out)
    measured(out)
    fastpath(out)
    catalogue(out, parts=10 if quick else CATALOGUE_PARTS)
    throughput(out, parts=3 if quick else THROUGHPUT_PARTS)
    return combine(out)


def _log(text: str) -> None:
    print(f"bench planning: {text}", file=sys.stderr, flush=True)


def _costs(results: list[dict]) -> dict:
    """Per-task wall and CPU time and the worker's peak memory over `results`' ``cost``."""
    costs = [r["cost"] for r in results if r.get("cost")]
    if not costs:
        return {}
    pick = {k: np.array([c[k] for c in costs]) for k in ("wall_s", "cpu_s", "rss_mb")}
    return {"tasks": len(costs),
            **{f"{k}_median": float(np.median(v)) for k, v in pick.items()},
            **{f"{k}_p95": float(np.percentile(v, 95)) for k, v in pick.items()},
            "rss_mb_max": float(pick["rss_mb"].max()),
            "wall_s_sum": float(pick["wall_s"].sum())}


def _cached_results(out: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted((out / "cache").glob("*/*.json"))]


def _reference_folder() -> Path:
    from simulator.parts import reference_meshes_dir

    folder = reference_meshes_dir()
    if folder is None or not (folder / "manifest.json").is_file():
        raise FileNotFoundError("the reference meshes: give --meshes DIR or FLYSCAN_MESHES")
    return folder


def reference(out: Path) -> dict:
    from planning.run import plan_catalogue

    plan_out = out / "reference"
    shutil.rmtree(plan_out, ignore_errors=True)
    _log("the reference parts' plan on 2 workers")
    run_ = plan_catalogue(_reference_folder(), plan_out, workers=2)
    parts = {}
    for row in run_.summary["rows"]:
        plan = json.loads((plan_out / "plans" / row["part"] / "plan.json").read_text())
        done = [c for c in plan["candidates"] if c["status"] == "done"]
        parts[row["part"]] = {
            "grasp": row.get("grasp"), "turn_deg": row.get("turn_deg"),
            "preset": row.get("preset"), "every_axis_fixed": row["status"] == "every axis fixed",
            "act": row.get("act"), "std": plan["chosen"]["predicted"]["std"],
            "score": row.get("score"), "candidates": len(plan["candidates"]),
            "candidates_fixing_every_axis": sum(c["observable"] for c in done),
            "failed": [f"{c['grasp']} {c['pass_direction_deg']:g} {c['preset']}: {c['reason']}"
                       for c in plan["candidates"] if c["status"] != "done"][:3],
            "failed_count": sum(c["status"] != "done" for c in plan["candidates"])}
    result = {"run": run_.summary["run"], "parts": parts,
              "cost": _costs(_cached_results(plan_out))}
    write_json(out / "reference.json", result)
    return result


def rerun(out: Path) -> dict:
    """The reference plan again on its cache: what it computes and how long it takes against
    the first run (target: under 10 %)."""
    from planning.run import plan_catalogue

    first = json.loads((out / "reference.json").read_text())["run"]
    again = plan_catalogue(_reference_folder(), out / "reference", workers=2, log=io.StringIO())
    result = {"computed": again.computed, "cached": again.cached, "wall_s": again.wall_s,
              "first_wall_s": first["wall_s"], "fraction": again.wall_s / first["wall_s"]}
    write_json(out / "rerun.json", result)
    return result


def measured(out: Path) -> dict:
    """A scan of each reference part as its plan says (``flyscan scan --plan``'s pass, the
    reference cell): reported sigmas against the plan's."""
    from scanner_core.cad import load_part
    from scanner_core.scanplan import load_scan_plan
    from simulator.cell import cell_with_effects
    from simulator.parts import simulated
    from simulator.session import misplacement_matrix, run_simulated_scan

    folder, plans = _reference_folder(), out / "reference" / "plans"
    manifest = json.loads((folder / "manifest.json").read_text())
    rows = []
    for index, name in enumerate(REFERENCE_PARTS):
        file_name = next(f for f in manifest if Path(f).stem == name)
        plan_path = plans / name / "plan.json"
        predicted = json.loads(plan_path.read_text())["chosen"]["predicted"]["std"]
        rng = np.random.default_rng([30, index])
        plan = load_scan_plan(plan_path)
        held = load_part(folder / file_name, manifest[file_name]["units"],
                         grasp=plan.nominal_grasp)
        cell = cell_with_effects(None, "none").with_pass(speed_mm_s=plan.speed_mm_s, fps=plan.fps)
        for seed in MEASURED_SEEDS:
            for misplaced in (False, True):
                values = _fitting_misplacement(held, rng) if misplaced else np.zeros(6)
                _, report = run_simulated_scan(simulated(held), cell,
                                               misplacement=misplacement_matrix(values),
                                               seed=seed, evaluate=False)
                pose = report.get("pose") or {}
                std = pose.get("std") or {}
                ratios = {a: (predicted[a] / std[a] if predicted.get(a) and std.get(a) else None)
                          for a in predicted}
                worst = max((max(r, 1 / r) for r in ratios.values() if r), default=None)
                rows.append({"part": name, "seed": seed, "misplacement": values.tolist(),
                             "observable": pose.get("observable"),
                             "free_axes": [f["label"] for f in pose.get("free_axes", [])],
                             "std": std, "ratio_predicted_over_measured": ratios,
                             "worst_factor": worst, "sigmas_off": (report.get("ground_truth", {})
                                                                   .get("pose_error", {})
                                                                   .get("sigmas"))})
                _log(f"measured {name} seed {seed} misplaced {misplaced}: worst factor "
                     f"{worst if worst is None else round(worst, 2)}")
    factors = [r["worst_factor"] for r in rows if r["worst_factor"] is not None]
    result = {"rows": rows, "worst_factor": max(factors) if factors else None,
              "within_2": sum(f <= TARGET_SIGMA_FACTOR for f in factors), "scans": len(rows),
              "still_every_axis_fixed": sum(bool(r["observable"]) for r in rows)}
    write_json(out / "measured.json", result)
    return result


def _fitting_misplacement(part, rng) -> np.ndarray:
    """A misplacement of the pose bench's set (up to 5 mm and 10 degrees) that leaves the
    part in the volume and out of the gripper (``check_fits``), the first of up to 50 draws."""
    from scanner_core.cad import PartError, check_fits
    from simulator.session import misplacement_matrix

    for _ in range(50):
        values = np.asarray(random_misplacement(rng, MISPLACEMENT_UP_TO_MM,
                                                MISPLACEMENT_UP_TO_DEG, up_to=True))
        try:
            check_fits(part, pose=misplacement_matrix(values) @ part.grasp)
        except PartError:
            continue
        return values
    raise RuntimeError(f"no misplacement of the set leaves {part.name} in the volume")


def fastpath(out: Path) -> dict:
    """The ray-cast path's verdict (no edges) against the rendered pass's, per candidate, and
    the time of each (the ray cast and its registration; the rendered candidate's
    ``planning.evaluate.evaluate``), one after the other in this process."""
    from planning.candidates import candidates
    from planning.catalogue import read_catalogue
    from planning.evaluate import evaluate
    from scanner_core.pose.registration import register
    from simulator.cell import PASS_PRESETS, load_cell
    from simulator.parts import simulated
    from simulator.virtual_setup import predict_cloud, reference_setup

    preset = PASS_PRESETS["default"]
    cell = load_cell()
    spacing = preset.speed_mm_s / preset.fps
    rows = []
    for entry in read_catalogue(_reference_folder()):
        plan = json.loads((out / "reference" / "plans" / entry.name / "plan.json").read_text())
        rendered = {(c["grasp"], c["pass_direction_deg"]): c for c in plan["candidates"]
                    if c["preset"] == "default" and c["status"] == "done"}
        base = simulated(entry.part)
        for cand in candidates(entry.part, presets=("default",))[0]:
            seen = rendered.get((cand.grasp, cand.turn_deg))
            if seen is None:
                continue
            part = base.with_grasp(cand.nominal)
            t0 = time.perf_counter()
            cloud = predict_cloud(part, reference_setup(cell, step_mm=spacing),
                                  pose=cand.nominal, threads=1)
            pose = register(cloud.points, cloud.normals, part.surface_model, cand.nominal,
                            frame_ids=cloud.step)
            fast_s = time.perf_counter() - t0
            rendered_s = evaluate(entry.mesh, cand, preview=False)["cost"]["wall_s"]
            free = sorted(f["label"] for f in pose.free_axes)
            rows.append({"part": entry.name, "grasp": cand.grasp, "turn_deg": cand.turn_deg,
                         "fast_observable": pose.observable, "fast_free": free,
                         "rendered_observable": seen["observable"],
                         "rendered_free": sorted(seen["free_axes"]),
                         "same_verdict": bool(pose.observable) == bool(seen["observable"])
                         and free == sorted(seen["free_axes"]),
                         "fast_s": fast_s, "rendered_s": rendered_s})
    result = {"rows": rows, "candidates": len(rows),
              "same_verdict": sum(r["same_verdict"] for r in rows),
              "fast_s_median": float(np.median([r["fast_s"] for r in rows])),
              "rendered_s_median": float(np.median([r["rendered_s"] for r in rows]))}
    write_json(out / "fastpath.json", result)
    _log(f"fast path: same verdict on {result['same_verdict']} of {len(rows)} candidates")
    return result


def catalogue(out: Path, *, parts: int = CATALOGUE_PARTS) -> dict:
    from planning.catalogue import procedural_catalogue
    from planning.run import plan_catalogue

    folder, plan_out = out / f"catalogue{parts}", out / f"plan{parts}"
    shutil.rmtree(folder, ignore_errors=True)
    shutil.rmtree(plan_out, ignore_errors=True)
    t0 = time.perf_counter()
    procedural_catalogue(folder, parts, seed=30)
    generate_s = time.perf_counter() - t0
    _log(f"{parts} procedural parts in {generate_s:.1f} s; planning them on 2 workers")
    load = os.getloadavg()
    run_ = plan_catalogue(folder, plan_out, workers=2)
    summary = run_.summary
    statuses = [r["status"] for r in summary["rows"]]
    result = {"parts": parts, "generate_s": generate_s, "run": summary["run"],
              "load_before": load, "load_after": os.getloadavg(),
              "every_axis_fixed": statuses.count("every axis fixed"),
              "axes_free": statuses.count("axes free"), "no_scan": statuses.count("no scan"),
              "broken": statuses.count("broken"),
              "candidates_per_part": run_.tasks / max(1, parts - statuses.count("broken")),
              "by_shape": _by_shape(summary["rows"]), "cost": _costs(_cached_results(plan_out)),
              "task_walls": [r["cost"]["wall_s"] for r in _cached_results(plan_out)
                             if r.get("cost")],
              "task_cpu": [r["cost"]["cpu_s"] for r in _cached_results(plan_out)
                           if r.get("cost")]}
    write_json(out / "catalogue.json", result)
    return result


def _by_shape(rows) -> dict:
    shapes: dict = {}
    for r in rows:
        shape = r["part"].split("_", 1)[-1]
        entry = shapes.setdefault(shape, {"parts": 0, "every_axis_fixed": 0})
        entry["parts"] += 1
        entry["every_axis_fixed"] += r["status"] == "every axis fixed"
    return shapes


def throughput(out: Path, *, parts: int = THROUGHPUT_PARTS, workers=(1, 2, 1, 2)) -> dict:
    """The same candidates on 1 and 2 workers, alternately (other jobs on the machine come and
    go: alternating spreads them over both), each cluster warmed up, each run with a fresh
    cache; the ratio of the medians."""
    from distributed import Client

    from planning.catalogue import procedural_catalogue
    from planning.evaluate import warm_up
    from planning.run import local_cluster, plan_catalogue

    folder = out / "throughput_catalogue"
    shutil.rmtree(folder, ignore_errors=True)
    procedural_catalogue(folder, parts, seed=31)
    runs = []
    for n in workers:
        plan_out = out / f"throughput_{n}"
        shutil.rmtree(plan_out, ignore_errors=True)
        with local_cluster(n) as cluster, Client(cluster) as client:
            client.run(warm_up)
            load = os.getloadavg()
            run_ = plan_catalogue(folder, plan_out, client=client, turn_step_deg=90.0,
                                  presets=("default",), resting=1, log=io.StringIO())
            runs.append({"workers": n, "tasks": run_.computed, "compute_s": run_.compute_s,
                         "per_s": run_.computed / run_.compute_s, "load_before": load,
                         "load_after": os.getloadavg(),
                         "cost": _costs(_cached_results(plan_out))})
        _log(f"{n} workers: {runs[-1]['tasks']} tasks in {run_.compute_s:.1f} s "
             f"(load before {load[0]:.2f})")
    def median(n):
        return float(np.median([r["per_s"] for r in runs if r["workers"] == n]))

    result = {"runs": runs, "ratio": median(max(workers)) / median(min(workers)),
              "target_ratio": TARGET_RATIO, "nice": os.nice(0)}
    write_json(out / "throughput.json", result)
    return result


PHASES = {"reference": reference, "rerun": rerun, "measured": measured, "fastpath": fastpath,
          "catalogue": catalogue, "throughput": throughput}


def projection(per_task_s: float, candidates_per_part: float, parts: int = 1000,
               workers=(2, 8, 32, 128)) -> dict:
    """A projection, not a measurement: `parts` parts of `candidates_per_part` candidates,
    each task taking `per_task_s` of a worker (its mean wall time measured with two workers
    on two cores, so the contention of two at once is in it), on N such workers (one core
    each), assuming they scale as these did and the scheduler's few milliseconds a task
    stay negligible; hours."""
    total = parts * candidates_per_part * per_task_s
    return {"parts": parts, "candidates_per_part": round(candidates_per_part, 2),
            "per_task_s": round(per_task_s, 3),
            "hours": {str(n): round(total / n / 3600, 2) for n in workers}}


def combine(out) -> dict:
    """``bench_planning.json`` and ``.png`` from the phases' files in `out`."""
    out = Path(out)
    phases = {name: json.loads((out / f"{name}.json").read_text())
              for name in PHASES if (out / f"{name}.json").is_file()}
    summary = {}
    if "throughput" in phases:
        t = phases["throughput"]
        summary["throughput"] = [{"workers": r["workers"], "per_s": round(r["per_s"], 3),
                                  "load_before": round(r["load_before"][0], 2),
                                  "load_after": round(r["load_after"][0], 2)}
                                 for r in t["runs"]]
        summary["ratio_2_over_1"] = round(t["ratio"], 3)
        # earlier runs of the phase, kept as throughput_attempt*.json: the cores are shared
        attempts = sorted(out.glob("throughput_attempt*.json"))
        if attempts:
            phases["throughput_attempts"] = [json.loads(a.read_text()) for a in attempts]
            summary["ratio_attempts"] = [
                {"ratio": round(a["ratio"], 3),
                 "load_before": [round(r["load_before"][0], 2) for r in a["runs"]],
                 "load_after": [round(r["load_after"][0], 2) for r in a["runs"]]}
                for a in phases["throughput_attempts"]]
    if "catalogue" in phases:
        c = phases["catalogue"]
        summary["catalogue"] = {k: c[k] for k in ("parts", "every_axis_fixed", "axes_free",
                                                 "no_scan", "broken")}
        summary["catalogue"]["wall_s"] = c["run"]["wall_s"]
        summary["task_cost"] = c["cost"]
        # from the mean wall time a task took here (two workers and other jobs on two cores)
        # and from its mean CPU time (what a core of its own would take)
        summary["projection"] = {
            "from_wall": projection(c["cost"]["wall_s_sum"] / c["cost"]["tasks"],
                                    c["candidates_per_part"]),
            "from_cpu": projection(float(np.mean(c["task_cpu"])), c["candidates_per_part"])}
    if "reference" in phases:
        r = phases["reference"]
        summary["reference"] = {"wall_s": r["run"]["wall_s"], "parts": {
            k: {f: v[f] for f in ("grasp", "turn_deg", "preset", "every_axis_fixed")}
            for k, v in r["parts"].items()}}
    if "rerun" in phases:
        summary["cached_rerun"] = {k: phases["rerun"][k] for k in ("computed", "wall_s",
                                                                  "fraction")}
    if "measured" in phases:
        m = phases["measured"]
        for kind, rows in (("nominal", [r for r in m["rows"] if not any(r["misplacement"])]),
                           ("misplaced", [r for r in m["rows"] if any(r["misplacement"])])):
            factors = [r["worst_factor"] for r in rows if r["worst_factor"] is not None]
            summary[f"sigma_{kind}"] = {
                "scans": len(rows), "worst_factor": max(factors, default=None),
                "within_2": sum(f <= TARGET_SIGMA_FACTOR for f in factors),
                "every_axis_fixed": sum(bool(r["observable"]) for r in rows)}
    if "fastpath" in phases:
        f = phases["fastpath"]
        summary["fast_path_same_verdict"] = f"{f['same_verdict']} of {f['candidates']}"
    result = {"summary": summary, **phases}
    write_json(out / "bench_planning.json", result)
    _chart(phases, out / "bench_planning.png")
    return result


def _chart(phases: dict, path: Path) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    ax = axes[0]
    if "throughput" in phases:
        runs = phases["throughput"]["runs"]
        n = sorted({r["workers"] for r in runs})
        medians = [float(np.median([r["per_s"] for r in runs if r["workers"] == k])) for k in n]
        ax.bar(n, medians, width=0.5, alpha=0.5, label="median")
        ax.scatter([r["workers"] for r in runs], [r["per_s"] for r in runs], c="k", s=12,
                   label="runs")
        for r in runs:
            ax.annotate(f"load {r['load_before'][0]:.1f}", (r["workers"], r["per_s"]),
                        fontsize=7, xytext=(4, 0), textcoords="offset points")
        ax.plot(n, [medians[0] * k for k in n], "k--", label="ideal")
        ax.set_xticks(n)
        ax.legend(fontsize=8)
        ratios = ", ".join(f"{a['ratio']:.2f}" for a in phases.get("throughput_attempts", []))
        ax.set_title(f"throughput: 2/1 = {phases['throughput']['ratio']:.2f}"
                     + (f" (attempts {ratios})" if ratios else ""), fontsize=9)
    ax.set_xlabel("workers")
    ax.set_ylabel("candidates per second")
    ax = axes[1]
    if "catalogue" in phases:
        walls = phases["catalogue"]["task_walls"]
        ax.hist(walls, bins=30)
        ax.set_title(f"task cost, {len(walls)} candidates of the catalogue", fontsize=9)
    ax.set_xlabel("seconds a task")
    ax = axes[2]
    if "measured" in phases:
        for i, name in enumerate(REFERENCE_PARTS):
            rows = [r for r in phases["measured"]["rows"] if r["part"] == name]
            values = [v for r in rows for v in r["ratio_predicted_over_measured"].values() if v]
            ax.scatter(np.full(len(values), i) + np.random.default_rng(i).uniform(
                -0.2, 0.2, len(values)), values, s=8)
        ax.axhspan(0.5, 2.0, color="g", alpha=0.1)
        ax.set_yscale("log")
        ax.set_xticks(range(len(REFERENCE_PARTS)), REFERENCE_PARTS, fontsize=8)
        ax.set_title("predicted / measured sigma per axis (green: within 2)", fontsize=9)
    save_figure(fig, path)

