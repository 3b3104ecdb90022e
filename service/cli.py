"""The flyscan command line: scan, simulate, serve, benchmark.

Every command calls the same library functions the service and the benchmarks use; this
module only parses arguments, reports errors clearly and exits non-zero on failure.
"""
from __future__ import annotations

import argparse
import atexit
import dataclasses
import gc
import json
import os
import re
import sys
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits


class UsageError(ValueError):
    """Bad command-line input."""


class ScanError(RuntimeError):
    """Bad input found only once the pass or sweep ran: the marker's views disagree (the
    calibration does not fit the cell), or the simulated camera sees nothing."""


class ScanFailed(RuntimeError):
    """The pass ran but gave no usable scan (no profile, or no point)."""


#: Sanity limits on the pass: beyond them a typo (mm/s for m/s, a frame rate for a period)
#: would simulate for hours.
MAX_SPEED_MM_S = 5000.0
MAX_FPS = 2000.0
#: A pass must give at least this many profiles along the part, or it cannot be scanned.
MIN_PROFILES = 5
#: Options whose value is a list of numbers that may start with a minus sign.
NUMBER_LIST_OPTIONS = ("--misplace", "--laser", "--camera")
#: Exit status of a pass that ran and failed (bad input exits with 2).
EXIT_SCAN_FAILED = 1
#: Seconds a stopping service waits for open connections (server-sent events) to close.
SHUTDOWN_GRACE_S = 3.0


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def _join_number_lists(argv: list[str]) -> list[str]:
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


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows an option's default, unless it has none or its help already names it."""

    def _get_help_string(self, action):
        if (action.default is None or action.default is False
                or action.default == argparse.SUPPRESS or "default" in (action.help or "")):
            return action.help
        return super()._get_help_string(action)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("flyscan")
    except PackageNotFoundError:
        return "unknown (not installed)"


