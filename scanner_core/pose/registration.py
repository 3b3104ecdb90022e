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
  training per part. Every converged fit is also refitted from turns near it about its
  weakest rotation, and one whose weakest turn is held loosely from the best turns of a
  sweep all the way round it (`_probe_turns`): a fit from a start far off can stop a degree
  or two short of the truth, and a round part picked from a bin can sit any turn off its
  nominal.
- **uncertainty**: the covariance of the six motion parameters is the cluster-robust
  sandwich ``H^-1 (sum_f g_f g_f^T) H^-1`` over the frames f (Liang and Zeger 1986): the
  points of one profile share that frame's placement error (the marker's triangulation), so
  they are not independent, and the sandwich takes that from the residuals themselves. The
  edge points along one edge of the model share an offset from it (a rounded edge, the stripe
  fading as the surface turns away): one variance for those offsets, pooled over the scan's
  edges (a random-effects model), each edge's residuals corrected for the part of its offset
  the fit took up, is added (``scanner_core.pose.confidence._shared_offsets``). To it are
  added what every profile shares and the fit cannot see in the residuals: the calibration's
  light plane (its uncertainty carried through the fit's response), its marker offset, and
  the robot's orientation report. ``PoseResult.std_terms`` gives each term's share per axis.

The model is the CAD surface sampled densely with face normals (`SurfaceModel.from_mesh`), or
any points with normals, such as the simulator's predicted cloud of the same pass
(`SurfaceModel.from_points`). Units: mm, radians inside, degrees in the report.

Each stage has a module of its own: the models in ``scanner_core.pose.models``, the fine stage
in ``scanner_core.pose.fine``, the coarse search, the agreement score and the probes in
``scanner_core.pose.search``, the uncertainty and the flags in ``scanner_core.pose.confidence``,
the inputs' checks in ``scanner_core.pose.inputs``.
This module holds the entry points (`register`, `scan_pose`), their settings and their result.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from scanner_core.pose.confidence import (EDGES_SEARCH_SIGNIFICANCE, MIN_COVERAGE,
                                          _coverage_flags, _flags, _rival_words, _uncertainty,
                                          edges_refute, judge, term_stds)
from scanner_core.pose.fine import _fine, _settling, _subsample, _Terms
from scanner_core.pose.inputs import (MAX_PROFILE_SPACING_MM, ScanPoseInputs,
                                      add_placement_error, check_inputs, edge_steps)
from scanner_core.pose.models import (BEVEL_MM, TOWARD_MIN, EdgeModel, SurfaceModel,
                                      merge_bevels, outline_adjacency)
from scanner_core.pose.search import (_better_turn, _coarse, _final_score, _probe_turns,
                                      _turn_deg)
from scanner_core.pose.symmetry import equivalent_to, nearest_equivalent

__all__ = ["PoseParams", "SurfaceModel", "EdgeModel", "PoseResult", "register", "scan_pose",
           "inputs_pose", "ScanPoseInputs",
           "AXIS_NAMES", "MIN_POSE_POINTS", "BEVEL_MM", "TOWARD_MIN", "merge_bevels",
           "outline_adjacency", "MAX_PROFILE_SPACING_MM", "MIN_COVERAGE"]

# Fits from a better turn of the last before the coarse search takes over: each turn is
# within one step of its grid, so this many cover a misplacement of that many steps about
# the weakest rotation.
_TURNS_BEFORE_SEARCH = 3

#: A scan with fewer points gives no pose (refused, with the reason), not a guess.
MIN_POSE_POINTS = 50

AXIS_NAMES = ("tx", "ty", "tz", "rx", "ry", "rz")
_STD_KEYS = ("tx_mm", "ty_mm", "tz_mm", "rx_deg", "ry_deg", "rz_deg")


@dataclass(frozen=True)
class PoseParams:
    """Settings of the registration.

    Attributes
    ----------
    max_points : int
        Scan points used by the fine stage (a seeded, even subsample beyond it).
    search_points : int
        Of those, the points the search for the minimum runs on (the fit from the nominal
        grasp, the coarse search and its candidate); the minimum found is then settled on
        all ``max_points``, which the probes for rival minima, the pose and its uncertainty
        use. On bench pose_time's scans 2 000 found the same minima as 6 000 (within
        0.12 um), each search fit at a third of the cost.
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
    act_edge_fraction : float
        A pose whose edge points the model explains fewer of than this is a poor fit, not
        acted on; between it and ``good_edge_fraction`` the flag ("edges: ...") informs only.
        The search ran already (``good_edge_fraction`` sends a fit to it), and a pose that
        explains most of its edge evidence is judged by its sigmas and its rivals: in the
        calibrated realistic cell (``flyscan bench place``) featuretype's poses matched 66-80 %
        of their edge points (the rest off the CAD's sharp edges) and placed the part as
        well as the other parts', yet 48 % of them were refused at 0.8.
    sigma_inflation : float
        The fit's own terms (the profiles' and the edges') are multiplied by this: 1 (none)
        by default, since with the edges' shared offsets and the calibration's light plane
        in, the sigmas hold on their own (``flyscan bench place``); a setting for a cell whose
        scans show an error none of the terms sees.
    coarse_step_deg, coarse_extent_deg : float
        The coarse grid of rotation vectors around the nominal: every combination of
        ``-extent..extent`` in ``step`` about the three {T} axes.
    coarse_points : int
        Scan points used to score each coarse candidate.
    coarse_iterations : int
        Iterations refining each coarse candidate.
    probe_weakness : float
        Every converged fit is probed with refits from turns of 1 and 2 degrees about its
        weakest rotation; one whose weakest rotation is held less than this (its information
        over the strongest rotation's, translations free) is also probed, unless the scan
        leaves it free, from the best turns of a sweep all the way round it (a part
        near-symmetric about it: cycloidal's lobes fit 90 degrees off, a many-lobed disc's
        any whole number of lobes): a minimum that fits clearly better is taken; another that
        fits as well makes the pose ambiguous, and the spread between them enters its
        uncertainty. A fit whose surfaces alone hold that rotation little (``_EDGES_ALONE``)
        is swept round too.
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
    act_tolerance_mm, act_tolerance_deg : float
        The placement tolerance the cell needs. A pose is acted on (`PoseResult.act`) only
        when every axis's 3 sigma lies within it (translations of the {T} origin, mm;
        rotations about the {T} axes, degrees), no rival minimum that fits as well lies
        beyond it, no motion is free, and nothing else flags the pose; it is observable when
        the first three hold. Defaults: 0.1 mm and 0.1 degrees, a precise placing cell
        (fixtures and press fits with a tenth of a millimetre of play).
    prior_mm, prior_deg : float
        What a pick can leave the part misplaced by (``flyscan bench place`` draws up to 10
        mm and 20 degrees): along a free motion the pose keeps its start, so its error there
        is bounded by this alone, and the other axes' sigmas take it in
        (``scanner_core.pose.confidence._free_prior``).
    robot_rotation_std_deg : float
        How far off the robot reports its orientation during the pass (its accuracy), degrees
        per axis: every profile is placed with the reported rotation, so the whole cloud turns
        by that error about the TCP, and the pose with it, however many profiles it has
        (``scan_pose`` adds it to the rotations' variance). Default 0.005 degrees; take the
        robot's datasheet or its own calibration. The realistic simulated cell's robot
        reports 0.002 degrees off; without this term ``flyscan bench place`` saw poses acted
        on 3.0 to 3.8 of their sigmas off about y_T.
    seed : int
        Seed of the subsampling.
    """

    max_points: int = 6000
    search_points: int = 2000
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
    act_edge_fraction: float = 0.5
    sigma_inflation: float = 1.0
    coarse_step_deg: float = 15.0
    coarse_extent_deg: float = 15.0
    coarse_points: int = 800
    coarse_iterations: int = 8
    coarse_sweep_deg: float = 1.0
    probe_weakness: float = 0.015
    max_fine_turn_deg: float = 45.0
    act_tolerance_mm: float = 0.1
    act_tolerance_deg: float = 0.1
    prior_mm: float = 10.0
    prior_deg: float = 20.0
    robot_rotation_std_deg: float = 0.005
    seed: int = 0

    def __post_init__(self):
        for name in ("act_tolerance_mm", "act_tolerance_deg", "prior_mm", "prior_deg"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"PoseParams.{name} must be finite and > 0, got {value!r}")
        if not (np.isfinite(self.robot_rotation_std_deg) and self.robot_rotation_std_deg >= 0):
            raise ValueError(f"PoseParams.robot_rotation_std_deg must be finite and >= 0, got "
                             f"{self.robot_rotation_std_deg!r}")
        if not self.search_points >= MIN_POSE_POINTS:
            raise ValueError(f"PoseParams.search_points must be at least {MIN_POSE_POINTS}, got "
                             f"{self.search_points!r}")


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
        Of the last fit: the one that settled the pose on every point.
    coarse : bool
        Whether the coarse search ran.
    turns : int
        Fits the search made from a better turn of its last fit about its weakest rotation
        (a fit a lobe or a tooth off) before the coarse search or without it.
    time_ms : float
        The registration's time; `normals_ms` before it (`scan_pose`) estimated the normals.
    flags : list of str
        What the fit itself says against the pose (a poor fit, large residuals, free
        motions, a rival minimum, a partial scan).
    rivals : list of (4, 4) float64
        Other minima that fit the scan as well (``scanner_core.pose.search._probe_turns``).
    observable : bool
        Every axis pinned within the act tolerance: no free motion, every axis's 3 sigma
        within ``PoseParams.act_tolerance_mm`` / ``act_tolerance_deg``, no rival beyond it.
    act : bool
        The one verdict a robot acts on: observable and no flag. False: do not place.
    act_reasons : list of str
        Why not to act; empty when `act`.
    covariance_terms : dict of str to (6, 6) float64
        `covariance` as the sum of its terms (``pose_confidence.COVARIANCE_TERMS``: the
        profiles' noise through the fit, the edges' and the faces' shared offsets, the
        inflation, the free motions' slack, the rivals, the calibration's light plane and
        marker offset, the robot's orientation report), each in the units of `covariance`.
    symmetry : dict or None
        The near symmetry that leaves a rotation loose, when one is found
        (``scanner_core.pose.symmetry.name_symmetry``): ``{"label": "87-fold about z_T",
        "axis": [x, y, z] in {T}, "fold": 87 or None, "period_deg", "continuous",
        "matched_fraction"}``.
    part_symmetry : dict or None
        For a part the CAD's own turns map onto itself
        (``scanner_core.pose.symmetry.exact_symmetries``): ``{"order": K, "turned_deg"}``,
        the K turns (the identity among them) that place it the same, and the one the pose
        was turned by from the fit's minimum to the equivalent nearest the nominal grasp.
        None for a part without.
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
    turns: int = 0
    time_ms: float = 0.0
    flags: list = field(default_factory=list)
    normals_ms: float = 0.0
    rivals: list = field(default_factory=list)
    observable: bool = False
    act: bool = False
    act_reasons: list = field(default_factory=list)
    symmetry: dict | None = None
    covariance_terms: dict = field(default_factory=dict)
    part_symmetry: dict | None = None

    def std_terms(self) -> dict:
        """Per term of `covariance` (``pose_confidence.COVARIANCE_TERMS``), the standard
        deviation it alone gives each axis, signed as its variance (``term_stds``)."""
        return term_stds(self.covariance_terms)

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
            "act": bool(self.act),
            "act_reasons": list(self.act_reasons),
            "observable": bool(self.observable),
            "free_axes": self.free_axes,
            "symmetry": self.symmetry,
            "part_symmetry": self.part_symmetry,
            "std": dict(zip(_STD_KEYS, clean(self.std))),
            "std_terms": {name: dict(zip(_STD_KEYS, clean(values)))
                          for name, values in self.std_terms().items()},
            "iterations": self.iterations,
            "coarse": self.coarse,
            "turns": self.turns,
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
    result = _register(points_t, normals_t, model, nominal, frame_ids=frame_ids, edges_t=edges_t,
                       edge_frame_ids=edge_frame_ids, edge_model=edge_model,
                       edge_steps_mm=edge_steps_mm, params=params)
    t0 = time.perf_counter()
    judge(result, model, params)
    result.time_ms += (time.perf_counter() - t0) * 1e3
    return result


def _register(points_t, normals_t, model: SurfaceModel, nominal, *, frame_ids, edges_t,
              edge_frame_ids, edge_model, edge_steps_mm, params: PoseParams,
              sheet=None) -> PoseResult:
    """:func:`register` without the verdict (``judge``), which `scan_pose` gives once its
    own flags and the placement's error are in. `sheet`: the light plane's uncertainty
    (``pose_confidence._uncertainty``)."""
    t0 = time.perf_counter()
    points, directions, frames = check_inputs(points_t, normals_t, frame_ids)
    agreement = np.cos(np.radians(params.normal_agreement_deg))
    nominal = np.asarray(nominal, dtype=np.float64)
    rng = np.random.default_rng(params.seed)
    used = _subsample(len(points), params.max_points, rng)
    surface = _Terms(points[used], directions[used], frames[used], model, agreement)
    edges = None
    if edges_t is not None and edge_model is not None and len(edge_model.points):
        e_points, _, e_frames = check_inputs(edges_t, None, edge_frame_ids, minimum=0)
        steps = edge_steps(edges_t, edge_steps_mm)
        if len(e_points):
            edges = _Terms(e_points, None, e_frames, edge_model, steps_mm=steps)

    edge_count = 0 if edges is None else len(edges.points)
    # The search (which minimum) on a subsample; the minimum found settled on every point.
    search = surface
    if len(surface.points) > params.search_points:
        search = surface.subset(_subsample(len(surface.points), params.search_points, rng))
    # The search's fits on a subsample place a minimum; the fit on every point settles it.
    seek = _settling(params, len(surface.points))
    fit = _fine(search, edges, nominal, seek, wander=True)
    coarse = False
    slid = _turn_deg(fit.pose, nominal) > params.max_fine_turn_deg
    searching = _looks_poor(fit, nominal, edge_count, params)
    # A fit a lobe or a tooth off is refitted from the turn that fits better, and so on a few
    # times; the coarse search runs when a fit looks poor or still has a better turn.
    turn = None if searching else _better_turn(search, edges, fit.pose, params)
    turns = 0
    while turn is not None and turns < _TURNS_BEFORE_SEARCH:
        turns += 1
        turned = _fine(search, edges, turn, seek)
        if (_looks_poor(turned, nominal, edge_count, params)
                or _final_score(search, edges, turned, params)
                <= _final_score(search, edges, fit, params)):
            break
        fit, turn = turned, _better_turn(search, edges, turned.pose, params)
    searching = searching or turn is not None
    if searching:
        starts = _coarse(search, edges, nominal, params, rng)
        candidate = _fine(search, edges, starts[0], seek)
        coarse = True
        candidate_slid = _turn_deg(candidate.pose, nominal) > params.max_fine_turn_deg
        if (slid and not candidate_slid) or (
                slid == candidate_slid and _final_score(search, edges, candidate, params)
                > _final_score(search, edges, fit, params)):
            fit = candidate
    if search is not surface:
        fit = _fine(surface, edges, fit.pose, seek, warm=False)
    group = model.symmetries
    # The other minima on every point: on fewer, a rival that fits as well can go unseen
    # (ADIS16480 seen on its end, bench pose: a rival 152 mdeg away, near the truth, missed).
    probed, rivals = _probe_turns(surface, edges, fit, params)
    if not coarse and _implausible(probed.pose, nominal, group, params):
        # The probes went all the way round from a fit that was itself off (a wrong minimum
        # that matched enough points not to look poor): the coarse search looks near the
        # start, where a misplacement can put the part, and its minimum is probed as well.
        coarse = True
        candidate = _fine(search, edges, _coarse(search, edges, nominal, params, rng)[0], seek)
        if search is not surface:
            candidate = _fine(surface, edges, candidate.pose, seek, warm=False)
        other, other_rivals = _probe_turns(surface, edges, candidate, params)
        if (not _implausible(other.pose, nominal, group, params)
                or _final_score(surface, edges, other, params)
                > _final_score(surface, edges, probed, params)):
            probed, rivals, fit = other, other_rivals, candidate
    before_probes, fit = fit.pose, probed
    # A part that maps onto itself under some turns is placed the same by each: the pose is
    # the one nearest the grasp, and the same minimum turned is no rival.
    equivalents = None
    if len(group) > 1:
        rivals = [r for r in rivals if not equivalent_to(fit.pose, r, group,
                                                         params.act_tolerance_mm,
                                                         params.act_tolerance_deg)]
        turn = nearest_equivalent(fit.pose, nominal, group)
        fit = dataclasses.replace(fit, pose=fit.pose @ turn)
        rivals = [r @ turn for r in rivals]
        turned_deg = float(np.degrees(Rotation.from_matrix(turn[:3, :3]).magnitude()))
        equivalents = {"order": int(len(group)), "turned_deg": round(turned_deg, 6)}
    covariance, std, free_axes, terms = _uncertainty(fit, params, rivals, sheet)
    flags = _flags(fit, free_axes, edge_count, params)
    turned = max(_turned_from(pose, nominal, group) for pose in (before_probes, fit.pose))
    if turned > params.max_fine_turn_deg:
        flags.append(f"implausible: the fit turned {turned:.0f} degrees from the start, farther "
                     f"than a misplacement the search covers ({params.max_fine_turn_deg:g})")
    if rivals:
        flags.append("ambiguous: " + "; ".join(_rival_words(fit.pose, r) for r in rivals)
                     + " fits as well")
    result = PoseResult(
        matrix=fit.pose, misplacement=fit.pose @ np.linalg.inv(nominal), rms_mm=fit.rms,
        inlier_fraction=fit.inlier_fraction, std=std, free_axes=free_axes,
        covariance=covariance, iterations=fit.iterations, coarse=coarse, turns=turns, flags=flags,
        rivals=list(rivals), covariance_terms=terms, part_symmetry=equivalents)
    result.time_ms = (time.perf_counter() - t0) * 1e3
    return result


def _turned_from(pose, nominal, group) -> float:
    """Degrees `pose` turned from the start `nominal`, modulo the part's own turns (`group`)."""
    return _turn_deg(pose @ nearest_equivalent(pose, nominal, group), nominal)


def _implausible(pose, nominal, group, params: PoseParams) -> bool:
    """Whether `pose` lies farther from the start than a misplacement can put the part
    (``PoseParams.max_fine_turn_deg``)."""
    return _turned_from(pose, nominal, group) > params.max_fine_turn_deg


def _looks_poor(fit, nominal, edge_count: int, params: PoseParams) -> bool:
    """Whether a fit of the search sends it to the coarse search: it turned farther from the
    start than a misplacement can, matches too few of its surface points, or its edge points
    refute it."""
    return (_turn_deg(fit.pose, nominal) > params.max_fine_turn_deg
            or fit.inlier_fraction < params.good_inlier_fraction
            or edges_refute(fit.edge_fraction, edge_count, params.good_edge_fraction,
                            EDGES_SEARCH_SIGNIFICANCE))


def scan_pose(scan, surface_model: SurfaceModel, nominal, *, edge_model: EdgeModel | None = None,
              params: PoseParams = PoseParams()) -> PoseResult:
    """The pose of a stitched scan (``scanner_core.types.Scan``): its cloud (up to
    ``params.max_points`` of it) with normals toward the camera, its frames as clusters, and
    its edge cloud when it has one. :func:`inputs_pose` of what it reads of the scan
    (``ScanPoseInputs.of``).

    Raises
    ------
    ValueError
        Fewer than `MIN_POSE_POINTS` points: no pose is better than a guess.
    """
    return inputs_pose(ScanPoseInputs.of(scan), surface_model, nominal, edge_model=edge_model,
                       params=params)


def inputs_pose(inputs: ScanPoseInputs, surface_model: SurfaceModel, nominal, *,
                edge_model: EdgeModel | None = None,
                params: PoseParams = PoseParams()) -> PoseResult:
    """:func:`scan_pose` of a scan's `inputs`: a function of them alone (a fixed seed), so
    the same inputs give the same pose, bit for bit."""
    from scanner_core.normals import estimate_normals

    if len(inputs.cloud) < MIN_POSE_POINTS:
        raise ValueError(f"a pose needs at least {MIN_POSE_POINTS} points, the scan has "
                         f"{len(inputs.cloud)}")
    use_edges = (edge_model is not None and inputs.edges is not None and len(inputs.edges) > 0)
    # Normals only where the fit looks (neighbours from the whole cloud): most of a pose's
    # time would otherwise go to normals it never uses.
    t0 = time.perf_counter()
    used = _subsample(len(inputs.cloud), params.max_points, np.random.default_rng(params.seed))
    normals = estimate_normals(inputs.cloud, sensors=inputs.sensors, frame_ids=inputs.frame_ids,
                               index=used)
    result = _register(inputs.cloud[used], normals, surface_model, nominal,
                       frame_ids=inputs.frame_ids[used],
                       edges_t=inputs.edges if use_edges else None,
                       edge_frame_ids=inputs.edge_frame_ids if use_edges else None,
                       edge_model=edge_model if use_edges else None,
                       edge_steps_mm=inputs.edge_steps_mm if use_edges else None, params=params,
                       sheet=None if inputs.sheet_covariance is None
                       else (inputs.sheet_frames, inputs.sheet_t, inputs.sheet_covariance))
    result.flags += _coverage_flags(inputs, result.matrix, surface_model)
    placement = inputs.placement_std_mm
    add_placement_error(result, np.zeros(3) if placement is None else placement,
                        params.robot_rotation_std_deg)
    judged = time.perf_counter()
    judge(result, surface_model, params)
    result.time_ms += (time.perf_counter() - judged) * 1e3
    result.normals_ms = (time.perf_counter() - t0) * 1e3 - result.time_ms
    return result
