"""The geometric window: per image column, the rows where the stripe can be at all.

The part hangs in the inspection volume below the TCP (x_T and y_T within half its size
either side, z_T from 0 at the gripper to its height). In a frame whose TCP position and
rotation are known (the marker and the robot), only the light sheet's section of that box can
light up: its projection bounds, per column, the rows of any true stripe. A peak outside is a
reflection (off the part onto the cell, or a secondary stripe far from the sheet), the gripper
or stray light, never the stripe (``scanner_core.stripe.extract``, ``row_min``/``row_max``).
"""
from __future__ import annotations

import numpy as np

from scanner_core.calibration import Calibration

#: The box's 12 edges as pairs of corner indices (corner k has bit i set for the upper bound
#: along axis i).
_BOX_EDGES = np.array([(a, a | (1 << i)) for a in range(8) for i in range(3) if not a & (1 << i)])


def volume_section_b(tcp_b, rotation_b, volume_mm, margin_mm: float, plane_b) -> np.ndarray:
    """Corners of the light sheet's section of the inspection volume, {B}, mm.

    Parameters
    ----------
    tcp_b : (3,) float64
        TCP position, {B}, mm.
    rotation_b : (3, 3) float64
        {T}'s rotation in {B}.
    volume_mm : (3,) float
        The inspection volume's size along x_T, y_T, z_T, mm.
    margin_mm : float
        Grown by this on every side (a misplaced part may reach out of it a little).
    plane_b : scanner_core.geometry.Plane
        The light sheet in {B}.

    Returns
    -------
    (K, 3) float64
        The points where the box's edges cross the sheet (K = 0, or 3 to 6), unordered.
    """
    vol = np.asarray(volume_mm, dtype=np.float64)
    lo = np.array([-vol[0] / 2, -vol[1] / 2, 0.0]) - margin_mm
    hi = np.array([vol[0] / 2, vol[1] / 2, vol[2]]) + margin_mm
    bits = (np.arange(8)[:, None] >> np.arange(3)) & 1
    corners_b = np.where(bits, hi, lo) @ np.asarray(rotation_b).T + np.asarray(tcp_b)
    side = corners_b @ plane_b.normal - plane_b.offset
    a, b = corners_b[_BOX_EDGES[:, 0]], corners_b[_BOX_EDGES[:, 1]]
    sa, sb = side[_BOX_EDGES[:, 0]], side[_BOX_EDGES[:, 1]]
    crossing = (sa < 0) != (sb < 0)
    t = sa[crossing] / (sa[crossing] - sb[crossing])
    return a[crossing] + t[:, None] * (b[crossing] - a[crossing])


def volume_rows(calibration: Calibration, tcp_b, rotation_b, volume_mm, *, margin_mm=5.0,
                margin_px=3.0) -> tuple[np.ndarray, np.ndarray]:
    """Per image column, the rows the inspection volume's section of the sheet projects to.

    The section is a convex polygon; its projection is convex too, so a column's range is the
    span of the rows where the column's line crosses the segments joining any two of its
    corners (the polygon's edges are among them; the other chords lie inside it).

    Parameters
    ----------
    calibration : Calibration
    tcp_b, rotation_b, volume_mm, margin_mm
        As for :func:`volume_section_b`.
    margin_px : float
        Rows added either side.

    Returns
    -------
    row_min, row_max : (W,) float64
        px; ``row_min > row_max`` in columns the section does not reach (no stripe possible).
    """
    cam = calibration.camera
    width = cam.width
    row_min = np.full(width, np.inf)
    row_max = np.full(width, -np.inf)
    corners = volume_section_b(tcp_b, rotation_b, volume_mm, margin_mm, calibration.light_plane_b)
    if len(corners) >= 2:
        px = cam.project(corners)
        px = px[np.isfinite(px).all(axis=1)]
        i, j = np.triu_indices(len(px), 1)
        u0, v0, u1, v1 = px[i, 0], px[i, 1], px[j, 0], px[j, 1]
        lo = np.ceil(np.minimum(u0, u1)).astype(np.int64).clip(0, width)
        hi = np.floor(np.maximum(u0, u1)).astype(np.int64).clip(-1, width - 1)
        for k in range(len(u0)):
            # A chord along a column (du = 0) is skipped: the chords from its two ends reach
            # that column too.
            if hi[k] < lo[k] or u1[k] == u0[k]:
                continue
            cols = np.arange(lo[k], hi[k] + 1)
            v = v0[k] + (cols - u0[k]) / (u1[k] - u0[k]) * (v1[k] - v0[k])
            span = slice(lo[k], hi[k] + 1)
            row_min[span] = np.minimum(row_min[span], v)
            row_max[span] = np.maximum(row_max[span], v)
    empty = row_min > row_max
    row_min = np.where(empty, cam.height, row_min - margin_px)
    row_max = np.where(empty, -1.0, row_max + margin_px)
    return row_min, row_max
