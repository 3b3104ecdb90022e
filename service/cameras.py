"""Real camera backends behind ``scanner_core.devices.Camera``.

- :class:`OpenCVCamera`: ``cv2.VideoCapture`` on a V4L2 device (index or ``/dev/videoN``), a
  GStreamer pipeline (only with an OpenCV built with GStreamer; the PyPI wheels are not), or a
  video file.
- :class:`GenICamCamera`: a GenICam camera through harvesters (the optional extra
  ``pip install 'flyscan[genicam]'``) and the GenTL producer (.cti) of the camera's vendor.
- ``service.pylon_camera.PylonCamera``: a Basler camera through pypylon (the optional extra
  ``pip install 'flyscan[pylon]'``), tested against Basler's own camera emulator.
- replay of a recorded pass: ``scanner_core.recording`` (``Recording.camera()``).

:func:`open_camera` turns the camera spec of the settings into one of them.

Like every device, constructing one does no I/O (except ``replay:``, see
:func:`open_camera`); ``open`` does. None of them is thread-safe: one thread opens, grabs and
closes (the service's acquisition thread); ``cv2.VideoCapture`` and a harvesters
``ImageAcquirer`` are not meant to be read from several threads either.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from scanner_core.devices import Camera, CameraClosed, CameraTimeout
from scanner_core.types import Frame
from service.camera_errors import CameraError


#: The accepted forms of a camera spec (:func:`open_camera`).
CAMERA_SPEC_FORMS = (
    "opencv:<index>            a V4L2 device by index, e.g. opencv:0",
    "opencv:/dev/videoN        a V4L2 device by path",
    "video:<file>              a video file (frame ids = frame index, t = index / fps)",
    "gstreamer:<pipeline>      a GStreamer pipeline ending in appsink",
    "genicam:<producer.cti>[#serial]  a GenICam camera through harvesters",
    "pylon:[serial][?option=value&...]  a Basler camera through pypylon (options: width, "
    "height, offset_x, offset_y, exposure_us, gain_db, fps, trigger, images)",
    "replay:<folder>           a pass recorded by scanner_core.recording",
)


def _to_mono(image: np.ndarray, source: str) -> np.ndarray:
    """A decoded image -> (H, W) uint8 mono.

    OpenCV decodes most video to BGR even when it was written grey; the three channels are
    then equal and ``COLOR_BGR2GRAY`` gives them back exactly (its fixed-point weights sum
    to one), so a lossless grey video round-trips bit for bit.
    """
    if image.dtype != np.uint8:
        raise CameraError(f"{source} gives {image.dtype} pixels; the scanner needs 8-bit mono")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        import cv2
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        import cv2
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    raise CameraError(f"{source} gives images of shape {image.shape}; expected (H, W) or (H, W, 1|3|4)")


class OpenCVCamera:
    """A camera read through ``cv2.VideoCapture``.

    Parameters
    ----------
    source : int or str
        A device index (V4L2 on Linux), a device path (``/dev/video0``), a GStreamer
        pipeline, or a video file path.
    fps : float, optional
        The frame rate, frames/s. When given it is the camera's rate (and is requested from a
        live device); otherwise ``CAP_PROP_FPS`` is used. A source that reports none (zero)
        without ``fps`` is refused by :meth:`open` rather than guessed: a file's clock is
        ``index / fps``.
    kind : {"device", "gstreamer", "file"}, optional
        What ``source`` is; guessed when None: an int or ``/dev/...`` is a device, a string
        with ``!`` a GStreamer pipeline, anything else a file.

    Attributes
    ----------
    width, height : int
        Image size, px; known after :meth:`open`.
    fps : float
        Frames/s; known after :meth:`open` (the ``fps`` argument before).

    Notes
    -----
    Frames (:meth:`grab`): ``image`` (H, W) uint8 (colour converted to grey). From a file,
    ``frame_id`` is the frame index (``CAP_PROP_POS_FRAMES`` before the read) and ``t`` the
    file clock ``index / fps``, s; the end of the file raises ``CameraClosed``. From a live
    source, ``frame_id`` counts the frames read (OpenCV does not expose the driver's sequence
    number, so drops inside the driver are not seen) and ``t`` is the capture timestamp
    ``CAP_PROP_POS_MSEC`` when the backend gives one (V4L2 does: the buffer's timestamp),
    ``time.monotonic()`` otherwise; the choice is made on the first frame and kept for the
    stream, since mixing the two clocks would corrupt the times. A failed live read raises
    ``CameraTimeout``; the read itself blocks in OpenCV, bounded by ``timeout`` only where the
    backend honours ``CAP_PROP_READ_TIMEOUT_MSEC``.

    Not thread-safe: open, grab and close from one thread.
    """

    KINDS = ("device", "gstreamer", "file")

    def __init__(self, source: int | str, *, fps: float | None = None, kind: str | None = None):
        if kind is None:
            if isinstance(source, int):
                kind = "device"
            elif str(source).startswith("/dev/"):
                kind = "device"
            elif "!" in str(source):
                kind = "gstreamer"
            else:
                kind = "file"
        if kind not in self.KINDS:
            raise ValueError(f"kind must be one of {self.KINDS}, got {kind!r}")
        if fps is not None and not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be a positive number, got {fps!r}")
        self.source = source
        self.kind = kind
        self.width = 0
        self.height = 0
        self.fps = float(fps) if fps is not None else 0.0
        self._fps_argument = fps
        self._capture = None
        self._count = 0
        self._use_pos_msec: bool | None = None
        self._read_timeout_ms: int | None = None

    @property
    def live(self) -> bool:
        """A device or pipeline (not a file)."""
        return self.kind != "file"

    def __repr__(self) -> str:
        return f"OpenCVCamera({self.source!r}, kind={self.kind!r})"

    @property
    def description(self) -> str:
        return {"device": "video device", "gstreamer": "GStreamer pipeline",
                "file": "video file"}[self.kind] + f" {self.source!r}"

    def open(self) -> None:
        import cv2

        if self._capture is not None:
            return
        if self.kind == "file" and not Path(self.source).is_file():
            raise CameraError(f"cannot open {self.description}: no such file")
        if self.kind == "gstreamer":
            from cv2 import videoio_registry
            if not videoio_registry.hasBackend(cv2.CAP_GSTREAMER):
                raise CameraError(
                    f"cannot open {self.description}: this OpenCV was built without GStreamer "
                    "(the opencv-python wheels are); use a build with GStreamer, or the device "
                    "through opencv:<index>")
            capture = cv2.VideoCapture(str(self.source), cv2.CAP_GSTREAMER)
        elif self.kind == "device" and isinstance(self.source, int):
            capture = cv2.VideoCapture(self.source)
        else:
            capture = cv2.VideoCapture(str(self.source))
        if not capture.isOpened():
            capture.release()
            raise CameraError(f"cannot open {self.description}")
        try:
            if self.live and self._fps_argument is not None:
                capture.set(cv2.CAP_PROP_FPS, float(self._fps_argument))  # a request; may be ignored
            width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
            height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
            if width <= 0 or height <= 0:
                raise CameraError(f"{self.description} reports no image size")
            reported = capture.get(cv2.CAP_PROP_FPS)
            fps = self._fps_argument
            if fps is None:
                if not (math.isfinite(reported) and reported > 0):
                    raise CameraError(
                        f"{self.description} reports no frame rate; pass fps= (a file's clock "
                        "is frame index / fps)")
                fps = reported
        except BaseException:
            capture.release()
            raise
        self.width, self.height, self.fps = width, height, float(fps)
        self._capture = capture
        self._count = 0
        self._use_pos_msec = None
        self._read_timeout_ms = None

    def close(self) -> None:
        if self._capture is not None:
            self._capture.release()
            self._capture = None

    def _set_read_timeout(self, timeout: float) -> None:
        """Ask the backend to give up a read after ``timeout`` (best effort)."""
        import cv2

        ms = max(1, int(round(timeout * 1e3)))
        prop = getattr(cv2, "CAP_PROP_READ_TIMEOUT_MSEC", None)
        if prop is not None and ms != self._read_timeout_ms:
            self._capture.set(prop, ms)  # False when the backend does not support it
            self._read_timeout_ms = ms

    def grab(self, timeout: float = 1.0) -> Frame:
        """The next frame (see the class notes for ids and times)."""
        import cv2

        capture = self._capture
        if capture is None:
            raise CameraClosed(f"{self.description} is not open")
        if not self.live:
            index = int(round(capture.get(cv2.CAP_PROP_POS_FRAMES)))
            ok, image = capture.read()
            if not ok or image is None:
                raise CameraClosed(f"{self.description} has ended after {index} frames")
            frame_id, t = index, index / self.fps
        else:
            self._set_read_timeout(timeout)
            ok, image = capture.read()
            if not ok or image is None:
                raise CameraTimeout(f"no frame from {self.description} within {timeout:g} s")
            wall = time.monotonic()
            msec = capture.get(cv2.CAP_PROP_POS_MSEC)
            if self._use_pos_msec is None:  # decided once: never mix two clocks in one stream
                self._use_pos_msec = bool(math.isfinite(msec) and msec > 0)
            t = msec * 1e-3 if self._use_pos_msec else wall
            frame_id = self._count
        self._count += 1
        image = _to_mono(image, self.description)
        if image.shape != (self.height, self.width):
            raise CameraError(f"{self.description} gave a {image.shape[1]}x{image.shape[0]} image; "
                              f"it reported {self.width}x{self.height}")
        return Frame(image, int(frame_id), float(t))


class GenICamCamera:
    """A GenICam camera (GigE Vision, USB3 Vision, ...) through harvesters.

    Parameters
    ----------
    cti_path : str or Path
        The GenTL producer (.cti) of the camera's vendor (or any compliant one).
    serial : str, optional
        The camera's serial number; the first camera found when None.
    fps : float, optional
        The frame rate when the camera's node map has no ``AcquisitionFrameRate``.

    Notes
    -----
    Needs the optional extra: ``pip install 'flyscan[genicam]'``. The camera must be set to
    an 8-bit mono pixel format (``Mono8``). ``frame_id`` is the producer's frame id (a gap is
    a frame lost between camera and host) when it gives one, else a running count; ``t`` is the
    buffer's timestamp, s: ``timestamp_ns`` when the producer gives it, else the raw
    ``timestamp`` over the device's tick frequency.

    Not thread-safe: open, grab and close from one thread.
    """

    def __init__(self, cti_path, *, serial: str | None = None, fps: float | None = None):
        self.cti_path = Path(cti_path)
        self.serial = serial
        self.width = 0
        self.height = 0
        self.fps = float(fps) if fps is not None else 0.0
        self._fps_argument = fps
        self._harvester = None
        self._acquirer = None
        self._count = 0
        # Fail early and clearly, before any hardware is touched: the producer first (the
        # thing only the camera's vendor can supply), then the Python package.
        self._check_producer()
        _harvesters_core()

    def __repr__(self) -> str:
        return f"GenICamCamera({str(self.cti_path)!r}, serial={self.serial!r})"

    def _check_producer(self) -> None:
        if not self.cti_path.is_file():
            raise CameraError(
                f"GenTL producer not found: {self.cti_path} (a GenTL producer from the camera "
                "vendor is required: a .cti file installed with its SDK)")

    def open(self) -> None:
        if self._acquirer is not None:
            return
        core = _harvesters_core()
        self._check_producer()
        harvester = core.Harvester()
        try:
            harvester.add_file(str(self.cti_path))
            harvester.update()
            if not harvester.device_info_list:
                raise CameraError(f"no camera found through {self.cti_path}")
            key = {"serial_number": self.serial} if self.serial else 0
            try:
                acquirer = harvester.create(key)
            except (ValueError, IndexError) as exc:
                raise CameraError(f"no camera with serial {self.serial!r} through "
                                  f"{self.cti_path}: {exc}") from None
            try:
                nodes = acquirer.remote_device.node_map
                width, height = int(nodes.Width.value), int(nodes.Height.value)
                fps = self._fps_argument
                if fps is None:
                    fps = _node_value(nodes, "AcquisitionFrameRate", "AcquisitionFrameRateAbs",
                                      "ResultingFrameRate")
                if fps is None or not (math.isfinite(fps) and fps > 0):
                    raise CameraError(f"the camera behind {self.cti_path} reports no frame rate; "
                                      "pass fps=")
                acquirer.start()
            except BaseException:
                acquirer.destroy()
                raise
        except BaseException:
            harvester.reset()
            raise
        self._harvester, self._acquirer = harvester, acquirer
        self.width, self.height, self.fps = width, height, float(fps)
        self._count = 0

    def close(self) -> None:
        acquirer, harvester = self._acquirer, self._harvester
        self._acquirer = self._harvester = None
        if acquirer is not None:
            try:
                acquirer.stop()
            finally:
                acquirer.destroy()
        if harvester is not None:
            harvester.reset()

    def grab(self, timeout: float = 1.0) -> Frame:
        acquirer = self._acquirer
        if acquirer is None:
            raise CameraClosed(f"the camera behind {self.cti_path} is not open")
        from genicam.gentl import TimeoutException  # installed with harvesters

        try:
            buffer = acquirer.fetch(timeout=timeout)
        except TimeoutException:
            raise CameraTimeout(f"no frame from the camera behind {self.cti_path} "
                                f"within {timeout:g} s") from None
        # The buffer returns to the producer's pool on leaving the block: copy the image out.
        with buffer:
            component = buffer.payload.components[0]
            if getattr(component, "data_format", "Mono8") != "Mono8":
                raise CameraError(f"the camera gives {component.data_format} pixels; set its "
                                  "PixelFormat to Mono8")
            image = np.array(component.data, dtype=np.uint8, copy=True).reshape(
                component.height, component.width)
            frame_id = _buffer_frame_id(buffer)
            t = _buffer_time_s(buffer)
        if frame_id is None:
            frame_id = self._count
        self._count += 1
        if t is None:
            t = time.monotonic()
        return Frame(image, int(frame_id), float(t))


def _harvesters_core():
    """``harvesters.core``, or a CameraError saying how to install it."""
    try:
        from harvesters import core
    except ImportError:
        raise CameraError("GenICam cameras need harvesters: pip install 'flyscan[genicam]'") from None
    return core


def _node_value(nodes, *names):
    """The first of the node map's features that exists, as float; None if none does."""
    for name in names:
        try:
            return float(getattr(nodes, name).value)
        except Exception:  # a missing feature raises the GenApi's own exceptions
            continue
    return None


