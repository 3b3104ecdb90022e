"""Is what the gripper holds the expected part, alone and whole? The cloud against the model at
the registered pose.

Every cloud point's signed deviation from the model's surface (outward positive, mm): the
point-to-plane distance to the nearest surface sample (``SurfaceModel``) where the point lies
over it, the distance itself where it lies beyond the sample's reach. The scan's own noise
``sigma`` comes from the deviations' changes between neighbouring points of a profile (their
robust spread, 1.4826 MAD, over sqrt 2): a bend or a second part moves whole regions, which
those changes do not see.
Points off the model are grouped into regions (those in touching cubes of ``LINK_SPACINGS`` of
the scan's larger sampling step) and each region judged by its kind:

- **extra material**: points outside the model by more than ``extra_mm`` (a second part, debris,
  a burr);
- **missing material**: points inside the model by more than ``extra_mm`` (a chip or a cut:
  the scan sees a surface where the model has material), or model surface the scan should
  have seen at this pose and has no point on (a hole added, a corner cut through: the
  scanner's own prediction from the sheets and the camera it was placed by,
  ``scanner_core.inspection.coverage``);
- **deformation**: points off the model by more than ``deform_mm`` but not ``extra_mm``, over
  a region (bent, warped);
- **wrong part**: more than ``wrong_part_share`` of the points off the model by ``deform_mm``.

A region fails when it spans ``MIN_REGION_PROFILES`` profiles (``MIN_PROFILE_POINTS`` points
of each) and its area (its points times the area a point samples: the profiles'
spacing times the points' spacing along a profile, mm^2) reaches ``min_area_mm2``. The
thresholds not given are derived from the scan's noise and sampling, never from a part:
``extra_mm = max(EXTRA_SIGMAS sigma, EXTRA_SPACINGS point spacing)``,
``deform_mm = DEFORM_SIGMAS sigma``, ``min_area_mm2 = MIN_REGION_SAMPLES`` points' area
(``MIN_DEFORMED_SAMPLES`` for a deformation).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
from numba import njit
from scipy import ndimage

from scanner_core.inspection.coverage import (NONE_MISSING, MissingSamples, missing_samples,
                                              warm_up_coverage)

__all__ = ["InspectionParams", "Inspection", "Region", "KINDS", "point_deviations",
           "inspect_scan", "point_spacing", "touching_groups", "warm_up_inspection",
           "EXTRA_SIGMAS", "DEFORM_SIGMAS", "EXTRA_SPACINGS", "MIN_REGION_SAMPLES",
           "MIN_REGION_PROFILES", "LINK_SPACINGS"]

#: The thresholds a part, the service or a caller may set (mm, mm^2); the rest are derived.
GIVEN_THRESHOLDS = ("extra_mm", "deform_mm", "min_area_mm2")
#: The kinds of a failing inspection, in the order they are reported.
KINDS = ("extra_material", "missing_material", "deformation", "wrong_part")
#: Off the model by more than this many of the scan's sigmas is material that is not the
#: model's (the reference cell's clouds hold 10-15 um RMS; 12 sigma lies far in the tail of
#: any scan whose registration and calibration hold).
EXTRA_SIGMAS = 12.0
#: ... and by more than this many steps between a profile's points: near the model's edges a
#: point of the edge's other side lies a step away (mixed pixels, the edge's rounding).
EXTRA_SPACINGS = 2.0
#: Off the model by more than this many sigmas, over a region, the surface is not the model's.
DEFORM_SIGMAS = 8.0
#: A region off the model by more than ``extra_mm`` counts from this many of the scan's
#: points' area, one by less (a deformation) from ``MIN_DEFORMED_SAMPLES``: material that is
#: not the model's stands far off it, a bend only a little, where a surface's own texture
#: and the registration's leftovers also lie.
MIN_REGION_SAMPLES = 8
MIN_DEFORMED_SAMPLES = 20
#: ... over at least this many profiles, each with ``MIN_PROFILE_POINTS`` of its points: one
#: profile grazing the model's rim, or glinting, is no region of the part.
MIN_REGION_PROFILES = 2
MIN_PROFILE_POINTS = 3
#: Points in touching cubes of this many sampling steps are one region.
LINK_SPACINGS = 1.5
#: A point farther than this many ``extra_mm`` from the model is off it, whatever its exact
#: distance (``point_deviations``' ``far_mm``).
FAR_EXTRAS = 4.0
#: ... and than this many of the model's sample spacings (the noise's first estimate takes
#: the table's answer farther than that: such points are its outliers anyway).
FAR_SPACINGS = 8.0
#: A wrong part: more than this share of the cloud off the model by ``deform_mm``.
WRONG_PART_SHARE = 0.5
#: The noise is never taken below this, mm (a cloud that fits to the micrometre is no reason
#: to call its next micrometre a fault).
MIN_SIGMA_MM = 0.005


@dataclass(frozen=True)
class InspectionParams:
    """Thresholds of the check; None: derived from the scan (the module's docstring).

    Attributes
    ----------
    extra_mm, deform_mm : float or None
        Off the model by more than these, mm.
    min_area_mm2 : float or None
        A failing region's area at least, mm^2.
    wrong_part_share : float
        Share of the cloud off the model that makes it another part.
    """

    extra_mm: float | None = None
    deform_mm: float | None = None
    min_area_mm2: float | None = None
    wrong_part_share: float = WRONG_PART_SHARE

    def __post_init__(self):
        for name in GIVEN_THRESHOLDS:
            value = getattr(self, name)
            if value is not None and not (isinstance(value, (int, float))
                                          and not isinstance(value, bool)
                                          and math.isfinite(value) and value > 0):
                raise ValueError(f"`{name}` must be a positive number of mm (mm^2 for an "
                                 f"area), got {value!r}")
        if not 0.0 < self.wrong_part_share <= 1.0:
            raise ValueError(f"`wrong_part_share` must be in (0, 1], got {self.wrong_part_share}")

    @classmethod
    def from_dict(cls, data) -> "InspectionParams":
        """The thresholds a part's plan or upload gives: a mapping of some of
        ``GIVEN_THRESHOLDS`` to positive numbers; ValueError naming what is wrong."""
        if not isinstance(data, dict):
            raise ValueError(f"the inspection's thresholds must be a mapping of "
                             f"{', '.join(GIVEN_THRESHOLDS)}, got {type(data).__name__}")
        unknown = sorted(set(data) - set(GIVEN_THRESHOLDS))
        if unknown:
            raise ValueError(f"unknown inspection thresholds {unknown}: give "
                             f"{', '.join(GIVEN_THRESHOLDS)}")
        return cls(**data)

    def given(self) -> dict:
        """The thresholds set (not derived from the scan), by name."""
        return {k: getattr(self, k) for k in GIVEN_THRESHOLDS if getattr(self, k) is not None}

    def over(self, base: "InspectionParams") -> "InspectionParams":
        """These thresholds where set, `base`'s elsewhere (a part's over the service's)."""
        return replace(base, **self.given())


@dataclass(frozen=True)
class Region:
    """One region off the model.

    Attributes
    ----------
    kind : str
        One of ``KINDS`` but ``wrong_part``.
    points : int
        Its cloud points (0 where the scan has none: ``evidence`` "no points").
    area_mm2 : float
    max_deviation_mm : float
        The largest deviation's magnitude in it, mm (NaN: no points to measure).
    centre_p : (3,) float64
        Its centroid, mm in {P}.
    evidence : str
        "off the model": points off it; "no points": model surface the scan should have
        seen and has no point on (``scanner_core.inspection.coverage``).
    profiles : int
        The profiles that cross it.
    """

    kind: str
    points: int
    area_mm2: float
    max_deviation_mm: float
    centre_p: np.ndarray
    evidence: str = "off the model"
    profiles: int = 0

    def to_dict(self) -> dict:
        deviation = (round(self.max_deviation_mm, 4) if math.isfinite(self.max_deviation_mm)
                     else None)
        return {"kind": self.kind, "evidence": self.evidence, "points": self.points,
                "profiles": self.profiles, "area_mm2": round(self.area_mm2, 3),
                "max_deviation_mm": deviation,
                "centre_p_mm": [round(float(v), 3) for v in self.centre_p]}

    def reason(self) -> str:
        where = f"at {np.round(self.centre_p, 1).tolist()} mm in the part's frame"
        if self.evidence == "no points":
            return (f"{self.kind.replace('_', ' ')}: {self.area_mm2:.1f} mm^2 of the model the "
                    f"scan should have seen has no point on it ({self.profiles} profiles) "
                    f"{where}")
        return (f"{self.kind.replace('_', ' ')}: {self.area_mm2:.1f} mm^2 up to "
                f"{self.max_deviation_mm:.2f} mm off the model {where}")


@dataclass
class Inspection:
    """The check's verdict.

    Attributes
    ----------
    conforms : bool
    failing : list of str
        The kinds that failed (``KINDS``' order).
    regions : list of Region
        The failing regions.
    deviations_mm : (N,) float32
        Every cloud point's signed deviation, mm (outward positive).
    sigma_mm : float
        The scan's noise about the model, mm.
    thresholds : dict
        ``extra_mm``, ``deform_mm``, ``min_area_mm2`` as used.
    off_share : float
        Share of the cloud off the model by ``deform_mm``.
    time_ms : float
    """

    conforms: bool
    failing: list
    regions: list
    deviations_mm: np.ndarray
    sigma_mm: float
    thresholds: dict
    off_share: float
    time_ms: float = 0.0
    reasons: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"conforms": self.conforms, "failing": list(self.failing),
                "reasons": list(self.reasons),
                "regions": [r.to_dict() for r in self.regions],
                "sigma_um": round(self.sigma_mm * 1e3, 2),
                "thresholds": {k: round(v, 4) for k, v in self.thresholds.items()},
                "off_share": round(self.off_share, 4), "time_ms": round(self.time_ms, 3)}


