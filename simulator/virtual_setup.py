"""The paper's scan simulator (section III): a virtual light source and camera swept over a part.

The light source fires a fan of rays in its light plane; each ray's first hit on the CAD
model is a candidate point, kept when the camera sees it (the visibility check). The setup,
not the mesh, moves: at step ``n`` the light source and the camera stand at their step-0
positions plus ``n * step_mm`` along the motion axis (the paper's Eq. 4, with the depth-buffer
line's rays). Eq. 4's step number is any integer: the sweep covers every step whose light
plane meets the part, negative ones included, wherever the user puts the setup at step 0.
The only inputs are the two positions and the two densities (step size and rays per line).

Frames: everything is given and returned in one *setup frame* in which the part is fixed,
{T} in the CLI (the gripper frame: the part hangs along +z_T, the setup moves along +y_T
relative to it). The part's pose ^T X_P places the mesh in it; the rays are cast in the
part's own frame, so one Embree scene per part serves every grasp and misplacement.

A point is kept when the light source lights it (first hit), the camera stands on the lit
side of its surface (no point from the back side) and nothing on the mesh lies between the
camera and the point (Embree's occlusion query). The camera's field of view and the stripe's
image are not modelled here: `simulator.render` does that for whole frames.

While it sweeps, a cloud keeps only each point's ray and face (8 bytes a point, see
`simulator._sweep`); its float64 arrays are computed on first use, and its PLY file is
written straight from the rays and faces, so writing millions of points costs one pass.
"""
from __future__ import annotations

import threading
import time
from bisect import bisect_left, bisect_right
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from scanner_core.geometry import (apply_transform, base_to_tcp, check_rigid,
                                   reflection_matrix, unit)
from scanner_core.ply import write_ply_rows
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
# enough that two threads share the work evenly and each thread's scratch (about 110 bytes a
# ray, reused from chunk to chunk) stays a few megabytes.
_CHUNK_RAYS = 1 << 16
# Clouds smaller than this are laid out by the calling thread alone: threads cost more.
_SERIAL_ROWS = 1 << 16
# Rows of a PLY file made at a time (about 4 MB): large enough that a write call costs
# nothing, small enough to stay in memory already in use. On the reference machine (a virtual
# machine) memory touched for the first time cost 0.3 to 3 ms a megabyte: more than the work
# done in it; a whole table of 3.8 M points (121 MB) took 0.05 to 0.35 s to allocate.
_PLY_BLOCK_ROWS = 1 << 17
# Directions in which `_check_paths` probes whether a viewpoint is inside the part: three,
# far from each other and from the axes (rays along a face's plane prove nothing).
_PROBES = unit(np.array([[0.57, 0.61, 0.55], [-0.7, 0.1, -0.71], [0.05, -0.9, 0.43]]))
MAIN_VIEW = "camera"


class SetupError(ValueError):
    """The virtual setup cannot sweep this part: a bad density, or a source or camera that
    stands in, or passes through, the part, or a source level with it."""


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


