"""``flyscan scan``: one part, one pass, from any source, to ``cloud.ply``, ``edges.ply`` and
``report.json``.

- ``--sim`` (the default when no other source is given): the simulated cell
  (``simulator.session.run_simulated_scan``), with the truth's figures in the report;
- ``--recording DIR``: a recorded pass (``scanner_core.recording.replay.replay_pass``), run
  and finished as the live pass was, against the part the recording holds or ``--part``;
- ``--camera SPEC [--robot ur://HOST]``: a real cell: the trigger is armed on the camera's
  stream and one pass through the sheet is scanned with the calibration given.

Every source runs the same pass session (``scanner_core.pipeline.session.run_session``) and
its finisher, so the same pass gives the same report; a failed pass writes its report alone.
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

from flyscan.common import (MAX_FPS, MAX_SPEED_MM_S, ScanError, UsageError,
                            add_act_tolerance, check_frame_spacing, check_out_dir,
                            check_part_args, load_part_model, non_negative_int, pose_params,
                            write_scan_files)

__all__ = ["add_parser", "run"]

#: Options that only the simulated cell takes, with their defaults (given with another
#: source, they are refused: they would silently do nothing).
SIM_ONLY = {"demo": False, "preset": "default", "speed": None, "fps": None, "misplace": None,
            "seed": 0, "perturb_seed": None, "surface": "default", "effects": None,
            "drop_rate": 0.0, "no_eval": False}
#: A live scan waits this long for the pass by default, s.
LIVE_TIMEOUT_S = 60.0


def add_parser(command) -> None:
    from scanner_core.cad import GRASPS
    from scanner_core.pipeline.exposure import EXPOSURE_MODES
    from scanner_core.stripe.extractor import METHODS

    scan = command("scan", help="scan a part: in the simulated cell (default), from a recorded "
                                "pass, or with a camera and a robot")
    source = scan.add_mutually_exclusive_group()
    source.add_argument("--sim", action="store_true",
                        help="the simulated cell (the default when no other source is given)")
    source.add_argument("--recording", type=Path, default=None,
                        help="a recorded pass (`flyscan record`): the report the live pass gave")
    source.add_argument("--camera", default=None,
                        help="a real cell's camera (opencv:0, video:FILE, gstreamer:PIPELINE, "
                             "genicam:PRODUCER.cti[#SERIAL], pylon:[SERIAL][?options], "
                             "replay:FOLDER): arms, waits for one "
                             "pass and scans it; needs --calibration")
    scan.add_argument("--robot", default=None,
                      help="with --camera: ur://HOST (ur-rtde) or replay:FOLDER")
    scan.add_argument("--timeout", type=float, default=LIVE_TIMEOUT_S,
                      help="with --camera: seconds to wait for the pass")
    part = scan.add_mutually_exclusive_group()
    part.add_argument("--part", type=Path, help="mesh file (STL, OBJ, PLY) of the part")
    part.add_argument("--demo", action="store_true",
                      help="the built-in procedural block (simulated cell)")
    scan.add_argument("--units", default=None, help="unit of the mesh file: mm, cm, m or inch")
    scan.add_argument("--grasp", choices=GRASPS, default="centred",
                      help="nominal grasp: the part centred under the TCP (default); 'flat': "
                           "turned a quarter so its smallest extent hangs along z_T (held by its "
                           "broadest side, as a suction cup holds it), then centred; 'identity': "
                           "the CAD origin at the TCP")
    scan.add_argument("--plan", type=Path, default=None,
                      help="the part's plan.json (flyscan plan): its grasp and pass direction "
                           "(a turn about z_T) replace --grasp; in the simulated cell its pass "
                           "speed and frame rate too, unless --preset, --speed or --fps is given")
    add_act_tolerance(scan)
    scan.add_argument("--calibration", type=Path, default=None,
                      help="calibration JSON the scanner uses (simulated cell: default the "
                           "cell's truth; a recording: default the one it was made with)")
    scan.add_argument("--method", default="cog", choices=METHODS, help="sub-pixel stripe estimator")
    scan.add_argument("--exposure", choices=list(EXPOSURE_MODES), default="fixed",
                      help="exposure control: fixed, dynamic (from the previous frames' stripe "
                           "peaks) or multiple (two exposures alternating)")
    sim = scan.add_argument_group("the simulated cell only")
    sim.add_argument("--preset", choices=["default", "fast", "slow"], default="default",
                     help="pass preset: default 200 mm/s at 162 fps; the paper's fast (1 m/s, "
                          "162 fps) and slow (50 mm/s, 16 fps) configurations")
    sim.add_argument("--speed", type=float, help="nominal pass speed, mm/s")
    sim.add_argument("--fps", type=float, help="camera frame rate, Hz")
    sim.add_argument("--misplace", default=None,
                     help="'tx,ty,tz,rx,ry,rz': the part's misplacement in the gripper, mm and "
                          "a rotation vector in degrees, in {T}; may start with a minus")
    sim.add_argument("--fault", default=None, metavar="KIND[:SIZE]",
                     help="the gripper holds the part with a fault, SIZE in mm: double (a "
                          "second part hooked on it), debris:D, chip:R, variant:L (longer), "
                          "hole:D (a variant drilled through), bend:F (its ends F toward the "
                          "sensor); the scanner registers the "
                          "good part (simulator.faults)")
    sim.add_argument("--held", type=Path, default=None, metavar="MESH",
                     help="the gripper holds this mesh instead (in the part's CAD frame and "
                          "--units, placed by its grasp and --misplace) while the scanner "
                          "registers the part")
    sim.add_argument("--seed", type=non_negative_int, default=0, help="image noise seed")
    sim.add_argument("--perturb-seed", type=non_negative_int, default=None,
                     help="perturb the simulated cell's true geometry (repeatably)")
    sim.add_argument("--surface", choices=["default", "matte", "dark", "shiny"],
                     default="default",
                     help="the simulated part's surface: the reference matte white, a matte cast, "
                          "a dark anodised or a shiny machined part (simulator.surfaces)")
    sim.add_argument("--effects", default=None,
                     help="what a real cell does that the scanner is not told: 'all', 'none' or "
                          "a comma-separated choice of lens, exposure, clocks, robot, led "
                          "(simulator.effects); default: those of the cell a --calibration "
                          "made by 'calibrate --sim' was made in, else none")
    sim.add_argument("--drop-rate", type=float, default=0.0, help="fraction of frames lost")
    sim.add_argument("--no-eval", action="store_true", help="skip the ground-truth accuracy")
    scan.add_argument("--out", type=Path, required=True,
                      help="folder for cloud.ply, edges.ply and report.json")


def run(args) -> int:
    if args.recording is not None or args.camera is not None:
        given = [name for name, default in SIM_ONLY.items() if getattr(args, name) != default]
        if given:
            names = ", ".join("--" + n.replace("_", "-") for n in given)
            source = "--recording" if args.recording is not None else "--camera"
            raise UsageError(f"{names}: the simulated cell's only, not with {source}")
    if args.robot is not None and args.camera is None:
        raise UsageError("--robot goes with --camera (a real cell)")
    check_part_args(args)
    if args.plan is not None and args.part is None:
        raise UsageError("--plan goes with --part: a plan is made for one mesh file")
    if args.plan is not None and args.grasp != "centred":
        raise UsageError("--plan gives the grasp: not with --grasp")
    check_out_dir(args.out)
    if args.recording is not None:
        return _from_recording(args)
    if args.camera is not None:
        return _from_cell(args)
    return _simulated(args)


# --------------------------------------------------------------------------------------------
# The sources
# --------------------------------------------------------------------------------------------

def _simulated(args) -> int:
    from scanner_core.geometry.calibration import load_calibration
    from scanner_core.pipeline.exposure import ExposureParams
    from scanner_core.pipeline import PipelineParams
    from flyscan.simcell import scan_effects, sim_cell
    from simulator.cell import PASS_PRESETS
    from simulator.parts import block_with_holes_and_steps, check_fits, part_from_mesh, simulated
    from simulator.session import parse_misplacement, run_simulated_scan
    from simulator.surfaces import with_surface

    # Everything is checked before the pass is simulated: a bad input writes nothing.
    if args.part is None and not args.demo:
        raise UsageError("give the part: --part FILE --units U, or --demo")
    for name, limit in (("speed", MAX_SPEED_MM_S), ("fps", MAX_FPS)):
        value = getattr(args, name)
        if value is not None and not 0 < value <= limit:
            raise UsageError(f"--{name} must be positive and at most {limit:g}, got {value}")
    if not 0.0 <= args.drop_rate < 1.0:
        raise UsageError(f"--drop-rate must be in [0, 1), got {args.drop_rate}")
    try:
        misplacement = parse_misplacement(args.misplace)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.demo:
        part = part_from_mesh(block_with_holes_and_steps(), name="demo-block", grasp=args.grasp)
    else:
        part = simulated(load_part_model(args))
    part = with_surface(part, args.surface)
    check_fits(part, pose=misplacement @ part.grasp)
    held = _held(args, part)
    calibration = load_calibration(args.calibration) if args.calibration else None
    cell = sim_cell(args.perturb_seed, scan_effects(args, calibration))
    preset = PASS_PRESETS[args.preset]
    plan = getattr(args, "loaded_plan", None) if args.preset == "default" else None
    speed, fps = (plan.speed_mm_s, plan.fps) if plan is not None else (preset.speed_mm_s,
                                                                        preset.fps)
    cell = cell.with_pass(speed_mm_s=args.speed or speed, fps=args.fps or fps)
    check_frame_spacing(part, cell.pass_profile.speed_mm_s, cell.pass_profile.fps)
    if calibration is not None:
        calibration.check_image_size(cell.calibration.camera.width,
                                     cell.calibration.camera.height)
    params = PipelineParams(stripe_method=args.method,
                            exposure=ExposureParams(mode=args.exposure))
    t0 = time.perf_counter()
    scan, report = run_simulated_scan(part, cell, calibration=calibration,
                                      misplacement=misplacement, seed=args.seed,
                                      drop_rate=args.drop_rate, params=params,
                                      evaluate=not args.no_eval, pose_params=pose_params(args),
                                      held=held)
    _check_marker(scan, params)
    report["wall_s"] = round(time.perf_counter() - t0, 3)
    paths = write_scan_files(args.out, scan, report)
    acc = report["ground_truth"].get("accuracy", {})
    print(f"scanned {part.name}: {report['frames']} frames, {report['points']} points, "
          f"processing {report['timings_ms']['processing']:.0f} ms for "
          f"{report['camera_time_s']:.2f} s of camera time")
    if acc.get("points_evaluated"):
        print(f"accuracy: RMS {acc['rms_um']:.1f} um, p99 {acc['p99_um']:.1f} um, "
              f"points without a visible source {acc.get('unmatched_points')}")
    return _done(paths)


def _held(args, part):
    """What the simulated gripper holds instead of ``part`` (``--fault``, ``--held``), or None."""
    if args.fault is None and args.held is None:
        return None
    if args.fault is not None and args.held is not None:
        raise UsageError("--fault and --held each say what the gripper holds: give one")
    import numpy as np

    from scanner_core.cad import load_part
    from simulator.faults import faulty_part
    from simulator.parts import part_from_mesh
    from simulator.surfaces import with_surface

    if args.fault is not None:
        try:
            return faulty_part(part, args.fault, np.random.default_rng(args.seed))
        except ValueError as exc:
            raise UsageError(f"--fault: {exc}") from None
    units = args.units or "mm"
    mesh = load_part(args.held, units, name=args.held.stem, grasp=part.grasp).mesh
    return with_surface(part_from_mesh(mesh, name=args.held.stem, source=str(args.held),
                                       grasp=part.grasp), part.surface)


def _from_recording(args) -> int:
    from scanner_core.pipeline.session import recorded_params
    from scanner_core.recording import RecordingError, load_recording
    from scanner_core.recording.replay import replay_pass

    try:
        recording = load_recording(args.recording)
    except RecordingError as exc:
        raise UsageError(str(exc)) from None
    part = load_part_model(args)
    params = recorded_params(recording,
                             stripe_method=None if args.method == "cog" else args.method,
                             exposure_mode=None if args.exposure == "fixed" else args.exposure)
    if args.calibration is not None:
        from scanner_core.geometry.calibration import load_calibration

        calibration = load_calibration(args.calibration)
        calibration.check_image_size(recording.width, recording.height)
        recording = dataclasses.replace(recording, calibration=calibration)
    t0 = time.perf_counter()
    outcome = replay_pass(recording, part, params=params, pose_params=pose_params(args),
                          source={"recording": str(args.recording)})
    wall_s = time.perf_counter() - t0
    outcome.report["wall_s"] = round(wall_s, 3)
    paths = write_scan_files(args.out, outcome.scan, outcome.report)
    print(f"scanned the recorded pass {args.recording}: {outcome.scan.frames} profiles, "
          f"{len(outcome.scan.cloud)} points, {wall_s:.2f} s")
    return _done(paths)


def _from_cell(args) -> int:
    from scanner_core.geometry.calibration import load_calibration
    from scanner_core.pipeline import PipelineParams
    from scanner_core.pipeline.exposure import ExposureParams
    from scanner_core.pipeline.session import run_session
    from scanner_core.pipeline.trigger import TriggerParams
    from service.cameras import open_camera
    from service.robots import open_robot

    if args.calibration is None:
        raise UsageError("--camera needs --calibration FILE: the scanner knows a real cell only "
                         "through its calibration (flyscan calibrate)")
    if not args.timeout > 0:
        raise UsageError(f"--timeout must be positive, got {args.timeout}")
    calibration = load_calibration(args.calibration)
    part = load_part_model(args)
    try:
        camera, robot = open_camera(args.camera), open_robot(args.robot)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    params = PipelineParams(stripe_method=args.method, exposure=ExposureParams(mode=args.exposure),
                            trigger=TriggerParams(arm_timeout_s=args.timeout))
    print(f"armed: waiting for a pass through the sheet ({args.timeout:g} s)",
          file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    outcome = run_session(camera, robot, calibration, params=params, part_model=part,
                          pose_params=pose_params(args),
                          frames_timeout_s=max(1.0, args.timeout),
                          source={"camera": args.camera, "robot": args.robot})
    _check_marker(outcome.scan, params)
    outcome.report["wall_s"] = round(time.perf_counter() - t0, 3)
    paths = write_scan_files(args.out, outcome.scan, outcome.report)
    print(f"scanned a pass from {args.camera}: {outcome.scan.frames} profiles, "
          f"{len(outcome.scan.cloud)} points")
    return _done(paths)


# --------------------------------------------------------------------------------------------
# Shared
# --------------------------------------------------------------------------------------------

def _check_marker(scan, params) -> None:
    if scan.marker_residual_px > params.max_marker_residual_px:
        raise ScanError(
            f"the marker's three views disagree (median residual {scan.marker_residual_px:.2f} px "
            f"over {scan.frames + scan.frames_unplaced} frames): does the calibration fit the cell?")


def _done(paths: dict) -> int:
    for key, path in paths.items():
        print(f"{key}: {path}")
    return 0