def point_deviations(points_p: np.ndarray, surface, *, exact_above: float | None = None,
                     far_mm: float | None = None) -> np.ndarray:
    """Signed deviation of each point from the model's surface, mm (outward positive).

    Parameters
    ----------
    points_p : (N, 3) float64
        mm in {P}.
    surface : scanner_core.pose.models.SurfaceModel
        Samples of the model's surface with outward normals, and their KD-tree.
    exact_above : float, optional
        None: every point's nearest sample from the KD-tree. A distance, mm: each point's
        sample comes from the surface's lookup table (``SurfaceModel.lookup``: a sample near
        the nearest, O(1) a point, exact on a planar face), and only the points it puts off
        by more than this, or beyond the sample's reach, ask the KD-tree. A point's
        deviation from the nearest sample's plane is at most its distance to the sample the
        table gives, so no point the tree would put farther off than ``exact_above`` is left
        to the table near a face; the table's answer differs only near an edge, by less.
    far_mm : float, optional
        With ``exact_above``: a point farther than this from every sample keeps the table's
        answer (its distance to the table's sample, signed by that sample's normal), and one
        beyond the table's band is outside by the band: off the model either way, and a
        KD-tree query slows with the distance (a second part's thousands of points).

    Returns
    -------
    (N,) float64
        ``(p - q) . n`` for the nearest sample ``q`` (normal ``n``) where the point lies over
        it (its offset along the surface within the samples' spacing), else ``|p - q|`` with
        that sign: a point beyond the surface's reach is as far as it is.
    """
    points_p = np.asarray(points_p, dtype=np.float64).reshape(-1, 3)
    if len(points_p) == 0:
        return np.zeros(0)
    if exact_above is None:
        _, index = surface.tree.query(points_p, workers=1)
        return _to_samples(points_p, surface, index)
    table = surface.lookup
    bounded = far_mm is not None
    distance, index = table.query(points_p, table.band_mm if bounded else np.inf)
    found = np.isfinite(distance)
    out = np.full(len(points_p), table.band_mm)
    along = _along_normals(points_p, surface.points, surface.normals, index)[found]
    out[found] = np.copysign(distance[found], along) if bounded else along
    if bounded:  # the table's own answer where the point lies over its sample
        over = np.abs(along) >= distance[found] - 2.0 * surface.spacing_mm
        out[np.nonzero(found)[0][over]] = along[over]
    # the table's sample lies within a voxel's diagonal of the nearest: a point farther than
    # that beyond the samples' reach may lie beyond the surface's edge, and asks the tree
    reach = 2.0 * surface.spacing_mm + table.voxel_mm * math.sqrt(3.0)
    again = np.nonzero(found & (~(np.abs(out) <= exact_above) | (distance > reach))
                       | (~found & (not bounded)))[0]
    if len(again):
        near, exact = surface.tree.query(points_p[again], workers=1,
                                         distance_upper_bound=far_mm if bounded else np.inf)
        ok = np.isfinite(near)
        out[again[ok]] = _to_samples(points_p[again[ok]], surface, exact[ok])
    return out


