"""Benchmark of the live service: per-frame cost, consecutive passes, latency, memory, load.

1. Per frame, one thread: the whole processing of a frame in a pass (tracked marker, trigger,
   stripe, triangulation, placement: ``scanner_core.pipeline``) against a plain copy of the same
   frame, timed frame by frame in the same run.
2. Consecutive passes through the service in simulated mode (``service.daemon.Service`` with
   the live simulated cell at 162 fps, its camera paced on the real clock), a ZeroMQ subscriber
   on loopback receiving every cloud: dropped frames, queue overflows, the latency from the
   pass's last frame to its cloud on ZeroMQ, the process's memory after every pass, and the CPU
   the processing takes against the camera time.

3. The pose's latency: passes of every part (the quick set: the demo block) at
   several pass speeds, so several point counts, at random misplacements (the issue's target
   set, seeded), through the same service with each reference part uploaded to it: from the
   pass's last frame to the pose's message on ZeroMQ (``latency_ms.pose_published``), its
   path stage by stage (``latency_ms.pose_path``) and the registration's own stages (fine,
   the turn check, coarse, probes: timed around ``scanner_core.pose.registration``'s calls to them), by
   part and point count, against the target: p95 within 150 ms up to 20 000 points. The
   service computes the pose once the part has left the sheet (``scanner_core.pose.ahead``);
   the same passes again with ``pose_ahead_frames`` 0 give the latency of a pose computed at
   the pass's end (``pose_at_pass_end``), and the pose's own time is reported beside.

``run(out_dir)`` writes ``service.json`` and ``service.png`` and returns the dict.
"""
from __future__ import annotations

import contextlib
import functools
import json
import os
import pathlib
import sys
import tempfile
import threading
import time

import numpy as np
from threadpoolctl import threadpool_limits

from scanner_core.pipeline import (MarkerTracker, PassAccumulator, PipelineParams, camera_frames,
                                   feed_frame, warm_up)
from scanner_core.pipeline.trigger import Trigger
from benchmarks.live import finished_scan, free_port, running_service
from benchmarks.parts import (DEMO_PART, MISPLACEMENT_SEED, MISPLACEMENT_UP_TO_DEG,
                              MISPLACEMENT_UP_TO_MM, REFERENCE_PARTS, bench_part, demo_pass,
                              random_misplacement)
from benchmarks.stats import spread
from benchmarks.results import machine_info, write_json

__all__ = ["run"]

PASSES, QUICK_PASSES = 100, 8
PER_FRAME_REPEATS, QUICK_PER_FRAME_REPEATS = 5, 2
TARGET_FRAME_RATIO = 5.0
TARGET_LATENCY_MEDIAN_MS = 30.0
TARGET_LATENCY_P99_MS = 100.0
TARGET_MEMORY_GROWTH = 0.05
#: A pass must be over within this long, s (the default pass takes about 2 s).
PASS_TIMEOUT_S = 30.0
#: The pose's target: from the pass's last frame to the pose on ZeroMQ, p95 at
#: most this, ms, for scans of up to `TARGET_POSE_POINTS` points, one worker core.
TARGET_POSE_P95_MS = 150.0
TARGET_POSE_POINTS = 20_000
#: Pass speeds of the pose's passes, mm/s: the point count goes as their inverse (the demo
#: block: about 5 000, 10 000 and 20 000 points; featuretype three times as many).
POSE_SPEEDS, QUICK_POSE_SPEEDS = (400.0, 200.0, 100.0), (200.0,)
#: Passes per part and speed.
POSE_PASSES, QUICK_POSE_PASSES = 4, 2
#: Point counts the latencies are grouped by (upper bounds).
POINT_BINS = (5_000, 10_000, 20_000, 40_000, 80_000)
#: The registration's stages timed in the service's passes: ``scanner_core.pose.registration``'s names.
POSE_STAGES = {"_fine": "fine", "_better_turn": "turn_check", "_coarse": "coarse",
               "_probe_turns": "probes"}


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _cpu_s() -> float:
    t = os.times()
    return t.user + t.system


