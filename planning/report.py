"""The plan's ranking and files: ``plans/<part>/plan.json``, ``catalogue.csv``,
``summary.json`` and ``report.html`` with a picture of each part's chosen scan.

Ranking (best first): a candidate whose pose fixes every axis (observable) before one that
does not; then fewer free axes; then the smallest largest sigma, as 3 sigma over the act
tolerance (``planning.evaluate.score``, compared in tenths of the tolerance, finer
differences being the noise of one pass); then a verdict to act on before one flagged; then
the faster pass; then the order the candidates were made in (centred, flat, resting faces;
turns ascending; presets fastest first). A pass that failed comes last.
"""
from __future__ import annotations

import csv
import html
import json
import math
from pathlib import Path

import numpy as np

from planning.evaluate import score
from scanner_core.fileio import save_json_atomic
from scanner_core.scanplan import PLAN_FORMAT

__all__ = ["rank", "write_outputs", "AXES"]

AXES = ("tx_mm", "ty_mm", "tz_mm", "rx_deg", "ry_deg", "rz_deg")


def rank(items, tolerance_mm: float, tolerance_deg: float) -> list:
    """`items` ((key, Candidate, result) triples in their made order), best first."""
    def order(indexed):
        i, (_, cand, result) = indexed
        if result.get("status") != "done":
            return (2, 0, 0.0, 0, 0.0, i)
        pose = result["pose"]
        s = score(result, tolerance_mm, tolerance_deg)
        return (0 if pose["observable"] else 1, len(pose["free_axes"]),
                round(s, 1) if math.isfinite(s) else math.inf, 0 if pose["act"] else 1,
                -result["speed_mm_s"], i)
    return [item for _, item in sorted(enumerate(items), key=order)]


def write_outputs(out, entries, per_part, results, *, tolerance_mm: float,
                  tolerance_deg: float) -> dict:
    """Rank each part's candidates and write every file; returns the summary (also
    ``summary.json``): per part its status, chosen candidate and sigmas, or its reason."""
    out = Path(out)
    (out / "plans").mkdir(parents=True, exist_ok=True)
    rows = []
    for entry in entries:
        if entry.part is None:
            rows.append({"part": entry.name, "status": "broken", "reason": entry.error,
                         "file": entry.path.name})
            continue
        info = per_part[entry.name]
        items = rank([(k, c, results.get(k, {"status": "error", "reason": "not computed"}))
                      for k, c in info["candidates"]], tolerance_mm, tolerance_deg)
        plan = _plan(entry, items, info["left_out"], tolerance_mm, tolerance_deg)
        folder = out / "plans" / entry.name
        folder.mkdir(parents=True, exist_ok=True)
        save_json_atomic(folder / "plan.json", plan)
        row = {"part": entry.name, "file": entry.path.name, "candidates": len(items),
               "failed": sum(r.get("status") != "done" for _, _, r in items)}
        if plan["chosen"] is None:
            row.update(status="no scan", reason=plan["reason"])
        else:
            chosen = plan["chosen"]
            predicted = chosen["predicted"]
            row.update(status="every axis fixed" if predicted["observable"] else "axes free",
                       grasp=chosen["grasp"]["name"], turn_deg=chosen["pass_direction_deg"],
                       preset=chosen["preset"], act=predicted["act"],
                       free_axes="; ".join(predicted["free_axes"]), score=predicted["score"],
                       surface_seen=predicted["surface_seen"],
                       edge_profiles=predicted["edge_profiles"],
                       **{a: predicted["std"][a] for a in AXES})
            best = items[0][2]
            if "preview" in best:
                row["picture"] = _picture(folder / "best.png", entry.name, chosen, best)
        rows.append(row)
    summary = {"parts": len(entries), "broken": sum(r["status"] == "broken" for r in rows),
               "every_axis_fixed": sum(r["status"] == "every axis fixed" for r in rows),
               "rows": rows}
    _csv(out / "catalogue.csv", rows)
    save_json_atomic(out / "summary.json", summary)
    (out / "report.html").write_text(_html(rows, out))
    return summary


def _plan(entry, items, left_out, tolerance_mm, tolerance_deg) -> dict:
    plan = {"format": PLAN_FORMAT, "part": entry.name, "source": str(entry.path),
            "units": entry.units, "mesh_sha256": entry.mesh.digest,
            "tolerance": {"mm": tolerance_mm, "deg": tolerance_deg}, "chosen": None,
            "candidates": [], "left_out": left_out}
    for key, cand, result in items:
        plan["candidates"].append({
            "grasp": cand.grasp, "pass_direction_deg": cand.turn_deg, "preset": cand.preset,
            "key": key, **_predicted(result, tolerance_mm, tolerance_deg)})
    key, cand, best = items[0] if items else (None, None, {})
    if best.get("status") != "done":
        plan["reason"] = ("no candidate fits the inspection volume" if not items else
                          f"no candidate gave a pose: {best.get('reason')}")
        return plan
    plan["chosen"] = {"grasp": {"name": cand.grasp, "base": cand.base.tolist()},
                      "pass_direction_deg": cand.turn_deg,
                      "nominal_grasp": cand.nominal.tolist(), "preset": cand.preset,
                      "speed_mm_s": best["speed_mm_s"], "fps": best["fps"],
                      "predicted": _predicted(best, tolerance_mm, tolerance_deg)}
    return plan


