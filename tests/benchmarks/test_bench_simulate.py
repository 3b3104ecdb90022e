"""The simulator benchmark's quick set: its files, rows consistent with each other, fits
recomputable from the rows, and the lossless levels of the simplification study."""
import importlib.util
import json

import numpy as np
import pytest
import trimesh

from benchmarks import simulate as bench
from benchmarks.simulate.plots import plot_side_by_side
from simulator.parts import part_from_mesh

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

pytest.importorskip("pymeshlab")


@pytest.fixture(scope="module")
def quick_bench(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_simulate")
    lines = []
    result = bench.run(out, quick=True, repeats=1, progress=lines.append)
    return out, result, lines


def test_writes_json_and_png_with_one_row_per_part_and_density(quick_bench):
    out, result, lines = quick_bench
    written = json.loads((out / "simulate.json").read_text())
    assert (out / "simulate.png").read_bytes()[:8] == PNG_MAGIC
    configs = {(r["part"], r["step_mm"], r["rays_per_line"]) for r in written["rows"]}
    assert len(configs) == len(written["rows"]) == 2 * len(bench.QUICK_STEPS_MM) * len(
        bench.QUICK_RAYS_PER_LINE)
    assert set(written["builds"]) == {"block", "block-26k"}
    assert written["builds"]["block-26k"]["faces"] == 64 * written["builds"]["block"]["faces"]
    assert len(lines) >= len(written["rows"])  # progress for every row
    for key in ("cpu_count", "numpy", "date"):
        assert key in written["machine"]


def test_rows_are_consistent_and_agree_with_the_reference_loop(quick_bench):
    _, result, _ = quick_bench
    for row in result["rows"]:
        lines = row["rays_cast"] // row["rays_per_line"]
        assert row["rays_cast"] == lines * row["rays_per_line"] and lines > 0
        assert 0 < row["points"] <= row["first_hits"] <= row["rays_cast"]
        assert row["mrays_per_s"] == pytest.approx(row["rays_cast"] / row["seconds"] / 1e6,
                                                   rel=2e-3)
        # The plain embreex loop finds the same points (robust packets aside: within 0.1 %).
        assert abs(row["reference_points"] - row["points"]) <= 1e-3 * row["points"]
    # The subdivided block has the same surface: the same points at every density.
    by_config = {}
    for row in result["rows"]:
        by_config.setdefault((row["step_mm"], row["rays_per_line"]), []).append(row["points"])
    for counts in by_config.values():
        assert max(counts) - min(counts) <= 1e-3 * max(counts)


def test_fits_and_summary_follow_from_the_rows(quick_bench):
    _, result, _ = quick_bench
    for name, fit in result["fits"].items():
        rows = [r for r in result["rows"] if r["part"] == name]
        x = np.array([r["points"] for r in rows], float)
        y = np.array([r["seconds"] for r in rows], float)
        slope, intercept = np.polyfit(x, y, 1)
        assert fit["fast"]["slope_us_per_point"] == pytest.approx(slope * 1e6, rel=1e-6)
        r2 = 1 - ((y - slope * x - intercept) ** 2).sum() / ((y - y.mean()) ** 2).sum()
        assert fit["fast"]["r2"] == pytest.approx(r2, abs=1e-9)
    summary = result["summary"]
    for key in ("mrays_per_s_big_part", "min_r2", "cost_ratio_at_equal_points"):
        t = summary[key]
        assert t["met"] == (t["value"] >= t["limit"] if t["op"] == ">=" else t["value"] <= t["limit"])
    tp = result["throughput"]
    assert tp["part"] == "block-26k" and len(tp["seconds"]) == bench.THROUGHPUT_RUNS
    assert tp["min_mrays_per_s"] <= tp["median_mrays_per_s"] <= tp["max_mrays_per_s"]
    assert summary["mrays_per_s_big_part"]["value"] == tp["median_mrays_per_s"]
    assert summary["min_r2"]["value"] == pytest.approx(
        min(f["fast"]["r2"] for f in result["fits"].values()), abs=1e-4)


def test_simplification_recovers_the_subdivided_block(quick_bench):
    _, result, _ = quick_bench
    (study,) = result["simplification"]
    assert study["full"]["faces"] == 26240
    levels = study["levels"]
    # Halving back towards the original block changes nothing the scanner sees.
    assert levels[0]["faces"] == 13120 and levels[0]["rms_um"] < 0.01
    chosen = study["chosen"]
    assert chosen is not None and chosen["rms_um"] <= 5.0 and chosen["coverage_change"] <= 0.01
    coarser = [lv for lv in levels if lv["faces"] < chosen["faces"]]
    assert all(lv["rms_um"] > 5.0 or lv["coverage_change"] > 0.01 for lv in coarser)
    assert chosen["faces"] < 1000 and chosen["switched"] <= 0.01 * study["full"]["points"]


# ------------------------------------------------------------------------------------------
# Side by side with Open3D
# ------------------------------------------------------------------------------------------

def test_side_by_side_runs_the_same_sweep_in_both_tools(quick_bench):
    out, result, lines = quick_bench
    side = result["open3d"]
    if importlib.util.find_spec("open3d") is None:
        assert "not installed" in side["skipped"]
        return
    assert side["part"] == "block-26k" and side["faces"] == 26240
    assert side["rays_cast"] == side["open3d_rays_cast"] >= bench.QUICK_SIDE_RAYS * 0.99
    # Robust and non-robust scenes may part on a ray grazing an edge; nothing more.
    assert abs(side["points"] - side["open3d_points"]) <= 1e-3 * side["points"]
    assert abs(side["first_hits"] - side["open3d_first_hits"]) <= 1e-3 * side["first_hits"]
    runs = side["runs"]
    assert len(runs["flyscan"]) == len(runs["open3d"]) == bench.QUICK_SIDE_RUNS
    median = side["median"]
    assert median["flyscan_wall_s"] == np.median([r["wall_s"] for r in runs["flyscan"]])
    assert side["ratios"]["whole_process"] == pytest.approx(
        median["flyscan_wall_s"] / median["open3d_wall_s"], abs=1e-4)
    assert side["ratios"]["ray_calls"] == pytest.approx(
        median["flyscan_sweep_s"] / median["open3d_ray_calls_s"], abs=1e-4)
    # A process is slower than the work inside it.
    for f, o in zip(runs["flyscan"], runs["open3d"]):
        assert f["wall_s"] > f["report"]["elapsed_s"] and o["wall_s"] > o["report"]["sweep_s"]
    target = side["target_whole_process"]
    assert target["met"] == (target["value"] <= bench.TARGET_WHOLE_RATIO)
    assert result["summary"]["open3d_side_by_side"]["whole_process_ratio"] == target
    assert any("side by side" in line for line in lines)


def test_side_by_side_is_skipped_with_a_note_without_open3d(monkeypatch, tmp_path, cell):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "open3d" else real(name, *a))
    part = part_from_mesh(trimesh.creation.box(extents=(20.0, 20.0, 20.0)), name="cube")
    side = bench.side_by_side(part, cell, rays=10_000, runs=1)
    assert set(side) == {"skipped"} and "pip install 'flyscan[bench]'" in side["skipped"]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    plot_side_by_side(ax, side)  # a note instead of bars
    fig.savefig(tmp_path / "skipped.png")
    plt.close(fig)
    assert (tmp_path / "skipped.png").read_bytes()[:8] == PNG_MAGIC