def per_frame(repeats: int) -> dict:
    """Whole per-frame processing against a copy of the same frame, one thread."""
    sim = demo_pass()
    sim.camera.open()
    sim.robot.connect()
    frames = list(camera_frames(sim.camera))
    calibration, params = sim.cell.calibration, PipelineParams()
    warm_up(calibration, params)
    copy_ms, frame_ms, in_pass = [], [], []
    for _ in range(repeats):
        tracker, trigger = MarkerTracker(calibration, params), Trigger(params.trigger)
        accumulator = PassAccumulator(calibration, sim.robot)
        trigger.arm()
        for frame in frames:
            t0 = time.perf_counter()
            frame.image.copy()
            t1 = time.perf_counter()
            step = feed_frame(frame, tracker, trigger, accumulator, params)
            t2 = time.perf_counter()
            copy_ms.append((t1 - t0) * 1e3)
            frame_ms.append((t2 - t1) * 1e3)
            in_pass.append(bool(step.emit))
    copy_ms, frame_ms, in_pass = map(np.asarray, (copy_ms, frame_ms, in_pass))
    copy_med = float(np.median(copy_ms))
    pass_med = float(np.median(frame_ms[in_pass]))
    return {
        "frames": len(frames), "repeats": repeats, "frames_in_pass": int(in_pass.sum() // repeats),
        "copy_ms_median": copy_med,
        "pass_frame_ms_median": pass_med,
        "pass_frame_ms_p90": float(np.percentile(frame_ms[in_pass], 90)),
        "idle_frame_ms_median": float(np.median(frame_ms[~in_pass])),
        "ratio_to_copy": pass_med / copy_med,
        "frames_per_second_one_core": 1e3 / pass_med,
    }


class _Receiver(threading.Thread):
    """One thread, one SUB socket: the receipt time of every cloud, by scan id."""

    def __init__(self, endpoint: str):
        super().__init__(daemon=True, name="bench-subscriber")
        import zmq

        self.socket = zmq.Context.instance().socket(zmq.SUB)
        self.socket.setsockopt(zmq.SUBSCRIBE, b"cloud")
        self.socket.setsockopt(zmq.RCVTIMEO, 200)
        self.socket.connect(endpoint)
        self.received: dict[str, tuple[float, float, int]] = {}
        self.stop = threading.Event()

    def run(self) -> None:
        import zmq

        while not self.stop.is_set():
            try:
                topic, header, payload = self.socket.recv_multipart()
            except zmq.Again:
                continue
            h = json.loads(header)
            self.received[h["scan_id"]] = (time.time(), h["t"], len(payload) // 12)
        self.socket.close(linger=0)


def passes(count: int, *, speed_mm_s: float | None = None) -> dict:
    """``count`` consecutive passes through the service in simulated mode."""
    from service.settings import Settings
    from simulator.driver import SimulatedCellOptions

    with tempfile.TemporaryDirectory() as tmp:
        zmq = f"tcp://127.0.0.1:{free_port()}"
        settings = Settings(data=pathlib.Path(tmp), zmq=zmq, retention=10)
        with running_service(settings, SimulatedCellOptions(speed_mm_s=speed_mm_s)) as service:
            rows = _passes(service, zmq, count)
    return _summarise(rows)


def _passes(service, zmq: str, count: int) -> list[dict]:
    """The passes through a running service, a subscriber on its ZeroMQ endpoint `zmq`."""
    receiver = _Receiver(zmq)
    receiver.start()
    time.sleep(0.5)  # the subscriber's slow join; the first pass's render
    rows = []
    try:
        for k in range(count):
            status0 = service.status()
            cpu0, wall0 = _cpu_s(), time.monotonic()
            job = service.arm(None, None)
            info = finished_scan(service, job.scan_id, PASS_TIMEOUT_S, 0.01)
            if info is None:
                raise TimeoutError(f"pass {k} did not finish")
            cpu, wall = _cpu_s() - cpu0, time.monotonic() - wall0
            status = service.status()
            t_recv = receiver.received.get(job.scan_id)
            timings = info["timings_ms"]
            rows.append({
                "scan_id": job.scan_id, "state": info["state"], "points": info["points"],
                "frames": info["frames"], "frames_dropped": info["frames_dropped"],
                "camera_frames_lost": status["frames_dropped"] - status0["frames_dropped"],
                "queue_overflows": info["queue_overflows"],
                "latency_send_ms": info["latency_ms"].get("last_frame_to_zmq"),
                "latency_pass_end_to_send_ms": info["latency_ms"].get("pass_end_to_zmq"),
                "zmq_transit_ms": (t_recv[0] - t_recv[1]) * 1e3 if t_recv else None,
                "received_points": t_recv[2] if t_recv else None,
                "processing_ms": timings.get("marker", 0.0) + timings.get("profiles", 0.0),
                "camera_time_s": (info["frames"] + info["frames_unplaced"]) / service.engine.fps,
                "cpu_s": cpu, "wall_s": wall, "rss_mb": _rss_mb(),
            })
            print(f"bench service: pass {k + 1}/{count}: {info['state']}, {info['points']} points, "
                  f"dropped {rows[-1]['frames_dropped']}, latency {rows[-1]['latency_send_ms']} ms",
                  file=sys.stderr, flush=True)
    finally:
        receiver.stop.set()
        receiver.join(2)
    return rows


def _summarise(rows: list[dict]) -> dict:
    latency = np.array([r["latency_send_ms"] + (r["zmq_transit_ms"] or 0.0) for r in rows
                        if r["latency_send_ms"] is not None])
    rss = np.array([r["rss_mb"] for r in rows])
    tenth = max(1, len(rss) // 10)
    early, late = float(np.median(rss[tenth: 2 * tenth])), float(np.median(rss[-tenth:]))
    processing_s = sum(r["processing_ms"] for r in rows) / 1e3
    camera_s = sum(r["camera_time_s"] for r in rows)
    return {
        "passes": len(rows),
        "failed": sum(r["state"] != "done" for r in rows),
        "frames_dropped": int(sum(r["frames_dropped"] for r in rows)),
        "camera_frames_lost": int(sum(r["camera_frames_lost"] for r in rows)),
        "queue_overflows": int(sum(r["queue_overflows"] for r in rows)),
        "clouds_received": sum(r["received_points"] == r["points"] for r in rows),
        "latency_ms": {"median": float(np.median(latency)), "p99": float(np.percentile(latency, 99)),
                       "max": float(latency.max()), "values": latency.round(3).tolist()},
        "rss_mb": {"early_median": early, "late_median": late, "growth": late / early - 1.0,
                   "values": rss.round(2).tolist()},
        # Processing (marker on the acquisition thread, profiles on the workers) per second of
        # camera time: cores it keeps busy at 162 fps. The simulated camera's rendering is not in it.
        "processing_cores": processing_s / camera_s,
        "process_cpu_cores": sum(r["cpu_s"] for r in rows) / sum(r["wall_s"] for r in rows),
        "rows": rows,
    }


@contextlib.contextmanager
def pose_stages(clock=time.perf_counter):
    """``scanner_core.pose.registration``'s calls to its stages timed (by `clock`, wall by default; ms,
    summed per stage) into the dict yielded, until the block ends; the passes are serial,
    the finisher thread the one caller."""
    import scanner_core.pose.registration as pose_module

    spent: dict[str, float] = {}
    saved = {name: getattr(pose_module, name) for name in POSE_STAGES
             if hasattr(pose_module, name)}

    def timed(function, label):
        @functools.wraps(function)
        def call(*args, **kwargs):
            t0 = clock()
            try:
                return function(*args, **kwargs)
            finally:
                spent[label] = spent.get(label, 0.0) + (clock() - t0) * 1e3
        return call

    for name, function in saved.items():
        setattr(pose_module, name, timed(function, POSE_STAGES[name]))
    try:
        yield spent
    finally:
        for name, function in saved.items():
            setattr(pose_module, name, function)


def _upload(service, name: str) -> str:
    """The reference part `name` added to the service's library (as ``PUT /parts/{name}``
    does: its mesh file and unit); the demo block is the service's own."""
    if name == DEMO_PART:
        return "demo"
    part = bench_part(name)
    source = pathlib.Path(part.source)
    service.parts.add(name, source.read_bytes(), part.units, suffix=source.suffix.lower())
    return name


def pose_latency(quick: bool = False, ahead_frames: int | None = None) -> dict:
    """The pose's latency from the pass's last frame to its message on ZeroMQ, by part and
    pass speed (so point count): one service per speed, every part uploaded to it.
    `ahead_frames`: the service's ``pose_ahead_frames`` (None: its default; 0: the pose is
    computed at the pass's end only)."""
    from service.settings import Settings
    from simulator.driver import SimulatedCellOptions

    names = (DEMO_PART,) if quick else (DEMO_PART, *REFERENCE_PARTS)
    speeds = QUICK_POSE_SPEEDS if quick else POSE_SPEEDS
    count = QUICK_POSE_PASSES if quick else POSE_PASSES
    rows = []
    for s_index, speed in enumerate(speeds):
        with tempfile.TemporaryDirectory() as tmp:
            settings = Settings(data=pathlib.Path(tmp), zmq=f"tcp://127.0.0.1:{free_port()}",
                                retention=10, **({} if ahead_frames is None
                                                 else {"pose_ahead_frames": ahead_frames}))
            options = SimulatedCellOptions(speed_mm_s=speed)
            with running_service(settings, options) as service, pose_stages() as spent:
                for p_index, name in enumerate(names):
                    in_library = _upload(service, name)
                    rng = np.random.default_rng([MISPLACEMENT_SEED, p_index, s_index])
                    done = 0
                    while done < count:
                        values = random_misplacement(rng, MISPLACEMENT_UP_TO_MM,
                                                     MISPLACEMENT_UP_TO_DEG, up_to=True)
                        spent.clear()
                        try:
                            job = service.arm(in_library, None, values)
                        except ValueError:  # leaves the inspection volume (PartError): another
                            continue
                        info = finished_scan(service, job.scan_id, PASS_TIMEOUT_S, 0.01)
                        if info is None:
                            raise TimeoutError(f"{name} at {speed:g} mm/s did not finish")
                        done += 1
                        rows.append(_pose_row(name, speed, values, info, dict(spent)))
                        r = rows[-1]
                        print(f"bench service: pose {name} {speed:g} mm/s: {r['points']} points, "
                              f"pose published {r['pose_published_ms']} ms (pose "
                              f"{r['pose_ms']} ms{', computed ahead' if r['ahead'] else ''})"
                              f"{' coarse' if r['coarse'] else ''}"
                              f"{' ambiguous' if r['ambiguous'] else ''}"
                              f"{' frames lost ' + str(r['frames_lost']) if r['frames_lost'] else ''}",
                              file=sys.stderr, flush=True)
    return {"parts": list(names), "speeds_mm_s": list(speeds), "passes_per_part_and_speed": count,
            "rows": rows, **_pose_summary(rows)}


def _pose_row(name: str, speed: float, values, info: dict, stages: dict) -> dict:
    latency, pose = info.get("latency_ms") or {}, info.get("pose") or {}
    flags = pose.get("flags") or []
    return {"part": name, "speed_mm_s": speed, "misplacement": values, "state": info["state"],
            "points": info["points"], "edge_points": info["edge_points"],
            # frames the pass lost (the simulated camera behind on a loaded machine): a
            # partial scan, whose pose may need the coarse search
            "frames_lost": (info.get("frames_dropped") or 0) + (info.get("queue_overflows") or 0),
            "pose_published_ms": latency.get("pose_published"), "pose_ms": latency.get("pose"),
            "pose_path_ms": latency.get("pose_path"), "stages_ms": stages,
            # kept from before the pass's end (``scanner_core.pose.ahead``): its own time
            "ahead": "pose_ahead" in latency, "pose_ahead_ms": latency.get("pose_ahead"),
            "registration_ms": pose.get("time_ms"), "normals_ms": pose.get("normals_ms"),
            "coarse": bool(pose.get("coarse")), "flags": len(flags),
            "ambiguous": any(str(f).startswith("ambiguous") for f in flags),
            "refused": pose.get("refused")}


def _pose_summary(rows: list[dict]) -> dict:
    by_part, by_points = {}, {}
    for name in dict.fromkeys(r["part"] for r in rows):
        mine = [r for r in rows if r["part"] == name]
        within = [r["pose_published_ms"] for r in mine if r["points"] <= TARGET_POSE_POINTS]
        by_part[name] = {"points_median": float(np.median([r["points"] for r in mine])),
                         "pose_published_ms": spread(r["pose_published_ms"] for r in mine),
                         "pose_published_ms_up_to_target_points": spread(within),
                         "coarse": sum(r["coarse"] for r in mine),
                         "ambiguous": sum(r["ambiguous"] for r in mine),
                         "path_ms_median": _median_dict([r["pose_path_ms"] for r in mine]),
                         "stages_ms_median": _median_dict([r["stages_ms"] for r in mine])}
    low = 0
    for high in (*POINT_BINS, np.inf):
        mine = [r["pose_published_ms"] for r in rows if low < r["points"] <= high]
        if mine:
            by_points[f"{low}-{high if np.isfinite(high) else 'more'}"] = spread(mine)
        low = high
    within = spread(r["pose_published_ms"] for r in rows if r["points"] <= TARGET_POSE_POINTS)
    whole = spread(r["pose_published_ms"] for r in rows
                   if r["points"] <= TARGET_POSE_POINTS and not r.get("frames_lost"))
    computed = spread((r.get("registration_ms") or 0.0) + (r.get("normals_ms") or 0.0)
                      for r in rows
                      if r["points"] <= TARGET_POSE_POINTS and r.get("registration_ms") is not None)
    return {"by_part": by_part, "by_points": by_points,
            "pose_published_ms_up_to_target_points": within,
            "ahead_kept": sum(bool(r.get("ahead")) for r in rows),
            # the pose's own time (normals and registration), wherever it was spent
            "pose_computed_ms_up_to_target_points": computed,
            "passes_with_frames_lost": sum(bool(r.get("frames_lost")) for r in rows),
            "pose_published_ms_up_to_target_points_whole_passes": whole,
            "target": {"p95_ms_max": TARGET_POSE_P95_MS, "points_up_to": TARGET_POSE_POINTS,
                       "met": within.get("n", 0) > 0 and within["p95"] <= TARGET_POSE_P95_MS}}


def _median_dict(dicts) -> dict:
    dicts = [d for d in dicts if d]
    keys = dict.fromkeys(k for d in dicts for k in d)
    return {k: float(np.median([d.get(k, 0.0) for d in dicts])) for k in keys}


def run(out_dir, quick: bool = False) -> dict:
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()  # the machine's other work shows in every figure here
    with threadpool_limits(limits=1, user_api="blas"):
        # The passes first: the per-frame stage holds a whole pass of frames in memory, which
        # the allocator keeps, and the passes' memory figure is the service's alone.
        live = passes(QUICK_PASSES if quick else PASSES)
        pose = pose_latency(quick)
        at_end = pose_latency(quick, ahead_frames=0)
        frame = per_frame(QUICK_PER_FRAME_REPEATS if quick else PER_FRAME_REPEATS)
        print(f"bench service: per frame {frame['pass_frame_ms_median']:.3f} ms, "
              f"{frame['ratio_to_copy']:.2f} x copy", file=sys.stderr)
    summary = {
        "frame_ratio_to_copy": {"value": frame["ratio_to_copy"], "target_max": TARGET_FRAME_RATIO,
                                "met": frame["ratio_to_copy"] <= TARGET_FRAME_RATIO},
        "frames_per_second_one_core": frame["frames_per_second_one_core"],
        "frames_dropped": {"value": live["frames_dropped"] + live["queue_overflows"],
                           "target_max": 0,
                           "met": live["frames_dropped"] + live["queue_overflows"] == 0},
        "memory_growth": {"value": live["rss_mb"]["growth"], "target_max": TARGET_MEMORY_GROWTH,
                          "met": abs(live["rss_mb"]["growth"]) <= TARGET_MEMORY_GROWTH},
        "latency_median_ms": {"value": live["latency_ms"]["median"],
                              "target_max": TARGET_LATENCY_MEDIAN_MS,
                              "met": live["latency_ms"]["median"] <= TARGET_LATENCY_MEDIAN_MS},
        "latency_p99_ms": {"value": live["latency_ms"]["p99"], "target_max": TARGET_LATENCY_P99_MS,
                           "met": live["latency_ms"]["p99"] <= TARGET_LATENCY_P99_MS},
        "processing_cores": {"value": live["processing_cores"], "target_max": 1.0,
                             "met": live["processing_cores"] <= 1.0},
        "passes_failed": live["failed"],
        "pose_published_p95_ms": {
            "value": pose["pose_published_ms_up_to_target_points"].get("p95"),
            "target_max": TARGET_POSE_P95_MS, "up_to_points": TARGET_POSE_POINTS,
            "met": pose["target"]["met"],
            "by_part": {name: part["pose_published_ms_up_to_target_points"].get("p95")
                        for name, part in pose["by_part"].items()},
            "passes_with_the_pose_computed_ahead": [pose["ahead_kept"], len(pose["rows"])],
            # the same passes with the pose computed at the pass's end (pose_ahead_frames 0)
            "at_pass_end": at_end["pose_published_ms_up_to_target_points"].get("p95"),
            "pose_computed_p95_ms": pose["pose_computed_ms_up_to_target_points"].get("p95")},
    }
    result = {"per_frame": frame, "passes": live, "pose": pose, "pose_at_pass_end": at_end,
              "summary": summary,
              "quick": quick,
              "machine": dict(machine_info(),
                              load_average_before=[round(v, 2) for v in load_before],
                              load_average_after=[round(v, 2) for v in os.getloadavg()])}
    result = write_json(out_dir / "service.json", result)
    from benchmarks.service_charts import plot  # matplotlib: only to draw

    plot(result, out_dir / "service.png")
    return result
