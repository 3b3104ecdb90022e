"""The calibration session folder: what ``flyscan calibrate --session DIR`` reads, what
``flyscan calibrate --write-session`` and the service's calibration sessions write.

Session folder (``flyscan calibrate --session DIR``; ``write_session`` writes one)
------------------------------------------------------------------------------------
``session.json``
    ``{"format": "flyscan-calibration-session", "version": 2, "image": {"width": W,
    "height": H, "fps": F}, "sphere_radius_mm": R, "cell": "name",
    "nominal": {...}}`` where ``nominal`` is a calibration object (the design the installer
    knows: the view strips and the LED's offset as built; its geometry is only a label).
    A session recorded with the robot adds ``"sphere_offset_t_mm": [x, y, z]`` (the sphere's
    centre in {T}) and ``"plan"`` (the plan it followed, ``scanner_core.calibration.plan``). Version 1
    folders (a stage's, without these) read as before.
``led.csv``
    Header ``image,x_mm,y_mm,z_mm``: one line per stage position of the LED in {B}, the image a
    file name in ``led/`` (8-bit greyscale PNG, W x H). Or, recorded with the robot, header
    ``image,x_m,y_m,z_m,rx_rad,ry_rad,rz_rad,samples``: the TCP pose the robot reported while
    the frame was taken, in UR's convention (the base frame, metres, a rotation vector), the
    mean of ``samples`` reports.
``sphere.csv``
    The same for the sphere's centre (or the TCP holding it), images in ``sphere/``.
``pass/`` (optional)
    A recording of a pass of the robot (``scanner_core.recording``'s format): the clocks and the LED's
    offset are estimated from it; without it the nominal LED offset and a zero clock offset
    are kept.
"""
from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from scanner_core.geometry.calibration import Calibration, CalibrationError

SESSION_FORMAT = "flyscan-calibration-session"
SESSION_VERSION = 2
#: The versions this flyscan reads.
SESSION_VERSIONS = (1, 2)
#: The two headers of led.csv and sphere.csv: a stage's positions, the robot's TCP poses.
STAGE_HEADER = ["image", "x_mm", "y_mm", "z_mm"]
ROBOT_HEADER = ["image", "x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad", "samples"]


class SessionError(ValueError):
    """A session folder that cannot be read: the message names the file and the field."""


@dataclass
class Session:
    """What a calibration session gave: frames, the stage's positions, the robot's pass.

    ``led_images`` and ``sphere_images`` are called once each and yield (H, W) uint8 frames in
    the order of their positions; ``pass_devices`` returns a (camera, robot) pair.

    A session recorded with the robot (``flyscan serve``'s calibration sessions) also has
    ``led_tcp_b`` (N, 4, 4) float64, the TCP poses ^B X_T (mm) the robot reported at the LED's
    positions: ``led_positions_b`` are then the nominal LED offset's, and the LED's offset is
    fitted (``scanner_core.calibration.ledpivot``); its sphere centres are the TCP poses ``sphere_tcp_b`` times
    ``sphere_offset_t_mm`` (3,), and ``plan`` is the plan it followed.
    """

    width: int
    height: int
    fps: float
    sphere_radius_mm: float
    nominal: Calibration
    led_positions_b: np.ndarray
    led_images: Callable[[], Iterable[np.ndarray]]
    sphere_centres_b: np.ndarray
    sphere_images: Callable[[], Iterable[np.ndarray]]
    pass_devices: Callable[[], tuple] | None = None
    cell_name: str = ""
    led_tcp_b: np.ndarray | None = None
    sphere_tcp_b: np.ndarray | None = None
    sphere_offset_t_mm: np.ndarray | None = None
    plan: dict | None = None


# ---------------------------------------------------------------------------------------------
# session folders


