"""The status page's pictures: the latest frame with what the scanner found on it, and the
last cloud seen from below. Drawn with OpenCV (a few ms), on request only, and bounded: the
camera, the trigger and the pipeline share the process.

- ``FramePicture``: ``/frame.png`` is rendered at most once per camera frame and at most every
  ``FRAME_PERIOD_S``, one render at a time, on its own thread; every client in between gets the
  same cached bytes. The frame is downscaled first (``cv2.resize``), then drawn and encoded by
  OpenCV, which releases the GIL. The render's full-frame temporaries stay in one thread's
  malloc arena: spread over a pool's threads, each thread's arena kept a copy of them.
- ``PreviewPictures``: a scan's ``preview.png`` is rendered once (on its first request) and kept
  (the last ``PREVIEW_CACHE`` scans); renders run one at a time, and beyond
  ``max_pending`` requests waiting for one the answer is ``Busy`` (a 503 with Retry-After).
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from scanner_core.geometry.calibration import Calibration
from scanner_core.pipeline import PipelineParams
from scanner_core.pipeline.frame import frame_stripe, marker_image
from scanner_core.io.ply import read_ply
from scanner_core.types import Frame, MarkerObservation

#: The frame is shown at this fraction of its size (1920 px wide -> 640).
FRAME_SCALE = 1 / 3
PREVIEW_SIZE = (480, 360)
#: At most this many points are drawn in the preview.
PREVIEW_POINTS = 60000
#: ``/frame.png`` is rendered at most this often, s (5 Hz).
FRAME_PERIOD_S = 0.2
#: Previews kept (the newest requested).
PREVIEW_CACHE = 64
#: PNG compression level of the pictures (OpenCV's default 1 of 0-9 would be bigger; 3 is a few
#: ms for the frame).
PNG_COMPRESSION = 3


def frame_png(frame: Frame, marker: MarkerObservation | None, calibration: Calibration,
              params: PipelineParams) -> bytes:
    """A frame (mono, colour or a mosaic) -> PNG at ``FRAME_SCALE``: its grey, the stripe the
    pipeline measures (``frame_stripe``) in green, marker views circled in red, the view strips
    outlined. Downscaled first: the drawing and the encoding work on a ninth of the pixels."""
    s = FRAME_SCALE
    grey = marker_image(frame.image, params)
    small = cv2.cvtColor(cv2.resize(grey, None, fx=s, fy=s, interpolation=cv2.INTER_AREA),
                         cv2.COLOR_GRAY2BGR)
    h, w = small.shape[:2]
    unplaced = MarkerObservation(np.full((3, 2), np.nan), np.full(3, np.nan), float("nan"))
    result, valid, _ = frame_stripe(frame.image, calibration, params, marker or unplaced)
    cols = np.nonzero(valid)[0]
    rows = np.clip(np.rint(result.row[cols] * s).astype(int), 0, h - 1)
    small[rows, np.clip((cols * s).astype(int), 0, w - 1)] = (0, 255, 0)
    if marker is not None:
        for x, y in marker.pixels:
            if np.isfinite(x):
                cv2.circle(small, (int(round(x * s)), int(round(y * s))), 6, (0, 0, 255), 1)
    for c0, c1 in calibration.strips:
        cv2.rectangle(small, (int(c0 * s), 0), (int((c1 - 1) * s), h - 1), (255, 160, 0), 1)
    cv2.putText(small, f"frame {frame.frame_id}", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                (255, 255, 255), 1, cv2.LINE_AA)
    return _png(small)


def _png(image) -> bytes:
    return cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])[1].tobytes()


class Busy(Exception):
    """Too many requests wait for a render: try again later."""


class FramePicture:
    """``/frame.png``, rendered at most once per frame id and once per ``period_s``; the same
    bytes for every request in between. ``renders`` counts the renders; ``thread`` is the one
    thread to call ``get`` on (``close`` ends it; the next call starts another)."""

    def __init__(self, period_s: float = FRAME_PERIOD_S, clock=time.monotonic):
        self.period_s = period_s
        self._clock = clock
        self._lock = threading.Lock()
        self._kept: tuple[bytes, int, float] | None = None  # (PNG, frame id, when drawn)
        self.renders = 0
        self.thread = self._new_thread()

    @staticmethod
    def _new_thread() -> ThreadPoolExecutor:
        return ThreadPoolExecutor(max_workers=1, thread_name_prefix="frame-picture")

    def close(self) -> None:
        ended, self.thread = self.thread, self._new_thread()  # a thread starts at its first call
        ended.shutdown(wait=True, cancel_futures=True)

    def cached(self, frame_id: int) -> tuple[bytes, int] | None:
        """(PNG, frame id shown) when the picture kept is fresh for ``frame_id``, else None.
        Takes no lock and draws nothing (for the event loop)."""
        kept = self._kept
        if kept is not None and (kept[1] == frame_id or self._clock() - kept[2] < self.period_s):
            return kept[0], kept[1]
        return None

    def get(self, latest, calibration: Calibration, params: PipelineParams) -> tuple[bytes, int]:
        """(PNG, frame id shown) for the engine's ``latest`` (frame, marker)."""
        frame, marker = latest
        with self._lock:  # one render at a time; the others wait for it and share it
            hit = self.cached(frame.frame_id)
            if hit is not None:
                return hit
            png = frame_png(frame, marker, calibration, params)
            self._kept = (png, frame.frame_id, self._clock())  # one assignment: atomic
            self.renders += 1
            return png, frame.frame_id


