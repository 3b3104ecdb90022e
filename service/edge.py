"""The service's edge: what every request meets before FastAPI reads a byte of its body.

A pure ASGI middleware (:class:`EdgeGuard`) in front of the routes. It sees a request's
headers first, so it can refuse cheaply what must never cost the service work:

- a protected route without the bearer token: 401 before the body is read (FastAPI solves a
  route's dependencies only after it has read and parsed the body: a token dependency alone
  let a 200 MB body in before its 401);
- a body larger than the route's limit: 413, from ``Content-Length`` at once, and while the
  body streams (chunked uploads have no length) as soon as the count passes the limit;
- more bodies at once than ``max_concurrent_bodies``: 503 with ``Retry-After`` (each body
  being read holds memory or a temporary file).

Which routes are protected: every one that changes something (any method but GET, HEAD and
OPTIONS) when a token is set, and the reads too with ``protect_reads``, but for the few that
tell nothing of the cell (``OPEN_PATHS``: health, the status page's shell, the API's docs).
"""
from __future__ import annotations

import json
import re
import secrets

from service.settings import Settings

__all__ = ["EdgeGuard", "BodyTooLarge", "OPEN_PATHS", "body_limit"]

#: Paths anyone may read whatever ``protect_reads`` says: they tell nothing of the cell.
OPEN_PATHS = re.compile(r"^/(health|docs|docs/oauth2-redirect|redoc|openapi\.json|"
                        r"static/[^/]+|static-offline-docs/[^/]+)?$")
#: Methods that only read.
READS = frozenset({"GET", "HEAD", "OPTIONS"})
#: Routes whose bodies are meshes (``max_part_bytes``), not JSON requests.
PART_UPLOAD = re.compile(r"^/parts/[^/]+$")
#: Seconds a client refused for lack of a free body slot is told to wait.
RETRY_AFTER_S = 1


class BodyTooLarge(Exception):
    """Raised from ``receive`` once a body passes its limit (the 413 has been sent)."""


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
        ``max_concurrent_bodies``; read at each request (tests change them).
    """

    def __init__(self, app, settings: Settings):
        self.app = app
        self.settings = settings
        self.bodies_in_flight = 0  # one event loop: no lock needed

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
        if self._protected(method, path) and not self._authorised(headers):
            await _problem(send, 401, "a valid bearer token is required",
                           {"www-authenticate": "Bearer", **unread})
            return
        limit = body_limit(settings, method, path)
        if declared.isdigit() and int(declared) > limit:
            await _problem(send, 413, _too_large(limit), unread)
            return
        if not has_body:
            await self.app(scope, receive, send)
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
        """Run the app, counting its body's bytes as they arrive; past ``limit`` answer 413
        and drop whatever the app then tries to send."""
        received = 0
        refused = False
        started = False

        async def counting_receive():
            nonlocal received, refused
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
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


def _too_large(limit: int) -> str:
    return f"the request body is larger than {limit} bytes ({limit / 2**20:.4g} MiB)"


async def _problem(send, status: int, detail: str, headers: dict | None = None) -> None:
    """Answer ``{"detail": ...}`` (the API's ``Problem``) with ``status``."""
    body = json.dumps({"detail": detail}).encode()
    raw = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
           *((k.encode(), v.encode()) for k, v in (headers or {}).items())]
    await send({"type": "http.response.start", "status": status, "headers": raw})
    await send({"type": "http.response.body", "body": body})
