"""The charts of ``bench stripe``: ``stripe.png`` (time against error, error against noise, the
reflections, the dynamic range) and ``stripe_scenes.png`` (the photographed lines)."""
from __future__ import annotations

import pathlib

import numpy as np

from benchmarks.results import pyplot, save_figure
from benchmarks.stripe.scenes import TARGET_MEASURED
from benchmarks.stripe.surfaces import TARGET_REFLECTION_ON_STRIPE

__all__ = ["plot", "plot_scenes"]


def plot(result: dict, path: pathlib.Path) -> None:
    """``stripe.png``."""
    plt = pyplot()
    import matplotlib.ticker

    fig, axes = plt.subplots(2, 3, figsize=(18, 10))
    ax0, ax1 = axes[0, 0], axes[0, 1]
    _plot_reflection(result, axes[0, 2])
    _plot_dynamic_range(result, axes[1, 0], axes[1, 1], axes[1, 2])
    noise = np.array(result["noise_levels_dn"])
    crb = np.array([result["crb_px"][str(n)] for n in noise])
    for i, (name, m) in enumerate(result["methods"].items()):
        color = f"C{i}"
        ref = m["at_reference_noise"]
        ax0.plot(m["time_ms"], ref["rms_px"], "o", color=color, label=name)
        ax0.plot(m["time_ms"], m["reference_speckle"]["rms_px"], "o", mfc="none", color=color)
        ax1.plot(noise, [e["rms_px"] for e in m["noise_sweep"]], "o-", color=color, label=name)
    ax0.axvline(result["copy_ms"], color="k", ls="--", label="image.copy()")
    ax0.axhline(result["crb_px"][str(result["reference_noise_dn"])], color="gray", ls=":",
                label="Cramer-Rao bound")
    ax0.set_xscale("log")
    ax0.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax0.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax0.set_xticks([0.1, 0.2, 0.5, 1, 2, 5])
    ax0.set_xlabel("time per 1920x1200 frame, ms (one thread)")
    ax0.set_ylabel("RMS error, px")
    ax0.set_title(f"read noise {result['reference_noise_dn']:g} DN "
                  "(filled: no speckle, open: speckle 0.1)")
    ax0.legend(fontsize=8)
    ax1.plot(noise, crb, "k--", label="Cramer-Rao bound")
    ax1.set_xscale("log")
    ax1.set_yscale("log")
    ax1.set_xlabel("read noise, DN (stripe peak 200 DN, sigma 1.5 px)")
    ax1.set_ylabel("RMS error, px")
    ax1.set_title("error vs noise (no speckle)")
    ax1.legend(fontsize=8)
    save_figure(fig, path, dpi=100)


def _plot_dynamic_range(result: dict, ax_valid, ax_rms, ax_cog) -> None:
    """Valid fraction and RMS error against the stripe's peak, break points marked."""
    import matplotlib.ticker

    dr = result["dynamic_range"]
    peaks = np.array(dr["peaks_dn"])
    rule = dr["break_rule"]
    series = dr["series"]

    def draw(ax_v, ax_r, name, color, ls, label):
        d = series[name]
        rms = np.array([np.nan if r is None else r for r in d["rms_px"]])
        ax_v.plot(peaks, d["valid_fraction"], ls, color=color, label=label, marker=".")
        if ax_r is not None:
            ax_r.plot(peaks, rms, ls, color=color, label=label, marker=".")
        for key, mk in (("low_dn", ">"), ("high_dn", "<")):
            b = d["breaks"][key]
            if b is None:
                continue
            # the break drawn on both panels at the first working (>) / first failing (<) peak
            ax_v.plot([b], [rule["min_valid"]], mk, color=color, ms=9, mec="k")
            if ax_r is not None:
                ax_r.plot([b], [rule["max_rms_px"]], mk, color=color, ms=9, mec="k")

    for i, m in enumerate(m for m in series if series[m]["options"] == {}):
        draw(ax_valid, ax_rms, m, f"C{i}", "-", m)
    draw(ax_cog, None, "cog", "C0", "-", "cog, threshold 20 DN")
    draw(ax_cog, None, "cog auto", "C1", "--", "cog, threshold auto")
    draw(ax_cog, None, "cog, saturation rejected (the earlier default)", "gray", ":",
         "cog, saturation rejected (before)")
    for ax in (ax_valid, ax_rms, ax_cog):
        ax.set_xscale("log")
        ax.axvline(255.0 - result["reference_model"]["background_dn"], color="k", lw=0.8, ls="--")
        ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.set_xlabel("stripe peak above background, DN "
                      "(sigma 1.5 px, noise 3 DN; dashed: full scale)")
    ax_valid.axhline(rule["min_valid"], color="gray", ls=":")
    ax_valid.set_ylabel("valid fraction")
    ax_valid.set_title("valid fraction vs peak (> first working, < first failing)")
    ax_valid.legend(fontsize=7)
    ax_rms.axhline(rule["max_rms_px"], color="gray", ls=":")
    ax_rms.set_yscale("log")
    ax_rms.set_ylabel("RMS error, px")
    ax_rms.set_title("sub-pixel error vs peak (break: valid < 90 % or RMS > 0.1 px)")
    ax_rms.legend(fontsize=7)
    ax_cog.axhline(rule["min_valid"], color="gray", ls=":")
    ax_cog.set_ylabel("valid fraction")
    ax_cog.set_title("cog valid fraction: fixed vs auto floors, and the earlier default")
    ax_cog.legend(fontsize=7)


