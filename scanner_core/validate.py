"""Input checks shared by the per-frame algorithms; their errors name the parameter."""
from __future__ import annotations

import numpy as np


def check_image(image) -> np.ndarray:
    """A 2-D uint8 frame, C-contiguous and writable, or ValueError naming `image` and what it
    got. A read-only frame (a camera's or a recording's buffer) is copied (about 0.1 ms for
    1152 x 1200): numba compiles every kernel a second time for read-only arrays, 15 of a
    cold start's 54 s, and a kernel compiled at a pass's first read-only frame would hold
    the GIL for seconds."""
    if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype != np.uint8:
        desc = (f"{image.shape} {image.dtype}" if isinstance(image, np.ndarray)
                else type(image).__name__)
        raise ValueError(f"`image` must be 2-D uint8, got {desc}")
    return np.require(image, requirements=("C", "W"))


def check_columns(columns, width: int, name: str = "columns", *, allow_empty: bool = False
                  ) -> tuple[int, int]:
    """A strip of columns ``(c0, c1)`` within an image ``width`` wide, or ValueError naming it."""
    try:
        c0, c1 = (int(c) for c in columns)
        whole = all(float(c) == int(c) for c in columns)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be a pair of ints (start, stop), got {columns!r}") from None
    if not whole or not (0 <= c0 <= c1 <= width if allow_empty else 0 <= c0 < c1 <= width):
        raise ValueError(f"`{name}` must satisfy 0 <= start {'<=' if allow_empty else '<'} stop "
                         f"<= image width {width}, got {columns!r}")
    return c0, c1
