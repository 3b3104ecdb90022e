"""Typed request and response bodies of the REST API (they make the OpenAPI schema)."""
from __future__ import annotations

from typing import Annotated, Literal

import numpy as np

from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from clients.placement import rigid_transform, ur_pose_to_matrix

RunState = Literal["idle", "armed", "scanning", "processing", "fault"]
ScanState = Literal["armed", "scanning", "processing", "done", "failed"]


class Problem(BaseModel):
    """An error: the reason, for a person and for the client's exception (a request that does
    not validate lists each field's problem: ``loc``, ``msg``, ``type``)."""

    detail: str | list[dict]


class Health(BaseModel):
    status: Literal["ok"] = "ok"


class CameraStatus(BaseModel):
    state: str = Field(description="streaming, stalled, closed or error")
    error: str | None = None
    fps: float
    frames: int
    frames_dropped: int
    exposure_mode: Literal["fixed", "dynamic", "multiple"] = Field(
        "fixed", description="exposure control in effect (fixed when the camera has none)")
    exposure_us: float | None = Field(None, description="the newest frame's exposure, us")
    gain: float = Field(1.0, description="the newest frame's analogue gain")
    exposure_updates: int = Field(0, description="exposure changes made by the control")


class QueueStatus(BaseModel):
    depth: int
    capacity: int
    overflows: int


class RobotStatus(BaseModel):
    connected: bool
    host: str | None = Field(None, description="the UR robot's address (ur://HOST); none when simulated")
    samples: int | None = Field(None, description="poses received since the service started")
    reconnects: int | None = None
    last_sample_age_s: float | None = Field(None, description="how old the newest pose is, s")
    last_error: str | None = None


class ZmqStatus(BaseModel):
    endpoint: str | None
    sent: int
    dropped: int


class Status(BaseModel):
    state: RunState
    fault_reason: str | None
    camera: CameraStatus
    robot: RobotStatus
    fps: float
    frames_dropped: int
    queue: QueueStatus
    zmq: ZmqStatus
    current_scan_id: str | None
    last_scan_id: str | None
    scans_done: int
    scans_failed: int
    clock_offset_s: float
    led_correction_t_mm: list[float] | None = Field(
        None, description="marker minus robot track in {T}, mm, subtracted by the cross-check")
    led_correction_from: str | None = Field(None, description="the scan it was learned from, or 'settings'")
    simulated: bool


Finite = Annotated[float, Field(allow_inf_nan=False)]
#: A UR pose: [x, y, z (m), rx, ry, rz (rotation vector, rad)].
UrPose = Annotated[list[Finite], Field(min_length=6, max_length=6)]
#: A 4x4 homogeneous transform, row-major, mm.
Matrix4 = Annotated[list[Annotated[list[Finite], Field(min_length=4, max_length=4)]],
                    Field(min_length=4, max_length=4)]


def taught_place_matrix(value) -> np.ndarray:
    """A taught place pose as given (a UR pose vector, m and rad, or a 4x4 in mm) -> ^B X_T,
    (4, 4) float64, mm; ValueError unless a rigid transform."""
    if len(value) == 6:
        return ur_pose_to_matrix(value)
    return rigid_transform(value, "taught_place")


def _rigid_taught_place(value):
    if value is not None:
        taught_place_matrix(value)
    return value


#: The TCP pose in the robot base at which a nominally held part lands right: what the place
#: correction starts from (``clients.placement``).
TaughtPlace = Annotated[UrPose | Matrix4, AfterValidator(_rigid_taught_place)]
TAUGHT_PLACE_DESCRIPTION = (
    "the taught place pose ^B X_T,place: the TCP pose in the robot base at which a part held at "
    "its nominal grasp lands right, as a UR pose [x, y, z (m), rx, ry, rz (rotation vector, "
    "rad)] or a 4x4 row-major transform in mm; with it, a scan with a pose carries `correction`")


class ScanRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    part: str | None = Field(None, description="a part of GET /parts; default the service's")
    timeout_s: float | None = Field(None, gt=0, le=600,
                                    description="fail when the marker has not appeared by then")
    misplace: list[Annotated[float, Field(allow_inf_nan=False)]] | None = Field(
        None, min_length=6, max_length=6,
        description="simulated mode only: the part's misplacement in the gripper, "
                    "[tx, ty, tz (mm), rx, ry, rz (rotation vector, degrees)]")
    record: bool = Field(False, description="also record the pass (every frame, the robot's "
                                            "samples) for replay: see the scan's `recording`")
    taught_place: TaughtPlace | None = Field(
        None, description=TAUGHT_PLACE_DESCRIPTION + "; default the service's setting")


