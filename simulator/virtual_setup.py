"""The paper's scan simulator (section III): a virtual light source and camera swept over a part.

The light source fires a fan of rays in its light plane; each ray's first hit on the CAD
model is a candidate point, kept when the camera sees it (the visibility check). The setup,
not the mesh, moves: at step ``n`` the light source and the camera stand at their step-0
positions plus ``n * step_mm`` along the motion axis (the paper's Eq. 4, with the depth-buffer
line's rays), and the steps run over the whole part. The only inputs are the two positions
and the two densities (step size and rays per line).

Frames: everything is given and returned in one *setup frame* in which the part is fixed,
{T} in the CLI (the gripper frame: the part hangs along +z_T, the setup moves along +y_T
relative to it). The part's pose ^T X_P places the mesh in it; the rays are cast in the
part's own frame, so one Embree scene per part serves every grasp and misplacement.

A point is kept when the light source lights it (first hit), the camera stands on the lit
side of its surface (no point from the back side) and nothing on the mesh lies between the
camera and the point (Embree's occlusion query). The camera's field of view and the stripe's
image are not modelled here: `simulator.render` does that for whole frames.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from scanner_core.geometry import (apply_transform, base_to_tcp, check_rigid,
                                   reflection_matrix, unit)
from scanner_core.ply import write_ply
from simulator import _sweep
from simulator.parts import Part
from simulator.raycast import SURFACE_TOL_MM, Intersector

__all__ = ["SetupError", "VirtualSetup", "PredictedCloud", "SweepPlan", "predict_cloud",
           "plan_sweep", "reference_setup",
           "save_predicted_cloud", "prepare", "warm_up", "DEFAULT_STEP_MM", "DEFAULT_RAYS_PER_LINE", "MAX_RAYS"]

DEFAULT_STEP_MM = 0.5
DEFAULT_RAYS_PER_LINE = 1000
#: A sweep casting more rays than this is refused: its cloud would not fit in memory, and a
#: step size typed in metres instead of millimetres should fail at once, not after an hour.
MAX_RAYS = 100_000_000
# Rays per Embree call: large enough to hide the per-call cost (12-26 us, NOTES.md), small
# enough that two threads share the work evenly.
_CHUNK_RAYS = 1 << 16
MAIN_VIEW = "camera"


class SetupError(ValueError):
    """The virtual setup cannot sweep this part: a bad density, or a source or camera that
    stands in, behind or level with the part."""


@dataclass(frozen=True)
class VirtualSetup:
    """The paper's inputs: where the light source and the camera stand, and the densities.

    Attributes
    ----------
    laser : (3,) float64
        Light source position at step 0, mm, in the setup frame.
    camera : (3,) float64
        Camera position (projection centre) at step 0, mm.
    step_mm : float
        Step size (the paper's StRs): how far the setup moves between two lines, mm.
    rays_per_line : int
        Rays in each line's fan (the depth-buffer resolution).
    views : tuple of (str, (3,) float64)
        Further viewpoints at step 0 (the camera reflected in each mirror, say): each point
        records whether it sees them; they do not filter the cloud.
    motion : (3,) float64
        Unit direction the setup moves along, relative to the part (+y of the setup frame).
    fan : (R, 3) float64, optional
        The line's ray directions, unit vectors across the motion (R = `rays_per_line`).
        By default the fan is fitted to the part: aimed at its centre, just covering it. Fix
        it (`with_fan`) to sweep several meshes of one part with the very same rays.
    """

    laser: np.ndarray
    camera: np.ndarray
    step_mm: float = DEFAULT_STEP_MM
    rays_per_line: int = DEFAULT_RAYS_PER_LINE
    views: tuple = ()
    motion: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    fan: np.ndarray | None = None

    def __post_init__(self):
        for name in ("laser", "camera", "motion"):
            value = np.array(getattr(self, name), dtype=np.float64)
            if value.shape != (3,) or not np.all(np.isfinite(value)):
                raise SetupError(f"`{name}` must be 3 finite coordinates (mm), got "
                                 f"{getattr(self, name)!r}")
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        if not np.isclose(np.linalg.norm(self.motion), 1.0):
            raise SetupError(f"`motion` must be a unit vector, got {self.motion.tolist()}")
        step = float(self.step_mm)
        if not (np.isfinite(step) and step > 0):
            raise SetupError(f"`step_mm` must be a positive length in mm, got {self.step_mm!r}")
        object.__setattr__(self, "step_mm", step)
        rays = self.rays_per_line
        if isinstance(rays, bool) or int(rays) != rays or rays < 2:
            raise SetupError(f"`rays_per_line` must be a whole number >= 2, got {rays!r}")
        object.__setattr__(self, "rays_per_line", int(rays))
        views = []
        for name, position in self.views:
            p = np.array(position, dtype=np.float64)
            if p.shape != (3,) or not np.all(np.isfinite(p)) or name == MAIN_VIEW:
                raise SetupError(f"view {name!r} needs a name other than {MAIN_VIEW!r} and 3 "
                                 f"finite coordinates, got {position!r}")
            p.setflags(write=False)
            views.append((str(name), p))
        object.__setattr__(self, "views", tuple(views))
        if self.fan is not None:
            fan = np.array(self.fan, dtype=np.float64)
            if (fan.shape != (self.rays_per_line, 3) or not np.all(np.isfinite(fan))
                    or not np.allclose(np.linalg.norm(fan, axis=1), 1.0)
                    or np.abs(fan @ self.motion).max() > 1e-9):
                raise SetupError(f"`fan` must be {self.rays_per_line} unit directions across "
                                 f"the motion, got an array of shape {fan.shape}")
            fan.setflags(write=False)
            object.__setattr__(self, "fan", fan)

    def with_fan(self, fan) -> "VirtualSetup":
        """The same setup with the line's rays fixed to `fan` ((R, 3) unit directions)."""
        return replace(self, fan=fan, rays_per_line=len(fan))

    def laser_at(self, step) -> np.ndarray:
        """Light source position at step number(s) `step`: (3,) or (N, 3) float64, mm."""
        return self._moved(self.laser, step)

    def camera_at(self, step) -> np.ndarray:
        """Camera position at step number(s) `step`: (3,) or (N, 3) float64, mm."""
        return self._moved(self.camera, step)

    def _moved(self, position, step) -> np.ndarray:
        return position + np.multiply.outer(np.asarray(step, np.float64),
                                            self.step_mm * self.motion)


@dataclass(frozen=True)
class PredictedCloud:
    """What the scanner should see of the part: the simulator's output.

    Attributes
    ----------
    points : (N, 3) float64
        mm, in the setup frame, on the mesh surface.
    normals : (N, 3) float64
        Unit surface normals at the points, pointing to the side the light comes from.
    step : (N,) int32
        Step number of each point: the light source stood at ``setup.laser_at(step)``.
    ray : (N,) int32
        Index of the point's ray in its line's fan (`fan`).
    face : (N,) int64
        Mesh face of each point.
    seen : dict of str to (N,) bool
        For each of ``setup.views``, whether that viewpoint sees the point too.
    fan : (R, 3) float64
        Unit directions of one line's rays, in the setup frame (the same at every step).
    steps : (int, int)
        First and last step number swept (inclusive); ``(0, -1)`` when none.
    rays_cast, first_hits, facing : int
        Rays fired; rays that hit the part; hits with the camera on the lit side.
    elapsed_s : float
        Wall time of the sweep (not of building the part's intersector).
    setup : VirtualSetup
    pose : (4, 4) float64
        The part's pose in the setup frame the sweep used.
    """

    points: np.ndarray
    normals: np.ndarray
    step: np.ndarray
    ray: np.ndarray
    face: np.ndarray
    seen: dict
    fan: np.ndarray
    steps: tuple[int, int]
    rays_cast: int
    first_hits: int
    facing: int
    elapsed_s: float
    setup: VirtualSetup
    pose: np.ndarray

    def __len__(self) -> int:
        return len(self.points)

    @property
    def rays_per_second(self) -> float:
        return self.rays_cast / self.elapsed_s if self.elapsed_s > 0 else float("nan")

    def summary(self) -> dict:
        """Counts and rates, JSON-ready."""
        return {"points": len(self), "rays_cast": self.rays_cast, "first_hits": self.first_hits,
                "facing_camera": self.facing, "steps": list(self.steps),
                "elapsed_s": round(self.elapsed_s, 6),
                "mrays_per_s": round(self.rays_per_second / 1e6, 3)}


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

    @property
    def steps(self) -> np.ndarray:
        """(S,) int64: the step numbers swept."""
        return np.arange(self.first, self.last + 1, dtype=np.int64)

    @property
    def rays(self) -> int:
        """Rays the sweep casts."""
        return max(self.last - self.first + 1, 0) * len(self.fan)


def predict_cloud(part: Part, setup: VirtualSetup, *, pose: np.ndarray | None = None,
                  threads: int = 2, max_rays: int = MAX_RAYS,
                  progress=None) -> PredictedCloud:
    """Sweep the virtual setup over a part and return the cloud the scanner should see.

    Parameters
    ----------
    part : Part
        The CAD part; its cached `Part.intersector` is built on first use.
    setup : VirtualSetup
        Positions at step 0 and densities, in the setup frame.
    pose : (4, 4) array_like, optional
        The part's pose in the setup frame (^T X_P, mm); default the part's nominal grasp.
    threads : int
        Worker threads (Embree and the kernels release the GIL). The result does not depend
        on it.
    max_rays : int
        Refuse sweeps casting more rays than this.
    progress : callable, optional
        Called as ``progress(rays_done, rays_total)`` as the sweep goes.

    Returns
    -------
    PredictedCloud
        Possibly empty (no ray hit the part, or the camera saw none of the hits): check
        `first_hits` and ``len()``.

    Raises
    ------
    SetupError
        The light source or the camera stands inside the part or passes through it during
        the sweep; the part is not wholly in front of the light source; the sweep would cast
        more than `max_rays` rays.
    """
    t0 = time.perf_counter()
    if int(threads) < 1:
        raise SetupError(f"`threads` must be >= 1, got {threads!r}")
    plan = plan_sweep(part, setup, pose=pose, max_rays=max_rays)
    ix = part.intersector
    steps = plan.steps
    # Several chunks per thread even for small sweeps, so both threads finish together.
    per_chunk = max(1, min(_CHUNK_RAYS // setup.rays_per_line,
                           -(-len(steps) // (4 * int(threads)))))
    chunks = [steps[i:i + per_chunk] for i in range(0, len(steps), per_chunk)]
    parts, done = [], 0
    with ThreadPoolExecutor(int(threads), thread_name_prefix="sweep") as pool:
        for chunk, result in zip(chunks, pool.map(lambda c: _sweep_chunk(ix, plan, c), chunks)):
            parts.append(result)
            done += len(chunk) * len(plan.fan)
            if progress is not None:
                progress(done, plan.rays)
    return _assemble(parts, setup, ix, plan, time.perf_counter() - t0)


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
    # The fan and the steps depend only on the part's extremes: its hull will do.
    vertices = apply_transform(pose, part.hull_vertices)
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
        pose=pose)
    if last >= first:
        _check_path(part, ix, plan.laser0, plan.shift, first, last, "light source")
        for name, view0 in plan.viewpoints:
            _check_path(part, ix, view0, plan.shift, first, last, name)
    return plan


def prepare(part: Part) -> float:
    """Build what a part's sweeps share (its intersector and hull) now; returns the seconds
    it took (nothing the second time)."""
    t0 = time.perf_counter()
    part.intersector  # noqa: B018 - cached properties: computed once, kept on the part
    part.hull_vertices  # noqa: B018
    return time.perf_counter() - t0


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel of the sweep, on a small cube, so
    that the first real sweep's time is the sweep's own."""
    import trimesh

    cube = Part(name="warm-up", mesh=trimesh.creation.box(extents=(10.0, 10.0, 10.0)),
                source="procedural:cube", units="mm", grasp=np.eye(4))
    setup = VirtualSetup(laser=[0.0, -10.0, 100.0], camera=[0.0, 40.0, 100.0], step_mm=1.0,
                         rays_per_line=64, views=(("other", [0.0, 40.0, 90.0]),))
    predict_cloud(cube, setup, threads=1)


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

    The setup moves forwards from step 0: a light plane already past the part's near end at
    step 0 would miss part of it, and is refused.
    """
    along = vertices @ setup.motion - setup.laser @ setup.motion
    # Python floats: a step in the denormals overflows to inf instead of warning.
    lo, hi = float(along.min()) / setup.step_mm, float(along.max()) / setup.step_mm
    if not (np.isfinite(lo) and np.isfinite(hi)) or max(abs(lo), abs(hi)) > 2 ** 62:
        raise SetupError(f"`step_mm` {setup.step_mm:g} is too small for a part "
                         f"{np.ptp(along):.3g} mm long")
    if lo < 0:
        raise SetupError(
            f"at step 0 the light plane is already {-along.min():.3f} mm past the part's near "
            "end (the setup moves forwards along the motion from step 0): start the light "
            "source and camera before the part")
    return int(np.ceil(lo)), int(np.floor(hi))


def _sweep_chunk(ix: Intersector, sweep: SweepPlan, steps: np.ndarray) -> dict:
    """Cast the lines of `steps`: lit points, then the visibility check from each viewpoint."""
    n = len(steps) * len(sweep.fan64)
    origins = np.empty((n, 3), np.float32)
    directions = np.empty((n, 3), np.float32)
    _sweep.fan_rays(sweep.laser0, sweep.shift, steps, sweep.fan32, origins, directions)
    face = ix.cast_faces(origins, directions)
    del origins, directions
    arrays = (np.empty(n, np.int64), np.empty((n, 3)), np.empty((n, 3)), np.empty(n, np.int64),
              np.empty(n, np.int64))
    k = _sweep.lit_points(sweep.laser0, sweep.shift, steps, sweep.fan64, face, sweep.normals,
                          sweep.offsets, *arrays)
    index, points, normals, faces, point_steps = (a[:k] for a in arrays)
    out = {"hits": int(np.count_nonzero(face >= 0)), "facing": 0, "seen": {}}
    for name, view0 in sweep.viewpoints:
        seen, facing = _visible_from(ix, sweep, view0, point_steps, points, normals)
        if name == MAIN_VIEW:
            out["facing"] = facing
            k = _sweep.keep_rows(seen, index, points, normals, faces, point_steps)
            index, points, normals, faces, point_steps = (
                a[:k] for a in (index, points, normals, faces, point_steps))
        else:
            out["seen"][name] = seen
    # Copies: views would keep the chunk's full-size buffers alive until the end.
    out.update(index=index.copy(), points=points.copy(), normals=normals.copy(),
               face=faces.copy(), step=point_steps.copy())
    out["seen"] = {name: seen.copy() for name, seen in out["seen"].items()}
    return out


def _visible_from(ix, sweep: SweepPlan, view0, point_steps, points, normals):
    """(K,) bool: the viewpoint sees each point; and how many points face it."""
    k = len(points)
    origins = np.empty((k, 3), np.float32)
    directions = np.empty((k, 3), np.float32)
    reach = np.empty(k, np.float32)
    chosen = np.empty(k, np.int64)
    m = _sweep.sight_rays(view0, sweep.shift, point_steps, points, normals, SURFACE_TOL_MM,
                          origins, directions, reach, chosen)
    seen = np.zeros(k, dtype=bool)
    if m:
        seen[chosen[:m]] = ~ix.occluded(origins[:m], directions[:m], reach[:m])
    return seen, m


def _assemble(parts, setup, ix, plan: SweepPlan, elapsed) -> PredictedCloud:
    pose = plan.pose
    rot = pose[:3, :3]
    n_rays = setup.rays_per_line

    def cat(key, shape, dtype):
        arrays = [p[key] for p in parts]
        return np.concatenate(arrays) if arrays else np.zeros(shape, dtype)

    points_p = cat("points", (0, 3), np.float64) + ix.centre
    # Each chunk numbers its rays from zero at a line's start: the ray in the fan is intact.
    index = cat("index", (0,), np.int64)
    seen = {name: (np.concatenate([p["seen"][name] for p in parts]) if parts
                   else np.zeros(0, bool)) for name, _ in setup.views}
    return PredictedCloud(
        points=apply_transform(pose, points_p),
        normals=cat("normals", (0, 3), np.float64) @ rot.T,
        step=cat("step", (0,), np.int64).astype(np.int32),
        ray=(index % n_rays).astype(np.int32),
        face=cat("face", (0,), np.int64),
        seen=seen, fan=plan.fan, steps=(plan.first, plan.last) if plan.rays else (0, -1),
        rays_cast=plan.rays,
        first_hits=sum(p["hits"] for p in parts), facing=sum(p["facing"] for p in parts),
        elapsed_s=elapsed, setup=setup, pose=pose)


def reference_setup(cell, *, step_mm: float = DEFAULT_STEP_MM,
                    rays_per_line: int = DEFAULT_RAYS_PER_LINE, laser=None, camera=None,
                    mirrors: bool = False) -> VirtualSetup:
    """The reference cell's light source and camera in {T}, at the start of its pass.

    Parameters
    ----------
    cell : simulator.cell.Cell
    step_mm, rays_per_line : float, int
        The densities.
    laser, camera : (3,) array_like, optional
        Positions in {T} at step 0 that replace the cell's.
    mirrors : bool
        Add the camera reflected in each of the cell's mirrors as the views ``left`` and
        ``right`` (the mirrors move with the setup).

    Returns
    -------
    VirtualSetup
        In {T}; it moves along +y_T, as the cell does relative to the part when the robot
        passes along +y_B.
    """
    pp = cell.pass_profile
    tcp_b = np.array([0.0, pp.start_y_mm, pp.height_mm])
    rot_b = cell.gripper_rotation_b
    cal = cell.calibration

    def to_t(point_b):
        return base_to_tcp(np.asarray(point_b, np.float64)[None], tcp_b, rot_b)[0]

    laser_t = to_t(cell.laser_origin_b) if laser is None else laser
    camera_t = to_t(cal.camera.origin) if camera is None else np.asarray(camera, np.float64)
    views = []
    if mirrors:
        # A mirror plane n . x = d in {B} is (R^T n) . x = d - n . tcp in {T}.
        for name, mirror in zip(("left", "right"), cal.mirrors):
            n_b, d_b = mirror.plane.normal, mirror.plane.offset
            flip = reflection_matrix(rot_b.T @ n_b, d_b - n_b @ tcp_b)
            views.append((name, apply_transform(flip, camera_t)))
    motion = unit(rot_b.T @ np.array([0.0, -1.0, 0.0]))  # the cell moves back along the pass
    return VirtualSetup(laser=laser_t, camera=camera_t, step_mm=step_mm,
                        rays_per_line=rays_per_line, views=tuple(views), motion=motion)


def _check_path(part: Part, ix: Intersector, start, shift, first: int, last: int,
                what: str) -> None:
    """Refuse a light source or camera that is inside the part, or passes through it.

    `start` and `shift` are relative to the intersector's centre, as in `SweepPlan`."""
    p0 = start + first * shift + ix.centre
    path = (last - first) * shift
    length = float(np.linalg.norm(path))
    if length > 0:
        dist, _ = ix.first_hit(p0[None], path[None])
        if dist[0] <= length:
            raise SetupError(f"the {what} passes through the part during the sweep (steps "
                             f"{first} to {last}): move it away from the part")
    if not part.mesh.is_watertight:
        return  # an open mesh has no inside
    probes = unit(np.array([[0.57, 0.61, 0.55], [-0.7, 0.1, -0.71], [0.05, -0.9, 0.43]]))
    dist, face = ix.first_hit(np.repeat(p0[None], 3, axis=0), probes)
    normals, _ = ix.face_planes
    # From inside a closed surface every ray leaves through a face that points the way the
    # ray goes (outward normals; trimesh's volume is negative for an inward-wound mesh).
    outward = 1.0 if part.mesh.volume >= 0 else -1.0
    inside = sum(f >= 0 and outward * (normals[f] @ d) > 0 for f, d in zip(face, probes))
    if inside >= 2:
        raise SetupError(f"the {what} is inside the part at step {first}")


def save_predicted_cloud(path, cloud: PredictedCloud, *, frame: str = "T") -> Path:
    """Write a predicted cloud as binary little-endian PLY (float32 x, y, z in mm).

    Per-vertex properties: ``step`` and ``ray`` (int32: the light source stood at
    ``laser + step * step_mm * motion``, the header's comments), ``nx, ny, nz`` (float32
    normals towards the light) and, for each extra view, ``seen_<name>`` (uint8).

    Returns
    -------
    pathlib.Path
    """
    s = cloud.setup
    fields = {"step": cloud.step, "ray": cloud.ray}
    fields.update({f"n{c}": cloud.normals[:, i].astype(np.float32) for i, c in enumerate("xyz")})
    fields.update({f"seen_{name}": seen.astype(np.uint8) for name, seen in cloud.seen.items()})

    def xyz(v):
        return " ".join(f"{x:.9g}" for x in v)

    comments = ["flyscan simulate", f"frame {frame}", "units mm",
                f"laser_step0 {xyz(s.laser)}", f"camera_step0 {xyz(s.camera)}",
                f"motion {xyz(s.motion)}", f"step_mm {s.step_mm:.9g}",
                f"rays_per_line {s.rays_per_line}", f"steps {cloud.steps[0]} {cloud.steps[1]}"]
    comments += [f"view_{name}_step0 {xyz(p)}" for name, p in s.views]
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return write_ply(path, cloud.points.astype(np.float32), fields=fields, comments=comments)
