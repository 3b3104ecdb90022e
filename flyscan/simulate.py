"""``flyscan simulate``: the paper's scan simulator (section III): the cloud a CAD part
would give, predicted by ray casting, as a PLY file."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from flyscan.common import ScanError, UsageError, check_part_args, load_part_model

__all__ = ["add_parser", "run"]


def add_parser(command) -> None:
    from scanner_core.cad import GRASPS

    sim = command("simulate", help="predict the cloud of a CAD part by ray casting "
                                   "(the paper's scan simulator)")
    src = sim.add_mutually_exclusive_group(required=True)
    src.add_argument("--part", type=Path, help="mesh file (STL, OBJ, PLY)")
    src.add_argument("--demo", action="store_true", help="the built-in procedural block")
    sim.add_argument("--units", default=None, help="unit of the mesh file: mm, cm, m or inch")
    sim.add_argument("--laser", default=None,
                     help="'x,y,z': light source at step 0, mm in {T} (default: the reference "
                          "cell's at the start of the pass)")
    sim.add_argument("--camera", default=None, help="'x,y,z': camera at step 0, mm in {T}")
    sim.add_argument("--step", type=float, default=None,
                     help="step size, mm: how far the setup moves along +y_T between lines "
                          "(default 0.5)")
    sim.add_argument("--rays", type=int, default=None, help="rays per line (default 1000)")
    sim.add_argument("--misplace", default=None, help="'tx,ty,tz,rx,ry,rz': mm and degrees, in {T}")
    sim.add_argument("--grasp", choices=GRASPS, default="centred",
                     help="nominal grasp (as for scan)")
    sim.add_argument("--mirrors", action="store_true",
                     help="also record whether the camera sees each point through each mirror")
    sim.add_argument("--threads", type=int, default=2, help="worker threads (default 2)")
    sim.add_argument("--out", type=Path, required=True, help="output PLY file")


def parse_point(text: str | None, option: str):
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not np.all(np.isfinite(values)):
        raise UsageError(f"{option} must be three finite numbers 'x,y,z' in mm, got {text!r}")
    return np.array(values)


#: Sweeps with more rays than this report their progress (about 2 s at 10 Mrays/s).
PROGRESS_RAYS = 20_000_000


class SweepProgress:
    """Prints a line on stderr at every tenth of a long sweep."""

    def __init__(self):
        self.shown = -1

    def __call__(self, done: int, total: int) -> None:
        tenth = 10 * done // max(total, 1)
        if total >= PROGRESS_RAYS and tenth > self.shown:
            self.shown = tenth
            print(f"swept {done / 1e6:.0f} of {total / 1e6:.0f} M rays ({10 * tenth} %)",
                  file=sys.stderr, flush=True)


def _load_part(args):
    """The simulator's part of ``--part``/``--units`` or ``--demo``, with its ``--grasp``."""
    from simulator.parts import block_with_holes_and_steps, part_from_mesh, simulated

    if args.demo:
        return part_from_mesh(block_with_holes_and_steps(), name="demo-block", grasp=args.grasp)
    return simulated(load_part_model(args))


def run(args) -> int:
    from concurrent.futures import ThreadPoolExecutor

    from simulator.cell import load_cell
    from simulator.parts import check_fits
    from simulator.virtual_setup import (DEFAULT_RAYS_PER_LINE, DEFAULT_STEP_MM, predict_cloud,
                                         prepare, reference_setup, save_predicted_cloud,
                                         warm_up)

    check_part_args(args)
    if args.part is None and not args.demo:
        raise UsageError("give the part: --part FILE --units U, or --demo")
    if args.out.suffix.lower() != ".ply":
        raise UsageError(f"--out must name a .ply file, got {args.out}")
    if args.out.is_dir():
        raise UsageError(f"--out {args.out} is a directory; give a file name ending in .ply")
    if args.threads < 1:
        raise UsageError(f"--threads must be >= 1, got {args.threads}")
    laser, camera = parse_point(args.laser, "--laser"), parse_point(args.camera, "--camera")
    misplacement = np.eye(4)
    if args.misplace is not None:  # simulator.session is the scan's: imported only if needed
        from simulator.session import parse_misplacement

        try:
            misplacement = parse_misplacement(args.misplace)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    # The setup is validated (a zero or negative step, too few rays) before the mesh loads.
    setup = reference_setup(load_cell(), laser=laser, camera=camera, mirrors=args.mirrors,
                            step_mm=DEFAULT_STEP_MM if args.step is None else args.step,
                            rays_per_line=(DEFAULT_RAYS_PER_LINE if args.rays is None
                                           else args.rays))
    # numba's start-up and the kernels' loading (mostly Python) run beside the mesh's loading
    # and its BVH build (mostly numpy and Embree, without the GIL).
    with ThreadPoolExecutor(1, thread_name_prefix="warm-up") as pool:
        warming = pool.submit(warm_up)
        part = _load_part(args)
        pose = misplacement @ part.grasp
        # The part as swept must fit the inspection volume, as in scan.
        check_fits(part, pose=pose)
        build_s = prepare(part)  # once per part: reported apart from the sweep
        warming.result()
    cloud = predict_cloud(part, setup, pose=pose, threads=args.threads,
                          progress=SweepProgress())
    summary = {"part": part.name, "faces": len(part.faces),
               "intersector_build_s": round(build_s, 4), **cloud.summary()}
    summary.update({f"seen_{name}": int(seen.sum()) for name, seen in cloud.seen.items()})
    if cloud.first_hits == 0:
        raise ScanError(f"no ray hit the part in {cloud.rays_cast} rays over steps "
                        f"{cloud.steps[0]}..{cloud.steps[1]}: is the part thinner than a step?")
    if len(cloud) == 0:
        raise ScanError(f"the camera sees none of the {cloud.first_hits} lit points: is it "
                        "behind the part, or on the other side of the light plane's lit surface?")
    path = save_predicted_cloud(args.out, cloud)
    print(json.dumps(summary))
    print(f"predicted {len(cloud)} points of {part.name} in {cloud.elapsed_s:.3f} s "
          f"({cloud.rays_per_second / 1e6:.1f} Mrays/s): {path}")
    return 0
