"""Procedural test parts, built with trimesh and manifold3d: the demo block and the unseen
cases beyond the reference parts (soft creases, holes and a step, a curved surface).

Every function returns a watertight ``trimesh.Trimesh`` in mm, in its part frame {P}, its
features described in ``mesh.metadata["features"]``; ``simulator.parts.part_from_mesh`` (or
``scanner_core.cad.part_from_mesh``) makes it a part.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import trimesh

__all__ = ["block_with_holes_and_steps", "faceted_dome", "fan_disk", "bracket_with_two_holes",
           "crowned_block"]


# Facets of the hole cylinders: round enough for the stripe and edge tests, few triangles.
_HOLE_SECTIONS = 48
# Cutting tools overshoot the faces they cut by this much (mm), so no coplanar faces remain
# for the boolean engine to resolve.
_CUT_OVERSHOOT = 1.0


def block_with_holes_and_steps(size=(60.0, 40.0, 20.0), *, hole_radius: float = 4.0,
                               blind_depth: float | None = None,
                               step_length: float | None = None,
                               step_depth: float | None = None) -> trimesh.Trimesh:
    """A watertight test block (mm) with a through hole, a blind hole and a step.

    The block is ``size = (L, W, H)`` in {P} with x in [-L/2, L/2], y in [-W/2, W/2] and z in
    [0, H], so `centred_grasp` of it is the identity. The features are on the max-z face, the
    underside that the scanner sees when the part hangs along +z_T:

    - a through hole along z at (-L/4, 0), radius `hole_radius`;
    - a blind hole from the max-z face at (0, 0), radius `hole_radius`, depth `blind_depth`
      (default H/2);
    - a step: the region x > L/2 - `step_length` (default L/4) is lowered from z = H to
      z = H - `step_depth` (default H/4).

    Hole cylinders have ``_HOLE_SECTIONS`` facets (a regular polygon inscribed in the circle).
    The features are described in ``mesh.metadata["features"]``.

    Returns
    -------
    trimesh.Trimesh
        Watertight mesh, mm.

    Raises
    ------
    ValueError
        When the features do not fit in the block.
    ImportError
        When no boolean engine (manifold3d) is installed.
    """
    length, width, height = (float(s) for s in size)
    if min(length, width, height) <= 0:
        raise ValueError(f"`size` must be 3 positive lengths, got {size!r}")
    blind_depth = height / 2.0 if blind_depth is None else float(blind_depth)
    step_length = length / 4.0 if step_length is None else float(step_length)
    step_depth = height / 4.0 if step_depth is None else float(step_depth)
    r = float(hole_radius)
    through_xy = (-length / 4.0, 0.0)
    blind_xy = (0.0, 0.0)
    step_x = length / 2.0 - step_length
    if not (0 < r and r < width / 2 and through_xy[0] - r > -length / 2
            and blind_xy[0] + r < step_x and through_xy[0] + r < blind_xy[0] - r):
        raise ValueError(f"`hole_radius` {r} does not fit the block {size!r}")
    if not 0 < blind_depth < height:
        raise ValueError(f"`blind_depth` must be in (0, {height}), got {blind_depth}")
    if not (0 < step_length < length / 2 and 0 < step_depth < height):
        raise ValueError(f"step {step_length} x {step_depth} mm does not fit the block {size!r}")
    _require_boolean_engine()
    import trimesh

    block = trimesh.creation.box(extents=(length, width, height))
    block.apply_translation((0.0, 0.0, height / 2.0))
    o = _CUT_OVERSHOOT
    through = trimesh.creation.cylinder(radius=r, height=height + 2 * o, sections=_HOLE_SECTIONS)
    through.apply_translation((*through_xy, height / 2.0))
    blind = trimesh.creation.cylinder(radius=r, height=blind_depth + o, sections=_HOLE_SECTIONS)
    blind.apply_translation((*blind_xy, height - blind_depth + (blind_depth + o) / 2.0))
    step = trimesh.creation.box(extents=(step_length + o, width + 2 * o, step_depth + o))
    step.apply_translation((step_x + (step_length + o) / 2.0, 0.0,
                            height - step_depth + (step_depth + o) / 2.0))
    mesh = trimesh.boolean.difference([block, through, blind, step], engine="manifold")
    if not mesh.is_watertight:
        raise RuntimeError("boolean difference gave a mesh that is not watertight")
    mesh.metadata["features"] = {
        "size": (length, width, height),
        "through_holes": [{"xy": through_xy, "radius": r}],
        "blind_holes": [{"xy": blind_xy, "radius": r, "depth": blind_depth}],
        "steps": [{"x_min": step_x, "depth": step_depth}],
        "hole_sections": _HOLE_SECTIONS,
    }
    return mesh


def _require_boolean_engine() -> None:
    try:
        import manifold3d  # noqa: F401  (trimesh's boolean engine)
    except ImportError as exc:
        raise ImportError("block_with_holes_and_steps needs the boolean engine manifold3d: "
                          "pip install manifold3d") from exc


# --------------------------------------------------------------------------------------------
# Procedural parts with soft creases, curved surfaces and holes
# --------------------------------------------------------------------------------------------

#: Default slopes (degrees from level) of a faceted dome's tiers, from its flat top outward:
#: creases of 18 to 20 degrees between tiers, soft (under the 30-degree feature angle of the
#: edge evaluation and the edge model). In the reference cell the camera looks up at about
#: 30 degrees from z_T, so a tier sloping more than about 60 degrees away from it (the 78 one,
#: on the side turned from the camera) is lit by the sheet and unseen: the stripe drops out
#: at a soft crease.
DOME_SLOPES_DEG = (0.0, 18.0, 38.0, 58.0, 78.0)
#: Facets around a dome's axis: 12 put 18 to 29 degrees between neighbouring facets of the
#: steeper tiers (2 asin(sin(slope) sin(180 / 12))), soft creases as well.
DOME_SECTORS = 12


def _dome_rings(radius: float, base_z: float, slopes_deg, sectors: int, phase: float,
                tier_drop: float):
    """Vertex rings of a faceted dome: its flat top, then one ring per tier outward, each
    tier falling `tier_drop` toward ``base_z`` at its slope (so spanning ``tier_drop /
    tan(slope)`` of the radius); the flat top takes the rest of `radius`. (K, sectors, 3)."""
    slopes = np.radians(np.asarray(slopes_deg, dtype=np.float64))
    if slopes.ndim != 1 or len(slopes) < 2 or np.any(np.diff(slopes) <= 0) \
            or slopes[0] < 0 or slopes[-1] >= np.pi / 2 or not tier_drop > 0:
        raise ValueError(f"`slopes_deg` must rise from >= 0 to < 90 degrees over at least two "
                         f"tiers and `tier_drop` be > 0, got {slopes_deg!r}, {tier_drop!r}")
    widths = tier_drop / np.tan(slopes[1:])
    top = radius - widths.sum()
    if not top > 0:
        raise ValueError(f"tiers of {tier_drop} mm at {slopes_deg!r} degrees need more than "
                         f"the radius {radius} mm")
    radii = top + np.concatenate([[0.0], np.cumsum(widths)])
    heights = base_z + tier_drop * np.arange(len(slopes) - 1, -1, -1)
    theta = phase + 2.0 * np.pi * np.arange(sectors) / sectors
    ring = np.stack([np.cos(theta), np.sin(theta), np.zeros(sectors)], axis=1)
    return np.stack([ring * r + (0.0, 0.0, z) for r, z in zip(radii, heights)])


def faceted_dome(radius: float = 30.0, base_height: float = 8.0, *,
                 slopes_deg=DOME_SLOPES_DEG, sectors: int = DOME_SECTORS,
                 tier_drop: float = 4.0, plinth_radius: float | None = None) -> trimesh.Trimesh:
    """A faceted dome on a prism: a creased surface the scanner sees (mm).

    A regular ``sectors``-gon prism of circumradius `radius`, z in [0, `base_height`], topped
    (toward +z, the underside the scanner sees when the part hangs along +z_T) by a convex
    faceted dome: a flat polygonal top, then tiers of rising slope (`slopes_deg`, degrees
    from level), each falling `tier_drop` toward the prism. Neighbouring tiers meet at creases
    of their slope difference; neighbouring facets of one tier at about
    ``2 asin(sin(slope) sin(180 / sectors))``. The steepest tier meets the prism's wall at
    ``90 - slopes_deg[-1]``: the part's outline seen along z. With `plinth_radius` (larger
    than `radius`) the prism is that wide and the dome stands on its face: its steepest tier
    meets a level face at a sharp (concave) crease, and the plinth's rim is the outline.

    Returns
    -------
    trimesh.Trimesh
        Watertight, convex; ``metadata["features"]`` gives the slopes, the tiers' radii and
        heights, and the crease angles.
    """
    import trimesh

    if not (radius > 0 and base_height > 0) or int(sectors) != sectors or sectors < 6:
        raise ValueError(f"`radius` and `base_height` must be > 0 and `sectors` an integer >= 6, "
                         f"got {radius!r}, {base_height!r}, {sectors!r}")
    rings = _dome_rings(float(radius), float(base_height), slopes_deg, int(sectors), 0.0,
                        float(tier_drop))
    base = rings[-1].copy()
    base[:, 2] = 0.0
    mesh = trimesh.convex.convex_hull(np.concatenate([rings.reshape(-1, 3), base]))
    if plinth_radius is not None:
        if not plinth_radius > radius:
            raise ValueError(f"`plinth_radius` must exceed `radius` {radius}, got "
                             f"{plinth_radius!r}")
        _require_boolean_engine()
        plinth = trimesh.creation.cylinder(radius=float(plinth_radius), height=base_height,
                                           sections=int(sectors))
        plinth.apply_translation((0.0, 0.0, base_height / 2.0))
        mesh = trimesh.boolean.union([mesh, plinth], engine="manifold")
    slopes = np.asarray(slopes_deg, dtype=np.float64)
    mesh.metadata["features"] = {
        "radius": float(radius), "base_height": float(base_height),
        "height": float(rings[0, 0, 2]), "slopes_deg": slopes.tolist(), "sectors": int(sectors),
        "tier_radii": np.linalg.norm(rings[:, 0, :2], axis=1).tolist(),
        "tier_heights": rings[:, 0, 2].tolist(),
        "crease_deg": np.diff(slopes).tolist(), "plinth_radius": plinth_radius,
    }
    return mesh


def fan_disk(radius: float = 45.0, thickness: float = 6.0, *, hub_radius: float = 20.0,
             hub_slopes_deg=(0.0, 20.0, 40.0, 62.0, 80.0), hub_sectors: int = 12,
             hub_tier_drop: float = 3.0,
             blades: int = 8, blade_height: float = 7.0, blade_thickness: float = 2.5,
             blade_pitch_deg: float = 30.0, blade_sections: int = 4,
             blade_twist_deg: float = 20.0) -> trimesh.Trimesh:
    """A fan-disk-like part (mm): a disc, a faceted hub and pitched, twisted blades.

    Toward +z (the underside the scanner sees when the part hangs along +z_T), on a regular
    48-gon disc of `radius` and `thickness` (z in [0, thickness]):

    - a faceted hub (:func:`faceted_dome`'s surface) of `hub_radius`, tiers at
      `hub_slopes_deg` each falling `hub_tier_drop`: soft creases of 18 to 22 degrees
      between tiers, and between the facets of a tier;
    - `blades` radial blades between the hub and the rim, `blade_height` tall, each a plate
      `blade_thickness` thick leaning `blade_pitch_deg` about its radial axis, twisted along
      its length: it is made of `blade_sections` straight pieces whose pitch grows by
      ``blade_twist_deg / (blade_sections - 1)`` from one to the next, each piece the hull
      of its two end sections, so neighbouring pieces meet at soft creases (a twisted blade's
      facets).

    Returns
    -------
    trimesh.Trimesh
        Watertight; ``metadata["features"]`` lists the dimensions.

    Raises
    ------
    ValueError
        When the hub and the blades do not fit the disc.
    """
    _require_boolean_engine()
    import trimesh

    r, t = float(radius), float(thickness)
    if not (0 < hub_radius < r - 4.0 and t > 0 and blade_height > 0 and blade_thickness > 0
            and int(blades) == blades and blades >= 0 and int(blade_sections) == blade_sections
            and blade_sections >= 2):
        raise ValueError(f"the hub ({hub_radius} mm) and blades must fit a disc of radius {r}")
    o = _CUT_OVERSHOOT
    disc = trimesh.creation.cylinder(radius=r, height=t, sections=48)
    disc.apply_translation((0.0, 0.0, t / 2.0))
    rings = _dome_rings(float(hub_radius), t, hub_slopes_deg, int(hub_sectors),
                        np.pi / hub_sectors, float(hub_tier_drop))
    foot = rings[-1].copy()
    foot[:, 2] = t - o
    hub = trimesh.convex.convex_hull(np.concatenate([rings.reshape(-1, 3), foot]))
    pieces = [disc, hub]
    r0, r1 = hub_radius - 1.0, r - 3.0  # into the hub's steep tier; short of the rim
    cuts = np.linspace(r0, r1, int(blade_sections))
    pitches = np.radians(blade_pitch_deg + np.linspace(0.0, blade_twist_deg, len(cuts)))
    for k in range(int(blades)):
        phi = 2.0 * np.pi * k / blades
        radial = np.array([np.cos(phi), np.sin(phi), 0.0])
        side = np.array([-np.sin(phi), np.cos(phi), 0.0])
        sections = []
        for rad, pitch in zip(cuts, pitches):
            lean = np.cos(pitch) * np.array([0.0, 0.0, 1.0]) + np.sin(pitch) * side
            across = np.cos(pitch) * side - np.sin(pitch) * np.array([0.0, 0.0, 1.0])
            centre = rad * radial + (0.0, 0.0, t - o)
            half = 0.5 * blade_thickness * across
            up = (blade_height + o) * lean
            sections.append(np.array([centre - half, centre + half,
                                      centre - half + up, centre + half + up]))
        for a, b in zip(sections[:-1], sections[1:]):
            pieces.append(trimesh.convex.convex_hull(np.concatenate([a, b])))
    mesh = trimesh.boolean.union(pieces, engine="manifold")
    if not mesh.is_watertight:
        raise RuntimeError("boolean union gave a mesh that is not watertight")
    mesh.metadata["features"] = {
        "radius": r, "thickness": t, "hub_radius": float(hub_radius),
        "hub_slopes_deg": list(map(float, hub_slopes_deg)), "hub_sectors": int(hub_sectors),
        "hub_height": float(rings[0, 0, 2] - t), "blades": int(blades),
        "blade_height": float(blade_height), "blade_pitch_deg": float(blade_pitch_deg),
        "blade_twist_deg": float(blade_twist_deg), "blade_sections": int(blade_sections),
    }
    return mesh


def bracket_with_two_holes(size=(70.0, 40.0, 6.0), *, step_height: float = 5.0,
                           step_x: float = 10.0, hole_radii=(4.0, 3.0),
                           rib_height: float = 0.0) -> trimesh.Trimesh:
    """A bracket (mm): a plate with two through holes and a step.

    The plate is ``size = (L, W, T)``, x in [-L/2, L/2], y in [-W/2, W/2]; toward +z (the
    underside the scanner sees), its part x > `step_x` is `step_height` thicker (z up to
    T + step_height), the rest z up to T. One through hole of ``hole_radii[0]`` in the thin
    part at x = (step_x - L/2) / 2, one of ``hole_radii[1]`` in the thick part at
    x = (step_x + L/2) / 2, both at y = 0 (``_HOLE_SECTIONS`` facets). With `rib_height`,
    a rib runs along x on the thin part's face at y = W/4 (2 mm wide): a lower step.

    Returns
    -------
    trimesh.Trimesh
        Watertight; ``metadata["features"]`` gives the holes' centres and radii and the step.
    """
    _require_boolean_engine()
    import trimesh

    length, width, t = (float(s) for s in size)
    h = float(step_height)
    x_thin = (step_x - length / 2.0) / 2.0
    x_thick = (step_x + length / 2.0) / 2.0
    r_thin, r_thick = (float(v) for v in hole_radii)
    if not (min(length, width, t, h, r_thin, r_thick) > 0 and -length / 2 < step_x < length / 2
            and x_thin - r_thin > -length / 2 and x_thin + r_thin < step_x
            and x_thick - r_thick > step_x and x_thick + r_thick < length / 2
            and max(r_thin, r_thick) < width / 4 - 1.5):
        raise ValueError(f"the holes {hole_radii!r} and the step at x = {step_x} do not fit "
                         f"the plate {size!r}")
    o = _CUT_OVERSHOOT
    plate = trimesh.creation.box(extents=(length, width, t))
    plate.apply_translation((0.0, 0.0, t / 2.0))
    thick = trimesh.creation.box(extents=(length / 2.0 - step_x, width, h + o))
    thick.apply_translation(((step_x + length / 2.0) / 2.0, 0.0, t + (h - o) / 2.0))
    pieces = [plate, thick]
    if rib_height > 0:
        rib = trimesh.creation.box(extents=(step_x + length / 2.0 - 4.0, 2.0, rib_height + o))
        rib.apply_translation(((step_x - length / 2.0) / 2.0, width / 4.0,
                               t + (rib_height - o) / 2.0))
        pieces.append(rib)
    body = trimesh.boolean.union(pieces, engine="manifold")
    holes = []
    for (x, rad) in ((x_thin, r_thin), (x_thick, r_thick)):
        hole = trimesh.creation.cylinder(radius=rad, height=t + h + 2 * o,
                                         sections=_HOLE_SECTIONS)
        hole.apply_translation((x, 0.0, (t + h) / 2.0))
        holes.append(hole)
    mesh = trimesh.boolean.difference([body, *holes], engine="manifold")
    if not mesh.is_watertight:
        raise RuntimeError("boolean difference gave a mesh that is not watertight")
    mesh.metadata["features"] = {
        "size": (length, width, t), "step": {"x_min": float(step_x), "height": h},
        "through_holes": [{"xy": (x_thin, 0.0), "radius": r_thin},
                          {"xy": (x_thick, 0.0), "radius": r_thick}],
        "rib_height": float(rib_height), "hole_sections": _HOLE_SECTIONS,
    }
    return mesh


def crowned_block(size=(60.0, 40.0, 10.0), *, crown_radius: float = 25.0,
                  crown_height: float = 8.0, axis_deg: float = 45.0,
                  sections: int = 96) -> trimesh.Trimesh:
    """A block with a cylindrical crown: a curved surface turning away from the camera (mm).

    A box ``size = (L, W, H)`` (z in [0, H]) topped, toward +z, by the part of a cylinder of
    `crown_radius` that rises `crown_height` above the box's face, its axis level and turned
    `axis_deg` from x about z, clipped to the box's outline. Where the crown turns more than
    about 60 degrees from level away from the camera (the cell's camera looks up at 30
    degrees from z_T), the sheet lights it and the camera does not see it: the stripe fades
    out on a smooth surface. The cylinder has `sections` facets around (creases of
    360 / sections degrees).

    Returns
    -------
    trimesh.Trimesh
        Watertight.
    """
    _require_boolean_engine()
    import trimesh

    length, width, height = (float(s) for s in size)
    rc, hc = float(crown_radius), float(crown_height)
    if not (min(length, width, height) > 0 and 0 < hc < rc):
        raise ValueError(f"crown {rc} x {hc} mm does not fit the block {size!r}")
    o = _CUT_OVERSHOOT
    block = trimesh.creation.box(extents=(length, width, height))
    block.apply_translation((0.0, 0.0, height / 2.0))
    span = 2.0 * float(np.hypot(length, width))
    cylinder = trimesh.creation.cylinder(radius=rc, height=span, sections=int(sections))
    cylinder.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    cylinder.apply_transform(trimesh.transformations.rotation_matrix(np.radians(axis_deg),
                                                                     [0, 0, 1]))
    cylinder.apply_translation((0.0, 0.0, height + hc - rc))
    clip = trimesh.creation.box(extents=(length, width, hc + o))
    clip.apply_translation((0.0, 0.0, height + (hc - o) / 2.0))
    crown = trimesh.boolean.intersection([cylinder, clip], engine="manifold")
    mesh = trimesh.boolean.union([block, crown], engine="manifold")
    if not mesh.is_watertight:
        raise RuntimeError("boolean union gave a mesh that is not watertight")
    mesh.metadata["features"] = {"size": (length, width, height), "crown_radius": rc,
                                 "crown_height": hc, "axis_deg": float(axis_deg),
                                 "sections": int(sections)}
    return mesh


#: The example parts `write_example_parts` writes: file name -> (maker, unit of the file).
EXAMPLE_PARTS = {
    "demo_block.stl": (block_with_holes_and_steps, "mm"),
    "bracket.stl": (bracket_with_two_holes, "inch"),
    "dome.stl": (faceted_dome, "mm"),
    "fan_disk.stl": (fan_disk, "mm"),
    "crowned_block.stl": (crowned_block, "mm"),
}
_MM_PER_UNIT = {"mm": 1.0, "inch": 25.4}


def write_example_parts(folder) -> dict:
    """Write the example parts into ``folder`` (made if missing) as binary STL files, each in
    its unit (the bracket in inches, as many CAD exports are), with ``manifest.json`` naming
    the units (``{"bracket.stl": {"units": "inch"}}``: ``flyscan plan`` reads it). Returns
    the manifest."""
    import json
    from pathlib import Path

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    manifest = {}
    for name, (make, units) in EXAMPLE_PARTS.items():
        mesh = make()
        mesh.apply_scale(1.0 / _MM_PER_UNIT[units])
        mesh.export(folder / name, file_type="stl")
        manifest[name] = {"units": units, "source": f"procedural:{make.__name__}"}
    (folder / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    return manifest
