"""A part's scan plan: how to hold it and which way to carry it through the sheet.

``flyscan plan`` (the ``planning`` package, over the simulator) writes one ``plan.json`` per
part; ``flyscan scan --plan FILE`` and the service (a ``plan.json`` in a stored part's folder)
read it here, as plain JSON: they never import the planner. The plan's fields that a scan
uses:

- ``grasp``: ``name`` (``centred``, ``flat`` or ``resting-K``: the part lying on the K-th
  largest stable face of its convex hull, picked from above by a suction cup) and ``base``,
  the 4x4 ^T X_P of that grasp, mm;
- ``pass_direction_deg``: a turn of the part about z_T before the pass (the robot turns its
  wrist), degrees: the sheet then crosses the part along another direction;
- ``nominal_grasp``: the 4x4 ^T X_P the scan registers against, `turned_grasp` of the two;
- ``preset``, ``speed_mm_s``, ``fps``: the pass;
- ``mesh_sha256``: the mesh file the plan was made for (a plan of another mesh is refused).

Units: mm, degrees where a person reads them (the turn), 4x4 row-major matrices.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scanner_core.geometry import check_rigid

__all__ = ["PLAN_FORMAT", "PlanError", "ScanPlan", "load_scan_plan", "turned_grasp",
           "file_sha256", "check_plan_grasp", "MIN_PROFILES", "too_few_profiles"]

#: Profiles a pass must give on the part, at least, for its pose to be asked for.
MIN_PROFILES = 5

#: The ``format`` field of a plan file this module reads.
PLAN_FORMAT = "flyscan-plan/1"
# Agreement asked of a plan's nominal grasp with the one its base and turn give, mm: float
# noise of a JSON round trip (17 significant digits) is far below it.
_GRASP_TOL_MM = 1e-6


class PlanError(ValueError):
    """A plan file that cannot be used: unreadable, of another format, inconsistent, or made
    for another mesh."""


@dataclass(frozen=True)
class ScanPlan:
    """What a scan takes from a part's plan.

    Attributes
    ----------
    part : str
        The part's name in the catalogue.
    grasp_name : str
        ``centred``, ``flat`` or ``resting-K``.
    base_grasp : (4, 4) float64
        ^T X_P of that grasp before the turn, mm.
    pass_direction_deg : float
        Turn about z_T, degrees.
    nominal_grasp : (4, 4) float64
        ^T X_P the scan registers against, mm.
    preset : str
        The pass preset's name (``default``, ``fast``, ``slow``).
    speed_mm_s, fps : float
        The pass.
    mesh_sha256 : str
        SHA-256 of the mesh file the plan was made for.
    inspection : scanner_core.inspection.InspectionParams or None
        The part's own inspection thresholds (the plan's ``inspection``: some of
        ``extra_mm``, ``deform_mm``, ``min_area_mm2``), None where the plan gives none.
    """

    part: str
    grasp_name: str
    base_grasp: np.ndarray
    pass_direction_deg: float
    nominal_grasp: np.ndarray
    preset: str
    speed_mm_s: float
    fps: float
    mesh_sha256: str
    inspection: object = None

    def check_mesh(self, path) -> None:
        """PlanError unless the mesh file at `path` is the one the plan was made for."""
        digest = file_sha256(path)
        if digest != self.mesh_sha256:
            raise PlanError(f"the plan of part {self.part!r} was made for another mesh "
                            f"(sha256 {self.mesh_sha256[:12]}..., {Path(path).name} has "
                            f"{digest[:12]}...): plan the part again (flyscan plan)")


def turned_grasp(grasp, turn_deg: float, vertices) -> np.ndarray:
    """The grasp turned about z_T by `turn_deg` and centred again in x_T, y_T.

    Parameters
    ----------
    grasp : (4, 4) array_like
        ^T X_P before the turn, mm.
    turn_deg : float
        Turn about z_T, degrees (right-handed).
    vertices : (V, 3) array_like
        The part's vertices in {P}, mm: the turned part's bounding box is centred under the
        TCP in x_T and y_T (its z_T span is unchanged).

    Returns
    -------
    (4, 4) float64
        ^T X_P.
    """
    grasp = check_rigid(grasp)
    a = np.radians(float(turn_deg))
    turn = np.eye(4)
    turn[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    out = turn @ grasp
    v = np.asarray(vertices, dtype=np.float64) @ out[:3, :3].T + out[:3, 3]
    out[:2, 3] -= (v[:, :2].min(axis=0) + v[:, :2].max(axis=0)) / 2.0
    return out


def file_sha256(path) -> str:
    """Hex SHA-256 of a file's bytes (read in blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def load_scan_plan(path) -> ScanPlan:
    """Read a part's ``plan.json``.

    Raises
    ------
    PlanError
        Missing or unreadable file, another format, a plan without a chosen scan (every
        candidate failed), a matrix that is not rigid, or a nominal grasp that its base
        grasp and turn do not give (checked when `ScanPlan.check_mesh` holds the vertices'
        file; here only the matrices' shapes and rigidity).
    """
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except FileNotFoundError:
        raise PlanError(f"plan file not found: {p}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise PlanError(f"cannot read plan file {p}: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != PLAN_FORMAT:
        found = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise PlanError(f"{p} is not a scan plan (format {found!r}, expected {PLAN_FORMAT!r})")
    chosen = data.get("chosen")
    if not isinstance(chosen, dict):
        raise PlanError(f"{p}: part {data.get('part')!r} has no chosen scan: "
                        f"{data.get('reason', 'no candidate succeeded')}")
    try:
        base = check_rigid(chosen["grasp"]["base"])
        nominal = check_rigid(chosen["nominal_grasp"])
        plan = ScanPlan(part=str(data["part"]), grasp_name=str(chosen["grasp"]["name"]),
                        base_grasp=base, pass_direction_deg=float(chosen["pass_direction_deg"]),
                        nominal_grasp=nominal, preset=str(chosen["preset"]),
                        speed_mm_s=float(chosen["speed_mm_s"]), fps=float(chosen["fps"]),
                        mesh_sha256=str(data["mesh_sha256"]),
                        inspection=_inspection(data.get("inspection"), p))
    except (KeyError, TypeError, ValueError) as exc:
        raise PlanError(f"{p}: a scan plan needs part, mesh_sha256 and chosen (grasp name and "
                        f"base, pass_direction_deg, nominal_grasp, preset, speed_mm_s, fps): "
                        f"{type(exc).__name__}: {exc}") from None
    if not (np.isfinite(plan.speed_mm_s) and plan.speed_mm_s > 0 and np.isfinite(plan.fps)
            and plan.fps > 0 and np.isfinite(plan.pass_direction_deg)):
        raise PlanError(f"{p}: speed_mm_s and fps must be positive and the turn finite")
    return plan


def _inspection(data, path):
    """A plan's ``inspection`` thresholds (``InspectionParams``), None where it has none."""
    if data is None:
        return None
    from scanner_core.inspection import InspectionParams
    try:
        return InspectionParams.from_dict(data)
    except ValueError as exc:
        raise PlanError(f"{path}: inspection: {exc}") from None


def check_plan_grasp(plan: ScanPlan, vertices) -> None:
    """PlanError unless the plan's nominal grasp is its base grasp turned by its pass
    direction (`turned_grasp`) for a part of these vertices (mm, {P})."""
    expected = turned_grasp(plan.base_grasp, plan.pass_direction_deg, vertices)
    if not np.allclose(expected, plan.nominal_grasp, atol=_GRASP_TOL_MM):
        raise PlanError(f"the plan of part {plan.part!r}: its nominal_grasp is not its base "
                        f"grasp turned {plan.pass_direction_deg:g} degrees about z_T")


def too_few_profiles(part, speed_mm_s: float, fps: float) -> str | None:
    """Why a pass at ``speed_mm_s`` (mm/s) and ``fps`` (frames/s) cannot scan ``part`` (a
    ``scanner_core.cad.PartModel``; it moves along y_T through the sheet): its frames are
    ``speed_mm_s / fps`` mm apart, too far for ``MIN_PROFILES`` profiles over the part's
    extent along y_T. None when they are near enough."""
    spacing = speed_mm_s / fps
    length = float(part.extents_t[1])
    if length / spacing >= MIN_PROFILES:
        return None
    need = MIN_PROFILES * speed_mm_s / length
    return (f"at {speed_mm_s:g} mm/s and {fps:g} fps the frames are {spacing:.3g} mm apart, "
            f"too few for the part's {length:.1f} mm along the pass (at least {MIN_PROFILES} "
            f"profiles): raise --fps to {need:.3g} or more, or lower --speed")
