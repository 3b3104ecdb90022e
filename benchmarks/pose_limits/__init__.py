"""Where the scan's methods fail: edge and pose error as the conditions worsen.

Five factors, each grown from the reference cell until the method breaks, one simulated pass
(``simulator.session.run_simulated_scan``) per level, part and trial:

- **noise**: the image's read noise (``ImageModel.read_noise_dn``);
- **pass speed**: the pass's nominal speed at the reference frame rate, so fewer profiles per
  mm (each row records their spacing, how many fall on the part, and whether ``flyscan scan``
  would refuse the pass for too few);
- **saturation**: the stripe's peak (``ImageModel.stripe_peak_dn``) past the sensor's full
  scale: saturated columns are measured from their flanks (the stripe's saturation fit) until
  the flanks clip too;
- **marker hidden**: the LED hidden in the right mirror for a growing fraction of the part's
  passage (0 to 1), then in the left mirror too (1 to 2: at 2 only the direct view is left).
  The simulated cell's mirror strip is narrowed (the truth only: the scanner keeps its
  calibration), so the marker is rendered in that view only while it stays inside the
  narrowed strip;
- **symmetry**: a cylinder with an off-centre blind hole whose offset shrinks to 0, where the
  part turns freely about its axis.

The edge cloud is scored against the CAD's sharp edges, its drop-outs also against the
outline (``simulator.evaluate.edge_accuracy``), the pose against the true grasp
(``report["ground_truth"]["pose_error"]``). Errors count only along the motions the pose
reports as constrained (a free motion has no sigma: its error is the misplacement it cannot
see). Each run gets a verdict:

``refused``
    the pass gave no scan, the pose was refused, or the command line refuses the pass (too few
    profiles along the part);
``flagged``
    the pose came back with flags or not observable;
``confidently wrong``
    no flag, and the error along the axes beyond 3 reported sigma is itself above the issue's
    target (20 um, 20 mdeg): silent garbage;
``within its sigma``
    no flag, an error above target, but the part of it beyond 3 sigma is not (the reported
    std says the pose is that uncertain);
``sigma miss``
    no flag, within target, but some axis beyond 3 reported sigma (harmless, but the sigma
    does not bound the error);
``ok``
    within target and within 3 sigma.

A flagged run whose constrained axes are wrong beyond 3 sigma and above target is listed too
(``flagged_but_unbounded``): the flag warns, but not about those axes. For a pose with a free
turn, ``free_axis_error_um`` is the error at the turn's axis, which the turn does not move.

A factor's pose break is the first level where some run is not ``ok`` or ``sigma miss``; its
edge break the first level where the edges miss their target (30 um RMS, fewer than 5 % beyond
0.5 mm), or vanish. The summary says where each breaks and how the pose behaved there.

The full run scans the demo block and the reference part `REFERENCE_PART` with the two
`TRIALS` (misplacement and camera seed) per level; the quick run (CI, under a minute) the demo
block only, three levels per factor, one trial. ``run(out_dir)`` writes ``pose_limits.json``
and ``pose_limits.png`` into ``out_dir`` and returns the dict.

The modules: `benchmarks.pose_limits.conditions` (the factors, the part and cell of each
level), `.levels` (one pass at one level: its row), `.verdicts` (the pose's figures and
verdict, the edges' verdict), `.summary` (where each factor breaks), `.plots` (the chart);
this one runs them and writes the figures.
"""
from __future__ import annotations

import os
import pathlib
import time

from threadpoolctl import threadpool_limits

from benchmarks.parts import REFERENCE_PART, bench_part
from benchmarks.pose_limits.conditions import (FACTORS, SYM_RADIUS_MM, Factor, condition,
                                               symmetric_part)
from benchmarks.pose_limits.levels import QUICK_TRIALS, TRIALS, demo_part, progress, run_level
from benchmarks.pose_limits.plots import plot
from benchmarks.pose_limits.summary import factor_summary
from benchmarks.pose_limits.verdicts import (GRACEFUL, USABLE, VERDICTS, pose_figures,
                                             pose_verdict)
from benchmarks.results import write_json
from benchmarks.targets import (EDGE_OUTLIER_MM, SIGMA_BOUND, TARGET_EDGE_OUTLIERS,
                                TARGET_EDGE_RMS_UM, TARGET_ROTATION_MDEG, TARGET_TRANSLATION_UM)
from simulator.cell import load_cell

__all__ = ["run", "FACTORS", "Factor", "symmetric_part", "condition", "run_level",
           "pose_figures", "pose_verdict", "demo_part", "TRIALS", "VERDICTS", "USABLE",
           "GRACEFUL", "SYM_RADIUS_MM",
           "TARGET_TRANSLATION_UM", "TARGET_ROTATION_MDEG", "TARGET_EDGE_RMS_UM",
           "TARGET_EDGE_OUTLIERS", "SIGMA_BOUND"]


