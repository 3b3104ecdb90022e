"""The parts the benchmarks scan and the misplacements they scan them at: defined once.

The full runs scan the four reference parts (their meshes where ``--meshes DIR`` or
``$FLYSCAN_MESHES`` points, ``simulator.parts.load_reference_part``); the quick runs the procedural
demo block (``simulator.parts.block_with_holes_and_steps``), which needs no mesh file.
``bench pose`` draws its scans' misplacements from `MISPLACEMENT_SEED`; ``bench coarse`` and
``bench edges`` scan the reference parts again at the same ones.
"""
from __future__ import annotations

import numpy as np

from simulator.cell import load_cell
from simulator import procedural
from simulator.parts import Part, block_with_holes_and_steps, load_reference_part, part_from_mesh
from simulator.session import SimulatedCell, simulated_cell

__all__ = ["REFERENCE_PARTS", "REFERENCE_PART", "DEMO_PART", "PROCEDURAL_PARTS",
           "VALIDATION_PARTS", "demo_part",
           "bench_part", "demo_pass",
           "MISPLACEMENT_UP_TO_MM", "MISPLACEMENT_UP_TO_DEG", "MISPLACEMENT_SEED",
           "random_misplacement", "AXES"]

REFERENCE_PARTS = ("idler_riser", "featuretype", "ADIS16480", "cycloidal")
#: The reference part a benchmark scans when it scans one beyond the demo block (the pass
#: presets, the side by sides, the full runs of pose_limits, surfaces and calibrate).
REFERENCE_PART = REFERENCE_PARTS[0]
#: The demo block's name in the benchmarks' figures.
DEMO_PART = "block"
_DEMO_SOURCE = "procedural:block_with_holes_and_steps"
#: The camera seed of the demo block's pass whose frames ``bench stripe`` and ``bench service``
#: time.
DEMO_PASS_SEED = 3

#: The issue's target set of misplacements: up to this far from the nominal grasp,
#: mm and degrees, in random directions.
MISPLACEMENT_UP_TO_MM, MISPLACEMENT_UP_TO_DEG = 5.0, 10.0
#: The six axes of a misplacement or a pose error: a translation (mm) and a rotation vector.
AXES = ("tx", "ty", "tz", "rx", "ry", "rz")
#: Seed of ``bench pose``'s scans: part ``i`` of `REFERENCE_PARTS` draws its misplacements
#: from ``np.random.default_rng([MISPLACEMENT_SEED, i])``.
MISPLACEMENT_SEED = 20261


#: Procedural parts the benchmarks scan beside the reference ones, by name: each made by
#: ``simulator.procedural`` (holes and steps, a creased hub and blades, a plate with a step,
#: a curved crown), no mesh file needed.
PROCEDURAL_PARTS = {
    DEMO_PART: procedural.block_with_holes_and_steps,
    "bracket": procedural.bracket_with_two_holes,
    "fan_disk": procedural.fan_disk,
    "crowned_block": procedural.crowned_block,
}




def _public_mesh(filename: str, size_mm: float):
    """A public mesh that a registry package ships (pymeshlab's sample meshes: the Stanford
    bunny, a bone), scaled to `size_mm` across: a part no benchmark here was made on."""
    def make():
        from importlib import resources

        import trimesh

        try:
            path = resources.files("pymeshlab") / "tests" / "sample_meshes" / filename
        except ModuleNotFoundError:
            raise ValueError(f"{filename}: the public sample meshes come with pymeshlab, "
                             f"which is not installed") from None
        if not path.is_file():
            raise ValueError(f"{filename}: not among pymeshlab's sample meshes ({path})")
        mesh = trimesh.load(str(path), force="mesh")
        mesh.apply_scale(size_mm / float(mesh.extents.max()))
        return mesh
    make.__name__ = f"public:{filename}"
    return make


#: Parts for checking the benchmarks' findings on what they were not made on: procedural
#: parts of other shapes and sizes, a faceted dome, and public meshes.
VALIDATION_PARTS = {
    "bracket_wide": lambda: procedural.bracket_with_two_holes(
        (90.0, 50.0, 8.0), step_height=3.0, step_x=-5.0, hole_radii=(5.0, 2.5)),
    "block_tall": lambda: procedural.block_with_holes_and_steps((50.0, 35.0, 30.0),
                                                                hole_radius=5.0),
    "fan_disk_6": lambda: procedural.fan_disk(38.0, blades=6, blade_pitch_deg=40.0),
    "dome": lambda: procedural.faceted_dome(35.0),
    "bunny": _public_mesh("bunny.obj", 70.0),
    "bone": _public_mesh("bone.ply", 80.0),
}


def demo_part(name: str = DEMO_PART) -> Part:
    """The procedural demo block (holes and steps), named `name` in the figures."""
    return part_from_mesh(block_with_holes_and_steps(), name=name, source=_DEMO_SOURCE)


def bench_part(name: str) -> Part:
    """The demo block for `DEMO_PART`, a part of `PROCEDURAL_PARTS` or `VALIDATION_PARTS`,
    else the reference part of that name."""
    if name == DEMO_PART:
        return demo_part()
    for registry in (PROCEDURAL_PARTS, VALIDATION_PARTS):
        if name in registry:
            return part_from_mesh(registry[name](), name=name,
                                  source=f"procedural:{registry[name].__name__}")
    return load_reference_part(name)


def demo_pass() -> SimulatedCell:
    """The demo block's pass through the reference cell at the nominal grasp: its simulated
    camera and robot (``simulator.session.simulated_cell``, seed `DEMO_PASS_SEED`)."""
    return simulated_cell(demo_part(), load_cell(), seed=DEMO_PASS_SEED)


def random_misplacement(rng: np.random.Generator, t_mm: float, r_deg: float, *,
                        up_to: bool) -> list[float]:
    """A translation and a rotation vector in random directions: of exactly `t_mm` and `r_deg`
    or, with `up_to`, of magnitudes uniform in ``[0, t_mm]`` and ``[0, r_deg]``.

    Returns
    -------
    list of 6 float
        tx, ty, tz mm and the rotation vector in degrees, rounded to 1e-6.
    """
    direction = rng.normal(size=3)
    axis = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    axis /= np.linalg.norm(axis)
    t, r = (rng.uniform(0.0, t_mm), rng.uniform(0.0, r_deg)) if up_to else (t_mm, r_deg)
    return [round(float(v), 6) for v in np.concatenate([direction * t, axis * r])]
