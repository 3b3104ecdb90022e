"""What one TCP connection may hold of the service: its file descriptor, and the event loop's
attention while it sends nothing.

uvicorn closes a connection that stays idle after an answer (``timeout_keep_alive``), but not
one that never sends a whole request head: a connection opened and left silent, or one
dribbling its headers a byte every few seconds (slowloris), is kept for ever. Enough of them
exhaust the process's file descriptors, and then the accept loop fails on every new connection
(``Too many open files``), ``/health`` and ``POST /scans`` included. Three bounds:

- **a head deadline** (`GuardedH11Protocol`): a connection that has not sent a whole request
  head within ``header_timeout_s`` of connecting, or of its previous answer, is closed;
- **a bound on connections**: past ``max_connections``, the oldest connection still waiting for
  a request head is closed to make room (a keep-alive client reconnects; an idle socket is
  gone); when none waits, the new connection is answered 503 and closed;
- **the file limit** raised to the hard limit at start (`raise_file_limit`), and
  ``max_connections`` kept below it with room for what is open at start, for a wake-up's
  worth of accepted connections (``ACCEPT_BACKLOG``, the listening socket's backlog) and for a
  scan's files (`connection_bound`), so that neither the accept loop nor the store runs out
  of descriptors.

A failing ``accept`` is logged once per ``LOG_INTERVAL_S`` with the count since
(`OncePerInterval`), never thousands of times a second.
"""
from __future__ import annotations

import logging
import os
import resource
import time
from collections import OrderedDict

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

__all__ = ["ACCEPT_BACKLOG", "GuardedH11Protocol", "OncePerInterval", "connection_bound",
           "guarded_protocol", "open_files", "quiet_crowding", "raise_file_limit"]

log = logging.getLogger("flyscan.connections")

#: Descriptors kept, beyond those open at start (the camera, the robot, ZeroMQ, the workers'
#: pipes), for the work of a scan: the store's files, a recording's, an upload's.
RESERVED_FILES = 128
#: Connections the accept loop takes in one wake-up (the listening socket's backlog, which
#: asyncio also accepts at once): their descriptors are open before any can be closed.
ACCEPT_BACKLOG = 128
#: The most connections served at once whatever the file limit: the cell's controller, a few
#: browsers and subscribers need tens.
MAX_CONNECTIONS = 4096
#: Least seconds between two log lines about refused connections.
LOG_INTERVAL_S = 10.0


