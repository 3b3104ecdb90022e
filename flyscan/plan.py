"""``flyscan plan CATALOGUE --out DIR``: a scan plan for every part of a catalogue folder,
each candidate scan a task on Dask distributed (``planning``; docs/planning.md)."""
from __future__ import annotations

from pathlib import Path

from flyscan.common import UsageError, check_out_dir

__all__ = ["add_parser", "run"]

PRESETS = ("fast", "default", "slow")


def add_parser(command) -> None:
    plan = command("plan", help="plan the scans of a catalogue of parts: for each part the grasp, "
                                "pass direction and speed whose scan fixes its pose best, "
                                "simulated as tasks on Dask distributed")
    plan.add_argument("catalogue", type=Path,
                      help="folder of CAD files (STL, OBJ, PLY), with an optional "
                           "manifest.json of their units ({\"part.stl\": {\"units\": \"mm\"}})")
    plan.add_argument("--units", default=None,
                      help="unit of the files the manifest does not name: mm, cm, m or inch")
    plan.add_argument("--scheduler", default=None,
                      help="address of a running Dask scheduler (tcp://HOST:8786); default a "
                           "local cluster on this machine")
    plan.add_argument("--workers", type=int, default=None,
                      help="workers of the local cluster (default one per core)")
    plan.add_argument("--turn-step", type=float, default=90.0,
                      help="pass directions: turns about z_T from 0 below 180 in this step, "
                           "degrees")
    plan.add_argument("--presets", default=",".join(PRESETS),
                      help="pass presets to try, comma-separated among fast, default, slow")
    plan.add_argument("--resting", type=int, default=3,
                      help="stable resting faces tried as suction grasps (largest first)")
    plan.add_argument("--cache", type=Path, default=None,
                      help="result cache folder (default OUT/cache): a rerun computes only "
                           "what is missing")
    plan.add_argument("--act-tolerance-mm", type=float, default=0.1,
                      help="placement tolerance the sigmas are ranked against, mm")
    plan.add_argument("--act-tolerance-deg", type=float, default=0.1,
                      help="placement tolerance for the rotations, degrees")
    plan.add_argument("--out", type=Path, required=True,
                      help="folder for plans/PART/plan.json, catalogue.csv, summary.json and "
                           "report.html")


def run(args) -> int:
    from planning.catalogue import CatalogueError
    from planning.run import plan_catalogue

    presets = tuple(p.strip() for p in args.presets.split(",") if p.strip())
    if not presets or any(p not in PRESETS for p in presets):
        raise UsageError(f"--presets must be among {', '.join(PRESETS)}, got {args.presets!r}")
    if not 0 < args.turn_step <= 180:
        raise UsageError(f"--turn-step must be in (0, 180] degrees, got {args.turn_step}")
    if args.workers is not None and args.workers < 1:
        raise UsageError(f"--workers must be at least 1, got {args.workers}")
    if args.workers is not None and args.scheduler:
        raise UsageError("--workers is for the local cluster, not with --scheduler")
    if args.resting < 0:
        raise UsageError(f"--resting must be 0 or more, got {args.resting}")
    for name in ("act_tolerance_mm", "act_tolerance_deg"):
        if not getattr(args, name) > 0:
            raise UsageError(f"--{name.replace('_', '-')} must be positive")
    check_out_dir(args.out)
    try:
        result = plan_catalogue(args.catalogue, args.out, units=args.units,
                                scheduler=args.scheduler, workers=args.workers,
                                turn_step_deg=args.turn_step, presets=presets,
                                resting=args.resting, cache=args.cache,
                                tolerance_mm=args.act_tolerance_mm,
                                tolerance_deg=args.act_tolerance_deg)
    except CatalogueError as exc:
        raise UsageError(str(exc)) from None
    except (OSError, TimeoutError) as exc:
        if not args.scheduler:
            raise
        raise UsageError(f"cannot reach the Dask scheduler {args.scheduler}: {exc}") from None
    summary = result.summary
    print(f"planned {summary['parts']} parts: {summary['every_axis_fixed']} with every axis "
          f"fixed, {summary['broken']} broken; {args.out / 'catalogue.csv'}")
    return 0
