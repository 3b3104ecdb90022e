"""Typed request and response bodies of the REST API (they make the OpenAPI schema)."""
from __future__ import annotations

from typing import Annotated, Literal

import numpy as np

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, model_validator

from clients.placement import rigid_transform
from scanner_core.io.rtde import ur_pose_to_matrix

RunState = Literal["idle", "armed", "scanning", "processing", "fault"]
ScanState = Literal["armed", "scanning", "processing", "done", "failed"]


class Problem(BaseModel):
    """An error: the reason, for a person and for the client's exception (a request that does
    not validate lists each field's problem: ``loc``, ``msg``, ``type``)."""

    detail: str | list[dict]


class Health(BaseModel):
    status: Literal["ok"] = "ok"


class CameraClockStatus(BaseModel):
    source: Literal["camera", "host"] = Field(
        description="camera: its timestamps mapped to the host clock; host: the time each "
                    "frame was received (a camera that stamps nothing)")
    offset_s: float | None = Field(None, description="host minus camera clock, s")
    drift_ppm: float | None = Field(None, description="host clock's rate minus the camera's, ppm")


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
    clock: CameraClockStatus | None = Field(
        None, description="how a camera with its own clock (pylon:) is mapped to the host's")


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
    parts: dict | None = Field(None, description="the parts' prepared models: prepared_mb (what "
                               "they hold), budget_mb (prepared_parts_mb), released (parts that "
                               "gave theirs back to stay within it)")


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


def check_reach(taught_mm: np.ndarray, reach_mm: float) -> None:
    """ValueError unless the taught place pose's TCP ((4, 4), mm in the robot base) lies
    within `reach_mm` of the base: a pose no robot can reach is a unit slip (mm given as m)
    or a typing error, and its correction would send the robot there."""
    distance = float(np.linalg.norm(taught_mm[:3, 3]))
    if not distance <= reach_mm:
        raise ValueError(f"taught_place lies {distance / 1e3:.4g} m from the robot base, beyond "
                         f"its reach ({reach_mm / 1e3:g} m, robot_reach_mm): a UR pose is in "
                         f"m and rad, a 4x4 in mm")


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
    # strict: "5" is no number and "yes" no boolean; a client that sends them has a bug
    model_config = ConfigDict(extra="forbid", strict=True)

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
    fault: str | None = Field(
        None, min_length=1, max_length=40, pattern=r"^[a-z]+(:[0-9.eE+-]+)?$",
        description="simulated mode only: what the gripper holds instead of the part, "
                    "KIND[:SIZE_MM] as `flyscan scan --fault` takes it (a double pick, "
                    "debris, a chip, a longer or drilled variant, a bend); the scan is "
                    "registered against the part and inspected")


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
    part_version: str | None = Field(None, description="the content hash of the part's model "
                                     "the scan was armed with, and registered against, "
                                     "whatever replaced the part since")
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
    inspection: dict | None = Field(
        None, description="the cloud against the model at the pose: conforms, or the failing "
                          "kinds (extra_material, missing_material, deformation, wrong_part) "
                          "with their regions; a failing one makes the pose's act false")
    correction: PlaceCorrection | None = Field(
        None, description="with a taught place pose (the request's or the settings') and a "
                          "finished scan: the corrected TCP place pose, or why not to place")


class ScanList(BaseModel):
    scans: list[ScanInfo]


class PartInfo(BaseModel):
    name: str
    version: str = Field(description="the part's content hash (its triangles, unit and nominal "
                                     "grasp): a scan names the version it was registered "
                                     "against")
    units: str
    simplified: dict | None = Field(None, description="a mesh far finer than the scan needs, "
                                    "simplified for registration: faces_from, faces_to, "
                                    "deviation_p99_um, deviation_max_um, kept (whether the "
                                    "simplified model is the part's)")
    faces: int
    source: str
    extents_mm: list[float]
    nominal_grasp: list[list[float]]
    inspection: dict[str, float] | None = Field(
        None, description="the part's own inspection thresholds (extra_mm, deform_mm, "
                          "min_area_mm2), from its upload or its plan, over the service's "
                          "settings; None: the service's, or derived from each scan")


class PartList(BaseModel):
    parts: list[PartInfo]
    default: str | None


# -- the calibration ------------------------------------------------------------------------
# Bounds: what a camera and a cell can be, so that an absurd calibration is refused at the
# edge, naming its field, rather than producing non-finite clouds and reports. The lens's
# optical checks (a rotation that is one, a unit normal, columns that tile the image) are the
# calibration's own (scanner_core.geometry.calibration), after these.

