"""The status page's pictures: the latest frame with what the scanner found on it, and the
last cloud seen from below. Drawn with OpenCV (a few ms), on request only."""
from __future__ import annotations

import cv2
import numpy as np

from scanner_core import stripe
from scanner_core.calibration import Calibration
from scanner_core.pipeline import PipelineParams
from scanner_core.ply import read_ply
from scanner_core.types import Frame, MarkerObservation

#: The frame is shown at this fraction of its size (1920 px wide -> 640).
FRAME_SCALE = 1 / 3
PREVIEW_SIZE = (480, 360)
#: At most this many points are drawn in the preview.
PREVIEW_POINTS = 60000


def frame_png(frame: Frame, marker: MarkerObservation | None, calibration: Calibration,
              params: PipelineParams) -> bytes:
    """(H, W) uint8 frame -> PNG: stripe rows in green, marker views circled in red, the view
    strips outlined."""
    image = cv2.cvtColor(frame.image, cv2.COLOR_GRAY2BGR)
    result = stripe.extract(frame.image, method=params.stripe_method,
                            threshold=params.stripe_threshold_dn, columns=calibration.direct_columns)
    cols = np.nonzero(result.valid)[0]
    rows = np.rint(result.row[cols]).astype(int)
    image[rows, cols] = (0, 255, 0)
    if marker is not None:
        for x, y in marker.pixels:
            if np.isfinite(x):
                cv2.circle(image, (int(round(x)), int(round(y))), 18, (0, 0, 255), 3)
    for c0, c1 in calibration.strips:
        cv2.rectangle(image, (c0, 0), (c1 - 1, image.shape[0] - 1), (255, 160, 0), 2)
    small = cv2.resize(image, None, fx=FRAME_SCALE, fy=FRAME_SCALE, interpolation=cv2.INTER_AREA)
    cv2.putText(small, f"frame {frame.frame_id}", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                (255, 255, 255), 1, cv2.LINE_AA)
    return cv2.imencode(".png", small)[1].tobytes()


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
    return cv2.imencode(".png", image)[1].tobytes()