def run(out_dir, quick: bool = False, *, seed_offset: int = 0) -> dict:
    """Run the failure-mode benchmark; write ``pose_limits.json`` and ``pose_limits.png``.

    Parameters
    ----------
    out_dir : path-like
        Output directory (created if missing).
    quick : bool
        The demo block only, `Factor.quick_levels`, one trial: for CI (under a minute).
    seed_offset : int
        Added to every trial's camera seed.

    Returns
    -------
    dict
        The figures written to ``pose_limits.json``; ``summary`` says where each factor breaks.
    """
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cell = load_cell()
    trials = QUICK_TRIALS if quick else TRIALS
    evaluate = not quick
    t_start = time.perf_counter()
    load_before = os.getloadavg()
    rows: list[dict] = []
    with threadpool_limits(limits=1):
        parts = [demo_part()] + ([] if quick else [bench_part(REFERENCE_PART)])
        # The reference level is the same pass for every factor but the symmetry: run it once.
        reference: dict = {}
        for factor in FACTORS:
            levels = factor.quick_levels if quick else factor.levels
            for part in parts if factor.name != "symmetry" else parts[:1]:
                for trial in trials:
                    for level in levels:
                        seed = trial["seed"] + seed_offset
                        key = (part.name, seed, tuple(trial["misplacement"]))
                        if factor.name != "symmetry" and level == levels[0] and key in reference:
                            row = dict(reference[key], factor=factor.name, level=level)
                        else:
                            row = run_level(factor.name, level, part, cell,
                                            misplacement=trial["misplacement"], seed=seed,
                                            evaluate=evaluate)
                            if factor.name != "symmetry" and level == levels[0]:
                                reference[key] = row
                        rows.append(row)
                        progress(row)

    factors = {}
    for factor in FACTORS:
        levels = factor.quick_levels if quick else factor.levels
        factors[factor.name] = factor_summary(
            factor, [r for r in rows if r["factor"] == factor.name], levels)
    wrong = [dict(case, factor=name) for name, s in factors.items()
             for case in s["confidently_wrong"]]
    result = {
        "quick": quick,
        "trials": [dict(t, seed=t["seed"] + seed_offset) for t in trials],
        "parts": [p.name for p in parts] + ["cylinder_hole_* (symmetry)"],
        "factors": {f.name: {"label": f.label, "unit": f.unit,
                             "levels": list(f.quick_levels if quick else f.levels)}
                    for f in FACTORS},
        "targets": {"translation_um": TARGET_TRANSLATION_UM,
                    "rotation_mdeg": TARGET_ROTATION_MDEG,
                    "edge_rms_um": TARGET_EDGE_RMS_UM,
                    "edge_outlier_fraction": TARGET_EDGE_OUTLIERS,
                    "edge_outlier_mm": EDGE_OUTLIER_MM, "sigma_bound": SIGMA_BOUND},
        "definitions": {
            "translation_um": "length of the translation error of the {T} origin along the "
                              "axes the pose reports as constrained (a sigma), um",
            "rotation_mdeg": "length of the rotation-vector error about the constrained axes, mdeg",
            "max_sigmas": "largest |error| / reported std over the constrained axes",
            "unbounded_translation_um": "length of the translation error along the axes "
                                        "beyond 3 reported sigma, um (likewise rotation, mdeg)",
            "free_axis_error_um": "for a free turn, the error of the point its axis passes "
                                  "through, across the axis, um",
            "verdicts": {
                "refused": "no scan, pose refused, or the command line refuses the pass",
                "flagged": "pose flags non-empty or not observable",
                "confidently wrong": "no flag, and the error along the axes beyond 3 reported "
                                     "sigma is above target",
                "within its sigma": "no flag, error above target, but not the part of it "
                                    "beyond 3 reported sigma",
                "sigma miss": "no flag, within target, but beyond 3 reported sigma",
                "ok": "within target and within 3 reported sigma"},
            "pose_break": "first level where some run is neither ok nor a sigma miss",
            "edge_break": f"first level whose edges miss {TARGET_EDGE_RMS_UM:g} um RMS or "
                          f"{100 * TARGET_EDGE_OUTLIERS:g} % beyond {EDGE_OUTLIER_MM:g} mm, or "
                          "vanish",
        },
        "rows": rows,
        "summary": {
            "factors": {name: {"statement": s["statement"], "pose_break": s["pose_break"],
                               "edge_break": s["edge_break"],
                               "first_flagged_or_refused": s["first_flagged_or_refused"],
                               "confidently_wrong_levels": sorted({c["level"] for c in
                                                                   s["confidently_wrong"]}),
                               # Refused by `flyscan scan`, confidently wrong through the
                               # service or the library, which do not check the spacing.
                               "confidently_wrong_past_cli_levels": sorted(
                                   {c["level"] for c in s["confidently_wrong_past_cli"]})}
                        for name, s in factors.items()},
            "confidently_wrong": wrong,
            "flagged_but_unbounded": [dict(case, factor=name) for name, s in factors.items()
                                      for case in s["flagged_but_unbounded"]],
            "graceful": not wrong,
        },
        "details": factors,
        "elapsed_s": round(time.perf_counter() - t_start, 1),
        "loadavg_1min": {"before": load_before[0], "after": os.getloadavg()[0]},
    }
    result = write_json(out_dir / "pose_limits.json", result)
    plot(result, out_dir / "pose_limits.png")
    return result
