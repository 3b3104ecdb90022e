"""Benchmark of the web side against the camera: passes armed over REST on a real
``flyscan serve --sim`` process while clients loop on the read endpoints nobody needs a token
for, and what each pass lost.

Load patterns (each run against the same service, with ``STORED`` scans on disk):

- ``quiet``: no other client;
- ``frame``: four clients looping on ``GET /frame.png``;
- ``preview``: four clients looping on ``GET /scans/{newest}/preview.png``;
- ``scans``: one client looping on ``GET /scans``;
- ``pages``: three status pages open (the page, its script and style, ``/events`` held open,
  ``GET /scans`` every second, the newest scan's preview and ``/frame.png`` as ``app.js`` asks);
- ``target``: the issue's target: three status pages and four clients looping on the picture
  endpoints (two on ``/frame.png``, two on the preview);
- ``bodies``: two clients sending 200 MB bodies over and over (chunked and with a
  Content-Length, to ``POST /scans``, ``PUT /calibration``, ``PUT /parts``, with and without
  the token: the service has one, ``TOKEN``, as a cell on a shared network would);
- ``slow``: four clients dribbling a chunked upload (``PUT /parts``, 1 KiB every 0.1 s), which
  hold the body slots: the passes are armed all the same (an arm's body is small);
- ``streams``: forty clients holding ``/events`` open (``max_event_streams`` of them served);
- ``idle``: 1100 idle TCP connections held open, each reopened as soon as the service closes
  it (``header_timeout_s``), against the service's open-file limit of 1024 (soft and hard, a
  cell PC's usual), and ``/health`` asked every 0.2 s;
- ``uploads``: two clients uploading, over and over, a binary STL at the size limit (1.3 M
  triangles, 62.5 MiB), each then deleted (the upload is read and simplified in the service's
  loader process);
- ``catalogue`` (no passes): parts far finer than the scan needs uploaded one after another
  under a memory budget for the prepared models (``prepared_parts_mb``), each armed and
  scanned, then all deleted: each arm's answer time and the service's memory.

The service runs with the open-file limit of 1024 and ``prepared_parts_mb`` at
``PREPARED_BUDGET_MB``.

For each pass: its state, frames, ``frames_dropped`` and ``queue_overflows`` and its latency
(``latency_ms``: the last frame to the cloud and to the pose on ZeroMQ); the clients' answers
by status code and the time each waited for an answer; the service's memory (``VmRSS``,
sampled every 0.2 s). ``run(out_dir)`` writes ``abuse.json`` and ``abuse.png``: ``flyscan bench
abuse --out OUT [--quick]``, or with the counts chosen ``python -m benchmarks.abuse OUT
[--passes N] [--target-passes N] [--patterns ...]``.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import tempfile
import threading
import time
from collections import Counter, defaultdict
from pathlib import Path

import httpx
import numpy as np

from benchmarks.live import ServeProcess, resident_mb
from benchmarks.stats import spread
from benchmarks.results import machine_info, pyplot, save_figure, write_json
from service.pictures import FRAME_PERIOD_S
from simulator.cell import load_cell
from simulator.live import CAMERA_BUFFER_FRAMES

__all__ = ["run"]

#: Scans on disk while the patterns run (the issue's case: 174; the quick set's fewer).
STORED, QUICK_STORED = 174, 20
PASSES, QUICK_PASSES = 5, 2
TARGET_PASSES, QUICK_TARGET_PASSES = 100, 3
START_TIMEOUT_S = 90.0
PASS_TIMEOUT_S = 60.0
#: How often a status page asks for the list of scans and for the frame, s (``app.js``).
PAGE_SCANS_PERIOD_S = 1.0
PAGE_FRAME_PERIOD_S = 0.2
#: Patterns, in the order they run.
PATTERNS = ("quiet", "frame", "preview", "scans", "pages", "target", "bodies", "slow", "streams",
            "idle", "uploads", "catalogue")
#: Idle connections of the ``idle`` pattern, and the service's open-file limit.
IDLE_CONNECTIONS, FILE_LIMIT = 1100, 1024
#: Passes of the ``uploads`` pattern (the issue's count), quick or not.
UPLOAD_PASSES, QUICK_UPLOAD_PASSES = 20, 3
#: The ``uploads`` pattern's mesh: an icosphere of 20 * 4^8 = 1 310 720 triangles, a binary
#: STL of 65 536 084 bytes, under ``max_part_bytes`` (64 MiB).
UPLOAD_SUBDIVISIONS = 8
#: The ``catalogue`` pattern: parts (icospheres of 327 680 triangles, each its own radius),
#: and the prepared models' budget (MB) of the service.
CATALOGUE_PARTS, QUICK_CATALOGUE_PARTS = 8, 3
PREPARED_BUDGET_MB = 400
#: A large body, bytes, sent in pieces of 1 MiB; a slow one's pieces and their period.
BIG_BODY, BIG_PIECE = 200 * 10**6, 1 << 20
SLOW_PIECE, SLOW_PERIOD_S = 1024, 0.1
#: The service's token (the passes are armed with it; the reads need none).
TOKEN = "abuse-bench-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
#: Event streams held open in ``streams``.
STREAMS = 40
#: The service's memory is sampled this often, s.
MEMORY_PERIOD_S = 0.2
#: ``/frame.png`` renders before the patterns (one every ``FRAME_PERIOD_S``).
WARM_FRAME_PICTURES = 5


def _one_pass(client: httpx.Client, part: str | None = None) -> dict:
    t0 = time.monotonic()
    scan_id = client.post("/scans", json={} if part is None else {"part": part}).json()["scan_id"]
    arm_ms = (time.monotonic() - t0) * 1e3
    deadline = time.monotonic() + PASS_TIMEOUT_S
    while time.monotonic() < deadline:
        info = client.get(f"/scans/{scan_id}").json()
        if info["state"] in ("done", "failed"):
            return {**info, "arm_ms": arm_ms}
        time.sleep(0.1)
    return {"scan_id": scan_id, "state": "timeout", "frames": 0, "frames_dropped": None,
            "queue_overflows": None, "latency_ms": {}, "arm_ms": arm_ms}


def _warm(client: httpx.Client, pid: int) -> dict:
    """What a process builds once and keeps: a first pass, then the pictures of its frames
    and of its scan. Its memory before and after, MB: a pattern's growth is then what its
    clients add, not the first use of what they ask for."""
    before = resident_mb(pid)
    scan_id = _one_pass(client)["scan_id"]
    for _ in range(WARM_FRAME_PICTURES):
        client.get("/frame.png")
        time.sleep(FRAME_PERIOD_S)
    client.get(f"/scans/{scan_id}/preview.png")
    client.get("/")
    return {"before": before, "after": resident_mb(pid)}


def _seed(data: Path, count: int) -> None:
    """One real pass, then ``count - 1`` copies of it on disk (new ids, older dates)."""
    served = ServeProcess(data, env={"FLYSCAN_TOKEN": TOKEN}, start_timeout_s=START_TIMEOUT_S)
    try:
        with httpx.Client(base_url=served.url, timeout=60, headers=AUTH) as client:
            info = _one_pass(client)
    finally:
        served.stop()
    scans = data / "scans"
    source = scans / info["scan_id"]
    for i in range(count - 1):
        copy = scans / f"seed-{i:04d}"
        shutil.copytree(source, copy)
        meta = json.loads((copy / "info.json").read_text())
        meta.update(scan_id=copy.name, created=meta["created"] - 3600 - i)
        (copy / "info.json").write_text(json.dumps(meta))


def _big_body():
    piece = b"x" * BIG_PIECE
    yield b'{"part": "'
    sent = 10
    while sent < BIG_BODY:
        yield piece[:min(BIG_PIECE, BIG_BODY - sent)]
        sent += BIG_PIECE


def _clients(url: str, pattern: str, stop: threading.Event, answers: Counter,
             waits: dict, mesh: Path | None = None) -> list[threading.Thread]:
    lock = threading.Lock()

    def count(key, waited_s=None):
        with lock:
            answers[key] += 1
            if waited_s is not None:
                waits[key.split(" ")[0]].append(waited_s)

    def newest(client):
        return client.get("/scans").json()["scans"][0]["scan_id"]

    def loop(paths):
        def body():
            with httpx.Client(base_url=url, timeout=60) as client:
                preview = f"/scans/{newest(client)}/preview.png"
                i = 0
                while not stop.is_set():
                    path = paths[i % len(paths)].replace("{preview}", preview)
                    i += 1
                    t0 = time.monotonic()
                    try:
                        r = client.get(path)
                        count(f"{path.split('/')[-1]} {r.status_code}", time.monotonic() - t0)
                    except httpx.HTTPError as exc:
                        count(f"{path.split('/')[-1]} {type(exc).__name__}")
        return body

    def bodies():
        routes = [("POST", "/scans"), ("PUT", "/calibration"), ("PUT", "/parts/big?units=mm")]
        with httpx.Client(base_url=url, timeout=120) as client:
            i = 0
            while not stop.is_set():
                method, path = routes[i % len(routes)]
                sized = (i // len(routes)) % 2 == 1
                token = (i // (2 * len(routes))) % 2 == 1
                i += 1
                headers = {"Content-Type": "application/json", **(AUTH if token else {})}
                if sized:
                    headers["Content-Length"] = str(BIG_BODY)
                t0 = time.monotonic()
                try:
                    r = client.request(method, path, content=_big_body(), headers=headers)
                    count(f"body {r.status_code}", time.monotonic() - t0)
                except httpx.HTTPError as exc:  # the service closed the connection mid-body
                    count(f"body {type(exc).__name__}", time.monotonic() - t0)

    def slow():
        host, port = url.removeprefix("http://").split(":")
        while not stop.is_set():
            with socket.create_connection((host, int(port)), timeout=30) as sock:
                sock.sendall(f"PUT /parts/slow?units=mm HTTP/1.1\r\nHost: {host}\r\n"
                             f"Authorization: Bearer {TOKEN}\r\n"
                             f"Transfer-Encoding: chunked\r\n\r\n".encode())
                piece = f"{SLOW_PIECE:x}\r\n".encode() + b"x" * SLOW_PIECE + b"\r\n"
                try:
                    while not stop.is_set():
                        sock.sendall(piece)
                        time.sleep(SLOW_PERIOD_S)
                        if _has_answer(sock):  # refused (503: no slot) or stopped (408, 413)
                            head = sock.recv(4096)
                            count(f"slow {head.split(b' ', 2)[1].decode() if head else 'closed'}")
                            break
                except OSError as exc:
                    count(f"slow {type(exc).__name__}")
            time.sleep(SLOW_PERIOD_S)  # then dribbles again

    def stream():
        host, port = url.removeprefix("http://").split(":")
        with socket.create_connection((host, int(port)), timeout=30) as sock:
            sock.sendall(f"GET /events HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())
            head = sock.recv(4096)
            count(f"stream {head.split(b' ', 2)[1].decode() if head else 'closed'}")
            while not stop.is_set() and head.startswith(b"HTTP/1.1 200"):
                if not sock.recv(65536):
                    break

    def page():
        with httpx.Client(base_url=url, timeout=60) as client:
            for path in ("/", "/static/app.js", "/static/style.css"):
                count(f"page {client.get(path).status_code}")
            # /events held open in a thread of its own
            def events():
                with httpx.Client(base_url=url, timeout=None) as sse:
                    with sse.stream("GET", "/events") as r:
                        for line in r.iter_lines():
                            if line.startswith("event:"):
                                count("events")
                            if stop.is_set():
                                return
            threading.Thread(target=events, daemon=True).start()
            next_scans = 0.0
            while not stop.is_set():
                now = time.monotonic()
                if now >= next_scans:
                    scans = client.get("/scans").json()["scans"]
                    count("page scans")
                    done = next((s for s in scans if s["state"] == "done"), None)
                    if done is not None:
                        preview = client.get(f"/scans/{done['scan_id']}/preview.png")
                        count(f"page preview {preview.status_code}")
                    next_scans = now + PAGE_SCANS_PERIOD_S
                count(f"page frame {client.get('/frame.png').status_code}")
                time.sleep(PAGE_FRAME_PERIOD_S)

    def idle():
        host, port = url.removeprefix("http://").split(":")
        held: list[socket.socket] = []
        try:
            while not stop.is_set():
                alive = []
                for sock in held:
                    try:  # non-blocking: select() takes no descriptor past 1023
                        closed = not sock.recv(1024)
                    except BlockingIOError:
                        closed = False
                    except OSError:
                        closed = True
                    if closed:
                        sock.close()
                        count("idle closed by the service")
                    else:
                        alive.append(sock)
                held = alive
                while len(held) < IDLE_CONNECTIONS:
                    sock = socket.socket()
                    sock.setblocking(False)
                    sock.connect_ex((host, int(port)))
                    held.append(sock)
                    count("idle opened")
                stop.wait(0.5)
        finally:
            for sock in held:
                sock.close()

    def health():
        with httpx.Client(base_url=url, timeout=10) as client:
            while not stop.is_set():
                t0 = time.monotonic()
                try:
                    r = client.get("/health")
                    count(f"health {r.status_code}", time.monotonic() - t0)
                except httpx.HTTPError as exc:
                    count(f"health {type(exc).__name__}", time.monotonic() - t0)
                stop.wait(0.2)

    def uploads():
        content = mesh.read_bytes()
        name = f"upload-{threading.get_ident() % 10000}"
        with httpx.Client(base_url=url, timeout=600, headers=AUTH) as client:
            while not stop.is_set():
                t0 = time.monotonic()
                try:
                    r = client.put(f"/parts/{name}", params={"units": "mm"}, content=content,
                                   headers={"Content-Type": "application/octet-stream"})
                    count(f"upload {r.status_code}", time.monotonic() - t0)
                    if r.status_code == 201:
                        client.delete(f"/parts/{name}")
                except httpx.HTTPError as exc:
                    count(f"upload {type(exc).__name__}", time.monotonic() - t0)

    targets = {
        "idle": [idle, health],
        "uploads": [uploads] * 2,
        "quiet": [],
        "frame": [loop(["/frame.png"])] * 4,
        "preview": [loop(["{preview}"])] * 4,
        "scans": [loop(["/scans"])],
        "pages": [page] * 3,
        "target": [page] * 3 + [loop(["/frame.png"])] * 2 + [loop(["{preview}"])] * 2,
        "bodies": [bodies] * 2,
        "slow": [slow] * 4,
        "streams": [stream] * STREAMS,
    }[pattern]
    return [threading.Thread(target=t, daemon=True) for t in targets]


def _has_answer(sock) -> bool:
    import select
    return bool(select.select([sock], [], [], 0)[0])


class _Memory(threading.Thread):
    """The service's ``VmRSS`` (MB) every `MEMORY_PERIOD_S` until stopped."""

    def __init__(self, pid: int):
        super().__init__(daemon=True)
        self.pid, self.samples, self.stop = pid, [], threading.Event()

    def run(self) -> None:
        while not self.stop.wait(MEMORY_PERIOD_S):
            try:
                rss = resident_mb(self.pid)
            except OSError:
                return
            if np.isfinite(rss):
                self.samples.append(rss)


