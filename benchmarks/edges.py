"""Edges at soft creases and on walls: edge points per part and per edge kind.

Every row is one simulated pass of the reference cell (the pass ``simulator.session
.run_simulated_scan`` makes, driven here so that the frames' truth is kept), its edge points
scored against the true CAD edges (``simulator.evaluate.edge_kind_accuracy``: sharp edges
over 30 degrees and, for drop-outs, the outline seen along z_T; in the (x_T, y_T) plane;
*false* beyond 0.5 mm). Three edge clouds per pass:

- **before**: the edge cloud with the points set aside as turned away put back (the scanner
  without ``scanner_core.edges.kinds.turned_away``; the step placement is in it);
- **model-free**: the scan's own edge cloud (drop-outs and steps), what the pose registers;
- **with the model**: after registration against the CAD (``scanner_core.pose.registration.scan_pose``),
  the points off every model edge set aside too (``edge_kinds.reclassify_with_model``; its
  figures are bounded by the model's tolerance by construction).

Each set-aside kind (occluded, grazing, turned away, off the model) is scored too, and the false
drop-outs of the "before" cloud and the points set aside as turned away are told apart by the
truth (``simulator.evaluate.dropout_causes``: the outline, a rim turned from the laser, a
surface unseen by the camera, or lit and seen but too faint).

Parts: the procedural ones of ``simulator.parts`` (faceted domes with creases of 15, 18-20 and
26 degrees, the 18-20 one also standing on a wider plinth, a fan disk, the bracket with two
holes and a 5 mm step, the bracket turned 35 degrees about z and leaning 6 degrees about y
(its step's wall leaning under its top edge), a crowned block, the demo block) and the four
reference parts, these at the misplacements and seeds ``flyscan bench pose`` scans them at.
The target: the model-free edge cloud within 30 um RMS (inliers, as ``bench pose``
scores) with fewer than 5 % of its points false, on every part.

``run(out_dir)`` writes ``edges.json`` and ``edges.png`` into ``out_dir`` and returns the dict;
``quick`` scans three procedural parts once each.
"""
from __future__ import annotations

import math
import pathlib
import sys
import time
from collections import Counter

import numpy as np
from threadpoolctl import threadpool_limits

from scanner_core.edges.kinds import EDGE_KIND_NAMES, kind_counts, reclassify_with_model
from scanner_core.edges import EdgeKind
from scanner_core.pipeline.session import run_session
from scanner_core.pose.registration import scan_pose
from benchmarks.parts import (MISPLACEMENT_SEED, MISPLACEMENT_UP_TO_DEG, MISPLACEMENT_UP_TO_MM,
                              REFERENCE_PARTS, random_misplacement)
from benchmarks.results import pyplot, save_figure, write_json
from benchmarks.targets import EDGE_OUTLIER_MM, TARGET_EDGE_OUTLIERS, TARGET_EDGE_RMS_UM
from simulator.cell import load_cell
from simulator.evaluate import dropout_causes, edge_distances, edge_kind_accuracy
from simulator.parts import (Part, block_with_holes_and_steps, bracket_with_two_holes,
                             crowned_block, faceted_dome, fan_disk, load_reference_part,
                             part_from_mesh)
from simulator.session import misplacement_matrix, simulated_cell

__all__ = ["run", "PROCEDURAL_PARTS", "REFERENCE_PARTS"]

#: name -> (mesh builder, the nominal grasp's turn before centring: a rotation vector, deg)
PROCEDURAL_PARTS = {
    "faceted_dome": (lambda: faceted_dome(), None),
    "faceted_dome_plinth": (lambda: faceted_dome(plinth_radius=40.0), None),
    "faceted_dome_15deg": (lambda: faceted_dome(slopes_deg=(0, 15, 30, 45, 60, 75),
                                                 tier_drop=3.0), None),
    "faceted_dome_26deg": (lambda: faceted_dome(slopes_deg=(0, 26, 52, 78)), None),
    "fan_disk": (lambda: fan_disk(), None),
    "bracket": (lambda: bracket_with_two_holes(), None),
    "bracket_turned": (lambda: bracket_with_two_holes(), (0.0, 0.0, 35.0)),
    # its 5 mm step's wall leaning 6 degrees under its top edge
    "bracket_leaning": (lambda: bracket_with_two_holes(), (0.0, -6.0, 0.0)),
    "crowned_block": (lambda: crowned_block(), None),
    "block": (lambda: block_with_holes_and_steps(), None),
}
QUICK_PARTS = ("faceted_dome", "faceted_dome_plinth", "bracket")
#: Passes per procedural part: the nominal grasp, then random misplacements.
SCANS_PER_PART, QUICK_SCANS = 4, 1
#: Passes per reference part: those of ``flyscan bench pose`` (its seed, misplacements up to
#: 5 mm and 10 degrees in random directions, seeds 0..7: ``benchmarks.parts``).
REFERENCE_SCANS = 8
#: The procedural parts' misplacements: the same range, their own seed.
SEED = 25
CLOUDS = ("before", "model_free", "with_model")


