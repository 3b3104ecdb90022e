"""The real camera backends: a video file feeds a pass end to end; the specs; the clear errors."""
import sys
import types

import cv2
import numpy as np
import pytest

from scanner_core.devices import Camera, CameraClosed, CameraTimeout
from scanner_core.pipeline import camera_frames, run_pass, warm_up
from scanner_core.types import Frame
from service import cameras
from service.cameras import CameraError, GenICamCamera, OpenCVCamera, open_camera
from scanner_core.recording import PassRecorder
from scanner_core.recording.replay import ReplayCamera
from simulator.session import simulated_cell


def write_video(path, images, fps, *, colour=False):
    """Images (N, H, W) uint8 -> an FFV1 AVI: lossless, and in every opencv-python wheel."""
    height, width = images[0].shape
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), fps, (width, height),
                             isColor=colour)
    assert writer.isOpened()
    for image in images:
        writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if colour else image)
    writer.release()
    return path


def test_a_video_file_feeds_a_pass_end_to_end(cell, block_part, tmp_path):
    """A lossless video of a simulated pass gives the same cloud as its frames did.

    The file clock starts at 0 while the simulated pass's starts at -lead_in, so the pass
    runs with that clock offset (robot time = file time - lead_in, exactly the frames' times).
    """
    fast = cell.with_pass(speed_mm_s=1000.0, fps=162.0, lead_in_s=0.1, lead_out_s=0.1)
    sim = simulated_cell(block_part, fast)
    warm_up(fast.calibration)
    sim.camera.open()
    sim.robot.connect()
    frames = list(camera_frames(sim.camera))
    live = run_pass(iter(frames), fast.calibration, sim.robot)
    path = write_video(tmp_path / "pass.avi", [f.image for f in frames], sim.camera.fps)

    camera = OpenCVCamera(str(path))
    assert isinstance(camera, Camera)
    camera.open()
    assert (camera.width, camera.height, camera.fps) == (sim.camera.width, sim.camera.height, 162.0)
    scan = run_pass(camera_frames(camera), fast.calibration, sim.robot,
                    clock_offset_s=-fast.pass_profile.lead_in_s)
    assert live.frames > 20
    assert np.array_equal(scan.cloud, live.cloud)
    assert np.array_equal(scan.frame_ids, live.frame_ids)
    assert np.array_equal(scan.edges, live.edges)

    camera.close()
    camera.open()  # again from the start: every frame, bit for bit, then the end
    replayed = list(camera_frames(camera))
    assert [f.frame_id for f in replayed] == [f.frame_id for f in frames]
    assert [f.t for f in replayed] == [i / 162.0 for i in range(len(frames))]
    assert all(np.array_equal(a.image, b.image) for a, b in zip(replayed, frames))
    with pytest.raises(CameraClosed, match="has ended"):
        camera.grab(1.0)
    camera.close()


def test_a_colour_video_is_read_as_grey_and_fps_can_be_given(tmp_path):
    images = np.random.default_rng(0).integers(0, 256, (3, 8, 10), dtype=np.uint8)
    path = write_video(tmp_path / "colour.avi", images, 30.0, colour=True)
    camera = OpenCVCamera(path, fps=100.0)  # a Path is a file
    assert camera.kind == "file"
    camera.open()
    frames = [camera.grab(1.0) for _ in range(3)]
    assert all(f.image.shape == (8, 10) and f.image.dtype == np.uint8 for f in frames)
    assert all(np.array_equal(f.image, image) for f, image in zip(frames, images))
    assert [f.t for f in frames] == [0.0, 0.01, 0.02]  # the given rate is the file clock


def test_opencv_camera_says_what_it_cannot_open(tmp_path):
    with pytest.raises(CameraError, match="video file .*missing.avi.*no such file"):
        OpenCVCamera(str(tmp_path / "missing.avi")).open()
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"not a video" * 100)
    with pytest.raises(CameraError, match="cannot open video file .*junk.avi"):
        OpenCVCamera(str(junk)).open()
    with pytest.raises(CameraError, match="video device 99"):
        OpenCVCamera(99).open()
    with pytest.raises(CameraClosed):
        OpenCVCamera(str(junk)).grab(1.0)  # not open
    with pytest.raises(ValueError, match="fps"):
        OpenCVCamera(0, fps=0.0)


