"""The procedural parts: watertight, their dimensions, their creases and holes."""
import numpy as np
import pytest
from numpy.testing import assert_allclose

from simulator.parts import (bracket_with_two_holes, centred_grasp, check_fits, crowned_block,
                             faceted_dome, fan_disk, part_from_mesh)

#: Float round-off of trimesh's and manifold's geometry, mm (and degrees for angles).
GEOMETRY_TOL = 1e-6
#: Soft creases: under the 30-degree feature angle of the edge model and the evaluation.
FEATURE_ANGLE_DEG = 30.0


def _crease_angles(mesh) -> np.ndarray:
    """Degrees between neighbouring faces, coplanar pairs (a facet's triangles) left out."""
    angles = np.degrees(np.asarray(mesh.face_adjacency_angles))
    return angles[angles > 1e-3]


@pytest.mark.parametrize("slopes", [(0.0, 18.0, 38.0, 58.0, 78.0), (0.0, 15.0, 30.0, 45.0, 60.0,
                                                                      75.0)])
def test_faceted_dome_is_a_convex_dome_of_soft_creases(slopes):
    mesh = faceted_dome(30.0, 8.0, slopes_deg=slopes, sectors=12, tier_drop=3.0)
    f = mesh.metadata["features"]
    assert mesh.is_watertight and mesh.is_volume and mesh.is_convex
    height = 8.0 + 3.0 * (len(slopes) - 1)
    assert_allclose(mesh.bounds, [[-30, -30, 0], [30, 30, height]], atol=GEOMETRY_TOL)
    assert_allclose(f["crease_deg"], np.diff(slopes))
    assert_allclose(centred_grasp(mesh), np.eye(4), atol=GEOMETRY_TOL)
    # every crease between the dome's facets is soft; the sharp ones are its rim and base
    top = mesh.face_normals[:, 2] > GEOMETRY_TOL
    adjacency = np.asarray(mesh.face_adjacency)
    on_dome = top[adjacency[:, 0]] & top[adjacency[:, 1]]
    angles = np.degrees(mesh.face_adjacency_angles)
    soft = angles[on_dome & (angles > 1e-3)]
    assert len(soft) >= 12 * (len(slopes) - 1)
    assert soft.max() < FEATURE_ANGLE_DEG
    # each tier's facets lie at its slope from level
    tilt = np.degrees(np.arccos(np.clip(mesh.face_normals[top, 2], -1, 1)))
    for slope in slopes:
        assert np.any(np.abs(tilt - slope) < 1.0)


def test_faceted_dome_refuses_tiers_that_do_not_fit():
    with pytest.raises(ValueError, match="slopes_deg"):
        faceted_dome(slopes_deg=(0.0, 40.0, 20.0))
    with pytest.raises(ValueError, match="radius"):
        faceted_dome(5.0, slopes_deg=(0.0, 5.0, 10.0), tier_drop=4.0)


def test_fan_disk_has_a_hub_of_soft_creases_and_sharp_blades():
    mesh = fan_disk()
    f = mesh.metadata["features"]
    assert mesh.is_watertight and mesh.is_volume
    lo, hi = mesh.bounds
    assert_allclose(lo, [-45.0, -45.0, 0.0], atol=GEOMETRY_TOL)
    assert_allclose(hi[:2], [45.0, 45.0], atol=GEOMETRY_TOL)
    hub_top = f["thickness"] + f["hub_height"]
    assert hi[2] == pytest.approx(hub_top, abs=GEOMETRY_TOL)  # the hub stands out the farthest
    angles = _crease_angles(mesh)
    assert np.sum((angles > 15.0) & (angles < FEATURE_ANGLE_DEG)) >= 40  # the hub's tiers
    assert np.sum(angles > 60.0) >= 8 * 8  # the blades' plate edges
    # a ray up the axis meets the hub's flat top; one between hub and blades the disc
    origins = np.array([[0.0, 0.0, 100.0], [30.0 * np.cos(np.pi / 8), 30.0 * np.sin(np.pi / 8),
                                             100.0]])
    hits, rays, _ = mesh.ray.intersects_location(origins, np.tile([0.0, 0.0, -1.0], (2, 1)),
                                                 multiple_hits=False)
    first = {int(r): h[2] for r, h in zip(rays, hits)}
    assert first[0] == pytest.approx(hub_top, abs=GEOMETRY_TOL)
    assert first[1] == pytest.approx(f["thickness"], abs=GEOMETRY_TOL)


def test_bracket_has_two_through_holes_and_a_5_mm_step():
    mesh = bracket_with_two_holes()
    f = mesh.metadata["features"]
    length, width, t = f["size"]
    assert mesh.is_watertight and mesh.is_volume
    assert_allclose(mesh.bounds, [[-length / 2, -width / 2, 0.0],
                                  [length / 2, width / 2, t + 5.0]], atol=GEOMETRY_TOL)
    sections = f["hole_sections"]
    holes = sum(0.5 * sections * h["radius"] ** 2 * np.sin(2 * np.pi / sections)
                * (t if h["xy"][0] < f["step"]["x_min"] else t + 5.0)
                for h in f["through_holes"])
    expected = length * width * t + (length / 2 - f["step"]["x_min"]) * width * 5.0 - holes
    assert_allclose(mesh.volume, expected, rtol=1e-9)
    # rays down through both holes meet nothing; beside them the plate and the step's top
    xs = [h["xy"] for h in f["through_holes"]] + [(-20.0, 12.0), (25.0, 12.0)]
    origins = np.array([[x, y, 50.0] for x, y in xs])
    _, rays, _ = mesh.ray.intersects_location(origins, np.tile([0.0, 0.0, -1.0], (4, 1)),
                                              multiple_hits=False)
    assert sorted(rays.tolist()) == [2, 3]
    with pytest.raises(ValueError, match="holes"):
        bracket_with_two_holes(hole_radii=(9.0, 3.0))


def test_crowned_block_is_a_curved_surface_over_a_block():
    mesh = crowned_block()
    f = mesh.metadata["features"]
    assert mesh.is_watertight and mesh.is_volume
    length, width, height = f["size"]
    assert_allclose(mesh.bounds, [[-length / 2, -width / 2, 0.0],
                                  [length / 2, width / 2, height + f["crown_height"]]],
                    atol=GEOMETRY_TOL)
    # the crown's facets turn by 360 / sections degrees: a smooth surface to the scanner
    on_crown = np.asarray(mesh.face_adjacency_angles) < np.radians(5.0)
    assert on_crown.sum() > f["sections"] // 2


@pytest.mark.parametrize("build", [faceted_dome, fan_disk, bracket_with_two_holes,
                                   crowned_block])
def test_procedural_parts_fit_the_inspection_volume(build):
    part = part_from_mesh(build(), name=build.__name__)
    check_fits(part)
    assert part.model_edges.sharp.any()