def _parse_args(argv):
    from scanner_core.exposure import EXPOSURE_MODES
    from scanner_core.stripe import METHODS
    from simulator.parts import GRASPS

    argv = _join_number_lists(list(sys.argv[1:] if argv is None else argv))
    parser = argparse.ArgumentParser(prog="flyscan", description=__doc__.splitlines()[0],
                                     formatter_class=_HelpFormatter)
    parser.add_argument("--version", action="version", version=f"flyscan {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    def command(name, **kwargs):
        return sub.add_parser(name, formatter_class=_HelpFormatter,
                              description=kwargs.get("help"), **kwargs)

    cal = command("calibrate", help="calibrate the views, the light plane, the clocks and the "
                                    "LED offset from a session (simulated, or a folder)")
    where = cal.add_mutually_exclusive_group(required=True)
    where.add_argument("--sim", action="store_true",
                       help="a simulated session in the simulated cell (see --effects)")
    where.add_argument("--session", type=Path, help="a session folder (service.calibrate)")
    cal.add_argument("--seed", type=_non_negative_int, default=0,
                     help="positions, stage errors and image noise of the simulated session")
    cal.add_argument("--perturb-seed", type=_non_negative_int, default=None,
                     help="perturb the simulated cell's geometry and effects (repeatably)")
    cal.add_argument("--effects", default="all",
                     help="the simulated cell's real-cell effects: 'all' (default), 'none' or a "
                          "comma-separated choice of lens, exposure, clocks, robot, led")
    cal.add_argument("--led-positions", type=_non_negative_int, default=200,
                     help="stage positions of the LED (simulated session)")
    cal.add_argument("--sphere-positions", type=_non_negative_int, default=40,
                     help="stage positions of the sphere (simulated session)")
    cal.add_argument("--write-session", type=Path, default=None,
                     help="also write the simulated session as a folder (PNG frames, CSV)")
    cal.add_argument("--out", type=Path, required=True, help="the calibration JSON to write")

    scan = command("scan", help="scan a CAD part in the simulated cell")
    src = scan.add_mutually_exclusive_group(required=True)
    src.add_argument("--part", type=Path, help="mesh file (STL, OBJ, PLY)")
    src.add_argument("--demo", action="store_true", help="the built-in procedural block")
    scan.add_argument("--units", default=None, help="unit of the mesh file: mm, cm, m or inch")
    scan.add_argument("--preset", choices=["default", "fast", "slow"], default="default",
                      help="pass preset: default 200 mm/s at 162 fps; the paper's fast (1 m/s, "
                           "162 fps) and slow (50 mm/s, 16 fps) configurations")
    scan.add_argument("--speed", type=float, help="nominal pass speed, mm/s")
    scan.add_argument("--fps", type=float, help="camera frame rate, Hz")
    scan.add_argument("--misplace", default=None,
                      help="'tx,ty,tz,rx,ry,rz': the part's misplacement in the gripper, mm and "
                           "a rotation vector in degrees, in {T}; may start with a minus")
    scan.add_argument("--seed", type=_non_negative_int, default=0, help="image noise seed")
    scan.add_argument("--perturb-seed", type=_non_negative_int, default=None,
                      help="perturb the simulated cell's true geometry (repeatably)")
    scan.add_argument("--calibration", type=Path, default=None,
                      help="calibration JSON the scanner uses (default: the cell's truth)")
    scan.add_argument("--grasp", choices=GRASPS, default="centred",
                      help="nominal grasp: the part centred under the TCP (default); 'flat': "
                           "turned a quarter so its smallest extent hangs along z_T (held by its "
                           "broadest side, as a suction cup holds it), then centred; 'identity': "
                           "the CAD origin at the TCP")
    scan.add_argument("--method", default="cog", choices=METHODS, help="sub-pixel stripe estimator")
    scan.add_argument("--surface", choices=["default", "matte", "dark", "shiny"],
                      default="default",
                      help="the simulated part's surface: the reference matte white, a matte cast, "
                           "a dark anodised or a shiny machined part (simulator.surfaces)")
    scan.add_argument("--exposure", choices=list(EXPOSURE_MODES), default="fixed",
                      help="exposure control: fixed, dynamic (from the previous frames' stripe "
                           "peaks) or multiple (two exposures alternating)")
    scan.add_argument("--effects", default=None,
                      help="what a real cell does that the scanner is not told: 'all', 'none' or "
                           "a comma-separated choice of lens, exposure, clocks, robot, led "
                           "(simulator.effects); default: those of the cell a --calibration "
                           "made by 'calibrate --sim' was made in, else none")
    scan.add_argument("--drop-rate", type=float, default=0.0, help="fraction of frames lost")
    scan.add_argument("--no-eval", action="store_true", help="skip the ground-truth accuracy")
    scan.add_argument("--out", type=Path, required=True,
                      help="folder for cloud.ply, edges.ply and report.json")

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

    serve = command("serve", help="run the real-time scanning service (REST, ZeroMQ, "
                                         "status page)")
    serve.add_argument("--config", type=Path, default=None, help="settings file (TOML)")
    serve.add_argument("--sim", action="store_true", default=None,
                       help="simulated devices: the reference cell with its camera and robot")
    serve.add_argument("--host", default=None, help="REST bind address (default 127.0.0.1)")
    serve.add_argument("--port", type=int, default=None, help="REST port (default 8000)")
    serve.add_argument("--zmq", default=None, help="ZeroMQ PUB endpoint (default tcp://127.0.0.1:5556)")
    serve.add_argument("--robot", default=None,
                       help="ur://HOST: the UR robot (ur-rtde); with --sim an RTDE emulator "
                            "is started at HOST and serves the simulated robot")
    serve.add_argument("--camera", default=None,
                       help="opencv:0, opencv:/dev/videoN, video:FILE, gstreamer:PIPELINE, "
                            "genicam:PRODUCER.cti[#SERIAL] or replay:FOLDER (not with --sim)")
    serve.add_argument("--data", type=Path, default=None, help="folder for scans and parts "
                                                               "(default ./flyscan-data)")
    serve.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])

    record = command("record", help="record the next pass of a running service (every frame "
                                    "and the robot's poses) for replay")
    record.add_argument("--url", default="http://127.0.0.1:8000", help="the service")
    record.add_argument("--part", default=None, help="part to scan (default the service's)")
    record.add_argument("--token", default=os.environ.get("FLYSCAN_TOKEN"),
                        help="bearer token, if the service has one (default $FLYSCAN_TOKEN)")
    record.add_argument("--timeout", type=float, default=60.0,
                        help="seconds to wait for the pass and its recording")

    replay = command("replay", help="run a recorded pass through the pipeline offline")
    replay.add_argument("recording", type=Path, help="a folder `flyscan record` made")
    replay.add_argument("--out", type=Path, required=True,
                        help="folder for cloud.ply, edges.ply and report.json")

    bench = command("bench", help="benchmarks: JSON figures and PNG charts")
    bench.add_argument("what", choices=["stripe", "scan", "simulate", "service", "pose",
                                        "coarse", "hardware", "surfaces", "calibrate", "edges"],
                       help="pose: registration accuracy, time, basin, sigma calibration and "
                            "the side-by-side with Open3D and small_gicp, then where pose and "
                            "edges break; coarse: the pose's coarse stage against OpenCV's "
                            "point-pair features (PPF); hardware: the UR cross-check through "
                            "ur-rtde, the robot link's loss and recovery, replay against real "
                            "time; edges: edge points per part and edge kind on creased, "
                            "curved and walled parts")
    bench.add_argument("--out", type=Path, required=True)
    bench.add_argument("--quick", action="store_true", help="fewer frames/parts (for CI)")
    bench.add_argument("--meshes", type=Path, default=None,
                       help="folder of the reference meshes and their manifest.json (default: "
                            "$FLYSCAN_MESHES, or ../shared/data/meshes beside a source checkout)")
    return parser.parse_args(argv)