class PreviewPictures:
    """Scans' ``preview.png``, each rendered once (while its cloud file stays the same) and
    kept for the last ``size`` scans. One render at a time; more than ``max_pending`` requests
    waiting for renders: ``Busy``. ``renders`` counts the renders, ``refused`` the Busy."""

    def __init__(self, max_pending: int, size: int = PREVIEW_CACHE, render=None):
        self.render = render or cloud_preview_png  # path -> PNG bytes
        self.max_pending = max_pending
        self.size = size
        self._state = threading.Lock()
        self._render = threading.Lock()
        self._cache: OrderedDict[tuple, bytes] = OrderedDict()
        self._pending = 0
        self.renders = 0
        self.refused = 0

    @staticmethod
    def _key(scan_id: str, path: Path) -> tuple:
        st = Path(path).stat()
        return scan_id, st.st_mtime_ns, st.st_size

    def cached(self, scan_id: str, path: Path) -> bytes | None:
        """The preview kept for the scan's cloud file as it is, else None (draws nothing)."""
        key = self._key(scan_id, path)
        with self._state:
            return self._hit(key)

    def get(self, scan_id: str, path: Path) -> bytes:
        key = self._key(scan_id, path)
        with self._state:
            if (png := self._hit(key)) is not None:
                return png
            if self._pending >= self.max_pending:
                self.refused += 1
                raise Busy(f"{self._pending} previews are being drawn")
            self._pending += 1
        try:
            with self._render:
                with self._state:
                    png = self._hit(key)
                if png is None:
                    png = self.render(path)
                    with self._state:
                        self.renders += 1
                        for old in [k for k in self._cache if k[0] == scan_id]:
                            del self._cache[old]
                        self._cache[key] = png
                        while len(self._cache) > self.size:
                            self._cache.popitem(last=False)
                return png
        finally:
            with self._state:
                self._pending -= 1

    def _hit(self, key) -> bytes | None:
        png = self._cache.get(key)
        if png is not None:
            self._cache.move_to_end(key)
        return png


