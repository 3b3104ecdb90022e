"""The paper's sweep written as a careful Open3D user would: the yardstick for `flyscan simulate`.

A standalone script (numpy and Open3D only, nothing of flyscan) that does the work of
``flyscan simulate --grasp identity --laser L --camera C --step S --rays R --out FILE`` on a
mesh file already in millimetres in the setup frame:

- the light plane's fan is fitted to the part as flyscan fits it (aimed at the part's centre
  across the motion, just covering it), and the steps are every integer n whose plane
  ``laser + n * step * motion`` meets the part;
- the fan's directions are computed once (the setup only translates), the rays are built in
  float32, many fans per call, and Open3D's ``RaycastingScene`` runs on all cores;
- first hits with ``cast_rays``; a hit is kept when the camera stands on its lit side and
  ``test_occlusions`` finds nothing between the camera and the point (up to 10 um before it,
  flyscan's surface tolerance): the same work as flyscan's visibility check;
- the kept points are written as flyscan's PLY (float32 x, y, z; int32 step and ray; float32
  normals towards the light) from one structured array in one write.

Run as ``python -m benchmarks.open3d_sweep --part FILE --laser x,y,z --camera x,y,z
--step MM --rays N [--out FILE.ply]``; it prints one JSON line of counts and phase times.
Open3D is an optional, benchmark-only dependency (``pip install flyscan[bench]``).
"""
from __future__ import annotations

import time

_T0 = time.perf_counter()

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402

import numpy as np  # noqa: E402

#: Rays per Open3D call: many fans, so the per-call cost and the thread start-up vanish.
CHUNK_RAYS = 1 << 18
#: flyscan's surface tolerance (simulator.raycast.SURFACE_TOL_MM), mm.
SURFACE_TOL_MM = 0.01


def fan_and_steps(vertices, laser, motion, step_mm, rays):
    """The fan's unit directions (R, 3) float64 and the first and last step, as flyscan's."""
    size = float(np.ptp(vertices, axis=0).max())
    aim = (vertices.min(axis=0) + vertices.max(axis=0)) / 2.0 - laser
    aim -= (aim @ motion) * motion
    if np.linalg.norm(aim) <= 1e-9 * max(size, 1.0):
        raise SystemExit("the light source lies on the part's axis along the motion")
    central = aim / np.linalg.norm(aim)
    across = np.cross(central, motion)
    across /= np.linalg.norm(across)
    rel = vertices - laser
    depth = rel @ central
    if depth.min() <= 0:
        raise SystemExit("the part is not wholly in front of the light source")
    w = (rel @ across) / depth
    fan = central + np.linspace(w.min(), w.max(), rays)[:, None] * across
    fan /= np.linalg.norm(fan, axis=1, keepdims=True)
    along = (vertices - laser) @ motion
    return fan, int(np.ceil(along.min() / step_mm)), int(np.floor(along.max() / step_mm))


