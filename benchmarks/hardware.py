"""Hardware in the loop, measured: the UR cross-check through the real ur-rtde client, the
robot link's loss and recovery, and the replay of a recorded pass against real time.

* Cross-check: the service in simulated mode with ``--robot ur://HOST``: the RTDE emulator
  (its own process) serves the simulated track to the real ur-rtde client. Passes at the
  reference speed: consistent, then with the robot's reports shifted 0.5 mm across and
  along the pass (``RtdeEmulator.set_bias``). Targets: deviation below 0.1 mm when
  consistent; every inconsistent pass flagged.
* Link: ``URRobot`` against the emulator; the connection dropped (closed, then refused) or
  stalled (open but silent), then restored. Targets: loss seen within 3 s, the robot back
  within 5 s of coming back.
* Replay: a pass recorded by the service (``POST /scans`` with ``record``) run through
  ``replay_recording``, as ``flyscan replay`` does. Target: at least 5 times real time.
"""
from __future__ import annotations

import pathlib
import sys
import tempfile
import time

import numpy as np

from benchmarks.live import finished_scan, free_port, running_service, wait_for
from benchmarks.results import pyplot, save_figure, write_json
from simulator.rtde_emulator import free_loopback_host

#: Passes of each kind (consistent, shifted across, shifted along); fewer with --quick.
PASSES, QUICK_PASSES = 8, 3
#: Loss-and-recovery trials of each kind (drop, stall).
LINK_TRIALS, QUICK_LINK_TRIALS = 5, 2
#: How long each outage lasts before the robot comes back, s.
OUTAGE_S = 2.0
REPLAY_REPEATS = 3
INCONSISTENCY_MM = 0.5
TARGET_DEVIATION_MM = 0.1
TARGET_DETECT_S, TARGET_RECOVER_S = 3.0, 5.0
TARGET_REPLAY_X = 5.0


def _scan(service, **kwargs) -> dict:
    job = service.arm(None, 30.0, **kwargs)
    return (finished_scan(service, job.scan_id, 60.0, 0.05)
            or {"state": "timeout", "scan_id": job.scan_id})


def cross_checks(passes: int, data: pathlib.Path) -> dict:
    """Consistent and inconsistent passes through the service with the real client; and a
    recorded pass, replayed."""
    from scanner_core.recording import load_recording
    from scanner_core.recording.replay import replay_recording
    from service.settings import Settings
    from simulator.driver import SimulatedCellOptions

    settings = Settings(robot=f"ur://{free_loopback_host(130)}", data=data,
                        zmq=f"tcp://127.0.0.1:{free_port()}")
    rows, replays = [], []
    with running_service(settings, SimulatedCellOptions(clock_offset_s=3.5),
                         robot=settings.robot) as service:
        wait_for(lambda: service.engine.robot.connected, 10.0)
        kinds = [("consistent", [0.0, 0.0, 0.0]), ("across", [INCONSISTENCY_MM, 0.0, 0.0]),
                 ("along", [0.0, INCONSISTENCY_MM, 0.0])]
        _scan(service)  # the first pass learns the clock offset and the LED correction
        for kind, bias in kinds:
            service.driver.emulator.set_bias(bias)
            for k in range(passes):
                info = _scan(service)
                check = info.get("cross_check") or {}
                rows.append({"kind": kind, "state": info["state"], "max_mm": check.get("max_mm"),
                             "rms_mm": check.get("rms_mm"), "flagged": check.get("flagged"),
                             "clock_offset_s": check.get("clock_offset_s")})
                print(f"bench hardware: {kind} pass {k + 1}/{passes}: max "
                      f"{check.get('max_mm') or float('nan'):.4f} mm, flagged "
                      f"{check.get('flagged')}", file=sys.stderr, flush=True)
        service.driver.emulator.set_bias([0.0, 0.0, 0.0])
        recorded = _scan(service, record=True)
        path = wait_for(lambda: (service.scan_info(recorded["scan_id"]).get("recording") or {})
                        .get("path"), 60.0, 0.1)
        recording = load_recording(service.settings.data / path)  # said relative to it
        camera_s = recording.frame_count / recording.fps
        for _ in range(REPLAY_REPEATS):
            t0 = time.perf_counter()
            scan = replay_recording(recording)
            wall = time.perf_counter() - t0
            replays.append({"wall_s": wall, "times_real_time": camera_s / wall,
                            "points": int(len(scan.cloud))})
        live_points = recorded.get("points")
    return {"rows": rows, "replay": {"frames": recording.frame_count, "camera_s": camera_s,
                                     "live_points": live_points, "runs": replays}}


def link_trials(trials: int) -> list[dict]:
    """Loss and recovery of the robot link, dropped and stalled."""
    from simulator.rtde_emulator import RtdeEmulator
    from service.ur_robot import URRobot

    rows = []
    with RtdeEmulator(free_loopback_host(200)).start() as emulator:
        emulator.set_track(time.monotonic(), 0.0, np.eye(3), [0.0, 0.0, 500.0])
        robot = URRobot(emulator.host)
        robot.connect()
        try:
            wait_for(lambda: robot.connected, 10.0)
            for fault in ("drop", "stall"):
                for _ in range(trials):
                    cut = time.monotonic()
                    getattr(emulator, fault)()
                    lost = wait_for(lambda: not robot.connected, 10.0)
                    detect = time.monotonic() - cut if lost else None
                    time.sleep(max(OUTAGE_S - (time.monotonic() - cut), 0.0))
                    emulator.restore()
                    back_at = time.monotonic()
                    back = wait_for(lambda: robot.connected, 15.0)
                    rows.append({"fault": fault, "detect_s": detect,
                                 "recover_s": time.monotonic() - back_at if back else None})
                    print(f"bench hardware: {fault}: lost after {detect} s, back after "
                          f"{rows[-1]['recover_s']} s", file=sys.stderr, flush=True)
                    time.sleep(0.5)
        finally:
            robot.disconnect()
    return rows


