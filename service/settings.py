"""The service's settings: one class, from a TOML file, the environment (``FLYSCAN_*``) and the
command line, in rising priority. Secrets (the bearer token) are never defaulted."""
from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import (BaseSettings, InitSettingsSource, PydanticBaseSettingsSource,
                               SettingsConfigDict)

from service.models import (TAUGHT_PLACE_DESCRIPTION, TaughtPlace, check_reach,
                            taught_place_matrix)


class Settings(BaseSettings):
    """Everything ``flyscan serve`` can be told.

    Attributes
    ----------
    host, port : str, int
        REST bind address; 127.0.0.1 unless told otherwise.
    zmq : str
        ZeroMQ PUB endpoint for clouds, edges, poses and status.
    data : Path
        Where scans and uploaded parts are stored.
    token : SecretStr or None
        When set, mutating endpoints require ``Authorization: Bearer <token>``.
    protect_reads : bool
        The reads too (scans, parts, status, calibration, metrics), for a cell whose network
        is shared; needs ``token``. Health, the status page's shell and the API's docs stay open.
    max_body_bytes, max_part_bytes : int
        The largest request body, bytes: JSON requests, and mesh uploads (``PUT /parts``).
    """

    model_config = SettingsConfigDict(env_prefix="FLYSCAN_", extra="forbid")

    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    zmq: str = "tcp://127.0.0.1:5556"
    zmq_hwm: int = Field(100, ge=1, description="ZeroMQ send high-water mark, messages")
    robot: str | None = Field(None, description="ur://HOST for a UR robot (ur-rtde); in a "
                                                "simulated cell an RTDE emulator is started at "
                                                "HOST")
    camera: str | None = Field(None, description="opencv:0, video:FILE, gstreamer:PIPELINE, "
                                                 "genicam:PRODUCER.cti[#SERIAL], "
                                                 "pylon:[SERIAL][?options], replay:FOLDER")
    data: Path = Path("flyscan-data")
    token: SecretStr | None = None
    protect_reads: bool = Field(False, description="the reads need the token too (needs token)")
    # Limits at the edge (service.edge): a JSON request is a few kB (a calibration with its
    # provenance, tens); a bin-picking part's mesh, a few MB.
    max_body_bytes: int = Field(1 << 20, ge=1024, le=1 << 30,
                                description="largest JSON request body, bytes (413 beyond)")
    max_part_bytes: int = Field(64 << 20, ge=1024, le=1 << 30,
                                description="largest mesh upload, bytes (413 beyond)")
    trusted_origins: list[str] = Field(
        default_factory=list,
        description="origins (scheme://host:port) besides the service's own whose pages may "
                    "send it writes; any other Origin or Referer on a write is refused (403)")
    header_timeout_s: float = Field(10.0, gt=0.0, le=600.0,
                                    description="a connection that sends no whole request head "
                                                "this long after opening or after its last "
                                                "answer is closed, s")
    max_connections: int | None = Field(None, ge=16, le=1_000_000,
                                        description="connections served at once; beyond, the "
                                                    "one idle longest is closed (default: the "
                                                    "open-file limit less the files open at "
                                                    "start and 256, at most 4096)")
    max_concurrent_bodies: int = Field(2, ge=1, le=64,
                                       description="request bodies read at once (503 beyond)")
    body_idle_s: float = Field(10.0, gt=0.0, le=600.0,
                               description="a request body whose next piece takes longer is "
                                           "answered 408, s")
    body_rate_in_pass_mb_s: float = Field(32.0, gt=0.0, le=100_000.0,
                                          description="while a scan is armed or its pass "
                                                      "runs, request bodies are read at most "
                                                      "this fast, MB/s (the sender waits; "
                                                      "the camera's frames come first)")
    max_pending_pictures: int = Field(4, ge=1, le=64,
                                      description="requests waiting at once for a scan's preview "
                                                  "to be drawn (503 beyond)")
    read_interval_s: float = Field(0.05, ge=0.0, le=10.0,
                                   description="least time between two answers to reads on one "
                                               "connection, s (0: none); reads with the token "
                                               "and /health are not paced")
    max_reads_per_s: float = Field(100.0, ge=1.0, le=100_000.0,
                                   description="reads answered per second, all connections "
                                               "together; beyond, a read waits its turn (503 "
                                               "when that is over 2 s)")
    max_event_streams: int = Field(16, ge=1, le=1024,
                                   description="status pages' event streams open at once (503 "
                                               "beyond)")
    prepared_parts_mb: float = Field(1024.0, ge=0.0, le=1e6,
                                     description="memory the parts' prepared models (surface "
                                                 "and edge models, trees, tables) may hold, "
                                                 "MB; past it, the least recently scanned give "
                                                 "theirs back")
    max_parts: int = Field(100, ge=1, le=10_000,
                           description="uploaded parts kept, at most (507 beyond)")
    calibration: Path | None = Field(None, description="calibration JSON; default the reference cell's")
    workers: int = Field(2, ge=1, le=16, description="frame-processing threads")
    queue_frames: int = Field(64, ge=1, description="frames waiting for a worker, at most")
    max_pass_s: float = Field(10.0, gt=0, description="a longer pass ends as 'too long'")
    arm_timeout_s: float = Field(10.0, gt=0, description="an armed scan with no marker fails")
    gap_frames: int = Field(3, ge=1, description="frames without the marker that end a pass")
    pose_ahead_frames: int = Field(
        4, ge=0, le=1000, description="frames without a point after which the part has left "
        "the sheet: the scan is assembled and its pose computed while the pass goes on, and "
        "kept when the pass adds nothing they read (scanner_core.pose.ahead); 0: at the "
        "pass's end only")
    camera_timeout_s: float = Field(1.0, gt=0, description="no frame this long: the camera stopped")
    retention: int = Field(200, ge=1, description="scans kept on disk; the oldest go first")
    recordings_kept: int = Field(5, ge=1, description="recorded passes kept (2.3 MB a frame)")
    disk_reserve_mb: float = Field(256.0, ge=0.0, le=1e6,
                                   description="free space kept for the scans' own files: a "
                                               "recording stops before it, and an arm that "
                                               "records with less than it and a second of "
                                               "frames free is refused (507), MB")
    stripe_method: Literal["cog", "gaussian3", "parabola", "blais_rioux", "lsq_gauss"] = "cog"
    stripe_signal: Literal["auto", "mono", "red", "green", "blue", "red_excess", "green_excess",
                           "blue_excess", "colour_excess"] = Field(
        "auto", description="what the stripe is looked for in: a mono frame as it is; a colour "
                            "frame's (or a Bayer mosaic's) largest colour excess (auto), one "
                            "channel, or one colour's excess v_k - (v_i + v_j) / 2")
    bayer: Literal["RGGB", "BGGR", "GRBG", "GBRG"] | None = Field(
        None, description="the camera's frames are raw Bayer mosaics of this pattern")
    exposure_mode: Literal["fixed", "dynamic", "multiple"] = Field(
        "fixed", description="fixed; dynamic: steered from the previous frames' stripe peaks; "
                             "multiple: two exposures alternating, the better exposed column "
                             "of each pair kept (a camera without exposure control: fixed)")
    exposure_target_dn: float = Field(180.0, gt=0, lt=255,
                                      description="dynamic: the stripe peak aimed at, DN above "
                                                  "the background")
    exposure_ratio: float = Field(8.0, gt=1, le=1000,
                                  description="multiple: the long exposure over the short one")
    default_part: str | None = Field(None, description="part used when a scan names none")
    clock_offset_s: float = Field(0.0, description="robot minus camera clock, s, until estimated")
    cross_check_tolerance_mm: float = Field(0.1, gt=0)
    act_tolerance_mm: float = Field(
        0.1, gt=0, le=100, description="the placement tolerance, mm: a pose is acted on "
        "(pose.act) only when every translation's 3 sigma lies within it")
    act_tolerance_deg: float = Field(
        0.1, gt=0, le=180, description="the placement tolerance, degrees: as act_tolerance_mm "
        "for rotations")
    robot_rotation_std_deg: float = Field(
        0.005, ge=0, le=1, description="how far off the robot reports its orientation (its "
        "accuracy), degrees: it turns every profile alike, so every pose's rotations carry it")
    inspect_extra_mm: float | None = Field(
        None, gt=0, le=100, description="the inspection: points farther off the model than this "
        "are extra or missing material, mm; unset: from each scan's noise "
        "(scanner_core.inspection)")
    inspect_deform_mm: float | None = Field(
        None, gt=0, le=100, description="the inspection: a region off the model by more than "
        "this is deformed, mm; unset: from each scan's noise")
    inspect_min_area_mm2: float | None = Field(
        None, gt=0, le=1e5, description="the inspection: a failing region's area at least, "
        "mm^2; unset: from each scan's sampling")
    led_correction_t_mm: tuple[float, float, float] | None = Field(
        None, description="marker minus robot track in {T}, mm, what the calibration's LED "
                          "offset misses; unset: learned from the first cross-checked pass")
    taught_place: TaughtPlace | None = Field(
        None, description=TAUGHT_PLACE_DESCRIPTION + "; used when a scan's request gives none")
    robot_reach_mm: float = Field(2000.0, gt=0.0, le=10_000.0,
                                  description="a taught place pose farther than this from the "
                                              "robot base is refused (422), mm")
    @field_validator("token", mode="before")
    @classmethod
    def _empty_token_is_none(cls, value):
        return None if value == "" else value

    @model_validator(mode="after")
    def _reads_need_a_token(self):
        if self.protect_reads and self.token is None:
            raise ValueError("protect_reads needs a token")
        return self

    @model_validator(mode="after")
    def _taught_place_within_reach(self):
        if self.taught_place is not None:
            check_reach(taught_place_matrix(self.taught_place), self.robot_reach_mm)
        return self

    @field_validator("zmq")
    @classmethod
    def _zmq_endpoint(cls, value: str) -> str:
        if "://" not in value:
            raise ValueError(f"must be a ZeroMQ endpoint such as tcp://127.0.0.1:5556, got {value!r}")
        return value

    @classmethod
    def settings_customise_sources(cls, settings_cls: type[BaseSettings],
                                   init_settings: PydanticBaseSettingsSource,
                                   env_settings: PydanticBaseSettingsSource,
                                   dotenv_settings: PydanticBaseSettingsSource,
                                   file_secret_settings: PydanticBaseSettingsSource):
        return init_settings, env_settings, file_secret_settings


def read_settings_file(config: Path) -> dict:
    """The settings of a TOML file, as read (FileNotFoundError, tomllib.TOMLDecodeError)."""
    config = Path(config)
    if not config.is_file():
        raise FileNotFoundError(f"settings file not found: {config}")
    with config.open("rb") as f:
        return tomllib.load(f)


def load_settings(config: Path | dict | None = None, **overrides) -> Settings:
    """Settings from ``config`` (a TOML file, or its settings already read), the environment
    and ``overrides``, in rising priority (None values are left out, so that an option not
    given on the command line does not hide the file's)."""
    overrides = {k: v for k, v in overrides.items() if v is not None}
    data = read_settings_file(config) if isinstance(config, (str, Path)) else dict(config or {})

    class FileSettings(Settings):
        @classmethod
        def settings_customise_sources(cls, settings_cls, init_settings, env_settings,
                                       dotenv_settings, file_secret_settings):
            return (init_settings, env_settings, InitSettingsSource(settings_cls, data),
                    file_secret_settings)

    return FileSettings(**overrides)
