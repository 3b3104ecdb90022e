"""Basler cameras through pypylon, Basler's own Python binding of its pylon SDK.

``--camera pylon:[SERIAL][?option=value&...]`` (:func:`parse_pylon_spec`) makes a
:class:`PylonCamera`: the camera of that serial number (the first one found without), set
up through its GenICam nodes: ``PixelFormat`` Mono8 (or an 8-bit Bayer mosaic), ``Width``, ``Height``, ``OffsetX``,
``OffsetY``, ``ExposureTime``, ``Gain``, ``AcquisitionFrameRate`` in free run, or a hardware
trigger (``TriggerMode`` On on a line). It implements ``scanner_core.devices.Camera`` and
``ExposureControl``: the exposure modes of ``scanner_core.pipeline.exposure`` drive ``ExposureTime``
and ``Gain`` through the nodes.

Frames: ``frame_id`` is the camera's block id (unwrapped: GigE Vision's 16-bit id wraps from
65535 to 1), so a frame lost anywhere between sensor and host, or one the camera delivers
incomplete (skipped here), is a gap the service counts as dropped. ``t`` is the camera's
timestamp mapped to the host's monotonic clock by ``scanner_core.pipeline.camclock.CameraClock``, whose
drift is measured (:attr:`PylonCamera.clock_status`); a camera that stamps nothing (Basler's
emulator stamps 0) gives the host time at which the frame was retrieved.

pypylon is the optional extra ``pip install 'flyscan[pylon]'``; it ships the pylon runtime and
Basler's camera emulator: with ``PYLON_CAMEMU=1`` in the environment an emulated camera
(serial ``0815-0000``) appears, and the option ``images=FOLDER`` makes it serve that folder's
image files in name order (its ``ImageFilename`` and ``ImageFileMode`` nodes), as the tests do.
Constructing does no I/O; ``open`` finds, configures and starts the camera. Not thread-safe:
one thread opens, grabs and closes.
"""
from __future__ import annotations

import math
import time
import warnings
from pathlib import Path
from urllib.parse import parse_qsl

import numpy as np

from scanner_core.pipeline.camclock import CameraClock
from scanner_core.devices import CameraClosed, CameraTimeout
from scanner_core.types import Frame
from service.camera_errors import CameraError

__all__ = ["PylonCamera", "PYLON_OPTIONS", "PIXEL_FORMATS", "parse_pylon_spec", "set_node"]

#: The options of a ``pylon:`` spec and what they are.
PYLON_OPTIONS = {
    "width": "image width, px (Width)",
    "height": "image height, px (Height)",
    "offset_x": "left edge of the region, px (OffsetX)",
    "offset_y": "top edge of the region, px (OffsetY)",
    "exposure_us": "exposure time, us (ExposureTime)",
    "gain_db": "analogue gain, dB (Gain)",
    "fps": "frame rate, Hz (AcquisitionFrameRate; with a trigger, the rate expected)",
    "trigger": "off (free run) or the input line of a hardware trigger: line1, line2, line3",
    "images": "Basler's emulator only: serve this folder's images (ImageFilename)",
    "pixel_format": "Mono8 (default) or a colour camera's raw 8-bit mosaic: BayerRG8, BayerBG8, "
                    "BayerGR8, BayerGB8 (then set the scanner's bayer to the pattern: RGGB, "
                    "BGGR, GRBG, GBRG)",
}
#: The 8-bit pixel formats the scanner reads: one byte a pixel, a frame (H, W) uint8.
PIXEL_FORMATS = ("Mono8", "BayerRG8", "BayerBG8", "BayerGR8", "BayerGB8")
#: Buffers the grab engine queues (MaxNumBuffer): 0.1 s at 162 fps, like a camera's own
#: buffer; a reader late by more loses frames, and their ids show it.
GRAB_BUFFERS = 16
#: Ticks per second of a camera timestamp when the camera does not say (USB3 Vision: ns).
DEFAULT_TICK_HZ = 1e9
#: A GigE Vision block id is 16 bits and skips 0: after 65535 comes 1.
GIGE_BLOCK_WRAP = 65535
#: An unavailable block id (pylon's UINT64 max).
NO_BLOCK_ID = 2**64 - 1


