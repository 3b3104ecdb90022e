"""The part's pose in the gripper from its scan: the misplacement the robot corrects.

The scan (points in {T}, with normals toward the sensor and the frame each point came from)
is registered against the CAD model in {P}, starting from the nominal grasp ^T X_P:

- **fine**: point-to-plane Gauss-Newton (Chen and Medioni 1992; Low 2004's linearisation),
  robust to outliers (gripper fingers, reflections) through a correspondence gate, a normal
  agreement test and Tukey's biweight on the residuals (IRLS, scale from the median absolute
  residual). Motions the scan does not constrain (a turn about a symmetry axis, a slide along
  a prism) are left at their starting value instead of drifting: the update is solved in the
  observable subspace of the information matrix only.
- **coarse**: used when the fine stage from the nominal grasp does not settle on a good fit; a
  grid of orientations around the nominal grasp, each with its translation seeded from the
  scan's extent, is refined briefly on a subsample; around the best few, a finer sweep about
  the rotation their fit pins down least (a flat part's turn in its plane, held by its edges
  alone) finds the basin a many-lobed outline leaves a degree or two wide. Candidates are
  ranked by their agreement at fixed tolerances (`_agreement`), not by their own robust
  scale, which favours a loose, unsettled fit. The same sweep checks a fit from the nominal
  grasp that looks good: one a lobe off matches every edge point but a keyway's. OpenCV's
  point-pair features (Drost et al. 2010), measured against it by ``flyscan bench coarse``,
  led to 11 of 16 poses where it found 15, in about 5 times the time, after 39-258 s of
  training per part. A converged fit whose weakest turn is held loosely is also refitted
  from turns near it and from the best turns of a sweep all the way round it
  (`_probe_turns`): a round part picked from a bin can sit any turn off its nominal.
- **uncertainty**: the covariance of the six motion parameters is the cluster-robust
  sandwich ``H^-1 (sum_f g_f g_f^T) H^-1`` over the frames f (Liang and Zeger 1986): the
  points of one profile share that frame's placement error (the marker's triangulation), so
  they are not independent, and the sandwich takes that from the residuals themselves. It is
  scaled by ``PoseParams.sigma_inflation`` (2.6, measured by ``flyscan bench pose``) for what
  it cannot see: biases shared by every profile that crosses one edge.

The model is the CAD surface sampled densely with face normals (`SurfaceModel.from_mesh`), or
any points with normals, such as the simulator's predicted cloud of the same pass
(`SurfaceModel.from_points`). Units: mm, radians inside, degrees in the report.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.ndimage import maximum_filter1d
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

__all__ = ["PoseParams", "SurfaceModel", "EdgeModel", "PoseResult", "register", "scan_pose",
           "AXIS_NAMES", "MIN_POSE_POINTS", "BEVEL_MM", "TOWARD_MIN", "merge_bevels",
           "outline_adjacency"]

#: Parallel sharp edges of the CAD closer than this (mm, about two pixels' footprint) are
#: one edge to the scanner: a chamfer's two (`merge_bevels`).
BEVEL_MM = 0.4

#: A face is turned toward the sensor when its unit normal's component along the view
#: exceeds this: a wall side-on to it (0, give or take float noise: a float32 STL's walls
#: carry +-1e-7) is not.
TOWARD_MIN = 1e-6

#: A scan with fewer points gives no pose (refused, with the reason), not a guess.
MIN_POSE_POINTS = 50

AXIS_NAMES = ("tx", "ty", "tz", "rx", "ry", "rz")
_AXIS_LABELS = ("x_T", "y_T", "z_T")
# Tukey's biweight constant: 95 % efficiency under Gaussian noise.
_TUKEY_C = 4.685
# The median absolute deviation of a Gaussian is 0.6745 sigma.
_MAD_TO_SIGMA = 1.0 / 0.6745


@dataclass(frozen=True)
class PoseParams:
    """Settings of the registration.

    Attributes
    ----------
    max_points : int
        Scan points used by the fine stage (a seeded, even subsample beyond it).
    gate_mm : float
        Correspondences farther than this are outliers at the start of the fine stage.
    min_gate_mm : float
        The gate shrinks to ``max(min_gate_mm, 6 sigma)`` as the fit settles.
    normal_agreement_deg : float
        A scan point and its model point whose normals differ by more are not matched (the
        other side of a thin wall, the wrong face at an edge).
    max_iterations : int
        Gauss-Newton iterations of the fine stage.
    tol_mm, tol_deg : float
        Convergence: an update smaller than both ends the fine stage.
    surface_noise_mm, edge_noise_mm : float
        The expected scatter of surface and edge points: they weight the two kinds against
        each other and decide what is observable (the geometry, not the noise of the
        moment: early in a fit the residuals are large for want of a good pose).
    free_std_mm : float
        A motion that the scan, at the expected scatter, would pin down no better than this
        (its standard deviation, mm; rotations as arc length at the scan's radius) is free:
        not observable. It keeps its starting value.
    min_frames : float
        Nor is a motion whose information comes from fewer profiles than this (their
        participation ratio): a profile's points share its placement error.
    good_inlier_fraction, good_edge_fraction : float
        The fine stage from the nominal grasp is accepted when at least these fractions of the
        surface points and of the edge points are inliers; otherwise the coarse search runs.
        (A sound fit may match fewer edge points: chamfers, rounded rims and occlusion
        boundaries give edge points the CAD's sharp edges do not have; at 0.6 instead of 0.8
        `bench pose` found wrong minima 6 degrees off accepted on idler_riser.)
    sigma_inflation : float
        The reported standard deviations are the sandwich estimate times this: what
        ``flyscan bench pose`` measured it takes for the errors of converged poses to stay
        within 3 sigma (the errors the sandwich cannot see: edge placement biases shared by
        all the profiles crossing one edge).
    coarse_step_deg, coarse_extent_deg : float
        The coarse grid of rotation vectors around the nominal: every combination of
        ``-extent..extent`` in ``step`` about the three {T} axes.
    coarse_points : int
        Scan points used to score each coarse candidate.
    coarse_iterations : int
        Iterations refining each coarse candidate.
    probe_weakness : float
        A converged fit whose weakest rotation is held less than this (its information over the
        strongest rotation's, translations free) is probed with refits from turns of 1 and 2
        degrees about it, and, unless the scan leaves it free, from the best turns of a sweep
        all the way round it (a part near-symmetric about it: cycloidal's lobes fit 90
        degrees off, a many-lobed disc's any whole number of lobes): a minimum that fits
        clearly better is taken; another that fits as well makes the pose ambiguous, and the
        spread between them enters its uncertainty. A fit whose surfaces alone hold that
        rotation little (``_EDGES_ALONE``) is probed too. (Measured at the bench's fits:
        idler_riser 0.030-0.043, held by its surfaces; ADIS16480 0.0023-0.026, featuretype
        0.044-0.055, cycloidal 0.016-0.032.)
    coarse_sweep_deg : float
        Step of the finer sweep about the weakest rotation of the best coarse candidates
        (across one step of the grid); the seeds it finds are refined like the grid's. Also
        the step of the probe's sweep all the way round (``probe_weakness``).
    max_fine_turn_deg : float
        The fine stage is a local search: a fit that turned farther than this from its start
        has slid onto another face of the part (a scan of one flat end fits any flat face;
        ``flyscan bench pose`` saw ADIS16480 fits 84 degrees off from starts 10 and 15
        degrees off, while converged fits turned at most 30 degrees, the bench's farthest
        start). It is not accepted: the coarse search runs from the start, and a pose that
        still lies this far from it is flagged implausible.
    seed : int
        Seed of the subsampling.
    """

    max_points: int = 6000
    gate_mm: float = 5.0
    min_gate_mm: float = 0.2
    normal_agreement_deg: float = 60.0
    max_iterations: int = 60
    tol_mm: float = 1e-5
    tol_deg: float = 1e-5
    surface_noise_mm: float = 0.01
    edge_noise_mm: float = 0.03
    free_std_mm: float = 0.05
    min_frames: float = 2.0
    good_inlier_fraction: float = 0.8
    good_edge_fraction: float = 0.8
    sigma_inflation: float = 2.6
    coarse_step_deg: float = 15.0
    coarse_extent_deg: float = 15.0
    coarse_points: int = 800
    coarse_iterations: int = 8
    coarse_sweep_deg: float = 1.0
    probe_weakness: float = 0.015
    max_fine_turn_deg: float = 45.0
    seed: int = 0


@dataclass(frozen=True, eq=False)
class SurfaceModel:
    """Points on the part's surface with their normals, in {P}, and a KD-tree over them.

    Attributes
    ----------
    points : (M, 3) float64
        mm in {P}.
    normals : (M, 3) float64
        Unit outward normals.
    """

    points: np.ndarray
    normals: np.ndarray
    spacing_mm: float = 0.5

    @classmethod
    def from_mesh(cls, mesh, *, spacing_mm: float = 0.25, max_points: int = 400_000,
                  seed: int = 0) -> "SurfaceModel":
        """Sample a mesh evenly by area, each sample with its face's normal.

        Point-to-plane distances to a sample's plane are exact on planar faces whatever the
        spacing; the spacing only decides which face a point finds near an edge.

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
        return cls(np.asarray(points, dtype=np.float64), normals, float(np.sqrt(area / count)))

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
        return cKDTree(self.points)


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
    def from_mesh(cls, mesh, *, feature_angle_deg: float = 30.0, spacing_mm: float = 0.1,
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
        boundary = _boundary_edges(np.asarray(mesh.faces))
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
        return cKDTree(self.points if len(self.points) else np.zeros((1, 3)) + np.inf)


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


def outline_adjacency(mesh, view) -> np.ndarray:
    """(A,) bool over ``mesh.face_adjacency`` (and its ``face_adjacency_edges``): whether the
    two faces lie on either side of the outline seen from `view`, (3,) in the mesh's frame:
    one turned toward it (beyond `TOWARD_MIN`), the other not."""
    toward = np.asarray(mesh.face_normals, dtype=np.float64) @ np.asarray(
        view, dtype=np.float64) > TOWARD_MIN
    adjacency = np.asarray(mesh.face_adjacency)
    return toward[adjacency[:, 0]] != toward[adjacency[:, 1]]


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


def _boundary_edges(faces: np.ndarray) -> np.ndarray:
    """(B, 2) vertex pairs used by one face only."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return unique[counts == 1]


@dataclass
class PoseResult:
    """The registered pose and how far to trust it.

    Attributes
    ----------
    matrix : (4, 4) float64
        ^T X_P, mm.
    misplacement : (4, 4) float64
        ``matrix @ inv(nominal)``: the correction in {T}.
    rms_mm : float
        RMS point-to-plane residual of the inliers.
    inlier_fraction : float
        Fraction of the used scan points matched within the final gate.
    std : (6,) float64
        Standard deviation of tx, ty, tz (mm, of the {T} origin's correction) and rx, ry, rz
        (degrees, about the {T} axes); NaN along a free motion.
    free_axes : list of dict
        The motions the scan does not constrain: ``{"kind": "translation" | "rotation",
        "axis": [x, y, z] in {T}, "label": ...}``.
    covariance : (6, 6) float64
        Of (tx, ty, tz in mm, rx, ry, rz in rad); NaN rows and columns along free motions.
    iterations : int
    coarse : bool
        Whether the coarse search ran.
    time_ms : float
        The registration's time; `normals_ms` before it (`scan_pose`) estimated the normals.
    flags : list of str
        Why not to trust the pose as it stands (a poor fit, too few edges, free motions);
        empty for a pose to act on.
    """

    matrix: np.ndarray
    misplacement: np.ndarray
    rms_mm: float
    inlier_fraction: float
    std: np.ndarray
    free_axes: list = field(default_factory=list)
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    iterations: int = 0
    coarse: bool = False
    time_ms: float = 0.0
    flags: list = field(default_factory=list)
    normals_ms: float = 0.0

    @property
    def observable(self) -> bool:
        return not self.free_axes

    def misplacement_vector(self) -> np.ndarray:
        """(6,) float64: translation mm and rotation vector degrees of `misplacement`."""
        rotvec = Rotation.from_matrix(self.misplacement[:3, :3]).as_rotvec(degrees=True)
        return np.concatenate([self.misplacement[:3, 3], rotvec])

    def to_dict(self) -> dict:
        """The ``pose`` entry of ``report.json`` (JSON-safe: NaN becomes None)."""
        vector = self.misplacement_vector()

        def clean(values):
            return [None if not np.isfinite(v) else round(float(v), 7) for v in values]

        return {
            "matrix": np.asarray(self.matrix).tolist(),
            "misplacement": {"translation_mm": clean(vector[:3]),
                             "rotation_deg": clean(vector[3:])},
            "rms_mm": round(float(self.rms_mm), 6),
            "inlier_fraction": round(float(self.inlier_fraction), 4),
            "observable": self.observable,
            "free_axes": self.free_axes,
            "std": dict(zip(("tx_mm", "ty_mm", "tz_mm", "rx_deg", "ry_deg", "rz_deg"),
                            clean(self.std))),
            "iterations": self.iterations,
            "coarse": self.coarse,
            "flags": list(self.flags),
            "time_ms": round(self.time_ms, 3),
            "normals_ms": round(self.normals_ms, 3),
        }


# --------------------------------------------------------------------------------------------
# Registration
# --------------------------------------------------------------------------------------------

def register(points_t, normals_t, model: SurfaceModel, nominal, *, frame_ids=None,
             edges_t=None, edge_frame_ids=None, edge_model: EdgeModel | None = None,
             edge_steps_mm=None, params: PoseParams = PoseParams()) -> PoseResult:
    """The part's pose ^T X_P from its scan.

    Parameters
    ----------
    points_t : (N, 3) float
        The scan in {T}, mm.
    normals_t : (N, 3) float or None
        Unit normals of the scan, oriented toward the sensor (``scanner_core.normals``):
        a model point whose normal differs by more than ``normal_agreement_deg`` is no match.
        NaN rows (or None) are used without that test.
    model : SurfaceModel
        The part's surface in {P}.
    nominal : (4, 4) array_like
        The nominal grasp ^T X_P, mm: the starting point, and what free motions keep.
    frame_ids : (N,) int, optional
        The frame of each point, for the uncertainty (each frame one cluster); default
        every point its own cluster, which underestimates the uncertainty of a real scan.
    edges_t : (M, 3) float, optional
        The edge cloud in {T}, mm; with `edge_model`, it constrains the in-plane motions.
    edge_frame_ids : (M,) int, optional
        The frame of each edge point.
    edge_model : EdgeModel, optional
        The part's sharp edges in {P}.
    edge_steps_mm : (M,) float, optional
        Per edge point, the height of its step (``Scan.edge_size_mm`` of a step point), 0 or
        NaN for a drop-out: a step's point lies half of it from the edge it was found at,
        and is matched from there. Default: every point a drop-out.
    params : PoseParams

    Returns
    -------
    PoseResult

    Raises
    ------
    ValueError
        Bad shapes, or fewer than 6 finite points.
    """
    t0 = time.perf_counter()
    points, directions, frames = _check_inputs(points_t, normals_t, frame_ids)
    agreement = np.cos(np.radians(params.normal_agreement_deg))
    nominal = np.asarray(nominal, dtype=np.float64)
    rng = np.random.default_rng(params.seed)
    used = _subsample(len(points), params.max_points, rng)
    surface = _Terms(points[used], directions[used], frames[used], model, agreement)
    edges = None
    if edges_t is not None and edge_model is not None and len(edge_model.points):
        e_points, _, e_frames = _check_inputs(edges_t, None, edge_frame_ids, minimum=0)
        steps = _edge_steps(edges_t, edge_steps_mm)
        if len(e_points):
            edges = _Terms(e_points, None, e_frames, edge_model, steps_mm=steps)

    fit = _fine(surface, edges, nominal, params)
    coarse = False
    slid = _turn_deg(fit.pose, nominal) > params.max_fine_turn_deg
    if (slid or fit.inlier_fraction < params.good_inlier_fraction
            or fit.edge_fraction < params.good_edge_fraction
            or _better_turn(surface, edges, fit.pose, params)):
        starts = _coarse(surface, edges, nominal, params, rng)
        candidate = _fine(surface, edges, starts[0], params)
        coarse = True
        candidate_slid = _turn_deg(candidate.pose, nominal) > params.max_fine_turn_deg
        if (slid and not candidate_slid) or (
                slid == candidate_slid and _final_score(surface, edges, candidate, params)
                > _final_score(surface, edges, fit, params)):
            fit = candidate
    before_probes = fit.pose
    fit, rivals = _probe_turns(surface, edges, fit, params)
    covariance, std, free_axes = _uncertainty(fit, params, rivals)
    flags = _flags(fit, free_axes, edges is not None, params)
    turned = _turn_deg(before_probes, nominal)
    if turned > params.max_fine_turn_deg:
        flags.append(f"implausible: the fit turned {turned:.0f} degrees from the start, farther "
                     f"than a misplacement the search covers ({params.max_fine_turn_deg:g})")
    if rivals:
        flags.append("ambiguous: " + "; ".join(_rival_words(fit.pose, r) for r in rivals)
                     + " fits as well")
    return PoseResult(
        matrix=fit.pose, misplacement=fit.pose @ np.linalg.inv(nominal), rms_mm=fit.rms,
        inlier_fraction=fit.inlier_fraction, std=std, free_axes=free_axes,
        covariance=covariance, iterations=fit.iterations, coarse=coarse,
        time_ms=(time.perf_counter() - t0) * 1e3, flags=flags)


def _turn_deg(pose, other) -> float:
    """The angle between two poses' rotations, degrees."""
    relative = np.asarray(pose)[:3, :3] @ np.asarray(other)[:3, :3].T
    return float(np.degrees(Rotation.from_matrix(relative).magnitude()))


# A converged fit is scored at this many times the expected scatter.
_FINAL_TOL = 5.0


def _final_score(surface, edges, fit: _Fit, params) -> float:
    """A converged fit's agreement at ``_FINAL_TOL`` times the expected scatter."""
    return _agreement(surface, edges, fit.pose, _FINAL_TOL * params.surface_noise_mm,
                      _FINAL_TOL * params.edge_noise_mm)


def _flags(fit: _Fit, free_axes, with_edges: bool, params: PoseParams) -> list[str]:
    flags = []
    if fit.inlier_fraction < params.good_inlier_fraction:
        flags.append(f"poor fit: {fit.inlier_fraction:.0%} of the points match the model")
    if with_edges and fit.edge_fraction < params.good_edge_fraction:
        flags.append(f"poor fit: {fit.edge_fraction:.0%} of the edge points match the model's "
                     "edges")
    if fit.rms > _RMS_FLAG * params.surface_noise_mm:
        flags.append(f"large residuals: {fit.rms * 1e3:.0f} um RMS")
    if free_axes:
        flags.append("not observable: " + ", ".join(a["label"] for a in free_axes))
    return flags


def scan_pose(scan, surface_model: SurfaceModel, nominal, *, edge_model: EdgeModel | None = None,
              params: PoseParams = PoseParams()) -> PoseResult:
    """The pose of a stitched scan (``scanner_core.types.Scan``): its cloud (up to
    ``params.max_points`` of it) with normals toward the camera, its frames as clusters, and
    its edge cloud when it has one.

    Raises
    ------
    ValueError
        Fewer than `MIN_POSE_POINTS` points: no pose is better than a guess.
    """
    from scanner_core.normals import estimate_normals
    from scanner_core.scanio import point_sensors

    if len(scan.cloud) < MIN_POSE_POINTS:
        raise ValueError(f"a pose needs at least {MIN_POSE_POINTS} points, the scan has "
                         f"{len(scan.cloud)}")
    edge_frames = getattr(scan, "edge_frame_ids", None)
    use_edges = edge_model is not None and len(scan.edges) > 0 and edge_frames is not None
    # Normals only where the fit looks (neighbours from the whole cloud): most of a pose's
    # time would otherwise go to normals it never uses.
    t0 = time.perf_counter()
    used = _subsample(len(scan.cloud), params.max_points, np.random.default_rng(params.seed))
    normals = estimate_normals(scan.cloud, sensors=point_sensors(scan), frame_ids=scan.frame_ids,
                               index=used)
    result = register(scan.cloud[used], normals, surface_model, nominal,
                      frame_ids=scan.frame_ids[used],
                      edges_t=scan.edges if use_edges else None,
                      edge_frame_ids=edge_frames if use_edges else None,
                      edge_model=edge_model if use_edges else None,
                      edge_steps_mm=_scan_steps(scan) if use_edges else None, params=params)
    result.flags += _coverage_flags(scan, result.matrix, surface_model)
    result.normals_ms = (time.perf_counter() - t0) * 1e3 - result.time_ms
    return result


def _scan_steps(scan) -> np.ndarray | None:
    """(M,) the height of each step point of the scan's edge cloud, 0 for a drop-out; None
    when the scan carries no kinds and sizes for its edge points."""
    from scanner_core.edges import EdgeKind

    kinds = getattr(scan, "edge_kind", None)
    sizes = getattr(scan, "edge_size_mm", None)
    if kinds is None or sizes is None or len(kinds) != len(scan.edges):
        return None
    return np.where(np.asarray(kinds) == EdgeKind.STEP,
                    np.nan_to_num(np.asarray(sizes, dtype=np.float64)), 0.0)


#: Profiles farther apart than this (mm) sample a part's features too coarsely for the
#: uncertainty to be trusted: a hole's rim crossed by two profiles pins little.
MAX_PROFILE_SPACING_MM = 3.0
#: A scan covering less of the part's length along the pass than this is partial.
MIN_COVERAGE = 0.9


def _coverage_flags(scan, pose, surface_model: SurfaceModel) -> list[str]:
    """Flags a pose cannot raise from its fit alone: profiles too far apart, and a pass that
    saw only part of the part (the trigger started late, or the pass ended early)."""
    flags = []
    spacing = scan.profile_spacing_mm
    if spacing > MAX_PROFILE_SPACING_MM:  # False for NaN: fewer than two profiles
        flags.append(f"sparse: {spacing:.1f} mm between profiles (at most "
                     f"{MAX_PROFILE_SPACING_MM:g})")
    normals_t = surface_model.normals @ pose[:3, :3].T
    facing = normals_t[:, 2] > 0.3  # the sensor looks up at the part along -z_T
    if facing.any():
        along = (surface_model.points[facing] @ pose[:3, :3].T + pose[:3, 3])[:, 1]
        seen = scan.cloud[:, 1]
        length = float(along.max() - along.min())
        overlap = min(along.max(), seen.max()) - max(along.min(), seen.min())
        coverage = max(0.0, float(overlap)) / length if length > 0 else 1.0
        if coverage < MIN_COVERAGE:
            flags.append(f"partial scan: {coverage:.0%} of the part's length along the pass")
    return flags


@dataclass
class _Terms:
    """One kind of correspondence: scan points (with normals for surfaces) and their model."""

    points: np.ndarray
    normals: np.ndarray | None
    frames: np.ndarray
    model: SurfaceModel | EdgeModel
    agreement: float = -1.0     # least cosine between `normals` and a match's normal
    steps_mm: np.ndarray | None = None  # edges: a step's height, 0 for a drop-out

    def subset(self, index) -> "_Terms":
        return _Terms(self.points[index], None if self.normals is None else self.normals[index],
                      self.frames[index], self.model, self.agreement,
                      None if self.steps_mm is None else self.steps_mm[index])


@dataclass
class _Fit:
    pose: np.ndarray
    rms: float
    inlier_fraction: float
    edge_fraction: float        # of the edge points, matched (1.0 without edges)
    iterations: int
    jacobian: np.ndarray        # (K, 6) of the inliers, about `centre`
    residuals: np.ndarray       # (K,)
    weights: np.ndarray         # (K,)
    frames: np.ndarray          # (K,) frame of each inlier
    centre: np.ndarray          # (3,)
    scale_mm: float             # radius that makes rotations comparable with translations


def _fine(surface: _Terms, edges: _Terms | None, start, params, *, iterations=None,
          gate_mm=None) -> _Fit:
    pose = start.copy()
    centre = surface.points.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((surface.points - centre) ** 2, axis=1)))) or 1.0
    gates = [params.gate_mm if gate_mm is None else gate_mm] * 2
    max_iter = params.max_iterations if iterations is None else iterations
    step_tol = np.array([params.tol_mm] * 3 + [np.radians(params.tol_deg)] * 3)
    # Far from the minimum, a quarter of the points steers as well as all of them.
    sparse = (surface.subset(slice(None, None, _WARM_STRIDE))
              if iterations is None and len(surface.points) >= _WARM_MIN_POINTS else None)
    it = 0
    for it in range(1, max_iter + 1):
        terms = surface if sparse is None else sparse
        rows, sigmas = _linearise(terms, edges, pose, centre, gates, params)
        jac, res, w = rows[:3]
        if len(res) < 6:
            break
        delta, observed = _solve(jac, res, w, scale, params.free_std_mm)
        pose = _apply(delta, centre) @ pose
        if gate_mm is None:
            gates = [max(params.min_gate_mm, min(g, 6.0 * sg)) for g, sg in zip(gates, sigmas)]
        if sparse is not None and (it >= _WARM_MAX_ITERATIONS
                                   or np.all(np.abs(observed) < _WARM_TOL_FACTOR * step_tol)):
            sparse = None
            continue
        if sparse is None and np.all(np.abs(observed) < step_tol):
            break
    if iterations is None:
        pose = _hold_free_motions(surface, edges, start, pose, centre, scale, gates, params)
    (jac, res, w, frames, matched), _ = _linearise(surface, edges, pose, centre, gates, params)
    inlier_fraction = matched / max(len(surface.points), 1)
    edge_fraction = ((len(res) - matched) / len(edges.points)) if edges is not None else 1.0
    rms = float(np.sqrt(np.sum(w * res**2) / np.sum(w))) if len(res) else np.inf
    return _Fit(pose, rms, inlier_fraction, edge_fraction, it, jac, res, w, frames, centre,
                scale)


def _hold_free_motions(surface, edges, start, pose, centre, scale, gates, params):
    """Take back what the fit moved along free motions, and settle the rest with them held.

    A free motion is one the scan does not pin down (`_observable`); a weak constraint (the
    facets of a turned cylinder) or the noise would otherwise leave it anywhere, and with it
    the {T} origin of a part turned about an axis that misses the origin.
    """
    (jac, res, w, frames, _), _ = _linearise(surface, edges, pose, centre, gates, params)
    if len(res) < 6:
        return pose
    _, vectors, strong = _directions(jac, w, frames, scale, params)
    free = vectors[:, ~strong]
    if free.shape[1] == 0:
        return pose
    s = np.array([1.0, 1.0, 1.0, scale, scale, scale])
    moved = pose @ np.linalg.inv(start)
    twist = np.concatenate([moved[:3, :3] @ centre + moved[:3, 3] - centre,
                            Rotation.from_matrix(moved[:3, :3]).as_rotvec()]) * s
    twist -= free @ (free.T @ twist)
    pose = _apply(twist / s, centre) @ start
    step_tol = np.array([params.tol_mm] * 3 + [np.radians(params.tol_deg)] * 3)
    for _ in range(params.max_iterations):
        (jac, res, w, _, _), _ = _linearise(surface, edges, pose, centre, gates, params)
        if len(res) < 6:
            break
        _, observed = _solve(jac, res, w, scale, params.free_std_mm)
        pose = _apply(observed, centre) @ pose
        if np.all(np.abs(observed) < step_tol):
            break
    return pose


def _linearise(surface, edges, pose, centre, gates, params):
    """Residuals, Jacobian rows, robust weights and frames of all correspondences at `pose`.

    Returns ``(jacobian, residuals, weights, frames, surface_inliers)`` and the robust scale
    of each kind (surface, edges).
    """
    parts, sigmas = [], []
    surface_rows = _surface_rows(surface, pose, centre, gates[0], params.surface_noise_mm)
    parts.append(surface_rows[:4])
    sigmas.append(surface_rows[4])
    matched = len(surface_rows[1])
    if edges is not None:
        edge_rows = _edge_rows(edges, pose, centre, gates[1], params.edge_noise_mm)
        parts.append(edge_rows[:4])
        sigmas.append(edge_rows[4])
    else:
        sigmas.append(np.inf)
    jac, res, w, frames = (np.concatenate(x) for x in zip(*parts))
    return (jac, res, w, frames, matched), sigmas


def _surface_rows(terms: _Terms, pose, centre, gate, noise_mm):
    """Point-to-plane rows: the residual of scan point s matched to model point q (normal n)
    is ``n . (s - X q)`` in {T}; a motion (t, w) about `centre` changes it by
    ``-[n, (s - centre) x n] . (t, w)``."""
    rotation, translation = pose[:3, :3], pose[:3, 3]
    spacing = _spacing(terms.model)
    idx, nearest = _match(terms, pose, gate + 2.0 * spacing)
    n_t = terms.model.normals[nearest] @ rotation.T
    if terms.normals is not None:
        # Scan normals point to the sensor, model normals out of the part: the same way up.
        scan_n = terms.normals[idx]
        agree = np.einsum("ij,ij->i", n_t, np.nan_to_num(scan_n, nan=0.0))
        ok = (agree >= terms.agreement) | ~np.isfinite(scan_n[:, 0])
        idx, nearest, n_t = idx[ok], nearest[ok], n_t[ok]
    q_t = terms.model.points[nearest] @ rotation.T + translation
    return _robust_rows(terms.points[idx], n_t, q_t, terms.frames[idx], centre, gate, noise_mm)


def _edge_rows(terms: _Terms, pose, centre, gate, noise_mm):
    """Edge rows: the distance in (x_T, y_T) from the edge point to the model's edge line,
    i.e. to the vertical plane through it (normal ``d x z_T`` for edge direction d)."""
    rotation, translation = pose[:3, :3], pose[:3, 3]
    idx, nearest = _match(terms, pose, gate + _spacing(terms.model) + _EDGE_SEARCH_MM)
    d_t = terms.model.directions[nearest] @ rotation.T
    m = np.stack([d_t[:, 1], -d_t[:, 0], np.zeros(len(d_t))], axis=1)
    length = np.linalg.norm(m, axis=1)
    ok = length > _MIN_EDGE_LEVEL  # an edge along z_T is no line in the (x_T, y_T) plane
    idx, nearest, m = idx[ok], nearest[ok], m[ok] / length[ok, None]
    q_t = terms.model.points[nearest] @ rotation.T + translation
    return _robust_rows(terms.points[idx], m, q_t, terms.frames[idx], centre, gate, noise_mm)


# A free motion moves the axes whose component in its unit direction exceeds this.
_TOUCHED = 0.2
# A fit whose residuals exceed this many times the expected scatter is flagged.
_RMS_FLAG = 5.0
# The fine fit's first iterations use every _WARM_STRIDE-th surface point (of at least
# _WARM_MIN_POINTS) until its steps fall below _WARM_TOL_FACTOR times the tolerance, for
# _WARM_MAX_ITERATIONS at most (matches to few points can cycle short of that).
_WARM_STRIDE = 4
_WARM_MIN_POINTS = 2000
_WARM_TOL_FACTOR = 100.0
_WARM_MAX_ITERATIONS = 6
# Information below this fraction of the strongest is no information (numerical zero).
_SINGULAR = 1e-10
# A free motion's turn part (scaled, of a unit motion) below this is round-off: it slides.
_FREE_TURN = 1e-8
# Model points that seed a coarse candidate's translation.
_SEED_POINTS = 5000
# Queries with more points than this use both cores.
_THREADED_QUERY = 50_000
# Floor of the robust scale, mm: no scan is better than this, and noise-free test data must
# not make the weights infinite.
_MIN_SIGMA_MM = 0.001
# An edge point at half a step's height lies this far from the step's edges in 3D (up to
# half the tallest step); the match searches that far, the residual is taken in the plane.
_EDGE_SEARCH_MM = 15.0
# |d x z_T| below this: the edge runs within 17 degrees of z_T.
_MIN_EDGE_LEVEL = 0.3


def _match(terms: _Terms, pose, bound):
    """Indices of the scan points with a model point within `bound` mm, and those points."""
    rotation, translation = pose[:3, :3], pose[:3, 3]
    local = (terms.points - translation) @ rotation  # the scan in {P}
    dist, nearest = _nearest(terms, local, rotation[2], bound)
    idx = np.nonzero(np.isfinite(dist))[0]
    return idx, nearest[idx]


def _nearest(terms: _Terms, local, up, bound):
    """Distance to and index of the nearest model point within `bound` mm (inf and the
    model's size beyond it) of each point of `local` ((..., N, 3), the scan in {P}).

    A step's edge point lies half the step's height from the edge it was found at, up or
    down the wall (paper section II), and as far from the wall's other edge: matched from
    where it lies, it finds either, or another edge near the wall's middle. It is matched
    from half its step above and below it along z_T (`up`, z_T in {P}, (..., 3)) as well,
    and keeps the nearest of the three matches: the edge it came from.
    """
    shape = local.shape[:-1]
    # Threads pay off only for large queries (each call starts its own).
    workers = -1 if int(np.prod(shape)) > _THREADED_QUERY else 1
    query = terms.model.tree.query
    dist, nearest = query(local.reshape(-1, 3), k=1, distance_upper_bound=bound,
                          workers=workers)
    dist, nearest = dist.reshape(shape), nearest.reshape(shape)
    if terms.steps_mm is None:
        return dist, nearest
    stepped = np.nonzero(terms.steps_mm > 0)[0]
    if not len(stepped):
        return dist, nearest
    half = 0.5 * terms.steps_mm[stepped, None]
    for sign in (1.0, -1.0):
        moved = local[..., stepped, :] + sign * half * up[..., None, :]
        d, n = query(moved.reshape(-1, 3), k=1, distance_upper_bound=bound, workers=workers)
        d, n = d.reshape(moved.shape[:-1]), n.reshape(moved.shape[:-1])
        nearer = d < dist[..., stepped]
        dist[..., stepped] = np.where(nearer, d, dist[..., stepped])
        nearest[..., stepped] = np.where(nearer, n, nearest[..., stepped])
    return dist, nearest


def _robust_rows(s_t, n_t, q_t, frames, centre, gate, noise_mm):
    """Rows with residual within `gate`, weighted by Tukey's biweight at their own robust
    scale and by the inverse variance of the expected scatter `noise_mm`."""
    res = np.einsum("ij,ij->i", n_t, s_t - q_t)
    inside = np.abs(res) <= gate
    s_t, n_t, res, frames = s_t[inside], n_t[inside], res[inside], frames[inside]
    if len(res) < 3:
        return np.zeros((0, 6)), np.zeros(0), np.zeros(0), np.zeros(0, np.int64), np.inf
    sigma = max(_MAD_TO_SIGMA * float(np.median(np.abs(res - np.median(res)))), _MIN_SIGMA_MM)
    u = res / (_TUKEY_C * sigma)
    w = np.where(np.abs(u) < 1.0, (1.0 - u**2) ** 2, 0.0) / noise_mm**2
    jac = np.hstack([n_t, np.cross(s_t - centre, n_t)])
    keep = w > 0
    return jac[keep], res[keep], w[keep], frames[keep], sigma


def _spacing(model) -> float:
    """Typical distance between a model's points, mm (for the match radius)."""
    return float(getattr(model, "spacing_mm", 0.5))


def _information(jac, w, scale):
    """J^T W J with rotations scaled to arc length at `scale` mm (comparable units)."""
    js = jac / np.array([1.0, 1.0, 1.0, scale, scale, scale])
    return js.T @ (js * w[:, None])


def _observable(values, free_std_mm):
    """Which eigen-directions of the information the scan pins down better than the limit."""
    return values > max(1.0 / free_std_mm**2, _SINGULAR * values[-1])


def _directions(jac, w, frames, scale, params):
    """Eigen-decomposition of the information and which directions are observable: pinned
    down better than ``free_std_mm`` at the expected scatter, by at least ``min_frames``
    profiles' worth of information (two points at a part's far end, in one profile, pin
    nothing one can trust: that profile's placement error moves them together)."""
    s = np.array([1.0, 1.0, 1.0, scale, scale, scale])
    values, vectors = np.linalg.eigh(_information(jac, w, scale))
    strong = _observable(values, params.free_std_mm)
    projected = ((jac / s) @ vectors) ** 2 * w[:, None]  # (K, 6) information per row
    _, inverse = np.unique(frames, return_inverse=True)
    per_frame = np.zeros((inverse.max() + 1, 6))
    np.add.at(per_frame, inverse, projected)
    total = per_frame.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        effective = total**2 / np.sum(per_frame**2, axis=0)  # participation ratio
    strong &= np.nan_to_num(effective) >= params.min_frames
    return values, vectors, strong


def _solve(jac, res, w, scale, free_std_mm):
    """Gauss-Newton step, and its size along the observable motions only.

    Every direction with information moves (early in a fit a motion may look free only for
    want of matches); the step's size for convergence leaves out the free motions, which a
    weak constraint (the facets of a turned cylinder) would otherwise creep along for ever.
    """
    s = np.array([1.0, 1.0, 1.0, scale, scale, scale])
    info = _information(jac, w, scale)
    rhs = (jac / s).T @ (w * res)
    values, vectors = np.linalg.eigh(info)
    moving = values > _SINGULAR * values[-1]
    step_scaled = vectors[:, moving] @ ((vectors[:, moving].T @ rhs) / values[moving])
    strong = _observable(values, free_std_mm)
    observed = vectors[:, strong] @ (vectors[:, strong].T @ step_scaled)
    return step_scaled / s, observed / s


def _apply(delta, centre) -> np.ndarray:
    """4x4 in {T}: rotate by ``delta[3:]`` about `centre`, then translate by ``delta[:3]``."""
    m = np.eye(4)
    rotation = Rotation.from_rotvec(delta[3:]).as_matrix()
    m[:3, :3] = rotation
    m[:3, 3] = centre + delta[:3] - rotation @ centre
    return m


def _agreement(surface: _Terms, edges: _Terms | None, pose, tol_surface: float,
               tol_edge: float) -> float:
    """How well `pose` explains the scan at fixed tolerances: the fraction of the surface
    points within `tol_surface` mm of the model's plane (normals agreeing) plus the fraction
    of the edge points within `tol_edge` mm of a model edge (in the (x_T, y_T) plane).

    Unlike a fit's own inlier fractions, which count within a multiple of the fit's own
    robust scale, this does not reward a loose, unsettled fit: it ranks the
    candidates of the coarse search, which are refined only briefly.
    """
    return float(_agreements(surface, edges, pose[None], tol_surface, tol_edge)[0])


def _agreements(surface: _Terms, edges: _Terms | None, poses, tol_surface: float,
                tol_edge: float, edge_search_mm: float = _EDGE_SEARCH_MM) -> np.ndarray:
    """(P,) :func:`_agreement` of each of the (P, 4, 4) `poses`, in one query of each model's
    tree (a sweep of 355 turns took 56 ms, as many single calls 123 ms). An edge point
    finds its model edge within `edge_search_mm` beyond `tol_edge` (a step's point of
    unknown height lies up to half the tallest step from its edge; a query that far costs
    six times one within a millimetre)."""
    scores = _matched_fraction(surface, poses, _surface_bound(surface, tol_surface),
                               tol_surface, planes=True)
    if edges is None or not len(edges.points):
        return scores + 1.0
    return scores + _matched_fraction(edges, poses, _edge_bound(edges, tol_edge, edge_search_mm),
                                      tol_edge, planes=False)


def _surface_bound(surface: _Terms, tol: float) -> float:
    """How far (mm) a surface point's model sample may lie for a match within `tol`."""
    return tol + 2.0 * _spacing(surface.model)


def _edge_bound(edges: _Terms, tol: float, search_mm: float = _EDGE_SEARCH_MM) -> float:
    return tol + _spacing(edges.model) + search_mm


def _matched_fraction(terms: _Terms, poses, bound, tol, *, planes: bool) -> np.ndarray:
    """(P,) fraction of `terms`' points :func:`_matched` at each pose."""
    matched = _matched(terms, poses, bound, tol, planes=planes)
    return matched.sum(axis=1) / max(len(terms.points), 1)


def _matched(terms: _Terms, poses, bound, tol, *, planes: bool) -> np.ndarray:
    """(P, N) bool: whether each of `terms`' points lies within `tol` of its model at each
    pose: of its plane (normals agreeing) for surfaces, of its edge across it in (x_T, y_T)
    for edges.
    Residuals are taken in {P}, where the model lies (a distance does not change with the
    frame), so each pose's rotation is applied once per point, not per match."""
    count, n = len(poses), len(terms.points)
    rotation, translation = poses[:, :3, :3], poses[:, :3, 3]
    local = (terms.points[None] - translation[:, None]) @ rotation  # (P, N, 3) in {P}
    dist, nearest = _nearest(terms, local, rotation[:, 2], bound)
    hit = np.nonzero(np.isfinite(dist.reshape(-1)))[0]
    which, nearest = hit // n, nearest.reshape(-1)[hit]
    offset = local.reshape(-1, 3)[hit] - terms.model.points[nearest]
    if planes:
        normal = terms.model.normals[nearest]
        res = np.abs(np.sum(normal * offset, axis=1))
        if terms.normals is not None:
            scan_n = (np.nan_to_num(terms.normals)[None] @ rotation).reshape(-1, 3)[hit]
            seen = np.isfinite(terms.normals[hit % n, 0])
            res[(np.sum(normal * scan_n, axis=1) < terms.agreement) & seen] = np.inf
        ok = res <= tol
    else:
        # across the edge in (x_T, y_T): the z_T component of (direction x offset) in {T},
        # over the length of the direction's (x_T, y_T) part
        up = rotation[which, 2, :]  # z_T in {P}
        direction = terms.model.directions[nearest]
        level = np.sqrt(np.maximum(1.0 - np.sum(up * direction, axis=1) ** 2, 0.0))
        across = np.abs(np.sum(up * np.cross(direction, offset), axis=1))
        ok = (level > _MIN_EDGE_LEVEL) & (across <= tol * level)
    matched = np.zeros(count * n, bool)
    matched[hit[ok]] = True
    return matched.reshape(count, n)


# The coarse candidates are ranked at these tolerances (mm, surface and edges): wide enough
# for a fit refined only briefly, narrow enough that a wrong turn (a feature a lobe off)
# does not pass.
_COARSE_TOL_MM = (0.1, 0.25)
# Distinct coarse candidates kept from the grid, each swept about its weakest rotation.
_COARSE_KEEP = 3
# Seeds from the sweeps refined and compared.
_SWEEP_SEEDS = 4
# Two candidates closer than this (degrees, and mm) are the same.
_SAME_DEG, _SAME_MM = 1.0, 0.5


def _coarse(surface: _Terms, edges: _Terms | None, nominal, params, rng) -> list[np.ndarray]:
    """Starts for the fine stage, best first, from a grid of orientations around the nominal
    grasp and, around the best of them, a finer sweep about the rotation their fit pins down
    least (a flat part's turn in its plane: the edges alone hold it, and the basin of a part
    with a many-lobed outline is a degree or two wide)."""
    few = surface.subset(_subsample(len(surface.points), params.coarse_points, rng))
    few_edges = None if edges is None else edges.subset(
        _subsample(len(edges.points), params.coarse_points, rng))
    angles = np.arange(-params.coarse_extent_deg, params.coarse_extent_deg + 1e-9,
                       params.coarse_step_deg)
    grid = np.array(np.meshgrid(angles, angles, angles, indexing="ij")).reshape(3, -1).T
    grid = grid[np.argsort(np.linalg.norm(grid, axis=1))]

    def refine(start):
        fit = _fine(few, few_edges, start, params, iterations=params.coarse_iterations,
                    gate_mm=params.gate_mm * 2)
        return fit.pose, _agreement(few, few_edges, fit.pose, *_COARSE_TOL_MM)

    candidates = []
    for rotvec in grid:
        turn = np.eye(4)
        turn[:3, :3] = Rotation.from_rotvec(np.radians(rotvec)).as_matrix()
        candidates.append(refine(_seed_translation(few.points, surface.model, turn @ nominal)))
    kept = _distinct(candidates, _COARSE_KEEP)
    # The sweep: about the weakest rotation of the best candidate's fit, through the scan's
    # centre, across the grid's step, without refinement (cheap); the best distinct seeds
    # are then refined like the grid's candidates.
    step = max(params.coarse_sweep_deg, 1e-3)
    half = params.coarse_step_deg / 2.0 + step
    offsets = np.arange(-half, half + 1e-9, step)
    centre = few.points.mean(axis=0)
    seeds = []
    for pose, _ in kept:
        axis = _weakest_rotation(few, few_edges, pose, centre, params)
        moved = _turned(pose, axis, centre, offsets)
        seeds.extend(zip(moved, _agreements(few, few_edges, moved, *_COARSE_TOL_MM)))
    refined = [refine(pose) for pose, _ in _distinct(seeds, _SWEEP_SEEDS, same_deg=step * 1.5)]
    return [pose for pose, _ in _distinct(refined + kept, _SWEEP_SEEDS)]


# Only a fit whose weakest rotation is held this much less than its strongest (their
# information, translations free) is checked for a better turn: a flat part turning in its
# plane, held by its outline alone (a 38-lobed disc: 0.006-0.008; a block, the reference
# parts' fits: 0.012-0.036). The check is one batch of about 30 agreements, some 20 ms.
_TURN_CHECK_WEAKNESS = 0.01
# A turn whose agreement beats the fit's by this much (fractions of the surface points plus
# of the edge points) sends a fit that looked good to the coarse search.
_BETTER_TURN = 0.02


def _better_turn(surface: _Terms, edges: _Terms | None, pose, params) -> bool:
    """Whether a turn of `pose` about its weakest rotation, within one step of the coarse
    grid, fits the scan better than `pose` itself: a fit that matches most of its points
    can still sit a lobe or a tooth off (every edge but a keyway's matches), the many-lobed
    outline then pins the wrong turn as tightly as the right one."""
    rng = np.random.default_rng(params.seed + 1)
    few = surface.subset(_subsample(len(surface.points), params.coarse_points, rng))
    few_edges = None if edges is None else edges.subset(
        _subsample(len(edges.points), params.coarse_points, rng))
    centre = few.points.mean(axis=0)
    axis, weakness = _weakest_rotation(few, few_edges, pose, centre, params, weakness=True)
    if weakness > _TURN_CHECK_WEAKNESS:
        return False  # every rotation is held by surfaces too: no turn hides a better fit
    own = _agreement(few, few_edges, pose, *_COARSE_TOL_MM)
    step = max(params.coarse_sweep_deg, 1e-3)
    angles = np.arange(step, params.coarse_step_deg + 1e-9, step)
    turned = _turned(pose, axis, centre, np.concatenate([angles, -angles]))
    return bool(np.any(_agreements(few, few_edges, turned, *_COARSE_TOL_MM) > own + _BETTER_TURN))


# The turns about the weakest rotation a converged fit is probed with, degrees: a part held by
# little but a few small features (ADIS16480, whose large faces lie parallel to the sheet) has
# minima a degree apart whose own curvature claims a few hundredths of a degree.
_PROBE_DEG = (-2.0, -1.0, 1.0, 2.0)
# And all the way round, for a part with a near symmetry about that rotation: cycloidal's
# lobes fit 90, 180 and 270 degrees off with 91 % of the points matched against 96 % at the
# truth, unflagged, for a start that far off (a round part picked from a bin); a 38-lobed
# disc's any whole number of lobes off. The sweep (:func:`_round_seeds`) turns the fit in
# steps of ``coarse_sweep_deg`` from beyond the near probes, scores each turn unrefined at
# loose tolerances (mm, surface and edges: lobes 0.4 mm high blur, a keyway does not, and a
# turn about a slightly wrong line still scores), with this many points of each kind, and
# keeps the best turn of each of its peaks (maxima this far either side, degrees) for the
# quick refinement: the 6 best peaks, at 60-80 ms a sweep.
_ROUND_FROM_DEG = 3.0
_ROUND_TOL_MM = (0.5, 1.0)
_ROUND_POINTS = 150
_ROUND_APART_DEG = 5.0
_ROUND_SEEDS = 6
_ROUND_FINE_DEG = 0.2
# A rotation the surfaces hold less than this (their weakest rotation's information over their
# strongest's) rests mostly on the edges, where an outline that repeats (lobes, teeth) can fit
# a turn off. Measured at the bench's fits: a disc seen on its flat face 1e-17, featuretype
# up to 6e-6, cycloidal 4.5e-4 to 4.4e-3 (its fits' weakness with the edges, 0.016-0.032,
# is above ``probe_weakness``), ADIS16480 1.6e-3 to 0.026, idler_riser 0.011-0.023.
_EDGES_ALONE = 7e-3
# Not about a rotation the scan leaves free (a cylinder's: weakness 2e-6, against 0.004 to
# 0.023 for the reference parts' weakest): every turn about it fits, and it is reported free.
_HELD_WEAKNESS = 1e-4
# A probe whose quick refinement scores within this of the fit's (coarse tolerances) is
# refined fully; one whose full fit then scores within _RIVAL_SCORE of the best is a rival.
_PROBE_MARGIN = 0.01
# The quick refinement of a probe: points and iterations (a tenth of the fit's cost).
_PROBE_POINTS, _PROBE_ITERATIONS = 400, 4
_RIVAL_SCORE = 0.002
# ... or within this many standard errors of the paired difference of the two agreements
# (McNemar 1947, per profile: of the points one pose matches and the other does not, as many
# each way when the scan cannot tell them apart). ADIS16480 seen on its 44 x 14 mm end in 12
# profiles has two minima 0.15 degree apart about z_T that differ by 8 of 2 600 surface
# points: the one 0.003 better was reported with a sigma of 20 mdeg.
_RIVAL_Z = 2.0
# A rival this close to the fit (degrees, mm) is the same minimum.
_RIVAL_SAME_DEG, _RIVAL_SAME_MM = 0.02, 0.02


def _probe_turns(surface: _Terms, edges: _Terms | None, fit: _Fit, params):
    """The converged fit checked against refits from turns of it about its weakest rotation.

    Returns the fit (or a probe's, when it scores clearly better: ``_BETTER_TURN``) and the
    others that score as well (within :func:`_rival_margin`, or better) but lie elsewhere:
    distinct minima the scan cannot tell apart, which the uncertainty must then cover.
    Probed: a fit whose weakest rotation is held less than ``probe_weakness``, or by its
    edges alone (its surfaces hold it less than ``_EDGES_ALONE``: a flat part turning in its
    plane, whose outline may repeat). A quick refinement (the coarse stage's) screens the turns: the
    probe cost 180-330 ms on featuretype's and cycloidal's scans (bench pose).
    """
    rng = np.random.default_rng(params.seed + 2)
    few = surface.subset(_subsample(len(surface.points), _PROBE_POINTS, rng))
    few_edges = None if edges is None else edges.subset(
        _subsample(len(edges.points), _PROBE_POINTS, rng))
    centre = few.points.mean(axis=0)
    axis, weakness = _weakest_rotation(few, few_edges, fit.pose, centre, params, weakness=True)
    if weakness > params.probe_weakness and (
            few_edges is None
            or _weakest_rotation(few, None, fit.pose, centre, params, weakness=True)[1]
            > _EDGES_ALONE):
        return fit, []
    own = _agreement(few, few_edges, fit.pose, *_COARSE_TOL_MM)
    fits = [fit]
    starts = list(_turned(fit.pose, axis, centre, _PROBE_DEG))
    if weakness > _HELD_WEAKNESS:
        starts += _round_seeds(few, few_edges, fit.pose, axis, params)
    for start in starts:
        quick = _fine(few, few_edges, start, params, iterations=_PROBE_ITERATIONS,
                      gate_mm=params.gate_mm * 2)
        if (_agreement(few, few_edges, quick.pose, *_COARSE_TOL_MM) >= own - _PROBE_MARGIN
                and all(not _same(quick.pose, f.pose, _RIVAL_SAME_DEG * 10, _RIVAL_SAME_MM * 10)
                        for f in fits)):
            fits.append(_fine(surface, edges, quick.pose, params))
    if len(fits) == 1:
        return fit, []
    scores = [_final_score(surface, edges, f, params) for f in fits]
    # Move to a probe's minimum only when it is clearly better (as the coarse stage would);
    # one barely better is a rival, not an answer.
    best = int(np.argmax(scores))
    keep = best if scores[best] > scores[0] + _BETTER_TURN else 0
    rivals = []
    for f, sc in zip(fits, scores):
        if (f is not fits[keep]
                and scores[keep] - sc <= _rival_margin(surface, edges, fits[keep].pose, f.pose,
                                                        params)
                and all(not _same(f.pose, other, _RIVAL_SAME_DEG, _RIVAL_SAME_MM)
                        for other in [fits[keep].pose] + rivals)):
            rivals.append(f.pose)
    return fits[keep], rivals


def _rival_margin(surface: _Terms, edges: _Terms | None, pose, other, params) -> float:
    """How much lower than `pose`'s final score `other`'s may be and still fit as well:
    ``_RIVAL_SCORE``, or ``_RIVAL_Z`` standard errors of the difference, counted on the
    points that only one of the two matches (each kind of point over its own number, as
    in :func:`_agreement`), but never more than ``_PROBE_MARGIN``. The points of one
    profile, surface and edge alike, share its placement, so they count as one cluster (as
    in :func:`_uncertainty`): its net share squared, never less than its discordant points'
    (McNemar's variance for independent points). The cap keeps a minimum that misses a
    whole profile or two from passing: with the differences in a few clusters, the
    difference is never more than a few standard errors, however large."""
    tol_surface, tol_edge = _FINAL_TOL * params.surface_noise_mm, _FINAL_TOL * params.edge_noise_mm
    kinds = [(surface, _surface_bound(surface, tol_surface), tol_surface, True)]
    if edges is not None and len(edges.points):
        kinds.append((edges, _edge_bound(edges, tol_edge), tol_edge, False))
    frames = np.concatenate([terms.frames for terms, *_ in kinds])
    _, cluster = np.unique(frames, return_inverse=True)
    net = np.zeros(cluster.max() + 1 if len(cluster) else 0)
    independent = np.zeros_like(net)
    start = 0
    for terms, bound, tol, planes in kinds:
        n = len(terms.points)
        first, second = _matched(terms, np.stack([pose, other]), bound, tol, planes=planes)
        mine = cluster[start:start + n]
        start += n
        net += np.bincount(mine, first.astype(float) - second, minlength=len(net)) / max(n, 1)
        independent += np.bincount(mine, (first != second).astype(float),
                                   minlength=len(net)) / max(n, 1) ** 2
    standard_error = float(np.sqrt(np.sum(np.maximum(net**2, independent))))
    return min(max(_RIVAL_SCORE, _RIVAL_Z * standard_error), _PROBE_MARGIN)


def _round_seeds(few: _Terms, few_edges: _Terms | None, pose, axis, params) -> list:
    """Starts all the way round the weakest rotation: `pose` turned about `axis` through the
    model's centre (on the axis of a part near-symmetric about it; the scan's own centre is
    not, when the scan sees one side) in steps of ``coarse_sweep_deg``, scored without
    refinement in one batch (:func:`_agreements`); the best turns of the ``_ROUND_SEEDS``
    best peaks of that score (maxima ``_ROUND_APART_DEG`` either side), as (4, 4) poses in
    {T}."""
    step = max(params.coarse_sweep_deg, 0.1)
    pivot = pose[:3, :3] @ few.model.points.mean(axis=0) + pose[:3, 3]
    few = few.subset(_evenly(len(few.points), _ROUND_POINTS))
    if few_edges is not None:
        few_edges = few_edges.subset(_evenly(len(few_edges.points), _ROUND_POINTS))
    moved = _turned(pose, axis, pivot, np.arange(_ROUND_FROM_DEG, 360.0 - _ROUND_FROM_DEG + 1e-9,
                                                 step))
    # an edge point matched near its edge (drop-outs, steps of known height) is all a rough
    # ranking needs
    scores = _agreements(few, few_edges, moved, *_ROUND_TOL_MM, edge_search_mm=_ROUND_TOL_MM[1])
    # the best turn of each peak of the score (a broad lobe's shoulders outscore a narrower
    # lobe's top): maxima within _ROUND_APART_DEG either side, best first
    reach = max(1, int(round(_ROUND_APART_DEG / step)))
    peaks = np.nonzero(scores >= maximum_filter1d(scores, 2 * reach + 1, mode="nearest"))[0]
    chosen = []
    for i in peaks[np.argsort(-scores[peaks], kind="stable")]:
        if all(abs(i - j) > reach for j in chosen):
            chosen.append(i)
            if len(chosen) == _ROUND_SEEDS:
                break
    # Each peak placed within a fraction of a degree, at the tight tolerances: a minimum
    # about a weakly held rotation can be narrower than the sweep's step (cycloidal's true
    # turn: a start 2 degrees off settles in a minimum 1.6 degrees off it).
    fine = np.arange(-step, step + 1e-9, _ROUND_FINE_DEG)
    local = np.concatenate([_turned(moved[i], axis, pivot, fine) for i in chosen]) if chosen \
        else np.zeros((0, 4, 4))
    tight = _agreements(few, few_edges, local, *_COARSE_TOL_MM).reshape(len(chosen), len(fine))
    return [local[k * len(fine) + int(np.argmax(row))] for k, row in enumerate(tight)]


def _turned(pose, axis, pivot, angles_deg) -> np.ndarray:
    """(K, 4, 4): `pose` turned by each of the (K,) `angles_deg` about the line through
    `pivot` (mm, {T}) along the unit `axis`."""
    turns = np.tile(np.eye(4), (len(angles_deg), 1, 1))
    turns[:, :3, :3] = Rotation.from_rotvec(
        np.radians(np.asarray(angles_deg, dtype=np.float64))[:, None] * axis).as_matrix()
    turns[:, :3, 3] = pivot - turns[:, :3, :3] @ pivot
    return turns @ pose


def _rival_motion(pose, rival) -> np.ndarray:
    """(6,): the rival's difference from `pose` as translation of the {T} origin (mm) and
    rotation vector (rad), the covariance's parameters."""
    d = rival @ np.linalg.inv(pose)
    return np.concatenate([d[:3, 3], Rotation.from_matrix(d[:3, :3]).as_rotvec()])


def _rival_words(pose, rival) -> str:
    m = _rival_motion(pose, rival)
    return (f"a pose {np.degrees(np.linalg.norm(m[3:])) * 1e3:.0f} mdeg and "
            f"{np.linalg.norm(m[:3]) * 1e3:.0f} um away")


def _distinct(candidates, count, *, same_deg=_SAME_DEG, same_mm=_SAME_MM):
    """Up to `count` of `(pose, score)` pairs, best first, no two closer than `same_deg`
    and `same_mm` (one basin's candidates count once)."""
    chosen = []
    for pose, score in sorted(candidates, key=lambda c: -c[1]):
        if all(not _same(pose, other, same_deg, same_mm) for other, _ in chosen):
            chosen.append((pose, score))
            if len(chosen) == count:
                break
    return chosen


def _same(a, b, same_deg=_SAME_DEG, same_mm=_SAME_MM) -> bool:
    return _turn_deg(a, b) < same_deg and np.linalg.norm(a[:3, 3] - b[:3, 3]) < same_mm


def _weakest_rotation(surface, edges, pose, centre, params, *, weakness: bool = False):
    """Unit axis in {T} of the rotation the fit at `pose` pins down least (translations
    free to follow: the Schur complement of the information); z_T when it cannot tell.
    With `weakness`, also the ratio of its information to the strongest rotation's."""
    (jac, _, w, _, _), _ = _linearise(surface, edges, pose, centre,
                                      [params.gate_mm * 2] * 2, params)
    if len(w) < 6:
        axis, ratio = np.array([0.0, 0.0, 1.0]), 0.0
    else:
        info = _information(jac, w, 1.0)
        tt, tr, rr = info[:3, :3], info[:3, 3:], info[3:, 3:]
        values, vectors = np.linalg.eigh(rr - tr.T @ np.linalg.pinv(tt) @ tr)
        axis = vectors[:, 0] * np.sign(vectors[np.argmax(np.abs(vectors[:, 0])), 0])
        ratio = float(values[0] / values[-1]) if values[-1] > 0 else 0.0
    return (axis, ratio) if weakness else axis


def _seed_translation(pts, model, pose) -> np.ndarray:
    """Shift `pose` so that the model's sensor-facing side meets the scan: centres in x, y,
    the nearest surfaces to the sensor (largest z_T) in z."""
    few = slice(None, None, max(1, len(model.points) // _SEED_POINTS))
    model_t = model.points[few] @ pose[:3, :3].T + pose[:3, 3]
    facing = (model.normals[few] @ pose[:3, :3].T)[:, 2] > 0.3
    if facing.sum() < 10:
        facing = np.ones(len(model_t), bool)
    shift = np.zeros(3)
    shift[:2] = np.median(pts[:, :2], axis=0) - np.median(model_t[facing, :2], axis=0)
    shift[2] = np.percentile(pts[:, 2], 95) - np.percentile(model_t[facing, 2], 95)
    moved = pose.copy()
    moved[:3, 3] += shift
    return moved


def _uncertainty(fit: _Fit, params, rivals=()) -> tuple[np.ndarray, np.ndarray, list]:
    """Covariance (cluster-robust over frames), per-axis std, and the free axes, about the
    {T} origin. Each rival minimum (``_probe_turns``) adds its difference's outer product: the
    scan cannot tell the fit from it, so the spread between them is uncertainty too."""
    nan6 = np.full(6, np.nan)
    if len(fit.residuals) < 6:
        return np.full((6, 6), np.nan), nan6, [{"kind": "all", "axis": None,
                                                 "label": "too few matched points"}]
    s = np.array([1.0, 1.0, 1.0, fit.scale_mm, fit.scale_mm, fit.scale_mm])
    js = fit.jacobian / s
    values, vectors, strong = _directions(fit.jacobian, fit.weights, fit.frames, fit.scale_mm,
                                          params)
    info_inv = vectors[:, strong] @ np.diag(1.0 / values[strong]) @ vectors[:, strong].T
    # Cluster-robust "meat": the weighted scores summed within each frame.
    scores = js * (fit.weights * fit.residuals)[:, None]
    _, inverse = np.unique(fit.frames, return_inverse=True)
    per_cluster = np.zeros((inverse.max() + 1, 6))
    np.add.at(per_cluster, inverse, scores)
    clusters = len(per_cluster)
    meat = per_cluster.T @ per_cluster * (clusters / max(clusters - 6, 1))
    cov_scaled = info_inv @ meat @ info_inv * params.sigma_inflation**2
    cov_centre = cov_scaled / np.outer(s, s)
    # About the {T} origin: t_o = t_c + c x w.
    c = fit.centre
    cross = np.array([[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]], [-c[1], c[0], 0.0]])
    to_origin = np.eye(6)
    to_origin[:3, 3:] = cross
    covariance = to_origin @ cov_centre @ to_origin.T
    for rival in rivals:
        m = _rival_motion(fit.pose, rival)
        covariance = covariance + np.outer(m, m)
    free_scaled = vectors[:, ~strong]
    free_axes = _free_motions(free_scaled, s, c)
    std = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    std[3:] = np.degrees(std[3:])
    if free_axes:
        # Along a free motion the scan says nothing: the axes it moves are not reported. A
        # free turn about an axis that misses the {T} origin carries the origin round with it:
        # those translation axes are not reported either.
        touched = np.zeros(6, bool)
        for axis in free_axes:
            direction = np.asarray(axis["axis"])
            if axis["kind"] == "translation":
                touched[:3] |= np.abs(direction) > _TOUCHED
                continue
            touched[3:] |= np.abs(direction) > _TOUCHED
            through = np.asarray(axis["through_mm"])
            swing = np.zeros(3)
            for angle in (np.pi / 2, np.pi, -np.pi / 2):
                turn = Rotation.from_rotvec(angle * direction).as_matrix()
                swing = np.maximum(swing, np.abs(turn @ -through + through))
            touched[:3] |= swing > 3.0 * np.nan_to_num(std[:3], nan=np.inf)
        std[touched] = np.nan
        covariance[touched, :] = np.nan
        covariance[:, touched] = np.nan
    return covariance, std, free_axes


def _free_motions(free_scaled, s, centre) -> list[dict]:
    """The free motions (orthonormal columns of `free_scaled`, scaled parameters) in words,
    turns first, then slides along the {T} axes where they can be: a free subspace that
    holds a turn and a slide can come out of the eigen-decomposition as two mixed motions
    (ADIS16480 with y_T and its turn free read "about z_T, about z_T")."""
    k = free_scaled.shape[1]
    if k > 1:
        _, sv, vt = np.linalg.svd(free_scaled[3:])  # singular values in descending order
        rank = int(np.sum(sv > _FREE_TURN))  # unit columns: an absolute floor
        basis = free_scaled @ vt.T  # the first `rank` turn; the rest only slide
        basis[3:, rank:] = 0.0
        if k - rank > 1:
            basis[:3, rank:] = _axis_aligned(basis[:3, rank:])
        free_scaled = basis
    return [_describe(v / np.linalg.norm(v), s, centre) for v in free_scaled.T]


def _axis_aligned(slides) -> np.ndarray:
    """An orthonormal basis of the span of `slides` ((3, m), orthonormal columns) whose
    vectors lie as close to the {T} axes as the span allows, nearest first."""
    projector = slides @ slides.T
    out = []
    for _ in range(slides.shape[1]):
        candidates = projector - sum((np.outer(b, b) for b in out), np.zeros((3, 3)))
        axis = int(np.argmax(np.linalg.norm(candidates, axis=0)))
        vector = candidates[:, axis]
        out.append(vector / np.linalg.norm(vector))
    return np.column_stack(out)


def _describe(vector_scaled, s, centre) -> dict:
    """A free motion (unit vector in scaled parameters) in words."""
    motion = vector_scaled / s
    t, w = motion[:3], motion[3:]
    if np.linalg.norm(w) * s[3] > np.linalg.norm(t):
        axis = w / np.linalg.norm(w)
        kind = "rotation"
        # The rotation's axis passes through the point where the motion leaves no translation.
        through = centre + np.cross(axis, t) / np.linalg.norm(w)
    else:
        axis = t / np.linalg.norm(t)
        kind = "translation"
        through = None
    axis = axis * np.sign(axis[np.argmax(np.abs(axis))])
    main = int(np.argmax(np.abs(axis)))
    label = (f"{'about' if kind == 'rotation' else 'along'} {_AXIS_LABELS[main]}"
             if abs(axis[main]) > 0.9 else f"{kind} {np.round(axis, 3).tolist()}")
    entry = {"kind": kind, "axis": np.round(axis, 6).tolist(), "label": label}
    if through is not None:
        entry["through_mm"] = np.round(through, 3).tolist()
    return entry


# --------------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------------

def _check_inputs(points_t, normals_t, frame_ids, minimum: int = 6):
    points = np.asarray(points_t, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points_t must be (N, 3), got {points.shape}")
    normals = (np.full(points.shape, np.nan) if normals_t is None
               else np.asarray(normals_t, dtype=np.float64))
    if normals.shape != points.shape:
        raise ValueError(f"normals_t must be {points.shape}, got {normals.shape}")
    frames = (np.arange(len(points)) if frame_ids is None
              else np.asarray(frame_ids, dtype=np.int64))
    if frames.shape != (len(points),):
        raise ValueError(f"frame_ids must be ({len(points)},), got {frames.shape}")
    keep = np.isfinite(points).all(axis=1)
    if keep.sum() < minimum:
        raise ValueError(f"a pose needs at least {minimum} finite points, got {int(keep.sum())}")
    return points[keep], normals[keep], frames[keep]


def _edge_steps(edges_t, edge_steps_mm) -> np.ndarray | None:
    """(K,) step heights of the finite edge points (as `_check_inputs` keeps them), mm, 0 for
    a drop-out; None without `edge_steps_mm`."""
    if edge_steps_mm is None:
        return None
    points = np.asarray(edges_t, dtype=np.float64)
    steps = np.asarray(edge_steps_mm, dtype=np.float64).reshape(-1)
    if steps.shape != (len(points),):
        raise ValueError(f"edge_steps_mm must be ({len(points)},), got {steps.shape}")
    if np.any(steps < 0) or np.any(np.isinf(steps)):
        raise ValueError("edge_steps_mm must be finite and >= 0 (a step's height, 0 or NaN "
                         "for a drop-out)")
    return np.nan_to_num(steps[np.isfinite(points).all(axis=1)], nan=0.0)


def _evenly(n: int, limit: int) -> np.ndarray:
    """At most `limit` indices spread evenly over ``range(n)``."""
    return np.unique(np.linspace(0, n - 1, min(n, limit)).astype(np.int64)) if n else np.arange(0)


def _subsample(n: int, limit: int, rng) -> np.ndarray:
    if n <= limit:
        return np.arange(n)
    return np.sort(rng.choice(n, size=limit, replace=False))
