"""The chart of ``bench pose_limits`` (``pose_limits.png``): per factor, the worst run's error
and its error in reported sigmas at every level, the verdicts marked, the breaks drawn."""
from __future__ import annotations

import pathlib

import numpy as np

from benchmarks.pose_limits.verdicts import VERDICTS
from benchmarks.results import pyplot, save_figure
from benchmarks.targets import SIGMA_BOUND, TARGET_EDGE_RMS_UM, TARGET_TRANSLATION_UM

__all__ = ["plot"]

_VERDICT_STYLE = {
    "ok": ("o", "none"), "sigma miss": ("o", "none"), "within its sigma": ("s", "none"),
    "flagged": ("^", "full"), "refused": ("X", "full"), "confidently wrong": ("*", "full"),
}
# Log-scale ranges of the two rows: error (um or mdeg) and error in reported sigmas.
_ERROR_RANGE = (0.3, 3e4)
_SIGMA_RANGE = (1e-2, 1e3)


def _worst(rows: list[dict]) -> dict | None:
    """The run that shows a level at its worst: the worst verdict, then the largest error."""
    if not rows:
        return None
    return max(rows, key=lambda r: (VERDICTS.index(r["verdict"]),
                                    max(r["pose"]["translation_um"] or 0.0,
                                        r["pose"]["rotation_mdeg"] or 0.0)))


def plot(result: dict, path: pathlib.Path) -> None:
    plt = pyplot()
    from matplotlib.lines import Line2D

    names = list(result["factors"])
    fig, axes = plt.subplots(2, len(names), figsize=(4.4 * len(names), 9.0), sharey="row",
                             squeeze=False)
    styles = ["-", "--", ":"]
    parts = list(dict.fromkeys(r["part"] for r in result["rows"] if r["factor"] != "symmetry"))
    lo, hi = _ERROR_RANGE
    slo, shi = _SIGMA_RANGE
    for j, name in enumerate(names):
        info = result["factors"][name]
        levels = info["levels"]
        x = np.arange(len(levels))
        rows = [r for r in result["rows"] if r["factor"] == name]
        top, bottom = axes[0, j], axes[1, j]
        groups = [None] if name == "symmetry" else parts
        for gi, part in enumerate(groups):
            ls = styles[gi % len(styles)]
            sel = [_worst([r for r in rows if r["level"] == lv
                           and (part is None or r["part"] == part)]) for lv in levels]

            def series(get):
                return np.array([get(r) if r is not None and get(r) is not None else np.nan
                                 for r in sel], dtype=float)

            t = series(lambda r: r["pose"]["translation_um"])
            rot = series(lambda r: r["pose"]["rotation_mdeg"])
            edge = series(lambda r: r["edges"].get("rms_um"))
            st = series(lambda r: r["pose"]["std_translation_um"])
            sr = series(lambda r: r["pose"]["std_rotation_mdeg"])
            sig = series(lambda r: r["pose"]["max_sigmas"])
            top.plot(x, np.clip(edge, lo, hi), ls, color="C2", lw=1.4)
            top.plot(x, np.clip(SIGMA_BOUND * st, lo, hi), ls, color="C0", lw=0.8, alpha=0.35)
            top.plot(x, np.clip(SIGMA_BOUND * sr, lo, hi), ls, color="C1", lw=0.8, alpha=0.35)
            top.plot(x, np.clip(t, lo, hi), ls, color="C0", lw=1.4)
            top.plot(x, np.clip(rot, lo, hi), ls, color="C1", lw=1.4)
            bottom.plot(x, np.clip(sig, slo, shi), ls, color="k", lw=1.0)
            for k, r in enumerate(sel):
                if r is None:
                    continue
                marker, fill = _VERDICT_STYLE[r["verdict"]]
                color = "red" if r["verdict"] == "confidently wrong" else "k"
                mfc = color if fill == "full" else "none"
                worse = np.nanmax([t[k], rot[k]]) if np.isfinite([t[k], rot[k]]).any() else hi
                top.plot(x[k], np.clip(worse, lo, hi), marker, color=color, ms=8, mfc=mfc)
                bottom.plot(x[k], np.clip(sig[k] if np.isfinite(sig[k]) else shi, slo, shi),
                            marker, color=color, ms=8, mfc=mfc)
        for ax in (top, bottom):
            ax.set_yscale("log")
            ax.set_xticks(x)
            ax.set_xticklabels([f"{lv:g}" for lv in levels])
            ax.grid(True, which="major", alpha=0.3)
        top.set_ylim(lo, hi)
        bottom.set_ylim(slo, shi)
        top.axhline(TARGET_TRANSLATION_UM, color="gray", ls=":", lw=1)
        top.axhline(TARGET_EDGE_RMS_UM, color="C2", ls=":", lw=0.8)
        bottom.axhline(SIGMA_BOUND, color="red", ls=":", lw=1)
        if j == 0:
            top.text(x[0], TARGET_TRANSLATION_UM, "pose target 20 um / 20 mdeg", fontsize=7,
                     color="gray", va="top")
            top.text(x[0], TARGET_EDGE_RMS_UM, "edge target 30 um", fontsize=7, color="C2",
                     va="bottom")
            bottom.text(x[0], SIGMA_BOUND, "3 sigma", fontsize=7, color="red", va="bottom")
        s = result["summary"]["factors"][name]
        notes = []
        for brk, color, label in ((s["pose_break"], "red", "pose breaks"),
                                  (s["edge_break"], "C2", "edges miss")):
            if brk is None:
                continue
            k = levels.index(brk["level"])
            for ax in (top, bottom):
                ax.axvline(k + (0.04 if color == "red" else -0.04), color=color, ls="--", lw=1.2,
                           alpha=0.8)
            what = brk["verdict"] if "verdict" in brk else brk["why"]
            notes.append((color, f"{label} at {brk['level']:g}: {what}"))
        for i, (color, text) in enumerate(notes):
            top.text(0.02, 0.97 - 0.06 * i, text, transform=top.transAxes, color=color,
                     fontsize=7.5, va="top", bbox={"fc": "white", "ec": "none", "alpha": 0.8})
        top.set_title(name, fontsize=11)
        bottom.set_xlabel(f"{info['label']}" + (f", {info['unit']}" if info["unit"] else ""),
                          fontsize=8)
    axes[0, 0].set_ylabel("error (worst run per level), um or mdeg")
    axes[1, 0].set_ylabel("worst constrained axis: |error| / reported std")
    handles = [Line2D([], [], color="C0", label="pose translation, um"),
               Line2D([], [], color="C1", label="pose rotation, mdeg"),
               Line2D([], [], color="k", lw=0.8, alpha=0.35, label="3 x reported std"),
               Line2D([], [], color="C2", label="edge RMS, um")]
    handles += [Line2D([], [], ls=styles[i % len(styles)], color="k", label=p)
                for i, p in enumerate(parts)]
    handles += [Line2D([], [], ls="none", marker=m, color="red" if v == "confidently wrong" else "k",
                       mfc=("red" if v == "confidently wrong" else "k") if f == "full" else "none",
                       label=v if v != "ok" else "ok / sigma miss")
                for v, (m, f) in _VERDICT_STYLE.items() if v != "sigma miss"]
    fig.legend(handles=handles, loc="lower center", ncol=6, fontsize=8)
    fig.suptitle("Where the methods fail: edge and pose error as each condition worsens "
                 f"({'quick' if result['quick'] else 'full'} run; symmetry: cylinder family)")
    save_figure(fig, path, dpi=110, rect=(0, 0.07, 1, 0.96))