def _sim_cell(perturb_seed, effects_text):
    """The simulated cell: the reference, perturbed and with a real cell's effects as asked."""
    from simulator.effects import simulated_cell

    try:
        return simulated_cell(perturb_seed, effects_text)
    except ValueError as exc:
        raise UsageError(f"--effects: {exc}") from None


def _scan_effects(args, calibration) -> str:
    """``--effects``, or else those of the simulated cell the calibration was made in (its
    provenance says, when ``calibrate --sim`` made it), or else none: a calibration learned in
    the realistic cell is scanned in that cell."""
    if args.effects is not None:
        return args.effects
    made_in = (calibration.provenance.get("simulated_cell") if calibration is not None else None)
    if not isinstance(made_in, dict):
        return "none"
    effects = ",".join(made_in.get("effects") or []) or "none"
    if made_in.get("perturb_seed") != args.perturb_seed:
        print(f"flyscan scan: note: the calibration was made in the simulated cell of "
              f"--perturb-seed {made_in.get('perturb_seed')}, this scan's is "
              f"{args.perturb_seed}: it will not fit", file=sys.stderr)
    print(f"flyscan scan: the simulated cell's effects: {effects} (as where the calibration "
          f"was made; --effects to choose)", file=sys.stderr)
    return effects


def _cmd_calibrate(args) -> int:
    from scanner_core.calibration import save_calibration
    from scanner_core.fileio import save_json_atomic
    from service.calibrate import calibrate_session, load_session, write_session

    if args.out.exists() and args.out.is_dir():
        raise UsageError(f"--out {args.out} is a folder; give the calibration file's path")
    cell = None
    if args.session is not None:
        session = load_session(args.session)
    else:
        from simulator.calsession import simulate_session

        for name in ("led_positions", "sphere_positions"):
            if getattr(args, name) < 3:
                raise UsageError(f"--{name.replace('_', '-')} must be at least 3")
        cell = _sim_cell(args.perturb_seed, args.effects)
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


