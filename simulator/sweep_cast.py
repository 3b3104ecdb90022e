"""The scan simulator's sweep (``simulator.virtual_setup``): the rays cast, line after line.

:func:`predict_cloud` plans the sweep (``simulator.sweep_plan``), then casts its lines in
chunks on a few threads (Embree and the kernels of ``simulator._sweep`` release the GIL):
each ray's first hit that the light source lights, then the visibility check from the camera
and from each further viewpoint; the kept points' rays and faces make the
``simulator.sweep_cloud.PredictedCloud``. :func:`prepare` and :func:`warm_up` pay a part's
and the kernels' one-off costs ahead.
"""
from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from simulator import _sweep
from simulator.parts import Part
from simulator.raycast import SURFACE_TOL_MM, Intersector
from simulator.sweep_cloud import PredictedCloud
from simulator.sweep_plan import MAX_RAYS, SweepPlan, plan_sweep
from simulator.sweep_setup import MAIN_VIEW, SetupError, VirtualSetup

__all__ = ["predict_cloud", "prepare", "warm_up"]

# Rays per Embree call: large enough to hide the per-call cost (12-26 us, docs/design.md), small
# enough that two threads share the work evenly and each thread's scratch (about 110 bytes a
# ray, reused from chunk to chunk) stays a few megabytes.
_CHUNK_RAYS = 1 << 16


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
