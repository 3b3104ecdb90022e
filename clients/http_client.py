"""HTTP client for the flyscan service's REST API: what a robot cell controller calls.

    from clients import FlyscanClient, PoseNotActionable, place_correction, ur_pose_to_matrix

    taught_place = ur_pose_to_matrix([0.4, -0.2, 0.1, 0.0, 3.1416, 0.0])  # ^B X_T,place, mm
    with FlyscanClient("http://127.0.0.1:8000", token="...") as api:
        api.health()                                  # {"status": "ok"}
        nominal = {p["name"]: p["nominal_grasp"] for p in api.parts()}["bracket"]
        scan_id = api.arm(part="bracket")             # 202: the trigger is armed
        info = api.wait(scan_id, timeout=30.0)        # polls until done; ScanFailed if failed
        # info["pose"]: None (no part), {"refused": why}, or the pose with "act" and "matrix"
        try:
            place = place_correction(taught_place, info["pose"], nominal)
            target = place.ur_pose                    # [x, y, z (m), rx, ry, rz (rad)] in {B}
        except PoseNotActionable as exc:              # refused, or act false: do not place
            print("not placing:", exc.reasons)
        xyz = api.cloud(scan_id)                      # (N, 3) float32, mm in the gripper frame {T}
        fields = api.cloud_fields(scan_id)            # {"x": ..., "frame_id": ..., "quality": ...}

``arm(..., taught_place=...)`` has the service compute the same correction: the scan's info then
carries ``correction`` (``act``, ``reasons``, ``tcp_place_mm``, ``ur_pose``).

Every error the service reports raises a :class:`FlyscanError` carrying the HTTP status and the
service's reason (``detail``); 401, 404, 409, 422 and 503 have their own subclasses. A service that
cannot be reached raises :class:`ServiceUnreachable`, a failed scan :class:`ScanFailed` (both
FlyscanErrors too), so ``except FlyscanError`` catches everything the service can answer.
``wait`` raises the built-in ``TimeoutError`` when the scan is not over in time.

The token, when given, is sent as ``Authorization: Bearer TOKEN`` with every request; the
service requires it on the mutating endpoints when it has one configured.
"""
from __future__ import annotations

import json
import os
import time
from typing import Any
from urllib.parse import quote

import httpx
import numpy as np

from .ply import parse_ply, xyz_array

__all__ = [
    "FlyscanClient", "FlyscanError", "ServiceUnreachable", "BadRequest", "Unauthorized",
    "NotFound", "Conflict", "Unprocessable", "ServiceUnavailable", "ScanFailed",
]

# States a scan never leaves.
_FINAL_STATES = ("done", "failed")
# A detail longer than this (an HTML error page from a proxy, say) is cut in messages.
_MAX_DETAIL_CHARS = 500


class FlyscanError(Exception):
    """The service answered with an error, or could not be asked.

    Attributes
    ----------
    status_code : int or None
        The HTTP status; None when there was no answer (:class:`ServiceUnreachable`) or the
        error is not an HTTP one (:class:`ScanFailed`).
    detail : str
        The service's reason, from its JSON body ``{"detail": ...}``.
    """

    def __init__(self, status_code: int | None, detail: str):
        self.status_code = status_code
        self.detail = detail
        super().__init__(f"HTTP {status_code}: {detail}" if status_code is not None else detail)


class ServiceUnreachable(FlyscanError):
    """No HTTP answer: connection refused, DNS failure, request timed out."""

    def __init__(self, detail: str):
        super().__init__(None, detail)


class BadRequest(FlyscanError):
    """400: the request is malformed."""


class Unauthorized(FlyscanError):
    """401 (or 403): a missing or wrong bearer token."""


class NotFound(FlyscanError):
    """404: unknown scan id or part name."""


class Conflict(FlyscanError):
    """409: a scan is already in progress, or the scan is not done yet."""


class Unprocessable(FlyscanError):
    """422: a bad unit, mesh, calibration or parameter."""


class ServiceUnavailable(FlyscanError):
    """503: the service cannot scan now (camera not streaming: fault)."""


class ScanFailed(FlyscanError):
    """The scan ended in state ``failed``.

    Attributes
    ----------
    reason : str
        Why, as the service put it ("marker gone", "timeout", "camera stopped", "too long", ...).
    info : dict
        The scan's full ScanInfo.
    """

    def __init__(self, reason: str, info: dict):
        self.reason = reason
        self.info = info
        super().__init__(None, f"scan {info.get('scan_id')} failed: {reason}")


_ERRORS_BY_STATUS: dict[int, type[FlyscanError]] = {
    400: BadRequest, 401: Unauthorized, 403: Unauthorized, 404: NotFound, 409: Conflict,
    422: Unprocessable, 503: ServiceUnavailable,
}