def _pattern(url: str, pid: int, pattern: str, passes: int, mesh: Path | None = None) -> dict:
    stop, answers, waits = threading.Event(), Counter(), defaultdict(list)
    threads = _clients(url, pattern, stop, answers, waits, mesh)
    memory = _Memory(pid)
    memory.start()
    for t in threads:
        t.start()
    time.sleep(1.0 if threads else 0.0)  # the clients are looping before the first pass
    infos = []
    try:
        with httpx.Client(base_url=url, timeout=60, headers=AUTH) as client:
            for _ in range(passes):
                infos.append(_one_pass(client))
    finally:
        stop.set()
        for t in threads:
            t.join(10)
        memory.stop.set()
        memory.join(5)
    dropped = [i["frames_dropped"] for i in infos]
    result = {
        "passes": len(infos),
        "failed": sum(i["state"] != "done" for i in infos),
        "failed_reasons": [i.get("reason") for i in infos if i["state"] != "done"],
        "frames": [i["frames"] for i in infos],
        "frames_dropped": dropped,
        "queue_overflows": [i["queue_overflows"] for i in infos],
        "dropped_total": sum(d or 0 for d in dropped),
        "passes_with_drops": sum(bool(d) for d in dropped),
        # the longest a frame of each pass waited in the camera's buffer (16 frames: 99 ms)
        "acquisition_lag_ms": [(i.get("timings_ms") or {}).get("acquisition_lag") for i in infos],
        "answers": dict(sorted(answers.items())),
        "answer_wait_ms": {k: spread([v * 1e3 for v in w]) for k, w in sorted(waits.items())},
        "latency_ms": {key: spread([(i.get("latency_ms") or {}).get(key) for i in infos])
                       for key in ("last_frame_to_zmq", "pose_published")},
        "arm_ms": spread([i.get("arm_ms") for i in infos]),
        "rss_mb": ({"start": memory.samples[0], "max": max(memory.samples),
                    "end": memory.samples[-1]} if memory.samples else {}),
    }
    lags = [lag for lag in result["acquisition_lag_ms"] if lag is not None]
    print(f"{pattern:8s} {result['passes']} passes, {result['failed']} failed, dropped "
          f"{dropped}, worst acquisition lag {max(lags, default=float('nan')):.1f} ms, "
          f"overflows {result['queue_overflows']}, answers {result['answers']}",
          flush=True)
    return result


