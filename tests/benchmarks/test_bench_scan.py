"""The scan benchmark's quick set: its files, its rows, and the accuracy of the procedural block."""
import json
import math

import pytest

from benchmarks import scan as bench

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
EXPECTED_RUNS = {(part, method) for part in ("block",)
                 for method in ("cog", "lsq_gauss")}
# The cloud-accuracy targets of the benchmark (micrometres, points).
RMS_TARGET_UM = 20.0
UNMATCHED_PER_10K_TARGET = bench.TARGET_UNMATCHED_PER_10K


@pytest.fixture(scope="module")
def quick_bench(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_scan")
    result = bench.run(out, quick=True)
    return out, result


def test_writes_one_row_per_part_and_method(quick_bench):
    out, result = quick_bench
    written = json.loads((out / "scan.json").read_text())
    runs = [(r["part"], r["method"]) for r in written["rows"]]
    assert len(runs) == len(set(runs))
    assert set(runs) == EXPECTED_RUNS
    assert written["presets"] == []
    assert written["summary"] == json.loads(json.dumps(result["summary"]))
    for key in ("cpu_count", "python", "numpy", "numba", "date"):
        assert key in written["machine"]


def test_accuracy_and_timing_fields_are_finite(quick_bench):
    out, _ = quick_bench
    rows = json.loads((out / "scan.json").read_text())["rows"]
    for row in rows:
        for key in ("rms_um", "p99_um", "max_um", "mean_signed_um", "unmatched_points"):
            value = row["accuracy"][key]
            assert isinstance(value, (int, float)) and math.isfinite(value), (row["part"], key, value)
        assert row["frames"] > 0 and row["points"] > 0
        assert row["processing_ms"] > 0
        assert math.isfinite(row["realtime_factor"]) and row["realtime_factor"] > 0


def test_png_is_written(quick_bench):
    out, _ = quick_bench
    data = (out / "scan.png").read_bytes()
    assert data[:8] == PNG_MAGIC


def test_block_with_cog_is_accurate(quick_bench):
    _, result = quick_bench
    row = next(r for r in result["rows"] if r["part"] == "block" and r["method"] == "cog")
    assert row["accuracy"]["rms_um"] <= RMS_TARGET_UM
    assert row["accuracy"]["unmatched_points"] <= UNMATCHED_PER_10K_TARGET * row["points"] / 1e4