def raise_file_limit() -> tuple[int, int]:
    """Raise this process's soft limit on open files to its hard limit (``RLIMIT_NOFILE``);
    the (soft, hard) limits in force after. A limit that cannot be raised is left as it is."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or soft < hard:
        target = hard if hard != resource.RLIM_INFINITY else max(soft, 1 << 20)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        except (ValueError, OSError) as exc:
            log.warning("the open-file limit stays at %d: %s", soft, exc)
    return resource.getrlimit(resource.RLIMIT_NOFILE)


_BUSY = b'{"detail": "every connection is busy with a request: try again"}'
#: The answer to a connection beyond ``max_connections`` when none can make room.
BUSY_ANSWER = (b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: application/json\r\n"
               b"retry-after: 1\r\nconnection: close\r\ncontent-length: "
               + str(len(_BUSY)).encode() + b"\r\n\r\n" + _BUSY)
#: What the accept loop and the guard log when connections crowd in: once per interval.
CROWDED_MESSAGES = ("Too many open files", "out of system resource", "every one busy")


def quiet_crowding(interval_s: float = LOG_INTERVAL_S) -> None:
    """Log the lines of ``CROWDED_MESSAGES`` (asyncio's failing ``accept``, uvicorn's, this
    module's) once per `interval_s`, with a count of those held back: a flood of
    connections must not fill the disk with its log."""
    for name in ("asyncio", "uvicorn.error", log.name):
        logger = logging.getLogger(name)
        if not any(isinstance(f, OncePerInterval) for f in logger.filters):
            logger.addFilter(OncePerInterval(CROWDED_MESSAGES, interval_s))


def connection_bound(setting: int | None, soft_file_limit: int, open_now: int = 0) -> int:
    """The connections served at once: `setting` when given, else the soft file limit less
    the descriptors open now, ``ACCEPT_BACKLOG`` and ``RESERVED_FILES``, at most
    ``MAX_CONNECTIONS``; never fewer than 16."""
    if setting is not None:
        return int(setting)
    room = int(soft_file_limit) - int(open_now) - ACCEPT_BACKLOG - RESERVED_FILES
    return max(16, min(MAX_CONNECTIONS, room))


def open_files() -> int:
    """Descriptors this process has open (0 where ``/proc`` does not say)."""
    try:
        return len(os.listdir("/proc/self/fd"))
    except OSError:
        return 0


class OncePerInterval(logging.Filter):
    """Let a record whose message contains one of `needles` through at most once per
    `interval_s`, saying how many were held back since; other records pass. `clock` gives
    the time, s (``time.monotonic``)."""

    def __init__(self, needles, interval_s: float = LOG_INTERVAL_S, clock=time.monotonic):
        super().__init__()
        self.needles = tuple(needles)
        self.interval_s = float(interval_s)
        self.clock = clock
        self.last = -float("inf")
        self.held = 0

    def filter(self, record: logging.LogRecord) -> bool:
        text = record.getMessage()
        if record.exc_info and record.exc_info[1] is not None:
            text += f" {record.exc_info[1]}"
        if not any(n in text for n in self.needles):
            return True
        now = self.clock()
        if now - self.last < self.interval_s:
            self.held += 1
            return False
        if self.held:
            record.msg = f"{record.getMessage()} ({self.held} more since the last such line)"
            record.args = ()
        self.last, self.held = now, 0
        return True


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with a request-head deadline and a bound on connections (module
    notes). `guarded_protocol` gives a subclass with the bounds set."""

    header_timeout_s: float = 10.0
    max_connections: int = MAX_CONNECTIONS
    #: The connections waiting for a request head, longest waiting first (one event loop:
    #: no lock). Kept in order so that making room costs the same with 10 or 10 000 open.
    waiting: OrderedDict = OrderedDict()

    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        self._head_deadline = None
        if len(self.connections) > self.max_connections and not self._make_room():
            log.warning("connections: %d open, every one busy with a request: new ones are "
                        "answered 503", len(self.connections))
            self.transport.write(BUSY_ANSWER)  # before its request: no h11 cycle to answer in
            self.transport.close()
            return
        self._await_head()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self.conn.their_state is not h11.IDLE:  # a request head came: busy, not waiting
            self.waiting.pop(self, None)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._await_head()

    def connection_lost(self, exc) -> None:
        if self._head_deadline is not None:
            self._head_deadline.cancel()
            self._head_deadline = None
        self.waiting.pop(self, None)
        super().connection_lost(exc)

    def _waiting(self) -> bool:
        """Between requests: no head received since the connection opened or its last
        answer (h11's peer state is IDLE then)."""
        return self.conn.their_state is h11.IDLE and not self.transport.is_closing()

    def _await_head(self) -> None:
        if self._head_deadline is not None:
            self._head_deadline.cancel()
        if not self.transport.is_closing():
            self.waiting.pop(self, None)
            self.waiting[self] = None  # the newest to wait
            self._head_deadline = self.loop.call_later(self.header_timeout_s, self._head_late)

    def _head_late(self) -> None:
        self._head_deadline = None
        if self._waiting():
            self.transport.close()

    def _make_room(self) -> bool:
        """Close the connection that has waited longest for a request head (this one is not
        listed yet); False when every other connection is busy with a request."""
        while self.waiting:
            oldest, _ = self.waiting.popitem(last=False)
            if oldest._waiting():
                oldest.transport.close()
                return True
        return False


def guarded_protocol(header_timeout_s: float, max_connections: int) -> type[GuardedH11Protocol]:
    """A `GuardedH11Protocol` subclass with these bounds (uvicorn's ``http=`` takes a class)."""
    return type("GuardedH11Protocol", (GuardedH11Protocol,),
                {"header_timeout_s": float(header_timeout_s),
                 "max_connections": int(max_connections), "waiting": OrderedDict()})
