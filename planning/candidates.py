"""A part's candidate scans: the grasps it may be held by, the turns about z_T it may be
carried through the sheet at, and the pass presets.

Grasps: the centred and the flat grasp (``scanner_core.cad``), and the part lying on one of
its stable resting faces, as a suction cup picks it from a flat bin: trimesh's
``compute_stable_poses`` (the faces of its convex hull over which its centre of mass stands),
the likeliest first. Held from above, the face it lay on hangs toward the sensor (along +z_T). A grasp that turns the part the way another
already does (the same face toward the sensor) is kept once, under its first name.

Turns: ``0, step, 2 step, ...`` below 180 degrees (a turn of 180 reverses the pass, which the
scanner sees nearly alike). Each candidate's nominal grasp is
``scanner_core.scanplan.turned_grasp`` of its grasp and turn; one that does not fit the
inspection volume is left out with the reason.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import QhullError

from scanner_core.cad import PartError, centred_grasp, check_fits, flat_grasp
from scanner_core.scanplan import turned_grasp

__all__ = ["Candidate", "PRESET_NAMES", "base_grasps", "resting_grasps", "candidates",
           "turns"]

#: The pass presets a plan chooses from (``simulator.cell.PASS_PRESETS``), fastest first.
PRESET_NAMES = ("fast", "default", "slow")
# Two grasps show the sensor the same face when their +z_T directions in {P} agree this well.
_SAME_FACE_COS = np.cos(np.radians(2.0))


@dataclass(frozen=True)
class Candidate:
    """One candidate scan of a part.

    Attributes
    ----------
    grasp : str
        ``centred``, ``flat`` or ``resting-K``.
    base : (4, 4) float64
        ^T X_P of the grasp before the turn, mm.
    turn_deg : float
        Pass direction: turn about z_T, degrees.
    preset : str
        One of `PRESET_NAMES`.
    nominal : (4, 4) float64
        ^T X_P the scan registers against (`turned_grasp`).
    """

    grasp: str
    base: np.ndarray
    turn_deg: float
    preset: str
    nominal: np.ndarray

    def key(self) -> dict:
        """JSON-safe identity of the candidate (what its result is cached under)."""
        return {"grasp": self.grasp, "base": np.round(self.base, 9).tolist(),
                "turn_deg": float(self.turn_deg), "preset": self.preset}

    @property
    def label(self) -> str:
        return f"{self.grasp} turned {self.turn_deg:g} deg, {self.preset}"


def turns(step_deg: float) -> list[float]:
    """Turns about z_T, degrees: ``0, step, ...`` below 180. ValueError unless 0 < step <= 180."""
    if not (np.isfinite(step_deg) and 0 < step_deg <= 180):
        raise ValueError(f"the turn step must be in (0, 180] degrees, got {step_deg}")
    return [float(t) for t in np.arange(0.0, 180.0 - 1e-9, step_deg)]


def resting_grasps(mesh: trimesh.Trimesh, *, count: int = 3,
                   center_mass=None) -> list[np.ndarray]:
    """The grasps of a part lying on its `count` likeliest stable resting faces.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part, mm, in {P}.
    count : int
        Faces kept at most.
    center_mass : (3,) array_like, optional
        The part's centre of mass in {P}, mm; default the hull's vertices' mean.

    Returns
    -------
    list of (4, 4) float64
        ^T X_P: the face's outward normal along +z_T (toward the sensor), centred as by
        ``scanner_core.cad.centred_grasp``. Likeliest face first (trimesh's
        ``compute_stable_poses``: the share of the directions the part may fall from that
        end on the face, which grows with its size).
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    try:
        if center_mass is None:
            center_mass = mesh.convex_hull.vertices.mean(axis=0)
        poses, chances = trimesh.poses.compute_stable_poses(
            mesh, center_mass=np.asarray(center_mass, dtype=np.float64))
    except (QhullError, ValueError, IndexError):
        return []  # flat or degenerate: the centred and flat grasps remain
    # The resting face's outward normal in {P}: it points down (-z) in the pose's world.
    normals = [pose[:3, :3].T @ np.array([0.0, 0.0, -1.0])
               for pose, chance in zip(poses, chances) if chance > 0]
    return [_face_down_grasp(v, n) for n in normals[:max(0, int(count))]]


def base_grasps(mesh: trimesh.Trimesh, *, resting: int = 3,
                center_mass=None) -> list[tuple[str, np.ndarray]]:
    """The named grasps of a part (its mesh, mm, in {P}): centred, flat, then ``resting-K``
    (`resting_grasps`), each kept once per face shown to the sensor. (name, (4, 4) ^T X_P)
    pairs, mm."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    named = [("centred", centred_grasp(vertices)), ("flat", flat_grasp(vertices))]
    named += [(f"resting-{k + 1}", g) for k, g in
              enumerate(resting_grasps(mesh, count=resting, center_mass=center_mass))]
    kept: list[tuple[str, np.ndarray]] = []
    for name, grasp in named:
        toward = grasp[2, :3]  # the {P} direction that hangs along +z_T
        if not any(toward @ other[2, :3] > _SAME_FACE_COS for _, other in kept):
            kept.append((name, grasp))
    return kept


def candidates(part, *, turn_step_deg: float = 90.0, presets=PRESET_NAMES,
               resting: int = 3) -> tuple[list[Candidate], list[dict]]:
    """Every candidate scan of `part` (``scanner_core.cad.PartModel``) and those left out.

    Returns
    -------
    kept : list of Candidate
    left_out : list of dict
        ``{"grasp", "turn_deg", "reason"}`` of grasps and turns that do not fit the volume.
    """
    unknown = [p for p in presets if p not in PRESET_NAMES]
    if unknown or not presets:
        raise ValueError(f"presets must be among {', '.join(PRESET_NAMES)}, got {list(presets)}")
    center = _center_mass(part)
    kept, left_out = [], []
    for name, base in base_grasps(part.mesh, resting=resting, center_mass=center):
        for turn in turns(turn_step_deg):
            nominal = turned_grasp(base, turn, part.vertices)
            try:
                _check_fits_at(part, nominal)
            except PartError as exc:
                left_out.append({"grasp": name, "turn_deg": turn, "reason": str(exc)})
                continue
            kept += [Candidate(name, base, turn, preset, nominal) for preset in presets]
    return kept, left_out


def _check_fits_at(part, nominal) -> None:
    """``check_fits`` of the part held at `nominal` as its nominal grasp (no misplacement's
    allowance into the gripper)."""
    from dataclasses import replace

    check_fits(replace(part, grasp=nominal))


def _center_mass(part):
    """The part's centre of mass in {P} (mm) when its mesh is closed, else None."""
    mesh = part.mesh
    if mesh.is_watertight and mesh.volume > 0:
        return np.asarray(mesh.center_mass, dtype=np.float64)
    return None


def _face_down_grasp(v, normal) -> np.ndarray:
    """^T X_P with the outward `normal` along +z_T, centred (``centred_grasp``)."""
    z = np.asarray(normal, dtype=np.float64)
    x = np.cross([0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    turn = np.eye(4)
    turn[:3, :3] = np.stack([x, y, z])  # rows: {P} directions of x_T, y_T, z_T
    return centred_grasp(v @ turn[:3, :3].T) @ turn
