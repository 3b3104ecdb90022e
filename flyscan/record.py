"""``flyscan record`` and ``flyscan replay``: a running service's next pass recorded (frames,
robot samples, the part), and a recording run again to the live pass's report."""
from __future__ import annotations

import sys
import time
from pathlib import Path

from flyscan.common import (ScanError, UsageError, add_act_tolerance,
                            check_out_dir, check_part_args, load_part_model, pose_params,
                            write_scan_files)

__all__ = ["add_parsers", "run_record", "run_replay"]


def add_parsers(command) -> None:
    import os

    record = command("record", help="record the next pass of a running service (every frame "
                                    "and the robot's poses, with the part) for replay")
    record.add_argument("--url", default="http://127.0.0.1:8000", help="the service")
    record.add_argument("--part", default=None, help="part to scan (default the service's)")
    record.add_argument("--token", default=os.environ.get("FLYSCAN_TOKEN"),
                        help="bearer token, if the service has one (default $FLYSCAN_TOKEN)")
    record.add_argument("--timeout", type=float, default=60.0,
                        help="seconds to wait for the pass and its recording")

    replay = command("replay", help="run a recorded pass through the pipeline offline: the "
                                    "report the live pass gave, pose and cross-check included")
    replay.add_argument("recording", type=Path, help="a folder `flyscan record` made")
    replay.add_argument("--part", type=Path, default=None,
                        help="mesh file to register against (default: the part the recording "
                             "holds)")
    replay.add_argument("--units", default=None, help="unit of --part: mm, cm, m or inch")
    add_act_tolerance(replay)
    replay.add_argument("--out", type=Path, required=True,
                        help="folder for cloud.ply, edges.ply and report.json")


def run_record(args) -> int:
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
          f"{recording['path']} (in the service's data folder, on its machine)")
    return 0


def run_replay(args) -> int:
    from scanner_core.recording import RecordingError, load_recording
    from scanner_core.recording.replay import replay_pass

    check_part_args(args)
    check_out_dir(args.out)
    try:
        recording = load_recording(args.recording)
    except RecordingError as exc:
        raise UsageError(str(exc)) from None
    part = load_part_model(args)
    t0 = time.perf_counter()
    outcome = replay_pass(recording, part, pose_params=pose_params(args))
    wall_s = time.perf_counter() - t0
    recorded_s = recording.frame_count / recording.fps
    report, scan = outcome.report, outcome.scan
    report["replay"] = {"recording": str(args.recording), "frames": recording.frame_count,
                        "wall_s": round(wall_s, 3),
                        "times_real_time": round(recorded_s / wall_s, 2) if wall_s > 0 else None}
    print(f"replayed {recording.frame_count} frames ({recorded_s:.2f} s of camera time) in "
          f"{wall_s:.2f} s, {recorded_s / wall_s:.1f} x real time: {scan.frames} profiles, "
          f"{len(scan.cloud)} points")
    paths = write_scan_files(args.out, scan, report)  # ScanFailed for a failed pass
    for key, path in paths.items():
        print(f"{key}: {path}")
    return 0