@pytest.mark.skipif(cv2.videoio_registry.hasBackend(cv2.CAP_GSTREAMER),
                    reason="this OpenCV has GStreamer")
def test_gstreamer_without_gstreamer_is_explained():
    with pytest.raises(CameraError, match="built without GStreamer"):
        OpenCVCamera("videotestsrc ! appsink").open()


class FakeCapture:
    """cv2.VideoCapture of a live device: images, POS_MSEC per frame, a failure when told."""

    def __init__(self, source, api=None, *, fps=0.0, msec=(10.0, 16.0, 22.0)):
        self.props = {cv2.CAP_PROP_FRAME_WIDTH: 10, cv2.CAP_PROP_FRAME_HEIGHT: 8,
                      cv2.CAP_PROP_FPS: fps, cv2.CAP_PROP_POS_MSEC: 0.0}
        self.msec = list(msec)
        self.released = False

    def isOpened(self):
        return True

    def get(self, prop):
        return self.props.get(prop, 0.0)

    def set(self, prop, value):
        return False

    def read(self):
        if not self.msec:
            return False, None
        self.props[cv2.CAP_PROP_POS_MSEC] = self.msec.pop(0)
        return True, np.full((8, 10, 3), 7, np.uint8)

    def release(self):
        self.released = True


def test_live_device_ids_times_and_failures(monkeypatch):
    monkeypatch.setattr(cv2, "VideoCapture", lambda *a: FakeCapture(*a))
    with pytest.raises(CameraError, match="reports no frame rate; pass fps="):
        OpenCVCamera(0).open()
    camera = OpenCVCamera("/dev/video3", fps=60.0)
    assert camera.kind == "device"
    camera.open()
    frames = [camera.grab(0.5) for _ in range(3)]
    assert [f.frame_id for f in frames] == [0, 1, 2]
    assert [f.t for f in frames] == [0.010, 0.016, 0.022]  # the capture's timestamps, s
    assert np.array_equal(frames[0].image, np.full((8, 10), 7, np.uint8))
    with pytest.raises(CameraTimeout):
        camera.grab(0.5)  # a failed live read: the camera stopped
    camera.close()

    # Without a capture timestamp the host's monotonic clock is used, for the whole stream.
    monkeypatch.setattr(cv2, "VideoCapture", lambda *a: FakeCapture(*a, fps=30.0, msec=(0, 0)))
    camera = OpenCVCamera(0)
    camera.open()
    assert camera.fps == 30.0
    import time
    before = time.monotonic()
    assert before <= camera.grab(0.5).t <= time.monotonic()


# ---------------------------------------------------------------------------------------------
# GenICam


def test_genicam_needs_the_producer(tmp_path):
    with pytest.raises(CameraError, match="GenTL producer not found: .*vendor.cti.*"
                                          "a GenTL producer from the camera vendor is required"):
        GenICamCamera(tmp_path / "vendor.cti")


def test_genicam_without_harvesters_says_how_to_install(tmp_path, monkeypatch):
    cti = tmp_path / "vendor.cti"
    cti.write_bytes(b"")
    monkeypatch.setitem(sys.modules, "harvesters", None)  # as if not installed
    with pytest.raises(CameraError, match=r"pip install 'flyscan\[genicam\]'"):
        GenICamCamera(cti)


