"""``flyscan calibrate``: a calibration from a session (recorded, or simulated in the
simulated cell), its report, and how far it is from the truth when the cell is simulated."""
from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path

import numpy as np

from flyscan.common import ScanError, UsageError, non_negative_int
from flyscan.simcell import sim_cell

__all__ = ["add_parser", "run"]


def add_parser(command) -> None:
    cal = command("calibrate", help="calibrate the views, the light plane, the clocks and the "
                                    "LED offset from a session (simulated, or a folder)")
    where = cal.add_mutually_exclusive_group(required=True)
    where.add_argument("--sim", action="store_true",
                       help="a simulated session in the simulated cell (see --effects)")
    where.add_argument("--session", type=Path, help="a session folder (scanner_core.calibration.session)")
    where.add_argument("--url", help="a running service: a session recorded by it with its "
                                     "robot, fitted there (docs/commissioning.md)")
    cal.add_argument("--session-id", default=None,
                     help="with --url: a session the cell controller recorded, to fit")
    cal.add_argument("--activate", action="store_true",
                     help="with --url: make the result the service's calibration")
    cal.add_argument("--token", default=os.environ.get("FLYSCAN_TOKEN"),
                     help="with --url: bearer token (default $FLYSCAN_TOKEN)")
    cal.add_argument("--seed", type=non_negative_int, default=0,
                     help="positions, stage errors and image noise of the simulated session")
    cal.add_argument("--perturb-seed", type=non_negative_int, default=None,
                     help="perturb the simulated cell's geometry and effects (repeatably)")
    cal.add_argument("--effects", default="all",
                     help="the simulated cell's real-cell effects: 'all' (default), 'none' or a "
                          "comma-separated choice of lens, exposure, clocks, robot, led")
    cal.add_argument("--led-positions", type=non_negative_int, default=200,
                     help="positions of the LED (simulated session, or --url's plan)")
    cal.add_argument("--sphere-positions", type=non_negative_int, default=40,
                     help="positions of the sphere (simulated session, or --url's plan)")
    cal.add_argument("--write-session", type=Path, default=None,
                     help="also write the simulated session as a folder (PNG frames, CSV)")
    cal.add_argument("--out", type=Path, required=True, help="the calibration JSON to write")


def run(args) -> int:
    from scanner_core.geometry.calibration import save_calibration
    from scanner_core.fileio import save_json_atomic
    from scanner_core.calibration.session import calibrate_session, load_session, write_session

    if args.out.exists() and args.out.is_dir():
        raise UsageError(f"--out {args.out} is a folder; give the calibration file's path")
    if args.url is None and (args.session_id or args.activate):
        raise UsageError("--session-id and --activate go with --url")
    if args.url is not None:
        from flyscan.calibrate_url import run_url

        return run_url(args)
    cell = None
    if args.session is not None:
        session = load_session(args.session)
    else:
        from simulator.calsession import simulate_session

        for name in ("led_positions", "sphere_positions"):
            if getattr(args, name) < 3:
                raise UsageError(f"--{name.replace('_', '-')} must be at least 3")
        cell = sim_cell(args.perturb_seed, args.effects)
        session = simulate_session(cell, seed=args.seed, led_count=args.led_positions,
                                   sphere_count=args.sphere_positions)
        if args.write_session is not None:
            write_session(args.write_session, session)
            print(f"session written to {args.write_session}")
    t0 = time.perf_counter()
    try:
        calibration, report = calibrate_session(session, seed=args.seed,
                                                progress=lambda m: print(m, flush=True))
    except (ValueError, np.linalg.LinAlgError) as exc:
        # The session's own errors (too few positions, a plane the sheet never cut, a pass
        # without the marker) say what to fix; nothing is written.
        raise ScanError(f"calibration failed: {exc}") from None
    report["time_s"] = round(time.perf_counter() - t0, 2)
    if cell is not None:
        from simulator.calsession import evaluate_calibration
        from simulator.effects import parse_effects

        # Which simulated cell it was made in: `flyscan scan --calibration` scans in the same.
        made_in = {"perturb_seed": args.perturb_seed, "effects": list(parse_effects(args.effects))}
        calibration = dataclasses.replace(
            calibration, provenance={**calibration.provenance, "simulated_cell": made_in})
        report["simulated_cell"] = made_in

        truth = evaluate_calibration(calibration, cell)
        report["against_truth"] = truth
        print("against the simulated truth: plane normal {plane_normal_deg:.4f} deg, offset "
              "{plane_offset_um:.1f} um; LED offset {led_offset_um:.1f} um; clock "
              "{clock_offset_ms:+.3f} ms".format(**truth))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_calibration(args.out, calibration)
    save_json_atomic(args.out.with_suffix(".report.json"), report)
    print(f"calibration written to {args.out} (report {args.out.with_suffix('.report.json')})")
    return 0
