"""The part's models a scan is registered against (``scanner_core.pose.registration``): its surface and
its sharp edges, sampled in {P}.

- `SurfaceModel`: points on the surface with their normals: the CAD sampled evenly by area
  (`SurfaceModel.from_mesh`), or any points with normals, such as the simulator's predicted
  cloud of the same pass (`SurfaceModel.from_points`).
- `EdgeModel`: points along the sharp edges with the edge's direction; the two edges of a
  chamfer narrower than ``BEVEL_MM`` made one line (`merge_bevels`), the one on the outline
  seen from the sensor where there is one (`outline_adjacency`, with the mesh's other edge
  tests in ``scanner_core.edges.mesh``).

Each keeps a KD-tree over its points (`tree`: the neighbours of its own samples, and the
points far from it), an exact grid search of them (`grid`: the fits' and the decisive
scores' nearest samples) and a lookup table for the search's screening (`lookup`), built on
first use. Units: mm.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from scanner_core.pose.nearest_table import NearestGrid, NearestTable
from scanner_core.edges.mesh import TOWARD_MIN, boundary_edges, outline_adjacency
from scanner_core.pose.symmetry import exact_symmetries, surface_moments

__all__ = ["SurfaceModel", "EdgeModel", "merge_bevels", "outline_adjacency", "BEVEL_MM",
           "TOWARD_MIN"]

#: Parallel sharp edges of the CAD closer than this (mm, about two pixels' footprint) are
#: one edge to the scanner: a chamfer's two (`merge_bevels`).
BEVEL_MM = 0.4
#: Edge samples within this many spacings whose directions agree within _CURVE_DEG degrees
#: lie on one edge curve (`EdgeModel.curves`).
_CURVE_SPACINGS = 2.0
_CURVE_DEG = 10.0
#: Samples whose normals differ by more than this, degrees, lie on two faces of a crease
#: (`SurfaceModel.crease_planes`): the edge model's feature angle (`EdgeModel.from_mesh`),
#: an edge the scanner sees. Below it two faces are a curved surface's facets, where a
#: point's nearest sample is as good as its neighbour's (a round shaft's 128 sides).
CREASE_DEG = 30.0
#: The nearest samples a sample's crease neighbour is looked for among.
CREASE_NEIGHBOURS = 8
#: Where an edge model without edges keeps its one unreachable point, mm.
_NOWHERE_MM = 1e9
#: How far from the models their lookup tables (`scanner_core.pose.nearest_table`) answer, mm:
#: the search's widest bounds at the default settings (twice ``PoseParams.gate_mm``, plus
#: two spacings for surfaces; plus the edge search, 15 mm, for edges). A wider bound is
#: answered by the KD-tree beyond them.
LOOKUP_BAND_MM = {"surface": 12.5, "edge": 26.0}


@dataclass(frozen=True, eq=False)
class SurfaceModel:
    """Points on the part's surface with their normals, in {P}, and a KD-tree over them.

    Attributes
    ----------
    points : (M, 3) float64
        mm in {P}.
    normals : (M, 3) float64
        Unit outward normals.
    spacing_mm : float
        Mean distance between samples.
    moments : tuple or None
        The surface's centroid, principal axes and second moments
        (``pose_symmetry.surface_moments``) of the mesh it was sampled from; None: of the
        samples, when first needed.
    faces : (M,) int64 or None
        The face each sample lies on: the mesh's triangles joined across edges where they
        meet at under ``CREASE_DEG`` (a flat face, a cylinder's wall, a chamfer), numbered
        from 0; None where the model has no mesh (`from_points`). The scan's points on one
        face share what shifts that face as a whole (``scanner_core.pose.confidence``).
    """

    points: np.ndarray
    normals: np.ndarray
    spacing_mm: float = 0.5
    moments: tuple | None = None
    faces: np.ndarray | None = None

    @classmethod
    def from_mesh(cls, mesh, *, spacing_mm: float = 0.25, max_points: int = 400_000,
                  seed: int = 0) -> "SurfaceModel":
        """Sample a mesh evenly by area, each sample with its face's normal.

        Point-to-plane distances to a sample's plane are exact on planar faces whatever the
        spacing; the spacing only decides which face a point finds near an edge: there a
        point of one face can find its nearest sample on the other, and read its distance to
        that face's plane (a rim's top-face point measured across to the wall below): the
        fine fit leaves such a point unmatched (`crease_planes`).

        Parameters
        ----------
        mesh : trimesh.Trimesh
            The part in {P}, mm.
        spacing_mm : float
            Mean distance between samples.
        max_points : int
            Upper bound on the samples (large parts get a coarser spacing).
        """
        import trimesh

        area = float(mesh.area)
        count = int(min(max_points, max(1000, area / spacing_mm**2)))
        rng_state = np.random.default_rng(seed)
        points, faces = trimesh.sample.sample_surface(mesh, count, seed=rng_state)
        normals = np.asarray(mesh.face_normals, dtype=np.float64)[faces]
        return cls(np.asarray(points, dtype=np.float64), normals, float(np.sqrt(area / count)),
                   surface_moments(mesh), smooth_faces(mesh)[faces])

    @classmethod
    def from_points(cls, points, normals) -> "SurfaceModel":
        """A model from points with normals (the simulator's predicted cloud, say), in {P}."""
        points = np.asarray(points, dtype=np.float64)
        normals = np.asarray(normals, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
            raise ValueError(f"points and normals must both be (M, 3), got {points.shape} "
                             f"and {normals.shape}")
        keep = np.isfinite(points).all(axis=1) & np.isfinite(normals).all(axis=1)
        n = normals[keep]
        return cls(points[keep], n / np.linalg.norm(n, axis=1, keepdims=True))

    @cached_property
    def tree(self) -> cKDTree:
        return _tree(self.points)

    @cached_property
    def grid(self) -> NearestGrid:
        """The exact nearest samples of the fits and of the scores that decide
        (`scanner_core.pose.nearest_table.NearestGrid`), the KD-tree answering far points."""
        return _grid(self)

    @cached_property
    def symmetries(self) -> np.ndarray:
        """(K, 4, 4) float64: the turns in {P} that map the part onto itself, the identity
        first (``pose_symmetry.exact_symmetries``); built on first use and kept."""
        if self.moments is None:
            centroid = self.points.mean(axis=0)
            moments, axes = np.linalg.eigh(np.cov((self.points - centroid).T))
        else:
            centroid, axes, moments = self.moments
        return exact_symmetries(self, centroid, axes, moments)

    @cached_property
    def lookup(self) -> NearestTable:
        """A lookup table of the nearest sample (`scanner_core.pose.nearest_table`), for the
        search's screening: approximate, O(1) a point."""
        return _lookup(self, LOOKUP_BAND_MM["surface"])

    @cached_property
    def crease_planes(self) -> np.ndarray:
        """(M, 4) float64: for each sample beside a crease, the plane ``(n, d)`` (``n . x =
        d``) of its ``CREASE_NEIGHBOURS`` nearest samples' whose normal is furthest from its
        own, where that is more than ``CREASE_DEG`` degrees; NaN rows elsewhere. A point
        matched to the sample that lies nearer that plane than the sample's own lies on the
        crease's other face, and the fine fit leaves it unmatched
        (``scanner_core.pose.fine``). Built on first use (`scanner_core.cad` builds it when
        a part is armed) and kept."""
        planes = np.full((len(self.points), 4), np.nan)
        if len(self.points) <= 1:
            return planes
        k = min(CREASE_NEIGHBOURS, len(self.points) - 1)
        _, index = self.tree.query(self.points, k=k + 1)
        index = index[:, 1:]
        cosine = np.einsum("mj,mkj->mk", self.normals, self.normals[index])
        far = np.argmin(cosine, axis=1)
        rows = np.nonzero(cosine[np.arange(len(far)), far] < np.cos(np.radians(CREASE_DEG)))[0]
        other = index[rows, far[rows]]
        planes[rows, :3] = self.normals[other]
        planes[rows, 3] = np.einsum("ij,ij->i", self.normals[other], self.points[other])
        return planes

    @cached_property
    def seed_cache(self) -> dict:
        """What the coarse search's seeds take of the model at a pose, by pose
        (``scanner_core.pose.search._seed_translations``): it does not depend on the scan,
        and the grid's poses around one grasp are the same at every pass."""
        return {}


@dataclass(frozen=True, eq=False)
class EdgeModel:
    """Points along the part's sharp edges with the edge's direction, in {P}, and a KD-tree.

    An edge point of the scan (where a profile crosses an edge: a drop-out or a step, placed
    at half the step's height) lies on the vertical wall through the edge, so it constrains
    the part across the edge in the (x_T, y_T) plane only: its residual is the distance to the
    vertical plane through the edge line. That is what the surfaces cannot give: a part whose
    visible faces are all level slides and turns freely over them. A step's point is matched
    from half its step above and below it as well (`register`'s ``edge_steps_mm``), to the
    edge it was found at rather than its wall's other one.

    Attributes
    ----------
    points : (M, 3) float64
        mm in {P}.
    directions : (M, 3) float64
        Unit direction of the edge each point lies on.
    """

    points: np.ndarray
    directions: np.ndarray
    spacing_mm: float = 0.1

    @classmethod
    def from_mesh(cls, mesh, *, feature_angle_deg: float = CREASE_DEG, spacing_mm: float = 0.1,
                  bevel_mm: float = BEVEL_MM, view=None) -> "EdgeModel":
        """Sample the mesh's sharp edges: faces meeting at more than `feature_angle_deg`, and
        the boundary of an open mesh; the two edges of a bevel narrower than `bevel_mm` (a
        chamfer the scanner sees as one edge) as one (`merge_bevels`).

        Parameters
        ----------
        view : (3,) array_like, optional
            The direction toward the sensor in {P} under the nominal grasp (its z_T: the
            grasp's third row). Of a bevel's two edges, the one on the outline seen from
            there (a face turned toward the sensor meets one that is not) is kept alone: a
            chamfered rim's drop-outs lie there (``scanner_core.edges.chamfered_dropouts``).
            Without it, or for a bevel with neither edge on the outline, the two are one
            line along their middle.
        """
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        is_sharp = mesh.face_adjacency_angles > np.radians(feature_angle_deg)
        sharp = mesh.face_adjacency_edges[is_sharp]
        boundary = boundary_edges(np.asarray(mesh.faces))
        segments = np.concatenate([sharp.reshape(-1, 2), boundary.reshape(-1, 2)])
        on_outline = np.zeros(len(segments), bool)
        if view is not None:
            on_outline[:len(sharp)] = outline_adjacency(mesh, view)[is_sharp]
        a, b = vertices[segments[:, 0]], vertices[segments[:, 1]]
        length = np.linalg.norm(b - a, axis=1)
        keep = length > 1e-9
        a, b, length, on_outline = a[keep], b[keep], length[keep], on_outline[keep]
        counts = np.maximum(1, np.ceil(length / spacing_mm).astype(int))
        owner = np.repeat(np.arange(len(a)), counts)
        first = np.cumsum(counts) - counts
        fraction = (np.arange(counts.sum()) - first[owner] + 0.5) / counts[owner]
        points = a[owner] + fraction[:, None] * (b - a)[owner]
        directions = ((b - a) / length[:, None])[owner]
        points, directions = merge_bevels(points, directions, bevel_mm, spacing_mm,
                                          on_outline=on_outline[owner] if view is not None
                                          else None)
        return cls(points, directions, spacing_mm)

    @cached_property
    def tree(self) -> cKDTree:
        # A part without sharp edges (a sphere): one point farther than any bound, never
        # matched (a tree of inf is refused by SciPy).
        return _tree(self.points if len(self.points) else np.full((1, 3), _NOWHERE_MM))

    @cached_property
    def grid(self) -> NearestGrid:
        """As `SurfaceModel.grid`."""
        return _grid(self)

    @cached_property
    def lookup(self) -> NearestTable:
        """As `SurfaceModel.lookup`."""
        return _lookup(self, LOOKUP_BAND_MM["edge"])

    @cached_property
    def curves(self) -> np.ndarray:
        """(M,) int64: the edge curve each sample lies on, numbered from 0.

        Samples closer than ``_CURVE_SPACINGS`` spacings whose directions agree within
        ``_CURVE_DEG`` degrees are on one curve: a straight edge, or a curved one whose
        facets turn less than that. The scan's points on one edge share an error (the real
        part's rounding of the CAD's sharp edge, the stripe fading as the surface turns away
        there), which the pose's covariance takes in by clustering them
        (``scanner_core.pose.confidence``).
        """
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        n = len(self.points)
        if n == 0:
            return np.zeros(0, np.int64)
        pairs = self.tree.query_pairs(_CURVE_SPACINGS * self.spacing_mm, output_type="ndarray")
        cosine = np.abs(np.einsum("ij,ij->i", self.directions[pairs[:, 0]],
                                  self.directions[pairs[:, 1]]))
        pairs = pairs[cosine > np.cos(np.radians(_CURVE_DEG))]
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        return connected_components(graph, directed=False)[1].astype(np.int64)


def smooth_faces(mesh, crease_deg: float = CREASE_DEG) -> np.ndarray:
    """(F,) int64: each triangle's face, the triangles joined across the edges where they meet
    at under `crease_deg` degrees (connected components), numbered from 0."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(mesh.faces)
    pairs = np.asarray(mesh.face_adjacency)[mesh.face_adjacency_angles < np.radians(crease_deg)]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def _tree(points) -> cKDTree:
    """A KD-tree over a model's points, built once per part: its own samples' neighbours,
    and the points its grid and lookup table leave to it. Sliding-midpoint splits (not
    balanced): on the reference parts' 150 000-400 000 samples it builds in about two thirds
    of the time and answers its queries about 10 % sooner; a nearest neighbour is a nearest
    neighbour either way."""
    return cKDTree(points, balanced_tree=False)


def _grid(model) -> NearestGrid:
    tree = model.tree

    def by_tree(points, k, bound):
        return tree.query(points, k=k, distance_upper_bound=bound)
    return NearestGrid(tree.data, far=by_tree)


def _lookup(model, band_mm: float) -> NearestTable:
    def by_tree(points, bound):
        return model.tree.query(points, k=1, distance_upper_bound=bound)
    return NearestTable(model.points, band_mm, fallback=by_tree)


def merge_bevels(points, directions, width_mm: float = BEVEL_MM, spacing_mm: float = 0.1, *,
                 on_outline=None):
    """Edge samples of parallel edges closer than `width_mm` made one line: the one on the
    outline where the other is not (`on_outline`), else their middle.

    A 0.2 mm chamfer has two sharp edges 0.28 mm apart; the scanner, whose pixel covers about
    0.2 mm, finds one edge between them. Matched to the nearer of the two, its edge points
    split between lines 0.2 mm apart in x_T, and the pose slides by tens of um toward
    whichever side happened to win more. One line is what the scanner sees: at a rim, the
    outline, where the chamfer's drop-outs are placed (``scanner_core.edges
    .chamfered_dropouts``); the middle, where the scanner's view is not known. ADIS16480
    (bench pose, from the nominal grasp): its outline's chamfers along the middle left a
    scan 0.86 degrees off about z_T, flagged free; along the outline, 66 mdeg, and a start
    7.5 mm and 15 degrees off lands on the truth instead of a minimum 0.15 degrees away.

    Parameters
    ----------
    points : (M, 3) float64
        Samples along the edges, mm.
    directions : (M, 3) float64
        Unit direction of each sample's edge.
    width_mm : float
        Parallel edges (within 10 degrees) closer than this are one; 0 merges nothing.
    spacing_mm : float
        The samples' spacing: of two samples closer than half of it after the merge, one is
        kept.
    on_outline : (M,) bool, optional
        Whether each sample's edge lies on the outline seen from the sensor
        (`EdgeModel.from_mesh`'s ``view``).

    Returns
    -------
    points, directions : (K, 3) float64, K <= M
    """
    points = np.asarray(points, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    if width_mm <= 0 or len(points) < 2:
        return points, directions
    if on_outline is not None:
        on_outline = np.asarray(on_outline, dtype=bool)
        if on_outline.shape != (len(points),):
            raise ValueError(f"on_outline must be ({len(points)},), got {on_outline.shape}")
    i, j, across = _bevel_pairs(points, directions, width_mm, spacing_mm)
    if on_outline is not None and len(i):
        inner = np.zeros(len(points), bool)
        one = on_outline[i] != on_outline[j]
        inner[np.where(on_outline[i], j, i)[one]] = True
        points, directions = points[~inner], directions[~inner]
        i, j, across = _bevel_pairs(points, directions, width_mm, spacing_mm)
    if not len(i):
        return points, directions
    shift = np.zeros_like(points)
    count = np.zeros(len(points))
    np.add.at(shift, i, across)
    np.add.at(shift, j, -across)
    np.add.at(count, i, 1)
    np.add.at(count, j, 1)
    moved = count > 0
    points = points.copy()
    points[moved] += shift[moved] / count[moved, None] / 2.0
    # Both lines now lie along the middle: keep one sample of each coincident pair.
    twins = cKDTree(points).query_pairs(spacing_mm / 2, output_type="ndarray")
    keep = np.ones(len(points), bool)
    keep[twins[:, 1]] = False
    return points[keep], directions[keep]


def _bevel_pairs(points, directions, width_mm, spacing_mm):
    """Pairs (i, j) of samples on parallel lines (within 10 degrees) closer than `width_mm`,
    and the offset across from i's line to j (K, 3)."""
    pairs = cKDTree(points).query_pairs(width_mm, output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    offset = points[j] - points[i]
    across = offset - np.einsum("ij,ij->i", offset, directions[i])[:, None] * directions[i]
    other_line = ((np.abs(np.einsum("ij,ij->i", directions[i], directions[j]))
                   > np.cos(np.radians(10.0)))
                  & (np.linalg.norm(across, axis=1) > spacing_mm / 2))
    return i[other_line], j[other_line], across[other_line]
