"""Edge kinds: which edge points mark an edge of the part, and which only mark where the
stripe left the camera's view or the sheet's light.

A profile's drop-out is where its stripe ends (``scanner_core.edges``). The part's outline
and a hole's rim end it; so does a surface that goes on but can no longer be measured: it
turned away from the camera (its back to the view, or hidden behind the part's own nearer
surface), or so far from the sheet's light that the stripe on it is too faint to be found.
On a curved or creased surface this happens away from any edge of the part: beyond a soft
crease (faces meeting at less than ``SOFT_CREASE_DEG``, which the part's CAD does not count
as an edge), on a dome's steep tier, a blade turned from the camera. One profile cannot tell
the two; the scan can say when the surface at the stripe's end was already close to that
limit.

**Model-free** (:func:`turned_away`, per scan, before registration). The surface at an edge
point's near side (the stripe's end: a drop-out's point, a step's point moved half its height
back toward the camera) gets its plane from the cloud (``scanner_core.normals``: its own and
the neighbouring profiles). Its *view margin* is the angle between the camera's line of sight
and that plane; its *light margin* is ``STRIPE_LOSS_DEG`` less the sheet's incidence on it.
A face beyond a soft crease turns by at most ``SOFT_CREASE_DEG`` from this one: when either
margin is smaller than that, the surface may go on beyond the stripe's end, turned out of
view or out of the light by a crease that is no edge, and the point says nothing certain
about an edge. Such points are set aside (``EdgeKind.TURNED_AWAY``), out of the edge cloud
the pose uses, and counted. The laser's rays are taken along the sheet's range axis, toward
the camera's side (the cell's laser shines up from below, as the camera looks up): the
scanner is not told where the fan's apex lies. The test cannot tell a surface that goes on
from a true edge on a steep face: such edges are set aside too (on the faceted dome, whose
rim lies on its 78-degree tier, all of them; on the fan disk's hub and blades 49 true points
of 266, none false). It adds 4-6 ms to a scan's stitching (the near sides' normals; 10k-12k
points, 2 cores).

**With the part's model** (:func:`reclassify_with_model`, after registration). The CAD
model says where its edges are (:class:`ModelEdges`: its sharp edges, and its outline seen
from the sensor under the registered pose, the outline for drop-outs only, as the edge
evaluation measures them). An edge point farther than ``MODEL_EDGE_TOL_MM`` from all of them
is set aside (``EdgeKind.OFF_MODEL``). Points set aside model-free stay
aside: on the faceted dome, those lying within the tolerance of its outline were 70-90 um
RMS from it (the stripe fading on a steep tier short of the rim). Distances are those the pose
matches edge points by: in the (x_T, y_T) plane (its residual is the distance to the
vertical plane through the edge). These figures use the registered model, so the edge cloud
after them is the model's word as much as the scan's: the model-free figures are the
scanner's own.

References
----------
.. [1] "Fast visual part inspection for bin picking", section II: edges
   as drop-outs and discontinuities along the profile.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from scanner_core.edges.filters import _nearest_of_profile, _points3
from scanner_core.edges.profile import EdgeKind, profile_axes
from scanner_core.geometry import angle_between, apply_transform
from scanner_core.edges.mesh import across_outline, boundary_edges

__all__ = ["SOFT_CREASE_DEG", "STRIPE_LOSS_DEG", "MODEL_EDGE_TOL_MM", "EDGE_KIND_NAMES",
           "AsideEdges", "sheet_range_b", "turned_away", "ModelEdges", "model_distances",
           "segment_distances", "reclassify_with_model", "kind_counts"]

#: Faces meeting at no more than this (degrees between their normals) make no edge of the part:
#: the feature angle of the CAD edge model (``scanner_core.pose.models.EdgeModel.from_mesh``) and of
#: the edge evaluation. So the surface beyond a drop-out may have turned by up to this much
#: from the one the stripe ended on, with no edge between them.
SOFT_CREASE_DEG = 30.0
#: The sheet's incidence on a matte surface at which the stripe is lost, degrees: on the
#: faceted dome (``simulator.parts.faceted_dome``) in the reference cell (stripe about 200 DN
#: at normal incidence, found down to about 30 DN) the stripe was measured on its 78-degree
#: tier up to 82.2 degrees of incidence (the fan's rays tilt a few degrees from the range
#: axis there) and lost from 82.5 degrees (cos 82 = 0.14: about 28 DN).
STRIPE_LOSS_DEG = 82.0
#: An edge point lies on the model's edge when it is within this of it, mm: the pose's own
#: agreement score (``scanner_core.pose.search._final_score``) counts an edge point as matched
#: within 5 times the expected edge scatter (``PoseParams.edge_noise_mm``, 0.03 mm).
MODEL_EDGE_TOL_MM = 0.15
#: A step's or drop-out's near side is the nearest point of its own profile within this, mm:
#: a profile's points lie about 0.16 mm apart, a step's point half the step's height (its
#: near end, computed) from its wall's top; a wider reach would take another surface.
NEAR_REACH_MM = 1.0
#: Point-segment pairs per block of the distance search (about 100 MB of temporaries).
PAIRS_PER_BLOCK = 1_000_000
#: Segments shorter than this (mm) count as points.
DEGENERATE_MM = 1e-9

#: Report names of ``EdgeKind`` codes.
EDGE_KIND_NAMES = {EdgeKind.DROPOUT: "dropout", EdgeKind.STEP: "step",
                   EdgeKind.OCCLUDED: "occluded", EdgeKind.GRAZING: "grazing",
                   EdgeKind.TURNED_AWAY: "turned_away", EdgeKind.OFF_MODEL: "off_model"}


@dataclass
class AsideEdges:
    """Edge points a scan keeps out of its edge cloud, and why (``Scan.edges_aside``).

    Attributes
    ----------
    points : (K, 3) float32
        mm in {T}.
    frame_ids : (K,) int32
    kind : (K,) uint8
        ``EdgeKind`` saying why: ``OCCLUDED``, ``GRAZING``, ``TURNED_AWAY``, ``OFF_MODEL``.
    found : (K,) uint8
        What the profile found there: ``EdgeKind.DROPOUT`` or ``EdgeKind.STEP``.
    size_mm : (K,) float32
        As ``Scan.edge_size_mm``.
    quality : (K,) float32
        As ``Scan.edge_quality``.
    """

    points: np.ndarray
    frame_ids: np.ndarray
    kind: np.ndarray
    found: np.ndarray
    size_mm: np.ndarray
    quality: np.ndarray

    def __len__(self) -> int:
        return len(self.kind)

    @classmethod
    def empty(cls) -> "AsideEdges":
        return cls(np.zeros((0, 3), np.float32), np.zeros(0, np.int32), np.zeros(0, np.uint8),
                   np.zeros(0, np.uint8), np.zeros(0, np.float32), np.zeros(0, np.float32))

    def select(self, mask) -> "AsideEdges":
        mask = np.asarray(mask)
        return AsideEdges(self.points[mask], self.frame_ids[mask], self.kind[mask],
                          self.found[mask], self.size_mm[mask], self.quality[mask])

    @staticmethod
    def concatenate(parts) -> "AsideEdges":
        parts = list(parts)
        if not parts:
            return AsideEdges.empty()
        return AsideEdges(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                            ("points", "frame_ids", "kind", "found", "size_mm", "quality")))


# ---------------------------------------------------------------------------------------------
# Model-free: the near side's view and light margins


def sheet_range_b(calibration) -> np.ndarray:
    """(3,) float64: the sheet's range axis in {B} (``scanner_core.edges.profile_axes``'
    ``e_d``: in the sheet, across the stripe, away from the camera), unit."""
    _, e_d = profile_axes(calibration.camera, calibration.light_plane_c)
    return np.einsum("ji,j->i", calibration.camera.rotation, e_d)  # {C} -> {B}, no BLAS


def turned_away(points_t, kinds, sizes_mm, range_t, sensors_t, cloud_t, cloud_frame_ids,
                frame_ids, cloud_sensors_t, *, crease_deg: float = SOFT_CREASE_DEG,
                loss_deg: float = STRIPE_LOSS_DEG, cloud_tree=None):
    """Edge points whose surface may go on unseen beyond them: turned out of the camera's
    view or out of the sheet's light by less than a soft crease (module docstring).

    Parameters
    ----------
    points_t : (M, 3) float
        Edge points in {T}, mm.
    kinds : (M,) int
        ``EdgeKind.DROPOUT`` or ``EdgeKind.STEP`` of each.
    sizes_mm : (M,) float
        A step's height, mm (``EdgePoints.size_mm``); unused for drop-outs.
    range_t : (M, 3) float
        The sheet's range axis (``scanner_core.edges.profile_axes``' ``e_d``: in the sheet,
        away from the camera) in {T} at each point's frame, unit.
    sensors_t : (M, 3) float
        The camera's centre in {T} at each point's frame, mm.
    cloud_t : (N, 3) float
        The scan's cloud in {T}, mm.
    cloud_frame_ids : (N,) int
    frame_ids : (M,) int
        The profile of each edge point.
    cloud_sensors_t : (N, 3) float
        The camera's centre at each cloud point's frame (``scanner_core.io.scanfiles.point_sensors``).
    crease_deg : float
        The largest crease that is no edge.
    loss_deg : float
        The sheet's incidence at which the stripe is lost.
    cloud_tree : scipy.spatial.cKDTree, optional
        A KD-tree over `cloud_t`; built here without.

    Returns
    -------
    turned : (M,) bool
        Either margin below `crease_deg`; False where the near side's plane is unknown (no
        point of its profile within ``NEAR_REACH_MM``, or too few neighbours for a plane).
    view_margin_deg, light_margin_deg : (M,) float64
        The margins, degrees; NaN where unknown.
    """
    from scipy.spatial import cKDTree

    from scanner_core.normals import estimate_normals

    points = _points3(points_t, "points_t")
    m = len(points)
    axis = _points3(range_t, "range_t")
    sensors = _points3(sensors_t, "sensors_t")
    kinds = np.asarray(kinds).reshape(-1)
    sizes = np.asarray(sizes_mm, dtype=np.float64).reshape(-1)
    frames = np.asarray(frame_ids).reshape(-1).astype(np.int64)
    if (axis.shape != points.shape or sensors.shape != points.shape
            or kinds.shape != (m,) or sizes.shape != (m,) or frames.shape != (m,)):
        raise ValueError(f"`range_t`, `sensors_t` must be ({m}, 3) and `kinds`, `sizes_mm`, "
                         f"`frame_ids` ({m},) like `points_t`, got {axis.shape}, "
                         f"{sensors.shape}, {kinds.shape}, {sizes.shape}, {frames.shape}")
    cloud = _points3(cloud_t, "cloud_t")
    cloud_frames = np.asarray(cloud_frame_ids).reshape(-1).astype(np.int64)
    view = np.full(m, np.nan)
    light = np.full(m, np.nan)
    if m == 0 or len(cloud) < 3:
        return np.zeros(m, bool), view, light
    # the near side's end: a step's point lies half its height beyond it, along the range axis
    half = np.where(kinds == EdgeKind.STEP, 0.5 * np.nan_to_num(sizes), 0.0)
    ends = points - half[:, None] * axis
    near = _nearest_of_profile(ends, frames, cloud, cloud_frames,
                               cKDTree(cloud) if cloud_tree is None else cloud_tree,
                               reach_mm=NEAR_REACH_MM)
    found = near >= 0
    if found.any():
        normals = estimate_normals(cloud, sensors=cloud_sensors_t, frame_ids=cloud_frames,
                                   index=near[found], fallback="nan").astype(np.float64)
        at = cloud[near[found]]
        sight = sensors[found] - at
        view[found] = 90.0 - np.degrees(angle_between(normals, sight, undirected=True))
        # the laser shines up the sheet from the camera's side: toward it is -e_d
        light[found] = loss_deg - np.degrees(angle_between(normals, -axis[found],
                                                           undirected=True))
    with np.errstate(invalid="ignore"):
        turned = (view < crease_deg) | (light < crease_deg)
    return turned, view, light


# ---------------------------------------------------------------------------------------------
# With the model: where the CAD says its edges are


@dataclass(frozen=True, eq=False)
class ModelEdges:
    """The part's sharp edges, and what its outline under a pose needs, in {P}.

    Attributes
    ----------
    vertices : (V, 3) float64
        mm in {P}.
    edges : (A, 2) int64
        Vertex pairs of the mesh's edges between two faces (``face_adjacency_edges``).
    faces : (A, 2) int64
        The two faces at each.
    face_normals : (F, 3) float64
    sharp : (A,) bool
        Faces meeting at more than the feature angle.
    boundary : (B, 2) int64
        Vertex pairs of edges used by one face only (an open mesh's border).
    """

    vertices: np.ndarray
    edges: np.ndarray
    faces: np.ndarray
    face_normals: np.ndarray
    sharp: np.ndarray
    boundary: np.ndarray

    @classmethod
    def from_mesh(cls, mesh, *, feature_angle_deg: float = SOFT_CREASE_DEG) -> "ModelEdges":
        """From a ``trimesh.Trimesh`` in {P}, mm (sharp: faces meeting at more than
        `feature_angle_deg`, as ``scanner_core.pose.models.EdgeModel.from_mesh``)."""
        return cls(np.asarray(mesh.vertices, dtype=np.float64),
                   np.asarray(mesh.face_adjacency_edges, dtype=np.int64).reshape(-1, 2),
                   np.asarray(mesh.face_adjacency, dtype=np.int64).reshape(-1, 2),
                   np.asarray(mesh.face_normals, dtype=np.float64),
                   np.asarray(mesh.face_adjacency_angles) > math.radians(feature_angle_deg),
                   boundary_edges(np.asarray(mesh.faces, dtype=np.int64)))

    def segments_t(self, pose, *, outline: bool = True) -> np.ndarray:
        """(S, 2, 3) float64: the sharp edges, the border and (with `outline`) the outline
        seen from the sensor (+z_T) under ``pose`` (^T X_P), placed in {T}, mm."""
        pose = np.asarray(pose, dtype=np.float64)
        keep = self.sharp.copy()
        if outline:
            keep |= across_outline(self.face_normals, self.faces, pose[2, :3])  # z_T in {P}
        index = np.concatenate([self.edges[keep], self.boundary])
        return apply_transform(pose, self.vertices[index].reshape(-1, 3)).reshape(-1, 2, 3)


def model_distances(points_t, kinds, model: ModelEdges, pose) -> np.ndarray:
    """(M,) float64: how far each edge point lies from the model's edges under ``pose``, mm,
    in the (x_T, y_T) plane, as the pose's residual for an edge point (its distance to the
    vertical plane through the edge it matches): a drop-out from the sharp edges and the
    outline seen from the sensor (a rounded rim's stripe ends where it turns away), a step
    (``kinds`` == ``EdgeKind.STEP``) from the sharp edges (its half-height point on a
    leaning wall lies off them, and the pose cannot use it either)."""
    points = _points3(points_t, "points_t")
    kinds = np.asarray(kinds).reshape(-1)
    if kinds.shape != (len(points),):
        raise ValueError(f"`kinds` must be ({len(points)},), got {kinds.shape}")
    out = np.full(len(points), np.inf)
    step = kinds == EdgeKind.STEP
    for mask, outline in ((~step, True), (step, False)):
        if mask.any():
            segments = model.segments_t(pose, outline=outline)
            out[mask] = segment_distances(points[mask, :2], segments[:, :, :2])
    return out


def segment_distances(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest segment, by brute force in blocks of
    ``PAIRS_PER_BLOCK`` point-segment pairs (this and the simulator's edge evaluation,
    ``simulator.evaluate.edge_distances``).

    Parameters
    ----------
    points : (N, D) float64
        D = 2 (in a plane, such as (x_T, y_T)) or 3, mm.
    segments : (S, 2, D) float64
        Their two ends, mm; one shorter than ``DEGENERATE_MM`` counts as a point.

    Returns
    -------
    (N,) float64
        mm; inf for every point when there is no segment.
    """
    out = np.full(len(points), np.inf)
    if len(segments) == 0 or len(points) == 0:
        return out
    a = segments[:, 0]
    ab = segments[:, 1] - a
    length2 = np.einsum("sk,sk->s", ab, ab)
    tiny = DEGENERATE_MM**2
    inv = np.where(length2 > tiny, 1.0 / np.maximum(length2, tiny), 0.0)
    block = max(1, PAIRS_PER_BLOCK // len(segments))
    for i0 in range(0, len(points), block):
        ap = points[i0:i0 + block, None, :] - a[None]
        t = np.clip(np.einsum("nsk,sk->ns", ap, ab) * inv, 0.0, 1.0)
        diff = ap - t[..., None] * ab[None]
        out[i0:i0 + block] = np.sqrt(np.einsum("nsk,nsk->ns", diff, diff).min(axis=1))
    return out


def reclassify_with_model(scan, model: ModelEdges, pose, *,
                          tol_mm: float = MODEL_EDGE_TOL_MM) -> int:
    """Edge kinds by the registered model, in place: the scan's edge points farther than
    `tol_mm` from every model edge (:func:`model_distances`) go aside
    (``EdgeKind.OFF_MODEL``). Points set aside before (turned away, occluded, grazing) stay
    aside: a point the scan could not vouch for is not made an edge by being near one.

    Parameters
    ----------
    scan : scanner_core.types.Scan
    model : ModelEdges
    pose : (4, 4) float
        The registered ^T X_P.
    tol_mm : float

    Returns
    -------
    int
        The points set aside.
    """
    aside = scan.edges_aside if scan.edges_aside is not None else AsideEdges.empty()
    distance = model_distances(scan.edges, scan.edge_kind, model, pose)
    off = ~(distance <= tol_mm)
    moved = AsideEdges(scan.edges[off], scan.edge_frame_ids[off],
                       np.full(int(off.sum()), EdgeKind.OFF_MODEL, np.uint8),
                       scan.edge_kind[off], scan.edge_size_mm[off], scan.edge_quality[off])
    keep = ~off
    scan.edges, scan.edge_frame_ids = scan.edges[keep], scan.edge_frame_ids[keep]
    scan.edge_kind, scan.edge_size_mm = scan.edge_kind[keep], scan.edge_size_mm[keep]
    scan.edge_quality = scan.edge_quality[keep]
    scan.edges_aside = AsideEdges.concatenate([aside, moved])
    return int(off.sum())


def kind_counts(scan) -> dict:
    """Edge points per kind (``EDGE_KIND_NAMES``): in the edge cloud and set aside."""
    counts = {name: 0 for name in EDGE_KIND_NAMES.values()}
    for kinds in (scan.edge_kind, getattr(scan.edges_aside, "kind", np.zeros(0, np.uint8))):
        codes, n = np.unique(np.asarray(kinds), return_counts=True)
        for code, count in zip(codes, n):
            name = EDGE_KIND_NAMES.get(int(code), str(int(code)))
            counts[name] = counts.get(name, 0) + int(count)
    return counts
