"""The service running for a benchmark: started in simulated mode and always stopped, passes
armed and waited for, a free loopback port. ``bench service`` and ``bench hardware`` drive the
service through these; ``bench abuse`` and the service's tests run it as its own process
(`ServeProcess`)."""
from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

__all__ = ["free_port", "free_ports", "wait_for", "running_service", "finished_scan", "ServeProcess",
           "resident_mb"]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on (for the service's ZeroMQ socket)."""
    return free_ports(1)[0]


def free_ports(count: int) -> list[int]:
    """`count` distinct free TCP ports on 127.0.0.1: held open together while they are
    picked (two calls of `free_port` in a row can return the same port)."""
    sockets = [socket.socket() for _ in range(count)]
    try:
        for s in sockets:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


def wait_for(predicate, timeout: float, poll: float = 0.01):
    """`predicate()` polled every `poll` s until it is truthy (then its value), or None after
    `timeout` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll)
    return None


@contextlib.contextmanager
def running_service(settings, options=None, *, robot: str | None = None):
    """The service of `settings` on the simulated cell of `options`
    (``simulator.driver.SimulatedCellOptions``; None: the reference cell), started; with
    `robot` (``ur://HOST``) the simulated robot is served by an RTDE emulator at HOST and read
    through the real ur-rtde client. Stopped on the way out, whatever happened."""
    from service.daemon import Service
    from service.ur_robot import URRobot, parse_robot_url
    from simulator.driver import SimulatedCellOptions, simulated_cell_devices

    devices = simulated_cell_devices(options or SimulatedCellOptions(),
                                     rtde_host=None if robot is None else parse_robot_url(robot),
                                     robot_client=URRobot)
    service = Service(settings, devices=devices)
    service.start()
    try:
        yield service
    finally:
        service.stop()


def finished_scan(service, scan_id: str, timeout: float, poll: float) -> dict | None:
    """The scan's info once it is done or failed, polled every `poll` s; None after `timeout` s."""

    def over():
        info = service.scan_info(scan_id)
        return info if info["state"] in ("done", "failed") else None

    return wait_for(over, timeout, poll)


def resident_mb(pid: int) -> float:
    """Process `pid`'s resident memory (``VmRSS``), MB; NaN when it has none (OSError when
    it has ended)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _limit_files(n: int) -> None:
    """In the child before it runs: at most `n` open files, soft and hard."""
    import resource

    resource.setrlimit(resource.RLIMIT_NOFILE, (n, n))


class ServeProcess:
    """A ``flyscan serve --sim`` process on free loopback ports (REST and ZeroMQ), its output
    in ``serve-PORT.log`` beside `data`; started and healthy once constructed (RuntimeError
    with the log's end otherwise, the process stopped).

    Parameters
    ----------
    data : Path
        The service's data folder.
    env : dict, optional
        Environment on top of this one's (``FLYSCAN_*`` settings).
    args : sequence of str
        More ``flyscan serve`` options.
    start_timeout_s : float
        How long start-up (imports, JIT warm-up, background frames) may take.
    file_limit : int, optional
        The process's open-file limit, soft and hard (a cell PC's usual 1024), else this
        one's.
    """

    def __init__(self, data: Path, *, env: dict | None = None, args=(),
                 start_timeout_s: float = 60.0, file_limit: int | None = None):
        import httpx  # the service's own dependency; not needed by the in-process benches

        self._httpx = httpx
        self.port, self.zmq_port = free_ports(2)
        self.url = f"http://127.0.0.1:{self.port}"
        self.zmq = f"tcp://127.0.0.1:{self.zmq_port}"
        self.data = data
        self.log = data.parent / f"serve-{self.port}.log"
        environ = {**os.environ, "OPENBLAS_NUM_THREADS": "1", **(env or {})}
        self._log_file = open(self.log, "w")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "flyscan", "serve", "--sim", "--port", str(self.port),
             "--zmq", self.zmq, "--data", str(data), *args],
            stdout=self._log_file, stderr=subprocess.STDOUT, env=environ,
            preexec_fn=None if file_limit is None else partial(_limit_files, file_limit))
        self.wait_healthy(start_timeout_s)

    def wait_healthy(self, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"flyscan serve exited: {self.log.read_text()[-2000:]}")
            try:
                if self._httpx.get(f"{self.url}/health", timeout=1.0).status_code == 200:
                    return
            except self._httpx.HTTPError:
                pass
            time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"flyscan serve did not start: {self.log.read_text()[-2000:]}")

    def stop(self, wait_s: float = 20.0) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(wait_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._log_file.close()