def _part(name: str) -> Part:
    if name in PROCEDURAL_PARTS:
        build, turn_deg = PROCEDURAL_PARTS[name]
        mesh = build()
        grasp = None
        if turn_deg is not None:
            from scipy.spatial.transform import Rotation

            grasp = np.eye(4)
            grasp[:3, :3] = Rotation.from_rotvec(turn_deg, degrees=True).as_matrix()
            grasp = _centred(mesh.vertices, grasp)
        return part_from_mesh(mesh, name=name, source=f"procedural:{name}", grasp=grasp)
    return load_reference_part(name)


def _centred(vertices, turn) -> np.ndarray:
    """``turn`` then centred under the TCP, as ``simulator.parts.centred_grasp``."""
    v = vertices @ turn[:3, :3].T
    lo, hi = v.min(axis=0), v.max(axis=0)
    out = turn.copy()
    out[:2, 3] = -(lo[:2] + hi[:2]) / 2.0
    out[2, 3] = -lo[2]
    return out


def _misplacements(name: str, count: int) -> list:
    """The misplacement (tx, ty, tz mm, rotation vector deg) of each pass of a part."""
    if name in REFERENCE_PARTS:
        rng = np.random.default_rng([MISPLACEMENT_SEED, REFERENCE_PARTS.index(name)])
        return [random_misplacement(rng, MISPLACEMENT_UP_TO_MM, MISPLACEMENT_UP_TO_DEG,
                                    up_to=True) for _ in range(count)]
    # the nominal grasp first
    rng = np.random.default_rng([SEED, list(PROCEDURAL_PARTS).index(name)])
    return [None] + [random_misplacement(rng, MISPLACEMENT_UP_TO_MM, MISPLACEMENT_UP_TO_DEG,
                                         up_to=True) for _ in range(count - 1)]


def _pass(part: Part, cell, values, seed: int):
    """One simulated pass as ``run_simulated_scan`` makes it (the pass session, no pose); the
    scan and the devices (their truth)."""
    sim = simulated_cell(part, cell, misplacement=misplacement_matrix(values), seed=seed)
    return run_session(sim.camera, sim.robot, cell.calibration, register=False).scan, sim


def _figures(acc: dict) -> dict:
    keys = ("count", "rms_um", "rms_inliers_um", "p99_um", "outlier_fraction")
    return {k: acc.get(k) for k in keys}


def scan_row(part: Part, cell, values, seed: int) -> dict:
    """One pass of ``part``: its edge clouds and set-aside kinds scored, its false drop-outs
    and turned-away points explained by the truth."""
    t0 = time.perf_counter()
    scan, sim = _pass(part, cell, values, seed)
    truth = sim.true_grasp
    kinds = edge_kind_accuracy(scan, part.mesh, truth, outlier_mm=EDGE_OUTLIER_MM)
    row = {"part": part.name, "seed": seed, "misplacement": values,
           "points": int(len(scan.cloud)), "frames": int(scan.frames),
           "counts": kind_counts(scan),
           "before": _figures(kinds["without_turned_away"]),
           "model_free": _figures(kinds["edges"]),
           "model_free_by_kind": {k: _figures(v) for k, v in
                                  kinds["edges"].get("by_kind", {}).items()},
           "aside": {k: _figures(v) for k, v in kinds["aside"].items()}}
    row["causes"] = _causes(scan, sim, cell, part)
    try:
        pose = scan_pose(scan, part.surface_model, part.grasp, edge_model=part.edge_model)
        error = pose.matrix @ np.linalg.inv(truth)
        row["pose_error_um"] = float(np.linalg.norm(error[:3, 3]) * 1e3)
        row["pose_flags"] = list(pose.flags)
        row["off_model"] = reclassify_with_model(scan, part.model_edges, pose.matrix)
        row["counts_with_model"] = kind_counts(scan)
        after = edge_kind_accuracy(scan, part.mesh, truth, outlier_mm=EDGE_OUTLIER_MM)
        row["with_model"] = _figures(after["edges"])
        row["off_model_points"] = _figures(after["aside"]["off_model"])
    except ValueError as exc:  # too few points for a pose
        row["pose_refused"] = str(exc)
        row["with_model"] = {"count": 0}
    row["wall_s"] = round(time.perf_counter() - t0, 3)
    return row


