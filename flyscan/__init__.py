"""The flyscan command line: scan, simulate, serve, record, replay, calibrate, plan, parts, bench.

Every command calls the same library functions the service and the benchmarks use; each
command's module only parses its arguments, reports errors clearly and exits non-zero on
failure (2: bad input; 1: a pass that ran and failed). The command line is also where the
simulated cell is wired in (``flyscan serve --sim``: ``flyscan.simdevices``), the one part
of ``service`` that imports the simulator.
"""
from __future__ import annotations

import argparse
import atexit
import gc
import sys

from threadpoolctl import threadpool_limits

from flyscan import bench, calibrate, parts, plan, record, scan, serve, simulate
from flyscan.common import (EXIT_SCAN_FAILED, HelpFormatter, ScanError,
                            ScanFailed, UsageError, check_frame_spacing, join_number_lists,
                            version)

__all__ = ["main", "build_parser", "parse_args", "UsageError", "ScanError", "ScanFailed",
           "check_frame_spacing"]

_COMMANDS = {"scan": scan.run, "simulate": simulate.run, "serve": serve.run,
             "record": record.run_record, "replay": record.run_replay,
             "calibrate": calibrate.run, "plan": plan.run, "bench": bench.run,
             "parts": parts.run}


def build_parser() -> argparse.ArgumentParser:
    """The parser of every command (``flyscan --help``)."""
    parser = argparse.ArgumentParser(prog="flyscan", description=__doc__.splitlines()[0],
                                     formatter_class=HelpFormatter)
    parser.add_argument("--version", action="version", version=f"flyscan {version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    def command(name, **kwargs):
        return sub.add_parser(name, formatter_class=HelpFormatter,
                              description=kwargs.get("help"), **kwargs)

    calibrate.add_parser(command)
    scan.add_parser(command)
    simulate.add_parser(command)
    serve.add_parser(command)
    record.add_parsers(command)
    plan.add_parser(command)
    parts.add_parser(command)
    bench.add_parser(command)
    return parser


def parse_args(argv=None) -> argparse.Namespace:
    return build_parser().parse_args(join_number_lists(list(sys.argv[1:] if argv is None
                                                            else argv)))


def main(argv=None) -> int:
    # A batch command lives for seconds: the cyclic collector's passes over the objects its
    # imports make (numba, trimesh) cost 0.1-0.2 s and free nothing that matters, and its last
    # collections at exit 0.3 s (frozen, they are skipped; in a test run, at the test's end).
    # The service lives on and keeps the collector.
    collecting = gc.isenabled()
    gc.disable()
    try:
        args = parse_args(argv)
        if args.command == "serve" or getattr(args, "what", None) == "hardware":
            gc.enable()  # long-lived: the service runs inside
        else:
            atexit.unregister(gc.freeze)
            atexit.register(gc.freeze)
        return _run(args)
    finally:
        if collecting:
            gc.enable()


def _run(args) -> int:
    # A real-time process keeps BLAS to one thread: OpenBLAS workers spin for ~100 ms after
    # each call and steal the other core (docs/design.md).
    from scanner_core.cad import PartError
    from scanner_core.geometry.calibration import CalibrationError
    from scanner_core.calibration.plane import PlaneCalibrationError
    from scanner_core.calibration.views import ViewCalibrationError
    from scanner_core.calibration.session import SessionError
    from scanner_core.recording import RecordingError
    from scanner_core.scanplan import PlanError

    errors = (UsageError, PartError, CalibrationError, ScanError, SessionError,
              ViewCalibrationError, PlaneCalibrationError, RecordingError, PlanError)
    if args.command in ("simulate", "scan", "bench", "calibrate"):
        from simulator.embree import EmbreeError
        from simulator.virtual_setup import SetupError

        errors += (SetupError, EmbreeError)
    with threadpool_limits(limits=1, user_api="blas"):
        try:
            return _COMMANDS[args.command](args)
        except errors as exc:
            print(f"flyscan {args.command}: error: {exc}", file=sys.stderr)
            return 2
        except ScanFailed as exc:
            print(f"flyscan {args.command}: scan failed: {exc}", file=sys.stderr)
            return EXIT_SCAN_FAILED