class PlaceCorrection(BaseModel):
    """Where to place the part: the TCP place pose that corrects the measured misplacement
    (``clients.placement.place_correction``). No move when ``act`` is false."""

    act: bool = Field(description="whether the robot may act on the pose; false: do not place")
    reasons: list[str] = Field(description="why not to act; empty when act")
    tcp_place_mm: Matrix4 | None = Field(
        description="^B X_T,corrected = taught_place @ nominal_grasp @ inv(pose.matrix): the "
                    "TCP pose in the robot base, 4x4 row-major, mm; null when not act")
    ur_pose: UrPose | None = Field(
        description="the same as a UR pose [x, y, z (m), rx, ry, rz (rotation vector, rad)] "
                    "in the robot base; null when not act")
    taught_place_mm: Matrix4 = Field(description="^B X_T,place as given, 4x4 row-major, mm")
    frames: str = Field(description="the frames and the equation, in words")


class ScanAccepted(BaseModel):
    scan_id: str
    state: ScanState


class ScanInfo(BaseModel):
    model_config = ConfigDict(extra="allow")

    scan_id: str
    state: ScanState
    reason: str | None = None
    part: str | None = None
    created: float
    finished: float | None = None
    frames: int = 0
    frames_dropped: int = 0
    frames_unplaced: int = 0
    queue_overflows: int = 0
    points: int = 0
    edge_points: int = 0
    edge_kinds: dict | None = Field(None, description="edge points per kind: in the edge cloud "
                                    "(dropout, step) and set aside (occluded, grazing, "
                                    "turned_away, off_model)")
    end_reason: str | None = None
    timings_ms: dict = Field(default_factory=dict)
    latency_ms: dict = Field(default_factory=dict)
    cross_check: dict | None = None
    pose: dict | None = None
    correction: PlaceCorrection | None = Field(
        None, description="with a taught place pose (the request's or the settings') and a "
                          "finished scan: the corrected TCP place pose, or why not to place")


class ScanList(BaseModel):
    scans: list[ScanInfo]


class PartInfo(BaseModel):
    name: str
    units: str
    faces: int
    source: str
    extents_mm: list[float]
    nominal_grasp: list[list[float]]


class PartList(BaseModel):
    parts: list[PartInfo]
    default: str | None


Vector3 = list[float]


class CameraModel(BaseModel):
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    rotation: list[Vector3] = Field(min_length=3, max_length=3, description="{C} axes in {B}, row-major")
    origin_mm: Vector3 = Field(min_length=3, max_length=3)
    distortion: list[float] = Field(default=[0.0] * 5, min_length=5, max_length=5,
                                    description="lens distortion k1, k2, p1, p2, k3 (OpenCV)")


class PlaneModel(BaseModel):
    normal: Vector3 = Field(min_length=3, max_length=3, description="unit normal")
    offset_mm: float


class MirrorModel(PlaneModel):
    columns: list[int] = Field(min_length=2, max_length=2, description="[c0, c1) of its view")


class CalibrationModel(BaseModel):
    """What the scanner knows of its cell (``scanner_core.calibration.Calibration``)."""

    camera: CameraModel
    light_plane_c: PlaneModel
    mirrors: list[MirrorModel]
    direct_columns: list[int] = Field(min_length=2, max_length=2)
    marker_offset_t_mm: Vector3 = Field(min_length=3, max_length=3)
    version: int = Field(default=2, description="calibration file version (1 or 2)")
    clock_offset_s: float = Field(default=0.0, description="robot clock minus camera clock, s")
    provenance: dict = Field(default={}, description="how it was made: date, cell, models, "
                                                     "residuals, observations")
    marker_offset_std_mm: Vector3 | None = Field(
        None, min_length=3, max_length=3,
        description="standard deviation of marker_offset_t_mm along the {T} axes, mm, as "
                    "flyscan calibrate measured it (0 to 10); every pose's translation "
                    "carries it. Null: not measured")