def _causes(scan, sim, cell, part) -> dict:
    """By the truth: why the false drop-outs of the cloud without the turned-away test ended,
    and why those set aside as turned away did (with how many of those were true edges)."""
    aside = scan.edges_aside
    turned = aside.kind == EdgeKind.TURNED_AWAY
    points = np.concatenate([np.asarray(scan.edges, np.float64),
                             aside.points[turned].astype(np.float64)])
    kinds = np.concatenate([scan.edge_kind, aside.found[turned]])
    frames = np.concatenate([scan.edge_frame_ids, aside.frame_ids[turned]])
    is_turned = np.concatenate([np.zeros(len(scan.edges), bool), np.ones(int(turned.sum()), bool)])
    out = {"false_before": {}, "turned_away": {}, "turned_away_true_edges": 0}
    if len(points) == 0:
        return out
    d_xy, _, _ = edge_distances(points, part.mesh, sim.true_grasp, kinds=kinds)
    false = d_xy > EDGE_OUTLIER_MM
    out["turned_away_true_edges"] = int((is_turned & ~false).sum())
    dropout = kinds == EdgeKind.DROPOUT
    explain = dropout & (false | is_turned)
    if explain.any():
        causes = dropout_causes(points[explain], frames[explain], scan.cloud, scan.frame_ids,
                                part.mesh, sim.camera.truths, cell.gripper_rotation_b, cell)
        causes = np.array(causes)
        out["false_before"] = dict(Counter(causes[false[explain]].tolist()))
        out["turned_away"] = dict(Counter(causes[is_turned[explain]].tolist()))
    out["false_before_steps"] = int((false & ~dropout).sum())
    return out


def _progress(row: dict) -> None:
    def f(cloud):
        c = row.get(cloud, {})
        rms = c.get("rms_inliers_um")
        return (f"{c.get('count', 0):4d} pts {rms if rms is not None else float('nan'):6.1f} um "
                f"{100 * (c.get('outlier_fraction') or 0):5.1f}% false")
    print(f"bench edges: {row['part']:19s} seed {row['seed']}  before {f('before')} | "
          f"model-free {f('model_free')} | with model {f('with_model')}  "
          f"({row['wall_s']:.1f} s)", file=sys.stderr, flush=True)


def _summary(rows: list[dict]) -> dict:
    """Per part and cloud: points, the worst scan's RMS (inliers and all) and false share,
    the false points over all scans; the points per kind; the causes."""
    parts = {}
    for name in dict.fromkeys(r["part"] for r in rows):
        mine = [r for r in rows if r["part"] == name]
        entry = {"scans": len(mine)}
        for cloud in CLOUDS:
            figs = [r[cloud] for r in mine if r.get(cloud, {}).get("count")]
            n = sum(f["count"] for f in figs)
            false = sum(round(f["outlier_fraction"] * f["count"]) for f in figs)
            entry[cloud] = {
                "points": int(n),
                "rms_inliers_um_worst": _worst(f.get("rms_inliers_um") for f in figs),
                "rms_um_worst": _worst(f.get("rms_um") for f in figs),
                "false_fraction_worst": _worst(f.get("outlier_fraction") for f in figs),
                "false_points": int(false),
                "false_fraction": (false / n) if n else None,
            }
        counts = Counter()
        causes = {"false_before": Counter(), "turned_away": Counter()}
        true_turned = 0
        off_model = 0
        for r in mine:
            counts.update(r["counts"])
            off_model += r.get("off_model", 0)
            for key in causes:
                causes[key].update(r["causes"].get(key, {}))
            true_turned += r["causes"].get("turned_away_true_edges", 0)
        counts.pop("off_model", None)  # none before registration
        entry["kinds"] = dict(counts)  # the model-free cloud's and what the scan set aside
        entry["off_model"] = off_model  # of those drop-outs and steps, after registration
        entry["causes"] = {k: dict(v) for k, v in causes.items()}
        entry["turned_away_true_edges"] = true_turned
        mf = entry["model_free"]
        entry["within_target"] = bool(
            (mf["rms_inliers_um_worst"] is None
             or mf["rms_inliers_um_worst"] <= TARGET_EDGE_RMS_UM)
            and (mf["false_fraction_worst"] is None
                 or mf["false_fraction_worst"] < TARGET_EDGE_OUTLIERS))
        parts[name] = entry
    return {"target": {"rms_inliers_um": TARGET_EDGE_RMS_UM,
                       "false_fraction_below": TARGET_EDGE_OUTLIERS,
                       "false_mm": EDGE_OUTLIER_MM, "cloud": "model_free"},
            "met": all(p["within_target"] for p in parts.values()),
            "parts": parts}