def fake_harvesters(monkeypatch, *, serials=("S1",), frames=((5, 1_000_000),)):
    """harvesters.core and genicam.gentl as far as GenICamCamera uses them."""
    class TimeoutException(Exception):
        pass

    class Component:
        data_format, width, height = "Mono8", 4, 2

        def __init__(self, value):
            self.data = np.full(8, value, np.uint8)

    class Buffer:
        def __init__(self, frame_id, ns):
            self.frame_id, self.timestamp_ns = frame_id, ns
            self.payload = types.SimpleNamespace(components=[Component(frame_id)])
            self.queued = False

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.queued = True

    class Acquirer:
        def __init__(self):
            value = types.SimpleNamespace
            self.remote_device = value(node_map=value(Width=value(value=4), Height=value(value=2),
                                                      AcquisitionFrameRate=value(value=200.0)))
            self.pending = [Buffer(*f) for f in frames]
            self.log = []

        def start(self):
            self.log.append("start")

        def fetch(self, timeout):
            if not self.pending:
                raise TimeoutException()
            return self.pending.pop(0)

        def stop(self):
            self.log.append("stop")

        def destroy(self):
            self.log.append("destroy")

    class Harvester:
        def __init__(self):
            self.files, self.device_info_list, self.acquirers = [], [], []

        def add_file(self, path):
            self.files.append(path)

        def update(self):
            self.device_info_list = [types.SimpleNamespace(serial_number=s) for s in serials]

        def create(self, key):
            if isinstance(key, dict) and key["serial_number"] not in serials:
                raise ValueError("no such device")
            self.acquirers.append(Acquirer())
            return self.acquirers[-1]

        def reset(self):
            pass

    core = types.SimpleNamespace(Harvester=Harvester)
    monkeypatch.setattr(cameras, "_harvesters_core", lambda: core)
    gentl = types.ModuleType("genicam.gentl")
    gentl.TimeoutException = TimeoutException
    monkeypatch.setitem(sys.modules, "genicam", types.ModuleType("genicam"))
    monkeypatch.setitem(sys.modules, "genicam.gentl", gentl)


def test_genicam_flow_against_a_fake_harvesters(tmp_path, monkeypatch):
    cti = tmp_path / "vendor.cti"
    cti.write_bytes(b"")
    fake_harvesters(monkeypatch)
    camera = GenICamCamera(cti, serial="S1")
    assert isinstance(camera, Camera)
    camera.open()
    assert (camera.width, camera.height, camera.fps) == (4, 2, 200.0)
    frame = camera.grab(0.1)
    assert frame.frame_id == 5 and frame.t == 1e-3
    assert np.array_equal(frame.image, np.full((2, 4), 5, np.uint8))
    with pytest.raises(CameraTimeout):
        camera.grab(0.1)
    camera.close()
    with pytest.raises(CameraClosed):
        camera.grab(0.1)
    with pytest.raises(CameraError, match="no camera with serial 'S9'"):
        GenICamCamera(cti, serial="S9").open()


# ---------------------------------------------------------------------------------------------
# Specs


def test_open_camera_parses_every_form(cell, tmp_path, monkeypatch):
    camera = open_camera("opencv:0")
    assert isinstance(camera, OpenCVCamera) and (camera.source, camera.kind) == (0, "device")
    camera = open_camera("opencv:/dev/video2")
    assert (camera.source, camera.kind) == ("/dev/video2", "device")
    camera = open_camera("video:/data/pass one.avi", fps=50.0)
    assert (camera.source, camera.kind, camera.fps) == ("/data/pass one.avi", "file", 50.0)
    pipeline = "v4l2src device=/dev/video0 ! videoconvert ! appsink"
    camera = open_camera(f"gstreamer:{pipeline}")
    assert (camera.source, camera.kind) == (pipeline, "gstreamer")

    cti = tmp_path / "vendor.cti"
    cti.write_bytes(b"")
    fake_harvesters(monkeypatch)
    camera = open_camera(f"genicam:{cti}#SN 42")
    assert isinstance(camera, GenICamCamera) and (camera.cti_path, camera.serial) == (cti, "SN 42")
    assert open_camera(f"genicam:{cti}").serial is None

    with PassRecorder(tmp_path / "rec", width=6, height=4, fps=20.0,
                      calibration=cell.calibration) as recorder:
        recorder.add_frame(Frame(np.zeros((4, 6), np.uint8), 0, 0.0))
    camera = open_camera(f"replay:{tmp_path / 'rec'}")
    assert isinstance(camera, ReplayCamera) and (camera.width, camera.height) == (6, 4)


@pytest.mark.parametrize("spec", ["", "0", "opencv:", "opencv:abc", "video:", "genicam:",
                                  "genicam:#SN", "replay:", "rtsp://camera/stream", "usb:0"])
def test_open_camera_rejects_a_bad_spec_with_the_forms(spec):
    with pytest.raises(ValueError, match="accepted forms") as info:
        open_camera(spec)
    for form in ("opencv:<index>", "video:<file>", "gstreamer:<pipeline>", "genicam:", "replay:"):
        assert form in str(info.value)