@njit(nogil=True, cache=True)
def _along_normals(points, sample_points, sample_normals, index):
    """``(p - q) . n`` of each point and its sample ``index`` (N,); NaN where the index is
    past the samples (none found). One pass: the gathered (N, 3) offsets and normals cost
    more than the products."""
    count = sample_points.shape[0]
    out = np.full(points.shape[0], np.nan)
    for i in range(points.shape[0]):
        k = index[i]
        if 0 <= k < count:
            out[i] = ((points[i, 0] - sample_points[k, 0]) * sample_normals[k, 0]
                      + (points[i, 1] - sample_points[k, 1]) * sample_normals[k, 1]
                      + (points[i, 2] - sample_points[k, 2]) * sample_normals[k, 2])
    return out


def warm_up_inspection() -> float:
    """Compile the check's numba kernels before the first check (the coverage's,
    ``warm_up_coverage``, and the deviations'), with the argument types a check gives them.
    Returns the time it took, ms."""
    t0 = time.perf_counter()
    warm_up_coverage()
    points = np.zeros((2, 3))
    _along_normals(points, points, np.tile([0.0, 0.0, 1.0], (2, 1)), np.array([0, 2]))
    return (time.perf_counter() - t0) * 1e3


def _to_samples(points_p, surface, index) -> np.ndarray:
    offset = points_p - surface.points[index]
    along = np.einsum("ij,ij->i", offset, surface.normals[index])
    across = np.sqrt(np.maximum(np.einsum("ij,ij->i", offset, offset) - along**2, 0.0))
    beyond = across > 2.0 * surface.spacing_mm
    out = along.copy()
    out[beyond] = np.copysign(np.linalg.norm(offset[beyond], axis=1), along[beyond])
    return out


