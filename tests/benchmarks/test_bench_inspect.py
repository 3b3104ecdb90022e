"""``flyscan bench inspect`` in its quick form: its files, and its figures as the rows say."""
import json

import numpy as np
import pytest

from benchmarks.inspection import SEEN_SPACING_MM, pod_fit, seen_piece
from flyscan import main


def test_the_pod_fit_finds_a_known_curve():
    """Hits drawn from a known logistic curve in ln(size): its a90 within the fit's error."""
    rng = np.random.default_rng(0)
    sizes = np.repeat([0.5, 1.0, 2.0, 4.0, 8.0], 400)
    b0, b1 = -1.0, 3.0
    hits = rng.uniform(size=len(sizes)) < 1.0 / (1.0 + np.exp(-(b0 + b1 * np.log(sizes))))
    fit = pod_fit(sizes, hits)
    assert fit["a90"] == pytest.approx(np.exp((np.log(9.0) - b0) / b1), rel=0.1)
    assert fit["a90_95"] > fit["a90"]
    assert pod_fit([1.0, 2.0, 3.0, 4.0], [True] * 4)["a90"] is None  # no slope to fit


def test_a_fault_is_seen_by_two_profiles_across_one_piece_of_it():
    """A difference 2 mm wide on two neighbouring sheets 1.2 mm apart is seen; the same two
    chords 12.7 mm apart (a plug through a stepped part, one face a profile) are two regions
    of one profile each, as the check would group them, and not seen."""
    along = np.arange(0.0, 2.0, SEEN_SPACING_MM)

    def chords(second_at):
        points = np.vstack([np.c_[along, np.zeros_like(along), np.zeros_like(along)],
                            np.c_[along, np.full_like(along, 1.2), np.full_like(along, second_at)]])
        frames = np.repeat([7, 8], len(along))
        return points, frames, np.ones(len(points))

    near = seen_piece(*chords(0.0), sampling_mm=1.2, point_step_mm=0.18)
    assert near["seen"] and near["seen_profiles"] == 2
    assert near["seen_chord_mm"] == pytest.approx(2 * len(along) * SEEN_SPACING_MM)
    apart = seen_piece(*chords(12.7), sampling_mm=1.2, point_step_mm=0.18)
    assert not apart["seen"] and apart["seen_profiles"] == 1


def test_quick_bench_inspect(tmp_path):
    assert main(["bench", "inspect", "--quick", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "inspect.json").read_text())
    assert (tmp_path / "inspect.png").stat().st_size > 10_000
    summary, rows = result["summary"], result["rows"]
    good = [r for r in rows if r["kind"] == "good" and r["posed"] and r["observable"]]
    assert summary["good_picks"] == len(good)
    loose = [r for r in rows if r["kind"] == "good" and r["posed"] and not r["observable"]]
    assert summary["good_picks_not_observable"] == len(loose)
    assert len(good) + len(loose) >= 3
    assert summary["false_rejects"] == sum(r["conforms"] is False for r in good) == 0
    assert summary["acted_on_detected"] == 0  # a detected fault is never acted on
    double = summary["faults"]["double"]  # caught: detected, or its scan failed
    assert double["trials"] == 1 and double["acted_on"] == 0
    assert double["detected"] + double["scan_failed_or_refused"] >= 1
    for kind in ("debris", "chip", "variant", "hole", "filled", "bend"):
        mine = [r for r in rows if r["kind"] == kind]
        assert summary["faults"][kind]["detected"] == sum(r["conforms"] is False for r in mine)
        seen = [r for r in mine if r.get("seen") and r["observable"]]  # at a fixed pose
        assert summary["faults"][kind]["seen"] == len(seen)
        assert all(r["seen_profiles"] >= 2 for r in seen)
    # a 6 mm hole drilled through the block: seen by the profiles, and found with no points
    (hole,) = [r for r in rows if r["kind"] == "hole" and r["size_mm"] == 6.0]
    assert hole["seen"] and hole["conforms"] is False and "missing_material" in hole["failing"]
    (pinhole,) = [r for r in rows if r["kind"] == "hole" and r["size_mm"] == 1.0]
    assert not pinhole["seen"]  # 1 mm across: at most one profile crosses it
    # the model drilled 6 mm, the gripper holding the block without the hole: the plug's
    # face, where the model has none, is extra material
    (filled,) = [r for r in rows if r["kind"] == "filled" and r["size_mm"] == 6.0]
    assert filled["seen"] and filled["conforms"] is False
    assert "extra_material" in filled["failing"]
    assert summary["check_ms"]["median"] > 0
    assert summary["check_ms"]["timed_picks"] == len(result["timed"]) >= 1  # apart, one core


def test_bench_inspect_timing_quick(tmp_path):
    """``--timing``: the check's time alone, its summary as its picks say; refused elsewhere."""
    assert main(["bench", "inspect", "--timing", "--quick", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "inspect_timing.json").read_text())
    assert (tmp_path / "inspect_timing.png").stat().st_size > 10_000
    timed, summary = result["timed"], result["summary"]
    assert len(timed) == summary["picks"] >= 1
    assert all(t["points"] > 1000 and t["check_ms"] > 0.0 for t in timed)
    per_20k = [t["check_ms"] * 20_000 / t["points"] for t in timed]
    assert summary["per_20000_points_median"] == pytest.approx(float(np.median(per_20k)))
    assert summary["check_ms_median"] == pytest.approx(
        float(np.median([t["check_ms"] for t in timed])))
    # each pick's scan checked again: the least of all its runs, held to its budget
    assert all(len(t["repeats_ms"]) == result["settings"]["repeats"] >= 1 for t in timed)
    assert all(t["check_ms_least"] == min([t["check_ms"], *t["repeats_ms"]]) for t in timed)
    budget = [t["check_ms_least"] * 20_000 / max(t["points"], 20_000) for t in timed]
    assert summary["least_per_budget_20000_p95"] == pytest.approx(
        float(np.percentile(budget, 95)))
    if len({t["points"] for t in timed}) > 1:  # a line through the least times, at 20 000
        line = np.polyfit([t["points"] for t in timed], [t["check_ms_least"] for t in timed], 1)
        assert summary["least_fit_ms_at_20000"] == pytest.approx(np.polyval(line, 20_000))
    else:  # one size of scan: no line
        assert summary["least_fit_ms_at_20000"] is None
    assert main(["bench", "scan", "--timing", "--out", str(tmp_path)]) == 2