#: The largest image side, pixels (a 150-megapixel sensor is 14 204 wide).
MAX_IMAGE_PX = 20_000
#: Focal length, pixels: a fisheye on a small sensor to a long lens on a large one.
FOCAL_PX = (10.0, 1e6)
#: Any position in the cell, mm: a robot cell is a few metres across.
CELL_MM = 10_000.0
#: The marker (the LED on the gripper) from the TCP, mm, each axis.
MARKER_MM = 1_000.0
#: OpenCV's radial (k1, k2, k3) and tangential (p1, p2) coefficients, each at most this in
#: magnitude: real lenses are under 1, strong fisheyes a few.
MAX_DISTORTION = 10.0
#: Mirrors beside the direct view: the cell has one or two; more than this is no cell.
MAX_MIRRORS = 8
#: Robot clock minus camera clock, s: two clocks counting from 1970 or from a boot differ by
#: less than this (317 years).
MAX_CLOCK_OFFSET_S = 1e10

_strict = ConfigDict(extra="forbid", strict=True)


def _bounded(low: float, high: float, what: str, **extra):
    return Field(ge=low, le=high, allow_inf_nan=False, description=f"{what}; {low:g} to {high:g}",
                 **extra)


Vector3 = list[float]
CellPoint = Annotated[float, Field(ge=-CELL_MM, le=CELL_MM, allow_inf_nan=False)]
UnitComponent = Annotated[float, Field(ge=-1.0, le=1.0, allow_inf_nan=False)]
Column = Annotated[int, Field(ge=0, le=MAX_IMAGE_PX)]


class CameraModel(BaseModel):
    model_config = _strict

    fx: float = _bounded(*FOCAL_PX, "focal length along x, pixels")
    fy: float = _bounded(*FOCAL_PX, "focal length along y, pixels")
    cx: float = _bounded(0.0, MAX_IMAGE_PX, "principal point x, pixels, within the image")
    cy: float = _bounded(0.0, MAX_IMAGE_PX, "principal point y, pixels, within the image")
    width: int = Field(ge=1, le=MAX_IMAGE_PX, description=f"pixels; 1 to {MAX_IMAGE_PX}")
    height: int = Field(ge=1, le=MAX_IMAGE_PX, description=f"pixels; 1 to {MAX_IMAGE_PX}")
    rotation: list[Annotated[list[UnitComponent], Field(min_length=3, max_length=3)]] = Field(
        min_length=3, max_length=3, description="{C} axes in {B}, row-major; each entry -1 to 1")
    origin_mm: list[CellPoint] = Field(min_length=3, max_length=3,
                                       description=f"mm; each -{CELL_MM:g} to {CELL_MM:g}")
    distortion: list[Annotated[float, Field(ge=-MAX_DISTORTION, le=MAX_DISTORTION,
                                            allow_inf_nan=False)]] = Field(
        default=[0.0] * 5, min_length=5, max_length=5,
        description=f"lens distortion k1, k2, p1, p2, k3 (OpenCV); each -{MAX_DISTORTION:g} to "
                    f"{MAX_DISTORTION:g}")

    @model_validator(mode="after")
    def _principal_point_in_image(self):
        if not (self.cx <= self.width and self.cy <= self.height):
            raise ValueError(f"the principal point ({self.cx}, {self.cy}) lies outside the "
                             f"{self.width} x {self.height} image")
        return self


class PlaneModel(BaseModel):
    model_config = _strict

    normal: list[UnitComponent] = Field(min_length=3, max_length=3,
                                        description="unit normal; each entry -1 to 1")
    offset_mm: float = _bounded(-CELL_MM, CELL_MM, "mm")


class MirrorModel(PlaneModel):
    columns: list[Column] = Field(min_length=2, max_length=2,
                                  description=f"[c0, c1) of its view; 0 to {MAX_IMAGE_PX}")


class PlaneUncertaintyModel(BaseModel):
    """``scanner_core.calibration.plane.PlaneUncertainty``: the light plane's covariance."""

    model_config = _strict

    centre_mm: list[CellPoint] = Field(min_length=3, max_length=3,
                                       description="a point of the plane, mm in {B}")
    axes: list[Annotated[list[UnitComponent], Field(min_length=3, max_length=3)]] = Field(
        min_length=2, max_length=2, description="two orthonormal directions in the plane")
    covariance: list[Annotated[list[Annotated[float, Field(ge=-1.0, le=1.0,
                                                           allow_inf_nan=False)]],
                               Field(min_length=3, max_length=3)]] = Field(
        min_length=3, max_length=3, description="of (tilt along axes[0], tilt along axes[1] "
                                                "in rad, shift along the normal in mm); each "
                                                "entry -1 to 1")


