"""``bench simulate`` side by side with Open3D: ``flyscan simulate`` and the same sweep written
as a careful Open3D user would (`benchmarks.open3d_sweep`), each run as a whole process in turn
on the same STL, the same setup and about the same rays. Open3D is an optional, benchmark-only
dependency (``pip install 'flyscan[bench]'``); without it the comparison is skipped with a
note."""
from __future__ import annotations

import importlib.util
import json
import pathlib
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np
import trimesh

from benchmarks.parts import REFERENCE_PART
from benchmarks.stats import judged
from simulator.parts import Part
from simulator.virtual_setup import reference_setup

__all__ = ["SIDE_BASE", "SIDE_LEVELS", "SIDE_RAYS", "SIDE_RAYS_PER_LINE", "SIDE_RUNS",
           "QUICK_SIDE_RAYS", "QUICK_SIDE_RUNS", "TARGET_WHOLE_RATIO", "side_by_side"]

# Side by side with Open3D: a part of about 100 k triangles (idler_riser split three times,
# 100 608), about this many rays (lines of 1000), each tool run this often, in turn.
SIDE_BASE, SIDE_LEVELS = REFERENCE_PART, 3
SIDE_RAYS, SIDE_RAYS_PER_LINE, SIDE_RUNS = 7_300_000, 1000, 5
QUICK_SIDE_RAYS, QUICK_SIDE_RUNS = 400_000, 1
#: The issue's target: the whole `flyscan simulate` against the whole Open3D script.
TARGET_WHOLE_RATIO = 0.6


def side_by_side(part: Part, cell, *, rays: int = SIDE_RAYS, runs: int = SIDE_RUNS,
                 progress=None) -> dict:
    """``flyscan simulate`` against the same sweep in Open3D, each a whole process, in turn.

    Both read the same STL (the part under its nominal grasp, in mm in {T}) and sweep it from
    the reference cell's setup with `SIDE_RAYS_PER_LINE` rays a line, the step chosen for
    about `rays` rays, and write their PLY; the outputs are deleted before each run, and the
    order alternates from run to run.

    Returns
    -------
    dict
        The command lines, per-run wall and CPU seconds of each process, each tool's own
        figures (flyscan's summary; the Open3D script's phases), their medians, the ratios
        (flyscan over Open3D) and the points each kept; or ``{"skipped": reason}`` when
        Open3D cannot be imported.
    """
    say = progress or (lambda line: None)
    if importlib.util.find_spec("open3d") is None:
        return {"skipped": "open3d is not installed (pip install 'flyscan[bench]'): no "
                           "comparison"}
    probe = reference_setup(cell, step_mm=1.0, rays_per_line=SIDE_RAYS_PER_LINE)
    vertices = part.vertices_t()
    extent = float(np.ptp(vertices @ probe.motion))
    step = extent * SIDE_RAYS_PER_LINE / rays
    setup = reference_setup(cell, step_mm=step, rays_per_line=SIDE_RAYS_PER_LINE)
    if not np.allclose(setup.motion, [0.0, 1.0, 0.0]):
        raise RuntimeError("the Open3D script sweeps along +y_T, the reference cell no longer")

    def xyz(v):
        return ",".join(repr(float(c)) for c in v)

    with tempfile.TemporaryDirectory(prefix="flyscan-side-") as tmp:
        mesh = pathlib.Path(tmp) / f"{part.name}-T.stl"
        trimesh.Trimesh(vertices, part.faces, process=False).export(mesh)
        common = ["--part", str(mesh), f"--laser={xyz(setup.laser)}",
                  f"--camera={xyz(setup.camera)}", "--step", repr(step),
                  "--rays", str(SIDE_RAYS_PER_LINE)]
        outs = {"flyscan": pathlib.Path(tmp) / "flyscan.ply",
                "open3d": pathlib.Path(tmp) / "open3d.ply"}
        commands = {
            "flyscan": [sys.executable, "-m", "flyscan", "simulate", *common, "--units",
                        "mm", "--grasp", "identity", "--out", str(outs["flyscan"])],
            "open3d": [sys.executable, "-m", "benchmarks.open3d_sweep", *common,
                       "--out", str(outs["open3d"])],
        }
        runs_of = {name: [] for name in commands}
        for i in range(runs):
            for name in (("flyscan", "open3d") if i % 2 == 0 else ("open3d", "flyscan")):
                for out in outs.values():
                    out.unlink(missing_ok=True)
                run = _timed(commands[name])
                if run["returncode"] != 0:
                    if name == "open3d" and "ImportError" in run["stderr"]:
                        return {"skipped": "open3d does not import: "
                                           + run["stderr"].strip().splitlines()[-1]}
                    raise RuntimeError(f"{name} failed ({run['returncode']}): {run['stderr']}")
                run["report"] = json.loads(run.pop("stdout").splitlines()[0])
                run.pop("stderr")
                runs_of[name].append(run)
            say(f"side by side, run {i + 1}/{runs}: flyscan {runs_of['flyscan'][-1]['wall_s']:.2f}"
                f" s, Open3D {runs_of['open3d'][-1]['wall_s']:.2f} s (whole processes)")
        shown = {name: " ".join(["python", *c[1:]]).replace(tmp, "$TMP")
                 for name, c in commands.items()}
    return _side_summary(part, setup, step, shown, runs_of)


