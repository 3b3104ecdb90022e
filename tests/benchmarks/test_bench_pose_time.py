"""bench pose_time, quick: the demo block's poses timed stage by stage, and right."""
import json

import numpy as np

from benchmarks.pose_time import run


def test_bench_pose_time_quick(tmp_path):
    result = run(tmp_path, quick=True, progress=lambda line: None)
    written = json.loads((tmp_path / "pose_time.json").read_text())
    assert (tmp_path / "pose_time.png").stat().st_size > 10_000
    rows = written["rows"]
    assert len(rows) == 2 and {r["part"] for r in rows} == {"block"}
    for row in rows:
        # the pose is right, and its time is the sum of stages it ran and more
        assert row["act"] and row["error_um"] < 30.0 and row["error_mdeg"] < 40.0, row
        assert row["stages_ms"]["fine"] > 0.0
        assert sum(row["stages_ms"].values()) <= row["ms"] * 1.05 + 1.0
    small = [r["ms"] for r in rows if r["points"] <= written["summary"]["target_points"]]
    summary = result["summary"]["up_to_target_points"]
    assert summary["n"] == len(small)
    assert np.isclose(summary["median"], np.median(small), rtol=1e-3)
