"""A ``flyscan serve --sim`` process for the tests, on free loopback ports."""
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import threading
from contextlib import contextmanager

import httpx
import uvicorn

#: Start-up (imports, JIT warm-up, background frames) takes a few seconds on 2 cores.
START_TIMEOUT_S = 60.0


def wait_for(predicate, timeout=30.0, poll=0.02):
    """The predicate's first truthy value within ``timeout`` s; TimeoutError otherwise."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll)
    raise TimeoutError("condition not met in time")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class RunningService:
    """A ``flyscan serve`` process and where to reach it."""

    def __init__(self, data: Path, *, env: dict | None = None, args=()):
        self.port, self.zmq_port = free_port(), free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.zmq = f"tcp://127.0.0.1:{self.zmq_port}"
        self.data = data
        self.log = data.parent / f"serve-{self.port}.log"
        environ = {**os.environ, "OPENBLAS_NUM_THREADS": "1", **(env or {})}
        self._log_file = open(self.log, "w")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "serve", "--sim", "--port", str(self.port),
             "--zmq", self.zmq, "--data", str(data), *args],
            stdout=self._log_file, stderr=subprocess.STDOUT, env=environ)
        self.wait_healthy()

    def wait_healthy(self) -> None:
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"flyscan serve exited: {self.log.read_text()[-2000:]}")
            try:
                if httpx.get(f"{self.url}/health", timeout=1.0).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        raise RuntimeError(f"flyscan serve did not start: {self.log.read_text()[-2000:]}")

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(15)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._log_file.close()


#: A fast pass (1 m/s: about half a second with lead-in and lead-out) keeps the tests short.
FAST_PASS = {"FLYSCAN_SIM_SPEED_MM_S": "1000"}




@contextmanager
def serve_in_thread(app):
    """Serve an ASGI app on a free loopback port from a thread of this process (real HTTP;
    for tests that must reach into the devices). Yields an httpx.Client on its URL."""
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=free_port(),
                                           log_level="warning", lifespan="on"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + START_TIMEOUT_S
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("the in-process server did not start")
        time.sleep(0.05)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{server.config.port}", timeout=10.0) as client:
            yield client
    finally:
        server.should_exit = True
        thread.join(30)
