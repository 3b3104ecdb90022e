"""Example: the loop a robot cell controller runs against the flyscan service.

    python -m clients.cell_controller --url http://127.0.0.1:8000 --zmq tcp://127.0.0.1:5556 \\
        --count 3 --part bracket [--token TOKEN]

For each pick: arm the scanner, let the robot carry the part through the laser sheet (in
simulated mode the service moves the simulated robot itself), wait for the scan, read its info
(pose when the part was registered, marker-versus-robot cross-check), fetch the cloud over REST
and, in parallel, receive it from the ZeroMQ publisher; print one line per scan. ``--count 0``
runs until Ctrl-C. Errors exit with status 1 and the service's reason. The token defaults to
the environment variable FLYSCAN_TOKEN.
"""
from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import threading
import time

import numpy as np

from .http_client import FlyscanClient, FlyscanError
from .subscriber import CloudSubscriber, MessageError

# A SUB socket misses what is published before its subscription reaches the publisher (slow
# joiner): give it this long after connecting, before the first scan is armed.
SUBSCRIBE_SETTLE_S = 0.3
# How long the ZeroMQ cloud may trail the REST state "done".
ZMQ_GRACE_S = 2.0
# Clouds kept for scans not yet asked for (another controller's scans are dropped, oldest first).
KEEP_CLOUDS = 8


class CloudCollector:
    """Receives the published clouds in its own thread (the socket's only user), by scan id."""

    def __init__(self, endpoint: str):
        self.endpoint = endpoint
        self.lost = 0
        self._clouds: dict[str, np.ndarray] = {}
        self._changed = threading.Condition()
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._error: Exception | None = None
        self._thread = threading.Thread(target=self._run, name="zmq-clouds", daemon=True)

    def __enter__(self) -> CloudCollector:
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            raise self._error
        return self

    def __exit__(self, *exc_info) -> None:
        self._stop.set()
        self._thread.join()

    def pop(self, scan_id: str, timeout: float) -> np.ndarray | None:
        """The cloud published for `scan_id`, or None when none came within `timeout` s."""
        with self._changed:
            self._changed.wait_for(lambda: scan_id in self._clouds, timeout)
            return self._clouds.pop(scan_id, None)

    def _run(self) -> None:
        # Every topic, so that `lost` counts exactly; only clouds are kept.
        try:
            sub = CloudSubscriber(self.endpoint).connect()
        except ConnectionError as exc:
            self._error = exc
            return
        finally:
            self._ready.set()
        with sub:
            while not self._stop.is_set():
                try:
                    msg = sub.receive(timeout=0.1)
                except TimeoutError:
                    continue
                except MessageError as exc:
                    print(f"zmq: refused a message: {exc}", file=sys.stderr)
                    continue
                with self._changed:
                    self.lost = sub.lost
                    if msg.topic == "cloud":
                        self._clouds[msg.scan_id] = msg.array
                        while len(self._clouds) > KEEP_CLOUDS:  # scans armed by others
                            self._clouds.pop(next(iter(self._clouds)))
                        self._changed.notify_all()


def run(api: FlyscanClient, clouds: CloudCollector, *, count: int, part: str | None,
        timeout: float, out=sys.stdout) -> int:
    """Scan `count` parts (0: until Ctrl-C), one line each; return how many were scanned."""
    api.health()
    time.sleep(SUBSCRIBE_SETTLE_S)
    done = 0
    try:
        for n in itertools.count(1) if count == 0 else range(1, count + 1):
            scan_id = api.arm(part=part)
            info = api.wait(scan_id, timeout=timeout)       # ScanFailed carries the reason
            rest_cloud = api.cloud(scan_id)
            zmq_cloud = clouds.pop(scan_id, timeout=ZMQ_GRACE_S)
            print(scan_line(n, info, rest_cloud, zmq_cloud, lost=clouds.lost), file=out,
                  flush=True)
            done += 1
    except KeyboardInterrupt:
        print(f"stopped by Ctrl-C after {done} scans", file=sys.stderr)
        raise
    return done


def scan_line(n: int, info: dict, rest_cloud: np.ndarray, zmq_cloud: np.ndarray | None,
              *, lost: int = 0) -> str:
    """One line: scan id, state, points, the misplacement to correct (or why not), cross-check,
    ZeroMQ."""
    misplacement = describe_pose(info.get("pose"))
    if zmq_cloud is None:
        zmq = f"zmq: no cloud received (lost {lost})"
    else:
        # Bit for bit: both are the same float32 array, sent two ways.
        same = zmq_cloud.shape == rest_cloud.shape and np.array_equal(zmq_cloud, rest_cloud)
        zmq = "zmq cloud == rest cloud" if same else "zmq cloud DIFFERS from rest cloud"
    return (f"#{n} {info['scan_id']} {info['state']}: {info['points']} points "
            f"({len(rest_cloud)} fetched), {info.get('edge_points')} edge points, "
            f"misplacement {misplacement}, cross-check {_compact(info.get('cross_check'))}, "
            f"{zmq}")


def describe_pose(pose: dict | None) -> str:
    """The misplacement a robot would correct, or why it should not act on it."""
    if not pose:
        return "no pose"
    if "refused" in pose:
        return f"no pose ({pose['refused']})"
    text = _compact(pose["misplacement"])
    if pose.get("flags"):
        text += " NOT TO ACT ON: " + "; ".join(pose["flags"])
    return text


def _compact(value) -> str:
    """JSON on one line, floats to 3 decimals."""
    def rounded(v):
        if isinstance(v, float):
            return round(v, 3)
        if isinstance(v, dict):
            return {k: rounded(x) for k, x in v.items()}
        if isinstance(v, list):
            return [rounded(x) for x in v]
        return v
    return json.dumps(rounded(value), separators=(",", ":"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m clients.cell_controller",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="the service's REST API")
    parser.add_argument("--zmq", default="tcp://127.0.0.1:5556", help="the service's publisher")
    parser.add_argument("--count", type=int, default=1, help="scans to run; 0: until Ctrl-C")
    parser.add_argument("--part", default=None, help="part name to register against")
    parser.add_argument("--token", default=os.environ.get("FLYSCAN_TOKEN"),
                        help="bearer token (default: $FLYSCAN_TOKEN)")
    parser.add_argument("--timeout", type=float, default=30.0, help="seconds per scan")
    args = parser.parse_args(argv)
    if args.count < 0:
        parser.error("--count must be >= 0")

    try:
        with FlyscanClient(args.url, token=args.token) as api, CloudCollector(args.zmq) as clouds:
            run(api, clouds, count=args.count, part=args.part, timeout=args.timeout)
    except (FlyscanError, TimeoutError, ConnectionError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:                           # the way to end --count 0
        return 0 if args.count == 0 else 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
