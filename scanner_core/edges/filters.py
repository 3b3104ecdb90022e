"""Edge points judged by the whole scan: what one profile cannot tell about its drop-outs
and steps, the scan's other profiles can.

- `occluded_dropouts`: drop-outs where the stripe vanished behind another part of the part
  (the line of sight past the edge runs through surface other profiles measured);
- `chamfered_dropouts`: drop-outs of an outline chamfered narrower than two columns, placed
  at the outline by the chamfer fitted along the edge's profiles;
- `grazing_edges`: edge points on a surface the light sheet grazes.

They run on a scan's edge cloud in {T} (``scanner_core.pipeline``); the edge kinds the scan
sets aside, with and without the part's model, are ``scanner_core.edges.kinds``.
"""
from __future__ import annotations

import math

import numpy as np

from scanner_core.edges.kernel import ROW_BEND_PX

__all__ = ["occluded_dropouts", "chamfered_dropouts", "grazing_edges", "CHAMFER_MAX_LEVEL",
           "CHAMFER_MIN_POINTS", "CHAMFER_MIN_GAIN", "CHAIN_FRAMES", "CHAIN_DEG",
           "CHAIN_SPACINGS", "CHAIN_MIN_MM", "GRAZING_DEG", "LONE_PROFILE_REACH"]


def occluded_dropouts(points_t, across_t, sensors_t, cloud_t, *, probe_mm: float = 0.5,
                      radius_mm: float = 1.0, clearance_mm: float = 2.0,
                      cloud_tree=None) -> np.ndarray:
    """Drop-outs where the stripe vanished behind another part of the part, not at an edge.

    A profile cannot tell a rim from the boundary of an occlusion cast by a feature outside
    the sheet (a boss in front of the sheet hides the surface behind it from the camera,
    which views the sheet at an angle): both look like a gap between stripe ends at one
    range. The scan can: the surface just past a true rim is empty, so the camera's line of
    sight to a probe point ``probe_mm`` past the edge (in the sheet, into the gap) crosses
    nothing; past an occlusion's boundary that line of sight runs through the occluder, whose
    surface facing the camera other profiles have measured. A drop-out is occluded when some
    cloud point lies within ``radius_mm`` of that line of sight, farther than
    ``clearance_mm`` from the probe (the edge's own surface lies near its start).

    One k-d tree query for the samples every ``radius_mm`` along all the lines of sight.

    Parameters
    ----------
    points_t : (M, 3) float
        Drop-out edge points in {T}, mm.
    across_t : (M, 3) float
        Unit vectors from each point into its gap, in {T} (``EdgePoints.across_b`` rotated).
    sensors_t : (M, 3) float
        The camera centre in {T} when each point's frame was taken, mm
        (``Scan.sensor_positions_t`` of its frame).
    cloud_t : (N, 3) float
        The scan's cloud in {T}, mm.
    probe_mm : float
    radius_mm : float
        Must exceed half the spacing of the profiles (1.2 mm at 200 mm/s and 162 fps), so
        that a line of sight through a measured surface passes near one of its points.
    clearance_mm : float
    cloud_tree : scipy.spatial.cKDTree, optional
        A KD-tree over `cloud_t` (the scan's other filters share one); built here without.

    Returns
    -------
    (M,) bool
        True where the drop-out is the boundary of an occlusion.
    """
    from scipy.spatial import cKDTree  # scipy only for this scan-level check

    points = _points3(points_t, "points_t")
    across = _points3(across_t, "across_t")
    sensors = _points3(sensors_t, "sensors_t")
    cloud = _points3(cloud_t, "cloud_t")
    if across.shape != points.shape or sensors.shape != points.shape:
        raise ValueError(f"`across_t` and `sensors_t` must be {points.shape} like `points_t`, "
                         f"got {across.shape} and {sensors.shape}")
    out = np.zeros(len(points), dtype=bool)
    if len(points) == 0 or len(cloud) == 0:
        return out
    lo, hi = cloud.min(axis=0) - radius_mm, cloud.max(axis=0) + radius_mm
    tree = cKDTree(cloud) if cloud_tree is None else cloud_tree
    probes = points + probe_mm * across
    sight = sensors - probes
    length = np.sqrt(np.einsum("ij,ij->i", sight, sight))
    sight /= length[:, None]
    # the line of sight leaves the cloud's bounding box after t_exit
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - probes) / sight
        t2 = (hi - probes) / sight
    t_far = np.nan_to_num(np.maximum(t1, t2), nan=np.inf, posinf=np.inf, neginf=-np.inf)
    t_exit = t_far.min(axis=1)
    t_exit = np.minimum(t_exit, length)
    # every line of sight's samples, every radius_mm from clearance_mm to t_exit, in one query
    reaching = np.nonzero(t_exit > clearance_mm)[0]
    if not len(reaching):
        return out
    counts = np.ceil((t_exit[reaching] + radius_mm - clearance_mm) / radius_mm).astype(np.int64)
    owner = np.repeat(np.arange(len(reaching)), counts)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    t = clearance_mm + (np.arange(len(owner)) - first[owner]) * radius_mm
    samples = probes[reaching][owner] + t[:, None] * sight[reaching][owner]
    dist, _ = tree.query(samples, distance_upper_bound=radius_mm)
    out[reaching] = np.logical_or.reduceat(np.isfinite(dist), first)
    return out