def _catalogue(url: str, pid: int, parts: int, folder: Path) -> dict:
    """Fine parts uploaded, armed and scanned one after another, then deleted: each arm's
    answer time, the service's memory after each scan and after the deletions."""
    import trimesh

    rows = []
    with httpx.Client(base_url=url, timeout=600, headers=AUTH) as client:
        rss_start = resident_mb(pid)
        for k in range(parts):
            path = folder / f"ball{k}.stl"
            trimesh.creation.icosphere(subdivisions=7, radius=20.0 + 2.0 * k).export(path)
            t0 = time.monotonic()
            info = client.put(f"/parts/ball{k}", params={"units": "mm"},
                              content=path.read_bytes(),
                              headers={"Content-Type": "application/octet-stream"}).json()
            upload_s = time.monotonic() - t0
            scan = _one_pass(client, part=f"ball{k}")
            prepared = client.get("/status").json().get("parts") or {}
            rows.append({"part": f"ball{k}", "upload_s": round(upload_s, 2),
                         "prepared_mb": prepared.get("prepared_mb"),
                         "released": prepared.get("released"),
                         "faces": info.get("faces"), "simplified": info.get("simplified"),
                         "arm_ms": round(scan["arm_ms"], 1), "state": scan["state"],
                         "frames_dropped": scan.get("frames_dropped"),
                         "rss_mb": round(resident_mb(pid), 1)})
            print(f"catalogue: ball{k} ({info.get('faces')} faces) uploaded in {upload_s:.1f} s, "
                  f"armed in {scan['arm_ms']:.0f} ms, {scan['state']}, service "
                  f"{rows[-1]['rss_mb']:.0f} MB, prepared models {prepared.get('prepared_mb')} "
                  f"MB ({prepared.get('released')} released)", flush=True)
        rss_full = resident_mb(pid)
        for k in range(parts):
            client.delete(f"/parts/ball{k}")
        time.sleep(1.0)
        rss_end = resident_mb(pid)
    print(f"catalogue: service {rss_start:.0f} MB before, {rss_full:.0f} MB with {parts} parts "
          f"(budget {PREPARED_BUDGET_MB} MB), {rss_end:.0f} MB after deleting them", flush=True)
    return {"parts": rows, "rss_start_mb": rss_start, "rss_full_mb": rss_full,
            "rss_end_mb": rss_end, "budget_mb": PREPARED_BUDGET_MB,
            "arm_ms": spread([r["arm_ms"] for r in rows]),
            "rss_max_mb": max(r["rss_mb"] for r in rows),
            "prepared_max_mb": max((r["prepared_mb"] or 0.0) for r in rows)}


