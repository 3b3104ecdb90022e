"""The REST API of calibration sessions and of the calibration history.

- ``POST /calibration/sessions`` a session and its plan (``PlanRequest``); ``GET
  /calibration/sessions/{id}`` its state; ``POST .../steps/{index}`` capture a plan's pose
  (the robot there: the cell controller took it, or the simulated robot is sent);
  ``POST .../pass`` record the sphere's pass; ``POST .../fit`` fit it into a new version.
- ``GET /calibration/history``, ``GET /calibration/history/{version}`` (with its
  calibration and report), ``GET /calibration/history/{version}/residuals.png``;
  ``POST /calibration/history/{version}/activate`` and ``POST /calibration/rollback``: the only
  ways besides ``PUT /calibration`` that change the service's calibration, refused (409)
  while a pass is acquired or processed.
"""
from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Path as PathParam, Response
from fastapi.responses import FileResponse
from fastapi.concurrency import run_in_threadpool

from service.api_common import Auth, EDGE, NO_ROOM, ServiceDep, UNAUTHORIZED, disk_error
from service.calhistory import NoPreviousVersion, NoSuchVersion, activate, rollback
from service.calsessions import NoSuchSession, SessionStateError
from service.engine import EngineBusy
from service.models import (CalibrationHistoryList, CalibrationSessionInfo,
                            CalibrationVersion, CalibrationVersionDetail, PlanRequest, Problem,
                            StepCaptured)

__all__ = ["calibrations"]

calibrations = APIRouter(tags=["calibration"], responses=EDGE)

SessionId = Annotated[str, PathParam(max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")]
Version = Annotated[int, PathParam(ge=1, le=1_000_000)]


def _problem(status: int, description: str) -> dict:
    return {status: {"model": Problem, "description": description}}


SESSION_ERRORS = {**_problem(404, "no such calibration session"),
                  **_problem(409, "not now: the session's state, or a scan in progress"),
                  **_problem(422, "not a valid request"), **UNAUTHORIZED, **NO_ROOM}


def _session(service, session_id: str):
    try:
        return service.calibration_sessions.get(session_id)
    except NoSuchSession as exc:
        raise HTTPException(404, str(exc.args[0])) from None


@calibrations.post("/calibration/sessions", status_code=201, response_model=CalibrationSessionInfo,
                   dependencies=Auth, responses={**_problem(422, "a plan that cannot be made "
                                                                 "(a real cell's geometry "
                                                                 "missing)"),
                                                 **UNAUTHORIZED, **NO_ROOM})
def create_session(body: PlanRequest, service: ServiceDep) -> dict:
    try:
        return service.calibration_sessions.create(body.model_dump())
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    except OSError as exc:
        raise disk_error(service, exc, "the session could not be written") from None


@calibrations.get("/calibration/sessions/{session_id}", response_model=CalibrationSessionInfo,
                  responses=_problem(404, "no such calibration session"))
def get_session(session_id: SessionId, service: ServiceDep) -> dict:
    return _session(service, session_id).info(with_plan=True)


@calibrations.post("/calibration/sessions/{session_id}/steps/{index}",
                   response_model=StepCaptured, dependencies=Auth, responses=SESSION_ERRORS)
async def capture_step(session_id: SessionId, index: Annotated[int, PathParam(ge=0, le=100_000)],
                       service: ServiceDep) -> dict:
    _session(service, session_id)
    try:
        return await run_in_threadpool(service.calibration_sessions.capture, session_id, index)
    except IndexError as exc:
        raise HTTPException(422, str(exc)) from None
    except (SessionStateError, EngineBusy) as exc:
        raise HTTPException(409, str(exc)) from None
    except OSError as exc:
        raise disk_error(service, exc, "the step could not be written") from None


@calibrations.post("/calibration/sessions/{session_id}/pass", status_code=202,
                   response_model=CalibrationSessionInfo, dependencies=Auth,
                   responses=SESSION_ERRORS)
def record_pass(session_id: SessionId, service: ServiceDep) -> dict:
    _session(service, session_id)
    try:
        return service.calibration_sessions.record_pass(session_id)
    except (SessionStateError, EngineBusy) as exc:
        raise HTTPException(409, str(exc)) from None
    except (KeyError, ValueError) as exc:
        raise HTTPException(422, str(exc)) from None


@calibrations.post("/calibration/sessions/{session_id}/fit", status_code=202,
                   response_model=CalibrationSessionInfo, dependencies=Auth,
                   responses=SESSION_ERRORS)
def fit_session(session_id: SessionId, service: ServiceDep) -> dict:
    _session(service, session_id)
    try:
        return service.calibration_sessions.fit(session_id)
    except SessionStateError as exc:
        raise HTTPException(409, str(exc)) from None


# -- the history -------------------------------------------------------------------------------

def _detail(service, entry: dict) -> dict:
    history = service.calibration_history
    return {**entry, "calibration": history.calibration(entry["version"]).to_dict(),
            "report": history.report(entry["version"])}


@calibrations.get("/calibration/history", response_model=CalibrationHistoryList)
def list_history(service: ServiceDep) -> dict:
    history = service.calibration_history
    return {"versions": history.entries(), "active": history.active}


@calibrations.get("/calibration/history/{version}", response_model=CalibrationVersionDetail,
                  responses=_problem(404, "no such version"))
def get_version(version: Version, service: ServiceDep) -> dict:
    try:
        return _detail(service, service.calibration_history.entry(version))
    except NoSuchVersion as exc:
        raise HTTPException(404, str(exc.args[0])) from None


@calibrations.get("/calibration/history/{version}/residuals.png", response_class=Response,
                  responses={200: {"content": {"image/png": {}},
                                   "description": "residuals per view and per position"},
                             **_problem(404, "no such version, or one without a fit's report")})
def residuals_png(version: Version, service: ServiceDep) -> Response:
    try:
        path = service.calibration_history.residuals_path(version)
    except NoSuchVersion as exc:
        raise HTTPException(404, str(exc.args[0])) from None
    if not path.is_file():  # drawn once, when the session was fitted
        raise HTTPException(404, f"version {version} was not fitted here: it has no residuals")
    return FileResponse(path, media_type="image/png")


def _activation(service, change) -> dict:
    try:
        return change()
    except NoSuchVersion as exc:
        raise HTTPException(404, str(exc.args[0])) from None
    except NoPreviousVersion as exc:
        raise HTTPException(409, str(exc)) from None
    except EngineBusy as exc:
        raise HTTPException(409, str(exc)) from None
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    except OSError as exc:
        raise disk_error(service, exc, "the calibration could not be saved") from None


ACTIVATION_ERRORS = {**_problem(404, "no such version"),
                     **_problem(409, "a scan is in progress (a pass is never interrupted), or "
                                     "nothing to roll back to"),
                     **_problem(422, "the version does not fit this camera's images"),
                     **UNAUTHORIZED, **NO_ROOM}


@calibrations.post("/calibration/history/{version}/activate", response_model=CalibrationVersion,
                   dependencies=Auth, responses=ACTIVATION_ERRORS)
def activate_version(version: Version, service: ServiceDep) -> dict:
    return _activation(service, lambda: activate(service, version))


@calibrations.post("/calibration/rollback", response_model=CalibrationVersion,
                   dependencies=Auth, responses=ACTIVATION_ERRORS)
def rollback_version(service: ServiceDep) -> dict:
    return _activation(service, lambda: rollback(service))