def run(out_dir, quick: bool = False) -> dict:
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="flyscan-bench-hardware-") as tmp:
        checks = cross_checks(QUICK_PASSES if quick else PASSES, pathlib.Path(tmp) / "data")
    links = link_trials(QUICK_LINK_TRIALS if quick else LINK_TRIALS)
    rows = checks["rows"]
    consistent = [r["max_mm"] for r in rows if r["kind"] == "consistent" and r["max_mm"] is not None]
    shifted = [r for r in rows if r["kind"] != "consistent"]
    detect = [r["detect_s"] for r in links]
    recover = [r["recover_s"] for r in links]
    replay_x = min(r["times_real_time"] for r in checks["replay"]["runs"])
    summary = {
        "consistent_max_deviation_mm": {
            "value": max(consistent) if consistent else None, "target_max": TARGET_DEVIATION_MM,
            "met": bool(consistent) and max(consistent) < TARGET_DEVIATION_MM},
        "inconsistent_flagged": {
            "value": sum(bool(r["flagged"]) for r in shifted) / max(len(shifted), 1),
            "target_min": 1.0, "passes": len(shifted),
            "met": bool(shifted) and all(r["flagged"] for r in shifted)},
        "loss_detected_s_max": {
            "value": None if None in detect else max(detect), "target_max": TARGET_DETECT_S,
            "met": None not in detect and max(detect) <= TARGET_DETECT_S},
        "recovered_s_max": {
            "value": None if None in recover else max(recover), "target_max": TARGET_RECOVER_S,
            "met": None not in recover and max(recover) <= TARGET_RECOVER_S},
        "replay_times_real_time_min": {"value": replay_x, "target_min": TARGET_REPLAY_X,
                                       "met": replay_x >= TARGET_REPLAY_X},
    }
    result = {"cross_check": checks, "link": links, "summary": summary, "quick": quick}
    result = write_json(out_dir / "hardware.json", result)
    _plot(result, out_dir / "hardware.png")
    return result


def _plot(result: dict, path: pathlib.Path) -> None:
    plt = pyplot()
    fig, (ax0, ax1, ax2) = plt.subplots(1, 3, figsize=(15, 4.5))
    rows = result["cross_check"]["rows"]
    for i, (kind, colour) in enumerate((("consistent", "C0"), ("across", "C3"), ("along", "C1"))):
        values = [r["max_mm"] for r in rows if r["kind"] == kind and r["max_mm"] is not None]
        flagged = sum(bool(r["flagged"]) for r in rows if r["kind"] == kind)
        ax0.plot(np.full(len(values), i) + np.linspace(-0.2, 0.2, len(values)), values, "o",
                 color=colour, label=f"{kind}: {flagged}/{len(values)} flagged")
    ax0.axhline(TARGET_DEVIATION_MM, color="r", ls="--", label="tolerance 0.1 mm")
    ax0.set_xticks([0, 1, 2], ["consistent", f"{INCONSISTENCY_MM} mm across",
                               f"{INCONSISTENCY_MM} mm along"])
    ax0.set_yscale("log")
    ax0.set_ylabel("cross-check max deviation per pass, mm")
    ax0.set_title("real ur-rtde client vs the RTDE emulator")
    ax0.legend(fontsize=8)
    links = result["link"]
    for j, (key, target) in enumerate((("detect_s", TARGET_DETECT_S),
                                       ("recover_s", TARGET_RECOVER_S))):
        for k, fault in enumerate(("drop", "stall")):
            values = [r[key] for r in links if r["fault"] == fault and r[key] is not None]
            ax1.plot(np.full(len(values), 2 * j + k), values, "o", color=f"C{k}",
                     label=fault if j == 0 else None)
        ax1.hlines(target, 2 * j - 0.4, 2 * j + 1.4, color="r", ls="--")
    ax1.set_xticks([0, 1, 2, 3], ["drop: lost", "stall: lost", "drop: back", "stall: back"])
    ax1.set_ylabel("seconds (red: target)")
    ax1.set_title("robot link: loss seen, and back after the robot returns")
    ax1.legend(fontsize=8)
    replay = result["cross_check"]["replay"]
    xs = [r["times_real_time"] for r in replay["runs"]]
    ax2.bar(range(len(xs)), xs, color="C0")
    ax2.axhline(TARGET_REPLAY_X, color="r", ls="--", label=f"target {TARGET_REPLAY_X:g} x")
    ax2.set_xlabel("replay run")
    ax2.set_ylabel("times real time")
    ax2.set_title(f"replay of a {replay['frames']}-frame recorded pass")
    ax2.legend(fontsize=8)
    save_figure(fig, path, dpi=100)