def sweep(scene, o3c, laser, camera, shift, first, last, fan):
    """Cast every fan; returns the kept rows, counts and the time spent in Open3D's calls."""
    fan32 = fan.astype(np.float32)
    n_rays = len(fan32)
    per_call = max(1, CHUNK_RAYS // n_rays)
    out, first_hits, calls_s = [], 0, 0.0
    for s0 in range(first, last + 1, per_call):
        steps = np.arange(s0, min(s0 + per_call, last + 1))
        origins = (laser + steps[:, None] * shift).astype(np.float32)
        cameras = (camera + steps[:, None] * shift).astype(np.float32)
        rays = np.empty((len(steps), n_rays, 6), np.float32)
        rays[:, :, :3] = origins[:, None, :]
        rays[:, :, 3:] = fan32[None]
        t0 = time.perf_counter()
        ans = scene.cast_rays(o3c.Tensor.from_numpy(rays.reshape(-1, 6)))
        calls_s += time.perf_counter() - t0
        t_hit = ans["t_hit"].numpy()
        hit = np.flatnonzero(np.isfinite(t_hit))
        first_hits += len(hit)
        step_i = hit // n_rays
        ray_i = hit - step_i * n_rays
        d = fan32[ray_i]
        p = origins[step_i]
        p += t_hit[hit, None] * d
        n = ans["primitive_normals"].numpy()[hit]
        n[np.einsum("ij,ij->i", n, d) > 0] *= -1.0  # towards the light
        view = p - cameras[step_i]
        facing = np.flatnonzero(np.einsum("ij,ij->i", n, view) < 0)
        view = view[facing]
        length = np.sqrt(np.einsum("ij,ij->i", view, view))
        sight = np.empty((len(facing), 6), np.float32)
        sight[:, :3] = cameras[step_i[facing]]
        # Scaled so that t = 1 stops SURFACE_TOL_MM before the point.
        np.multiply(view, np.maximum(1.0 - SURFACE_TOL_MM / length, 0.0)[:, None],
                    out=sight[:, 3:])
        t0 = time.perf_counter()
        occluded = scene.test_occlusions(o3c.Tensor.from_numpy(sight), tnear=0.0,
                                         tfar=1.0).numpy()
        calls_s += time.perf_counter() - t0
        keep = facing[~occluded]
        out.append((p[keep], n[keep], steps[step_i[keep]], ray_i[keep]))
    return out, first_hits, calls_s


def write_ply(path, rows):
    """flyscan's PLY layout, from one structured array in one write."""
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("step", "<i4"),
                      ("ray", "<i4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")])
    count = sum(len(r[0]) for r in rows)
    table = np.empty(count, dtype)
    flat = table.view(np.float32).reshape(count, 8)
    ints = table.view(np.int32).reshape(count, 8)
    at = 0
    for p, n, step, ray in rows:
        k = len(p)
        flat[at:at + k, 0:3] = p
        ints[at:at + k, 3] = step
        ints[at:at + k, 4] = ray
        flat[at:at + k, 5:8] = n
        at += k
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {count}"]
    header += [f"property {'int' if dtype[name].kind == 'i' else 'float'} {name}"
               for name in dtype.names]
    with open(path, "wb") as fh:
        fh.write(("\n".join(header + ["end_header"]) + "\n").encode("ascii"))
        fh.write(memoryview(table).cast("B"))
    return count


def _point(text):
    values = [float(v) for v in text.split(",")]
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"need 'x,y,z', got {text!r}")
    return np.array(values)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", required=True, help="mesh file, mm, in the setup frame")
    parser.add_argument("--laser", type=_point, required=True)
    parser.add_argument("--camera", type=_point, required=True)
    parser.add_argument("--motion", type=_point, default=np.array([0.0, 1.0, 0.0]))
    parser.add_argument("--step", type=float, required=True, help="mm")
    parser.add_argument("--rays", type=int, required=True, help="rays per line")
    parser.add_argument("--out", default=None, help="PLY file (default: write nothing)")
    args = parser.parse_args(argv)
    times = {}
    t = time.perf_counter()
    import open3d as o3d

    o3c = o3d.core
    times["import_open3d_s"] = time.perf_counter() - t
    t = time.perf_counter()
    mesh = o3d.t.io.read_triangle_mesh(args.part)
    vertices = mesh.vertex.positions.numpy().astype(np.float64)
    if len(vertices) == 0:
        raise SystemExit(f"no mesh in {args.part}")
    times["load_s"] = time.perf_counter() - t
    t = time.perf_counter()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    motion = args.motion / np.linalg.norm(args.motion)
    fan, first, last = fan_and_steps(vertices, args.laser, motion, args.step, args.rays)
    times["build_s"] = time.perf_counter() - t
    t = time.perf_counter()
    rows, first_hits, calls_s = sweep(scene, o3c, args.laser, args.camera, args.step * motion,
                                      first, last, fan)
    times["sweep_s"] = time.perf_counter() - t
    times["ray_calls_s"] = calls_s
    t = time.perf_counter()
    if args.out:
        points = write_ply(args.out, rows)
    else:
        points = sum(len(r[0]) for r in rows)
    times["write_s"] = time.perf_counter() - t
    times["since_start_s"] = time.perf_counter() - _T0
    print(json.dumps({"open3d": o3d.__version__, "faces": int(len(mesh.triangle.indices)),
                      "steps": [first, last], "rays_cast": (last - first + 1) * args.rays,
                      "first_hits": int(first_hits), "points": int(points),
                      **{k: round(v, 4) for k, v in times.items()}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