def _timed(command: list[str]) -> dict:
    """Run a process; its wall and CPU seconds (user + system), exit code and output."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": round(wall, 4), "cpu_s": round(cpu, 4), "returncode": done.returncode,
            "stdout": done.stdout, "stderr": done.stderr}


def _side_summary(part: Part, setup, step: float, commands: dict[str, str],
                  runs_of: dict) -> dict:
    def median(name, key, report=False):
        values = [r["report"][key] if report else r[key] for r in runs_of[name]]
        return float(np.median(values))

    fly, o3d = runs_of["flyscan"], runs_of["open3d"]
    whole = median("flyscan", "wall_s") / median("open3d", "wall_s")
    return {
        "part": part.name, "faces": len(part.faces), "step_mm": step,
        "rays_per_line": setup.rays_per_line, "rays_cast": fly[0]["report"]["rays_cast"],
        "open3d_rays_cast": o3d[0]["report"]["rays_cast"],
        "points": fly[0]["report"]["points"], "open3d_points": o3d[0]["report"]["points"],
        "first_hits": fly[0]["report"]["first_hits"],
        "open3d_first_hits": o3d[0]["report"]["first_hits"],
        "open3d_version": o3d[0]["report"]["open3d"],
        # $TMP/<part>-T.stl: the part under its nominal grasp, mm in {T}, binary STL.
        "commands": commands,
        "runs": runs_of,
        "median": {
            "flyscan_wall_s": median("flyscan", "wall_s"),
            "open3d_wall_s": median("open3d", "wall_s"),
            "flyscan_cpu_s": median("flyscan", "cpu_s"),
            "open3d_cpu_s": median("open3d", "cpu_s"),
            "flyscan_sweep_s": median("flyscan", "elapsed_s", True),
            "open3d_ray_calls_s": median("open3d", "ray_calls_s", True),
            "open3d_sweep_s": median("open3d", "sweep_s", True),
            "open3d_import_s": median("open3d", "import_open3d_s", True),
            "open3d_write_s": median("open3d", "write_s", True),
        },
        "ratios": {
            "whole_process": round(whole, 4),
            "whole_process_per_run": [round(f["wall_s"] / o["wall_s"], 4)
                                      for f, o in zip(fly, o3d)],
            "whole_process_cpu": round(median("flyscan", "cpu_s") / median("open3d", "cpu_s"), 4),
            "ray_calls": round(median("flyscan", "elapsed_s", True)
                               / median("open3d", "ray_calls_s", True), 4),
            "sweep": round(median("flyscan", "elapsed_s", True)
                           / median("open3d", "sweep_s", True), 4),
        },
        "target_whole_process": judged(whole, TARGET_WHOLE_RATIO, "<="),
    }
