"""Tests of simulator.parts: units, loading errors, cleaning, grasp, fit, the procedural block."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from numpy.testing import assert_allclose

from simulator import parts
from simulator.parts import (
                             PartError, block_with_holes_and_steps, centred_grasp, check_fits,
                             load_part, load_reference_part, part_from_mesh,
                             )

# Tolerance on lengths after unit conversion and float32 STL storage, mm.
LENGTH_TOL_MM = 1e-4


def _box_file(tmp_path, extents, name="box.stl", offset=(0.0, 0.0, 0.0)):
    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_translation(offset)
    path = tmp_path / name
    mesh.export(path)
    return path


@pytest.mark.parametrize("unit, factor, raw", [
    ("mm", 1.0, (60.0, 40.0, 20.0)),
    ("cm", 10.0, (6.0, 4.0, 2.0)),
    ("m", 1000.0, (0.06, 0.04, 0.02)),
    ("inch", 25.4, (2.0, 1.5, 0.5)),
    ("metre", 1000.0, (0.06, 0.04, 0.02)),  # spelling used by the reference manifest
    ("INCH", 25.4, (2.0, 1.5, 0.5)),
])
def test_units_conversion(tmp_path, unit, factor, raw):
    raw = np.asarray(raw)
    path = _box_file(tmp_path, raw)
    part = load_part(path, unit)
    assert part.units in parts.UNITS_MM
    assert_allclose(part.extents, raw * factor, atol=LENGTH_TOL_MM)
    assert part.name == "box" and part.source == str(path)


def test_inch_box(tmp_path):
    path = _box_file(tmp_path, (2.0, 1.0, 0.5))
    part = load_part(path, "inch", name="bracket")
    assert part.name == "bracket"
    assert_allclose(part.extents, [50.8, 25.4, 12.7], atol=LENGTH_TOL_MM)


def test_the_version_names_the_content_not_the_file(tmp_path):
    box = trimesh.creation.box(extents=(30.0, 20.0, 10.0))
    box.export(tmp_path / "box.ply")
    box.export(tmp_path / "box.obj")
    ply = load_part(tmp_path / "box.ply", "mm", name="one")
    obj = load_part(tmp_path / "box.obj", "mm", name="two")
    assert ply.version == obj.version and len(ply.version) == 16
    assert load_part(tmp_path / "box.ply", "cm").version != ply.version
    assert load_part(tmp_path / "box.ply", "mm", grasp="identity").version != ply.version
    longer = _box_file(tmp_path, (30.0, 20.0, 10.5), name="longer.stl")
    assert load_part(longer, "mm").version != ply.version


def test_unknown_unit(tmp_path):
    path = _box_file(tmp_path, (10, 10, 10))
    with pytest.raises(PartError, match=r"unknown unit 'furlong'; allowed: mm, cm, m, inch"):
        load_part(path, "furlong")


def test_missing_file(tmp_path):
    with pytest.raises(PartError, match="part file not found: .*nope.stl"):
        load_part(tmp_path / "nope.stl", "mm")


def test_empty_file(tmp_path):
    path = tmp_path / "empty.stl"
    path.write_bytes(b"")
    with pytest.raises(PartError, match="part file is empty: .*empty.stl"):
        load_part(path, "mm")


@pytest.mark.parametrize("suffix, match", [
    (".stl", "neither a binary STL .* nor an ASCII STL"),
    (".obj", "must be text"),
    (".ply", "Not a ply file"),
])
def test_garbage_file(tmp_path, suffix, match):
    path = tmp_path / f"garbage{suffix}"
    path.write_bytes(np.random.default_rng(7).integers(0, 256, 300, dtype=np.uint8).tobytes())
    with pytest.raises(PartError, match=f"cannot read part file .*garbage{suffix}.*{match}"):
        load_part(path, "mm")


def test_text_garbage_stl(tmp_path):
    path = tmp_path / "notes.stl"
    path.write_text("solid x\nthis is not a facet\nendsolid\n")
    with pytest.raises(PartError, match="notes.stl"):
        load_part(path, "mm")


def test_no_triangles(tmp_path):
    path = tmp_path / "points.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(PartError, match="has no triangles"):
        load_part(path, "mm")


def test_unsupported_format(tmp_path):
    path = tmp_path / "part.step"
    path.write_text("ISO-10303-21;")
    with pytest.raises(PartError, match="unsupported format '.step'"):
        load_part(path, "mm")


def test_nan_vertices(tmp_path):
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 0\nv 10 0 0\nv 0 nan 0\nv 0 0 10\nf 1 2 3\nf 1 2 4\n")
    with pytest.raises(PartError, match="NaN or infinite"):
        load_part(path, "mm")


def test_nan_vertices_in_memory():
    mesh = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, np.inf, 0]], [[0, 1, 2]], process=False)
    with pytest.raises(PartError, match="1 vertices with NaN or infinite"):
        part_from_mesh(mesh, name="bad")


def test_open_mesh_loads(tmp_path):
    box = trimesh.creation.box(extents=(30, 20, 10))
    open_mesh = trimesh.Trimesh(box.vertices, box.faces[:-2])  # drop one face of the box
    path = tmp_path / "open.stl"
    open_mesh.export(path)
    part = load_part(path, "mm")
    assert not part.mesh.is_watertight
    assert len(part.mesh.faces) == 10
    assert_allclose(part.extents, [30, 20, 10], atol=LENGTH_TOL_MM)


def test_degenerate_faces_and_unreferenced_vertices_dropped(tmp_path):
    box = trimesh.creation.box(extents=(30, 20, 10))
    v = np.vstack([box.vertices, [[100.0, 100.0, 100.0]]])  # unreferenced
    degenerate = [[0, 0, 1], [0, 1, 1]]  # repeated indices: zero area
    path = tmp_path / "degenerate.obj"
    lines = [f"v {a} {b} {c}" for a, b, c in v]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.vstack([box.faces, degenerate])]
    path.write_text("\n".join(lines) + "\n")
    part = load_part(path, "mm")
    assert len(part.mesh.faces) == 12
    assert len(part.mesh.vertices) == 8
    assert part.mesh.is_watertight
    assert_allclose(part.extents, [30, 20, 10], atol=LENGTH_TOL_MM)


@pytest.mark.parametrize("extents, unit, hint", [
    ((0.05, 0.02, 0.01), "mm", "smaller .* did you mean units='m'"),
    ((2.0, 1.0, 0.5), "mm", "smaller .* did you mean units='inch'"),
    ((150.0, 40.0, 20.0), "m", "larger .* did you mean units='mm'"),
])
def test_implausible_size_is_refused(tmp_path, extents, unit, hint):
    path = _box_file(tmp_path, extents)
    with pytest.raises(PartError, match=hint):
        load_part(path, unit)


def test_a_misplaced_pose_is_checked_against_the_volume():
    part = part_from_mesh(block_with_holes_and_steps(), name="block")
    lifted = np.eye(4)
    lifted[2, 3] = -6.0  # 6 mm up into the gripper: beyond the tilt tolerance
    with pytest.raises(PartError, match="6.0 mm into the gripper"):
        check_fits(part, pose=lifted @ part.grasp)
    lifted[2, 3] = -4.0  # within it (a tilt lifts an edge by as much)
    check_fits(part, pose=lifted @ part.grasp)
    turned = np.eye(4)
    turned[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # 90 degrees about z: 40 x 60 mm
    check_fits(part, pose=turned @ part.grasp)
    with pytest.raises(PartError, match="outside the inspection volume"):
        check_fits(part, pose=np.array([[1, 0, 0, 60.0], [0, 1, 0, 0], [0, 0, 1, 0],
                                        [0, 0, 0, 1]]) @ part.grasp)


def test_centred_grasp(tmp_path):
    path = _box_file(tmp_path, (30.0, 20.0, 10.0), offset=(100.0, -50.0, 7.0))
    part = load_part(path, "mm")
    g = part.grasp
    assert_allclose(g[:3, :3], np.eye(3))
    assert_allclose(g, centred_grasp(part.mesh))
    v = part.vertices_t()
    assert_allclose(v.min(axis=0), [-15.0, -10.0, 0.0], atol=LENGTH_TOL_MM)
    assert_allclose(v.max(axis=0), [15.0, 10.0, 10.0], atol=LENGTH_TOL_MM)
    assert not g.flags.writeable


@pytest.mark.parametrize("extents, hanging", [((14.0, 44.0, 47.0), 14.0),
                                              ((44.0, 14.0, 47.0), 14.0),
                                              ((44.0, 47.0, 14.0), 14.0)])
def test_flat_grasp_hangs_the_smallest_extent_along_z(tmp_path, extents, hanging):
    path = _box_file(tmp_path, extents, offset=(5.0, -3.0, 2.0))
    part = load_part(path, "mm", grasp="flat")
    g = part.grasp
    assert_allclose(g[:3, :3] @ g[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(g[:3, :3]) > 0
    v = part.vertices_t()
    assert_allclose(v.min(axis=0)[2], 0.0, atol=LENGTH_TOL_MM)
    assert_allclose(v.max(axis=0)[2], hanging, atol=LENGTH_TOL_MM)
    assert_allclose(v.min(axis=0)[:2], -v.max(axis=0)[:2], atol=LENGTH_TOL_MM)  # centred
    assert sorted(np.ptp(v, axis=0)) == pytest.approx(sorted(extents))
    if extents[2] == hanging:  # already flat: the centred grasp itself
        assert_allclose(g, centred_grasp(part.vertices))


def test_a_grasp_by_an_unknown_name_is_refused(tmp_path):
    with pytest.raises(PartError, match="grasp must be one of centred, flat, identity"):
        load_part(_box_file(tmp_path, (10.0, 10.0, 10.0)), "mm", grasp="upside-down")


def test_check_fits(tmp_path):
    check_fits(load_part(_box_file(tmp_path, (150.0, 150.0, 100.0)), "mm"))
    big = load_part(_box_file(tmp_path, (160.0, 40.0, 20.0), name="big.stl"), "mm")
    with pytest.raises(PartError, match=r"part .big. is 160\.0 x 40\.0 x 20\.0 mm in {T}; "
                                        r"the inspection volume is 150 x 150 x 100 mm"):
        check_fits(big)
    check_fits(big, volume_mm=(200.0, 200.0, 200.0))


def test_check_fits_uses_grasp_rotation():
    box = trimesh.creation.box(extents=(140.0, 40.0, 20.0))
    turned = np.eye(4)
    turned[:3, :3] = trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0])[:3, :3]
    part = part_from_mesh(box, name="upright", grasp=turned)
    with pytest.raises(PartError, match="20.0 x 40.0 x 140.0 mm"):
        check_fits(part)


def test_part_from_mesh_converts_and_copies():
    box = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    part = part_from_mesh(box, name="b", units="cm", source="procedural:box")
    assert_allclose(part.extents, [20.0, 10.0, 5.0])
    assert_allclose(box.extents, [2.0, 1.0, 0.5])  # input untouched
    assert part.source == "procedural:box" and part.units == "cm"


def _hole_area(radius, sections):
    return 0.5 * sections * radius**2 * np.sin(2 * np.pi / sections)  # inscribed polygon


def test_block_geometry():
    mesh = block_with_holes_and_steps()
    f = mesh.metadata["features"]
    (length, width, height) = f["size"]
    assert mesh.is_watertight and mesh.is_volume
    assert_allclose(mesh.bounds, [[-30, -20, 0], [30, 20, 20]], atol=1e-9)
    hole = _hole_area(4.0, f["hole_sections"])
    step = f["steps"][0]
    expected = (length * width * height - hole * height - hole * f["blind_holes"][0]["depth"]
                - (length / 2 - step["x_min"]) * width * step["depth"])
    assert_allclose(mesh.volume, expected, rtol=1e-9)
    assert_allclose(centred_grasp(mesh), np.eye(4), atol=1e-12)


def test_block_holes_and_step_seen_by_rays():
    mesh = block_with_holes_and_steps()
    f = mesh.metadata["features"]
    height = f["size"][2]
    # Rays from beyond the max-z face (the side the scanner sees) travelling in -z: the first
    # hit is the height of the surface there.
    (tx, ty) = f["through_holes"][0]["xy"]
    (bx, by) = f["blind_holes"][0]["xy"]
    step = f["steps"][0]
    xs = [(tx, ty), (bx, by), (step["x_min"] + 5.0, 0.0), (-5.0, 10.0)]
    origins = np.array([[x, y, height + 10.0] for x, y in xs])
    dirs = np.tile([0.0, 0.0, -1.0], (len(xs), 1))
    locs, ray_idx, _ = mesh.ray.intersects_location(origins, dirs, multiple_hits=False)
    first = {int(i): loc[2] for i, loc in zip(ray_idx, locs)}
    assert 0 not in first  # the through hole: nothing in the way
    assert_allclose(first[1], height - f["blind_holes"][0]["depth"], atol=1e-6)
    assert_allclose(first[2], height - step["depth"], atol=1e-6)
    assert_allclose(first[3], height, atol=1e-6)


def test_block_rejects_bad_features():
    with pytest.raises(ValueError, match="hole_radius"):
        block_with_holes_and_steps(hole_radius=25.0)
    with pytest.raises(ValueError, match="blind_depth"):
        block_with_holes_and_steps(blind_depth=30.0)


def test_block_as_part_fits():
    part = part_from_mesh(block_with_holes_and_steps(), name="block", source="procedural:block")
    check_fits(part)
    assert_allclose(part.extents_t, [60.0, 40.0, 20.0])


def test_reference_part_unknown(tmp_path, monkeypatch):
    (tmp_path / "manifest.json").write_text('{"a.stl": {"units": "mm"}}')
    monkeypatch.setenv("FLYSCAN_MESHES", str(tmp_path))
    with pytest.raises(PartError, match="available: a.stl"):
        load_reference_part("nope")


def test_reference_part_from_env(tmp_path, monkeypatch):
    _box_file(tmp_path, (2.0, 1.0, 0.5), name="Bracket.STL")
    (tmp_path / "manifest.json").write_text('{"Bracket.STL": {"units": "inch", "faces": 12}}')
    monkeypatch.setenv("FLYSCAN_MESHES", str(tmp_path))
    part = load_reference_part("bracket")
    assert part.name == "Bracket" and part.units == "inch"
    assert_allclose(part.extents, [50.8, 25.4, 12.7], atol=LENGTH_TOL_MM)


def test_reference_meshes_missing(tmp_path, monkeypatch):
    monkeypatch.setenv("FLYSCAN_MESHES", str(tmp_path / "none"))
    with pytest.raises(PartError, match="FLYSCAN_MESHES"):
        load_reference_part("idler_riser")