class CalibrationModel(BaseModel):
    """What the scanner knows of its cell (``scanner_core.geometry.calibration.Calibration``): every
    field required but those with a default, none other allowed, each value within what a
    camera and a cell can be (its description says the bounds)."""

    model_config = _strict

    camera: CameraModel
    light_plane_c: PlaneModel
    mirrors: list[MirrorModel] = Field(min_length=1, max_length=MAX_MIRRORS,
                                       description=f"1 to {MAX_MIRRORS} mirrors")
    direct_columns: list[Column] = Field(min_length=2, max_length=2,
                                         description=f"[c0, c1); 0 to {MAX_IMAGE_PX}")
    marker_offset_t_mm: list[Annotated[float, Field(ge=-MARKER_MM, le=MARKER_MM,
                                                    allow_inf_nan=False)]] = Field(
        min_length=3, max_length=3, description=f"the marker in {{T}}, mm; each -{MARKER_MM:g} "
                                                f"to {MARKER_MM:g}")
    version: Literal[1, 2] = Field(default=2, description="calibration file version (1 or 2)")
    clock_offset_s: float = _bounded(-MAX_CLOCK_OFFSET_S, MAX_CLOCK_OFFSET_S,
                                     "robot clock minus camera clock, s", default=0.0)
    provenance: dict = Field(default={}, description="how it was made: date, cell, models, "
                                                     "residuals, observations")
    marker_offset_std_mm: Vector3 | None = Field(
        None, min_length=3, max_length=3,
        description="standard deviation of marker_offset_t_mm along the {T} axes, mm, as "
                    "flyscan calibrate measured it (0 to 10); every pose's translation "
                    "carries it. Null: not measured")
    light_plane_uncertainty_b: PlaneUncertaintyModel | None = Field(
        None, description="how well flyscan calibrate fixed the light plane, in {B}: the "
                          "covariance of its tilts along `axes` and its shift along its normal "
                          "at `centre_mm`; every pose carries it. Null: not measured")


# -- calibration sessions and history ----------------------------------------------

#: A rotation vector, rad (UR's convention): each component within 2 pi.
RotationVector = Annotated[list[Annotated[float, Field(ge=-6.3, le=6.3, allow_inf_nan=False)]],
                           Field(min_length=3, max_length=3)]
#: A point in the cell, mm.
Point3 = Annotated[list[CellPoint], Field(min_length=3, max_length=3)]


class PlanRequest(BaseModel):
    """A calibration session's plan, generated for the cell (``scanner_core.calibration.plan``). In the
    simulated cell every geometry field defaults to the cell's; with a real cell the pass and
    the sphere's holder must be given."""

    model_config = _strict

    led_count: int = Field(200, ge=12, le=2000, description="LED poses")
    sphere_count: int = Field(40, ge=3, le=500, description="sphere poses")
    tilt_deg: float = Field(20.0, gt=0, le=30, description="how far the turned LED poses turn "
                                                          "the tool, degrees")
    tilted_fraction: float = Field(0.5, ge=0, le=1, description="share of turned LED poses")
    seed: int = Field(0, ge=0, le=2**31 - 1)
    tcp_rotation: RotationVector | None = Field(
        None, description="the tool's orientation in a pass: a UR rotation vector, rad")
    pass_start_y_mm: float | None = _bounded(-5000, 5000, "the pass's start along y of the "
                                             "robot base, mm", default=None)
    pass_end_y_mm: float | None = _bounded(-5000, 5000, "the pass's end, mm", default=None)
    pass_height_mm: float | None = _bounded(-5000, 5000, "the TCP's height in a pass, mm",
                                            default=None)
    sphere_offset_t_mm: Point3 | None = Field(
        None, description="the sphere's centre in {T}, mm (its holder as drawn, or measured "
                          "with the robot's TCP wizard)")
    sphere_radius_mm: float = _bounded(1.0, 200.0, "the sphere's radius, mm", default=28.625)


class CalibrationSessionInfo(BaseModel):
    session_id: str
    state: Literal["recording", "recording pass", "ready to fit", "fitting", "fitted", "failed"]
    steps: int = Field(description="poses in the plan")
    captured: int = Field(description="poses captured")
    pass_scan_id: str | None = None
    pass_state: Literal["not recorded", "recording", "done", "failed"] = "not recorded"
    version: int | None = Field(None, description="the calibration version the fit made")
    figures: dict | None = Field(None, description="the fit's residuals")
    error: str | None = None
    plan: dict | None = Field(None, description="the plan: every TCP pose in UR's convention "
                                                "[x, y, z (m), rx, ry, rz (rad)]")


class StepCaptured(BaseModel):
    index: int
    kind: Literal["led", "sphere"]
    image: str
    tcp: list[float] = Field(description="the TCP pose the robot reported, UR convention")
    samples: int = Field(description="robot reports averaged")
    off_plan_mm: float = Field(description="reported minus planned TCP position, mm")
    off_plan_deg: float = Field(description="reported minus planned orientation, degrees")


class CalibrationVersion(BaseModel):
    version: int
    created: str
    source: str
    active: bool
    figures: dict = Field(default_factory=dict)
    has_report: bool = False


class CalibrationVersionDetail(CalibrationVersion):
    calibration: CalibrationModel
    report: dict | None = None


class CalibrationHistoryList(BaseModel):
    versions: list[CalibrationVersion]
    active: int | None
