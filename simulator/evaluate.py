"""Scan accuracy against the ground truth the simulator knows.

Distances are to the true CAD surface (exact closest points, trimesh), after mapping the
cloud from {T} back to {P} through the true grasp. Provenance: every cloud point must lie
near a stripe sample that the renderer found lit by the laser and seen by the camera in the
same frame (or between two samples of one pixel column: their blend); a point that does not
came from a surface the camera cannot see (or from nothing at all). Edge points are scored
against the CAD's sharp edges, and drop-outs also against the part's outline seen along z_T
(:func:`edge_accuracy`); a scan's edge points per kind, those it set aside included
(:func:`edge_kind_accuracy`), and why a drop-out's stripe ended by the true section of the part
by the sheet (:func:`dropout_causes`).
"""
from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from scanner_core.edges.kinds import segment_distances
from scanner_core.geometry import apply_transform, base_to_tcp
from scanner_core.pose.registration import outline_adjacency

#: Closest-point queries cost about 0.1 ms each; larger clouds are subsampled (seeded).
MAX_EVAL_POINTS = 30000
#: A cloud point farther than this from every visible stripe sample of its frame has no
#: visible source (the stripe error is tens of micrometres).
PROVENANCE_TOL_MM = 0.2
#: Separates frames in the provenance search (far larger than any part).
FRAME_SPACING_MM = 1.0e5


def cloud_accuracy(cloud_t, frame_ids, mesh: trimesh.Trimesh, true_grasp: np.ndarray,
                   truths: dict | None = None, gripper_rotation_b=None, *,
                   max_points: int = MAX_EVAL_POINTS, seed: int = 0) -> dict:
    """Distances from cloud points to the true surface, and each point's provenance.

    Parameters
    ----------
    cloud_t : (N, 3) float
        Cloud in {T}, mm.
    frame_ids : (N,) int
    mesh : trimesh.Trimesh
        The part in {P}, mm.
    true_grasp : (4, 4) float64
        True ^T X_P.
    truths : dict frame_id -> simulator.render.FrameTruth, optional
        With ``gripper_rotation_b``: enables the provenance check.

    Returns
    -------
    dict
        ``points_evaluated``, ``rms_um``, ``p99_um``, ``max_um``, ``mean_signed_um`` (along
        the surface normal: a bias check), and with truths ``unmatched_points``.
    """
    cloud_t = np.asarray(cloud_t, dtype=np.float64)
    n = len(cloud_t)
    if n == 0:
        return {"points_evaluated": 0}
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(n, max_points, replace=False)) if n > max_points else np.arange(n)
    points_p = apply_transform(np.linalg.inv(true_grasp), cloud_t[pick])
    closest, distance, face = trimesh.proximity.closest_point(mesh, points_p)
    signed = np.einsum("ij,ij->i", points_p - closest, mesh.face_normals[face])
    out = {
        "points_evaluated": int(len(pick)),
        "rms_um": float(np.sqrt(np.mean(distance**2)) * 1e3),
        "p99_um": float(np.percentile(distance, 99) * 1e3),
        "max_um": float(distance.max() * 1e3),
        "mean_signed_um": float(signed.mean() * 1e3),
    }
    if truths is not None:
        out["unmatched_points"] = int(unmatched(cloud_t, frame_ids, truths, gripper_rotation_b).sum())
    return out


def unmatched(cloud_t, frame_ids, truths: dict, gripper_rotation_b) -> np.ndarray:
    """(N,) bool: points with no lit-and-seen stripe sample within PROVENANCE_TOL_MM in
    their own frame.

    A pixel column holding several samples (section segments meeting in it, a surface and a
    wall at a rim) shows their blend: the stripe measured there lies between them, and it
    has visible sources. So the chords between the samples of one column, in the order of
    their rows, count as sources too."""
    r = np.asarray(gripper_rotation_b, dtype=np.float64)
    ref, ref_ids = [], []
    for fid in np.unique(frame_ids):
        truth = truths[int(fid)]
        points = _with_column_chords(truth.stripe_columns, truth.stripe_rows,
                                     truth.stripe_points_b)
        ref.append(base_to_tcp(points, truth.tcp_b, r))
        ref_ids.append(np.full(len(points), fid))
    ref = np.concatenate(ref) if ref else np.zeros((0, 3))
    if len(ref) == 0:
        return np.ones(len(cloud_t), dtype=bool)
    ref_ids = np.concatenate(ref_ids).astype(np.float64)
    tree = cKDTree(np.column_stack([ref, ref_ids * FRAME_SPACING_MM]))
    query = np.column_stack([cloud_t, np.asarray(frame_ids, np.float64) * FRAME_SPACING_MM])
    dist, _ = tree.query(query, distance_upper_bound=PROVENANCE_TOL_MM)
    return ~np.isfinite(dist)


