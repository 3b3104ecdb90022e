"""The edges benchmark, quick: its files, its figures per part and edge kind."""
import json

from benchmarks import edges as bench
from benchmarks.targets import TARGET_EDGE_RMS_UM

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_quick_bench_writes_figures_per_part_and_kind(tmp_path):
    """Three procedural parts, one pass each. Measured: the faceted dome 13 of 38 points
    false before the turned-away test, none kept after it; the dome on a plinth 39 -> 16.5 um
    RMS (inliers); the bracket 16.7 um, no point set aside."""
    result = bench.run(tmp_path, quick=True)
    saved = json.loads((tmp_path / "edges.json").read_text())
    assert (tmp_path / "edges.png").read_bytes()[:8] == PNG_MAGIC
    assert saved["summary"] == result["summary"]
    parts = result["summary"]["parts"]
    assert set(parts) == set(bench.QUICK_PARTS)
    dome = parts["faceted_dome"]
    assert dome["before"]["false_fraction_worst"] > 0.2
    assert dome["model_free"]["false_points"] == 0
    assert dome["kinds"]["turned_away"] > 0
    assert set(dome["causes"]["false_before"]) <= {"faint", "unseen"}
    plinth = parts["faceted_dome_plinth"]
    assert plinth["before"]["rms_inliers_um_worst"] > TARGET_EDGE_RMS_UM
    assert plinth["within_target"] and plinth["model_free"]["points"] >= 100
    bracket = parts["bracket"]
    assert bracket["within_target"] and bracket["kinds"]["turned_away"] == 0
    assert result["summary"]["met"]
    (row,) = [r for r in result["scans"] if r["part"] == "bracket"]
    assert row["pose_error_um"] < 20.0 and row["with_model"]["count"] > 100