def _plot_reflection(result: dict, ax) -> None:
    """Fraction of the columns on the true stripe per policy, for each reflection scene."""
    on = result["reflection"]["on_stripe_fraction"]
    kinds = list(on)
    policies = list(next(iter(on.values())))
    width = 0.8 / len(policies)
    for i, policy in enumerate(policies):
        x = np.arange(len(kinds)) + (i - (len(policies) - 1) / 2) * width
        ax.bar(x, [on[k][policy] for k in kinds], width, label=policy, color=f"C{i}")
    ax.axhline(TARGET_REFLECTION_ON_STRIPE, color="k", ls=":", label="target 98 %")
    ax.set_xticks(np.arange(len(kinds)))
    ax.set_xticklabels([f"{k}" for k in kinds])
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("fraction of columns on the true stripe")
    r = result["reflection"]
    ax.set_title(f"reflection at {r['ratio']:g}x, {r['offsets_px'][0]:g}-{r['offsets_px'][1]:g} "
                 f"rows away (glints: every {r['glint']['period']}th column "
                 f"{r['glint']['ratio']:g}x)", fontsize=9)
    ax.legend(fontsize=7)


def plot_scenes(result: dict, path: pathlib.Path) -> None:
    """``stripe_scenes.png``."""
    plt = pyplot()

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(16, 7))
    _scenes_panels(result["photographed_lines"], ax0, ax1)
    cell = result["cell_frames"]
    fig.suptitle(f"stripe on a frame of the reference cell: {cell['stripe_ms']:.3f} ms, "
                 f"{cell['ratio_to_copy']:.2f} x a copy of the frame ({cell['frames']} frames)")
    save_figure(fig, path, dpi=100)


def _scenes_panels(scenes: dict, ax_measured, ax_rms) -> None:
    """Measured share and RMS error per scene, fixed and noise-derived thresholds."""
    names = list(scenes)
    y = np.arange(len(names))
    for i, (key, label) in enumerate((("fixed_20dn", "threshold 20 DN"), ("auto", "auto"))):
        m = [scenes[n][key]["measured_fraction"] for n in names]
        r = [scenes[n][key]["rms_in_sigmas"] or np.nan for n in names]
        ax_measured.barh(y + (i - 0.5) * 0.38, m, 0.38, color=f"C{i}", label=label)
        ax_rms.barh(y + (i - 0.5) * 0.38, r, 0.38, color=f"C{i}", label=label)
        for k, n in enumerate(names):
            f = scenes[n][key]["false_columns"]
            if f:
                ax_measured.text(1.005, k + (i - 0.5) * 0.38, f"{f} false", va="center",
                                 fontsize=7, color=f"C{i}")
    labels = [n + ("" if scenes[n]["held_to_target"] else " (not held)") for n in names]
    for ax in (ax_measured, ax_rms):
        ax.set_yticks(y)
        ax.set_yticklabels(labels, fontsize=8)
        ax.invert_yaxis()
        ax.legend(fontsize=7, loc="lower left")
    ax_measured.axvline(TARGET_MEASURED, color="k", ls=":", label="target 99 %")
    ax_measured.set_xlim(0.0, 1.12)
    ax_measured.set_xlabel("share of the columns holding a stripe measured")
    ax_measured.set_title("lines as photographs show them (640 x 480, 3 frames each)")
    ax_rms.set_xscale("log")
    ax_rms.set_xlabel("RMS error, in the line's own sigmas")
    ax_rms.set_title("error of the measured columns")
