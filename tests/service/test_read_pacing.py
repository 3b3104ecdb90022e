"""Reads paced at the edge: a connection's reads answered at most every
``read_interval_s``, all reads at most ``max_reads_per_s``, a read whose turn is too far off
refused with 503; liveness and reads with the token not paced. The schedule as a function,
then counts of answers over real HTTP against ``flyscan serve --sim`` (an upper bound the pace
guarantees, not a speed)."""
import socket
import threading
import time

import httpx
import pytest

from running import TOKEN, wait_for
from service.edge import MAX_READ_WAIT_S, read_turn


def test_a_connection_waits_its_interval_and_every_read_the_shared_pace():
    # a new connection, nothing queued: now
    assert read_turn(10.0, None, 0.0, 0.1, 100.0) == (10.0, 10.0)
    # its next read 0.1 s after its last turn, whatever the shared pace
    assert read_turn(10.02, 10.1, 10.03, 0.1, 100.0) == (10.1, 10.1)
    # the shared pace beyond the connection's: wait for it
    assert read_turn(10.0, None, 10.5, 0.1, 100.0) == (10.0, 10.5)
    # a shared turn more than MAX_READ_WAIT_S away: refused, the connection's pace kept
    own, shared = read_turn(10.0, 10.05, 10.0 + MAX_READ_WAIT_S + 0.01, 0.1, 100.0)
    assert own == 10.05 and shared is None


def _loop(url, path, seconds, counts, key, headers=None):
    with httpx.Client(base_url=url, timeout=30, headers=headers) as client:
        client.get(path)  # connected before the clock starts
        end = time.monotonic() + seconds
        n = 0
        while time.monotonic() < end:
            n += client.get(path).status_code == 200
        counts[key] = n


@pytest.mark.parametrize("path", ["/status", "/frame.png"])
def test_a_looping_client_is_paced_and_another_connection_is_not_slowed_by_it(service, path):
    counts = {}
    loops = [threading.Thread(target=_loop, args=(service.url, path, 1.0, counts, k))
             for k in ("a", "b")]
    for t in loops:
        t.start()
    for t in loops:
        t.join()
    # at most one answer per read_interval_s (0.05 s) per connection, and one at the start ...
    assert counts["a"] <= 21 and counts["b"] <= 21, counts
    # ... and each connection gets its share
    assert counts["a"] >= 10 and counts["b"] >= 10, counts


def test_liveness_is_not_paced(service):
    counts = {}
    _loop(service.url, "/health", 1.0, counts, "health")
    assert counts["health"] > 60, counts  # three times what a paced connection gets


def test_reads_with_the_token_are_not_paced(guarded):
    counts = {}
    _loop(guarded.url, "/status", 1.0, counts, "trusted",
          headers={"Authorization": f"Bearer {TOKEN}"})
    assert counts["trusted"] > 60, counts


def _open_stream(url: str) -> socket.socket:
    """``GET /events`` held open (raw HTTP), once its first answer line has come."""
    host, port = url.removeprefix("http://").split(":")
    sock = socket.create_connection((host, int(port)), timeout=30)
    sock.sendall(f"GET /events HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())
    return sock


def test_event_streams_are_bounded(service):
    """``max_event_streams`` (16) status pages' streams at once; one more is 503 with
    Retry-After; a closed one frees its place."""
    streams = [_open_stream(service.url) for _ in range(16)]
    try:
        heads = [s.recv(4096) for s in streams]
        assert all(h.startswith(b"HTTP/1.1 200") for h in heads), heads
        refused = httpx.get(f"{service.url}/events", timeout=30)
        assert refused.status_code == 503 and refused.headers["retry-after"] == "5"
        assert "max_event_streams" in refused.json()["detail"]
        streams.pop().close()

        def accepted():
            with httpx.stream("GET", f"{service.url}/events", timeout=30) as r:
                return r.status_code == 200 or None
        assert wait_for(accepted, timeout=10)
    finally:
        for s in streams:
            s.close()


def test_bodies_are_read_at_the_pass_rate_only_while_a_scan_is_armed_or_running(monkeypatch):
    """Each piece of a body waits ``piece / rate`` while the service acquires, and not at all
    otherwise; the body reaches the app whole either way."""
    import asyncio

    import service.edge as edge
    from service.edge import EdgeGuard
    from service.settings import Settings

    waits = []

    async def recorded_sleep(seconds):
        waits.append(seconds)

    monkeypatch.setattr(edge.asyncio, "sleep", recorded_sleep)
    pieces = [b"x" * 1000, b"y" * 3000, b""]
    got = []

    async def app(scope, receive, send):
        while True:
            message = await receive()
            got.append(message.get("body", b""))
            if not message.get("more_body"):
                break
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"{}"})

    def run(acquiring):
        queue = [{"type": "http.request", "body": p, "more_body": i < len(pieces) - 1}
                 for i, p in enumerate(pieces)]

        async def receive():
            return queue.pop(0)

        async def send(message):
            pass

        guard = EdgeGuard(app, Settings(body_rate_in_pass_mb_s=2.0), acquiring=lambda: acquiring)
        scope = {"type": "http", "method": "POST", "path": "/scans", "headers": [
            (b"content-type", b"application/json"), (b"transfer-encoding", b"chunked")],
            "client": ("127.0.0.1", 5)}
        asyncio.run(guard(scope, receive, send))

    run(False)
    assert waits == [] and b"".join(got) == b"".join(pieces)
    got.clear()
    run(True)
    assert waits == [1000 / 2e6, 3000 / 2e6] and b"".join(got) == b"".join(pieces)
