"""The simulator benchmark's quick set: its files, rows consistent with each other, fits
recomputable from the rows, and the lossless levels of the simplification study."""
import json

import numpy as np
import pytest

from service.bench import simulate as bench

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