def _worst(values):
    values = [v for v in values if v is not None and math.isfinite(v)]
    return max(values) if values else None


def run(out_dir, quick: bool = False) -> dict:
    """Run the benchmark; write ``edges.json`` and ``edges.png`` into ``out_dir``."""
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cell = load_cell()
    names = QUICK_PARTS if quick else (*PROCEDURAL_PARTS, *REFERENCE_PARTS)
    t_start = time.perf_counter()
    rows = []
    with threadpool_limits(limits=1, user_api="blas"):
        for name in names:
            part = _part(name)
            count = (QUICK_SCANS if quick else
                     REFERENCE_SCANS if name in REFERENCE_PARTS else SCANS_PER_PART)
            for seed, values in enumerate(_misplacements(name, count)):
                rows.append(scan_row(part, cell, values, seed))
                _progress(rows[-1])
    result = {"quick": quick, "seed": SEED,
              "kinds": {int(k): v for k, v in EDGE_KIND_NAMES.items()},
              "scans": rows, "wall_s": round(time.perf_counter() - t_start, 1)}
    result["summary"] = _summary(rows)
    result = write_json(out_dir / "edges.json", result)  # an empty set's RMS is NaN: null
    _plot(result, out_dir / "edges.png")
    return result


def _plot(result: dict, path: pathlib.Path) -> None:
    plt = pyplot()
    parts = result["summary"]["parts"]
    names = list(parts)
    x = np.arange(len(names))
    fig, axes = plt.subplots(3, 1, figsize=(max(10, 1.1 * len(names) + 3), 13))
    width = 0.27
    colors = {"before": "lightcoral", "model_free": "tab:blue", "with_model": "tab:green"}
    labels = {"before": "before (turned-away points kept)", "model_free": "model-free (scan's own)",
              "with_model": "with the registered model"}
    for k, cloud in enumerate(CLOUDS):
        rms = [parts[n][cloud]["rms_inliers_um_worst"] or np.nan for n in names]
        axes[0].bar(x + (k - 1) * width, rms, width, color=colors[cloud], label=labels[cloud])
        false = [100 * (parts[n][cloud]["false_fraction_worst"] or 0.0) for n in names]
        axes[1].bar(x + (k - 1) * width, false, width, color=colors[cloud], label=labels[cloud])
    axes[0].axhline(TARGET_EDGE_RMS_UM, color="k", ls=":", lw=1)
    axes[0].set_yscale("log")  # the faceted domes' 330 um before beside 15-30 um
    axes[0].set_ylabel("worst scan's RMS to the true edges, um, log\n(inliers; none: no "
                       "points)")
    axes[1].axhline(100 * TARGET_EDGE_OUTLIERS, color="k", ls=":", lw=1)
    axes[1].set_ylabel(f"worst scan's points beyond {EDGE_OUTLIER_MM:g} mm, %")
    kinds = [k for k in result["kinds"].values() if k != "off_model"]
    bottom = np.zeros(len(names))
    cmap = plt.get_cmap("tab10")
    for i, kind in enumerate(kinds):
        counts = np.array([parts[n]["kinds"].get(kind, 0) for n in names], dtype=float)
        axes[2].bar(x, counts, 0.6, bottom=bottom, color=cmap(i), label=kind)
        bottom += counts
    for xi, n, top in zip(x, names, bottom):
        if parts[n]["off_model"]:
            axes[2].annotate(f"{parts[n]['off_model']} off the model", (xi, top), ha="center",
                             va="bottom", fontsize=7)
    axes[2].set_ylabel("edge points per kind, all scans\n(model-free; text: set aside after "
                       "registration)")
    for ax in axes:
        ax.set_xticks(x)
        ax.set_xticklabels(names, rotation=30, ha="right", fontsize=8)
        ax.legend(fontsize=7)
    axes[0].set_title("Edges at soft creases and on walls: per part (dotted: the target)")
    save_figure(fig, path, dpi=90)