def _cmd_scan(args) -> int:
    from scanner_core.calibration import load_calibration
    from scanner_core.exposure import ExposureParams
    from scanner_core.pipeline import PipelineParams
    from scanner_core.scanio import save_scan
    from scanner_core.fileio import save_json_atomic
    from simulator.cell import PASS_PRESETS, load_cell
    from simulator.parts import check_fits
    from simulator.session import parse_misplacement, run_simulated_scan
    from simulator.surfaces import with_surface

    # Everything is checked before the pass is simulated: a bad input writes nothing.
    _check_part_args(args)
    for name, limit in (("speed", MAX_SPEED_MM_S), ("fps", MAX_FPS)):
        value = getattr(args, name)
        if value is not None and not 0 < value <= limit:
            raise UsageError(f"--{name} must be positive and at most {limit:g}, got {value}")
    _check_out_dir(args.out)
    if not 0.0 <= args.drop_rate < 1.0:
        raise UsageError(f"--drop-rate must be in [0, 1), got {args.drop_rate}")
    try:
        misplacement = parse_misplacement(args.misplace)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    part = with_surface(_load_part(args), args.surface)
    check_fits(part, pose=misplacement @ part.grasp)
    calibration = load_calibration(args.calibration) if args.calibration else None
    cell = _sim_cell(args.perturb_seed, _scan_effects(args, calibration))
    preset = PASS_PRESETS[args.preset]
    cell = cell.with_pass(speed_mm_s=args.speed or preset.speed_mm_s, fps=args.fps or preset.fps)
    _check_frame_spacing(part, cell.pass_profile.speed_mm_s, cell.pass_profile.fps)
    if calibration is not None:
        calibration.check_image_size(cell.calibration.camera.width,
                                     cell.calibration.camera.height)
    params = PipelineParams(stripe_method=args.method,
                            exposure=ExposureParams(mode=args.exposure))
    t0 = time.perf_counter()
    scan, report = run_simulated_scan(part, cell, calibration=calibration,
                                      misplacement=misplacement, seed=args.seed,
                                      drop_rate=args.drop_rate,
                                      params=params,
                                      evaluate=not args.no_eval)
    if scan.marker_residual_px > params.max_marker_residual_px:
        raise ScanError(
            f"the marker's three views disagree (median residual {scan.marker_residual_px:.2f} px "
            f"over {scan.frames + scan.frames_unplaced} frames): does the calibration fit the cell?")
    report["wall_s"] = round(time.perf_counter() - t0, 3)
    failure = _scan_failure(scan)
    if failure is not None:
        # The pass's record is kept: its report says what was acquired and why it failed.
        report.update(status="failed", failure=failure)
        args.out.mkdir(parents=True, exist_ok=True)
        save_json_atomic(args.out / "report.json", report)
        raise ScanFailed(f"{failure}; the pass's report: {args.out / 'report.json'}")
    paths = save_scan(args.out, scan, report)
    acc = report["ground_truth"].get("accuracy", {})
    print(f"scanned {part.name}: {report['frames']} frames, {report['points']} points, "
          f"processing {report['timings_ms']['processing']:.0f} ms for "
          f"{report['camera_time_s']:.2f} s of camera time")
    if acc.get("points_evaluated"):
        print(f"accuracy: RMS {acc['rms_um']:.1f} um, p99 {acc['p99_um']:.1f} um, "
              f"points without a visible source {acc.get('unmatched_points')}")
    for key, path in paths.items():
        print(f"{key}: {path}")
    return 0


def _scan_failure(scan) -> str | None:
    """Why a pass that ran gave no usable scan, or None."""
    if scan.frames == 0:
        return f"the marker never triggered: no profile was acquired (the pass ended: {scan.end_reason})"
    if len(scan.cloud) == 0:
        return (f"no points: {scan.frames} profiles were acquired but the stripe was found on "
                "none of them")
    return None


def _check_out_dir(out: Path) -> None:
    """Refuse an output folder that cannot be written, before the pass runs (writes nothing)."""
    import tempfile

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


def _check_frame_spacing(part, speed_mm_s: float, fps: float) -> None:
    """Refuse a pass whose frames are too far apart to give `MIN_PROFILES` on the part."""
    spacing = speed_mm_s / fps
    length = float(part.extents_t[1])  # the part moves along y_T through the light sheet
    if length / spacing < MIN_PROFILES:
        need = MIN_PROFILES * speed_mm_s / length
        raise UsageError(
            f"at {speed_mm_s:g} mm/s and {fps:g} fps the frames are {spacing:.3g} mm apart, "
            f"too few for the part's {length:.1f} mm along the pass (at least {MIN_PROFILES} "
            f"profiles): raise --fps to {need:.3g} or more, or lower --speed")


def _check_part_args(args) -> None:
    if args.demo and args.units is not None:
        raise UsageError("--units applies only to --part: the demo part is built in mm")
    if args.part is not None and args.units is None:
        raise UsageError("--units is required with --part: a mesh file carries no reliable unit")


def _load_part(args):
    """The part of ``--part``/``--units`` or ``--demo``, with the ``--grasp`` asked for."""
    from simulator.parts import block_with_holes_and_steps, load_part, part_from_mesh

    if args.demo:
        return part_from_mesh(block_with_holes_and_steps(), name="demo-block", grasp=args.grasp)
    return load_part(args.part, args.units, grasp=args.grasp)


def _parse_point(text: str | None, option: str):
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


class _SweepProgress:
    """Prints a line on stderr at every tenth of a long sweep."""

    def __init__(self):
        self.shown = -1

    def __call__(self, done: int, total: int) -> None:
        tenth = 10 * done // max(total, 1)
        if total >= PROGRESS_RAYS and tenth > self.shown:
            self.shown = tenth
            print(f"swept {done / 1e6:.0f} of {total / 1e6:.0f} M rays ({10 * tenth} %)",
                  file=sys.stderr, flush=True)


