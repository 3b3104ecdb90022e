"""The pose benchmark's quick set (the procedural block): its files, its structure, and figures
that would show a broken registration: accuracy on the block, the basin at small
misplacements, the side by side's same start and target."""
import json
import math

import numpy as np
import pytest

from benchmarks import pose as bench
from benchmarks.pose.calibration import max_abs_z, result_key
from benchmarks.pose.trials import recommend

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# The demo block with its edges (the default configuration): well inside these, or broken.
BLOCK_TRANSLATION_UM = 50.0
BLOCK_ROTATION_MDEG = 50.0


@pytest.fixture(scope="module")
def quick_bench(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_pose")
    lines = []
    result = bench.run(out, quick=True, progress=lines.append)
    return out, result, lines


def test_writes_json_and_charts(quick_bench):
    out, result, lines = quick_bench
    written = json.loads((out / "pose.json").read_text())
    assert written["summary"] == json.loads(json.dumps(result["summary"]))
    for name in ("pose.png", "pose_calibration.png"):
        assert (out / name).read_bytes()[:8] == PNG_MAGIC
    for key in ("cpu_count", "python", "numpy", "date"):
        assert key in written["machine"]
    assert written["quick"] is True and written["settings"]["parts"] == ["block"]
    assert len(lines) >= bench.QUICK_SCANS_PER_PART  # progress for every scan


def test_one_trial_per_scan_and_configuration(quick_bench):
    _, result, _ = quick_bench
    trials = result["trials"]
    keys = {(t["scan"], t["config"]) for t in trials}
    assert len(keys) == len(trials) == bench.QUICK_SCANS_PER_PART * len(bench.QUICK_CONFIGS)
    assert [c["config"] for c in result["configs"]] == list(bench.QUICK_CONFIGS)
    for t in trials:
        assert t["refused"] is None
        assert math.isfinite(t["time_ms"]) and t["time_ms"] > 0
        assert len(t["translation_um"]) == 3 and len(t["rotation_mdeg"]) == 3
        norm = math.sqrt(sum(v * v for v in t["translation_um"]))
        assert t["translation_norm_um"] == pytest.approx(norm, rel=1e-4, abs=1e-3)
        # A sigma for every axis the pose observes, none for a free one.
        assert (None in t["std_um_mdeg"]) == bool(t["free_axes"])
    for c in result["configs"]:
        assert c["time_ms"]["n"] == bench.QUICK_SCANS_PER_PART


def test_the_block_is_registered_accurately_with_its_edges(quick_bench):
    _, result, _ = quick_bench
    default = next(c for c in result["configs"] if c["config"] == bench.DEFAULT_CONFIG)
    assert default["not_observable"] < default["trials"]
    # Every trial, free axes included: with its edges the block has none to slide along.
    assert default["all_trials"]["translation_um"]["max"] < BLOCK_TRANSLATION_UM
    assert default["all_trials"]["rotation_mdeg"]["max"] < BLOCK_ROTATION_MDEG
    assert default["converged"] == 1.0
    # Its visible faces are mostly level: without the edges it slides and turns (unless a
    # tilt shows a step's side), and says so: no configuration gives a confident wrong pose.
    surfaces = next(c for c in result["configs"] if c["config"] == "mesh")
    assert surfaces["not_observable"] >= 1
    assert all(c["confident_wrong"] == 0 for c in result["configs"])
    assert result["summary"]["model"]["keep"] in ("mesh", "predicted")


def test_basin_converges_at_small_misplacements(quick_bench):
    _, result, _ = quick_bench
    levels = result["basin"]["levels"]
    assert [(lv["mm"], lv["deg"]) for lv in levels] == list(bench.QUICK_BASIN_LEVELS)
    smallest = levels[0]["displaced start"]
    assert smallest["trials"] == bench.QUICK_BASIN_TRIALS
    assert smallest["success_rate"] == 1.0
    basin = result["summary"]["basin"]
    assert basin["trials"] == len(bench.QUICK_BASIN_LEVELS) * bench.QUICK_BASIN_TRIALS
    assert basin["success_rate"]["met"] == (basin["success_rate"]["value"] >= bench.TARGET_BASIN)
    # With its edges the block fixes every axis at its true pose: every trial is in scope.
    assert all(i["observable_at_truth"] for i in result["scans"])
    assert basin["all_trials"]["trials"] == basin["trials"]
    assert basin["unobservable_scans"]["trials"] == 0


def test_basin_target_leaves_out_scans_with_a_free_axis(quick_bench, tmp_path):
    """A trial on a scan that is not observable at its true pose leaves the target's scope,
    stays in the rate over every trial, and is scored along the axes its pose reports."""
    out, result, _ = quick_bench
    written = json.loads((out / "pose.json").read_text())
    row = written["basin"]["trials"][0]
    assert row["success"] and not row["free_axes"]  # in the target's scope as it stands
    own_before = result["summary"]["basin"]["own_report"]
    row.update(scan_observable=False, success=False, free_axes=["along y_T"],
               flags=["not observable: along y_T"],
               translation_um=[1.0, 500.0, 1.0], std_um_mdeg=[5.0, None, 5.0, 9.0, 9.0, 9.0])
    (tmp_path / "pose.json").write_text(json.dumps(written))
    basin = bench.rebuild(tmp_path)["summary"]["basin"]
    before = result["summary"]["basin"]
    assert basin["trials"] == before["trials"] - 1
    assert basin["converged"] == before["converged"] - 1
    assert basin["all_trials"]["trials"] == before["trials"]
    assert basin["all_trials"]["converged"] == before["converged"] - 1
    unobservable = basin["unobservable_scans"]
    assert unobservable["trials"] == 1
    assert unobservable["flagged"] == 1 and unobservable["confident_wrong"] == 0
    # By each trial's own report, a pose with a free axis leaves the scope too.
    assert basin["own_report"]["trials"] == own_before["trials"] - 1
    assert basin["own_report"]["misses"] == own_before["misses"]
    # 500 um along the free y_T is not held against it; its known axes are within limits.
    assert unobservable["converged_known_axes"] == int(
        np.linalg.norm(row["rotation_mdeg"]) < bench.SUCCESS_DEG * 1e3)


def test_calibration_is_consistent(quick_bench):
    _, result, _ = quick_bench
    cal = result["calibration"][bench.DEFAULT_CONFIG]
    assert cal["all"]["trials"] == bench.QUICK_SCANS_PER_PART
    worst = [max(abs(v) for v in z if v is not None) for z in cal["z"]]
    within = sum(w <= bench.SIGMA_BOUND for w in worst) / len(worst)
    assert cal["all"]["within"] == pytest.approx(within)
    assert cal["all"]["inflation_needed"] >= 1.0
    summary = result["summary"]["calibration"]
    assert summary["within_3_sigma"]["met"] == (within >= bench.TARGET_CALIBRATED)
    # The basin's registrations count too, each against its own sigma; starts that land on
    # the same minimum are one distinct result.
    basin = [r for r in result["basin"]["trials"] if not r.get("refused")]
    basin_worst = [max(abs(v) for v in r["z"] if v is not None) for r in basin]
    registrations = summary["basin_registrations"]
    assert registrations["trials"] == len(basin)
    assert registrations["within"] == pytest.approx(
        sum(w <= bench.SIGMA_BOUND for w in basin_worst) / len(basin))
    assert registrations["worst_axis_z_max"] == pytest.approx(max(basin_worst))
    assert 1 <= registrations["distinct_results"] <= len(basin)
    unflagged = {result_key(r): r for r in basin if not r["flags"]}
    if unflagged:
        assert registrations["unflagged_distinct_results_within"] == pytest.approx(
            np.mean([max_abs_z(r) <= bench.SIGMA_BOUND for r in unflagged.values()]))


def test_side_by_side_has_every_method_or_a_note(quick_bench):
    _, result, _ = quick_bench
    side = result["side_by_side"]
    (case,) = side["cases"]
    methods = case["methods"]
    assert "flyscan" in methods and "flyscan surfaces, all points" in methods
    for library, names in (("open3d", ["open3d point-to-plane"]),
                           ("small_gicp", ["small_gicp plane ICP", "small_gicp GICP"])):
        assert (library in side["skipped"]) != all(n in methods for n in names)
    for name, m in methods.items():
        assert m["total_ms"] == pytest.approx(m["preprocess_ms"] + m["register_ms"], rel=0.05)
        if not name.startswith("flyscan"):
            assert case["ratios"][f"flyscan/{name}"] == pytest.approx(
                methods["flyscan"]["total_ms"] / m["total_ms"], rel=1e-4)
    assert methods["flyscan"]["translation_um"] < BLOCK_TRANSLATION_UM


def test_the_edge_cloud_is_scored_against_the_cad_edges(quick_bench):
    """The demo block's edges (sharp, no chamfer): near their CAD edges, few strays, and the
    summary's verdicts follow from the per-scan figures."""
    _, result, _ = quick_bench
    scored = [s["edges"] for s in result["scans"]]
    assert len(scored) == bench.QUICK_SCANS_PER_PART and all(e["count"] > 20 for e in scored)
    assert np.median([e["rms_inliers_um"] for e in scored]) < bench.TARGET_EDGE_RMS_UM
    assert max(e["outlier_fraction"] for e in scored) < bench.TARGET_EDGE_OUTLIERS
    edges = result["summary"]["edges"]
    worst = max(e["rms_inliers_um"] for e in scored)
    assert edges["rms_inliers_um_worst"]["value"] == pytest.approx(worst, rel=1e-3)
    assert edges["rms_inliers_um_worst"]["met"] == (worst <= bench.TARGET_EDGE_RMS_UM)
    assert edges["outlier_fraction_worst"]["met"] == (
        max(e["outlier_fraction"] for e in scored) < bench.TARGET_EDGE_OUTLIERS)


def test_model_choice_compares_times_on_the_same_scans():
    """On a tie in accuracy, the predicted cloud is kept when it is faster scan by scan (half
    the time here), not when it is 10 % slower on every scan; two parts ten times apart in
    time do not enter the comparison."""
    summary = {"confident_wrong": 0, "within_target": 0.9,
               "translation_um": {"p95": 5.0}, "rotation_mdeg": {"p95": 9.0},
               "time_ms": {"median": 0.0}}
    configs = {"mesh+edges": dict(summary), "predicted+edges": dict(summary)}

    def trials(pred_factor):
        rows = []
        for part, n, ms in (("fast", 5, 60.0), ("slow", 4, 900.0)):
            for i in range(n):
                rows.append({"config": "mesh+edges", "part": part, "scan": i,
                             "time_ms": ms, "refused": False})
                rows.append({"config": "predicted+edges", "part": part, "scan": i,
                             "time_ms": ms * pred_factor, "refused": False})
        return rows

    slower = recommend(configs, trials(1.1))
    assert slower["keep"] == "mesh"
    assert slower["time_ratio_predicted_to_mesh"] == pytest.approx(1.1)
    faster = recommend(configs, trials(0.5))
    assert faster["keep"] == "predicted"
    assert faster["time_ratio_predicted_to_mesh"] == pytest.approx(0.5)


def test_basin_own_report_counts_a_miss_that_claims_every_axis(quick_bench, tmp_path):
    """A trial whose pose reports no free axis but lands off the truth (a rival minimum) is
    a miss in the target's scope and by its own report, listed with its flags."""
    out, result, _ = quick_bench
    written = json.loads((out / "pose.json").read_text())
    row = written["basin"]["trials"][0]
    row.update(success=False, translation_um=[1.0, 2.0, 1.0], rotation_mdeg=[0.0, 0.0, 142.0],
               rotation_angle_mdeg=142.0, flags=["ambiguous: a pose 151 mdeg away fits as well"])
    (tmp_path / "pose.json").write_text(json.dumps(written))
    basin = bench.rebuild(tmp_path)["summary"]["basin"]
    before = result["summary"]["basin"]
    assert basin["converged"] == before["converged"] - 1
    own = basin["own_report"]
    assert own["converged"] == before["own_report"]["converged"] - 1
    (miss,) = [m for m in own["misses"] if m not in before["own_report"]["misses"]]
    assert miss["rotation_mdeg"] == 142.0 and miss["flags"] == row["flags"]
