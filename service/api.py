"""The REST API: one router per resource, the service injected, every response declared.

``create_app(settings)`` builds the FastAPI application; its lifespan starts and stops the
service. Tests build the app with a service of their own (``create_app(service=...)``).
In front of the routes, ``service.edge.EdgeGuard`` checks the token and the body's size
before FastAPI reads a byte of it. A disk that refuses (full, read-only) is a 507 with the
reason, its paths relative to the data folder (``service.problems``).
"""
from __future__ import annotations

import asyncio
import functools
import shutil
from contextlib import asynccontextmanager
from importlib.metadata import version as package_version
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, FastAPI, HTTPException, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, StreamingResponse
from fastapi_offline import FastAPIOffline
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import compile_path
from fastapi.exception_handlers import http_exception_handler

from scanner_core.geometry.calibration import Calibration, CalibrationError
from scanner_core.inspection import InspectionParams
from service.daemon import Service
from service.engine import EngineBusy, EngineFault
from service.models import (CalibrationModel, Health, PartInfo, PartList, Problem, ScanAccepted, ScanInfo, ScanList,
                            ScanRequest, Status)
from service.api_calibration import calibrations
from service.calhistory import keep_and_activate
from service.api_common import (Auth, BODY_NOT_PARSED, EDGE, NO_ROOM, NOT_FOUND, ServiceDep,
                                UNAUTHORIZED, disk_error as _disk_error)
from service.edge import EdgeGuard
from service.parts import PartInUse, PartQuotaExceeded, grasp_from_query, part_info
from service.pictures import Busy, NoDeviations
from service.settings import Settings
from scanner_core.cad import GRASPS, PartError

STATIC = Path(__file__).resolve().parent / "static"
#: Server-sent events: how often the status page is told the service's status, s.
EVENTS_PERIOD_S = 0.5
#: Seconds a client refused a preview (too many being drawn) is told to wait.
PICTURE_RETRY_S = 1


# ---------------------------------------------------------------------------------------------
system = APIRouter(tags=["system"], responses=EDGE)


@system.get("/health", response_model=Health)
def health() -> Health:
    return Health()


@system.get("/status", response_model=Status)
def get_status(service: ServiceDep) -> dict:
    return service.status()