def _cmd_simulate(args) -> int:
    from concurrent.futures import ThreadPoolExecutor

    from simulator.cell import load_cell
    from simulator.parts import check_fits
    from simulator.virtual_setup import (DEFAULT_RAYS_PER_LINE, DEFAULT_STEP_MM, predict_cloud,
                                         prepare, reference_setup, save_predicted_cloud,
                                         warm_up)

    _check_part_args(args)
    if args.out.suffix.lower() != ".ply":
        raise UsageError(f"--out must name a .ply file, got {args.out}")
    if args.out.is_dir():
        raise UsageError(f"--out {args.out} is a directory; give a file name ending in .ply")
    if args.threads < 1:
        raise UsageError(f"--threads must be >= 1, got {args.threads}")
    laser, camera = _parse_point(args.laser, "--laser"), _parse_point(args.camera, "--camera")
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
                          progress=_SweepProgress())
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


def _cmd_record(args) -> int:
    from clients.http_client import FlyscanClient, FlyscanError, ScanFailed as PassFailed

    deadline = time.monotonic() + args.timeout
    try:
        with FlyscanClient(args.url, token=args.token) as client:
            scan_id = client.arm(part=args.part, record=True)
            print(f"armed {scan_id}: waiting for the pass", file=sys.stderr, flush=True)
            try:
                info = client.wait(scan_id, timeout=args.timeout)
            except PassFailed as exc:
                info = exc.info  # a failed pass is recorded too: that is when it is wanted
            while (info.get("recording") or {}).get("state") == "recording":
                if time.monotonic() > deadline:
                    raise ScanError(f"the recording of {scan_id} was not written within "
                                    f"{args.timeout:g} s")
                time.sleep(0.2)
                info = client.scan(scan_id)
    except (FlyscanError, TimeoutError, OSError) as exc:
        raise ScanError(f"{args.url}: {exc}") from None
    recording = info.get("recording") or {}
    if not recording.get("path"):
        raise ScanError(f"scan {scan_id} ({info['state']}) was not recorded: "
                        f"{recording.get('error', 'the service gave no recording')}")
    print(f"recorded {scan_id} ({info['state']}): {recording['frames']} frames, "
          f"{recording['robot_samples']} robot samples, {recording['bytes'] / 1e6:.0f} MB in "
          f"{recording['path']} (on the service's machine)")
    return 0


def _cmd_replay(args) -> int:
    from scanner_core.report import scan_report
    from scanner_core.scanio import save_scan
    from service.recording import RecordingError, load_recording, replay_recording

    _check_out_dir(args.out)
    try:
        recording = load_recording(args.recording)
    except RecordingError as exc:
        raise UsageError(str(exc)) from None
    t0 = time.perf_counter()
    scan = replay_recording(recording)
    wall_s = time.perf_counter() - t0
    recorded_s = recording.frame_count / recording.fps
    report = scan_report(scan, None, replay={
        "recording": str(args.recording), "frames": recording.frame_count, "wall_s": round(wall_s, 3),
        "times_real_time": round(recorded_s / wall_s, 2) if wall_s > 0 else None})
    failure = _scan_failure(scan)
    if failure is not None:
        report.update(status="failed", failure=failure)
    paths = save_scan(args.out, scan, report)
    print(f"replayed {recording.frame_count} frames ({recorded_s:.2f} s of camera time) in "
          f"{wall_s:.2f} s, {recorded_s / wall_s:.1f} x real time: {scan.frames} profiles, "
          f"{len(scan.cloud)} points")
    for key, path in paths.items():
        print(f"{key}: {path}")
    if failure is not None:
        raise ScanFailed(failure)
    return 0


