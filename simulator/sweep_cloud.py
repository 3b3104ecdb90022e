"""The scan simulator's output (``simulator.virtual_setup``): the predicted cloud, and its
PLY file.

While it sweeps, a cloud keeps only each point's ray and face (8 bytes a point, see
`simulator._sweep`); :class:`PredictedCloud` computes its float64 arrays on first use, and
:func:`save_predicted_cloud` writes its PLY file straight from the rays and faces, block by
block, so writing millions of points costs one pass.
"""
from __future__ import annotations

from bisect import bisect_left, bisect_right
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from scanner_core.io.ply import write_ply_rows
from simulator import _sweep
from simulator.sweep_plan import SweepPlan
from simulator.sweep_setup import VirtualSetup

__all__ = ["PredictedCloud", "save_predicted_cloud"]

# Clouds smaller than this are laid out by the calling thread alone: threads cost more.
_SERIAL_ROWS = 1 << 16
# Rows of a PLY file made at a time (about 4 MB): large enough that a write call costs
# nothing, small enough to stay in memory already in use. On the reference machine (a virtual
# machine) memory touched for the first time cost 0.3 to 3 ms a megabyte: more than the work
# done in it; a whole table of 3.8 M points (121 MB) took 0.05 to 0.35 s to allocate.
_PLY_BLOCK_ROWS = 1 << 17


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



def save_predicted_cloud(path, cloud: PredictedCloud, *, frame: str = "T") -> Path:
    """Write a predicted cloud as binary little-endian PLY (float32 x, y, z in mm).

    Per-vertex properties: ``step`` and ``ray`` (signed int32: the light source stood at
    ``laser + step * step_mm * motion``, the header's comments; a step may be negative),
    ``nx, ny, nz`` (float32 normals towards the light) and, for each extra view,
    ``seen_<name>`` (uint8). The rows are made from the cloud's rays and faces block by
    block as the file is written (`scanner_core.io.ply.write_ply_rows`), without the cloud's
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
