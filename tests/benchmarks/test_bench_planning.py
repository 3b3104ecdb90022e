"""bench planning's summary (benchmarks.planning.combine) from its phases' files, and the
projection's arithmetic: synthetic phase figures, no cluster."""
import json

import pytest

from benchmarks.planning import combine, projection


def test_the_projection_scales_the_measured_task_cost():
    p = projection(per_task_s=1.5, candidates_per_part=20.0, parts=1000, workers=(2, 10))
    # 1000 parts x 20 candidates x 1.5 s = 30 000 s of a worker's time
    assert p["hours"] == {"2": pytest.approx(30000 / 2 / 3600, abs=0.01),
                          "10": pytest.approx(30000 / 10 / 3600, abs=0.01)}


def test_combine_summarises_the_phases(tmp_path):
    runs = [{"workers": 1, "tasks": 10, "compute_s": 10.0, "per_s": 1.0,
             "load_before": [0.5, 0.5, 0.5], "load_after": [1, 1, 1], "cost": {}},
            {"workers": 2, "tasks": 10, "compute_s": 5.5, "per_s": 10 / 5.5,
             "load_before": [0.7, 0.5, 0.5], "load_after": [2, 1, 1], "cost": {}}]
    (tmp_path / "throughput.json").write_text(json.dumps({"runs": runs, "ratio": 10 / 5.5 / 1.0}))
    # (the ratio is throughput()'s, of the medians per worker count)
    rows = [{"part": "a", "seed": 1, "misplacement": [0] * 6, "observable": True,
             "worst_factor": 1.5, "ratio_predicted_over_measured": {"tx_mm": 1.5}},
            {"part": "a", "seed": 1, "misplacement": [1, 0, 0, 0, 0, 0], "observable": False,
             "worst_factor": 2.5, "ratio_predicted_over_measured": {"tx_mm": 0.4}}]
    (tmp_path / "measured.json").write_text(json.dumps({"rows": rows, "worst_factor": 2.5,
                                                        "within_2": 1, "scans": 2}))
    result = combine(tmp_path)
    summary = result["summary"]
    assert summary["ratio_2_over_1"] == pytest.approx(1.818, abs=1e-3)
    assert summary["sigma_nominal"] == {"scans": 1, "worst_factor": 1.5, "within_2": 1,
                                        "every_axis_fixed": 1}
    assert summary["sigma_misplaced"]["within_2"] == 0
    assert (tmp_path / "bench_planning.png").stat().st_size > 1000
    assert json.loads((tmp_path / "bench_planning.json").read_text())["summary"] == summary
