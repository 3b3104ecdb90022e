"""Example: the loop a robot cell controller runs against the flyscan service.

    python -m clients.cell_controller --url http://127.0.0.1:8000 --zmq tcp://127.0.0.1:5556 \\
        --count 3 --part bracket [--place X,Y,Z,RX,RY,RZ] [--seed N] [--token TOKEN]

For each pick: arm the scanner, let the robot carry the part through the laser sheet (in
simulated mode the service moves the simulated robot itself), wait for the scan, read its info
(pose when the part was registered, marker-versus-robot cross-check), fetch the cloud over REST
and, in parallel, receive it from the ZeroMQ publisher; then correct the place pose: the TCP
pose that puts the part, held as measured, where a nominally held part lands at the taught
place pose (``--place``, a UR pose in the robot base: metres and a rotation vector in
radians), or do not place when the pose is not to act on. Print one line per scan.

In simulated mode (the service's ``/status`` says so) each pick is misplaced in the gripper at
random (``--seed``), and the line also gives the placed part's error against the truth: where
the corrected move puts the truly held part, against where the nominal part belongs.
``--count 0`` runs until Ctrl-C. Errors exit with status 1 and the service's reason. The token
defaults to the environment variable FLYSCAN_TOKEN.
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
from .placement import (PoseNotActionable, place_correction, pose_actionable, rotvec_to_matrix,
                        ur_pose_to_matrix)
from .subscriber import CloudSubscriber, MessageError

# A SUB socket misses what is published before its subscription reaches the publisher (slow
# joiner): give it this long after connecting, before the first scan is armed.
SUBSCRIBE_SETTLE_S = 0.3
# How long the ZeroMQ cloud may trail the REST state "done".
ZMQ_GRACE_S = 2.0
# Clouds kept for scans not yet asked for (another controller's scans are dropped, oldest first).
KEEP_CLOUDS = 8
#: The taught place pose when --place gives none: a UR pose in the robot base {B}, [x, y, z (m),
#: rx, ry, rz (rotation vector, rad)]: 400 mm out, 200 mm to the side, 100 mm up, the TCP's z
#: pointing down (half a turn about x_B).
DEFAULT_PLACE = (0.4, -0.2, 0.1, float(np.pi), 0.0, 0.0)
#: Simulated mode: each pick's misplacement in the gripper is drawn uniformly within these, per
#: axis (mm; rotation vector, degrees): what a pick leaves, well inside the inspection volume.
SIM_MISPLACE_MM = 1.0
SIM_MISPLACE_DEG = 2.0


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
        timeout: float, out=sys.stdout, taught_place=DEFAULT_PLACE, seed: int = 0) -> int:
    """Scan `count` parts (0: until Ctrl-C), one line each; return how many were scanned.

    `taught_place` is ^B X_T,place as a UR pose (m, rad). On a simulated cell every pick is
    misplaced at random (seeded by `seed`) and the placed part's error is measured.
    """
    api.health()
    simulated = bool(api.status().get("simulated"))
    rng = np.random.default_rng(seed)
    taught = ur_pose_to_matrix(taught_place)
    time.sleep(SUBSCRIBE_SETTLE_S)
    done = 0
    try:
        for n in itertools.count(1) if count == 0 else range(1, count + 1):
            misplace = random_misplacement(rng) if simulated else None
            scan_id = api.arm(part=part, misplace=misplace, taught_place=taught_place)
            info = api.wait(scan_id, timeout=timeout)       # ScanFailed carries the reason
            rest_cloud = api.cloud(scan_id)
            zmq_cloud = clouds.pop(scan_id, timeout=ZMQ_GRACE_S)
            nominal = nominal_grasp(api, info.get("part"))
            print(scan_line(n, info, rest_cloud, zmq_cloud, lost=clouds.lost) + "; "
                  + place_line(info.get("pose"), taught, nominal, misplace), file=out,
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
    if "act" in pose:
        if pose["act"] is not True:
            text += " NOT TO ACT ON: " + "; ".join(pose_actionable(pose)[1])
    elif pose.get("flags"):
        text += " NOT TO ACT ON: " + "; ".join(pose["flags"])
    return text


def nominal_grasp(api: FlyscanClient, part: str | None) -> np.ndarray | None:
    """The part's nominal grasp ^T X_P (4, 4) mm from ``GET /parts``; None without a part."""
    if part is None:
        return None
    for info in api.parts():
        if info["name"] == part:
            return np.asarray(info["nominal_grasp"], dtype=np.float64)
    raise FlyscanError(None, f"part {part!r} of the scan is not in GET /parts")