def _upload_mesh(folder: Path) -> Path:
    import trimesh

    path = folder / "limit.stl"
    trimesh.creation.icosphere(subdivisions=UPLOAD_SUBDIVISIONS, radius=30.0).export(path)
    return path


def run(out_dir, quick: bool = False, passes: int | None = None, target_passes: int | None = None,
        patterns=PATTERNS) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    passes = passes or (QUICK_PASSES if quick else PASSES)
    target_passes = target_passes or (QUICK_TARGET_PASSES if quick else TARGET_PASSES)
    stored = QUICK_STORED if quick else STORED
    with tempfile.TemporaryDirectory(prefix="flyscan-abuse-") as tmp:
        data = Path(tmp) / "data"
        _seed(data, stored)
        load_before = os.getloadavg()
        _raise_file_limit()  # the idle pattern's own sockets
        mesh = _upload_mesh(Path(tmp)) if "uploads" in patterns else None
        served = ServeProcess(data, env={"FLYSCAN_TOKEN": TOKEN,
                                         "FLYSCAN_PREPARED_PARTS_MB": str(PREPARED_BUDGET_MB)},
                              start_timeout_s=START_TIMEOUT_S, file_limit=FILE_LIMIT)
        try:
            with httpx.Client(base_url=served.url, timeout=60, headers=AUTH) as client:
                warm = _warm(client, served.process.pid)
            print(f"warm-up: service {warm['before']:.0f} MB before its first pass and "
                  f"pictures, {warm['after']:.0f} MB after", flush=True)
            results, catalogue = {}, None
            for p in patterns:
                if p == "catalogue":
                    catalogue = _catalogue(served.url, served.process.pid,
                                           QUICK_CATALOGUE_PARTS if quick else CATALOGUE_PARTS,
                                           Path(tmp))
                    continue
                count = {"target": target_passes,
                         "uploads": QUICK_UPLOAD_PASSES if quick else UPLOAD_PASSES}.get(p, passes)
                results[p] = _pattern(served.url, served.process.pid, p, count, mesh)
        finally:
            served.stop()
    summary = {p: {**{k: r[k] for k in ("passes", "failed", "dropped_total",
                                        "passes_with_drops")},
                   "acquisition_lag_ms": spread(r["acquisition_lag_ms"]),
                   "rss_growth_mb": (r["rss_mb"]["max"] - r["rss_mb"]["start"]
                                     if r["rss_mb"] else None),
                   "pose_published_p95_ms": r["latency_ms"]["pose_published"].get("p95"),
                   "arm_max_ms": r["arm_ms"].get("max"),
                   **({"health_max_ms": r["answer_wait_ms"]["health"].get("max"),
                       "health_answers": {k: v for k, v in r["answers"].items()
                                          if k.startswith("health")}}
                      if p == "idle" and "health" in r["answer_wait_ms"] else {})}
               for p, r in results.items()}
    if catalogue is not None:
        summary["catalogue"] = {k: catalogue[k] for k in ("rss_start_mb", "rss_max_mb",
                                                          "rss_end_mb", "budget_mb",
                                                          "prepared_max_mb")}
        summary["catalogue"]["arm_max_ms"] = catalogue["arm_ms"].get("max")
    result = {"summary": summary, "warm_rss_mb": warm, "stored_scans": stored,
              "loadavg_before": load_before,
              "loadavg_after": os.getloadavg(), "patterns": results, "catalogue": catalogue,
              "file_limit": FILE_LIMIT, "machine": machine_info()}
    write_json(out_dir / "abuse.json", result)
    _chart(result, out_dir / "abuse.png")
    return result