def test_the_open3d_script_sweeps_as_flyscan_does(tmp_path, cell):
    """The yardstick itself: the Open3D script's cloud is flyscan's, ray for ray."""
    pytest.importorskip("open3d")
    from scanner_core.io.ply import read_ply
    from benchmarks import open3d_sweep
    from simulator.virtual_setup import VirtualSetup, predict_cloud

    box = trimesh.creation.box(extents=(40.0, 30.0, 20.0))
    box.apply_translation((0.0, 0.0, 10.0))
    box.apply_transform(trimesh.transformations.rotation_matrix(0.3, [0.2, 0.1, 1.0]))
    part = part_from_mesh(box, name="tilted box", grasp=np.eye(4))
    mesh = tmp_path / "box.stl"
    part.mesh.export(mesh)
    laser, camera = [0.0, -130.0, 400.0], [0.0, 95.0, 439.7]
    cloud = predict_cloud(part, VirtualSetup(laser=laser, camera=camera, step_mm=0.5,
                                             rays_per_line=300))
    out = tmp_path / "o3d.ply"
    assert open3d_sweep.main(["--part", str(mesh), "--laser=0,-130,400",
                              "--camera=0,95,439.7", "--step", "0.5", "--rays", "300",
                              "--out", str(out)]) == 0
    points, fields = read_ply(out)
    ours = cloud.step.astype(np.int64) * 300 + cloud.ray
    theirs = fields["step"].astype(np.int64) * 300 + fields["ray"]
    common, i, j = np.intersect1d(ours, theirs, assume_unique=True, return_indices=True)
    assert len(common) >= 0.999 * max(len(ours), len(theirs)) and len(ours) > 10_000
    np.testing.assert_allclose(points[j], cloud.points[i], atol=2e-3)  # float32 hits
    normals = np.stack([fields[f"n{c}"] for c in "xyz"], axis=1)
    np.testing.assert_allclose(normals[j], cloud.normals[i], atol=1e-5)
