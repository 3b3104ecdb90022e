"""The service's edge: what every request meets before FastAPI reads a byte of its body.

A pure ASGI middleware (:class:`EdgeGuard`) in front of the routes. It sees a request's
headers first, so it can refuse cheaply what must never cost the service work:

- a protected route without the bearer token: 401 before the body is read (FastAPI solves a
  route's dependencies only after it has read and parsed the body: a token dependency alone
  let a 200 MB body in before its 401);
- a body larger than the route's limit: 413, from ``Content-Length`` at once, and while the
  body streams (chunked uploads have no length) as soon as the count passes the limit;
- more bodies at once than ``max_concurrent_bodies``: 503 with ``Retry-After`` (each body
  being read holds memory or a temporary file); a body declared small (``SMALL_BODY_BYTES``,
  an arm request's few bytes) takes no slot, so uploads dribbled slowly cannot keep a cell
  controller from arming; a body whose next piece takes longer than ``body_idle_s`` is
  answered 408 and its slot freed;
- a body arriving while a scan is armed or its pass runs: read no faster than
  ``body_rate_in_pass_mb_s`` (each piece then waits its turn in an ``asyncio`` sleep, and TCP
  holds the sender back). What took frames on a slow machine was the reading itself:
  uploads streamed to their 64 MiB limit, a dozen in a pass, competing with the camera;
- reads faster than ``read_interval_s`` on one connection, or than ``max_reads_per_s`` all
  together: paced, i.e. the answer waits its turn (an ``asyncio`` sleep, which costs the
  camera nothing), and beyond ``MAX_READ_WAIT_S`` of waiting, 503 with ``Retry-After``.
  What took the camera's frames under clients looping on the reads was the web framework's
  own Python per request (about half a core at 900 answers a second, with the pictures
  cached): a client that waits for its answers (every browser and every polling loop) is
  slowed to the pace, and its work with it.

- a write from another site: 403 when its ``Origin`` (or, without one, its ``Referer``) is
  neither the service's own (the ``Host`` it was asked at) nor one of ``trusted_origins``,
  with or without a token; and 415 for a write whose body a browser's form could have sent
  (``FORM_TYPES``), or, but for a part's upload, that says it is not JSON. A page the
  operator's browser opens can post a form to the cell PC's service without asking anyone
  (no CORS preflight for a form): this is what stops it arming a scan or rolling the
  calibration back. A request without ``Content-Type`` (a script's) is read as the route's
  own kind: a browser's form always says its type.

Which routes are protected: every one that changes something (any method but GET, HEAD and
OPTIONS) when a token is set, and the reads too with ``protect_reads``, but for the few that
tell nothing of the cell (``OPEN_PATHS``: health, the status page's shell, the API's docs).
"""
from __future__ import annotations

import asyncio
import json
import re
import secrets
from urllib.parse import urlsplit

from service.settings import Settings

__all__ = ["EdgeGuard", "BodyTooLarge", "OPEN_PATHS", "FORM_TYPES", "body_limit", "foreign_write",
           "read_turn"]

#: Paths anyone may read whatever ``protect_reads`` says: they tell nothing of the cell.
OPEN_PATHS = re.compile(r"^/(health|docs|docs/oauth2-redirect|redoc|openapi\.json|"
                        r"static/[^/]+|static-offline-docs/[^/]+)?$")
#: Methods that only read.
READS = frozenset({"GET", "HEAD", "OPTIONS"})
#: Routes whose bodies are meshes (``max_part_bytes``), not JSON requests.
PART_UPLOAD = re.compile(r"^/parts/.+$")  # a name with a slash is 404, not 415
#: Seconds a client refused for lack of a free body slot is told to wait.
RETRY_AFTER_S = 1
#: Bodies declared this small (bytes) take no slot of ``max_concurrent_bodies``.
SMALL_BODY_BYTES = 64 << 10
#: What a browser's form (or any cross-site request that asks no one first) may send.
FORM_TYPES = frozenset({"application/x-www-form-urlencoded", "multipart/form-data",
                        "text/plain"})
#: Paths never paced: liveness.
UNPACED_PATHS = re.compile(r"^/health$")
#: A read that would wait longer than this for its turn (s) is refused with 503.
MAX_READ_WAIT_S = 2.0
#: Connections whose pace is remembered; the oldest are forgotten beyond.
PACED_CONNECTIONS = 4096


class BodyTooLarge(Exception):
    """Raised from ``receive`` once a body passes its limit or stalls (the 413 or 408 has
    been sent)."""


