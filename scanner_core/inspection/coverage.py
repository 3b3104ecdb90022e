"""What the scan should have seen of the model at the pose and found no point on: missing
material where the scanner sees nothing (a hole added, a face or a corner cut away through
the part, a shorter part).

The prediction is the scanner's own, from what it knows: the model at the registered pose,
and each placed frame's light plane and camera centre in {T} (``Scan.sheet_planes_t``,
``Scan.sensor_positions_t``: the calibration's sheet and camera, placed by the frame's
gripper pose). For a sample ``q`` of the model's surface (normal ``n``):

- **crossed**: the sheet swept over ``q`` between two placed frames no farther apart than
  ``GAP_STEPS`` of the pass's median step (a dropped frame leaves its stretch unpredicted);
  ``q`` belongs to the nearer of the two frames;
- **lit and seen**: at that frame, ``n`` turns to the camera centre ``C`` and to the laser's
  source ``L`` within ``MAX_INCIDENCE_DEG``, and no part of the model lies between ``q`` and
  either (rays cast against the mesh);
- **covered**: a point of its own frame's profile lies within ``COVER_STEPS`` point steps of
  ``q``, a step along the pass between two frames' sheets counting as ``FRAME_STEPS`` point
  steps (the sample lies at most half a step off that sheet). Each profile answers for the
  samples nearer its sheet than any other's, as a hole's true edge between two profiles is
  as likely nearer the one as the other: a neighbouring profile, whose points beside a hole
  lie a step away, says nothing of the samples the hole's own profile crossed. On a face
  inclined to the sheet (``n . m = sin b`` for the pass direction ``m``) a profile lies
  ``s tan b`` across from a sample ``s`` beyond it, and that is allowed for.

Missing: crossed, lit and seen, not covered. The calibration does not hold the laser's
source: it is taken at the foot of the camera centre on the sheet, ``L = C - (n_s . C -
o_s) n_s`` (a sheet shining up from below the part and a camera beside it at the
triangulation angle put it there within some tens of mm), and a sample counts as lit only
when it is lit from there and from ``LASER_SOURCE_SPREAD_MM`` to either side of it along the
sheet: a shadow's edge is uncertain, so the prediction keeps to what every plausible source
lights. A region counts only from its *core*: missing samples with at most
``1 - CORE_SHARE`` of their neighbours within the margin (the pass's profile step, at least
``MIN_MARGIN_STEPS`` sample spacings) unexpected (not crossed, turned away, hidden), away
from the prediction's edges (a silhouette's, a grazing face's, a partly lit end's), and at
least ``MISSING_SHARE`` of them missing (no sliver narrower than the margin), and missing
from the other bracketing profile's view too (where a face's edge lies between two sheets,
the nearer one may pass beyond it); a hole in a face, ringed by covered samples, has one
when it is wider than about twice the margin.

A narrower hole, crossed by two profiles, has a core of another kind: on each of them a
*ringed stretch*, missing samples that lie along the profile's line on their face with a
covered sample of that profile as the nearest one on either side (not an unexpected one,
nor none: a face's end, a shadow, the pass's end), and a ringed stretch of another profile
within ``PAIR_MARGINS`` margins (one profile's gap is a glint's or a speck's as likely as
the part's). Samples within a margin of the model's sharp edges are left out of it: where a
profile ends beside an edge decides whether a sample there is covered.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from scanner_core.geometry import planes_moved

__all__ = ["MissingSamples", "ProfileIndex", "missing_samples", "sheet_crossings",
           "bracketing_frames", "lit_and_seen", "warm_up_coverage", "MAX_INCIDENCE_DEG",
           "GAP_STEPS", "COVER_STEPS",
           "FRAME_STEPS", "CORE_SHARE", "COVERAGE_SPACING_MM", "LASER_SOURCE_SPREAD_MM",
           "RING_MARGINS", "MIN_STRETCH_SAMPLES", "PAIR_MARGINS"]

#: A face turned farther than this from the camera or the laser returns too little light to
#: be counted on (a grazing face drops out of real scans first).
MAX_INCIDENCE_DEG = 60.0
#: The laser's source is taken this far to either side of the camera's foot on the sheet too.
LASER_SOURCE_SPREAD_MM = 100.0
#: Two placed frames farther apart than this many median steps: a frame lost between them,
#: and nothing predicted there.
GAP_STEPS = 1.5
#: A sample is covered by a cloud point within this many point steps (scaled distance).
COVER_STEPS = 3.0
#: ... a step between two frames' sheets counting as this many point steps.
FRAME_STEPS = 3.0
#: A core sample: at least this share of its neighbours within the margin expected.
CORE_SHARE = 0.9
#: ... and at least this share of them missing: a region narrower than the margin (a thin
#: ledge, which the stripe crosses in too few pixels to be kept as a profile's segment) is
#: not one the scan can be said to have missed.
MISSING_SHARE = 0.5
#: The margin is at least this many sample spacings.
MIN_MARGIN_STEPS = 2.0
#: A stretch of a profile missing, ringed by covered samples of that profile: looked for
#: within this many margins of each missing sample, ...
RING_MARGINS = 2.5
#: ... among the samples this many spacings off its tangent plane at most, and turned from its
#: normal by less than this (the same face, a curved one's too), ...
RING_BAND_SPACINGS = 0.5
RING_TURN_DEG = 30.0
#: ... holding at least this many missing samples; and with a ringed sample of another
#: profile within this many margins.
MIN_STRETCH_SAMPLES = 2
PAIR_MARGINS = 2.0
#: Spacing of the model's samples the coverage is judged on, mm (``PartModel.coverage_model``).
COVERAGE_SPACING_MM = 0.6
#: Rays leave a sample this far off its face, mm, so as not to meet the face itself.
RAY_OFFSET_MM = 0.02


@dataclass(frozen=True)
class MissingSamples:
    """The model's samples the scan should have seen and has no point on.

    Attributes
    ----------
    index : (K,) int64
        Into the samples.
    core : (K,) bool
        Deep in missing ones (the module's docstring): a region counts only with one.
    frame : (K,) int64
        The placed frame (index into ``Scan.sheet_planes_t``) whose sheet crossed each.
    """

    index: np.ndarray
    core: np.ndarray
    frame: np.ndarray


NONE_MISSING = MissingSamples(np.zeros(0, np.int64), np.zeros(0, bool), np.zeros(0, np.int64))


def sheet_crossings(samples_p: np.ndarray, planes_p: np.ndarray):
    """The frame whose sheet crossed each sample, where two placed frames bracket it closely.

    Parameters
    ----------
    samples_p : (M, 3) float64
        mm in {P}.
    planes_p : (F, 4) float64
        Each placed frame's sheet in {P}, ``(n, offset)`` with ``n . x = offset``.

    Returns
    -------
    frame : (M,) int64
        Index into the F frames of the nearer bracketing frame; -1 where none brackets the
        sample within ``GAP_STEPS`` of the median step (before or after the pass, or over a
        lost frame).
    step_mm : float
        The median step between neighbouring frames' sheets, mm (NaN: fewer than 2 frames).
    direction : (3,) float64
        The sheets' mean normal in {P}.
    """
    frame, _, step, direction = bracketing_frames(samples_p, planes_p)
    return frame, step, direction


def bracketing_frames(samples_p: np.ndarray, planes_p: np.ndarray, sensors_p=None,
                      normals_p=None, max_incidence_deg: float = MAX_INCIDENCE_DEG):
    """``sheet_crossings``, and the farther of the two bracketing frames too: ``(nearer
    (M,), farther (M,), step_mm, direction)``, both -1 where no two bracket a sample.

    With `sensors_p` (F, 3) and `normals_p` (M, 3), also -1 where the sample's face turns
    farther than `max_incidence_deg` from the nearer frame's camera centre, or is so square
    to the pass (``|n . m| > sin`` of it) that no light in the sheet meets it within it.
    """
    samples_p = np.asarray(samples_p, dtype=np.float64).reshape(-1, 3)
    if len(planes_p) < 2:
        none = np.full(len(samples_p), -1, np.int64)
        return none, none.copy(), float("nan"), np.array([0.0, 0.0, 1.0])
    normals = planes_p[:, :3]
    direction = normals.mean(axis=0)
    direction /= np.linalg.norm(direction)
    # the sheets' positions along their mean normal (they turn by the robot's few mdeg)
    positions = planes_p[:, 3] / (normals @ direction)
    order = np.argsort(positions)
    sorted_positions = np.ascontiguousarray(positions[order])
    step = float(np.median(np.diff(sorted_positions)))
    facing = sensors_p is not None and normals_p is not None
    limit = math.radians(max_incidence_deg)
    # without the facing test the kernel never reads normals or sensors: any arrays of their
    # types stand in, so that one compiled signature serves both
    nearer, farther = _bracket(
        np.ascontiguousarray(samples_p), sorted_positions, order.astype(np.int64), direction,
        GAP_STEPS * step,
        np.ascontiguousarray(normals_p if facing else samples_p, dtype=np.float64),
        np.ascontiguousarray(sensors_p if facing else planes_p[:, :3], dtype=np.float64),
        facing, math.cos(limit), math.sin(limit))
    return nearer, farther, step, direction


def warm_up_coverage() -> float:
    """Compile `bracketing_frames`', `ProfileIndex`'s and `lit_and_seen`'s kernels before the
    first check (some 1-2 s on a fresh install, and the compiler's memory with it, which the
    first pass would otherwise take): three samples and two sheets, with the argument types a
    check gives them. Returns the time it took, ms."""
    t0 = time.perf_counter()
    samples = np.array([[0.0, 0.5, 0.0], [0.0, 0.2, 1.0], [0.0, 3.0, 0.0]])
    planes = np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 1.0, 0.0, 1.0]])
    bracketing_frames(samples, planes, np.array([[0.0, 0.0, 50.0], [0.0, 1.0, 50.0]]),
                      np.tile([0.0, 0.0, 1.0], (3, 1)))
    ProfileIndex(samples, np.array([0, 1, -1]), 2, planes[0, :3]).covered(
        samples, np.array([0, 1, 1]), np.ones(3))
    lit_and_seen(samples, np.tile([0.0, 0.0, 1.0], (3, 1)), np.tile([0.0, 0.0, 50.0], (3, 1)),
                 np.tile(planes[0], (3, 1)))
    return (time.perf_counter() - t0) * 1e3


@njit(nogil=True, cache=True)
def _bracket(points, sorted_positions, order, direction, widest, normals, sensors, facing,
             cos_limit, sin_limit):
    """The loop of ``bracketing_frames``, one sample at a time (no (M, 3) temporaries)."""
    m, f = points.shape[0], sorted_positions.shape[0]
    nearer = np.full(m, -1, np.int64)
    farther = np.full(m, -1, np.int64)
    first, last = sorted_positions[0], sorted_positions[f - 1]
    # the sheets lie about evenly apart: the first position at or beyond a height is found
    # from a guess in a step or two (a binary search's mispredicted branches cost more)
    per_step = (f - 1) / (last - first) if last > first else 0.0
    for i in range(m):
        height = (points[i, 0] * direction[0] + points[i, 1] * direction[1]
                  + points[i, 2] * direction[2])
        if height <= first or height > last:
            continue
        right = min(max(int((height - first) * per_step), 1), f - 1)
        while sorted_positions[right - 1] >= height:
            right -= 1
        while sorted_positions[right] < height:
            right += 1
        left = right - 1
        if sorted_positions[right] - sorted_positions[left] > widest:
            continue
        if height - sorted_positions[left] <= sorted_positions[right] - height:
            near, far = order[left], order[right]
        else:
            near, far = order[right], order[left]
        if facing:
            along = (normals[i, 0] * direction[0] + normals[i, 1] * direction[1]
                     + normals[i, 2] * direction[2])
            if abs(along) > sin_limit:
                continue
            dx = sensors[near, 0] - points[i, 0]
            dy = sensors[near, 1] - points[i, 1]
            dz = sensors[near, 2] - points[i, 2]
            turn = normals[i, 0] * dx + normals[i, 1] * dy + normals[i, 2] * dz
            if turn <= cos_limit * math.sqrt(dx * dx + dy * dy + dz * dz):
                continue
        nearer[i], farther[i] = near, far
    return nearer, farther


class ProfileIndex:
    """A cloud's points by profile, each profile's sorted along one axis across the pass:
    whether a profile holds a point within a radius of a query is a binary search and a
    scan of the points within the radius along that axis, stopped at the first one near
    enough. (A KD-tree over the cloud, a fourth coordinate keeping profiles apart, is
    slower to build and to ask: a profile's points lie along a curve, and the tree's cells
    hold many profiles.)

    Parameters
    ----------
    points : (N, 3) float64
        The cloud, mm (in whatever metric the queries use: ``missing_samples`` squeezes the
        pass's direction).
    profiles : (N,) int64
        Each point's profile, ``0 .. count - 1``; -1: none (the point is never asked for).
    count : int
        The number of profiles.
    direction : (3,) float64
        The pass's direction (unit): the points are sorted along the axis across it in which
        the cloud spreads most.
    shrink : float
        Distances along `direction` count this many times theirs (points and queries alike
        moved to ``x + (shrink - 1) (x . m) m``): ``missing_samples`` counts a frame's step
        as a few point steps.
    """

    def __init__(self, points: np.ndarray, profiles: np.ndarray, count: int,
                 direction: np.ndarray, shrink: float = 1.0):
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        self.direction = np.ascontiguousarray(direction, dtype=np.float64)
        self.shrink = float(shrink)
        across = np.linalg.svd(np.eye(3) - np.outer(self.direction, self.direction))[0][:, :2]
        # (2, N): a reduction along axis 0 of an (N, 2) array is far slower
        spans = np.ptp(across.T @ points.T, axis=1) if len(points) else np.zeros(2)
        self.axis = np.ascontiguousarray(across[:, int(np.argmax(spans))])
        self.points, self.along, self.starts = _sort_by_profile(
            points, np.asarray(profiles, dtype=np.int64), int(count), self.axis,
            self.direction, self.shrink - 1.0)

    def covered(self, query: np.ndarray, profiles: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """(M,) bool: whether profile ``profiles[i]`` holds a point within ``radius[i]``
        (mm) of ``query[i]`` (M, 3); False for a profile outside ``0 .. count - 1``."""
        query = np.ascontiguousarray(query, dtype=np.float64).reshape(-1, 3)
        return _covered(self.points, self.along, self.starts, query,
                        np.asarray(profiles, dtype=np.int64),
                        np.broadcast_to(np.asarray(radius, dtype=np.float64), len(query)).copy(),
                        self.axis, self.direction, self.shrink - 1.0)


@njit(nogil=True, cache=True)
def _sort_by_profile(points, profiles, count, axis, direction, stretch):
    """``ProfileIndex``'s arrays: the points grouped by profile (a counting sort), each
    group sorted along `axis` and squeezed along `direction` (``x + stretch (x . m) m``);
    their coordinate along `axis` (square to `direction`); where each group starts
    (count+1)."""
    starts = np.zeros(count + 1, np.int64)
    for p in profiles:
        if 0 <= p < count:
            starts[p + 1] += 1
    for k in range(count):
        starts[k + 1] += starts[k]
    fill = starts[:-1].copy()
    along = np.empty(starts[count])
    slot = np.empty(starts[count], np.int64)
    for i in range(points.shape[0]):
        p = profiles[i]
        if 0 <= p < count:
            j = fill[p]
            fill[p] += 1
            slot[j] = i
            along[j] = points[i, 0] * axis[0] + points[i, 1] * axis[1] + points[i, 2] * axis[2]
    grouped = np.empty((starts[count], 3))
    sorted_along = np.empty(starts[count])
    for k in range(count):
        a, b = starts[k], starts[k + 1]
        rising = falling = True  # a profile's points come by column: often sorted already
        for j in range(a + 1, b):
            rising &= along[j] >= along[j - 1]
            falling &= along[j] <= along[j - 1]
        if rising:
            order = np.arange(b - a)
        elif falling:
            order = np.arange(b - a)[::-1]
        else:
            order = np.argsort(along[a:b], kind="mergesort")
        for r in range(b - a):
            j = a + order[r]
            sorted_along[a + r] = along[j]
            grouped[a + r, 0], grouped[a + r, 1], grouped[a + r, 2] = _squeezed(
                points, slot[j], direction, stretch)
    return grouped, sorted_along, starts


@njit(nogil=True, cache=True, inline="always")
def _squeezed(points, i, direction, stretch):
    """Point ``i`` of `points` (N, 3) moved to ``x + stretch (x . m) m``, m `direction`."""
    moved = stretch * (points[i, 0] * direction[0] + points[i, 1] * direction[1]
                       + points[i, 2] * direction[2])
    return (points[i, 0] + moved * direction[0], points[i, 1] + moved * direction[1],
            points[i, 2] + moved * direction[2])


@njit(nogil=True, cache=True)
def _covered(points, along, starts, query, profiles, radius, axis, direction, stretch):
    """``ProfileIndex.covered``'s loop, one query at a time, each squeezed as the points
    are."""
    m, count = query.shape[0], starts.shape[0] - 1
    out = np.zeros(m, np.bool_)
    for i in range(m):
        p = profiles[i]
        if p < 0 or p >= count:
            continue
        a, b = starts[p], starts[p + 1]
        x, y, z = _squeezed(query, i, direction, stretch)
        r = radius[i]
        u = x * axis[0] + y * axis[1] + z * axis[2]
        lo = a + np.searchsorted(along[a:b], u - r)
        for j in range(lo, b):
            if along[j] > u + r:
                break
            dx, dy, dz = points[j, 0] - x, points[j, 1] - y, points[j, 2] - z
            if dx * dx + dy * dy + dz * dz <= r * r:
                out[i] = True
                break
    return out


def lit_and_seen(samples_p, normals_p, sensors_p, sheets_p, occluded=None, *,
                 max_incidence_deg: float = MAX_INCIDENCE_DEG, sources_p=None) -> np.ndarray:
    """Which samples the laser lights and the camera sees, each at its own frame.

    Parameters
    ----------
    samples_p, normals_p : (K, 3) float64
        Points of the model's surface and their outward unit normals, {P}.
    sensors_p : (K, 3) float64
        The camera centre of each sample's frame, {P}.
    sheets_p : (K, 4) float64
        That frame's sheet, ``(n, offset)``.
    occluded : callable(origins (R, 3), directions (R, 3)) -> (R,) bool, optional
        Whether a ray meets the model (``PartModel.occluded``); None: the faces' turn alone.
    max_incidence_deg : float
    sources_p : (K, 3) float64, optional
        The laser's source for each sample where it is known (the simulator's, for an
        evaluation): its light alone; None: the camera's foot on the sheet, and to either
        side (the module's docstring).

    Returns
    -------
    (K,) bool
    """
    if not len(samples_p):
        return np.zeros(0, bool)
    cos_limit = math.cos(math.radians(max_incidence_deg))
    samples_p = np.ascontiguousarray(samples_p, dtype=np.float64)
    normals_p = np.ascontiguousarray(normals_p, dtype=np.float64)
    sensors_p = np.ascontiguousarray(sensors_p, dtype=np.float64)
    if sources_p is None:
        rays = _light_rays(samples_p, sensors_p, np.ascontiguousarray(sheets_p, np.float64),
                           LASER_SOURCE_SPREAD_MM)
    else:
        rays = np.stack([sensors_p - samples_p,
                         np.asarray(sources_p, dtype=np.float64) - samples_p])
    out = _facing_all(normals_p, rays, cos_limit)
    if occluded is None:
        return out
    for ray in rays:
        which = np.nonzero(out)[0]
        if not len(which):
            break
        origins = samples_p[which] + RAY_OFFSET_MM * normals_p[which]
        out[which[occluded(origins, ray[which])]] = False
    return out


@njit(nogil=True, cache=True)
def _light_rays(samples, sensors, sheets, spread):
    """(4, K, 3): from each sample to its frame's camera centre, then to the laser's source at
    the camera's foot on the sheet, ``L = C - (n_s . C - o_s) n_s``, and `spread` mm to
    either side of it along the sheet (square to the light's way to the sample)."""
    count = samples.shape[0]
    rays = np.empty((4, count, 3))
    for i in range(count):
        nx, ny, nz = sheets[i, 0], sheets[i, 1], sheets[i, 2]
        foot = nx * sensors[i, 0] + ny * sensors[i, 1] + nz * sensors[i, 2] - sheets[i, 3]
        tx = sensors[i, 0] - foot * nx - samples[i, 0]
        ty = sensors[i, 1] - foot * ny - samples[i, 1]
        tz = sensors[i, 2] - foot * nz - samples[i, 2]
        ax, ay, az = ny * tz - nz * ty, nz * tx - nx * tz, nx * ty - ny * tx
        scale = spread / max(math.sqrt(ax * ax + ay * ay + az * az), 1e-12)
        ax, ay, az = ax * scale, ay * scale, az * scale
        for c in range(3):
            rays[0, i, c] = sensors[i, c] - samples[i, c]
        rays[1, i, 0], rays[1, i, 1], rays[1, i, 2] = tx, ty, tz
        rays[2, i, 0], rays[2, i, 1], rays[2, i, 2] = tx - ax, ty - ay, tz - az
        rays[3, i, 0], rays[3, i, 1], rays[3, i, 2] = tx + ax, ty + ay, tz + az
    return rays


@njit(nogil=True, cache=True)
def _facing_all(normals, rays, cos_limit):
    """(K,) bool: whether each sample's face turns within the limit to every one of its rays
    (R, K, 3): ``n . r > cos_limit |r|``."""
    count = normals.shape[0]
    out = np.ones(count, np.bool_)
    for r in range(rays.shape[0]):
        for i in range(count):
            if not out[i]:
                continue
            x, y, z = rays[r, i, 0], rays[r, i, 1], rays[r, i, 2]
            turn = normals[i, 0] * x + normals[i, 1] * y + normals[i, 2] * z
            out[i] = turn > cos_limit * math.sqrt(x * x + y * y + z * z)
    return out


def missing_samples(points_p: np.ndarray, samples, occluded, pose_matrix: np.ndarray,
                    sheet_planes_t: np.ndarray, sensor_positions_t: np.ndarray, *,
                    point_spacing_mm: float, frame_ids=None,
                    sheet_frame_ids=None, sharp_edges=None,
                    measured_box_t=None) -> MissingSamples:
    """The model's samples the scan should have seen at this pose and has no point near.

    Parameters
    ----------
    points_p : (N, 3) float64
        The cloud in {P}, mm.
    samples : scanner_core.pose.models.SurfaceModel
        The model's surface samples (``PartModel.coverage_model``), {P}, with their tree.
    occluded : callable(origins, directions) -> bool array
        Whether rays in {P} meet the model (``PartModel.occluded``).
    pose_matrix : (4, 4) float64
        The registered ^T X_P.
    sheet_planes_t, sensor_positions_t : (F, 4), (F, 3) float64
        ``Scan.sheet_planes_t``, ``Scan.sensor_positions_t``.
    point_spacing_mm : float
        The step between a profile's points, mm.
    frame_ids : (N,) int, optional
        Each point's frame; None: any profile covers any sample (the scan's frames unknown).
    sheet_frame_ids : (F,) int, optional
        The frame of each sheet, as ``frame_ids`` names them; None: ``0 .. F-1``.
    sharp_edges : scanner_core.pose.models.EdgeModel, optional
        The model's sharp edges, with their tree (``PartModel.edge_model``): with them and
        `frame_ids`, a stretch of a profile ringed by its own covered samples is a core too
        (the module's docstring).
    measured_box_t : (2, 3) float, optional
        The box in {T} (lower and upper corners, mm) outside which the pass measured nothing
        (``Scan.measured_box_t``): a sample outside it at the pose is not expected.

    Returns
    -------
    MissingSamples
        None missing where the scan carries no sheets (a scan made by hand, a file's).
    """
    sheet_planes_t = np.asarray(sheet_planes_t, dtype=np.float64).reshape(-1, 4)
    sensors_t = np.asarray(sensor_positions_t, dtype=np.float64).reshape(-1, 3)
    if len(sheet_planes_t) < 2 or len(sensors_t) != len(sheet_planes_t) or not len(points_p):
        return NONE_MISSING
    pose = np.asarray(pose_matrix, dtype=np.float64)
    rotation, translation = pose[:3, :3], pose[:3, 3]
    planes_p = planes_moved(sheet_planes_t, rotation.T, -rotation.T @ translation)
    sensors_p = (sensors_t - translation) @ rotation
    # crossed, turned to the camera, and not so square to the pass that no light in the
    # sheet meets it within the limit (the laser's exact turn and the rays later, on the
    # uncovered few)
    frame, other, step, direction = bracketing_frames(samples.points, planes_p, sensors_p,
                                                      samples.normals)
    if not (math.isfinite(step) and step > 0):
        return NONE_MISSING
    point_step = point_spacing_mm if math.isfinite(point_spacing_mm) and point_spacing_mm > 0 \
        else step
    crossed = np.nonzero(frame >= 0)[0]
    if measured_box_t is not None and len(crossed):
        # the scanner looks for the stripe only within its volume: a part tilted out of it
        # (a wide disc's rim above the gripper's plane) is cut off there, not missing
        box = np.asarray(measured_box_t, dtype=np.float64).reshape(2, 3)
        at_t = samples.points[crossed] @ rotation.T + translation
        crossed = crossed[np.all((at_t >= box[0]) & (at_t <= box[1]), axis=1)]
    if not len(crossed):  # the sheets met none of the model (a pass's first frames alone)
        return NONE_MISSING
    q, n = samples.points[crossed], samples.normals[crossed]
    # covered: a cloud point near, a frame's step along the pass counting FRAME_STEPS points'
    shrink = min(FRAME_STEPS * point_step / step, 1.0)

    sine = np.abs(n @ direction)
    radius = COVER_STEPS * point_step + 0.5 * step * sine / np.sqrt(1.0 - sine**2)
    if frame_ids is not None:
        # each sample is asked of its own frame's profile only
        sheets = (np.arange(len(sheet_planes_t)) if sheet_frame_ids is None
                  else np.asarray(sheet_frame_ids))
        order = np.argsort(sheets)
        slot = np.clip(np.searchsorted(sheets[order], frame_ids), 0, len(order) - 1)
        own = np.where(sheets[order][slot] == frame_ids, order[slot], -1)
        profiles = ProfileIndex(points_p, own, len(sheet_planes_t), direction, shrink)
        is_covered = profiles.covered(q, frame[crossed], radius)
    else:
        is_covered = ProfileIndex(points_p, np.zeros(len(points_p), np.int64), 1,
                                  direction, shrink).covered(q, np.zeros(len(q), np.int64),
                                                             radius)
    open_ = np.nonzero(~is_covered)[0]
    if not len(open_):
        return NONE_MISSING
    which = crossed[open_]
    seen = lit_and_seen(q[open_], n[open_], sensors_p[frame[which]], planes_p[frame[which]],
                        occluded)
    missing = which[seen]
    if not len(missing):
        return NONE_MISSING
    # the core: missing samples whose neighbours are expected (covered or missing), away
    # from the prediction's edges
    status = np.zeros(len(samples.points), np.int8)  # 0 unexpected, 1 covered, 2 missing
    status[crossed[is_covered]] = 1
    status[missing] = 2
    margin = max(step, MIN_MARGIN_STEPS * samples.spacing_mm)
    at = samples.points[missing]
    # each missing sample's neighbours by their status: as many nearest as the fullest ball
    # holds, in arrays (a ball's list of Python ints for each of thousands of missing
    # samples is memory the interpreter keeps), not a tree over the thousands expected
    most = int(samples.tree.query_ball_point(at, margin, return_length=True, workers=1).max())
    _, neighbour = samples.tree.query(at, k=max(most, 1), distance_upper_bound=margin,
                                      workers=1)
    neighbour = neighbour.reshape(len(at), -1)
    inside = neighbour < len(samples.points)
    around_status = np.where(inside, status[np.minimum(neighbour, len(samples.points) - 1)],
                             -1)
    sizes = inside.sum(axis=1)
    expected = (around_status > 0).sum(axis=1)
    gone = (around_status == 2).sum(axis=1)
    core = (expected >= CORE_SHARE * sizes) & (gone >= MISSING_SHARE * sizes)
    if frame_ids is not None and core.any():
        # and missing from the other bracketing profile's view too: where a face's edge lies
        # between the two sheets, the sample's own sheet may pass beyond it
        ask = np.nonzero(core)[0]
        reach = radius[np.searchsorted(crossed, missing[ask])]
        core[ask[profiles.covered(at[ask], other[missing[ask]], reach)]] = False
    if frame_ids is not None and sharp_edges is not None and not core.all():
        # a hole between one and two margins wide holds no such sample, but each profile that
        # crossed it has a stretch missing with its own covered samples either side; within a
        # margin of a sharp edge, where a profile ends decides whether a sample is covered
        rest = np.nonzero(~core)[0]
        edge, _ = sharp_edges.tree.query(at[rest], distance_upper_bound=margin, workers=1)
        rest = rest[np.isinf(edge)]
        rest = rest[_paired(at[rest], frame[missing[rest]], margin)]
        rest = rest[_ringed_stretches(samples, status, missing[rest], frame[missing[rest]],
                                      planes_p, step, margin)]
        core[rest[_paired(at[rest], frame[missing[rest]], margin)]] = True
    return MissingSamples(missing, core, frame[missing])


def _ringed_stretches(samples, status: np.ndarray, which: np.ndarray, frames: np.ndarray,
                      planes_p: np.ndarray, step: float, margin: float) -> np.ndarray:
    """Which of the missing samples `which` (K,) lie on a stretch of their own profile that
    is ringed by covered samples of it: along the profile's line on the sample's face (``t =
    m x n``, the sheet's normal ``m`` and the face's ``n``), among the samples within half a
    step of the sample's sheet (`frames` (K,), into `planes_p`) and on its face (within
    ``RING_BAND_SPACINGS`` of its tangent plane, turned less than ``RING_TURN_DEG``), the
    nearest sample that is not missing on each side, within ``RING_MARGINS`` margins, is
    covered, and at least ``MIN_STRETCH_SAMPLES`` missing ones lie between the two. `status`
    (M,) int8: 0 unexpected, 1 covered, 2 missing, over all the samples. Returns (K,) bool.

    A face's edge, a shadow or a silhouette ends a stretch with an unexpected sample, or
    with none: only a gap inside the face a profile was seen on is ringed."""
    if not len(which):
        return np.zeros(0, bool)
    points, normals = samples.points, samples.normals
    at, up = points[which], normals[which]
    reach = RING_MARGINS * margin
    most = int(samples.tree.query_ball_point(at, reach, return_length=True, workers=1).max())
    _, near = samples.tree.query(at, k=max(most, 1), distance_upper_bound=reach, workers=1)
    near = near.reshape(len(at), -1)
    inside = near < len(points)
    near = np.minimum(near, len(points) - 1)
    offset = points[near] - at[:, None, :]
    sheet = planes_p[frames]
    beside = np.einsum("kjd,kd->kj", points[near], sheet[:, :3]) - sheet[:, 3:4]
    on_face = ((np.abs(np.einsum("kjd,kd->kj", offset, up))
                <= RING_BAND_SPACINGS * samples.spacing_mm)
               & (np.einsum("kjd,kd->kj", normals[near], up)
                  >= math.cos(math.radians(RING_TURN_DEG))))
    along = np.cross(sheet[:, :3], up)
    along /= np.maximum(np.linalg.norm(along, axis=1, keepdims=True), 1e-12)
    u = np.einsum("kjd,kd->kj", offset, along)
    line = inside & on_face & (np.abs(beside) <= 0.5 * step)
    state = status[near]
    ends = []
    for side in (-1.0, 1.0):
        # the nearest sample on this side that is not missing: covered, or the stretch is
        # not ringed
        distance = np.where(line & (side * u > 0) & (state != 2), side * u, np.inf)
        first = np.argmin(distance, axis=1)
        rows = np.arange(len(at))
        ringed = np.isfinite(distance[rows, first]) & (state[rows, first] == 1)
        ends.append((ringed, side * distance[rows, first]))
    (left_ok, left), (right_ok, right) = ends
    between = (line & (state == 2) & (u > left[:, None]) & (u < right[:, None])).sum(axis=1)
    return left_ok & right_ok & (between >= MIN_STRETCH_SAMPLES)


def _paired(at: np.ndarray, frames: np.ndarray, margin: float) -> np.ndarray:
    """Which of the samples at `at` (K, 3) have one of another profile (`frames` (K,))
    within ``PAIR_MARGINS`` margins: a gap one profile alone shows is a glint's or a speck's
    as likely as the part's."""
    if len(at) < 2:
        return np.zeros(len(at), bool)
    pairs = cKDTree(at).query_pairs(PAIR_MARGINS * margin, output_type="ndarray")
    other = frames[pairs[:, 0]] != frames[pairs[:, 1]]
    out = np.zeros(len(at), bool)
    out[pairs[other].ravel()] = True
    return out