def inspect_scan(cloud_t: np.ndarray, frame_ids: np.ndarray, pose_matrix: np.ndarray, surface,
                 *, profile_spacing_mm: float, point_spacing_mm: float,
                 params: InspectionParams = InspectionParams(), coverage_model=None,
                 occluded=None, sheet_planes_t=None, sensor_positions_t=None,
                 sheet_frame_ids=None, sharp_edges=None, measured_box_t=None) -> Inspection:
    """The check of a cloud against the model at its registered pose.

    Parameters
    ----------
    cloud_t : (N, 3) float
        The scan's cloud, mm in {T}.
    frame_ids : (N,) int
        Each point's profile.
    pose_matrix : (4, 4) float64
        The registered ^T X_P.
    surface : scanner_core.pose.models.SurfaceModel
        The model's surface.
    profile_spacing_mm, point_spacing_mm : float
        The scan's sampling, mm: between its profiles, and between a profile's points.
    params : InspectionParams
    coverage_model : scanner_core.pose.models.SurfaceModel, optional
        The model's samples the scan's coverage is judged on (``PartModel.coverage_model``);
        with ``occluded``, ``sheet_planes_t`` and ``sensor_positions_t`` (``Scan``'s), the
        model surface the scan should have seen and has no point on is missing material
        (``scanner_core.inspection.coverage``). None: only the points are judged.
    occluded : callable(origins (R, 3), directions (R, 3)) -> (R,) bool, optional
        Whether rays in {P} meet the model (``PartModel.occluded``).
    sheet_planes_t, sensor_positions_t : (F, 4), (F, 3) float64, optional
    sheet_frame_ids : (F,) int, optional
        The frame of each sheet (``Scan.tcp_frame_ids``), as ``frame_ids`` names them; None:
        ``0 .. F-1``.
    sharp_edges : scanner_core.pose.models.EdgeModel, optional
        The model's sharp edges (``PartModel.edge_model``): with them a hole narrower than
        twice the profile step is found too (``coverage.missing_samples``).
    measured_box_t : (2, 3) float, optional
        ``Scan.measured_box_t``: the model outside it is not expected in the scan.

    Returns
    -------
    Inspection
    """
    t0 = time.perf_counter()
    cloud_t = np.asarray(cloud_t, dtype=np.float64).reshape(-1, 3)
    frame_ids = np.asarray(frame_ids)
    inverse = np.linalg.inv(np.asarray(pose_matrix, dtype=np.float64))
    points_p = cloud_t @ inverse[:3, :3].T + inverse[:3, 3]
    along = _step(point_spacing_mm)
    across = max(_step(profile_spacing_mm), along)
    # the noise from the lookup table's deviations (exact on planar faces, a point's own
    # changes between neighbours); then every point they put off by half the smallest
    # threshold asks the KD-tree
    dev = point_deviations(points_p, surface, exact_above=np.inf,
                           far_mm=FAR_SPACINGS * surface.spacing_mm)
    sigma = _noise(dev, frame_ids)
    extra = params.extra_mm or max(EXTRA_SIGMAS * sigma, EXTRA_SPACINGS * along)
    deform = min(params.deform_mm or DEFORM_SIGMAS * sigma, extra)
    again = np.nonzero(np.abs(dev) > 0.5 * deform)[0]
    dev[again] = point_deviations(points_p[again], surface, exact_above=0.5 * deform,
                                  far_mm=max(FAR_EXTRAS * extra, FAR_SPACINGS * surface.spacing_mm))
    sample_area = across * along
    min_area = params.min_area_mm2 or MIN_REGION_SAMPLES * sample_area
    min_areas = (min_area, min_area,
                 params.min_area_mm2 or MIN_DEFORMED_SAMPLES * sample_area)
    kinds = np.full(len(dev), -1, np.int8)
    kinds[(np.abs(dev) > deform) & (np.abs(dev) <= extra)] = 2  # deformation
    kinds[dev > extra] = 0  # extra material
    kinds[dev < -extra] = 1  # missing material
    off = kinds >= 0
    off_share = float(off.mean()) if len(dev) else 0.0
    regions = []
    if sheet_frame_ids is None and sheet_planes_t is not None:
        sheet_frame_ids = np.arange(len(sheet_planes_t))
    missing, samples = NONE_MISSING, None
    if coverage_model is not None and occluded is not None and sheet_planes_t is not None:
        samples = coverage_model
        missing = missing_samples(points_p, coverage_model, occluded, pose_matrix,
                                  sheet_planes_t, sensor_positions_t, point_spacing_mm=along,
                                  frame_ids=frame_ids, sheet_frame_ids=sheet_frame_ids,
                                  sharp_edges=sharp_edges, measured_box_t=measured_box_t)
    missing_regions, flanks = _missing_regions(
        points_p, np.nonzero(kinds == 1)[0], np.nonzero((kinds == 2) & (dev < 0))[0], dev,
        frame_ids, missing, samples, sheet_frame_ids, min_area, sample_area,
        LINK_SPACINGS * across)
    regions += missing_regions
    kinds[flanks] = 1  # a chip's flanks are the chip's, not a deformation beside it
    # A surface bent or warped lies off the model in stretches of its profiles; a point off
    # alone between points on it is the stripe's (a glint, a mixed peak, the exposure's smear
    # over a small rounded feature), however many of them one place gathers.
    stretches = _in_stretches(dev, frame_ids, deform)
    for kind in (0, 2):
        members = np.nonzero((kinds == kind) & (stretches if kind == 2 else True))[0]
        if len(members) * sample_area < min_areas[kind]:
            continue
        for group in touching_groups(cloud_t[members], LINK_SPACINGS * across):
            idx = members[group]
            area = len(idx) * sample_area
            if area < min_areas[kind]:  # and so are the rest: the groups come largest first
                break
            _, per_profile = np.unique(frame_ids[idx], return_counts=True)
            if (per_profile >= MIN_PROFILE_POINTS).sum() < MIN_REGION_PROFILES:
                continue
            regions.append(Region(KINDS[kind], int(len(idx)), float(area),
                                  float(np.max(np.abs(dev[idx]))), points_p[idx].mean(axis=0),
                                  profiles=int((per_profile >= MIN_PROFILE_POINTS).sum())))
    failing = [k for k in KINDS[:3] if any(r.kind == k for r in regions)]
    reasons = [r.reason() for r in regions]
    if off_share > params.wrong_part_share:
        failing.append("wrong_part")
        reasons.append(f"wrong part: {off_share:.0%} of the cloud lies off the model by more "
                       f"than {deform:.3f} mm")
    return Inspection(conforms=not failing, failing=failing, regions=regions,
                      deviations_mm=dev.astype(np.float32), sigma_mm=sigma,
                      thresholds={"extra_mm": extra, "deform_mm": deform,
                                  "min_area_mm2": min_area,
                                  "min_deformed_area_mm2": min_areas[2]},
                      off_share=off_share, time_ms=(time.perf_counter() - t0) * 1e3,
                      reasons=reasons)


