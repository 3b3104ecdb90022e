"""What the commands share: their errors and exit codes, argument types, and input checks
that run before any pass (a bad input writes nothing)."""
from __future__ import annotations

import argparse
import dataclasses
import re
import tempfile
from pathlib import Path

__all__ = ["UsageError", "ScanError", "ScanFailed", "EXIT_SCAN_FAILED", "MAX_SPEED_MM_S",
           "MAX_FPS", "non_negative_int", "join_number_lists", "HelpFormatter",
           "version", "check_out_dir", "check_frame_spacing", "check_part_args",
           "load_part_model", "print_pose", "write_scan_files"]


class UsageError(ValueError):
    """Bad command-line input."""


class ScanError(RuntimeError):
    """Bad input found only once the pass or sweep ran: the marker's views disagree (the
    calibration does not fit the cell), or the simulated camera sees nothing."""


class ScanFailed(RuntimeError):
    """The pass ran but gave no usable scan (``scanner_core.pipeline.finish.pass_failure``)."""


#: Sanity limits on the pass: beyond them a typo (mm/s for m/s, a frame rate for a period)
#: would simulate for hours.
MAX_SPEED_MM_S = 5000.0
MAX_FPS = 2000.0
#: Options whose value is a list of numbers that may start with a minus sign.
NUMBER_LIST_OPTIONS = ("--misplace", "--laser", "--camera")
#: Exit status of a pass that ran and failed (bad input exits with 2).
EXIT_SCAN_FAILED = 1


def non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def join_number_lists(argv: list[str]) -> list[str]:
    """``--misplace -1,0,0,...`` -> ``--misplace=-1,0,0,...``.

    argparse takes a value with a leading minus for an option unless it is a single number;
    a list of numbers is not, yet misplacements are negative half the time.
    """
    out = []
    args = iter(argv)
    for arg in args:
        if arg in NUMBER_LIST_OPTIONS:
            value = next(args, None)
            if value is not None and value.startswith("-") and _NUMBER_LIST.match(value):
                out.append(f"{arg}={value}")
                continue
            out.append(arg)
            if value is not None:
                out.append(value)
            continue
        out.append(arg)
    return out


_NUMBER_LIST = re.compile(r"^\s*-?[\d.]")


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows an option's default, unless it has none or its help already names it."""

    def _get_help_string(self, action):
        if (action.default is None or action.default is False
                or action.default == argparse.SUPPRESS or "default" in (action.help or "")):
            return action.help
        return super()._get_help_string(action)


def version() -> str:
    from importlib.metadata import PackageNotFoundError, version as installed

    try:
        return installed("flyscan")
    except PackageNotFoundError:
        return "unknown (not installed)"


def check_out_dir(out: Path) -> None:
    """Refuse an output folder that cannot be written, before the pass runs (writes nothing)."""
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} exists and is not a directory")
    existing = out
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise UsageError(f"--out {out}: {existing} is a file, not a directory")
    try:  # os.access is no guide when running as root, or on a read-only mount
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as exc:
        raise UsageError(f"--out {out} cannot be written: no file can be created in "
                         f"{existing} ({exc.strerror})") from None


def check_frame_spacing(part, speed_mm_s: float, fps: float) -> None:
    """Refuse a pass whose frames are too far apart (``scanner_core.scanplan.too_few_profiles``)."""
    from scanner_core.scanplan import too_few_profiles

    refusal = too_few_profiles(part, speed_mm_s, fps)
    if refusal is not None:
        raise UsageError(refusal)


def check_part_args(args) -> None:
    if getattr(args, "demo", False) and args.units is not None:
        raise UsageError("--units applies only to --part: the demo part is built in mm")
    if args.part is not None and args.units is None:
        raise UsageError("--units is required with --part: a mesh file carries no reliable unit")
    if args.part is None and args.units is not None:
        raise UsageError("--units applies only to --part")


def load_part_model(args):
    """The scanner's model of the part of ``--part``/``--units`` with its ``--grasp``
    (``scanner_core.cad.PartModel``), or None without ``--part``. With ``--plan``, the
    plan's nominal grasp (its grasp turned by its pass direction), after checking that the
    plan was made for this mesh file; the plan read is kept as ``args.loaded_plan``."""
    from scanner_core.cad import load_part
    from scanner_core.scanplan import check_plan_grasp, load_scan_plan

    args.loaded_plan = None
    if args.part is None:
        return None
    plan_path = getattr(args, "plan", None)
    if plan_path is None:
        return load_part(args.part, args.units, grasp=getattr(args, "grasp", None))
    plan = load_scan_plan(plan_path)
    plan.check_mesh(args.part)
    part = load_part(args.part, args.units, grasp=plan.nominal_grasp)
    check_plan_grasp(plan, part.vertices)
    args.loaded_plan = plan
    if plan.inspection is not None:  # the part's own thresholds, over the command's
        part = dataclasses.replace(part, inspection=plan.inspection)
    return part


def add_act_tolerance(parser) -> None:
    """``--act-tolerance-mm`` and ``--act-tolerance-deg``: the placement tolerance the pose's
    ``act`` verdict holds it to (``scanner_core.pose.registration.PoseParams``; not imported here: every
    command's parser is built at start, and the pose's imports are not light)."""
    parser.add_argument("--act-tolerance-mm", type=float, default=None,
                        help="placement tolerance, mm: the pose is acted on only when every "
                             "translation's 3 sigma lies within it (default 0.1)")
    parser.add_argument("--act-tolerance-deg", type=float, default=None,
                        help="placement tolerance, degrees, for the rotations (default 0.1)")


def pose_params(args):
    """The ``PoseParams`` of ``--act-tolerance-mm``/``--act-tolerance-deg``; a usage error
    for a tolerance that is not finite and positive."""
    from scanner_core.pose.registration import PoseParams

    given = {name: value for name, value in (("act_tolerance_mm", args.act_tolerance_mm),
                                              ("act_tolerance_deg", args.act_tolerance_deg))
             if value is not None}
    try:
        return PoseParams(**given)
    except ValueError as exc:
        raise UsageError(str(exc).replace("PoseParams.act_tolerance_", "--act-tolerance-")
                         .replace("_", "-")) from None


def print_pose(report: dict) -> None:
    """One line on the pose's verdict: act, or why not."""
    pose = report.get("pose")
    if not pose:
        return
    if "refused" in pose:
        print(f"pose: refused: {pose['refused']}")
        return
    move = pose["misplacement"]
    words = (f"misplacement {move['translation_mm']} mm, {move['rotation_deg']} degrees")
    if pose.get("act"):
        print(f"pose: act: {words}")
    else:
        print(f"pose: do not act: {'; '.join(pose.get('act_reasons') or [])}")


def write_scan_files(out, scan, report) -> dict:
    """The scan's files (``flyscan scan`` and ``flyscan replay``): a failed pass keeps its
    report (what was acquired, why it failed) and writes no cloud that could pass for a scan:
    ScanFailed after writing it."""
    from scanner_core.fileio import save_json_atomic
    from scanner_core.io.scanfiles import save_scan

    if report.get("state") == "failed":
        out.mkdir(parents=True, exist_ok=True)
        save_json_atomic(out / "report.json", report)
        raise ScanFailed(f"{report['reason']}; the pass's report: {out / 'report.json'}")
    paths = save_scan(out, scan, report)
    print_pose(report)
    return paths
