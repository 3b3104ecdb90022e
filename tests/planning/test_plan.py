"""flyscan plan: a catalogue of three small procedural parts and a broken file on a
LocalCluster of two process workers, one of which is killed mid-run; the same results as
in process; a rerun that computes nothing; the plan read back by flyscan scan and the
service."""
import io
import json
import os
import shutil
import signal

import numpy as np
import pytest

from planning.cache import candidate_key
from planning.candidates import base_grasps, candidates, resting_grasps, turns
from planning.catalogue import procedural_catalogue, read_catalogue
from planning.evaluate import PLAN_SEED, evaluate
from planning.run import local_cluster, plan_catalogue
from scanner_core.cad import part_from_mesh
from scanner_core.inspection import InspectionParams
from scanner_core.scanplan import PlanError, load_scan_plan, turned_grasp
from flyscan import main

# The test's candidates: few and quick (the fast pass has 45 frames).
OPTIONS = dict(turn_step_deg=90.0, presets=("fast",), resting=1)
# The fields of a result that are the machine's, not the part's.
COST = "cost"


@pytest.fixture(scope="module")
def catalogue(tmp_path_factory):
    folder = tmp_path_factory.mktemp("catalogue")
    procedural_catalogue(folder, 3, seed=7, extra_broken=True)
    return folder


@pytest.fixture(scope="module")
def planned(catalogue, tmp_path_factory):
    """The catalogue planned on two process workers, one killed once the first result is in
    (while the other tasks are queued or running)."""
    from distributed import Client

    out = tmp_path_factory.mktemp("plan")
    killed = []

    def kill_one(done, total, client):
        if killed:
            return
        busy = [addr for addr, keys in client.processing().items() if keys]
        if not busy:  # (workers=[] would mean every worker) try at the next result
            return
        pids = client.run(os.getpid, workers=busy[:1])
        for addr, pid in pids.items():
            os.kill(pid, signal.SIGKILL)
            killed.append((addr, done, total))

    environment = dict(os.environ)
    with local_cluster(2) as cluster, Client(cluster) as client:
        started = dict(os.environ)
        in_workers = client.run(os.getenv, "MALLOC_TRIM_THRESHOLD_")
        run = plan_catalogue(catalogue, out, client=client, on_result=kill_one,
                             log=io.StringIO(), **OPTIONS)
    return run, out, killed, (environment, in_workers, started, dict(os.environ))


def _without_cost(result: dict) -> dict:
    return {k: v for k, v in result.items() if k != COST}


def test_a_killed_worker_loses_nothing_and_changes_nothing(planned, catalogue):
    run, out, killed, _ = planned
    assert len(killed) == 1 and killed[0][1] < killed[0][2], "a worker was killed mid-run"
    assert run.errors == 0
    assert run.computed == run.tasks > 0 and run.cached == 0
    # every candidate as the same code gives it in this process
    entries = [e for e in read_catalogue(catalogue) if e.part is not None]
    for entry in entries:
        plan = json.loads((out / "plans" / entry.name / "plan.json").read_text())
        kept, _ = candidates(entry.part, **OPTIONS)
        assert len(plan["candidates"]) == len(kept)
        stored = {c["key"]: c for c in plan["candidates"]}
        for cand in kept:
            key = candidate_key(entry.mesh.digest, entry.units, cand.key(), PLAN_SEED)
            here = evaluate(entry.mesh, cand, preview=False)
            cached = json.loads((out / "cache" / key[:2] / f"{key}.json").read_text())
            assert _without_cost(cached) == json.loads(json.dumps(_without_cost(here)))
            assert stored[key]["status"] == here["status"]


def test_the_cluster_leaves_this_process_environment_as_it_was(planned):
    """distributed's nannies write their workers' variables (MALLOC_TRIM_THRESHOLD_, ...)
    into the process that starts them, also when a killed worker is started again; a
    service started afterwards inherited them."""
    environment, in_workers, started, closed = planned[3]
    assert set(in_workers.values()) == {"65536"}  # the workers have theirs
    assert started == environment
    assert closed == environment