def _missing_regions(points_p, recessed, sunken, dev, frame_ids, missing: MissingSamples,
                     samples, sheet_frame_ids, min_area: float, point_area: float,
                     link: float) -> tuple[list[Region], np.ndarray]:
    """Missing material: the points inside the model by more than ``extra_mm`` (`recessed`,
    indices into `points_p`), the points inside it by less, down to ``deform_mm``, beside them
    (`sunken`: a chip's flanks, which slope from the model's surface to its deepest point), and
    the model's samples the scan should have seen and has no point near (`missing`), grouped
    together, a group holding recessed points or a core missing sample. It is a region when it
    spans ``MIN_REGION_PROFILES`` profiles (those with ``MIN_PROFILE_POINTS`` of its points,
    and the frames whose sheets crossed its missing samples), reaches `min_area` (its points'
    area and its samples'), and stands on something sure: the points of such profiles
    covering `min_area` themselves, or a core missing sample
    (``scanner_core.inspection.coverage``). A chip seen as recessed points by one profile and
    as nothing by the next is one region; sunken points alone are a deformation's, or the
    texture's, not missing material. Returns the regions and the sunken points in them."""
    n_points = len(recessed) + len(sunken)
    if samples is None or not len(missing.index):
        sample_points, sample_area = np.zeros((0, 3)), 0.0
        sheet_ids = np.zeros(0, np.int64)
    else:
        sample_points, sample_area = samples.points[missing.index], samples.spacing_mm**2
        sheet_ids = np.asarray(sheet_frame_ids)[missing.frame]
    nothing = [], np.zeros(0, np.int64)
    if len(recessed) == 0 and not missing.core.any():
        return nothing
    if n_points * point_area + len(sample_points) * sample_area < min_area:
        return nothing
    members = np.concatenate([recessed, sunken]).astype(np.int64)
    deep = np.zeros(n_points, bool)
    deep[:len(recessed)] = True
    out, flanks = [], []
    for group in touching_groups(np.vstack([points_p[members], sample_points]), link):
        at, smp = group[group < n_points], group[group >= n_points] - n_points
        if not deep[at].any() and not missing.core[smp].any():
            continue
        idx = members[at]
        ids, per_profile = np.unique(frame_ids[idx], return_counts=True)
        by_points = set(ids[per_profile >= MIN_PROFILE_POINTS].tolist())
        profiles = len(by_points | set(sheet_ids[smp].tolist()))
        area = len(idx) * point_area + len(smp) * sample_area
        # either evidence must hold a region's area on its own: a few recessed points at a
        # face's edge beside the strip its sheets missed are neither
        placed = np.isin(frame_ids[idx], list(by_points)).sum() * point_area
        sure = placed >= min_area or bool(missing.core[smp].any())
        if not sure or area < min_area or profiles < MIN_REGION_PROFILES:
            continue
        centre = np.vstack([points_p[idx], sample_points[smp]]).mean(axis=0)
        evidence = ("off the model" if not len(smp) else "no points" if not len(idx)
                    else "off the model and no points")
        out.append(Region("missing_material", int(len(idx)), float(area),
                          float(np.max(np.abs(dev[idx]))) if len(idx) else float("nan"),
                          centre, evidence=evidence, profiles=profiles))
        flanks.append(members[at[~deep[at]]])
    return out, np.concatenate(flanks) if flanks else nothing[1]