def _pylon():
    """``pypylon.pylon`` and ``pypylon.genicam``, or a CameraError saying how to install."""
    try:
        # pypylon's SWIG modules warn (DeprecationWarning: "builtin type SwigPyPacked has no
        # __module__ attribute") while they initialise; where warnings are errors (pytest's
        # filterwarnings, python -W error) that error inside the module's C initialisation
        # kills the interpreter with a segmentation fault. Imported once, quietly.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            from pypylon import genicam, pylon
    except ImportError:
        raise CameraError("Basler cameras need pypylon: pip install 'flyscan[pylon]'") from None
    return pylon, genicam


def parse_pylon_spec(rest: str) -> PylonCamera:
    """``[SERIAL][?option=value&...]`` (the part after ``pylon:``) -> a PylonCamera (not
    opened); ValueError naming the options for an unknown or malformed one."""
    serial, _, query = rest.partition("?")
    options: dict = {}
    for key, value in parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query)):
        if key not in PYLON_OPTIONS:
            names = ", ".join(PYLON_OPTIONS)
            raise ValueError(f"unknown pylon option {key!r}; the options are {names}")
        if key in ("trigger", "images", "pixel_format"):
            options[key] = value
            continue
        try:
            number = float(value) if key in ("exposure_us", "gain_db", "fps") else int(value)
        except ValueError:
            raise ValueError(f"pylon option {key}={value!r}: {PYLON_OPTIONS[key]}, a number") from None
        options[key] = number
    return PylonCamera(serial or None, **options)


def set_node(nodes, name: str, value, *, unit: str = "", owner: str = "the camera"):
    """Write one GenICam node, or a CameraError saying why not in the camera's own terms: a
    node it does not have, a value outside its range (with the range), an entry it does not
    offer (with those it does). Returns the value the camera holds afterwards."""
    _, genicam = _pylon()
    node = nodes.GetNode(name)
    if node is None or not genicam.IsAvailable(node):
        raise CameraError(f"{owner} has no {name} node")
    if hasattr(node, "Symbolics"):  # an enumeration
        offered = list(node.Symbolics)
        if value not in offered:
            raise CameraError(f"{name} {value!r} is not offered by {owner}; it offers "
                              f"{', '.join(offered)}")
    elif hasattr(node, "Min") and hasattr(node, "Max"):
        low, high = node.Min, node.Max
        if not low <= value <= high:
            raise CameraError(f"{name} {value:g}{unit} is out of range for {owner}: "
                              f"{low:g} to {high:g}{unit}")
    if not genicam.IsWritable(node):  # e.g. the image format while the camera streams
        raise CameraError(f"{owner}'s {name} cannot be written now")
    try:
        node.Value = value
    except genicam.GenericException as exc:  # an increment not met, a node locked, ...
        raise CameraError(f"{owner} refused {name} = {value!r}: "
                          f"{exc.GetDescription() if hasattr(exc, 'GetDescription') else exc}") from None
    return node.Value