class FlyscanClient:
    """Synchronous client of the flyscan REST API (one ``httpx.Client``, connections reused).

    Parameters
    ----------
    base_url : str
        Where the service listens.
    token : str, optional
        Bearer token; the service demands it on mutating endpoints when it has one.
    timeout : float
        Seconds for each HTTP request (not for a whole scan: see :meth:`wait`).
    transport : httpx.BaseTransport, optional
        For tests (``httpx.MockTransport``); the network otherwise.

    Constructing the client does no I/O; the first request connects. Use it as a context
    manager, or call :meth:`close`.
    """

    def __init__(self, base_url: str = "http://127.0.0.1:8000", *, token: str | None = None,
                 timeout: float = 10.0, transport: httpx.BaseTransport | None = None):
        self.base_url = base_url.rstrip("/")
        headers = {"Accept": "application/json"}
        if token:
            headers["Authorization"] = f"Bearer {token}"
        self._http = httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout,
                                  transport=transport)

    # -- life cycle ---------------------------------------------------------------------------
    def close(self) -> None:
        """Close the connections."""
        self._http.close()

    def __enter__(self) -> FlyscanClient:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"FlyscanClient({self.base_url!r})"

    # -- service ------------------------------------------------------------------------------
    def health(self) -> dict:
        """``GET /health``: ``{"status": "ok"}`` when the service is up."""
        return self._json("GET", "/health")

    def status(self) -> dict:
        """``GET /status``: trigger state, fault reason, camera, robot, fps, frames dropped."""
        return self._json("GET", "/status")

    # -- scans --------------------------------------------------------------------------------
    def arm(self, part: str | None = None, timeout_s: float | None = None,
            misplace=None, record: bool = False, taught_place=None,
            fault: str | None = None) -> str:
        """``POST /scans``: arm the trigger for the next pass; return the new scan id.

        ``misplace`` ([tx, ty, tz, rx, ry, rz], mm and degrees) moves the part in the gripper
        for the pass, and ``fault`` (``KIND[:SIZE_MM]``, as ``flyscan scan --fault``) has the
        gripper hold that fault of the part instead: honoured by a simulated cell only.
        ``record`` also records the pass on the service's side (its ScanInfo's
        ``recording.path``, once written).
        ``taught_place``, the TCP pose in the robot base at which a nominally held part lands
        right (^B X_T,place: a UR pose [x, y, z (m), rx, ry, rz (rad)] or a 4x4 in mm), has
        the finished scan's info carry ``correction``: the corrected TCP place pose, or why
        not to place (``clients.placement``). Unprocessable (422) unless a rigid transform.

        Raises Conflict (409) when a scan is in progress, NotFound (404) for an unknown part,
        ServiceUnavailable (503) when the camera is not streaming.
        """
        request = {"part": part, "timeout_s": timeout_s}
        if record:
            request["record"] = True
        if misplace is not None:
            request["misplace"] = [float(v) for v in misplace]
        if fault is not None:
            request["fault"] = str(fault)
        if taught_place is not None:
            request["taught_place"] = np.asarray(taught_place, dtype=np.float64).tolist()
        body = self._json("POST", "/scans", json=request)
        try:
            return str(body["scan_id"])
        except (KeyError, TypeError):
            raise FlyscanError(None, f"POST /scans answered without a scan_id: {body!r}") from None

    def scan(self, scan_id: str) -> dict:
        """``GET /scans/{id}``: the scan's ScanInfo (state, reason, points, pose, timings...)."""
        return self._json("GET", f"/scans/{_segment(scan_id)}")

    def scans(self) -> list[dict]:
        """``GET /scans``: every stored scan's ScanInfo, newest first."""
        return self._json("GET", "/scans")["scans"]

    def wait(self, scan_id: str, timeout: float = 30.0, poll_s: float = 0.05) -> dict:
        """Poll the scan until it is ``done`` (return its ScanInfo) or ``failed``.

        Raises
        ------
        ScanFailed
            The scan failed; ``reason`` says why, ``info`` is the ScanInfo.
        TimeoutError
            Still not over after `timeout` seconds.
        """
        if poll_s <= 0:
            raise ValueError(f"`poll_s` must be > 0, got {poll_s}")
        deadline = time.monotonic() + timeout
        while True:
            info = self.scan(scan_id)
            state = info.get("state")
            if state == "done":
                return info
            if state == "failed":
                raise ScanFailed(info.get("reason") or "no reason given", info)
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"scan {scan_id} still {state!r} after {timeout:g} s")
            time.sleep(min(poll_s, remaining))

    def cloud(self, scan_id: str) -> np.ndarray:
        """``GET /scans/{id}/cloud.ply``: the point cloud, (N, 3) float32, mm in {T}."""
        return xyz_array(self.cloud_fields(scan_id))

    def cloud_fields(self, scan_id: str) -> dict[str, np.ndarray]:
        """The cloud's per-vertex properties, ``{"x": (N,) float32, ..., "frame_id": ...}``."""
        return parse_ply(self._bytes("GET", f"/scans/{_segment(scan_id)}/cloud.ply"))

    def edges(self, scan_id: str) -> np.ndarray:
        """``GET /scans/{id}/edges.ply``: the edge cloud, (N, 3) float32, mm in {T}."""
        return xyz_array(self.edges_fields(scan_id))

    def edges_fields(self, scan_id: str) -> dict[str, np.ndarray]:
        """The edge cloud's per-vertex properties."""
        return parse_ply(self._bytes("GET", f"/scans/{_segment(scan_id)}/edges.ply"))

    def delete(self, scan_id: str) -> None:
        """``DELETE /scans/{id}``."""
        self._request("DELETE", f"/scans/{_segment(scan_id)}")

    # -- parts and calibration ----------------------------------------------------------------
    def parts(self) -> list[dict]:
        """``GET /parts``: the known parts (name, units, faces, ...)."""
        return self._json("GET", "/parts")["parts"]

    def upload_part(self, name: str, path: str | os.PathLike, units: str,
                    grasp=None, inspection: dict | None = None) -> dict:
        """``PUT /parts/{name}?units=...&format=...[&grasp=...]``: upload a mesh file (STL, OBJ
        or PLY, told by its suffix) as a part; returns its PartInfo (``nominal_grasp``: the
        ^T X_P the place correction starts from).

        A mesh file carries no reliable unit, so `units` (mm, cm, m, inch) is required.
        `grasp` is the nominal grasp: a name (``centred``, ``flat`` or ``identity``: see
        docs/design.md), or the taught ^T X_P itself, a (4, 4) rigid transform in mm of the
        part's CAD frame in the TCP (sent as ``grasp_matrix``); None: the service's default,
        ``centred``. `inspection`: the part's own inspection thresholds, some of
        ``extra_mm``, ``deform_mm``, ``min_area_mm2`` (mm, mm^2; sent as ``inspect_<name>``).
        Raises Unprocessable (422) for a bad unit, grasp, threshold or mesh, ValueError for a
        grasp that is neither a name nor a 4x4.
        """
        params = {"units": units, "format": os.path.splitext(os.fspath(path))[1][1:].lower()}
        for key, value in (inspection or {}).items():
            params[f"inspect_{key}"] = value
        if isinstance(grasp, str):
            params["grasp"] = grasp
        elif grasp is not None:
            matrix = np.asarray(grasp, dtype=np.float64)
            if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
                raise ValueError(f"`grasp` must be a name or a finite 4x4 (mm), got shape "
                                 f"{matrix.shape}")
            params["grasp_matrix"] = ",".join(repr(float(v)) for v in matrix.ravel())
        with open(path, "rb") as f:
            content = f.read()
        return self._json("PUT", f"/parts/{_segment(name)}", params=params,
                          content=content,
                          headers={"Content-Type": "application/octet-stream"})

    def calibration(self) -> dict:
        """``GET /calibration``: the calibration in use."""
        return self._json("GET", "/calibration")

    def put_calibration(self, calibration: dict) -> dict | None:
        """``PUT /calibration``: replace the calibration; returns the service's answer."""
        response = self._request("PUT", "/calibration", json=calibration)
        return _decode_json(response) if response.content else None

    # -- plumbing -----------------------------------------------------------------------------
    def _request(self, method: str, path: str, **kwargs) -> httpx.Response:
        try:
            response = self._http.request(method, path, **kwargs)
        except httpx.TimeoutException as exc:
            reason = str(exc) or type(exc).__name__
            raise ServiceUnreachable(f"{method} {self.base_url}{path} timed out: {reason}") \
                from None
        except httpx.TransportError as exc:
            reason = str(exc) or type(exc).__name__
            raise ServiceUnreachable(f"cannot reach the flyscan service at {self.base_url} "
                                     f"({method} {path}): {reason}") from None
        if response.is_error:
            cls = _ERRORS_BY_STATUS.get(response.status_code, FlyscanError)
            raise cls(response.status_code, _error_detail(response))
        return response

    def _json(self, method: str, path: str, **kwargs) -> Any:
        return _decode_json(self._request(method, path, **kwargs))

    def _bytes(self, method: str, path: str) -> bytes:
        return self._request(method, path, headers={"Accept": "*/*"}).content


