"""The verdicts of ``bench pose_limits``: the pose's error along the motions it reports as
constrained, against its reported std and the targets, and the edge cloud against its target
(the verdicts are described in ``benchmarks.pose_limits``)."""
from __future__ import annotations

import math

import numpy as np

from benchmarks.parts import AXES
from benchmarks.targets import (SIGMA_BOUND, TARGET_EDGE_OUTLIERS, TARGET_EDGE_RMS_UM,
                                TARGET_ROTATION_MDEG, TARGET_TRANSLATION_UM)

__all__ = ["VERDICTS", "USABLE", "GRACEFUL", "pose_figures", "pose_verdict", "edge_verdict",
           "finite_or_none"]

VERDICTS = ("ok", "sigma miss", "within its sigma", "flagged", "refused", "confidently wrong")
#: Verdicts at which the pose is still usable as reported.
USABLE = ("ok", "sigma miss")
#: Verdicts that are not silent garbage.
GRACEFUL = ("ok", "sigma miss", "within its sigma", "flagged", "refused")


def finite_or_none(x, digits: int = 3):
    """`x` rounded to `digits`, or None when it is None or not finite."""
    if x is None:
        return None
    x = float(x)
    return round(x, digits) if math.isfinite(x) else None



def pose_figures(report: dict) -> dict:
    """Pose error along the constrained motions, the reported std, and the verdict's inputs,
    from a simulated scan's report (``run_simulated_scan``)."""
    pose = report.get("pose")
    out = {"refused": None, "flags": [], "observable": None, "free_axes": [],
           "translation_um": None, "rotation_mdeg": None, "std_translation_um": None,
           "std_rotation_mdeg": None, "max_sigmas": None, "worst_axis": None,
           "unbounded_translation_um": None, "unbounded_rotation_mdeg": None, "unbounded": None,
           "error_um_mdeg": None, "sigmas": None, "coarse": None, "free_axis_error_um": None}
    if pose is None:
        out["refused"] = "no pose"
        return out
    if "refused" in pose:
        out["refused"] = pose["refused"]
        return out
    error = report["ground_truth"]["pose_error"]
    values = np.array(error["translation_um"] + error["rotation_mdeg"], dtype=np.float64)
    sigmas = error["sigmas"]
    constrained = np.array([s is not None for s in sigmas])
    std = pose["std"]
    keys = ("tx_mm", "ty_mm", "tz_mm", "rx_deg", "ry_deg", "rz_deg")
    std_values = np.array([std[k] if std[k] is not None else np.nan for k in keys]) * 1e3
    ratio = np.array([s if s is not None else -np.inf for s in sigmas])
    beyond = ratio > SIGMA_BOUND  # constrained axes whose error the reported std does not bound
    worst = int(np.argmax(ratio)) if constrained.any() else None

    def length(values, mask):
        return finite_or_none(np.linalg.norm(values[mask])) if mask.any() else None

    unbounded_t = float(np.linalg.norm(values[:3][beyond[:3]]))
    unbounded_r = float(np.linalg.norm(values[3:][beyond[3:]]))
    out.update({
        "flags": list(pose.get("flags", [])),
        "observable": bool(pose["observable"]),
        "free_axes": [a["label"] for a in pose.get("free_axes", [])],
        "coarse": pose.get("coarse"),
        # Lengths of the error vector along the constrained axes: um at the {T} origin, mdeg.
        "translation_um": length(values[:3], constrained[:3]),
        "rotation_mdeg": length(values[3:], constrained[3:]),
        "std_translation_um": length(std_values[:3], constrained[:3]),
        "std_rotation_mdeg": length(std_values[3:], constrained[3:]),
        "max_sigmas": finite_or_none(ratio[worst]) if worst is not None else None,
        "worst_axis": AXES[worst] if worst is not None else None,
        # The part of the error beyond 3 reported sigma: above target, it is silent garbage
        # unless the pose is flagged.
        "unbounded_translation_um": round(unbounded_t, 3),
        "unbounded_rotation_mdeg": round(unbounded_r, 3),
        "unbounded": bool(unbounded_t > TARGET_TRANSLATION_UM
                          or unbounded_r > TARGET_ROTATION_MDEG),
        "error_um_mdeg": [finite_or_none(v) for v in values],
        "sigmas": sigmas,
        "free_axis_error_um": _free_axis_error(report),
    })
    return out


def _free_axis_error(report: dict) -> float | None:
    """For a pose with a free turn: how far the point of its axis ("through_mm") is from where
    the truth puts it, um: the placement's error regardless of the turn (a cylinder turned
    about its own axis is placed the same)."""
    pose = report["pose"]
    axes = pose.get("free_axes", [])
    # With a free slide as well the axis's point is not defined: only free turns are scored.
    if not axes or any(a.get("kind") != "rotation" or a.get("through_mm") is None for a in axes):
        return None
    error = np.asarray(pose["matrix"]) @ np.linalg.inv(np.asarray(report["ground_truth"]["grasp"]))
    worst = 0.0
    for axis in axes:
        c = np.asarray(axis["through_mm"], dtype=np.float64)
        moved = error[:3, :3] @ c + error[:3, 3] - c
        along = np.asarray(axis["axis"], dtype=np.float64)
        moved -= (moved @ along) * along / (along @ along)  # sliding along the axis: no matter
        worst = max(worst, float(np.linalg.norm(moved)) * 1e3)
    return round(worst, 3)



def pose_verdict(pose: dict) -> str:
    """The verdict (``benchmarks.pose_limits``) of `pose_figures`, before any command-line
    refusal."""
    if pose["refused"]:
        return "refused"
    if pose["flags"] or not pose["observable"]:
        return "flagged"
    if pose["unbounded"]:
        return "confidently wrong"
    over = ((pose["translation_um"] or 0.0) > TARGET_TRANSLATION_UM
            or (pose["rotation_mdeg"] or 0.0) > TARGET_ROTATION_MDEG)
    if over:
        return "within its sigma"
    return "sigma miss" if (pose["max_sigmas"] or 0.0) > SIGMA_BOUND else "ok"


def edge_verdict(edges: dict) -> tuple[bool, str | None]:
    """(within target, why not)."""
    if not edges.get("count"):
        return False, "no edge points"
    why = []
    if edges["rms_um"] > TARGET_EDGE_RMS_UM:
        why.append(f"RMS {edges['rms_um']:.0f} um > {TARGET_EDGE_RMS_UM:g} um")
    if edges["outlier_fraction"] > TARGET_EDGE_OUTLIERS:
        why.append(f"{edges['outlier_fraction']:.0%} beyond 0.5 mm > {TARGET_EDGE_OUTLIERS:.0%}")
    return not why, "; ".join(why) or None