def _noise(dev: np.ndarray, frame_ids: np.ndarray) -> float:
    """The scan's noise about the model, mm: the robust spread of the deviation's changes
    between neighbouring points of one profile (those within 5 of a first spread) over
    sqrt 2; of the deviations themselves when the profiles hold too few neighbours."""
    same = frame_ids[1:] == frame_ids[:-1]
    values, per_value = np.diff(dev)[same], math.sqrt(2.0)
    if len(values) < 20:
        values, per_value = dev, 1.0
    if not len(values):
        return MIN_SIGMA_MM
    spread = 1.4826 * float(np.median(np.abs(values)))
    near = np.abs(values) <= 5.0 * spread
    if near.sum() >= 20:
        spread = 1.4826 * float(np.median(np.abs(values[near])))
    return max(spread / per_value, MIN_SIGMA_MM)


def _step(value: float) -> float:
    """A sampling step, mm; 0.5 where the scan cannot say (too few profiles or points)."""
    return float(value) if math.isfinite(value) and value > 0 else 0.5


def _in_stretches(dev: np.ndarray, frame_ids: np.ndarray, threshold: float) -> np.ndarray:
    """(N,) bool: the points off the model by more than `threshold` (mm) whose neighbour along
    their profile, the point before or after them, is off it the same way (`dev`, (N,) mm,
    signed; ``frame_ids`` (N,), in ``Scan.cloud``'s order: by profile, each by column)."""
    dev = np.asarray(dev, dtype=np.float64)
    off = np.where(np.abs(dev) > threshold, np.sign(dev), 0.0)
    frame_ids = np.asarray(frame_ids)
    pair = (frame_ids[1:] == frame_ids[:-1]) & (off[1:] == off[:-1]) & (off[1:] != 0.0)
    inside = np.zeros(len(dev), bool)
    inside[1:] |= pair
    inside[:-1] |= pair
    return inside