def _segment(value: str) -> str:
    """One URL path segment: a scan id or part name with '/', '?', '#' escaped."""
    value = str(value)
    if not value:
        raise ValueError("an empty scan id or part name")
    return quote(value, safe="")


def _decode_json(response: httpx.Response) -> Any:
    try:
        return response.json()
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise FlyscanError(response.status_code,
                           f"{response.request.method} {response.request.url.path} answered "
                           f"with non-JSON: {response.text[:_MAX_DETAIL_CHARS]!r}") from None


def _error_detail(response: httpx.Response) -> str:
    """The reason in an error answer: ``{"detail": "..."}``, FastAPI's validation list, or text."""
    try:
        detail = response.json()["detail"]
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError):
        text = response.text.strip()[:_MAX_DETAIL_CHARS]
        return text or response.reason_phrase or "no reason given"
    if isinstance(detail, list):
        # FastAPI's request validation: [{"loc": ["query", "units"], "msg": "...", ...}, ...]
        parts = []
        for item in detail:
            if isinstance(item, dict) and "msg" in item:
                loc = ".".join(str(p) for p in item.get("loc", ()))
                parts.append(f"{loc}: {item['msg']}" if loc else str(item["msg"]))
            else:
                parts.append(str(item))
        return "; ".join(parts)
    return str(detail)[:_MAX_DETAIL_CHARS]
