"""What the cell's neighbours' connections can do to ``flyscan serve --sim`` in its own
process, under a cell PC's usual open-file limit (1024, soft and hard): idle sockets by the
thousand and slowloris heads are closed, and the cell controller is answered meanwhile."""
import logging
import os
import resource
import socket
import time

import httpx
import pytest

from running import FAST_PASS, RunningService, wait_for
from service.connections import ACCEPT_BACKLOG

FILE_LIMIT = 1024
IDLE_CONNECTIONS = 1100
HEADER_TIMEOUT_S = 3.0


@pytest.fixture(scope="module")
def crowded(tmp_path_factory):
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < IDLE_CONNECTIONS + 200:
        pytest.skip(f"this process may open {hard} files: too few to crowd the service")
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard if hard != resource.RLIM_INFINITY
                                                 else max(soft, 8192), hard))
    running = RunningService(tmp_path_factory.mktemp("crowded") / "data",
                             env={**FAST_PASS, "FLYSCAN_HEADER_TIMEOUT_S": str(HEADER_TIMEOUT_S)},
                             file_limit=FILE_LIMIT)
    yield running
    running.stop()


def _open_idle(port: int, n: int) -> list[socket.socket]:
    sockets = []
    for _ in range(n):
        s = socket.socket()
        s.setblocking(False)
        s.connect_ex(("127.0.0.1", port))
        sockets.append(s)
    return sockets


def _closed_by_peer(s: socket.socket) -> bool:
    try:
        return s.recv(1024) == b""
    except BlockingIOError:
        return False
    except OSError:  # reset
        return True


def _service_files(service) -> int:
    return len(os.listdir(f"/proc/{service.process.pid}/fd"))


def test_idle_connections_by_the_thousand_stop_nothing(crowded):
    log_before = crowded.log.stat().st_size
    files_before = _service_files(crowded)
    idle = _open_idle(crowded.port, IDLE_CONNECTIONS)
    try:
        time.sleep(0.5)  # all of them accepted, or waiting in the backlog
        t0 = time.monotonic()
        health = httpx.get(f"{crowded.url}/health", timeout=10.0)
        health_s = time.monotonic() - t0
        t0 = time.monotonic()
        arm = httpx.post(f"{crowded.url}/scans", json={}, timeout=10.0)
        arm_s = time.monotonic() - t0
        assert health.status_code == 200 and health_s < 2.0, (health.status_code, health_s)
        assert arm.status_code == 202 and arm_s < 2.0, (arm.status_code, arm_s)
        scan_id = arm.json()["scan_id"]
        done = wait_for(lambda: httpx.get(f"{crowded.url}/scans/{scan_id}").json()["state"]
                        in ("done", "failed") and True, timeout=30)
        assert done
        # The idle sockets the service took are closed once their head is late: its
        # descriptors come back to what it held before the crowd. Counted on the service's
        # side: a client socket the kernel finished while the accept queue was full reads
        # ESTABLISHED to the client but is not the service's until a retransmitted SYN-ACK
        # finds room, so how many the client sees closed within a deadline is the kernel's
        # timing, not the service's doing.
        settled = wait_for(lambda: _service_files(crowded) <= files_before + ACCEPT_BACKLOG
                           or None, timeout=HEADER_TIMEOUT_S + 10.0, poll=0.2)
        assert settled
        assert sum(_closed_by_peer(s) for s in idle) >= ACCEPT_BACKLOG
    finally:
        for s in idle:
            s.close()
    scans = httpx.get(f"{crowded.url}/scans").json()["scans"]
    assert [s["scan_id"] for s in scans if s["state"] != "done"] == []  # no orphan arm
    assert httpx.get(f"{crowded.url}/scans/{scan_id}").json()["state"] == "done"
    assert crowded.log.stat().st_size - log_before < 1 << 20


def test_a_head_dribbled_a_byte_at_a_time_is_closed(crowded):
    s = socket.create_connection(("127.0.0.1", crowded.port))
    s.settimeout(0.05)
    started = time.monotonic()
    s.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n")
    closed_after = None
    try:
        while time.monotonic() - started < HEADER_TIMEOUT_S + 5.0:
            try:
                s.sendall(b"X")
                if s.recv(1024) == b"":
                    closed_after = time.monotonic() - started
                    break
            except socket.timeout:
                pass
            except OSError:
                closed_after = time.monotonic() - started
                break
            time.sleep(0.5)
    finally:
        s.close()
    assert closed_after is not None and closed_after < HEADER_TIMEOUT_S + 1.5
    # a client that sends its request in time is answered
    assert httpx.get(f"{crowded.url}/health").status_code == 200


def test_the_file_limit_is_raised_and_the_connections_bounded_below_it():
    from service.connections import connection_bound, raise_file_limit

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(512, hard), hard))
        now_soft, now_hard = raise_file_limit()
        assert now_hard == hard and (now_soft == hard or hard == resource.RLIM_INFINITY)
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    assert connection_bound(None, 1024, open_now=150) == 1024 - 150 - 128 - 128
    assert connection_bound(None, 1 << 20, open_now=150) == 4096
    assert connection_bound(100, 1024) == 100


def test_a_flood_of_accept_errors_is_logged_once_per_interval():
    from service.connections import OncePerInterval

    clock = [100.0]  # the flood within one interval however slow the machine

    records = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append(record.getMessage())

    logger = logging.getLogger("test.crowding")
    logger.propagate = False
    logger.addHandler(Keep())
    logger.addFilter(OncePerInterval(["Too many open files"], interval_s=0.2,
                                     clock=lambda: clock[0]))
    for _ in range(10_000):
        logger.error("socket.accept() out of system resource: [Errno 24] Too many open files")
    logger.error("something else")
    clock[0] += 0.25
    logger.error("socket.accept() out of system resource: [Errno 24] Too many open files")
    assert len(records) == 3 and records[1] == "something else"
    assert "9999 more since the last such line" in records[2]