def random_misplacement(rng: np.random.Generator) -> list[float]:
    """[tx, ty, tz (mm), rx, ry, rz (rotation vector, degrees)] within the SIM_MISPLACE_ bounds."""
    return [*rng.uniform(-SIM_MISPLACE_MM, SIM_MISPLACE_MM, 3).round(3),
            *rng.uniform(-SIM_MISPLACE_DEG, SIM_MISPLACE_DEG, 3).round(3)]


def misplacement_matrix(misplace) -> np.ndarray:
    """The simulated cell's convention: [tx, ty, tz mm, rotation vector deg] -> (4, 4) in {T};
    the part truly held is ``misplacement_matrix(misplace) @ nominal`` (X_T = R X_P + t)."""
    m = np.eye(4)
    m[:3, :3] = rotvec_to_matrix(np.radians(np.asarray(misplace[3:], dtype=np.float64)))
    m[:3, 3] = misplace[:3]
    return m


def placed_error(placed: np.ndarray, target: np.ndarray) -> tuple[float, float]:
    """How far a placed part ^B X_P is from its target ^B X_P: the distance of their {P}
    origins, um, and the angle between them, millidegrees."""
    translation_um = float(np.linalg.norm(placed[:3, 3] - target[:3, 3])) * 1e3
    turn = placed[:3, :3] @ target[:3, :3].T
    cos = np.clip((np.trace(turn) - 1.0) / 2.0, -1.0, 1.0)
    return translation_um, float(np.degrees(np.arccos(cos))) * 1e3


def place_line(pose: dict | None, taught: np.ndarray, nominal: np.ndarray | None,
               misplace=None) -> str:
    """Where to move the TCP to place the part (a UR pose), or why not to place; with the
    simulated misplacement, also the placed part's error against the truth."""
    try:
        if nominal is None:
            raise PoseNotActionable(["no part, so no nominal grasp"])
        correction = place_correction(taught, pose, nominal)
    except PoseNotActionable as exc:
        return "do not place: " + "; ".join(exc.reasons)
    text = "place at " + _compact(correction.ur_pose.tolist(), digits=5)
    if misplace is not None:
        truth = misplacement_matrix(misplace) @ nominal            # ^T X_P truly held
        error_um, error_mdeg = placed_error(correction.tcp_place_mm @ truth, taught @ nominal)
        text += f", placed part off by {error_um:.1f} um, {error_mdeg:.1f} mdeg (truth)"
    return text


def _compact(value, digits: int = 3) -> str:
    """JSON on one line, floats to `digits` decimals."""
    def rounded(v):
        if isinstance(v, float):
            return round(v, digits)
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
    parser.add_argument("--place", default=",".join(f"{v:.10g}" for v in DEFAULT_PLACE),
                        help="the taught place pose, the TCP in the robot base, as a UR pose "
                             "'x,y,z,rx,ry,rz' (m; rotation vector, rad); a leading minus "
                             "needs --place=-0.4,... (default %(default)s)")
    parser.add_argument("--seed", type=int, default=0,
                        help="simulated mode: seed of the random misplacements")
    args = parser.parse_args(argv)
    if args.count < 0:
        parser.error("--count must be >= 0")
    try:
        place = [float(v) for v in args.place.split(",")]
        ur_pose_to_matrix(place)
    except ValueError as exc:
        parser.error(f"--place: {exc}")

    try:
        with FlyscanClient(args.url, token=args.token) as api, CloudCollector(args.zmq) as clouds:
            run(api, clouds, count=args.count, part=args.part, timeout=args.timeout,
                taught_place=place, seed=args.seed)
    except (FlyscanError, TimeoutError, ConnectionError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:                           # the way to end --count 0
        return 0 if args.count == 0 else 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
