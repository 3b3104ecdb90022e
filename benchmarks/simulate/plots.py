"""The chart of ``bench simulate`` (``simulate.png``): runtime against points, throughput, the
simplification study, and the side by side with Open3D."""
from __future__ import annotations

import pathlib

import numpy as np

from benchmarks.results import pyplot, save_figure
from benchmarks.simulate.sweeps import TARGET_MRAYS_PER_S, xy

__all__ = ["plot", "plot_side_by_side"]


def plot(result: dict, path: pathlib.Path) -> None:
    """``simulate.png``."""
    plt = pyplot()
    rows, fits = result["rows"], result["fits"]
    fig, axes = plt.subplots(1, 4, figsize=(22.5, 5.2))
    ax = axes[0]
    for i, name in enumerate(result["builds"]):
        colour = f"C{i}"
        label = f"{name} ({result['builds'][name]['faces']} tri)"
        for prefix, style, tag in (("", "o-", ""), ("reference_", "x--", " reference")):
            x, y = xy(rows, name, prefix)
            order = np.argsort(x)
            ax.plot(np.asarray(x)[order] / 1e6, np.asarray(y)[order], style, color=colour,
                    ms=4, lw=1, label=label + tag if prefix == "" else None,
                    alpha=1.0 if prefix == "" else 0.6)
    ax.set_xlabel("points generated (millions)")
    ax.set_ylabel("runtime (s)")
    ax.set_title("runtime against points (solid: 2 threads, packets;\n"
                 "dashed: reference loop, embreex, 1 thread)")
    ax.legend(fontsize=7)
    ax = axes[1]
    for i, name in enumerate(result["builds"]):
        sel = sorted((r for r in rows if r["part"] == name), key=lambda r: r["rays_cast"])
        ax.semilogx([r["rays_cast"] for r in sel], [r["mrays_per_s"] for r in sel], "o-",
                    color=f"C{i}", ms=4, label=f"{name} (R2 {fits[name]['fast']['r2']:.3f})")
    ax.axhline(TARGET_MRAYS_PER_S, color="k", ls=":", lw=1, label="target 8 Mrays/s")
    ax.set_xlabel("rays cast")
    ax.set_ylabel("Mrays/s (with the visibility check)")
    ax.set_title("throughput")
    ax.legend(fontsize=7)
    ax = axes[2]
    for i, study in enumerate(result["simplification"]):
        faces = [study["full"]["faces"]] + [lv["faces"] for lv in study["levels"]]
        rms = [1e-3] + [max(lv["rms_um"], 1e-3) for lv in study["levels"]]
        ax.loglog(faces, rms, "o-", color=f"C{i + 5}", ms=4, label=study["part"])
        if study["chosen"]:
            ax.plot(study["chosen"]["faces"], max(study["chosen"]["rms_um"], 1e-3), "*",
                    color=f"C{i + 5}", ms=14,
                    label=f"  chosen: {study['chosen']['faces']} tri, sweep "
                          f"{100 * study['sweep_time_saved']:.0f} % faster")
    ax.axhline(5.0, color="k", ls=":", lw=1, label="5 um RMS")
    ax.set_xlabel("triangles")
    ax.set_ylabel("RMS point-to-plane deviation from the full mesh (um; 0 drawn at 0.001)")
    ax.set_title("simplification: coarsest mesh within 5 um")
    ax.legend(fontsize=7)
    plot_side_by_side(axes[3], result["open3d"])
    save_figure(fig, path, dpi=110)


def plot_side_by_side(ax, side: dict) -> None:
    """Bars: whole processes and ray work, flyscan against Open3D (medians, each run a dot)."""
    if "skipped" in side:
        ax.text(0.5, 0.5, "Open3D comparison skipped:\n" + side["skipped"], ha="center",
                va="center", wrap=True, fontsize=9, transform=ax.transAxes)
        ax.set_axis_off()
        return
    m, runs = side["median"], side["runs"]
    groups = [("whole process\n(wall)", m["flyscan_wall_s"], m["open3d_wall_s"],
               [r["wall_s"] for r in runs["flyscan"]], [r["wall_s"] for r in runs["open3d"]]),
              ("whole process\n(CPU, 2 cores)", m["flyscan_cpu_s"], m["open3d_cpu_s"],
               [r["cpu_s"] for r in runs["flyscan"]], [r["cpu_s"] for r in runs["open3d"]]),
              ("ray work: sweep /\ncast_rays + test_occlusions", m["flyscan_sweep_s"],
               m["open3d_ray_calls_s"], [r["report"]["elapsed_s"] for r in runs["flyscan"]],
               [r["report"]["ray_calls_s"] for r in runs["open3d"]])]
    x = np.arange(len(groups))
    width = 0.38
    for offset, index, colour, label in ((-width / 2, 1, "C0", "flyscan simulate"),
                                         (width / 2, 2, "C3", f"Open3D {side['open3d_version']}")):
        ax.bar(x + offset, [g[index] for g in groups], width, color=colour, alpha=0.8,
               label=label)
        for i, g in enumerate(groups):
            ax.plot(np.full(len(g[index + 2]), x[i] + offset), g[index + 2], "k.", ms=3)
    for i, g in enumerate(groups):
        ax.text(x[i], max(g[1], g[2]) * 1.04, f"x{g[1] / g[2]:.2f}", ha="center", fontsize=9)
    ax.set_xticks(x, [g[0] for g in groups], fontsize=8)
    ax.set_ylabel("seconds (median of runs in turn; dots: each run)")
    target = side["target_whole_process"]
    ax.set_title(f"side by side: {side['part']} ({side['faces']} tri), "
                 f"{side['rays_cast'] / 1e6:.1f} M rays\nwhole process x{target['value']:.2f} "
                 f"(target <= {target['limit']})")
    ax.legend(fontsize=7)

