"""The charts of ``flyscan bench service`` (``benchmarks.service``): ``service.png``, its
targets read from the result it draws."""
from __future__ import annotations

import pathlib

import numpy as np

from benchmarks.results import pyplot, save_figure

__all__ = ["plot", "plot_pose"]


def plot(result: dict, path: pathlib.Path) -> None:
    """``service.png``: per-frame cost, the clouds' latency, memory (top); the pose's latency
    by point count, its path and the registration's stages (bottom)."""
    plt = pyplot()
    frame, live, summary = result["per_frame"], result["passes"], result["summary"]
    ratio = summary["frame_ratio_to_copy"]["target_max"]
    fig, axes = plt.subplots(2, 3, figsize=(15, 9.5))
    (ax0, ax1, ax2), (ax3, ax4, ax5) = axes
    bars = {"copy": frame["copy_ms_median"], "idle frame": frame["idle_frame_ms_median"],
            "pass frame": frame["pass_frame_ms_median"]}
    ax0.bar(list(bars), list(bars.values()), color=["gray", "C1", "C0"])
    ax0.axhline(ratio * frame["copy_ms_median"], color="r", ls="--",
                label=f"target: {ratio:g} x copy")
    ax0.set_ylabel("ms per 1920x1200 frame (median, one thread)")
    ax0.set_title(f"per frame: {frame['ratio_to_copy']:.1f} x copy")
    ax0.legend(fontsize=8)
    latency = np.array(live["latency_ms"]["values"])
    ax1.hist(latency, bins=30, color="C0")
    for value, name, style in ((summary["latency_median_ms"]["target_max"], "target median", "--"),
                               (summary["latency_p99_ms"]["target_max"], "target p99", ":")):
        ax1.axvline(value, color="r", ls=style, label=name)
    ax1.axvline(live["latency_ms"]["median"], color="k", label="median")
    ax1.set_xlabel("last frame of the pass -> cloud received over ZeroMQ, ms")
    ax1.set_ylabel("passes")
    ax1.set_title(f"{live['passes']} passes at 162 fps: median {live['latency_ms']['median']:.1f} ms, "
                  f"p99 {live['latency_ms']['p99']:.1f} ms")
    ax1.legend(fontsize=8)
    ax2.plot(np.arange(1, live["passes"] + 1), live["rss_mb"]["values"], "o-", ms=3)
    ax2.set_xlabel("pass")
    ax2.set_ylabel("process RSS, MB")
    ax2.set_title(f"memory: {100 * live['rss_mb']['growth']:+.1f} %, dropped frames "
                  f"{live['frames_dropped'] + live['queue_overflows']}")
    plot_pose(result["pose"], ax3, ax4, ax5, at_end=result.get("pose_at_pass_end"))
    save_figure(fig, path, dpi=100)


def plot_pose(pose: dict, ax_points, ax_path, ax_stages, at_end: dict | None = None) -> None:
    """The pose's latency against the point count per part (and, crossed, with the pose
    computed at the pass's end); its path and the registration's stages per part
    (medians)."""
    rows = [r for r in pose["rows"] if r["pose_published_ms"] is not None]
    end_rows = [] if at_end is None else [r for r in at_end["rows"]
                                          if r["pose_published_ms"] is not None]
    for k, name in enumerate(pose["parts"]):
        mine = [r for r in rows if r["part"] == name]
        ax_points.scatter([r["points"] for r in mine], [r["pose_published_ms"] for r in mine],
                          s=18, color=f"C{k}", label=name)
        coarse = [r for r in mine if r["coarse"] or r["ambiguous"]]
        ax_points.scatter([r["points"] for r in coarse], [r["pose_published_ms"] for r in coarse],
                          s=60, facecolors="none", edgecolors=f"C{k}")
        late = [r for r in end_rows if r["part"] == name]
        ax_points.scatter([r["points"] for r in late], [r["pose_published_ms"] for r in late],
                          s=14, marker="x", color=f"C{k}", alpha=0.5,
                          label=f"{name}, at the pass's end" if k == 0 else None)
    target_ms, target_points = pose["target"]["p95_ms_max"], pose["target"]["points_up_to"]
    ax_points.axhline(target_ms, color="r", ls="--", label=f"target p95 {target_ms:g} ms")
    ax_points.axvline(target_points, color="gray", ls=":")
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullLocator

    ax_points.set_xscale("log")
    ax_points.set_yscale("log")
    for axis, ticks, label in (
            (ax_points.xaxis, (500, 1_000, 2_000, 5_000, 10_000, 20_000, 50_000, 100_000),
             lambda v, _: f"{v / 1000:g}k"),
            (ax_points.yaxis, (10, 20, 50, 100, 150, 200, 500, 1_000, 2_000, 5_000, 10_000),
             lambda v, _: f"{v:g}")):
        axis.set_major_locator(FixedLocator(ticks))
        axis.set_minor_locator(NullLocator())
        axis.set_major_formatter(FuncFormatter(label))
    ax_points.set_ylim(bottom=min([100.0] + [0.8 * r["pose_published_ms"]
                                             for r in rows + end_rows]))
    ax_points.set_xlabel("points in the scan")
    ax_points.set_ylabel("last frame -> pose on ZeroMQ, ms")
    within = pose["pose_published_ms_up_to_target_points"]
    late = "" if at_end is None else (
        f"; x: the pose at the pass's end, "
        f"{at_end['pose_published_ms_up_to_target_points'].get('p95') or float('nan'):.0f} ms")
    ax_points.set_title(f"pose latency, p95 up to {target_points // 1000}k points "
                        f"{within.get('p95') or float('nan'):.0f} ms\n(ringed: coarse or "
                        f"ambiguous{late})", fontsize=9)
    ax_points.legend(fontsize=7)
    for ax, key, title in ((ax_path, "path_ms_median", "the pose's path (median per part)"),
                           (ax_stages, "stages_ms_median", "registration's stages (median)")):
        names = list(pose["by_part"])
        stages = list(dict.fromkeys(k for p in pose["by_part"].values() for k in p[key]))
        bottom = np.zeros(len(names))
        for j, stage in enumerate(stages):
            values = np.array([pose["by_part"][n][key].get(stage, 0.0) for n in names])
            ax.bar(names, values, bottom=bottom, label=stage, color=f"C{j % 10}")
            bottom += values
        ax.set_ylabel("ms")
        ax.set_title(title, fontsize=9)
        ax.legend(fontsize=7)
        ax.tick_params(axis="x", labelrotation=20, labelsize=8)