def _cmd_serve(args) -> int:
    import logging

    import uvicorn
    from pydantic import ValidationError

    from service.api import create_app
    from service.daemon import Service
    from service.settings import load_settings

    try:
        settings = load_settings(args.config, sim=args.sim, host=args.host, port=args.port,
                                 zmq=args.zmq, robot=args.robot, camera=args.camera,
                                 data=args.data)
        service = Service(settings)
    except FileNotFoundError as exc:
        raise UsageError(str(exc)) from None
    except ValidationError as exc:
        first = exc.errors()[0]
        raise UsageError(f"setting {'.'.join(map(str, first['loc']))}: {first['msg']}") from None
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    _check_addresses(settings)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(name)s: %(message)s")
    url = f"http://{settings.host}:{settings.port}/"
    print(f"flyscan serve: status page {url}, REST {url}docs, ZeroMQ {settings.zmq}, "
          f"data {settings.data.resolve()}{' (simulated cell)' if settings.sim else ''}",
          flush=True)
    # Open event streams (a status page left open) must not hold up a Ctrl-C for ever.
    config = uvicorn.Config(create_app(service=service), host=settings.host, port=settings.port,
                            log_level=args.log_level, access_log=False,
                            timeout_graceful_shutdown=SHUTDOWN_GRACE_S)
    server = uvicorn.Server(config)
    try:
        server.run()
    except KeyboardInterrupt:  # uvicorn re-raises Ctrl-C once it has shut down cleanly
        pass
    return 0 if server.started else 2


def _check_addresses(settings) -> None:
    """Both addresses free before anything starts: a clear error, not a start-up traceback."""
    import socket

    import zmq

    try:
        with socket.create_server((settings.host, settings.port)):
            pass
    except OSError as exc:
        raise UsageError(f"cannot serve HTTP on {settings.host}:{settings.port}: {exc.strerror}") from None
    probe = zmq.Context.instance().socket(zmq.PUB)
    try:
        probe.bind(settings.zmq)
    except zmq.ZMQError as exc:
        raise UsageError(f"cannot bind the ZeroMQ publisher to {settings.zmq}: {exc}") from None
    finally:
        probe.close(linger=0)


def _cmd_bench(args) -> int:
    from simulator.parts import MESHES_ENV

    if args.meshes is not None:
        if not (args.meshes / "manifest.json").is_file():
            raise UsageError(f"--meshes {args.meshes} holds no manifest.json")
        os.environ[MESHES_ENV] = str(args.meshes)  # the benchmarks' reference-part loader reads it
    if args.what == "stripe":
        from service.bench import stripe as bench
    elif args.what == "simulate":
        from service.bench import simulate as bench
    elif args.what == "service":
        from service.bench import service as bench
    elif args.what == "hardware":
        from service.bench import hardware as bench
    elif args.what == "surfaces":
        from service.bench import surfaces as bench
    elif args.what == "calibrate":
        from service.bench import calibrate as bench
    elif args.what == "coarse":
        from service.bench import coarse as bench
    elif args.what == "edges":
        from service.bench import edges as bench
    elif args.what == "pose":
        from service.bench import pose as bench
        from service.bench import pose_limits
        limits = pose_limits.run(args.out, quick=args.quick)
        print(json.dumps(limits.get("summary", {}), indent=2))
    else:
        from service.bench import scan as bench
    result = bench.run(args.out, quick=args.quick)
    print(json.dumps(result.get("summary", {}), indent=2))
    print(f"written to {args.out}")
    return 0


def main(argv=None) -> int:
    # A batch command lives for seconds: the cyclic collector's passes over the objects its
    # imports make (numba, trimesh) cost 0.1-0.2 s and free nothing that matters, and its last
    # collections at exit 0.3 s (frozen, they are skipped; in a test run, at the test's end).
    # The service lives on and keeps the collector.
    collecting = gc.isenabled()
    gc.disable()
    try:
        args = _parse_args(argv)
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
    # each call and steal the other core (NOTES.md).
    from scanner_core.calibration import CalibrationError
    from scanner_core.planecal import PlaneCalibrationError
    from scanner_core.viewcal import ViewCalibrationError
    from service.calibrate import SessionError
    from simulator.embree import EmbreeError
    from simulator.parts import PartError
    from simulator.virtual_setup import SetupError

    with threadpool_limits(limits=1, user_api="blas"):
        try:
            return {"scan": _cmd_scan, "simulate": _cmd_simulate, "serve": _cmd_serve,
                    "record": _cmd_record, "replay": _cmd_replay, "calibrate": _cmd_calibrate,
                    "bench": _cmd_bench}[args.command](args)
        except (UsageError, PartError, CalibrationError, ScanError, SetupError,
                EmbreeError, SessionError, ViewCalibrationError, PlaneCalibrationError) as exc:
            print(f"flyscan {args.command}: error: {exc}", file=sys.stderr)
            return 2
        except ScanFailed as exc:
            print(f"flyscan {args.command}: scan failed: {exc}", file=sys.stderr)
            return EXIT_SCAN_FAILED


if __name__ == "__main__":
    sys.exit(main())