class PylonCamera:
    """A Basler camera through pypylon (``Camera`` and ``ExposureControl``).

    Parameters
    ----------
    serial : str, optional
        The camera's serial number; the first camera pylon finds when None.
    width, height, offset_x, offset_y : int, optional
        The region of the sensor read out, px; the camera's current one when None.
    exposure_us : float, optional
        Exposure time, us; the camera's current one when None.
    gain_db : float, optional
        Analogue gain, dB; the camera's current one when None.
    fps : float, optional
        Free run: the frame rate asked of the camera, Hz; with a trigger, the rate the trigger
        is expected to come at (the camera cannot know it). The camera's current rate when None.
    trigger : {"off", "line1", "line2", "line3"}
        Free run, or a frame start on the rising edge of that input line.
    images : str or Path, optional
        Basler's emulator only: the folder of image files it serves, in name order.

    Attributes
    ----------
    width, height : int
        Image size, px; known after :meth:`open`.
    fps : float
        Frames/s: the camera's resulting frame rate after :meth:`open`.
    exposure_range_us, gain_range : (2,) tuple of float
        What ``ExposureTime`` (us) and ``Gain`` (as a factor: 1 is 0 dB) accept; after :meth:`open`.
    exposure_us, gain : float
        The exposure (us) and gain (factor) set; every frame reports them.
    frames_incomplete : int
        Frames the camera delivered broken (skipped: their ids are gaps).
    """

    TRIGGERS = ("off", "line1", "line2", "line3")

    def __init__(self, serial: str | None = None, *, width: int | None = None,
                 height: int | None = None, offset_x: int | None = None,
                 offset_y: int | None = None, exposure_us: float | None = None,
                 gain_db: float | None = None, fps: float | None = None, trigger: str = "off",
                 images: str | Path | None = None, pixel_format: str = "Mono8"):
        if trigger not in self.TRIGGERS:
            raise ValueError(f"pylon trigger must be one of {', '.join(self.TRIGGERS)}, got {trigger!r}")
        for name, value in (("width", width), ("height", height)):
            if value is not None and value < 1:
                raise ValueError(f"pylon {name} must be >= 1 px, got {value}")
        for name, value in (("offset_x", offset_x), ("offset_y", offset_y)):
            if value is not None and value < 0:
                raise ValueError(f"pylon {name} must be >= 0 px, got {value}")
        for name, value in (("exposure_us", exposure_us), ("fps", fps)):
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"pylon {name} must be a positive number, got {value!r}")
        if pixel_format not in PIXEL_FORMATS:
            raise ValueError(f"pylon pixel_format must be one of {', '.join(PIXEL_FORMATS)}, "
                             f"got {pixel_format!r}")
        if trigger != "off" and fps is None:
            raise ValueError("a triggered pylon camera needs fps= (the rate the trigger comes at)")
        self.serial = serial
        self.config = {"width": width, "height": height, "offset_x": offset_x,
                       "offset_y": offset_y, "exposure_us": exposure_us, "gain_db": gain_db,
                       "fps": fps, "trigger": trigger, "images": images,
                       "pixel_format": pixel_format}
        self.width = width or 0
        self.height = height or 0
        self.fps = float(fps) if fps is not None else 0.0
        self.exposure_range_us = (math.nan, math.nan)
        self.gain_range = (math.nan, math.nan)
        self.exposure_us, self.gain = math.nan, 1.0
        self.frames_incomplete = 0
        self._camera = None
        self._tick_hz = DEFAULT_TICK_HZ
        self._clock = CameraClock()
        self._stamped: bool | None = None
        self._block = (None, 0)  # (last raw block id, added for the wraps so far)
        self._count = 0

    def __repr__(self) -> str:
        return f"PylonCamera({self.serial!r})"

    @property
    def description(self) -> str:
        return f"Basler camera {self.serial}" if self.serial else "the first Basler camera"

    # -- life cycle -------------------------------------------------------------------------

    def open(self) -> None:
        if self._camera is not None:
            return
        pylon, genicam = _pylon()
        factory = pylon.TlFactory.GetInstance()
        devices = list(factory.EnumerateDevices())
        if self.serial is not None:
            devices = [d for d in devices if d.GetSerialNumber() == self.serial]
        if not devices:
            raise CameraError(f"no {'Basler camera with serial ' + repr(self.serial) if self.serial else 'Basler camera'}"
                              " found by pylon (PYLON_CAMEMU=1 adds an emulated one)")
        try:
            camera = pylon.InstantCamera(factory.CreateDevice(devices[0]))
            camera.Open()
        except genicam.GenericException as exc:
            raise CameraError(f"cannot open {self.description}: {exc}") from None
        self.serial = devices[0].GetSerialNumber()
        try:
            self._configure(camera)
            camera.MaxNumBuffer.Value = GRAB_BUFFERS
            camera.StartGrabbing(pylon.GrabStrategy_OneByOne)
        except BaseException:
            camera.Close()
            raise
        self._camera = camera
        self._clock = CameraClock()
        self._stamped = None
        self._block = (None, 0)
        self._count = 0

    def close(self) -> None:
        camera, self._camera = self._camera, None
        if camera is not None:
            try:
                camera.StopGrabbing()
            finally:
                camera.Close()

    def _configure(self, camera) -> None:
        """Every node the options name, in an order the camera accepts (the offsets to 0
        before the size grows, then the offsets), then what it resulted in."""
        nodes, owner, c = camera.GetNodeMap(), self.description, self.config
        put = lambda name, value, unit="": set_node(nodes, name, value, unit=unit, owner=owner)
        put("PixelFormat", c["pixel_format"])  # one byte a pixel: mono, or a raw mosaic
        if c["images"] is not None:
            folder = Path(c["images"])
            if not folder.is_dir():
                raise CameraError(f"pylon images={folder}: no such folder")
            put("ImageFilename", str(folder.resolve()))
            put("ImageFileMode", "On")
            put("TestImageSelector", "Off")
        for axis, size in (("X", "width"), ("Y", "height")):
            if c[size] is not None or c[f"offset_{axis.lower()}"] is not None:
                put(f"Offset{axis}", 0)
            if c[size] is not None:
                put(size.capitalize(), int(c[size]), " px")
            if c[f"offset_{axis.lower()}"] is not None:
                put(f"Offset{axis}", int(c[f"offset_{axis.lower()}"]), " px")
        if nodes.GetNode("ExposureAuto") is not None and _available(nodes, "ExposureAuto"):
            put("ExposureAuto", "Off")  # the scanner steers the exposure, never the camera
        if nodes.GetNode("GainAuto") is not None and _available(nodes, "GainAuto"):
            put("GainAuto", "Off")
        exposure = _node(nodes, "ExposureTime", "ExposureTimeAbs")
        gain = _node(nodes, "Gain", "GainAbs")
        if exposure is None:
            raise CameraError(f"{owner} has no ExposureTime node")
        if c["exposure_us"] is not None:
            put(exposure, float(c["exposure_us"]), " us")
        if c["gain_db"] is not None:
            if gain is None:
                raise CameraError(f"{owner} has no Gain node")
            put(gain, float(c["gain_db"]), " dB")
        if c["trigger"] == "off":
            if _available(nodes, "TriggerMode"):
                if _available(nodes, "TriggerSelector"):
                    put("TriggerSelector", "FrameStart")
                put("TriggerMode", "Off")
            rate = _node(nodes, "AcquisitionFrameRate", "AcquisitionFrameRateAbs")
            if c["fps"] is not None:
                if rate is None:
                    raise CameraError(f"{owner} has no AcquisitionFrameRate node")
                if _available(nodes, "AcquisitionFrameRateEnable"):
                    put("AcquisitionFrameRateEnable", True)
                put(rate, float(c["fps"]), " Hz")
        else:
            if _available(nodes, "TriggerSelector"):
                put("TriggerSelector", "FrameStart")
            put("TriggerMode", "On")
            put("TriggerSource", c["trigger"].capitalize())
            if _available(nodes, "TriggerActivation"):
                put("TriggerActivation", "RisingEdge")
        self.width = int(nodes.GetNode("Width").Value)
        self.height = int(nodes.GetNode("Height").Value)
        self.exposure_range_us = (float(nodes.GetNode(exposure).Min),
                                  float(nodes.GetNode(exposure).Max))
        self.exposure_us = float(nodes.GetNode(exposure).Value)
        self._exposure_node, self._gain_node = exposure, gain
        if gain is not None:
            node = nodes.GetNode(gain)
            self.gain_range = (10 ** (node.Min / 20), 10 ** (node.Max / 20))
            self.gain = 10 ** (float(node.Value) / 20)
        else:
            self.gain_range, self.gain = (1.0, 1.0), 1.0
        fps = c["fps"] if c["trigger"] != "off" else None
        if fps is None:
            fps = _value(nodes, "ResultingFrameRate", "ResultingFrameRateAbs",
                         "AcquisitionFrameRate", "AcquisitionFrameRateAbs")
        if fps is None or not (math.isfinite(fps) and fps > 0):
            raise CameraError(f"{owner} reports no frame rate; give fps=")
        self.fps = float(fps)
        self._tick_hz = _value(nodes, "GevTimestampTickFrequency") or DEFAULT_TICK_HZ

    # -- exposure ---------------------------------------------------------------------------

    def set_exposure(self, exposure_us: float, gain: float = 1.0) -> None:
        """``ExposureTime`` (us) and ``Gain`` (a factor, written in dB) from the next frames;
        ValueError outside the camera's ranges. Without chunk data a frame does not carry its
        own exposure, so the one or two frames in flight when it changes report the new one."""
        camera = self._camera
        if camera is None:
            raise CameraClosed(f"{self.description} is not open")
        (low, high), (glow, ghigh) = self.exposure_range_us, self.gain_range
        if not low <= exposure_us <= high:
            raise ValueError(f"exposure {exposure_us:g} us is outside {self.description}'s "
                             f"range {low:g} to {high:g} us")
        if not glow * (1 - 1e-9) <= gain <= ghigh * (1 + 1e-9):
            raise ValueError(f"gain {gain:g} is outside {self.description}'s range "
                             f"{glow:g} to {ghigh:g}")
        nodes = camera.GetNodeMap()
        self.exposure_us = float(set_node(nodes, self._exposure_node, float(exposure_us),
                                          unit=" us", owner=self.description))
        if self._gain_node is not None and gain != self.gain:
            db = min(max(20 * math.log10(gain), nodes.GetNode(self._gain_node).Min),
                     nodes.GetNode(self._gain_node).Max)
            self.gain = 10 ** (float(set_node(nodes, self._gain_node, db, unit=" dB",
                                              owner=self.description)) / 20)

    # -- frames -----------------------------------------------------------------------------

    def grab(self, timeout: float = 1.0) -> Frame:
        """The next complete frame; a broken one is skipped (its id becomes a gap)."""
        camera = self._camera
        if camera is None:
            raise CameraClosed(f"{self.description} is not open")
        pylon, _ = _pylon()
        deadline = time.monotonic() + max(float(timeout), 0.0)
        while True:
            remaining_ms = max(int((deadline - time.monotonic()) * 1e3), 0)
            result = camera.RetrieveResult(remaining_ms, pylon.TimeoutHandling_Return)
            host = time.monotonic()
            if not result.IsValid():
                if not camera.IsGrabbing():
                    raise CameraClosed(f"{self.description} stopped grabbing")
                raise CameraTimeout(f"no frame from {self.description} within {timeout:g} s")
            try:
                block = int(result.BlockID)
                if not result.GrabSucceeded():
                    # Lost for the scanner: the next frame's id shows the gap.
                    self.frames_incomplete += 1
                    self._frame_id(block)
                    continue
                image = np.array(result.GetArray(), dtype=np.uint8, copy=True)
                ticks = int(result.TimeStamp)
            finally:
                result.Release()
            if image.shape != (self.height, self.width):
                raise CameraError(f"{self.description} gave a {image.shape[1]}x{image.shape[0]} "
                                  f"image; it is set to {self.width}x{self.height}")
            return Frame(image, self._frame_id(block), self._time(ticks, host),
                         self.exposure_us, self.gain)

    def _frame_id(self, block: int) -> int:
        """The block id unwrapped to an ever-increasing frame id (a running count when the
        transport gives none)."""
        self._count += 1
        if block == NO_BLOCK_ID:
            return self._count - 1
        last, added = self._block
        if last is not None and block < last:
            added += GIGE_BLOCK_WRAP if last <= GIGE_BLOCK_WRAP else 2**32
        self._block = (block, added)
        return block + added

    def _time(self, ticks: int, host: float) -> float:
        """Host time of the exposure, s (see the module's notes)."""
        if self._stamped is None:  # decided on the first frame: never mix two clocks
            self._stamped = ticks != 0
        if not self._stamped:
            return host
        return self._clock.map(ticks / self._tick_hz, host)

    @property
    def clock_status(self) -> dict:
        """How frame times are made: ``source`` (camera or host), the mapping's offset (s) and
        drift (ppm) when the camera stamps its frames."""
        if not self._stamped:
            return {"source": "host", "offset_s": None, "drift_ppm": None}
        estimate = self._clock.estimate()
        drift = estimate.drift_ppm
        return {"source": "camera", "offset_s": estimate.offset_s,
                "drift_ppm": None if math.isnan(drift) else round(drift, 3)}


def _available(nodes, name: str) -> bool:
    _, genicam = _pylon()
    node = nodes.GetNode(name)
    return node is not None and genicam.IsAvailable(node)


def _node(nodes, *names: str) -> str | None:
    """The first of the names the camera has (SFNC name, then the older GigE one)."""
    return next((name for name in names if _available(nodes, name)), None)


def _value(nodes, *names: str) -> float | None:
    """The first readable one of the float nodes, or None."""
    _, genicam = _pylon()
    for name in names:
        node = nodes.GetNode(name)
        if node is not None and genicam.IsReadable(node):
            return float(node.Value)
    return None
