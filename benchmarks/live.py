"""The service running for a benchmark: started in simulated mode and always stopped, passes
armed and waited for, a free loopback port. ``bench service`` and ``bench hardware`` drive the
service through these."""
from __future__ import annotations

import contextlib
import socket
import time

__all__ = ["free_port", "wait_for", "running_service", "finished_scan"]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on (for the service's ZeroMQ socket)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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
def running_service(settings):
    """The service of `settings` (``service.cli.serve.service_for``), started; stopped on the
    way out, whatever happened."""
    from service.cli.serve import service_for

    service = service_for(settings)
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
