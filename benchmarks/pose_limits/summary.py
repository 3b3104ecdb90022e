"""The summary of ``bench pose_limits``: per factor, where the pose and the edges break, how
the pose behaved there, and the statement that says it in one sentence."""
from __future__ import annotations

from benchmarks.parts import AXES
from benchmarks.pose_limits.conditions import Factor
from benchmarks.pose_limits.verdicts import GRACEFUL, USABLE, VERDICTS
from benchmarks.targets import TARGET_ROTATION_MDEG, TARGET_TRANSLATION_UM

__all__ = ["factor_summary"]


def _pose_reason(row: dict) -> str:
    pose = row["pose"]
    if row["verdict"] == "refused":
        return row["cli_refusal"] or pose["refused"]
    if row["verdict"] == "flagged":
        why = "; ".join(pose["flags"]) or "not observable"
        if pose["unbounded"]:
            axis = AXES.index(pose["worst_axis"])
            why += (f" (and axis {pose['worst_axis']}, reported as constrained, is off by "
                    f"{abs(pose['error_um_mdeg'][axis]):.0f} {'um' if axis < 3 else 'mdeg'} at "
                    f"{pose['max_sigmas']:.1f} sigma)")
        return why
    parts = []
    if (pose["translation_um"] or 0.0) > TARGET_TRANSLATION_UM:
        parts.append(f"translation {pose['translation_um']:.1f} um > {TARGET_TRANSLATION_UM:g} um")
    if (pose["rotation_mdeg"] or 0.0) > TARGET_ROTATION_MDEG:
        parts.append(f"rotation {pose['rotation_mdeg']:.1f} mdeg > {TARGET_ROTATION_MDEG:g} mdeg")
    if pose["max_sigmas"] is not None:
        parts.append(f"worst axis {pose['worst_axis']} at {pose['max_sigmas']:.1f} sigma")
    return ", ".join(parts)


def _level_summary(rows: list[dict]) -> dict:
    verdicts = [r["verdict"] for r in rows]
    worst = max(verdicts, key=VERDICTS.index)
    return {
        "runs": len(rows),
        "verdicts": verdicts,
        "worst_verdict": worst,
        "pose_usable": all(v in USABLE for v in verdicts),
        "edges_within_target": all(r["edges_within_target"] for r in rows),
    }


def factor_summary(factor: Factor, rows: list[dict], levels) -> dict:
    by_level = {lv: [r for r in rows if r["level"] == lv] for lv in levels}
    pose_break = edge_break = first_flag = None
    for lv in levels:
        runs = by_level[lv]
        if pose_break is None and any(r["verdict"] not in USABLE for r in runs):
            broken = [r for r in runs if r["verdict"] not in USABLE]
            worst = max(broken, key=lambda r: VERDICTS.index(r["verdict"]))
            pose_break = {
                "level": lv, "verdict": worst["verdict"], "part": worst["part"],
                "seed": worst["seed"], "why": _pose_reason(worst),
                # flags non-empty, not observable, or refused: told rather than silent
                "flagged_or_refused": all(r["verdict"] in ("flagged", "refused") for r in broken),
                "graceful": all(r["verdict"] in GRACEFUL for r in broken),
            }
        if edge_break is None and any(not r["edges_within_target"] for r in runs):
            bad = next(r for r in runs if not r["edges_within_target"])
            edge_break = {"level": lv, "part": bad["part"], "seed": bad["seed"],
                          "why": bad["edges_miss"],
                          "at_reference": lv == levels[0]}
        if first_flag is None and any(r["verdict"] in ("flagged", "refused") for r in runs):
            first_flag = lv
    wrong = [{"level": r["level"], "part": r["part"], "seed": r["seed"],
              "why": _pose_reason(r), "error_um_mdeg": r["pose"]["error_um_mdeg"],
              "sigmas": r["pose"]["sigmas"]}
             for r in rows if r["verdict"] == "confidently wrong"]
    flagged_unbounded = [
        {"level": r["level"], "part": r["part"], "seed": r["seed"], "why": _pose_reason(r),
         "error_um_mdeg": r["pose"]["error_um_mdeg"], "sigmas": r["pose"]["sigmas"],
         "free_axis_error_um": r["pose"]["free_axis_error_um"]}
        for r in rows if r["verdict"] == "flagged" and r["pose"]["unbounded"]]
    # The command line refuses these passes; the service and the library do not check.
    past_cli = [{"level": r["level"], "part": r["part"], "seed": r["seed"],
                 "error_um_mdeg": r["pose"]["error_um_mdeg"], "sigmas": r["pose"]["sigmas"]}
                for r in rows if r["cli_refusal"] and r["pose_verdict"] == "confidently wrong"]
    misses = [{"level": r["level"], "part": r["part"], "seed": r["seed"],
               "worst_axis": r["pose"]["worst_axis"], "sigmas": r["pose"]["max_sigmas"]}
              for r in rows if r["verdict"] == "sigma miss"]
    return {
        "unit": factor.unit,
        "levels": list(levels),
        "statement": _statement(factor, levels, pose_break, edge_break, first_flag, wrong,
                                past_cli),
        "per_level": {str(lv): _level_summary(by_level[lv]) for lv in levels},
        "pose_break": pose_break,
        "edge_break": edge_break,
        "first_flagged_or_refused": first_flag,
        "confidently_wrong": wrong,
        "flagged_but_unbounded": flagged_unbounded,
        "confidently_wrong_past_cli": past_cli,
        "sigma_misses": misses,
    }


def _statement(factor: Factor, levels, pose_break, edge_break, first_flag, wrong,
               past_cli) -> str:
    """Where a factor breaks, in one sentence."""
    unit = f" {factor.unit}" if factor.unit else ""
    if pose_break is None:
        text = f"the pose holds up to {levels[-1]:g}{unit}"
    else:
        text = (f"the pose breaks at {pose_break['level']:g}{unit} ({pose_break['verdict']}: "
                f"{pose_break['why']})")
    text += (f"; first flagged or refused at {first_flag:g}{unit}" if first_flag is not None
             else "; never flagged or refused")
    if wrong:
        text += ("; confidently wrong at " + ", ".join(sorted({f"{c['level']:g}{unit}"
                                                               for c in wrong})))
    if past_cli:
        text += ("; refused by the command line, but confidently wrong where nothing checks the "
                 "spacing (the service, the library) at " + ", ".join(sorted({f"{c['level']:g}{unit}" for c in past_cli})))
    if edge_break is None:
        text += f"; the edges hold up to {levels[-1]:g}{unit}"
    else:
        where = "already at" if edge_break["at_reference"] else "from"
        text += (f"; the edges miss their target {where} {edge_break['level']:g}{unit} "
                 f"({edge_break['why']})")
    return text