#: A chain's face next to the gap is a chamfer when its fitted level is below this fraction
#: of the face further in.
CHAMFER_MAX_LEVEL = 0.85
#: Fewest drop-outs along one edge to fit its chamfer by.
CHAMFER_MIN_POINTS = 6
#: A chamfer must explain its chain's levels better than a sharp edge by this much per
#: profile (mean squared residual, squared fractions of the face's level: 0.07 of it RMS).
#: An edge the profiles cross at one phase fits a sharp edge as well (the chamfer's level
#: and the lit fraction cannot be told apart): nothing is moved then. Noise alone gained
#: at most 0.002 on 800 synthetic sharp chains (6-30 profiles, 0.03-0.05 of level noise,
#: the phase varying or fixed); ADIS16480's chamfer chains gained 0.011 to 0.076.
CHAMFER_MIN_GAIN = 0.005
#: Drop-outs along one edge: within this many profiles of each other, their directions into
#: the gap within CHAIN_DEG, and within CHAIN_SPACINGS profile spacings (at least
#: CHAIN_MIN_MM) of each other.
CHAIN_FRAMES = 3
CHAIN_DEG = 30.0
CHAIN_SPACINGS = 2.5
CHAIN_MIN_MM = 2.0
_CHAMFER_LEVELS = np.linspace(0.2, 1.0, 81)
_CHAMFER_WIDTHS_PX = np.linspace(1.0, 2.0, 41)
# Elements of the chamfer fit's arrays at a time (levels x widths x points: 16 MB of float64).
_CHAMFER_BLOCK = 2_000_000