def body_limit(settings: Settings, method: str, path: str) -> int:
    """The most bytes a request's body may have on this route."""
    if method == "PUT" and PART_UPLOAD.match(path):
        return settings.max_part_bytes
    return settings.max_body_bytes


class EdgeGuard:
    """ASGI middleware: authentication, body limits and body concurrency, before the app.

    Parameters
    ----------
    app : ASGI application
    settings : Settings
        ``token``, ``protect_reads``, ``max_body_bytes``, ``max_part_bytes``,
        ``max_concurrent_bodies``, ``body_idle_s``, ``body_rate_in_pass_mb_s``,
        ``read_interval_s``, ``max_reads_per_s``; read at each request (tests change them).
    acquiring : callable() -> bool, optional
        Whether a scan is armed or its pass runs (``Service.acquiring``): bodies are then read
        at ``body_rate_in_pass_mb_s``. None: never.
    """

    def __init__(self, app, settings: Settings, acquiring=None):
        self.app = app
        self.settings = settings
        self.acquiring = acquiring
        self.bodies_in_flight = 0  # one event loop: no lock needed
        self._next_on_connection: dict = {}  # (host, port) -> when its next read may go
        self._next_read = 0.0  # when the next read may go, all connections together
        self.reads_paced = self.reads_refused = 0

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        settings = self.settings
        method, path = scope["method"], scope["path"]
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        declared = headers.get("content-length", "")
        has_body = (declared.isdigit() and int(declared) > 0) or "transfer-encoding" in headers
        # A body refused unread: the connection is closed after the answer, so that the
        # server does not go on receiving (and discarding) what the client still sends.
        unread = {"connection": "close"} if has_body else {}
        if method not in READS:
            refused = foreign_write(headers, method, path, settings.trusted_origins)
            if refused is not None:
                await _problem(send, *refused, unread)
                return
        if self._protected(method, path) and not self._authorised(headers):
            await _problem(send, 401, "a valid bearer token is required",
                           {"www-authenticate": "Bearer", **unread})
            return
        if method in READS and not UNPACED_PATHS.match(path) and not (
                settings.token is not None and self._authorised(headers)):
            if not await self._paced(scope.get("client")):
                await _problem(send, 503, "too many reads: try again",
                               {"retry-after": str(RETRY_AFTER_S)})
                return
        limit = body_limit(settings, method, path)
        if declared.isdigit() and int(declared) > limit:
            await _problem(send, 413, _too_large(limit), unread)
            return
        if not has_body:
            await self.app(scope, receive, send)
            return
        if declared.isdigit() and int(declared) <= SMALL_BODY_BYTES:
            await self._limited(scope, receive, send, limit)
            return
        if self.bodies_in_flight >= settings.max_concurrent_bodies:
            await _problem(send, 503, f"{self.bodies_in_flight} request bodies are being read: "
                                      f"try again", {"retry-after": str(RETRY_AFTER_S), **unread})
            return
        self.bodies_in_flight += 1
        try:
            await self._limited(scope, receive, send, limit)
        finally:
            self.bodies_in_flight -= 1

    async def _paced(self, client) -> bool:
        """Wait for this read's turn (`read_turn`); False, without waiting for the shared
        turn, when it is over ``MAX_READ_WAIT_S`` away."""
        settings = self.settings
        now = asyncio.get_running_loop().time()
        key = tuple(client) if client and settings.read_interval_s > 0 else None
        previous = self._next_on_connection.pop(key, None) if key else None
        own, shared = read_turn(now, previous, self._next_read, settings.read_interval_s,
                                settings.max_reads_per_s)
        if key:
            self._next_on_connection[key] = own + settings.read_interval_s
            if len(self._next_on_connection) > PACED_CONNECTIONS:
                del self._next_on_connection[next(iter(self._next_on_connection))]
        if shared is None:
            self.reads_refused += 1
            await asyncio.sleep(own - now)
            return False
        self._next_read = shared + 1.0 / settings.max_reads_per_s
        if shared > now:
            self.reads_paced += 1
            await asyncio.sleep(shared - now)
        return True

    def _protected(self, method: str, path: str) -> bool:
        if self.settings.token is None:
            return False
        if method not in READS:
            return True
        return self.settings.protect_reads and not OPEN_PATHS.match(path)

    def _authorised(self, headers: dict) -> bool:
        scheme, _, given = headers.get("authorization", "").partition(" ")
        expected = self.settings.token.get_secret_value()
        return scheme.lower() == "bearer" and secrets.compare_digest(
            given.strip().encode(), expected.encode())

    async def _limited(self, scope, receive, send, limit: int) -> None:
        """Run the app, counting its body's bytes as they arrive; past ``limit`` answer 413,
        a piece that takes over ``body_idle_s`` 408, and drop whatever the app then tries to
        send."""
        idle_s = self.settings.body_idle_s
        received = 0
        refused = False
        started = False
        complete = False

        async def counting_receive():
            nonlocal received, refused, complete
            if complete:
                return await receive()  # the body is in: what follows is the disconnect
            try:
                message = await asyncio.wait_for(receive(), idle_s)
            except TimeoutError:
                if not started:
                    refused = True
                    await _problem(send, 408, f"no part of the request body came for "
                                              f"{idle_s:g} s", {"connection": "close"})
                raise BodyTooLarge("the request body stalled") from None
            complete = message["type"] != "http.request" or not message.get("more_body")
            if message["type"] == "http.request":
                piece = len(message.get("body", b""))
                received += piece
                if piece and self.acquiring is not None and self.acquiring():
                    await asyncio.sleep(piece / (self.settings.body_rate_in_pass_mb_s * 1e6))
                if received > limit:
                    if not started:
                        refused = True
                        await _problem(send, 413, _too_large(limit), {"connection": "close"})
                    raise BodyTooLarge(_too_large(limit))
            return message

        async def guarded_send(message):
            nonlocal started
            if refused:
                return  # the 413 went out: the app's own answer to the failed read is dropped
            started = True
            await send(message)

        try:
            await self.app(scope, counting_receive, guarded_send)
        except BodyTooLarge:
            if not refused:
                raise


