"""``flyscan bench``: the benchmarks, each writing JSON figures and PNG charts."""
from __future__ import annotations

import json
import os
from pathlib import Path

from flyscan.common import UsageError

__all__ = ["add_parser", "run"]

#: The benchmarks, with what the longer ones measure.
BENCHMARKS = ("stripe", "scan", "simulate", "service", "pose", "coarse", "hardware", "surfaces",
              "calibrate", "edges", "place", "abuse", "pose_time", "planning", "real", "inspect")


def add_parser(command) -> None:
    bench = command("bench", help="benchmarks: JSON figures and PNG charts")
    bench.add_argument("what", choices=BENCHMARKS,
                       help="pose: registration accuracy, time, basin, sigma calibration and "
                            "the side-by-side with Open3D and small_gicp, then where pose and "
                            "edges break; coarse: the pose's coarse stage against OpenCV's "
                            "point-pair features (PPF); hardware: the UR cross-check through "
                            "ur-rtde, the robot link's loss and recovery, replay against real "
                            "time; edges: edge points per part and edge kind on creased, "
                            "curved and walled parts; place: the closed loop (pick, scan, "
                            "correct, place) in the calibrated realistic cell; abuse: passes "
                            "armed over REST while clients loop on the status page's reads "
                            "(frames dropped per load pattern); pose_time: the pose's own CPU "
                            "time by part, point count and stage; planning: flyscan plan's "
                            "throughput on 1 and 2 workers, task cost, the reference parts' "
                            "plans against flyscan scan with them, a 100-part catalogue; real: "
                            "the stripe on public photographs of laser lines on planar targets "
                            "against a naive peak finder (give the folder of their clones); "
                            "inspect: the inspection's probability of detection per fault kind "
                            "and size, its false rejects on good picks, the time it adds")
    bench.add_argument("folder", nargs="?", type=Path, default=None,
                       help="real: the folder holding clones of the photographs' repositories "
                            "(benchmarks.real_photos.SETS says which; the bench names any missing)")
    bench.add_argument("--out", type=Path, required=True)
    bench.add_argument("--quick", action="store_true", help="fewer frames/parts (for CI)")
    bench.add_argument("--picks", type=int, default=None,
                       help="place: picks per part in each cell (default 10; --quick 4)")
    bench.add_argument("--cells", default=None,
                       help="place: the realistic cells' perturb seeds, comma-separated "
                            "(default 1,2,3,4,5; --quick 1)")
    bench.add_argument("--parts", default=None,
                       help="place: part names, comma-separated: the reference parts "
                            "(idler_riser, featuretype, ADIS16480, cycloidal) and the "
                            "procedural block, bracket, fan_disk, crowned_block (default: all "
                            "eight; --quick block); for checks on parts the bench was not made "
                            "on, bracket_wide, block_tall, fan_disk_6, dome and the public "
                            "meshes bunny and bone")
    bench.add_argument("--timing", action="store_true",
                       help="inspect: only the check's time, on good picks of every part on "
                            "one core (minutes; the whole bench takes about an hour)")
    bench.add_argument("--meshes", type=Path, default=None,
                       help="folder of the reference meshes and their manifest.json (or "
                            "$FLYSCAN_MESHES)")


def _seeds(text):
    """``--cells``: comma-separated whole numbers, or None."""
    if text is None:
        return None
    try:
        seeds = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise UsageError(f"--cells must be comma-separated whole numbers, got {text!r}") from None
    if not seeds or min(seeds) < 0:
        raise UsageError(f"--cells must name at least one perturb seed >= 0, got {text!r}")
    return seeds


def _names(text):
    """``--parts``: comma-separated names the benchmarks know, or None."""
    if text is None:
        return None
    from benchmarks.parts import DEMO_PART, PROCEDURAL_PARTS, REFERENCE_PARTS, VALIDATION_PARTS

    known = (DEMO_PART,) + tuple(PROCEDURAL_PARTS) + REFERENCE_PARTS + tuple(VALIDATION_PARTS)
    names = [v.strip() for v in text.split(",") if v.strip()]
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise UsageError(f"--parts: unknown part(s) {unknown or text!r}: choose from "
                         f"{', '.join(dict.fromkeys(known))}")
    return names


def run(args) -> int:
    from simulator.parts import MESHES_ENV

    if args.meshes is not None:
        if not (args.meshes / "manifest.json").is_file():
            raise UsageError(f"--meshes {args.meshes} holds no manifest.json")
        os.environ[MESHES_ENV] = str(args.meshes)  # the benchmarks' reference-part loader reads it
    if args.what == "stripe":
        from benchmarks import stripe as bench
    elif args.what == "simulate":
        from benchmarks import simulate as bench
    elif args.what == "service":
        from benchmarks import service as bench
    elif args.what == "hardware":
        from benchmarks import hardware as bench
    elif args.what == "surfaces":
        from benchmarks import surfaces as bench
    elif args.what == "calibrate":
        from benchmarks import calibrate as bench
    elif args.what == "coarse":
        from benchmarks import coarse as bench
    elif args.what == "edges":
        from benchmarks import edges as bench
    elif args.what == "place":
        from benchmarks import place as bench
    elif args.what == "inspect":
        from benchmarks import inspection as bench
    elif args.what == "abuse":
        from benchmarks import abuse as bench
    elif args.what == "pose_time":
        from benchmarks import pose_time as bench
    elif args.what == "planning":
        from benchmarks import planning as bench
    elif args.what == "real":
        from benchmarks import real_photos as bench
    elif args.what == "pose":
        from benchmarks import pose as bench
        from benchmarks import pose_limits
        limits = pose_limits.run(args.out, quick=args.quick)
        print(json.dumps(limits.get("summary", {}), indent=2))
    else:
        from benchmarks import scan as bench
    for option in ("picks", "cells", "parts"):
        if getattr(args, option) is not None and args.what != "place":
            raise UsageError(f"--{option} is for bench place only")
    if args.timing and args.what != "inspect":
        raise UsageError("--timing is for bench inspect only")
    if args.picks is not None and args.picks < 1:
        raise UsageError(f"--picks must be at least 1, got {args.picks}")
    if args.folder is not None and args.what != "real":
        raise UsageError(f"bench {args.what} takes no folder (only bench real does)")
    if args.what == "real":
        if args.folder is None:
            raise UsageError("bench real needs the folder holding clones of "
                             + ", ".join(f"https://github.com/{s.repository}" for s in bench.SETS)
                             + " (docs/stripe.md)")
        if not args.folder.is_dir():
            raise UsageError(f"bench real: {args.folder} is not a folder")
    extra = {}
    if args.what == "real":
        extra = {"folder": args.folder}
    if args.what == "place":
        extra = {"picks": args.picks, "cells": _seeds(args.cells), "parts": _names(args.parts)}
    runner = bench.run_timing if args.timing else bench.run
    try:
        result = runner(args.out, quick=args.quick, **extra)
    except FileNotFoundError as exc:  # bench real: a set's clone missing or incomplete
        raise UsageError(str(exc)) from None
    print(json.dumps(result.get("summary", {}), indent=2))
    print(f"written to {args.out}")
    return 0