def _buffer_frame_id(buffer) -> int | None:
    """The producer's frame id (GenTL BUFFER_INFO_FRAMEID), when it gives one."""
    for owner in (buffer, getattr(buffer, "_buffer", None)):
        if owner is None:
            continue
        try:
            value = owner.frame_id
        except Exception:  # not implemented by this producer
            continue
        if value is not None:
            return int(value)
    return None


def _buffer_time_s(buffer) -> float | None:
    """The buffer's timestamp, s: ``timestamp_ns``, else ticks over the tick frequency."""
    try:
        return int(buffer.timestamp_ns) * 1e-9
    except Exception:  # not implemented by this producer
        pass
    try:
        ticks, frequency = int(buffer.timestamp), float(buffer.timestamp_frequency)
    except Exception:
        return None
    return ticks / frequency if ticks and frequency > 0 else None


def open_camera(spec: str, *, fps: float | None = None) -> Camera:
    """The camera a spec names (not opened).

    Parameters
    ----------
    spec : str
        One of :data:`CAMERA_SPEC_FORMS`: ``opencv:0``, ``opencv:/dev/video0``,
        ``video:/path/file.avi``, ``gstreamer:<pipeline>``,
        ``genicam:/path/producer.cti[#serial]``, ``pylon:[serial][?options]``
        (``service.pylon_camera.parse_pylon_spec``), ``replay:/path/to/recording``.
    fps : float, optional
        Frame rate for a source that does not report one (OpenCV and GenICam).

    Returns
    -------
    Camera
        ``replay:`` loads and validates the recording's metadata now (so that a bad folder is
        reported with the settings), its frames are mapped on ``open``.

    Raises
    ------
    ValueError
        Anything else, with the accepted forms.
    """
    kind, sep, rest = spec.partition(":") if isinstance(spec, str) else ("", "", "")
    if kind == "pylon" and sep:  # ``pylon:`` alone is the first Basler camera found
        from service.pylon_camera import parse_pylon_spec
        return parse_pylon_spec(rest)
    if sep and rest:
        if kind == "opencv":
            if rest.isdigit():
                return OpenCVCamera(int(rest), fps=fps, kind="device")
            if rest.startswith("/dev/"):
                return OpenCVCamera(rest, fps=fps, kind="device")
        elif kind == "video":
            return OpenCVCamera(rest, fps=fps, kind="file")
        elif kind == "gstreamer":
            return OpenCVCamera(rest, fps=fps, kind="gstreamer")
        elif kind == "genicam":
            path, _, serial = rest.partition("#")
            if path:
                return GenICamCamera(path, serial=serial or None, fps=fps)
        elif kind == "replay":
            from scanner_core.recording import load_recording
            from scanner_core.recording.replay import ReplayCamera
            return ReplayCamera(load_recording(rest))
    forms = "\n  ".join(CAMERA_SPEC_FORMS)
    raise ValueError(f"unknown camera spec {spec!r}; accepted forms:\n  {forms}")


__all__ = ["CAMERA_SPEC_FORMS", "CameraError", "GenICamCamera", "OpenCVCamera", "open_camera"]