@system.get("/metrics", response_class=Response,
            responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format"}})
def metrics(service: ServiceDep) -> Response:
    service.metrics.pictures(service.frame_picture.renders, service.previews.renders,
                             service.previews.refused)
    return Response(service.metrics.render(service.status()),
                    media_type="text/plain; version=0.0.4; charset=utf-8")


@system.get("/calibration", response_model=CalibrationModel)
def get_calibration(service: ServiceDep) -> dict:
    return service.engine.calibration.to_dict()


@system.put("/calibration", response_model=CalibrationModel, dependencies=Auth,
            responses={**UNAUTHORIZED,
                       409: {"model": Problem, "description": "a scan is in progress"},
                       422: {"model": Problem, "description": "not a valid calibration (each "
                                                              "field bounded, none unknown), or "
                                                              "not for this camera's images"},
                       **NO_ROOM})
def put_calibration(body: CalibrationModel, service: ServiceDep) -> dict:
    try:
        calibration = Calibration.from_dict(body.model_dump())
    except CalibrationError as exc:
        raise HTTPException(422, str(exc)) from None
    try:
        keep_and_activate(service, calibration)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    except EngineBusy as exc:
        raise HTTPException(409, str(exc)) from None
    except OSError as exc:
        raise _disk_error(service, exc, "the calibration could not be saved") from None
    return calibration.to_dict()


# ---------------------------------------------------------------------------------------------
scans = APIRouter(prefix="/scans", tags=["scans"], responses=EDGE)
_HTTP_METHODS = frozenset({"GET", "PUT", "POST", "DELETE", "PATCH", "HEAD"})


@scans.post("", status_code=202, response_model=ScanAccepted, dependencies=Auth,
            responses={**UNAUTHORIZED, **NOT_FOUND,
                       409: {"model": Problem, "description": "a scan is already in progress"},
                       422: {"model": Problem, "description": "malformed request"},
                       503: {"model": Problem, "description": "the camera is not streaming"},
                       **NO_ROOM})
async def arm_scan(service: ServiceDep, http: Request,
                   request: ScanRequest | None = None) -> ScanAccepted:
    request = request or ScanRequest()
    if await http.is_disconnected():
        # Its client gave up waiting (a crowded service): an armed scan nobody knows of
        # would take the next pass and answer the controller's retry with 409.
        raise HTTPException(499, "the client closed the connection before the scan was armed")
    try:
        job = await asyncio.to_thread(
            service.arm, request.part, request.timeout_s, request.misplace,
            record=request.record, taught_place=request.taught_place, fault=request.fault)
    except KeyError:
        raise HTTPException(404, f"unknown part {request.part!r}: see GET /parts") from None
    except ValueError as exc:  # a misplacement out of the inspection volume (PartError), a
        raise HTTPException(422, str(exc)) from None  # taught place beyond the robot's reach
    except EngineBusy as exc:
        raise HTTPException(409, str(exc)) from None
    except EngineFault as exc:
        raise HTTPException(503, str(exc)) from None
    except OSError as exc:  # the recording's folder cannot be made
        raise _disk_error(service, exc, "cannot record the pass") from None
    return ScanAccepted(scan_id=job.scan_id, state=job.state)


@scans.get("", response_model=ScanList)
def list_scans(service: ServiceDep) -> dict:
    return {"scans": service.list_scans()}


def _scan_or_404(service: Service, scan_id: str) -> dict:
    try:
        return service.scan_info(scan_id)
    except KeyError:
        raise HTTPException(404, f"no scan {scan_id!r}") from None


@scans.get("/{scan_id}", response_model=ScanInfo, responses=NOT_FOUND)
def get_scan(scan_id: str, service: ServiceDep) -> dict:
    return _scan_or_404(service, scan_id)


def _scan_file(service: Service, scan_id: str, name: str) -> Path:
    info = _scan_or_404(service, scan_id)
    try:
        return service.store.file(scan_id, name)
    except KeyError:
        raise HTTPException(409, f"scan {scan_id} has no {name} ({info['state']}"
                                 f"{': ' + info['reason'] if info.get('reason') else ''})") from None


PLY_RESPONSES = {200: {"content": {"application/octet-stream": {}}, "description": "binary PLY"},
                 **NOT_FOUND, 409: {"model": Problem, "description": "the scan has no cloud"}}


@scans.get("/{scan_id}/cloud.ply", response_class=FileResponse, responses=PLY_RESPONSES)
def get_cloud(scan_id: str, service: ServiceDep) -> FileResponse:
    return FileResponse(_scan_file(service, scan_id, "cloud.ply"), media_type="application/octet-stream")


@scans.get("/{scan_id}/edges.ply", response_class=FileResponse, responses=PLY_RESPONSES)
def get_edges(scan_id: str, service: ServiceDep) -> FileResponse:
    return FileResponse(_scan_file(service, scan_id, "edges.ply"), media_type="application/octet-stream")


@scans.get("/{scan_id}/preview.png", response_class=Response,
           responses={200: {"content": {"image/png": {}}, "description": "the cloud seen from below"},
                      **NOT_FOUND, 409: {"model": Problem, "description": "the scan has no cloud"},
                      503: {"model": Problem, "description": "too many previews being drawn: "
                                                             "try again after Retry-After s"}})
async def get_preview(scan_id: str, service: ServiceDep) -> Response:
    return await _scan_picture(service, scan_id, service.previews)


async def _scan_picture(service: Service, scan_id: str, pictures) -> Response:
    """A picture of the scan's cloud (``service.pictures.PreviewPictures``): on the event loop
    when it is kept (no thread hop), in a thread to draw it."""
    path = _scan_file(service, scan_id, "cloud.ply")
    try:
        png = pictures.cached(scan_id, path)
        if png is None:
            png = await asyncio.to_thread(pictures.get, scan_id, path)
    except Busy as exc:
        raise HTTPException(503, f"{exc}: try again",
                            headers={"Retry-After": str(PICTURE_RETRY_S)}) from None
    except NoDeviations as exc:
        raise HTTPException(409, str(exc)) from None
    except FileNotFoundError:  # deleted meanwhile
        raise HTTPException(404, f"no scan {scan_id!r}") from None
    return Response(png, media_type="image/png")


@scans.get("/{scan_id}/deviation.png", response_class=Response,
           responses={200: {"content": {"image/png": {}},
                            "description": "the cloud seen from below, each point coloured by its "
                                           "deviation from the model at the pose, the "
                                           "inspection's failing regions circled"},
                      **NOT_FOUND, 409: {"model": Problem,
                                         "description": "the scan has no cloud, or no pose"},
                      503: {"model": Problem, "description": "too many pictures being drawn: "
                                                             "try again after Retry-After s"}})
async def get_deviation_map(scan_id: str, service: ServiceDep) -> Response:
    return await _scan_picture(service, scan_id, service.deviation_maps)


@scans.delete("/{scan_id}", status_code=204, response_class=Response, dependencies=Auth,
              responses={**UNAUTHORIZED, **NOT_FOUND,
                         409: {"model": Problem, "description": "the scan is in progress"},
                         **NO_ROOM})
def delete_scan(scan_id: str, service: ServiceDep) -> Response:
    try:
        service.delete_scan(scan_id)
    except KeyError:
        raise HTTPException(404, f"no scan {scan_id!r}") from None
    except ValueError as exc:
        raise HTTPException(409, str(exc)) from None
    except OSError as exc:
        raise _disk_error(service, exc, f"scan {scan_id} could not be deleted") from None
    return Response(status_code=204)


# ---------------------------------------------------------------------------------------------
parts = APIRouter(prefix="/parts", tags=["parts"], responses=EDGE)


@parts.get("", response_model=PartList)
def list_parts(service: ServiceDep) -> dict:
    return {"parts": [part_info(service.parts.get(n), service.parts.simplified(n))
                      for n in service.parts.names()],
            "default": service.default_part}


@parts.put("/{name}", status_code=201, response_model=PartInfo, dependencies=Auth,
           responses={**UNAUTHORIZED,
                      413: {"model": Problem, "description": "the mesh file is too large "
                                                             "(max_part_bytes)"},
                      422: {"model": Problem, "description": "bad unit, name or mesh (counts "
                                                             "the file cannot hold, no "
                                                             "thickness or volume, too large "
                                                             "for its unit, out of the volume)"},
                      507: {"model": Problem, "description": "no room: max_parts parts are "
                                                             "stored, or the disk refused"}},
           openapi_extra={"requestBody": {"required": True, "content": {
               "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}}})
async def put_part(name: str, request: Request, service: ServiceDep,
                   units: Annotated[str, Query(description="unit of the mesh: mm, cm, m or inch")],
                   format: Annotated[str, Query(pattern="^(stl|obj|ply)$")] = "stl",
                   grasp: Annotated[str | None, Query(
                       pattern=f"^({'|'.join(GRASPS)})$",
                       description="the nominal grasp by name; default centred")] = None,
                   grasp_matrix: Annotated[str | None, Query(
                       max_length=1000,
                       description="the nominal grasp ^T X_P instead, as taught: 16 comma-"
                                   "separated numbers, a 4x4 row-major rigid transform, mm")]
                   = None,
                   inspect_extra_mm: Annotated[float | None, Query(
                       gt=0, description="this part's inspection: extra or missing material "
                                         "beyond this many mm off the model; default the "
                                         "service's setting, or derived from each scan")]
                   = None,
                   inspect_deform_mm: Annotated[float | None, Query(
                       gt=0, description="this part's deformation threshold, mm")] = None,
                   inspect_min_area_mm2: Annotated[float | None, Query(
                       gt=0, description="this part's smallest failing region, mm^2")]
                   = None) -> dict:
    library = service.parts
    if grasp is not None and grasp_matrix is not None:
        raise HTTPException(422, "give grasp (a name) or grasp_matrix (a 4x4), not both")
    try:  # the cheap refusals before a byte of the body is read
        inspection = InspectionParams(extra_mm=inspect_extra_mm, deform_mm=inspect_deform_mm,
                                      min_area_mm2=inspect_min_area_mm2)
        chosen = (grasp or "centred") if grasp_matrix is None else grasp_from_query(grasp_matrix)
        library.check_name(name)
        library.check_room(name)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    except PartQuotaExceeded as exc:
        raise HTTPException(507, str(exc)) from None
    # Streamed to disk as it arrives (the edge stops it past max_part_bytes): a large upload
    # never sits in memory whole.
    try:
        staging = await asyncio.to_thread(library.staging)
    except OSError as exc:
        raise _disk_error(service, exc, "the mesh could not be stored") from None
    try:
        with open(staging / f"mesh.{format}", "wb") as mesh:
            async for chunk in request.stream():
                mesh.write(chunk)
        part = await asyncio.to_thread(library.add_staged, name, staging, units,
                                       suffix=f".{format}", grasp=chosen,
                                       inspection=inspection)
        await asyncio.to_thread(service.prepare_part, name)
    except (PartError, ValueError) as exc:
        raise HTTPException(422, str(exc)) from None
    except PartQuotaExceeded as exc:
        raise HTTPException(507, str(exc)) from None
    except OSError as exc:
        raise _disk_error(service, exc, "the mesh could not be stored") from None
    finally:
        await asyncio.to_thread(shutil.rmtree, staging, True)  # moved into place, or dropped
    return part_info(part, library.simplified(name))


@parts.delete("/{name}", status_code=204, response_class=Response, dependencies=Auth,
              responses={**UNAUTHORIZED, **NOT_FOUND,
                         409: {"model": Problem, "description": "a built-in part, the default "
                                                                "part, or one a pending scan "
                                                                "uses"},
                         **NO_ROOM})
def delete_part(name: str, service: ServiceDep) -> Response:
    try:
        service.delete_part(name)
    except KeyError:
        raise HTTPException(404, f"unknown part {name!r}: see GET /parts") from None
    except PartInUse as exc:
        raise HTTPException(409, str(exc)) from None
    except OSError as exc:
        raise _disk_error(service, exc, f"part {name!r} could not be deleted") from None
    return Response(status_code=204)


# ---------------------------------------------------------------------------------------------
page = APIRouter(tags=["status page"], responses=EDGE)


@page.get("/", response_class=HTMLResponse, include_in_schema=False)
def index() -> HTMLResponse:
    return HTMLResponse((STATIC / "index.html").read_text())


@page.get("/static/{name}", include_in_schema=False)
def static_file(name: str) -> FileResponse:
    path = (STATIC / name).resolve()
    if path.parent != STATIC or not path.is_file():
        raise HTTPException(404, f"no file {name!r}")
    return FileResponse(path)


@page.get("/frame.png", response_class=Response,
          responses={200: {"content": {"image/png": {}},
                           "description": "the latest frame with the stripe and marker drawn"},
                     404: {"model": Problem, "description": "no frame yet"}})
async def latest_frame(service: ServiceDep) -> Response:
    # on the event loop when the picture kept is fresh (no thread hop), on its thread to draw it
    latest = service.engine.latest
    if latest is None:
        raise HTTPException(404, "no frame has arrived yet")
    hit = service.frame_picture.cached(latest[0].frame_id)
    if hit is None:
        hit = await asyncio.get_running_loop().run_in_executor(
            service.frame_picture.thread, service.frame_picture.get, latest,
            service.engine.calibration, service.engine.params)
    png, frame_id = hit
    return Response(png, media_type="image/png",
                    headers={"Cache-Control": "no-store", "X-Frame-Id": str(frame_id)})


@page.get("/events", response_class=StreamingResponse,
          responses={200: {"content": {"text/event-stream": {}},
                           "description": "the status, as server-sent events"},
                     503: {"model": Problem, "description": "max_event_streams are open"}})
async def events(request: Request, service: ServiceDep) -> StreamingResponse:
    if service.event_streams >= service.settings.max_event_streams:
        raise HTTPException(503, f"{service.event_streams} event streams are open, the most this "
                                 f"service serves (max_event_streams): try again later",
                            headers={"Retry-After": "5"})
    service.event_streams += 1  # counted now (a burst sees it), freed when the answer ends

    async def stream():
        while not await request.is_disconnected():
            yield await asyncio.to_thread(service.status_event, EVENTS_PERIOD_S / 2)
            await asyncio.sleep(EVENTS_PERIOD_S)

    return _Counted(stream(), service, media_type="text/event-stream",
                    headers={"Cache-Control": "no-store"})


class _Counted(StreamingResponse):
    """An event stream that frees its place in ``Service.event_streams`` when it ends, however
    it ends (a stream whose generator never started included)."""

    def __init__(self, content, service: Service, **kwargs):
        super().__init__(content, **kwargs)
        self._service = service

    async def __call__(self, scope, receive, send):
        try:
            await super().__call__(scope, receive, send)
        finally:
            self._service.event_streams -= 1


# ---------------------------------------------------------------------------------------------


def create_app(settings: Settings | None = None, *, service: Service | None = None) -> FastAPI:
    """The application; its lifespan starts the service and stops it."""
    if service is None:
        service = Service(settings if settings is not None else Settings())  # a real cell's

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        await asyncio.to_thread(service.start)
        try:
            yield
        finally:
            await asyncio.to_thread(service.stop)

    # The documentation pages' scripts are served by the service itself: a cell network is
    # often offline (fastapi-offline ships Swagger UI and ReDoc).
    app = FastAPIOffline(title="flyscan", version=package_version("flyscan"), lifespan=lifespan,
                         description="In-flight laser-line 3D scanner: arm a scan, fetch its cloud.")
    app.state.service = service
    for router in (system, scans, parts, calibrations, page):
        app.include_router(router)
    # Outside every route, inside Starlette's error middleware: the token and the body's size
    # are checked before FastAPI reads the body (it reads it before solving dependencies).
    app.add_middleware(EdgeGuard, settings=service.settings,
                       acquiring=getattr(service, "acquiring", None))

    @app.exception_handler(StarletteHTTPException)
    async def http_problem(request: Request, exc: StarletteHTTPException) -> Response:
        # FastAPI answers 400 for a body json.loads cannot take (invalid UTF-8, nesting past
        # the interpreter's recursion limit): a malformed request like any other, 422.
        if exc.status_code == 400 and exc.detail == BODY_NOT_PARSED:
            return JSONResponse(status_code=422, content={
                "detail": "the body is not a JSON document (UTF-8, nested a few hundred deep "
                          "at most)"})
        if exc.status_code == 405:
            # Starlette's Allow names the methods of the first route whose path matched
            # (GET of /scans/{id}); the resource also has the others' (its DELETE). Read from
            # the API's own description: the routes of included routers are not listed flat.
            allowed = sorted({method for regex, methods in resources() if regex.match(
                request.url.path) for method in methods} | {"OPTIONS"})
            if request.method == "OPTIONS":  # what may be done here: asked, and answered
                return Response(status_code=204, headers={"Allow": ", ".join(allowed)})
            exc = StarletteHTTPException(405, exc.detail, headers={"Allow": ", ".join(allowed)})
        return await http_exception_handler(request, exc)

    @functools.cache
    def resources() -> list:
        """(compiled path, its methods) of every path of the API (``app.openapi()``)."""
        out = []
        for path, operations in app.openapi().get("paths", {}).items():
            methods = {m.upper() for m in operations if m.upper() in _HTTP_METHODS}
            if "GET" in methods:
                methods.add("HEAD")
            out.append((compile_path(path)[0], methods))
        return out

    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        # Each field's location and problem, without echoing the input back: it may hold
        # what JSON cannot carry (a NaN), and a 422 must never turn into a 500.
        errors = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in exc.errors()]
        return JSONResponse(status_code=422, content={"detail": errors})

    return app