def _raise_file_limit() -> None:
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or soft < hard:
        resource.setrlimit(resource.RLIMIT_NOFILE,
                           (hard if hard != resource.RLIM_INFINITY else 65536, hard))


def _chart(result: dict, path: Path) -> None:
    plt = pyplot()
    names = list(result["patterns"])
    catalogue = result.get("catalogue")
    fig, axes = plt.subplots(1, 3 if catalogue else 2, figsize=(18 if catalogue else 12, 4))
    ax_drops, ax_cost = axes[:2]
    if catalogue:
        ax_parts = axes[2]
        rows = catalogue["parts"]
        k = np.arange(1, len(rows) + 1)
        ax_parts.plot(k, [r["rss_mb"] for r in rows], "o-", label="service memory after its scan, MB")
        ax_parts.plot(k, [r["prepared_mb"] or 0.0 for r in rows], "s-",
                      label="the parts' prepared models, MB")
        ax_parts.axhline(catalogue["budget_mb"], color="C1", ls="--", lw=0.8,
                         label="prepared_parts_mb")
        ax_parts.axhline(catalogue["rss_start_mb"] + catalogue["budget_mb"], color="k", ls="--",
                         lw=0.8, label="memory at start + prepared_parts_mb")
        ax_parts.axhline(catalogue["rss_end_mb"], color="g", ls=":", lw=1,
                         label="after deleting them all")
        arm = ax_parts.twinx()
        arm.bar(k, [r["arm_ms"] for r in rows], 0.3, color="C1", alpha=0.5)
        arm.set_ylabel("arm answered in, ms (bars)")
        ax_parts.set_xlabel("fine parts uploaded, each armed and scanned")
        ax_parts.legend(fontsize=7, loc="lower right")
        ax_parts.set_title(f"a growing catalogue ({rows[0]['faces'] if rows else '?'} "
                           f"triangles a part after simplification)", fontsize=9)
    # what the simulated camera's buffer holds, ms (16 frames at the cell's 162 fps: 99 ms)
    buffer_ms = CAMERA_BUFFER_FRAMES / load_cell().pass_profile.fps * 1e3
    for x, name in enumerate(names):
        pattern = result["patterns"][name]
        lags = [lag if lag is not None else np.nan for lag in pattern["acquisition_lag_ms"]]
        ax_drops.scatter([x] * len(lags), lags, s=12, alpha=0.6)
        ax_drops.annotate(f"{pattern['dropped_total']} lost", (x, buffer_ms), ha="center",
                          va="bottom", fontsize=8)
    ax_drops.axhline(buffer_ms, color="k", ls="--", lw=0.8)
    ax_drops.set_xticks(range(len(names)), names, rotation=30)
    ax_drops.set_ylim(0, buffer_ms * 1.2)
    ax_drops.set_ylabel("longest wait of a frame in the camera's buffer, ms")
    ax_drops.set_title(f"passes under web load ({result['stored_scans']} stored scans); "
                       f"dashed: what the buffer holds", fontsize=9)
    growth = [result["summary"][n]["rss_growth_mb"] or 0.0 for n in names]
    latency = [result["summary"][n]["pose_published_p95_ms"] or 0.0 for n in names]
    x = np.arange(len(names))
    ax_cost.bar(x - 0.2, growth, 0.4, label="service memory growth, MB")
    ax_cost.bar(x + 0.2, latency, 0.4, label="last frame to pose on ZeroMQ, p95, ms")
    ax_cost.set_xticks(x, names, rotation=30)
    ax_cost.legend(fontsize=8)
    ax_cost.set_title("what each load cost")
    save_figure(fig, path)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--passes", type=int)
    parser.add_argument("--target-passes", type=int)
    parser.add_argument("--patterns", nargs="+", choices=PATTERNS, default=list(PATTERNS))
    a = parser.parse_args()
    run(a.out, a.quick, a.passes, a.target_passes, tuple(a.patterns))
