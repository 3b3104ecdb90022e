"""The pose bench's (c): the calibration of the reported uncertainty. For every trial, the
signed error over the reported standard deviation per axis (free axes, with no sigma, left
out): the share of trials with every axis within `SIGMA_BOUND` sigma, and the factor by which
the sigmas would have to be inflated to reach `TARGET_CALIBRATED`."""
from __future__ import annotations

import numpy as np

from benchmarks.parts import AXES
from benchmarks.stats import fraction, judged
from benchmarks.targets import SIGMA_BOUND

__all__ = ["TARGET_CALIBRATED", "calibration", "calibration_summary", "max_abs_z",
           "result_key"]

#: Every axis within SIGMA_BOUND reported sigma in at least this share of the trials.
TARGET_CALIBRATED = 0.99


def calibration(rows: list[dict]) -> dict:
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
        for i, axis in enumerate(AXES):
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


def calibration_summary(cal: dict, config: str, basin_trials: list[dict]) -> dict:
    """The summary's ``calibration``: `cal` (`calibration` of `config`'s trials) against the
    target, and the basin's registrations (`basin_trials`) beside it."""
    summary = {
        "config": config,
        "within_3_sigma": judged(cal["all"]["within"], TARGET_CALIBRATED, ">="),
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
    done = [r for r in basin_trials if not r.get("refused")]
    basin_cal = calibration(done)
    distinct = list({result_key(r): r for r in done}.values())
    summary["basin_registrations"] = {
        **{k: basin_cal["all"][k] for k in ("trials", "within", "worst_axis_z_max")
           if k in basin_cal["all"]},
        "distinct_results": len(distinct),
        "distinct_results_within": fraction([max_abs_z(r) <= SIGMA_BOUND for r in distinct]),
        # The poses a robot would act on: those without any flag.
        "unflagged_distinct_results_within": fraction(
            [max_abs_z(r) <= SIGMA_BOUND for r in distinct if not r.get("flags")]),
    }
    return summary


def max_abs_z(row: dict) -> float:
    """The largest |error| / reported sigma over a trial's axes with a sigma (0 if none)."""
    z = [abs(v) for v in row.get("z") or () if v is not None and np.isfinite(v)]
    return float(max(z)) if z else 0.0


def result_key(row: dict) -> tuple:
    """A registration's result to 0.1 um / 0.1 mdeg on its scan: starts that land on the
    same minimum share it."""
    error = [*row["translation_um"], *row["rotation_mdeg"]]
    return (row["part"], row["scan"], row["kind"], *np.round(error, 1).tolist())