def test_the_summary_reports_the_broken_mesh_and_plans_the_others(planned):
    run, out, *_ = planned
    rows = {r["part"]: r for r in run.summary["rows"]}
    assert rows["broken"]["status"] == "broken"
    assert "broken.stl" in rows["broken"]["reason"] and "no triangles" in rows["broken"]["reason"]
    assert run.summary["parts"] == 4 and run.summary["broken"] == 1
    planned_parts = [name for name in rows if name != "broken"]
    assert len(planned_parts) == 3
    csv_text = (out / "catalogue.csv").read_text()
    html_text = (out / "report.html").read_text()
    for name in planned_parts:
        plan = load_scan_plan(out / "plans" / name / "plan.json")
        assert plan.preset == "fast"
        assert rows[name]["grasp"] == plan.grasp_name
        assert (out / rows[name]["picture"]).stat().st_size > 1000
        assert name in csv_text and rows[name]["picture"] in html_text
    assert "broken" in csv_text and "no triangles" in html_text


def test_a_cached_rerun_computes_nothing(planned, catalogue):
    run, out, *_ = planned
    before = {p: p.read_bytes() for p in sorted((out / "plans").glob("*/plan.json"))}
    again = plan_catalogue(catalogue, out, workers=1, log=io.StringIO(), **OPTIONS)
    assert (again.computed, again.cached, again.workers) == (0, run.tasks, 0)
    assert {p: p.read_bytes() for p in before} == before


def test_the_ranking_puts_a_scan_that_fixes_every_axis_first(planned):
    _, out, *_ = planned
    for path in (out / "plans").glob("*/plan.json"):
        plan = json.loads(path.read_text())
        done = [c for c in plan["candidates"] if c["status"] == "done"]
        chosen = plan["chosen"]["predicted"]
        if any(c["observable"] for c in done):
            assert chosen["observable"]
            scores = [c["score"] for c in done if c["observable"]]
            assert chosen["score"] <= min(scores) + 0.05  # compared in tenths of the tolerance


def test_flyscan_scan_takes_the_plan(planned, catalogue, tmp_path, capsys):
    _, out, *_ = planned
    name = "p0000_block"
    plan_path = out / "plans" / name / "plan.json"
    plan = json.loads(plan_path.read_text())
    # the part's own inspection thresholds, written into its plan
    plan["inspection"] = {"extra_mm": 0.9, "min_area_mm2": 2.5}
    plan_path = tmp_path / "plan.json"
    plan_path.write_text(json.dumps(plan))
    assert main(["scan", "--part", str(catalogue / f"{name}.stl"), "--units", "mm", "--plan",
                 str(plan_path), "--no-eval", "--out", str(tmp_path / "scan")]) == 0
    report = json.loads((tmp_path / "scan" / "report.json").read_text())
    assert report["inspection"]["thresholds"]["extra_mm"] == 0.9
    assert report["inspection"]["thresholds"]["min_area_mm2"] == 2.5
    np.testing.assert_allclose(report["ground_truth"]["nominal_grasp"],
                               plan["chosen"]["nominal_grasp"], atol=1e-9)
    assert report["frames"] == plan["chosen"]["predicted"]["frames"]
    # the plan's seed and no misplacement: the very pass the planner judged
    assert report["pose"]["std"] == plan["chosen"]["predicted"]["std"]
    # a plan of another mesh, and a file that is no plan: clear errors, exit 2
    other = catalogue / "p0001_bracket.stl"
    assert main(["scan", "--part", str(other), "--units", "mm", "--plan", str(plan_path),
                 "--out", str(tmp_path / "x")]) == 2
    assert "made for another mesh" in capsys.readouterr().err
    wrong = dict(plan, inspection={"extra_mm": "big"})
    (tmp_path / "wrong.json").write_text(json.dumps(wrong))
    assert main(["scan", "--part", str(catalogue / f"{name}.stl"), "--units", "mm", "--plan",
                 str(tmp_path / "wrong.json"), "--out", str(tmp_path / "w")]) == 2
    assert "inspection" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text("{\"format\": \"something\"}")
    assert main(["scan", "--part", str(other), "--units", "mm", "--plan", str(bad),
                 "--out", str(tmp_path / "y")]) == 2
    assert "is not a scan plan" in capsys.readouterr().err