@dataclass(frozen=True, eq=False)
class PredictedCloud:
    """What the scanner should see of the part: the simulator's output.

    Attributes
    ----------
    points : (N, 3) float64
        mm, in the setup frame, on the mesh surface.
    normals : (N, 3) float64
        Unit surface normals at the points, pointing to the side the light comes from.
    step : (N,) int32
        Step number of each point (any integer, negative too): the light source stood at
        ``setup.laser_at(step)``.
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

    Notes
    -----
    The sweep keeps each point's ray and face only; `points`, `normals`, `step`, `ray` and
    `face` are computed from them, all at once, when one of them is first read, and kept.
    `save_predicted_cloud` needs none of them.
    """

    seen: dict
    fan: np.ndarray
    steps: tuple[int, int]
    rays_cast: int
    first_hits: int
    facing: int
    elapsed_s: float
    setup: VirtualSetup
    pose: np.ndarray
    # The points as the sweep kept them, chunk by chunk: (first step, (K,) int32 ray numbered
    # from that step's ray 0, (K,) int32 face), with the plan that lays them out.
    _hits: tuple = field(repr=False)
    _plan: "SweepPlan" = field(repr=False)
    _threads: int = field(default=1, repr=False)

    def __len__(self) -> int:
        return self._offsets[-1]

    @property
    def rays_per_second(self) -> float:
        return self.rays_cast / self.elapsed_s if self.elapsed_s > 0 else float("nan")

    @property
    def points(self) -> np.ndarray:
        return self._arrays[0]

    @property
    def normals(self) -> np.ndarray:
        return self._arrays[1]

    @property
    def step(self) -> np.ndarray:
        return self._arrays[2]

    @property
    def ray(self) -> np.ndarray:
        return self._arrays[3]

    @property
    def face(self) -> np.ndarray:
        return self._arrays[4]

    def summary(self) -> dict:
        """Counts and rates, JSON-ready."""
        return {"points": len(self), "rays_cast": self.rays_cast, "first_hits": self.first_hits,
                "facing_camera": self.facing, "steps": list(self.steps),
                "elapsed_s": round(self.elapsed_s, 6),
                "mrays_per_s": round(self.rays_per_second / 1e6, 3)}

    @cached_property
    def _offsets(self) -> list[int]:
        """Row of each chunk's first point, and the total."""
        return np.concatenate([[0], np.cumsum([len(ray) for _, ray, _ in self._hits],
                                              dtype=np.int64)]).tolist()

    @cached_property
    def _arrays(self) -> tuple:
        n = len(self)
        out = (np.empty((n, 3)), np.empty((n, 3)), np.empty(n, np.int32),
               np.empty(n, np.int32), np.empty(n, np.int64))
        self._plan.to_setup  # noqa: B018 - computed once, before the threads read it
        chunks = range(len(self._hits))
        if self._threads <= 1 or n < _SERIAL_ROWS:
            for i in chunks:
                self._emit(_sweep.emit_points, i, 0, n, *out)
        else:
            with ThreadPoolExecutor(self._threads, thread_name_prefix="emit") as pool:
                list(pool.map(lambda i: self._emit(_sweep.emit_points, i, 0, n, *out), chunks))
        return out

    def _ply_blocks(self, rows: int | None = None):
        """The PLY vertex table of `save_predicted_cloud`, in blocks of up to `rows` rows.

        A worker thread makes each block while the caller writes the one before, in two
        buffers: the whole table never exists at once. Each block is valid until the next is
        asked for. One (empty) block for an empty cloud.
        """
        dtype = np.dtype([(c, "<f4") for c in "xyz"] + [("step", "<i4"), ("ray", "<i4")]
                         + [(f"n{c}", "<f4") for c in "xyz"]
                         + [(f"seen_{name}", "u1") for name in self.seen])
        # The kernel writes the fixed fields through a view that skips the flags after them.
        fixed = np.dtype({"names": dtype.names[:8], "formats": [dtype[i] for i in range(8)],
                          "offsets": [dtype.fields[name][1] for name in dtype.names[:8]],
                          "itemsize": dtype.itemsize})
        n, offsets = len(self), self._offsets
        rows = max(1, _PLY_BLOCK_ROWS if rows is None else int(rows))
        buffers = [np.empty(min(rows, n), dtype) for _ in range(2)]
        self._plan.to_setup  # noqa: B018 - computed once, before the thread reads it

        def fill(which, lo):
            block = buffers[which][:min(rows, n - lo)]
            # The chunks that hold rows lo to lo + len(block).
            for i in range(max(bisect_right(offsets, lo) - 1, 0),
                           bisect_left(offsets, lo + len(block))):
                self._emit(_sweep.emit_rows, i, lo, lo + len(block), block.view(fixed))
            for name, seen in self.seen.items():
                block[f"seen_{name}"] = seen[lo:lo + len(block)]
            return block

        starts = range(0, max(n, 1), rows)
        with ThreadPoolExecutor(1, thread_name_prefix="ply") as pool:
            pending = pool.submit(fill, 0, 0)
            for b, _ in enumerate(starts):
                block = pending.result()
                if b + 1 < len(starts):
                    pending = pool.submit(fill, (b + 1) % 2, starts[b + 1])
                yield block

    def _emit(self, kernel, chunk: int, lo: int, hi: int, *out) -> None:
        """Run an emit kernel (`simulator._sweep`) over the rows of chunk `chunk` that fall in
        rows ``lo`` to ``hi`` of the cloud, into `out` (whose row 0 is the cloud's row `lo`)."""
        start, end = self._offsets[chunk], self._offsets[chunk + 1]
        a, b = max(lo, start) - start, min(hi, end) - start
        if a >= b:
            return
        plan = self._plan
        first, ray, face = self._hits[chunk]
        kernel(plan.laser0, plan.shift, first, plan.fan64, ray[a:b], face[a:b], plan.normals,
               plan.offsets, plan.to_setup[0], plan.to_setup[1], *out, start + a - lo)


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
    threads = int(threads)
    plan = plan_sweep(part, setup, pose=pose, max_rays=max_rays)
    ix = part.intersector
    n_rays = len(plan.fan)
    # Several chunks per thread even for small sweeps, so both threads finish together.
    lines = plan.last - plan.first + 1
    per_chunk = max(1, min(_CHUNK_RAYS // n_rays, -(-lines // (4 * threads))))
    starts = range(plan.first, plan.last + 1, per_chunk)
    local = threading.local()

    def sweep(first):
        scratch = getattr(local, "scratch", None)
        if scratch is None:  # one per thread, reused by all its chunks
            scratch = local.scratch = _Scratch(per_chunk * n_rays)
        return _sweep_chunk(ix, plan, first, min(per_chunk, plan.last + 1 - first), scratch)

    parts, done = [], 0
    with ThreadPoolExecutor(threads, thread_name_prefix="sweep") as pool:
        for result in pool.map(sweep, starts):
            parts.append(result)
            done += result["lines"] * n_rays
            if progress is not None:
                progress(done, plan.rays)
    return _assemble(parts, setup, plan, threads, time.perf_counter() - t0)


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


def prepare(part: Part) -> float:
    """Build what a part's sweeps share (its intersector and face planes) now; returns the
    seconds it took (nothing the second time)."""
    t0 = time.perf_counter()
    part.intersector.face_planes  # noqa: B018 - cached properties: computed once, kept
    return time.perf_counter() - t0


def warm_up() -> None:
    """Load every kernel of a sweep and of its output from numba's cache (compiling them the
    first time), on a tetrahedron, so that the first real sweep's time is the sweep's own.

    It takes the real code paths, so it loads exactly the signatures they use: a sweep
    without extra views and one with two (the mirrors), the cloud's arrays and its PLY rows.
    Most of its time is numba's own start-up, paid once by the first kernel of a process.
    """
    part = Part(name="warm-up", source="procedural:tetrahedron", units="mm", grasp=np.eye(4),
                vertices=np.array([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [0.0, 5.0, 0.0],
                                   [0.0, 0.0, 8.0]]),
                faces=np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [2, 0, 3]]))
    for views in ((), (("left", [-20.0, 40.0, 100.0]), ("right", [20.0, 40.0, 100.0]))):
        setup = VirtualSetup(laser=[0.0, -10.0, 100.0], camera=[0.0, 40.0, 100.0],
                             step_mm=2.0, rays_per_line=16, views=views)
        cloud = predict_cloud(part, setup, threads=1)
        cloud.points  # noqa: B018 - computes the arrays
        for _ in cloud._ply_blocks():
            pass


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


