"""The conditions of ``bench pose_limits``: five factors, each grown from the reference cell
until the method breaks (the read noise, the pass speed, the stripe's saturation, the marker
hidden in the mirrors, the part's symmetry), and the part and the true cell of each level."""
from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np
import trimesh

from scanner_core.geometry import Mirror
from simulator.cell import Cell, marker_pixels
from simulator.motion import PassMotion
from simulator.parts import Part, part_from_mesh

__all__ = ["Factor", "FACTORS", "symmetric_part", "condition", "SYM_RADIUS_MM"]

# The symmetric family: a cylinder with a blind hole off its axis (mm). Enough sections that
# the facets (radius * (1 - cos(pi / n)): 1.9 um at r = 25, n = 256) say nothing of the turn.
SYM_RADIUS_MM, SYM_HEIGHT_MM, SYM_SECTIONS = 25.0, 20.0, 256
SYM_HOLE_RADIUS_MM, SYM_HOLE_DEPTH_MM, SYM_HOLE_SECTIONS = 4.0, 8.0, 128
# The hole's cutter overshoots the face it cuts, so no coplanar faces remain for the boolean.
_CUT_OVERSHOOT_MM = 1.0
# Time steps of the pass sampled to find where the marker is as the part crosses the sheet.
_MARKER_TRACK_SAMPLES = 4001


@dataclass(frozen=True)
class Factor:
    """One condition grown from the reference cell.

    Attributes
    ----------
    name : str
    label : str
        The x axis.
    unit : str
    levels, quick_levels : tuple of float
        In growing severity; the first is the reference cell's value (or, for the
        symmetry, the least symmetric part).
    """

    name: str
    label: str
    unit: str
    levels: tuple
    quick_levels: tuple


FACTORS = (
    Factor("noise", "read noise (reference 3 DN)", "DN", (3, 6, 10, 15, 20, 25), (3, 15, 25)),
    Factor("speed", "pass speed at 162 fps (reference 200 mm/s)", "mm/s",
           (200, 400, 700, 1000, 1500, 2500, 4000), (200, 1000, 2500)),
    # to 800 x full scale: since the width gates follow the frame the clipped
    # plateaus that continue the stripe are measured, and the pose first breaks past 200 x
    Factor("saturation", "stripe peak (full scale 255 DN, reference 200 DN)", "DN",
           (200, 400, 1000, 2000, 3000, 5000, 10000, 20000, 50000, 100000, 200000),
           (200, 1000, 200000)),
    Factor("marker", "marker hidden: fraction of the pass (0-1 right mirror, 1-2 both)", "",
           (0.0, 0.5, 1.0, 1.25, 1.5, 1.75, 2.0), (0.0, 1.0, 2.0)),
    Factor("symmetry", "off-centre hole's offset from the cylinder axis", "mm",
           (12.0, 6.0, 3.0, 1.0, 0.3, 0.0), (12.0, 1.0, 0.0)),
)


@functools.lru_cache(maxsize=8)
def symmetric_part(offset_mm: float) -> Part:
    """A cylinder (radius 25, height 20 mm, axis z in {P}, z in [0, 20]) with a blind hole
    (radius 4, depth 8 mm) in its max-z face, the underside the scanner sees, ``offset_mm``
    off the axis along x. At offset 0 the part turns freely about its axis. Kept once built
    (treat as read-only): its Embree scene and surface model are reused."""
    offset_mm = float(offset_mm)
    if not 0.0 <= offset_mm <= SYM_RADIUS_MM - SYM_HOLE_RADIUS_MM - 1.0:
        raise ValueError(f"`offset_mm` must be in [0, {SYM_RADIUS_MM - SYM_HOLE_RADIUS_MM - 1.0}],"
                         f" got {offset_mm}")
    body = trimesh.creation.cylinder(radius=SYM_RADIUS_MM, height=SYM_HEIGHT_MM,
                                     sections=SYM_SECTIONS)
    body.apply_translation((0.0, 0.0, SYM_HEIGHT_MM / 2.0))
    cut = SYM_HOLE_DEPTH_MM + _CUT_OVERSHOOT_MM
    hole = trimesh.creation.cylinder(radius=SYM_HOLE_RADIUS_MM, height=cut,
                                     sections=SYM_HOLE_SECTIONS)
    hole.apply_translation((offset_mm, 0.0, SYM_HEIGHT_MM - SYM_HOLE_DEPTH_MM + cut / 2.0))
    mesh = trimesh.boolean.difference([body, hole], engine="manifold")
    return part_from_mesh(mesh, name=f"cylinder_hole_{offset_mm:g}mm",
                          source=f"procedural:cylinder with a hole {offset_mm:g} mm off its axis")


