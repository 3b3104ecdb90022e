"""The geometric window: per image column, the rows where the stripe can be at all.

The part hangs in the inspection volume below the TCP (x_T and y_T within half its size
either side, z_T from 0 at the gripper to its height). In a frame whose TCP position and
rotation are known (the marker and the robot), only the light sheet's section of that box can
light up: its projection bounds, per column, the rows of any true stripe. A peak outside is a
reflection (off the part onto the cell, or a secondary stripe far from the sheet), the gripper
or stray light, never the stripe (``scanner_core.stripe.extractor.extract``, ``row_min``/``row_max``).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from scanner_core.geometry.calibration import Calibration

#: The box's 12 edges as pairs of corner indices (corner k has bit i set for the upper bound
#: along axis i).
_BOX_EDGES = np.array([(a, a | (1 << i)) for a in range(8) for i in range(3) if not a & (1 << i)])


def volume_box_t(volume_mm, margin_mm: float) -> np.ndarray:
    """(2, 3) float64: the inspection volume's lower and upper corners in {T}, mm, grown by
    `margin_mm` on every side: x_T and y_T within half its size either side, z_T from 0 at
    the gripper to its height (`volume_mm`, (3,))."""
    vol = np.asarray(volume_mm, dtype=np.float64)
    return np.array([[-vol[0] / 2, -vol[1] / 2, 0.0], [vol[0] / 2, vol[1] / 2, vol[2]]]) \
        + np.array([[-margin_mm], [margin_mm]])


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
    lo, hi = volume_box_t(volume_mm, margin_mm)
    out = np.empty((len(_BOX_EDGES), 3))
    k = _section(lo, hi, np.asarray(rotation_b, dtype=np.float64),
                 np.asarray(tcp_b, dtype=np.float64),
                 np.asarray(plane_b.normal, dtype=np.float64), float(plane_b.offset), out)
    return out[:k]


@njit(nogil=True, cache=True)
def _section(lo, hi, rotation, tcp, normal, offset, out):
    """The box ``lo <= x <= hi`` ({T}) placed by ``rotation``, ``tcp`` into {B}, cut by the
    plane ``normal . x = offset``: the crossing points of its edges written into ``out``,
    their count returned. (A dozen tiny numpy calls cost 20 us a frame; this, about 1.)"""
    corners = np.empty((8, 3))
    side = np.empty(8)
    for k in range(8):
        local = np.empty(3)
        for i in range(3):
            local[i] = hi[i] if (k >> i) & 1 else lo[i]
        for i in range(3):
            corners[k, i] = (rotation[i, 0] * local[0] + rotation[i, 1] * local[1]
                             + rotation[i, 2] * local[2] + tcp[i])
        side[k] = (corners[k, 0] * normal[0] + corners[k, 1] * normal[1]
                   + corners[k, 2] * normal[2] - offset)
    n = 0
    for e in range(_BOX_EDGES.shape[0]):
        a = _BOX_EDGES[e, 0]
        b = _BOX_EDGES[e, 1]
        if (side[a] < 0) != (side[b] < 0):
            t = side[a] / (side[a] - side[b])
            for i in range(3):
                out[n, i] = corners[a, i] + t * (corners[b, i] - corners[a, i])
            n += 1
    return n


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
    corners = volume_section_b(tcp_b, rotation_b, volume_mm, margin_mm, calibration.light_plane_b)
    px = cam.project(corners) if len(corners) >= 2 else np.zeros((0, 2))
    return _chord_rows(px, cam.width, float(cam.height), float(margin_px))


@njit(nogil=True, cache=True)
def _chord_rows(px, width, height, margin_px):
    """Per column of a frame ``width`` wide, the span of the rows where the chords between
    any two of the projected corners ``px`` (K, 2; NaN rows skipped) cross it, widened by
    ``margin_px``; ``(height, -1)`` in the columns no chord reaches."""
    row_min = np.full(width, np.inf)
    row_max = np.full(width, -np.inf)
    k = px.shape[0]
    for i in range(k):
        for j in range(i + 1, k):
            u0, v0, u1, v1 = px[i, 0], px[i, 1], px[j, 0], px[j, 1]
            # A chord along a column (du = 0) is skipped: the chords from its two ends reach
            # that column too. A corner behind the camera (NaN) gives no chord.
            if u1 == u0 or not (np.isfinite(u0) and np.isfinite(v0) and np.isfinite(u1)
                                and np.isfinite(v1)):
                continue
            lo = max(int(np.ceil(min(u0, u1))), 0)
            hi = min(int(np.floor(max(u0, u1))), width - 1)
            for c in range(lo, hi + 1):
                v = v0 + (c - u0) / (u1 - u0) * (v1 - v0)
                row_min[c] = min(row_min[c], v)
                row_max[c] = max(row_max[c], v)
    for c in range(width):
        if row_min[c] > row_max[c]:
            row_min[c] = height
            row_max[c] = -1.0
        else:
            row_min[c] -= margin_px
            row_max[c] += margin_px
    return row_min, row_max