class _Scratch:
    """One thread's working arrays for chunks of up to `rays` rays, reused chunk after chunk
    (fresh memory costs more than the work done in it)."""

    def __init__(self, rays: int):
        self.origins = np.empty((rays, 3), np.float32)  # light rays, then sight rays
        self.directions = np.empty((rays, 3), np.float32)
        self.index = np.empty(rays, np.int64)
        self.points = np.empty((rays, 3))
        self.normals = np.empty((rays, 3))
        self.faces = np.empty(rays, np.int64)
        self.steps = np.empty(rays, np.int64)
        self.reach = np.empty(rays, np.float32)
        self.chosen = np.empty(rays, np.int64)


def _sweep_chunk(ix: Intersector, sweep: SweepPlan, first: int, lines: int,
                 scratch: _Scratch) -> dict:
    """Cast the lines of steps ``first`` to ``first + lines - 1``: lit points, then the
    visibility check from each viewpoint; returns the kept points' rays and faces."""
    steps = np.arange(first, first + lines, dtype=np.int64)
    n = lines * len(sweep.fan64)
    origins, directions = scratch.origins[:n], scratch.directions[:n]
    _sweep.fan_rays(sweep.laser0, sweep.shift, steps, sweep.fan32, origins, directions)
    face = ix.cast_faces(origins, directions)
    rows = (scratch.index[:n], scratch.points[:n], scratch.normals[:n], scratch.faces[:n],
            scratch.steps[:n])
    k = _sweep.lit_points(sweep.laser0, sweep.shift, steps, sweep.fan64, face, sweep.normals,
                          sweep.offsets, *rows)
    index, points, normals, faces, point_steps = (a[:k] for a in rows)
    out = {"lines": lines, "hits": int(np.count_nonzero(face >= 0)), "facing": 0, "seen": {}}
    for name, view0 in sweep.viewpoints:
        seen, facing = _visible_from(ix, sweep, view0, point_steps, points, normals, scratch)
        if name == MAIN_VIEW:
            out["facing"] = facing
            k = _sweep.keep_rows(seen, index, points, normals, faces, point_steps)
            index, points, normals, faces, point_steps = (
                a[:k] for a in (index, points, normals, faces, point_steps))
        else:
            out["seen"][name] = seen
    # Copies out of the scratch: 8 bytes a point, from which the rest is recomputed.
    out.update(first=first, ray=index.astype(np.int32), face=faces.astype(np.int32))
    return out