def _hidden_cell(cell: Cell, part: Part, hidden: float) -> Cell:
    """The cell with the marker hidden in the right mirror for the first ``min(hidden, 1)`` of
    the part's passage through the sheet, and in the left mirror for the first
    ``hidden - 1`` of it beyond 1: the truth's mirror strips narrowed to where the marker is
    still visible (the scanner keeps its calibration)."""
    if not 0.0 <= hidden <= 2.0:
        raise ValueError(f"`hidden` must be in [0, 2], got {hidden}")
    if hidden == 0.0:
        return cell
    cal = cell.calibration
    # The part crosses the sheet (y_B = 0) while the TCP's y_B runs over the part's y_T range
    # ({T} has y_T = -y_B): the first point to cross is the one with the smallest y_T.
    y_t = part.vertices_t()[:, 1]
    motion = PassMotion(cell.pass_profile)
    times = np.linspace(0.0, motion.duration_s, _MARKER_TRACK_SAMPLES)
    tcp = motion.tcp_position(times)
    mirrors = list(cal.mirrors)
    for index, fraction in ((1, min(hidden, 1.0)), (0, max(hidden - 1.0, 0.0))):
        if fraction == 0.0:
            continue
        c0, c1 = mirrors[index].columns
        if fraction >= 1.0:
            mirrors[index] = Mirror(mirrors[index].plane, (c0, c0))  # never inside its strip
            continue
        y_cut = y_t.min() + fraction * (y_t.max() - y_t.min())
        k_start = int(np.searchsorted(tcp[:, 1], y_t.min()))
        k_cut = int(np.searchsorted(tcp[:, 1], y_cut))
        columns = marker_pixels(cell, tcp[[k_start, k_cut]])[:, 1 + index, 0]
        if columns[0] > columns[1]:  # moving toward lower columns: hide those above the cut
            mirrors[index] = Mirror(mirrors[index].plane, (c0, int(math.floor(columns[1])) + 1))
        else:
            mirrors[index] = Mirror(mirrors[index].plane, (int(math.ceil(columns[1])), c1))
    return dataclasses.replace(cell, calibration=dataclasses.replace(cal, mirrors=tuple(mirrors)))


def condition(factor: str, level: float, part: Part, cell: Cell) -> tuple[Part, Cell]:
    """The part and the (true) simulated cell of one level of a factor; the scanner's
    calibration stays the reference cell's."""
    image = cell.image_model
    if factor == "noise":
        return part, dataclasses.replace(cell, image_model=dataclasses.replace(
            image, read_noise_dn=float(level)))
    if factor == "speed":
        return part, cell.with_pass(speed_mm_s=float(level))
    if factor == "saturation":
        return part, dataclasses.replace(cell, image_model=dataclasses.replace(
            image, stripe_peak_dn=float(level)))
    if factor == "marker":
        return part, _hidden_cell(cell, part, float(level))
    if factor == "symmetry":
        return symmetric_part(level), cell
    raise ValueError(f"unknown factor {factor!r}; one of {[f.name for f in FACTORS]}")

