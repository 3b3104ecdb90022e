"""The pose bench's charts: ``pose.png`` (accuracy against time per configuration, the basin,
the calibration's histogram and QQ plot, the side by side) and ``pose_calibration.png`` (per
configuration and axis, |error| / sigma of every trial)."""
from __future__ import annotations

import pathlib

import numpy as np
from scipy import stats

from benchmarks.parts import AXES, MISPLACEMENT_UP_TO_DEG, MISPLACEMENT_UP_TO_MM
from benchmarks.pose.basin import BASIN_TARGET_LEVEL, TARGET_BASIN
from benchmarks.pose.trials import DEFAULT_CONFIG, SUCCESS_DEG, SUCCESS_MM, fmt
from benchmarks.results import pyplot, save_figure
from benchmarks.targets import SIGMA_BOUND, TARGET_ROTATION_MDEG, TARGET_TRANSLATION_UM

__all__ = ["plot", "plot_calibration"]


def plot(result: dict, path: pathlib.Path) -> None:
    plt = pyplot()
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
    save_figure(fig, path, dpi=100)


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
                 f"misplacements up to {MISPLACEMENT_UP_TO_MM:g} mm / {MISPLACEMENT_UP_TO_DEG:g} deg")
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


def plot_calibration(result: dict, path: pathlib.Path) -> None:
    """Per configuration and per axis: |error| / sigma of every trial."""
    plt = pyplot()
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
        ax.set_xticks(range(6), list(AXES))
        within = cal["all"]["within"]
        ax.set_title(f"{name}\nall axes within 3 sigma: "
                     f"{'n/a' if within is None else f'{within:.0%}'}, inflate x"
                     f"{fmt(cal['all']['inflation_needed'])}", fontsize=9)
    axes[0, 0].set_ylabel("|error| / reported sigma per trial (free axes left out)")
    save_figure(fig, path, dpi=100)