def point_spacing(cloud_t: np.ndarray, frame_ids: np.ndarray) -> float:
    """Median distance between neighbouring points of one profile, mm (NaN: no two).

    ``cloud_t`` (N, 3) is sorted by ``frame_ids`` (N,) and each profile's points by column,
    as ``Scan.cloud`` is."""
    cloud_t = np.asarray(cloud_t, dtype=np.float64).reshape(-1, 3)
    same = np.asarray(frame_ids)[1:] == np.asarray(frame_ids)[:-1]
    if not same.any():
        return float("nan")
    steps = np.linalg.norm(np.diff(cloud_t, axis=0), axis=1)[same]
    return float(np.median(steps))


def touching_groups(points: np.ndarray, radius: float) -> list[np.ndarray]:
    """Indices of `points` (M, 3) split into groups, largest first: the points of cubes of
    side `radius` that touch (face, edge or corner) are one group. Two points within
    `radius` always are; two of touching cubes may be up to 2 sqrt(3) `radius` apart. Linear
    in the points, where linking every pair within `radius` grows with their density (a
    second part's thousands of points)."""
    cells = np.floor((points - points.min(axis=0)) / radius).astype(np.int64)
    shape = cells.max(axis=0) + 1
    grid = np.zeros(tuple(shape), bool)
    grid[tuple(cells.T)] = True
    labels, count = ndimage.label(grid, structure=np.ones((3, 3, 3), bool))
    point_labels = labels[tuple(cells.T)] - 1
    order = np.argsort(point_labels, kind="stable")
    groups = np.split(order, np.cumsum(np.bincount(point_labels, minlength=count))[:-1])
    return sorted((g for g in groups if len(g)), key=len, reverse=True)
