"""The error of the real camera backends (``service.cameras``, ``service.pylon_camera``)."""
from __future__ import annotations

__all__ = ["CameraError"]


class CameraError(RuntimeError):
    """A camera cannot be opened or gives frames the scanner cannot use."""
