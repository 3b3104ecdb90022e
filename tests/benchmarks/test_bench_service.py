"""bench service's pose latency: its summary by part and point count, against the target, and
its chart, on hand-made rows (the service's run itself is the benchmark's, not a test's)."""
import pytest

from benchmarks import service as bench
from benchmarks.results import pyplot
from benchmarks.service_charts import plot_pose


def _row(part, points, published, coarse=False, ambiguous=False):
    return {"part": part, "speed_mm_s": 200.0, "points": points, "pose_published_ms": published,
            "pose_ms": published - 50.0, "coarse": coarse, "ambiguous": ambiguous,
            "pose_path_ms": {"pass_end": 18.0, "registration": published - 60.0},
            "stages_ms": {"fine": 40.0, "probes": published - 120.0}}


ROWS = [_row("block", 5_000, 120.0), _row("block", 10_000, 140.0), _row("block", 21_000, 400.0),
        _row("gear", 8_000, 900.0, coarse=True), _row("gear", 9_000, 130.0, ambiguous=True)]


def test_the_summary_groups_by_part_and_points_and_judges_up_to_the_target_points():
    summary = bench._pose_summary(ROWS)
    block, gear = summary["by_part"]["block"], summary["by_part"]["gear"]
    assert block["pose_published_ms"]["n"] == 3
    assert block["pose_published_ms_up_to_target_points"]["max"] == 140.0  # 21 000 left out
    assert gear["coarse"] == 1 and gear["ambiguous"] == 1
    assert block["path_ms_median"]["pass_end"] == 18.0
    assert summary["by_points"]["0-5000"]["n"] == 1
    assert summary["by_points"]["5000-10000"]["n"] == 3
    assert summary["by_points"]["20000-40000"]["max"] == 400.0
    within = summary["pose_published_ms_up_to_target_points"]
    assert within["n"] == 4 and within["max"] == 900.0
    assert not summary["target"]["met"]  # gear's coarse pass is above 150 ms at p95
    assert bench._pose_summary(ROWS[:2])["target"]["met"]


def test_the_chart_draws(tmp_path):
    pose = {"parts": ["block", "gear"], "rows": ROWS, **bench._pose_summary(ROWS)}
    plt = pyplot()
    fig, axes = plt.subplots(1, 3)
    plot_pose(pose, *axes)
    fig.savefig(tmp_path / "pose.png")
    plt.close(fig)
    assert (tmp_path / "pose.png").stat().st_size > 0


def test_the_stage_timer_restores_the_pose_module():
    import scanner_core.pose.registration as pose_module

    before = {name: getattr(pose_module, name) for name in bench.POSE_STAGES
              if hasattr(pose_module, name)}
    assert before  # the stages the bench times still exist under these names
    with bench.pose_stages() as spent:
        assert all(getattr(pose_module, name) is not f for name, f in before.items())
        assert spent == {}
    assert all(getattr(pose_module, name) is f for name, f in before.items())


@pytest.mark.parametrize("values, n", [([None, None], 0), ([1.0, None, 3.0], 2)])
def test_stats_leave_out_missing_values(values, n):
    assert bench.spread(values)["n"] == n