def chamfered_dropouts(points_t, across_t, frame_ids, stripe_end, per_px_t, spacing_mm):
    """Drop-outs of a chamfered outline, placed at the outline.

    A chamfer between one and two columns wide (ADIS16480's 0.2 mm, 1.25 px in the
    reference cell) lights the stripe's last column or two at a level of its own, below the
    face's: the half-level crossing of the face's level falls on the chamfer, about 0.4 px
    inside the outline. One profile cannot tell the chamfer's width and level from where the
    outline lies in its last column. An edge's profiles can: along it the chamfer keeps its
    width ``w`` (px) and level ``c`` (of the face's), while the outline's place in the last
    lit column, the fraction ``f`` of it lit, changes from profile to profile. Pixels
    integrate the light they receive, so the last column holds ``c f`` of the face's level,
    and the one before ``c`` when the chamfer covers it, or ``c`` on its chamfered share
    ``w - f`` and the face's level on the rest (``"a pixel column holding the wall is lit
    in part by the near surface, in proportion to the share of the pixel it covers"``, as
    at steps). ``c`` and ``w`` are fitted to the chain's levels by least squares (a grid:
    ``c`` from 0.2 to 1, ``w`` from 1 to 2 px), each profile's ``f`` with them in closed
    form. Where ``c`` is below ``CHAMFER_MAX_LEVEL``, explains the levels better than a
    sharp edge by ``CHAMFER_MIN_GAIN``, and the chain's last columns lie off
    their faces' lines by ``ROW_BEND_PX`` or more (median: a face turned against the one
    inward puts its stripe on a line of its own, as :func:`_bends` judges a wider chamfer;
    one partly lit column's row is too noisy to judge alone), its points move to the
    outline, ``1 - f`` px in from the outer side of their last lit column, but for those
    whose profile found the chamfer's own level (``stripe_end``'s last field), which the
    half-level crossing of that level places already. Elsewhere the
    half-level placement stands: a sharp edge's last column holds the face's level times
    ``f``, a blurred edge dims over a few columns without turning its rows, and a chamfer
    two columns wide or more has been placed by its own level in the profile.

    ADIS16480's 16 outline chains in the bench's 8 scans fitted ``c`` 0.42 to 0.79 with their
    rows 0.31 to 0.50 px off; their points moved from 26-75 um RMS to 13-35 um. Costs 1.5 ms
    for a scan's 28 drop-outs, 6 ms for 220 (bench pose's scans, 2 cores); memory, one
    (widths, points) array at a time.

    Parameters
    ----------
    points_t : (M, 3) float
        Drop-out points in {T}, mm.
    across_t : (M, 3) float
        Unit vectors from each point into its gap, in {T}.
    frame_ids : (M,) int
        The profile of each point.
    stripe_end : (M, 5) float
        ``EdgePoints.stripe_end`` of each point.
    per_px_t : (M, 3) float
        ``EdgePoints.per_px_b`` of each point, rotated into {T}.
    spacing_mm : float
        The profiles' spacing along the pass, mm (NaN: CHAIN_MIN_MM is the reach).

    Returns
    -------
    points : (M, 3) float64
        The points, those of chamfered chains moved.
    chamfer_level : (M,) float64
        The fitted chamfer level of each point's chain (of the face's); NaN where no chain
        was fitted (fewer than CHAMFER_MIN_POINTS with levels).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    points = _points3(points_t, "points_t")
    across = _points3(across_t, "across_t")
    per_px = _points3(per_px_t, "per_px_t")
    end = np.asarray(stripe_end, dtype=np.float64)
    frames = np.asarray(frame_ids).reshape(-1).astype(np.int64)  # unsigned ids would wrap
    m = len(points)
    if across.shape != points.shape or per_px.shape != points.shape or end.shape != (m, 5) \
            or frames.shape != (m,):
        raise ValueError(f"`across_t`, `per_px_t` must be ({m}, 3), `stripe_end` ({m}, 5) and "
                         f"`frame_ids` ({m},), got {across.shape}, {per_px.shape}, "
                         f"{end.shape}, {frames.shape}")
    out = points.copy()
    level = np.full(m, np.nan)
    usable = np.nonzero(np.isfinite(end[:, :3]).all(axis=1) & np.isfinite(per_px).all(axis=1))[0]
    if len(usable) < CHAMFER_MIN_POINTS:
        return out, level
    reach = max(CHAIN_MIN_MM, CHAIN_SPACINGS * spacing_mm) if np.isfinite(spacing_mm) \
        else CHAIN_MIN_MM
    pairs = cKDTree(points[usable]).query_pairs(reach, output_type="ndarray")
    i, j = usable[pairs[:, 0]], usable[pairs[:, 1]]
    apart = np.abs(frames[i] - frames[j])
    linked = ((apart >= 1) & (apart <= CHAIN_FRAMES)
              & (np.einsum("ij,ij->i", across[i], across[j]) > math.cos(math.radians(CHAIN_DEG))))
    graph = coo_matrix((np.ones(int(linked.sum())), (i[linked], j[linked])), shape=(m, m))
    _, label = connected_components(graph, directed=False)
    for chain in np.unique(label[usable]):
        members = usable[label[usable] == chain]
        if len(members) < CHAMFER_MIN_POINTS:
            continue
        c, _, fill, gain = _fit_chamfer(end[members, 0], end[members, 1])
        level[members] = c
        if (c < CHAMFER_MAX_LEVEL and gain >= CHAMFER_MIN_GAIN
                and abs(np.median(end[members, 3])) >= ROW_BEND_PX):
            shift_px = np.where(end[members, 4] > 0, 0.0, end[members, 2] - (1.0 - fill))
            out[members] += shift_px[:, None] * per_px[members]
    return out, level


def _fit_chamfer(last, before):
    """The chamfer level c and width w (px) that best explain one chain's last two column
    levels (:func:`chamfered_dropouts`), each profile's lit fraction f of its last column
    under them, and how much better per profile than a sharp edge (c = 1) they explain
    them (mean squared residual, in squared fractions of the face's level): c, w, the
    fractions and the gain. Levels are tried from 1 down, a tie keeping the higher (a
    sharp edge crossed at one phase fits c = f, f = 1 as well as c = 1). The levels go
    through in blocks of (levels, widths, points) arrays of at most ``_CHAMFER_BLOCK``."""
    w = _CHAMFER_WIDTHS_PX[None, :, None]
    levels = _CHAMFER_LEVELS[::-1]
    step = max(1, _CHAMFER_BLOCK // (len(_CHAMFER_WIDTHS_PX) * max(len(last), 1)))
    best_cost, best = np.inf, None
    sharp_cost = np.inf
    for start in range(0, len(levels), step):
        c = levels[start:start + step, None, None]
        # f <= w - 1: the column before is all chamfer
        f_a = np.clip(last / c, 0.0, w - 1.0)
        cost_a = (last - c * f_a) ** 2 + (before - c) ** 2
        # f >= w - 1: the column before holds face on f - w + 1 of it
        rest = before - c + (1.0 - c) * (w - 1.0)
        f_b = np.clip((c * last + (1.0 - c) * rest) / (c**2 + (1.0 - c) ** 2), w - 1.0, 1.0)
        cost_b = (last - c * f_b) ** 2 + (before - c - (1.0 - c) * (f_b - w + 1.0)) ** 2
        first = cost_a <= cost_b
        totals = np.where(first, cost_a, cost_b).sum(axis=2)  # (levels, widths)
        width_of = np.argmin(totals, axis=1)  # the first width at its least, as one by one
        least = totals[np.arange(len(totals)), width_of]
        if start == 0:
            sharp_cost = float(least[0])  # c = 1: the first level tried
        k = int(np.argmin(least))  # the first (highest) level at the block's least
        if least[k] < best_cost:
            j = width_of[k]
            best_cost = float(least[k])
            best = (float(c[k, 0, 0]), float(_CHAMFER_WIDTHS_PX[j]),
                    np.where(first[k, j], f_a[k, j], f_b[k, j]))
    c, width, fill = best
    return c, width, fill, (sharp_cost - best_cost) / len(last)


def _on_own_profile(points, frame_ids, cloud, cloud_frames, tree, k: int = 32):
    """Each point moved to the nearest cloud point of its own profile (among its `k` nearest
    cloud points; kept where none is)."""
    if len(frame_ids) != len(points):
        raise ValueError(f"`frame_ids` must be ({len(points)},), got {frame_ids.shape}")
    nearest = _nearest_of_profile(points, frame_ids, cloud, cloud_frames, tree, k)
    found = nearest >= 0
    out = points.copy()
    out[found] = cloud[nearest[found]]
    return out


def _nearest_of_profile(points, frame_ids, cloud, cloud_frames, tree, k: int = 32,
                        reach_mm: float = np.inf):
    """(M,) index of the nearest cloud point of each point's own profile within `reach_mm`
    (among its `k` nearest cloud points; ``tree`` is over ``cloud``), -1 where none."""
    k = min(k, len(cloud))
    dist, nearest = tree.query(points, k=k, distance_upper_bound=reach_mm)
    dist, nearest = dist.reshape(len(points), k), nearest.reshape(len(points), k)
    inside = np.isfinite(dist)
    safe = np.where(inside, nearest, 0)
    same = inside & (cloud_frames[safe] == frame_ids[:, None])
    first = np.argmax(same, axis=1)
    hit = same[np.arange(len(points)), first]
    return np.where(hit, safe[np.arange(len(points)), first], -1)


def _points3(points, name: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"`{name}` must be (N, 3), got {arr.shape}")
    return arr


#: A surface turned closer than this to the light sheet (degrees between their normals) is
#: grazed by it: the sheet, some 0.1 mm thick, lights a band many times wider on it, and the
#: stripe there breaks into gaps and jumps that are no edge of the part.
GRAZING_DEG = 25.0
#: The grazing test's neighbourhood spans at least this many profile spacings.
LONE_PROFILE_REACH = 2.1


def grazing_edges(points_t, sheet_normals_t, cloud_t, cloud_frame_ids, spacing_mm: float, *,
                  frame_ids=None, radius_mm: float = 2.5, grazing_deg: float = GRAZING_DEG,
                  min_points: int = 8, cloud_tree=None) -> np.ndarray:
    """Edge points on a surface the light sheet grazes.

    A profile alone cannot tell: the sheet cuts a wall turned a few degrees from it along a
    curve that looks like any other. The scan can. Where the cloud around the edge point
    holds two profiles or more, their plane's normal (principal axis of least spread) lies
    within ``grazing_deg`` of the sheet's. Where it holds the point's own profile only,
    although the profiles lie closer than half ``radius_mm`` apart, the surface climbs
    between them by more than about 60 degrees from level: the next profile landed out of
    reach, and the sheet grazes the surface as well. A wall tilted 7 degrees toward the
    camera (the demo block misplaced by a rotation) gave 16 % of its edge points more than
    0.5 mm from any edge of the part, all on the three profiles that cut that wall; 0.8 %
    with this filter.

    Parameters
    ----------
    points_t : (M, 3) float
        Edge points in {T}, mm.
    sheet_normals_t : (M, 3) float
        Unit normal of the light sheet in {T} at each point's frame.
    cloud_t : (N, 3) float
        The scan's cloud in {T}, mm.
    cloud_frame_ids : (N,) int
        The profile of each cloud point.
    spacing_mm : float
        The profiles' spacing along the pass (median): at more than half ``radius_mm``, a
        lone profile says nothing, and only the plane test applies.
    frame_ids : (M,) int, optional
        The profile of each edge point: its neighbourhood is then centred on the nearest
        cloud point of that profile. A step's point lies half the step's height off the
        surface (2.5 mm on a 5 mm step), where a neighbourhood about it reaches its own
        profile's points only and the test would take it for a grazed wall.
    radius_mm : float
        Neighbourhood of each edge point: about twice the profiles' spacing at the default
        pass (1.2 mm at 200 mm/s and 162 fps); widened to ``LONE_PROFILE_REACH`` spacings
        (up to twice itself) on a faster pass. A misplaced part's pass spaced its profiles
        1.28 mm apart: with the neighbourhood fixed, walls 7 degrees from the sheet kept
        edge points up to 0.5 mm off (idler_riser, 96 um RMS, now 54 um).
    grazing_deg : float
    min_points : int
        Fewer cloud points than this within the radius: nothing to judge by, the point is kept.
    cloud_tree : scipy.spatial.cKDTree, optional
        A KD-tree over `cloud_t`; built here without.

    Returns
    -------
    (M,) bool
        The edge points on a grazed surface.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points_t, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(sheet_normals_t, dtype=np.float64).reshape(-1, 3)
    cloud = np.asarray(cloud_t, dtype=np.float64).reshape(-1, 3)
    frames = np.asarray(cloud_frame_ids).reshape(-1)
    out = np.zeros(len(points), bool)
    if len(points) == 0 or len(cloud) < min_points:
        return out
    if np.isfinite(spacing_mm):
        # Reach a level surface's next profiles even on a fast pass: a lone profile then
        # means a surface climbing past 60 degrees, not one the pass left sparse.
        # (up to twice the radius: a wider neighbourhood would mix surfaces)
        radius_mm = max(radius_mm, min(LONE_PROFILE_REACH * spacing_mm, 2.0 * radius_mm))
    dense = np.isfinite(spacing_mm) and spacing_mm < radius_mm / 2
    cos_limit = math.cos(math.radians(grazing_deg))
    tree = cKDTree(cloud) if cloud_tree is None else cloud_tree
    if frame_ids is not None:
        points = _on_own_profile(points, np.asarray(frame_ids).reshape(-1), cloud, frames, tree)
    near = tree.query_ball_point(points, radius_mm)
    counts = np.array([len(n) for n in near], np.int64)
    judged = np.nonzero(counts >= min_points)[0]
    if not len(judged):
        return out
    # every judged neighbourhood at once: segments of one flat index array
    members = np.concatenate([near[i] for i in judged]).astype(np.int64)
    first = np.concatenate([[0], np.cumsum(counts[judged])[:-1]])
    lone = (np.minimum.reduceat(frames[members], first)
            == np.maximum.reduceat(frames[members], first))
    owner = np.repeat(np.arange(len(judged)), counts[judged])
    centre = np.add.reduceat(cloud[members], first) / counts[judged][:, None]
    local = cloud[members] - centre[owner]
    scatter = np.add.reduceat(local[:, :, None] * local[:, None, :], first)
    _, axes = np.linalg.eigh(scatter)
    grazed = np.abs(np.einsum("ki,ki->k", axes[:, :, 0], normals[judged])) > cos_limit
    out[judged] = np.where(lone, dense, grazed)
    return out