def test_the_service_takes_a_stored_parts_plan(planned, catalogue, tmp_path):
    from service.parts import PLAN_FILE, PartLibrary

    _, out, *_ = planned
    name = "p0000_block"
    library = PartLibrary(tmp_path)
    library.open()
    library.add(name, (catalogue / f"{name}.stl").read_bytes(), "mm",
                inspection=InspectionParams(extra_mm=0.6, deform_mm=0.2))
    centred = library.get(name).grasp
    plan = load_scan_plan(out / "plans" / name / "plan.json")
    data = json.loads((out / "plans" / name / "plan.json").read_text())
    data["inspection"] = {"extra_mm": 0.7}
    (tmp_path / "parts" / name / PLAN_FILE).write_text(json.dumps(data))
    again = PartLibrary(tmp_path)
    again.open()
    np.testing.assert_allclose(again.get(name).grasp, plan.nominal_grasp, atol=1e-9)
    # the upload's thresholds kept with the part, the plan's over them
    assert again.get(name).inspection.given() == {"extra_mm": 0.7, "deform_mm": 0.2}
    assert plan.grasp_name != "centred" or plan.pass_direction_deg != 0 or \
        np.allclose(centred, plan.nominal_grasp)


def test_plan_command_refuses_bad_input(tmp_path, capsys):
    assert main(["plan", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]) == 2
    assert "catalogue folder not found" in capsys.readouterr().err
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "a.stl").write_bytes(b"solid a\nendsolid a\n")
    assert main(["plan", str(tmp_path / "c"), "--out", str(tmp_path / "o")]) == 2
    assert "no unit for a.stl" in capsys.readouterr().err
    assert main(["plan", str(tmp_path / "c"), "--units", "mm", "--presets", "warp",
                 "--out", str(tmp_path / "o")]) == 2
    assert "--presets must be among" in capsys.readouterr().err
    with pytest.raises(PlanError, match="not found"):
        load_scan_plan(tmp_path / "missing.json")


def test_candidates_of_a_box():
    import trimesh

    part = part_from_mesh(trimesh.creation.box((60.0, 40.0, 10.0)), name="box")
    grasps = base_grasps(part.mesh, resting=3)
    # flat shows the sensor the face centred shows (the box is flat already), and so does one
    # of the two broad resting faces: kept are centred, the other broad face, a 60 x 10 side
    assert [n for n, _ in grasps][0] == "centred" and len(grasps) == 3
    assert all(n.startswith("resting-") for n, _ in grasps[1:])
    toward = np.array([g[2, :3] for _, g in grasps])  # the {P} direction along +z_T
    np.testing.assert_allclose(toward[:2], [[0, 0, 1], [0, 0, -1]], atol=1e-9)
    np.testing.assert_allclose(np.abs(toward[2]), [0, 1, 0], atol=1e-9)
    faces = resting_grasps(part.mesh, count=6)
    assert len(faces) == 6  # a box rests on each face
    toward = np.array([g[2, :3] for g in faces])
    np.testing.assert_allclose(np.abs(toward).sum(axis=1), 1.0, atol=1e-9)  # face normals
    kept, left_out = candidates(part, turn_step_deg=90.0, presets=("fast", "default"))
    assert len(kept) == 3 * 2 * 2 and left_out == []
    assert turns(45.0) == [0.0, 45.0, 90.0, 135.0]
    turned = turned_grasp(part.grasp, 90.0, part.vertices)
    v = part.vertices @ turned[:3, :3].T + turned[:3, 3]
    np.testing.assert_allclose(np.ptp(v, axis=0), [40.0, 60.0, 10.0], atol=1e-9)
    np.testing.assert_allclose(v[:, :2].min(axis=0) + v[:, :2].max(axis=0), 0.0, atol=1e-9)
    with pytest.raises(ValueError, match="turn step"):
        turns(0.0)