def cloud_preview_png(path) -> bytes:
    """The cloud (x, y in {T}) seen along +z_T, coloured by depth z_T."""
    points, _ = read_ply(path)
    w, h = PREVIEW_SIZE
    image = np.full((h, w, 3), 24, np.uint8)
    if len(points):
        pts = np.asarray(points, dtype=np.float64)[:: max(1, len(points) // PREVIEW_POINTS)]
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        span = max(hi[0] - lo[0], hi[1] - lo[1], 1e-6)
        scale = 0.9 * min(w, h) / span
        u = ((pts[:, 0] - (lo[0] + hi[0]) / 2) * scale + w / 2).astype(int)
        v = ((pts[:, 1] - (lo[1] + hi[1]) / 2) * scale + h / 2).astype(int)
        depth = (pts[:, 2] - lo[2]) / max(hi[2] - lo[2], 1e-6)
        colours = cv2.applyColorMap((255 * depth).astype(np.uint8)[:, None], cv2.COLORMAP_VIRIDIS)[:, 0]
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        image[v[inside], u[inside]] = colours[inside]
        cv2.putText(image, f"{len(points)} points", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    (255, 255, 255), 1, cv2.LINE_AA)
    return _png(image)


class NoDeviations(ValueError):
    """The scan's cloud carries no deviation from a model (it was not posed)."""


def deviation_map_png(path) -> bytes:
    """The cloud (x, y in {T}) seen along +z_T, each point coloured by its deviation from the
    model at the pose (``cloud.ply``'s ``deviation``, mm: blue inside, red outside, white on
    it, saturating at the inspection's ``extra_mm``), the failing regions circled (their area,
    at their centre) and named; the verdict at the top. NoDeviations for a cloud without them.
    """
    import json

    points, fields = read_ply(path)
    if "deviation" not in fields:
        raise NoDeviations("the scan has no deviation map: it was not registered to a model")
    report_path = Path(path).with_name("report.json")
    inspection, pose = {}, {}
    try:
        report = json.loads(report_path.read_text())
        inspection, pose = report.get("inspection") or {}, report.get("pose") or {}
    except (OSError, ValueError):
        pass
    limit = float((inspection.get("thresholds") or {}).get("extra_mm") or 0.5)
    w, h = PREVIEW_SIZE
    image = np.full((h, w, 3), 24, np.uint8)
    pts = np.asarray(points, dtype=np.float64)
    dev = np.asarray(fields["deviation"], dtype=np.float64)
    if len(pts):
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        span = max(hi[0] - lo[0], hi[1] - lo[1], 1e-6)
        scale = 0.85 * min(w, h) / span
        to_px = lambda xy: np.c_[(xy[:, 0] - (lo[0] + hi[0]) / 2) * scale + w / 2,
                                 (xy[:, 1] - (lo[1] + hi[1]) / 2) * scale + h / 2]
        uv = to_px(pts).astype(int)
        t = np.clip(np.nan_to_num(dev / limit), -1.0, 1.0)
        # BGR: white on the model, to red outside (t > 0), to blue inside (t < 0)
        colours = np.empty((len(t), 3))
        colours[:, 0] = 255 * (1 - np.clip(t, 0, 1))
        colours[:, 1] = 255 * (1 - np.abs(t))
        colours[:, 2] = 255 * (1 - np.clip(-t, 0, 1))
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        order = np.argsort(np.abs(t[inside]))  # the farthest off drawn last, on top
        image[uv[inside][order, 1], uv[inside][order, 0]] = colours[inside][order].astype(np.uint8)
        matrix = np.asarray(pose.get("matrix") or np.eye(4), dtype=np.float64)
        for region in inspection.get("regions") or ():
            centre_t = matrix[:3, :3] @ np.asarray(region["centre_p_mm"]) + matrix[:3, 3]
            (u, v), = to_px(centre_t[None, :2]).astype(int)
            radius = max(int(np.sqrt(region["area_mm2"] / np.pi) * scale) + 4, 8)
            cv2.circle(image, (int(u), int(v)), radius, (0, 255, 255), 1, cv2.LINE_AA)
            cv2.putText(image, region["kind"].replace("_", " "), (int(u) + radius + 2, int(v)),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 255, 255), 1, cv2.LINE_AA)
    verdict = ("conforms" if inspection.get("conforms")
               else "fails: " + ", ".join(inspection.get("failing") or ["?"])
               if inspection else "deviation")
    cv2.putText(image, f"{verdict}; +-{limit:.2f} mm", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                (255, 255, 255), 1, cv2.LINE_AA)
    return _png(image)
