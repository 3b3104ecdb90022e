"""What every router of the REST API shares: the service dependency, the token check and the
statuses the edge and the disk may answer (``service.api``, ``service.api_calibration``)."""
from __future__ import annotations

import secrets
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.daemon import Service
from service.models import Problem
from service.problems import disk_reason


async def get_service(request: Request) -> Service:
    # async: FastAPI runs a plain def dependency in its thread pool, a hop per request
    return request.app.state.service


ServiceDep = Annotated[Service, Depends(get_service)]
_bearer = HTTPBearer(auto_error=False)


def require_token(service: ServiceDep,
                  credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    """Mutating endpoints need the bearer token when one is configured."""
    token = service.settings.token
    if token is None:
        return
    given = credentials.credentials if credentials is not None else ""
    if not secrets.compare_digest(given.encode(), token.get_secret_value().encode()):
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "a valid bearer token is required",
                            headers={"WWW-Authenticate": "Bearer"})


Auth = [Depends(require_token)]
UNAUTHORIZED = {401: {"model": Problem, "description": "token missing or wrong"}}
NOT_FOUND = {404: {"model": Problem, "description": "no such scan or part"}}
#: What the edge (``service.edge``) may answer on any route: 401 on a protected one (every
#: change with a token set; the reads too with ``protect_reads``), 413 for a body past the
#: route's limit, 503 when too many bodies are being read at once or a read's turn is too far
#: off (``read_interval_s``, ``max_reads_per_s``).
EDGE = {401: {"model": Problem, "description": "token missing or wrong (reads: with "
                                              "protect_reads)"},
        403: {"model": Problem, "description": "a write from another site: its Origin (or "
                                              "Referer) is neither this service's nor one of "
                                              "trusted_origins"},
        408: {"model": Problem, "description": "the request body stalled (no part of it for "
                                              "body_idle_s)"},
        415: {"model": Problem, "description": "a write whose body a browser's form could "
                                              "send, or not JSON (a part's upload: a mesh)"},
        413: {"model": Problem, "description": "the request body is larger than the route's "
                                              "limit (max_body_bytes, max_part_bytes)"},
        503: {"model": Problem, "description": "the service is busy (too many request "
                                              "bodies at once, or reads faster than it paces "
                                              "them: retry), or a device is not ready"}}
NO_ROOM = {507: {"model": Problem, "description": "the disk refused (full or read-only): the "
                                                 "reason, relative to the data folder"}}


#: FastAPI's detail when ``json.loads`` raised on a body (made a 422 below).
BODY_NOT_PARSED = "There was an error parsing the body"


def disk_error(service: Service, exc: OSError, what: str) -> HTTPException:
    return HTTPException(507, f"{what}: {disk_reason(exc, service.settings.data)}")


