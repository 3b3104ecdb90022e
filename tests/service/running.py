"""A ``flyscan serve --sim`` process for the tests, on free loopback ports."""
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import httpx
import uvicorn

from benchmarks.live import ServeProcess, free_port
from benchmarks.live import wait_for as poll_until

#: Start-up (imports, JIT warm-up, background frames) takes a few seconds on 2 cores.
START_TIMEOUT_S = 60.0


def wait_for(predicate, timeout=30.0, poll=0.02):
    """The predicate's first truthy value within ``timeout`` s; TimeoutError otherwise."""
    value = poll_until(predicate, timeout, poll)
    if value is None:
        raise TimeoutError("condition not met in time")
    return value


class RunningService(ServeProcess):
    """A ``flyscan serve`` process and where to reach it (``benchmarks.live.ServeProcess``)."""

    def __init__(self, data: Path, *, env: dict | None = None, args=(),
                 file_limit: int | None = None):
        super().__init__(data, env=env, args=args, start_timeout_s=START_TIMEOUT_S,
                         file_limit=file_limit)


#: The token of the tests' services that have one.
TOKEN = "s3cret"

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
