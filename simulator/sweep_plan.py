"""A sweep of the scan simulator (``simulator.virtual_setup``), checked and laid out.

:func:`plan_sweep` finds the steps whose light plane meets the part (Eq. 4), fits the line's
fan of rays to the part, refuses a light source or viewpoint inside the part or passing
through it, and moves everything into the frame the rays are cast in (the part's, relative to
its intersector's centre): a :class:`SweepPlan`, which the sweep (``simulator.sweep_cast``)
and its cloud (``simulator.sweep_cloud``) share.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from scanner_core.geometry import apply_transform, check_rigid, unit
from simulator.parts import Part
from simulator.raycast import Intersector
from simulator.sweep_setup import MAIN_VIEW, SetupError, VirtualSetup

__all__ = ["SweepPlan", "plan_sweep", "MAX_RAYS"]

#: A sweep casting more rays than this is refused: its cloud would not fit in memory, and a
#: step size typed in metres instead of millimetres should fail at once, not after an hour.
MAX_RAYS = 100_000_000
# Directions in which `_check_paths` probes whether a viewpoint is inside the part: three,
# far from each other and from the axes (rays along a face's plane prove nothing).
_PROBES = unit(np.array([[0.57, 0.61, 0.55], [-0.7, 0.1, -0.71], [0.05, -0.9, 0.43]]))


@dataclass(frozen=True)
class SweepPlan:
    """One sweep's geometry, checked, in the frame the rays are cast in: the part's frame
    relative to its intersector's centre (`Intersector.centre`).

    Attributes
    ----------
    fan : (R, 3) float64
        The line's unit ray directions in the setup frame.
    first, last : int
        Step numbers swept, inclusive (``last < first`` when the sheet never meets the part).
    laser0, shift : (3,) float64
        Light source at step 0 and its move per step, mm.
    viewpoints : tuple of (str, (3,) float64)
        The camera (`MAIN_VIEW`) first, then the setup's extra views, at step 0.
    fan64, fan32 : (R, 3)
        The ray directions in the part frame.
    normals, offsets : (F, 3), (F,) float64
        The part's face planes (`Intersector.face_planes`).
    pose : (4, 4) float64
        The part's pose in the setup frame (^T X_P), checked rigid.
    centre : (3,) float64
        The intersector's centre in the part's frame, mm.
    """

    fan: np.ndarray
    first: int
    last: int
    laser0: np.ndarray
    shift: np.ndarray
    viewpoints: tuple
    fan64: np.ndarray
    fan32: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray
    pose: np.ndarray
    centre: np.ndarray

    @property
    def steps(self) -> np.ndarray:
        """(S,) int64: the step numbers swept."""
        return np.arange(self.first, self.last + 1, dtype=np.int64)

    @property
    def rays(self) -> int:
        """Rays the sweep casts."""
        return max(self.last - self.first + 1, 0) * len(self.fan)

    @cached_property
    def to_setup(self) -> tuple[np.ndarray, np.ndarray]:
        """(3, 3) and (3,) float64: ``x_setup = rot @ x + trans`` for x in the sweep's frame
        (the part's, relative to `centre`)."""
        rot = np.array(self.pose[:3, :3])
        return rot, rot @ self.centre + self.pose[:3, 3]



def plan_sweep(part: Part, setup: VirtualSetup, *, pose: np.ndarray | None = None,
               max_rays: int = MAX_RAYS) -> SweepPlan:
    """Check a sweep and lay it out in the part's frame (see `predict_cloud`).

    Raises
    ------
    SetupError
        As `predict_cloud`.
    """
    try:
        pose = part.grasp if pose is None else check_rigid(pose)
    except ValueError as exc:
        raise SetupError(f"`pose`: {exc}") from None
    vertices = apply_transform(pose, part.vertices)  # the fan and the steps need its extremes
    first, last = _step_range(setup, vertices)
    lines = max(last - first + 1, 0)
    if lines * setup.rays_per_line > max_rays:
        raise SetupError(f"the sweep would cast {lines * setup.rays_per_line:.3g} rays ({lines} "
                         f"lines of {setup.rays_per_line}), more than {max_rays:.3g}: use a "
                         f"larger step ({setup.step_mm:g} mm now) or fewer rays per line")
    fan = _fan(setup, vertices) if setup.fan is None else setup.fan
    ix = part.intersector
    inv = np.linalg.inv(pose)
    rot = inv[:3, :3]
    fan_p = unit(fan @ rot.T)
    normals, offsets = ix.face_planes
    viewpoints = ((MAIN_VIEW, setup.camera),) + setup.views
    plan = SweepPlan(
        fan=fan, first=first, last=max(last, first - 1),
        laser0=apply_transform(inv, setup.laser) - ix.centre,
        shift=rot @ (setup.step_mm * setup.motion),
        viewpoints=tuple((name, apply_transform(inv, p) - ix.centre) for name, p in viewpoints),
        fan64=fan_p, fan32=fan_p.astype(np.float32), normals=normals, offsets=offsets,
        pose=pose, centre=ix.centre)
    if last >= first:
        _check_paths(part, ix, plan)
    return plan


def _fan(setup: VirtualSetup, vertices: np.ndarray) -> np.ndarray:
    """The line's rays: the depth-buffer line perpendicular to the central ray, in the light
    plane (the plane through the source across the motion), just covering the part."""
    m = setup.motion
    size = float(np.ptp(vertices, axis=0).max())
    aim = (vertices.min(axis=0) + vertices.max(axis=0)) / 2.0 - setup.laser
    aim -= (aim @ m) * m
    if np.linalg.norm(aim) <= 1e-9 * max(size, 1.0):
        raise SetupError("the light source lies on the part's axis along the motion: its light "
                         "plane has no direction towards the part")
    central = unit(aim)
    across = unit(np.cross(central, m))
    rel = vertices - setup.laser
    depth = rel @ central
    if depth.min() <= 0:
        raise SetupError(
            "the part is not wholly in front of the light source (it would need a fan of 180 "
            f"degrees or more): the source at {np.round(setup.laser, 3).tolist()} mm is level "
            "with or inside the part's extent; move it away from the part")
    w = (rel @ across) / depth
    return unit(central + np.linspace(w.min(), w.max(), setup.rays_per_line)[:, None] * across)


def _step_range(setup: VirtualSetup, vertices: np.ndarray) -> tuple[int, int]:
    """First and last step whose light plane meets the part (Eq. 4: y + NmSt * StRs).

    NmSt is any integer: a setup given where it stands, its light plane already in or past
    the part at step 0, sweeps the part with negative steps too.
    """
    along = vertices @ setup.motion - setup.laser @ setup.motion
    # Python floats: a step in the denormals overflows to inf instead of warning.
    lo, hi = float(along.min()) / setup.step_mm, float(along.max()) / setup.step_mm
    # The PLY file stores the step as int32.
    if not (np.isfinite(lo) and np.isfinite(hi)) or max(abs(lo), abs(hi)) > 2 ** 31 - 2:
        raise SetupError(f"`step_mm` {setup.step_mm:g} is too small: the part lies up to "
                         f"{max(abs(lo), abs(hi)):.3g} steps from the light source at step 0, "
                         "more than int32 step numbers hold; use a larger step, or start the "
                         "setup nearer the part")
    return int(np.ceil(lo)), int(np.floor(hi))


def _check_paths(part: Part, ix: Intersector, plan: SweepPlan) -> None:
    """Refuse a light source or viewpoint that is inside the part, or passes through it.

    One Embree call for every path: its segment from the first step to the last, and three
    probes from its first position. Only when two probes of a position hit the part does the
    mesh's closure and orientation decide whether it is inside (an open mesh has no inside).
    """
    named = (("light source", plan.laser0),) + plan.viewpoints
    start = np.array([p for _, p in named]) + plan.first * plan.shift + ix.centre
    path = (plan.last - plan.first) * plan.shift
    length = float(np.linalg.norm(path))
    n = len(named)
    origins = np.concatenate([start, np.repeat(start, len(_PROBES), axis=0)])
    directions = np.concatenate([np.broadcast_to(path if length > 0 else _PROBES[0], (n, 3)),
                                 np.tile(_PROBES, (n, 1))])
    dist, face = ix.first_hit(origins, directions)
    probe_faces = face[n:].reshape(n, len(_PROBES))
    for i, (what, _) in enumerate(named):
        if length > 0 and dist[i] <= length:
            raise SetupError(f"the {what} passes through the part during the sweep (steps "
                             f"{plan.first} to {plan.last}): move it away from the part")
        hit = probe_faces[i] >= 0
        normals, _ = ix.face_planes
        along = np.einsum("ij,ij->i", normals[probe_faces[i][hit]], _PROBES[hit])
        # From inside a closed surface every ray leaves through a face that points the way the
        # ray goes (outward normals; trimesh's volume is negative for an inward-wound mesh).
        # The mesh's closure (trimesh, built only now) is asked only when probes could say so.
        if max(np.count_nonzero(along > 0), np.count_nonzero(along < 0)) < 2:
            continue
        if not part.mesh.is_watertight:
            continue
        outward = 1.0 if part.mesh.volume >= 0 else -1.0
        if np.count_nonzero(outward * along > 0) >= 2:
            raise SetupError(f"the {what} is inside the part at step {plan.first}")