def _visible_from(ix, sweep: SweepPlan, view0, point_steps, points, normals, scratch):
    """(K,) bool: the viewpoint sees each point; and how many points face it."""
    k = len(points)
    origins, directions = scratch.origins[:k], scratch.directions[:k]
    reach, chosen = scratch.reach[:k], scratch.chosen[:k]
    m = _sweep.sight_rays(view0, sweep.shift, point_steps, points, normals, SURFACE_TOL_MM,
                          origins, directions, reach, chosen)
    seen = np.zeros(k, dtype=bool)
    if m:
        seen[chosen[:m]] = ~ix.occluded(origins[:m], directions[:m], reach[:m])
    return seen, m


def _assemble(parts, setup, plan: SweepPlan, threads: int, elapsed) -> PredictedCloud:
    seen = {name: (np.concatenate([p["seen"][name] for p in parts]) if parts
                   else np.zeros(0, bool)) for name, _ in setup.views}
    return PredictedCloud(
        seen=seen, fan=plan.fan, steps=(plan.first, plan.last) if plan.rays else (0, -1),
        rays_cast=plan.rays,
        first_hits=sum(p["hits"] for p in parts), facing=sum(p["facing"] for p in parts),
        elapsed_s=elapsed, setup=setup, pose=plan.pose,
        _hits=tuple((p["first"], p["ray"], p["face"]) for p in parts), _plan=plan,
        _threads=threads)


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


def save_predicted_cloud(path, cloud: PredictedCloud, *, frame: str = "T") -> Path:
    """Write a predicted cloud as binary little-endian PLY (float32 x, y, z in mm).

    Per-vertex properties: ``step`` and ``ray`` (signed int32: the light source stood at
    ``laser + step * step_mm * motion``, the header's comments; a step may be negative),
    ``nx, ny, nz`` (float32 normals towards the light) and, for each extra view,
    ``seen_<name>`` (uint8). The rows are made from the cloud's rays and faces block by
    block as the file is written (`scanner_core.ply.write_ply_rows`), without the cloud's
    float64 arrays.

    Returns
    -------
    pathlib.Path
    """
    s = cloud.setup

    def xyz(v):
        return " ".join(f"{x:.9g}" for x in v)

    comments = ["flyscan simulate", f"frame {frame}", "units mm",
                f"laser_step0 {xyz(s.laser)}", f"camera_step0 {xyz(s.camera)}",
                f"motion {xyz(s.motion)}", f"step_mm {s.step_mm:.9g}",
                f"rays_per_line {s.rays_per_line}", f"steps {cloud.steps[0]} {cloud.steps[1]}"]
    comments += [f"view_{name}_step0 {xyz(p)}" for name, p in s.views]
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return write_ply_rows(path, cloud._ply_blocks(), count=len(cloud), comments=comments)