class SessionWriter:
    """Writes a session folder one frame at a time (the service records a session so, as the
    robot reaches each pose; :func:`write_session` writes a whole :class:`Session` with it).

    ``add(kind, image, ...)`` with either ``position_b`` (a stage's, mm) or ``tcp_b`` (the
    robot's reported ^B X_T, mm, and how many reports it is the mean of); one folder holds one
    kind of position. Rows reach the CSV files as they are added, so a session cut short keeps
    what it had. ``pass_folder`` is where the pass's recording goes.
    """

    def __init__(self, folder, *, width: int, height: int, fps: float, sphere_radius_mm: float,
                 nominal: Calibration, cell_name: str = "", sphere_offset_t_mm=None,
                 plan: dict | None = None):
        self.folder = Path(folder)
        if self.folder.exists():
            raise SessionError(f"{self.folder} exists already")
        self.robot = sphere_offset_t_mm is not None
        for kind in ("led", "sphere"):
            (self.folder / kind).mkdir(parents=True)
        meta = {"format": SESSION_FORMAT, "version": SESSION_VERSION if self.robot else 1,
                "image": {"width": int(width), "height": int(height), "fps": float(fps)},
                "sphere_radius_mm": float(sphere_radius_mm), "cell": cell_name,
                "nominal": nominal.to_dict()}
        if self.robot:
            meta["sphere_offset_t_mm"] = [float(v) for v in sphere_offset_t_mm]
            meta["plan"] = plan
        (self.folder / "session.json").write_text(json.dumps(meta, indent=1))
        self.counts = {"led": 0, "sphere": 0}
        for kind in ("led", "sphere"):
            with open(self.folder / f"{kind}.csv", "w", newline="") as f:
                csv.writer(f).writerow(ROBOT_HEADER if self.robot else STAGE_HEADER)

    @classmethod
    def reopen(cls, folder) -> "SessionWriter":
        """The writer of a folder written before (a service restarted mid-session): what it
        adds goes after the rows there. SessionError when it is no session folder."""
        folder = Path(folder)
        try:
            meta = json.loads((folder / "session.json").read_text())
            counts = {}
            for kind in ("led", "sphere"):
                with open(folder / f"{kind}.csv", newline="") as f:
                    counts[kind] = max(sum(1 for row in csv.reader(f) if row) - 1, 0)
        except (OSError, ValueError) as exc:
            raise SessionError(f"{folder} is no session folder: {exc}") from None
        writer = cls.__new__(cls)
        writer.folder, writer.robot, writer.counts = folder, "sphere_offset_t_mm" in meta, counts
        return writer

    @property
    def pass_folder(self) -> Path:
        return self.folder / "pass"

    def add(self, kind: str, image: np.ndarray, *, position_b=None, tcp_b=None,
            samples: int = 1) -> str:
        """One frame (H, W) uint8 and where it was taken; returns the image's file name."""
        import cv2

        if kind not in self.counts:
            raise ValueError(f"`kind` must be led or sphere, got {kind!r}")
        if (tcp_b is not None) != self.robot or (position_b is not None) == self.robot:
            raise ValueError("give tcp_b in a session recorded with the robot, position_b in "
                             "a stage's")
        name = f"{self.counts[kind]:06d}.png"
        if not cv2.imwrite(str(self.folder / kind / name), image):
            raise OSError(f"could not write {self.folder / kind / name}")
        if self.robot:
            from scanner_core.io.rtde import matrix_to_ur_pose

            row = [name] + [repr(float(v)) for v in matrix_to_ur_pose(tcp_b)] + [int(samples)]
        else:
            row = [name] + [repr(float(v)) for v in position_b]
        # Opened for each row: a session left unfinished holds no file open.
        with open(self.folder / f"{kind}.csv", "a", newline="") as f:
            csv.writer(f).writerow(row)
        self.counts[kind] += 1
        return name

    def close(self) -> None:
        """Nothing is held open (kept for ``with``)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def write_session(folder, session: Session) -> None:
    """Write ``session`` as a folder (module docstring), its pass (if any) as a recording in
    ``pass/`` (raw frames: about 2.3 MB per 1920 x 1200 frame)."""
    robot = session.led_tcp_b is not None
    with SessionWriter(folder, width=session.width, height=session.height, fps=session.fps,
                       sphere_radius_mm=session.sphere_radius_mm, nominal=session.nominal,
                       cell_name=session.cell_name, plan=session.plan,
                       sphere_offset_t_mm=session.sphere_offset_t_mm if robot else None) as w:
        for kind, where, images in (
                ("led", session.led_tcp_b if robot else session.led_positions_b,
                 session.led_images),
                ("sphere", session.sphere_tcp_b if robot else session.sphere_centres_b,
                 session.sphere_images)):
            for p, img in zip(where, images()):
                w.add(kind, img, **({"tcp_b": p} if robot else {"position_b": p}))
    if session.pass_devices is not None:
        _record_pass(Path(folder) / "pass", session)


def _record_pass(folder: Path, session: Session) -> None:
    """The session's pass as a recording: every frame, and the robot's samples it still holds."""
    from scanner_core.devices import CameraClosed
    from scanner_core.recording import ROBOT_SAMPLE_HZ, robot_samples
    from scanner_core.recording import PassRecorder

    camera, robot = session.pass_devices()
    camera.open()
    robot.connect()
    try:
        with PassRecorder(folder, width=session.width, height=session.height, fps=session.fps,
                          calibration=session.nominal,
                          notes="calibration pass (flyscan calibrate)") as recorder:
            while True:
                try:
                    recorder.add_frame(camera.grab(1.0))
                except CameraClosed:
                    break
            newest = robot.latest().t
            recorder.add_robot_poses(robot_samples(robot, newest - 10.0 + 1.0 / ROBOT_SAMPLE_HZ,
                                                    newest))
    finally:
        camera.close()
        robot.disconnect()


def load_session(folder) -> Session:
    """Read a session folder; SessionError naming the file and field that is wrong."""
    import cv2

    folder = Path(folder)
    meta_path = folder / "session.json"
    try:
        meta = json.loads(meta_path.read_text())
    except FileNotFoundError:
        raise SessionError(f"{meta_path} not found: not a calibration session folder") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SessionError(f"{meta_path} is not valid JSON: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format") != SESSION_FORMAT:
        raise SessionError(f"{meta_path}: `format` must be {SESSION_FORMAT!r}")
    if meta.get("version") not in SESSION_VERSIONS:
        raise SessionError(f"{meta_path}: session version {meta.get('version')!r} is not one "
                           f"this flyscan reads ({', '.join(map(str, SESSION_VERSIONS))})")
    try:
        width, height = int(meta["image"]["width"]), int(meta["image"]["height"])
        fps = float(meta["image"]["fps"])
        radius = float(meta["sphere_radius_mm"])
        nominal = Calibration.from_dict(meta["nominal"])
        sphere_t = meta.get("sphere_offset_t_mm")
        if sphere_t is not None:
            sphere_t = np.array(sphere_t, dtype=np.float64).reshape(3)
    except (KeyError, TypeError, ValueError) as exc:
        raise SessionError(f"{meta_path}: missing or malformed field {exc}") from None
    if not radius > 0:
        raise SessionError(f"{meta_path}: `sphere_radius_mm` must be positive, got {radius}")

    def table(kind):
        """(positions (N, 3) mm, TCP poses (N, 4, 4) mm or None, images)."""
        path = folder / f"{kind}.csv"
        try:
            with open(path, newline="") as f:
                rows = list(csv.reader(f))
        except FileNotFoundError:
            raise SessionError(f"{path} not found") from None
        robot = bool(rows) and rows[0] == ROBOT_HEADER
        if not rows or (rows[0] != STAGE_HEADER and not robot):
            raise SessionError(f"{path}: the header must be {','.join(STAGE_HEADER)} (a stage's "
                               f"positions) or {','.join(ROBOT_HEADER)} (the robot's TCP)")
        if robot and sphere_t is None:
            raise SessionError(f"{meta_path}: `sphere_offset_t_mm` is needed with the robot's "
                               f"poses in {path.name}")
        try:
            names = [r[0] for r in rows[1:]]
            values = np.array([[float(v) for v in r[1:7 if robot else 4]] for r in rows[1:]])
            values = values.reshape(-1, 6 if robot else 3)
        except (ValueError, IndexError) as exc:
            raise SessionError(f"{path}: {exc}") from None
        if not np.isfinite(values).all():
            raise SessionError(f"{path}: positions must be finite numbers")
        tcp = None
        positions = values
        if robot:
            from scanner_core.io.rtde import ur_pose_to_matrix

            tcp = np.array([ur_pose_to_matrix(v) for v in values]).reshape(-1, 4, 4)
            offset = sphere_t if kind == "sphere" else nominal.marker_offset_t
            positions = tcp[:, :3, 3] + tcp[:, :3, :3] @ np.asarray(offset)

        def images():
            for name in names:
                img = cv2.imread(str(folder / kind / name), cv2.IMREAD_UNCHANGED)
                if img is None or img.shape != (height, width) or img.dtype != np.uint8:
                    raise SessionError(f"{folder / kind / name}: not an 8-bit {width} x {height} "
                                       f"greyscale image")
                yield img
        return positions, tcp, images

    led, led_tcp, led_images = table("led")
    sphere, sphere_tcp, sphere_images = table("sphere")
    pass_devices = None
    if (folder / "pass").is_dir():
        from scanner_core.recording import load_recording
        from scanner_core.recording.replay import ReplayCamera, ReplayRobot

        recording = load_recording(folder / "pass")

        def pass_devices():
            return ReplayCamera(recording), ReplayRobot.of(recording)
    try:
        nominal.check_image_size(width, height)
    except CalibrationError as exc:
        raise SessionError(f"{meta_path}: nominal calibration: {exc}") from None
    return Session(width, height, fps, radius, nominal, led, led_images, sphere, sphere_images,
                   pass_devices, str(meta.get("cell", "")), led_tcp, sphere_tcp,
                   sphere_t if led_tcp is not None else None, meta.get("plan"))
