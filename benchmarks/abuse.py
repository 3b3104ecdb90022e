"""Benchmark of the web side against the camera (issue 28): passes armed over REST on a real
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
  endpoints (two on ``/frame.png``, two on the preview).

For each pass: its state, frames, ``frames_dropped`` and ``queue_overflows`` (the scan's info),
and the clients' answers by status code. ``run(out_dir)`` writes ``abuse.json`` and
``abuse.png``: ``flyscan bench abuse --out OUT [--quick]``, or with the counts chosen
``python -m benchmarks.abuse OUT [--passes N] [--target-passes N] [--patterns ...]``.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import httpx

from benchmarks.live import ServeProcess
from benchmarks.results import machine_info, pyplot, save_figure, write_json

__all__ = ["run"]

#: Scans on disk while the patterns run (the issue's case: 174).
STORED = 174
PASSES, QUICK_PASSES = 5, 2
TARGET_PASSES, QUICK_TARGET_PASSES = 100, 3
START_TIMEOUT_S = 90.0
PASS_TIMEOUT_S = 60.0
#: How often a status page asks for the list of scans and for the frame, s (``app.js``).
PAGE_SCANS_PERIOD_S = 1.0
PAGE_FRAME_PERIOD_S = 0.2


def _one_pass(client: httpx.Client) -> dict:
    scan_id = client.post("/scans", json={}).json()["scan_id"]
    deadline = time.monotonic() + PASS_TIMEOUT_S
    while time.monotonic() < deadline:
        info = client.get(f"/scans/{scan_id}").json()
        if info["state"] in ("done", "failed"):
            return info
        time.sleep(0.1)
    return {"scan_id": scan_id, "state": "timeout", "frames": 0, "frames_dropped": None,
            "queue_overflows": None}


def _seed(data: Path, count: int) -> None:
    """One real pass, then ``count - 1`` copies of it on disk (new ids, older dates)."""
    served = ServeProcess(data, start_timeout_s=START_TIMEOUT_S)
    try:
        with httpx.Client(base_url=served.url, timeout=60) as client:
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


def _clients(url: str, pattern: str, stop: threading.Event, answers: Counter) -> list[threading.Thread]:
    lock = threading.Lock()

    def count(key):
        with lock:
            answers[key] += 1

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
                    try:
                        r = client.get(path)
                        count(f"{path.split('/')[-1]} {r.status_code}")
                    except httpx.HTTPError as exc:
                        count(f"{path.split('/')[-1]} {type(exc).__name__}")
        return body

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

    targets = {
        "quiet": [],
        "frame": [loop(["/frame.png"])] * 4,
        "preview": [loop(["{preview}"])] * 4,
        "scans": [loop(["/scans"])],
        "pages": [page] * 3,
        "target": [page] * 3 + [loop(["/frame.png"])] * 2 + [loop(["{preview}"])] * 2,
    }[pattern]
    return [threading.Thread(target=t, daemon=True) for t in targets]


def _pattern(url: str, pattern: str, passes: int) -> dict:
    stop, answers = threading.Event(), Counter()
    threads = _clients(url, pattern, stop, answers)
    for t in threads:
        t.start()
    time.sleep(1.0 if threads else 0.0)  # the clients are looping before the first pass
    infos = []
    try:
        with httpx.Client(base_url=url, timeout=60) as client:
            for _ in range(passes):
                infos.append(_one_pass(client))
    finally:
        stop.set()
        for t in threads:
            t.join(10)
    dropped = [i["frames_dropped"] for i in infos]
    result = {
        "passes": len(infos),
        "failed": sum(i["state"] != "done" for i in infos),
        "frames": [i["frames"] for i in infos],
        "frames_dropped": dropped,
        "queue_overflows": [i["queue_overflows"] for i in infos],
        "dropped_total": sum(d or 0 for d in dropped),
        "passes_with_drops": sum(bool(d) for d in dropped),
        "answers": dict(sorted(answers.items())),
    }
    print(f"{pattern:8s} {result['passes']} passes, {result['failed']} failed, dropped "
          f"{dropped}, overflows {result['queue_overflows']}, answers {result['answers']}",
          flush=True)
    return result


def run(out_dir, quick: bool = False, passes: int | None = None, target_passes: int | None = None,
        patterns=("quiet", "frame", "preview", "scans", "pages", "target")) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    passes = passes or (QUICK_PASSES if quick else PASSES)
    target_passes = target_passes or (QUICK_TARGET_PASSES if quick else TARGET_PASSES)
    with tempfile.TemporaryDirectory(prefix="flyscan-abuse-") as tmp:
        data = Path(tmp) / "data"
        _seed(data, STORED)
        load_before = os.getloadavg()
        served = ServeProcess(data, start_timeout_s=START_TIMEOUT_S)
        try:
            with httpx.Client(base_url=served.url, timeout=60) as client:
                _one_pass(client)  # warm: the first pass of a process builds what it keeps
            results = {p: _pattern(served.url, p, target_passes if p == "target" else passes)
                       for p in patterns}
        finally:
            served.stop()
    summary = {p: {k: r[k] for k in ("passes", "failed", "dropped_total", "passes_with_drops")}
               for p, r in results.items()}
    result = {"summary": summary, "stored_scans": STORED, "loadavg_before": load_before,
              "loadavg_after": os.getloadavg(), "patterns": results, "machine": machine_info()}
    write_json(out_dir / "abuse.json", result)
    _chart(result, out_dir / "abuse.png")
    return result


def _chart(result: dict, path: Path) -> None:
    plt = pyplot()
    names = list(result["patterns"])
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for x, name in enumerate(names):
        dropped = [d or 0 for d in result["patterns"][name]["frames_dropped"]]
        ax.scatter([x] * len(dropped), dropped, s=12, alpha=0.6)
    ax.set_xticks(range(len(names)), names)
    ax.set_ylabel("frames dropped per pass")
    ax.set_title(f"passes under web load ({result['stored_scans']} stored scans)")
    save_figure(fig, path)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--passes", type=int)
    parser.add_argument("--target-passes", type=int)
    parser.add_argument("--patterns", nargs="+",
                        default=["quiet", "frame", "preview", "scans", "pages", "target"])
    a = parser.parse_args()
    run(a.out, a.quick, a.passes, a.target_passes, tuple(a.patterns))
