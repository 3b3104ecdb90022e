"""The coarse-stage benchmark's quick set (the procedural block): its files, one row per method
and scan with times that add up, and the block found from starts 10 mm and 20 degrees off."""
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from benchmarks import coarse as bench

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def quick_bench(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_coarse")
    lines = []
    return out, bench.run(out, quick=True, progress=lines.append), lines


def test_writes_json_and_chart(quick_bench):
    out, result, lines = quick_bench
    written = json.loads((out / "coarse.json").read_text())
    assert written["summary"] == json.loads(json.dumps(result["summary"]))
    assert (out / "coarse.png").read_bytes()[:8] == PNG_MAGIC
    assert written["settings"]["parts"] == ["block"]
    assert len(lines) == 1 + bench.QUICK_SCANS_PER_PART + 1  # training, each scan, done


def test_one_row_per_method_and_scan_with_times_that_add_up(quick_bench):
    _, result, _ = quick_bench
    trials = result["trials"]
    assert sorted((t["scan"], t["method"]) for t in trials) == sorted(
        (i, m) for i in range(bench.QUICK_SCANS_PER_PART) for m in bench.METHODS)
    assert result["parts"]["block"]["ppf_train_s"] > 0
    for t in trials:
        assert t.get("refused") is None, t
        if t["method"] == "flyscan":
            assert t["time_ms"] == pytest.approx(t["register_ms"]) and t["register_ms"] > 0
        else:
            # the whole cloud's normals, PPF's match, the registration(s) from its poses
            assert t["match_ms"] > 0 and t["normals_ms"] > 0 and t["register_ms"] > 0
            assert t["time_ms"] == pytest.approx(t["register_ms"] + t["normals_ms"]
                                                 + t["match_ms"])
    summary = result["summary"]
    for method in bench.METHODS:
        rows = [t for t in trials if t["method"] == method]
        assert summary[method]["success_rate"] == pytest.approx(
            np.mean([t["success"] for t in rows]))
        assert summary[method]["confident_wrong"] == sum(
            not t["success"] and not t["flags"] for t in rows)


def test_flyscan_finds_the_block_from_starts_10_mm_and_20_degrees_off(quick_bench):
    """flyscan's search seeded by the start lands within 0.1 mm and 0.1 degree of the truth
    (PPF, trained on 1000 points in the quick set, may not: the block is nearly symmetric)."""
    _, result, _ = quick_bench
    for t in result["trials"]:
        assert np.linalg.norm(t["start_offset"][:3]) == pytest.approx(bench.START_LEVEL[0])
        if t["method"] == "flyscan":
            assert t["success"], t
            assert t["translation_norm_um"] < 100 and t["rotation_angle_mdeg"] < 100


def test_ppf_poses_map_the_model_onto_the_scene(block_part):
    """Fed the model's own samples moved by a known pose, PPF's best pose is that pose to its
    discretisation (30 angle steps of 12 degrees, positions to 5 % of the part's diameter):
    its poses are ^T X_P, as the fine stage's (the inverse would be 80 degrees off)."""
    model = block_part.surface_model
    detector, _ = bench.ppf_detector(model, points=bench.QUICK_PPF_MODEL_POINTS)
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_rotvec(np.radians([10.0, -20.0, 35.0])).as_matrix()
    truth[:3, 3] = [5.0, -3.0, 40.0]
    keep = np.random.default_rng(0).choice(len(model.points), 20000, replace=False)
    points = model.points[keep] @ truth[:3, :3].T + truth[:3, 3]
    normals = model.normals[keep] @ truth[:3, :3].T
    poses, match_ms = bench.ppf_poses(detector, points, normals)
    assert match_ms > 0 and 1 <= len(poses) <= bench.TOP_K
    error = poses[0] @ np.linalg.inv(truth)
    assert np.degrees(Rotation.from_matrix(error[:3, :3]).magnitude()) < 12.0
    assert np.linalg.norm(error[:3, 3]) < 6.0