def foreign_write(headers: dict, method: str, path: str, trusted=()) -> tuple[int, str] | None:
    """(status, reason) when a write must be refused as from another site: 403 for an
    ``Origin`` (or, without one, a ``Referer``) that is neither the ``Host`` asked nor in
    `trusted`; 415 for a body type a form could send (``FORM_TYPES``), or a type other
    than JSON but for a part's upload. None when it may go on. `headers` are lower-cased."""
    for name in ("origin", "referer"):
        value = headers.get(name)
        if value is None:
            continue
        parts = urlsplit(value) if value != "null" else None
        origin = "null" if parts is None else f"{parts.scheme}://{parts.netloc}".lower()
        own = parts is not None and parts.netloc.lower() == headers.get("host", "").lower()
        if not (own or origin in {t.rstrip("/").lower() for t in trusted}):
            return 403, (f"a write from another site ({name} {origin}) is refused: only this "
                         f"service's own pages and trusted_origins may send writes")
        break
    media = headers.get("content-type", "").partition(";")[0].strip().lower()
    if not media:
        return None
    upload = method == "PUT" and PART_UPLOAD.match(path)
    if media in FORM_TYPES or not (upload or media == "application/json"
                                   or media.endswith("+json")):
        kind = "the mesh as application/octet-stream" if upload else "application/json"
        return 415, f"a body of type {media} is refused here: send {kind}"
    return None


def read_turn(now: float, connection_next: float | None, shared_next: float,
              interval_s: float, max_per_s: float) -> tuple[float, float | None]:
    """When a read may be answered (s, on the event loop's clock).

    Parameters
    ----------
    now : float
    connection_next : float or None
        When this connection's next read may go (its previous one's turn plus
        `interval_s`); None for a connection not paced or not seen yet.
    shared_next : float
        When the next read of any connection may go.
    interval_s, max_per_s : float
        ``read_interval_s`` and ``max_reads_per_s``.

    Returns
    -------
    own : float
        The connection's turn, ``max(now, connection_next)``: its pace holds even when the
        read is refused, so a client looping on refusals is slowed as well.
    shared : float or None
        The read's turn among all reads, ``max(own, shared_next)``; None when that is more
        than ``MAX_READ_WAIT_S`` away (refused).
    """
    own = now if connection_next is None else max(now, connection_next)
    shared = max(own, shared_next)
    return own, (None if shared - now > MAX_READ_WAIT_S else shared)


def _too_large(limit: int) -> str:
    return f"the request body is larger than {limit} bytes ({limit / 2**20:.4g} MiB)"


async def _problem(send, status: int, detail: str, headers: dict | None = None) -> None:
    """Answer ``{"detail": ...}`` (the API's ``Problem``) with ``status``."""
    body = json.dumps({"detail": detail}).encode()
    raw = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
           *((k.encode(), v.encode()) for k, v in (headers or {}).items())]
    await send({"type": "http.response.start", "status": status, "headers": raw})
    await send({"type": "http.response.body", "body": body})
