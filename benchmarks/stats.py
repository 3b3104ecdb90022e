"""The small statistics the benchmarks' summaries are made of, and a figure judged against its
target: one definition each, so that a p95 or a rate means the same in every summary."""
from __future__ import annotations

import numpy as np
from scipy import stats as _scipy_stats

__all__ = ["spread", "fraction", "lower_95", "judged", "PERCENTILE"]

#: The high percentile of `spread`.
PERCENTILE = 95


def spread(values) -> dict:
    """n, median, p95 and max of the finite values (None and NaN left out)."""
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=np.float64)
    if len(v) == 0:
        return {"n": 0, "median": None, "p95": None, "max": None}
    return {"n": int(len(v)), "median": float(np.median(v)),
            "p95": float(np.percentile(v, PERCENTILE)), "max": float(v.max())}


def fraction(flags) -> float | None:
    """The share of true flags; None for none."""
    flags = list(flags)
    return sum(bool(f) for f in flags) / len(flags) if flags else None


def lower_95(successes: int, trials: int) -> float:
    """One-sided 95 % Clopper-Pearson lower bound of a success rate."""
    return (float(_scipy_stats.beta.ppf(0.05, successes, trials - successes + 1)) if successes
            else 0.0)


def judged(value, limit, op: str) -> dict:
    """A figure against its target: ``value`` (rounded to 1e-4; None when not measured, never
    met), ``limit``, ``op`` (one of ``>=``, ``<=``, ``<``: value op limit) and ``met``."""
    if value is None:
        return {"value": None, "limit": limit, "op": op, "met": False}
    met = {">=": value >= limit, "<=": value <= limit, "<": value < limit}[op]
    return {"value": round(float(value), 4), "limit": limit, "op": op, "met": bool(met)}