def _with_column_chords(columns, rows, points) -> np.ndarray:
    """The samples' points followed by points every ``PROVENANCE_TOL_MM / 2`` along the
    chords between consecutive samples (by row) of each column: (N + M, 3)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) < 2:
        return points
    order = np.lexsort((rows, columns))
    pts = points[order]
    pair = np.nonzero(np.diff(np.asarray(columns)[order]) == 0)[0]
    if len(pair) == 0:
        return points
    a, b = pts[pair], pts[pair + 1]
    steps = np.ceil(np.linalg.norm(b - a, axis=1) / (0.5 * PROVENANCE_TOL_MM)).astype(np.int64)
    inner = np.maximum(steps - 1, 0)  # interior points of each chord
    which = np.repeat(np.arange(len(pair)), inner)
    k = np.arange(inner.sum()) - np.repeat(np.cumsum(inner) - inner, inner) + 1
    t = (k / steps[which])[:, None]
    return np.concatenate([points, a[which] + t * (b[which] - a[which])])


# ---------------------------------------------------------------------------------------------
# Edge points against the CAD's sharp edges

#: Point-segment pairs per block of the brute-force distance search (about 100 MB of
#: temporaries at this size).
EDGE_PAIRS_PER_BLOCK = 1_000_000
#: Segments shorter than this (mm) in the measuring plane count as points (a vertical edge
#: seen along z_T).
EDGE_DEGENERATE_MM = 1e-9
#: ``EdgePoints.kind`` codes (``scanner_core.edges.EdgeKind``) and their report names.
EDGE_KIND_NAMES = {0: "dropout", 1: "step"}
STEP_KIND = {name: code for code, name in EDGE_KIND_NAMES.items()}["step"]
#: A drop-out this much nearer the outline than any sharp edge (mm) is counted as placed
#: by the outline (``dropouts_off_sharp_edges``).
OUTLINE_COUNTED_MM = 0.01
#: A face is a wall (a step's riser) when its normal, in {T}, is within this of level.
WALL_MAX_NZ = 0.5
#: A step's half-height point lies at most this far up or down its wall from the edge, mm.
WALL_REACH_MM = 15.0


def sharp_edges(mesh: trimesh.Trimesh, feature_angle_deg: float = 30.0, *,
                faces: bool = False):
    """The mesh's sharp edges: where its faces meet at more than ``feature_angle_deg``
    (``mesh.face_adjacency_angles``), plus its boundary edges (open meshes).

    Returns
    -------
    (S, 2, 3) float64
        Segments in the mesh's frame, mm.
    (S, 2) int64, with ``faces``
        The two faces meeting at each segment (a boundary edge's one face twice).
    """
    angles = np.asarray(mesh.face_adjacency_angles)
    is_sharp = angles > np.radians(feature_angle_deg)
    sharp = np.asarray(mesh.face_adjacency_edges)[is_sharp]
    boundary_rows = trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)
    boundary = mesh.edges_sorted[boundary_rows]
    index = np.concatenate([sharp.reshape(-1, 2), np.asarray(boundary).reshape(-1, 2)])
    segments = np.asarray(mesh.vertices, dtype=np.float64)[index]
    if not faces:
        return segments
    boundary_face = np.asarray(mesh.edges_face)[np.asarray(boundary_rows, dtype=np.int64)]
    pairs = np.concatenate([np.asarray(mesh.face_adjacency)[is_sharp].reshape(-1, 2),
                            np.repeat(boundary_face.reshape(-1, 1), 2, axis=1)])
    return segments, pairs.astype(np.int64)


def outline_edges(mesh: trimesh.Trimesh, true_grasp: np.ndarray) -> np.ndarray:
    """The part's outline seen along z_T: the mesh edges where a face turned toward the
    sensor (+z_T) meets one that is not, placed in {T} by the true grasp.

    A drop-out marks where the lit surface ends along its profile. At a sharp rim that is
    the sharp edge; at a rounded or drafted rim (cycloidal's lobes: a face 8 degrees off
    vertical below the top's edge, then a wall) it is where the surface turns away, which
    no sharp edge marks: 0.1-0.3 mm outside the top's edge in (x_T, y_T) there.

    Returns
    -------
    (S, 2, 3) float64
        Segments in {T}, mm.
    """
    grasp = np.asarray(true_grasp, dtype=np.float64)
    # z_T in {P}: the grasp's third row
    turn = outline_adjacency(mesh, grasp[2, :3])
    segments = np.asarray(mesh.vertices, dtype=np.float64)[
        np.asarray(mesh.face_adjacency_edges)[turn]]
    return apply_transform(grasp, segments.reshape(-1, 3)).reshape(-1, 2, 3)


def _wall_distances(points: np.ndarray, segments: np.ndarray, face_normals: np.ndarray):
    """(N,) distance from each step point to the nearest wall through a sharp edge, taken
    across the wall (and beyond the edge's ends along it), for points within
    ``WALL_REACH_MM`` of the edge up or down the wall.

    A step's point sits at half the step's height on its riser (paper section II); when the
    riser leans (the part turned about x_T or y_T), that point lies off the (x_T, y_T)
    projection of the riser's top and bottom edges by half the height times the lean's
    tangent, by design. Across the riser itself, it is off by its own error only.

    Parameters
    ----------
    points : (N, 3) float64
        Step points in {T}, mm.
    segments : (S, 2, 3) float64
        Sharp edges in {T}, mm.
    face_normals : (S, 2, 3) float64
        The unit normals, in {T}, of the two faces at each edge; the more level one, if
        within ``WALL_MAX_NZ`` of level, is the wall.
    """
    out = np.full(len(points), np.inf)
    nz = np.abs(face_normals[:, :, 2])
    wall_normal = face_normals[np.arange(len(segments)), np.argmin(nz, axis=1)]
    a = segments[:, 0]
    along = segments[:, 1] - a
    length = np.linalg.norm(along, axis=1)
    is_wall = (nz.min(axis=1) < WALL_MAX_NZ) & (length > EDGE_DEGENERATE_MM)
    if not is_wall.any() or len(points) == 0:
        return out
    a, wall_normal, length = a[is_wall], wall_normal[is_wall], length[is_wall]
    along = along[is_wall] / length[:, None]
    up = np.cross(wall_normal, along)  # in the wall, across the edge
    block = max(1, EDGE_PAIRS_PER_BLOCK // len(a))
    for i0 in range(0, len(points), block):
        ap = points[i0:i0 + block, None, :] - a[None]
        t = np.einsum("nsk,sk->ns", ap, along)
        beyond = t - np.clip(t, 0.0, length[None])
        across = np.einsum("nsk,sk->ns", ap, wall_normal)
        reach = np.abs(np.einsum("nsk,sk->ns", ap, up))
        d = np.where(reach <= WALL_REACH_MM, np.hypot(across, beyond), np.inf)
        out[i0:i0 + block] = d.min(axis=1)
    return out


def _edge_stats(distance_xy: np.ndarray, distance_3d: np.ndarray, outlier_mm: float) -> dict:
    if len(distance_xy) == 0:
        return {"count": 0}
    inliers = distance_xy[distance_xy <= outlier_mm]
    return {
        "count": int(len(distance_xy)),
        "rms_um": float(np.sqrt(np.mean(distance_xy**2)) * 1e3),
        "median_um": float(np.median(distance_xy) * 1e3),
        "p99_um": float(np.percentile(distance_xy, 99) * 1e3),
        "outlier_fraction": float(np.mean(distance_xy > outlier_mm)),
        "rms_inliers_um": (float(np.sqrt(np.mean(inliers**2)) * 1e3) if len(inliers)
                           else float("nan")),
        "rms_3d_um": float(np.sqrt(np.mean(distance_3d**2)) * 1e3),
        "p99_3d_um": float(np.percentile(distance_3d, 99) * 1e3),
    }


def edge_distances(edges_t, mesh: trimesh.Trimesh, true_grasp: np.ndarray, *, kinds=None,
                   feature_angle_deg: float = 30.0):
    """Each edge point's distance to the edges it is measured against (:func:`edge_accuracy`).

    Returns
    -------
    d_xy : (N,) float64
        In the (x_T, y_T) plane, mm: to the sharp edges, a step also across its wall, a
        drop-out (every point without `kinds`) also to the outline.
    d_3d : (N,) float64
        In 3-D to the sharp edges, mm.
    info : dict
        ``sharp_edges``, ``outline_edges`` (segments) and ``dropouts_off_sharp_edges``.
    """
    points = np.asarray(edges_t, dtype=np.float64).reshape(-1, 3)
    grasp = np.asarray(true_grasp, dtype=np.float64)
    edges_p, faces = sharp_edges(mesh, feature_angle_deg, faces=True)
    segments = apply_transform(grasp, edges_p.reshape(-1, 3)).reshape(-1, 2, 3)
    d_xy = segment_distances(points[:, :2], segments[:, :, :2])
    d_3d = segment_distances(points, segments)
    dropout = np.ones(len(points), bool)
    if kinds is not None:
        step = np.asarray(kinds).reshape(-1) == STEP_KIND
        dropout = ~step
        if step.any():
            normals_t = np.asarray(mesh.face_normals, dtype=np.float64)[faces] @ grasp[:3, :3].T
            d_xy[step] = np.minimum(d_xy[step],
                                    _wall_distances(points[step], segments, normals_t))
    outline = outline_edges(mesh, grasp)
    to_outline = segment_distances(points[dropout, :2], outline[:, :, :2])
    off_sharp = int(np.sum(to_outline < d_xy[dropout] - OUTLINE_COUNTED_MM))
    d_xy[dropout] = np.minimum(d_xy[dropout], to_outline)
    return d_xy, d_3d, {"sharp_edges": int(len(segments)), "outline_edges": int(len(outline)),
                        "dropouts_off_sharp_edges": off_sharp}


def edge_accuracy(edges_t, mesh: trimesh.Trimesh, true_grasp: np.ndarray, *, kinds=None,
                  feature_angle_deg: float = 30.0, outlier_mm: float = 0.5) -> dict:
    """Distances from edge points to the CAD's sharp edges, and from drop-outs also to the
    part's outline (the edge target).

    The sharp edges (:func:`sharp_edges`: faces meeting at more than ``feature_angle_deg``,
    plus boundary edges) are placed in {T} by the true grasp. Each edge point's distance to
    the nearest of them is measured in the (x_T, y_T) plane: the scanner looks along z_T, so
    a vertical wall's top and bottom edges project onto one line, and a step's edge point,
    placed at half the step height on the wall (paper section II), lies on that line. The
    3-D distance is reported for information, to the sharp edges only: for a step it
    includes half the step height by design. Walls tilted away from z_T (a misplacement's
    rotation) move a step point off the projected line by half the step height times the
    tilt's tangent; with ``kinds``, a step point is also measured across the wall it lies on
    (:func:`_wall_distances`), and the nearer of the two counts. A drop-out (every point,
    without ``kinds``) is also measured to the outline seen along z_T
    (:func:`outline_edges`): where a rounded or drafted rim turns away from the sensor, the
    stripe ends away from any sharp edge.

    Parameters
    ----------
    edges_t : (N, 3) float
        Edge points in {T}, mm.
    mesh : trimesh.Trimesh
        The part in {P}, mm.
    true_grasp : (4, 4) float64
        True ^T X_P.
    kinds : (N,) int, optional
        ``EdgePoints.kind`` per point: adds the same figures per kind (``"dropout"``,
        ``"step"``).
    feature_angle_deg : float
        Faces meeting at more than this make a sharp edge.
    outlier_mm : float
        Points farther than this (in x_T, y_T) from every edge they are measured against
        are outliers.

    Returns
    -------
    dict
        ``count``, ``rms_um``, ``median_um``, ``p99_um``, ``outlier_fraction`` (farther than
        ``outlier_mm``), ``rms_inliers_um``, ``rms_3d_um``, ``p99_3d_um``, ``sharp_edges``
        and ``outline_edges`` (segments), ``dropouts_off_sharp_edges`` (drop-outs nearer
        the outline than any sharp edge by more than 10 um), and with ``kinds`` one dict
        per kind under ``by_kind``.
    """
    points = np.asarray(edges_t, dtype=np.float64).reshape(-1, 3)
    if kinds is not None:
        kinds = np.asarray(kinds).reshape(-1)
        if kinds.shape != (len(points),):
            raise ValueError(f"`kinds` must be ({len(points)},), got {kinds.shape}")
    d_xy, d_3d, info = edge_distances(points, mesh, true_grasp, kinds=kinds,
                                      feature_angle_deg=feature_angle_deg)
    out = _edge_stats(d_xy, d_3d, outlier_mm)
    out.update(info)
    if kinds is not None:
        out["by_kind"] = {name: _edge_stats(d_xy[kinds == code], d_3d[kinds == code], outlier_mm)
                          for code, name in EDGE_KIND_NAMES.items()}
    return out


# ---------------------------------------------------------------------------------------------
# Edge kinds of a scan: the edge cloud and what the scan set aside, by the truth


def edge_kind_accuracy(scan, mesh: trimesh.Trimesh, true_grasp: np.ndarray, *,
                       outlier_mm: float = 0.5) -> dict:
    """:func:`edge_accuracy` of a scan's edge cloud, and of each kind of edge point it set
    aside (``Scan.edges_aside``, ``scanner_core.edges.EdgeKind``), each point measured as what
    its profile found (a drop-out or a step).

    Returns
    -------
    dict
        ``edges``: the edge cloud's figures (``by_kind``: drop-outs and steps); ``aside``: one
        dict per reason (``occluded``, ``grazing``, ``turned_away``, ``off_model``) with the
        figures of the points set aside for it (``count`` 0 when none); ``without_turned_away``:
        the edge cloud with the turned-away points put back (what the scan gave before
        ``scanner_core.edges.kinds.turned_away``).
    """
    from scanner_core.edges.kinds import EDGE_KIND_NAMES, AsideEdges
    from scanner_core.edges import EdgeKind

    def figures(points, kinds) -> dict:
        if len(points) == 0:
            return {"count": 0}
        out = edge_accuracy(points, mesh, true_grasp, kinds=kinds, outlier_mm=outlier_mm)
        out.pop("sharp_edges")
        out.pop("outline_edges")
        return out

    aside = scan.edges_aside if scan.edges_aside is not None else AsideEdges.empty()
    result = {"edges": figures(scan.edges, scan.edge_kind), "aside": {}}
    for code, name in EDGE_KIND_NAMES.items():
        if code in (EdgeKind.DROPOUT, EdgeKind.STEP):
            continue
        mine = aside.kind == code
        result["aside"][name] = figures(aside.points[mine], aside.found[mine])
    turned = aside.kind == EdgeKind.TURNED_AWAY
    result["without_turned_away"] = figures(
        np.concatenate([np.asarray(scan.edges, np.float64).reshape(-1, 3),
                        aside.points[turned].astype(np.float64)]),
        np.concatenate([scan.edge_kind, aside.found[turned]]))
    return result


#: A drop-out's surface "goes on" when the true section of the part by the sheet has a point
#: within this of it (mm) farther into the gap than DROPOUT_BEYOND_MM: about six columns of
#: the reference cell, past a partly lit last column.
DROPOUT_REACH_MM = 1.0
DROPOUT_BEYOND_MM = 0.05
#: The true section is sampled this finely (mm).
SECTION_STEP_MM = 0.05
#: Causes of a drop-out by the truth (:func:`dropout_causes`).
DROPOUT_CAUSES = ("outline", "unlit", "unseen", "faint")


def dropout_causes(points_t, frame_ids, cloud_t, cloud_frame_ids, mesh: trimesh.Trimesh,
                   truths: dict, gripper_rotation_b, cell) -> list[str]:
    """Why each drop-out's stripe ended, by the true section of the part by the sheet.

    Into the gap (away from the nearest points of the drop-out's own profile, in the sheet),
    within ``DROPOUT_REACH_MM``: ``"outline"``, nothing of the part; ``"unlit"``, only faces
    turned from the laser (the part's outline seen from the sensor, a rim); ``"unseen"``, a
    face lit by the laser that the camera does not see (its back to the camera, or hidden by
    the part); ``"faint"``, a face lit and seen, its stripe too faint to be found (the sheet
    grazing it). The first two are edges of the part, the others where the stripe left the
    camera's view or the light.

    Parameters
    ----------
    points_t : (M, 3) float
        Drop-out points in {T}, mm.
    frame_ids : (M,) int
    cloud_t : (N, 3) float
        The scan's cloud in {T} (each drop-out's side: its own profile's points).
    cloud_frame_ids : (N,) int
    mesh : trimesh.Trimesh
        The part in {P}.
    truths : dict frame_id -> simulator.render.FrameTruth
        With ``part_pose_b`` and ``tcp_b``.
    gripper_rotation_b : (3, 3) float
    cell : simulator.cell.Cell
        The true cell: its light plane, camera centre and laser origin.

    Returns
    -------
    list of str
        One of ``DROPOUT_CAUSES`` per point.
    """
    points = np.asarray(points_t, dtype=np.float64).reshape(-1, 3)
    frames = np.asarray(frame_ids).reshape(-1)
    cloud = np.asarray(cloud_t, dtype=np.float64).reshape(-1, 3)
    cloud_frames = np.asarray(cloud_frame_ids).reshape(-1)
    rotation = np.asarray(gripper_rotation_b, dtype=np.float64)
    plane = cell.calibration.light_plane_b
    out = []
    sections = {}
    for p_t, fid in zip(points, frames):
        truth = truths[int(fid)]
        to_p = np.linalg.inv(truth.part_pose_b)
        # the point and its profile in {B}, then {P}
        p_b = rotation @ p_t + truth.tcp_b
        own = cloud[cloud_frames == fid]
        own_b = own @ rotation.T + truth.tcp_b
        if int(fid) not in sections:
            sections[int(fid)] = _section(mesh, to_p, plane)
        samples, normals = sections[int(fid)]
        p_p = apply_transform(to_p, p_b[None])[0]
        if len(own_b):
            near = own_b[np.argsort(np.linalg.norm(own_b - p_b, axis=1))[:5]]
            gap_b = p_b - near.mean(axis=0)
        else:
            gap_b = np.zeros(3)
        gap_b -= (gap_b @ plane.normal) * plane.normal
        length = np.linalg.norm(gap_b)
        if len(samples) == 0 or length == 0:
            out.append("outline")
            continue
        gap_p = to_p[:3, :3] @ (gap_b / length)
        rel = samples - p_p
        beyond = ((np.linalg.norm(rel, axis=1) < DROPOUT_REACH_MM)
                  & (rel @ gap_p > DROPOUT_BEYOND_MM))
        if not beyond.any():
            out.append("outline")
            continue
        laser_p = apply_transform(to_p, cell.laser_origin_b[None])[0]
        camera_p = apply_transform(to_p, cell.calibration.camera.origin[None])[0]
        at, n = samples[beyond], normals[beyond]
        lit = np.einsum("ij,ij->i", n, laser_p - at) > 0
        if not lit.any():
            out.append("unlit")
            continue
        at, n = at[lit], n[lit]
        sight = camera_p - at
        sight /= np.linalg.norm(sight, axis=1)[:, None]
        front = np.einsum("ij,ij->i", n, sight) > 0
        seen = front.copy()
        if front.any():
            seen[front] = ~mesh.ray.intersects_any(at[front] + 1e-3 * sight[front], sight[front])
        out.append("faint" if seen.any() else "unseen")
    return out


def _section(mesh: trimesh.Trimesh, to_p: np.ndarray, plane_b):
    """The part's section by the sheet, in {P}: points every ``SECTION_STEP_MM`` with their
    faces' normals."""
    normal_p = to_p[:3, :3] @ np.asarray(plane_b.normal, np.float64)
    origin_p = apply_transform(to_p, (plane_b.offset * np.asarray(plane_b.normal))[None])[0]
    lines, faces = trimesh.intersections.mesh_plane(mesh, normal_p, origin_p, return_faces=True)
    if len(lines) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    length = np.linalg.norm(lines[:, 1] - lines[:, 0], axis=1)
    count = np.maximum(1, np.ceil(length / SECTION_STEP_MM).astype(int))
    owner = np.repeat(np.arange(len(lines)), count)
    first = np.cumsum(count) - count
    t = (np.arange(count.sum()) - first[owner] + 0.5) / count[owner]
    samples = lines[owner, 0] + t[:, None] * (lines[owner, 1] - lines[owner, 0])
    return samples, np.asarray(mesh.face_normals)[faces[owner]]