def _predicted(result: dict, tolerance_mm, tolerance_deg) -> dict:
    if result.get("status") != "done":
        return {"status": result.get("status", "error"), "reason": result.get("reason")}
    s = score(result, tolerance_mm, tolerance_deg)
    pose = result["pose"]
    return {"status": "done", "observable": pose["observable"], "act": pose["act"],
            "free_axes": pose["free_axes"], "std": pose["std"], "flags": pose["flags"],
            "score": round(s, 4) if math.isfinite(s) else None,
            **{k: result[k] for k in ("frames", "points", "edge_points", "edge_profiles",
                                      "surface_seen")},
            "cost": result.get("cost")}


def _picture(path: Path, name: str, chosen: dict, result: dict) -> str:
    """The chosen scan's cloud seen from the sensor (x_T, y_T, coloured by z_T) and from the
    side (y_T, z_T), its edge points in red, its sigmas in the title; a PNG."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cloud, edges = np.asarray(result["preview"]), np.asarray(result["preview_edges"])
    fig, (top, side) = plt.subplots(1, 2, figsize=(8, 3.6), gridspec_kw={"width_ratios": [1, 1]})
    for ax, (i, j) in ((top, (0, 1)), (side, (0, 2))):
        if len(cloud):
            ax.scatter(cloud[:, i], cloud[:, j], c=cloud[:, 2], s=1, cmap="viridis")
        if len(edges):
            ax.scatter(edges[:, i], edges[:, j], c="red", s=2)
        ax.set_xlabel("xyz"[i] + "_T (mm)")
        ax.set_ylabel("xyz"[j] + "_T (mm)")
        ax.set_aspect("equal", adjustable="datalim")
    side.invert_yaxis()  # z_T points down
    std = chosen["predicted"]["std"]
    words = ", ".join(f"{a.split('_')[0]} " + ("free" if std[a] is None else
                      f"{std[a] * 1e3:.1f} {'um' if a.endswith('mm') else 'mdeg'}") for a in AXES)
    fig.suptitle(f"{name}: {chosen['grasp']['name']}, turned {chosen['pass_direction_deg']:g}"
                 f" deg, {chosen['preset']}\nsigma {words}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return f"plans/{path.parent.name}/{path.name}"


def _csv(path: Path, rows: list[dict]) -> None:
    columns = ["part", "status", "grasp", "turn_deg", "preset", "act", "free_axes", *AXES,
               "score", "surface_seen", "edge_profiles", "candidates", "failed", "reason",
               "file"]
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)


def _html(rows: list[dict], out: Path) -> str:
    cells = []
    for r in rows:
        sig = "".join(f"<td>{'' if r.get(a, '') in ('', None) else f'{r[a] * 1e3:.1f}'}</td>"
                      if a in r else "<td></td>" for a in AXES)
        pic = (f'<img src="{html.escape(r["picture"])}" width="480">' if r.get("picture")
               else html.escape(r.get("reason") or ""))
        what = (f"{r.get('grasp', '')}, {r.get('turn_deg', '')} deg, {r.get('preset', '')}"
                if r.get("grasp") else "")
        cells.append(f"<tr><td>{html.escape(r['part'])}</td><td>{html.escape(r['status'])}"
                     f"</td><td>{html.escape(what)}</td>{sig}<td>{pic}</td></tr>")
    head = "".join(f"<th>{a.split('_')[0]} ({'um' if a.endswith('mm') else 'mdeg'})</th>"
                   for a in AXES)
    return ("<!doctype html><meta charset='utf-8'><title>flyscan plan</title>"
            "<style>td,th{border:1px solid #ccc;padding:3px;font:12px sans-serif}</style>"
            f"<h1>Scan plan: {len(rows)} parts</h1><p>Each part's chosen scan (grasp, turn "
            "about z_T, pass preset), its predicted sigma per axis (blank: free) and its "
            "cloud; plans in plans/PART/plan.json, all candidates there.</p>"
            f"<table><tr><th>part</th><th>status</th><th>scan</th>{head}<th>picture or reason"
            f"</th></tr>{''.join(cells)}</table>\n")


def load_json(path) -> dict:
    return json.loads(Path(path).read_text())
