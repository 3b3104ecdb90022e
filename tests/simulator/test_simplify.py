"""The simplification study: the ray-by-ray deviation, and the coarsest mesh within tolerance."""
import numpy as np
import pytest
import trimesh

from simulator.parts import part_from_mesh
from simulator.simplify import cloud_deviation, coarsest_simplification, simplify_part
from simulator.virtual_setup import VirtualSetup, predict_cloud

pytest.importorskip("pymeshlab")

SETUP = VirtualSetup(laser=[0.0, -130.3, 400.0], camera=[0.0, 94.7, 439.7], step_mm=0.5,
                     rays_per_line=200)


def _part(mesh, name):
    return part_from_mesh(mesh, name=name, grasp=np.eye(4))


@pytest.fixture(scope="module")
def cube():
    box = trimesh.creation.box(extents=(40.0, 40.0, 40.0))
    box.apply_translation((0.0, 0.0, 20.0))
    return _part(box, "cube")


def test_identical_clouds_deviate_by_nothing(cube):
    cloud = predict_cloud(cube, SETUP)
    d = cloud_deviation(cloud, cloud)
    assert d["rms_um"] == 0.0 and d["missing"] == d["extra"] == 0
    assert d["matched"] == len(cloud)


def test_a_surface_moved_along_its_normal_deviates_by_the_move(cube):
    ref = predict_cloud(cube, SETUP)
    nearer = cube.mesh.copy()
    nearer.apply_translation((0.0, 0.0, 0.003))  # the lit face 3 um nearer the light
    moved = predict_cloud(_part(nearer, "nearer"), SETUP.with_fan(ref.fan))
    d = cloud_deviation(ref, moved)
    assert d["rms_um"] == pytest.approx(3.0, abs=1e-3)
    assert d["max_um"] == pytest.approx(3.0, abs=1e-3)
    assert d["switched"] == d["missing"] == d["extra"] == 0


def test_a_ray_on_another_surface_counts_as_coverage_not_error(cube):
    """A step 2 mm high across part of the face: its rays switch surface."""
    ref = predict_cloud(cube, SETUP)
    stepped = trimesh.boolean.union(
        [cube.mesh, trimesh.creation.box(extents=(10.0, 40.0, 2.0),
                                         transform=trimesh.transformations.translation_matrix(
                                             (15.0, 0.0, 40.0)))], engine="manifold")
    other = predict_cloud(_part(stepped, "stepped"), SETUP.with_fan(ref.fan))
    d = cloud_deviation(ref, other)
    assert d["rms_um"] < 1e-6  # the rest of the face did not move
    # The top of the step (x in [10, 20]) is a quarter of the face.
    assert d["switched"] / len(ref) == pytest.approx(0.25, abs=0.03)
    assert d["coverage_change"] >= d["switched"] / len(ref)


def test_clouds_of_different_sweeps_are_not_compared(cube):
    other = VirtualSetup(laser=SETUP.laser, camera=SETUP.camera, step_mm=0.25, rays_per_line=200)
    ref = predict_cloud(cube, SETUP)
    with pytest.raises(ValueError, match="different sweeps"):
        cloud_deviation(ref, predict_cloud(cube, other))
    moved = np.eye(4)
    moved[0, 3] = 1.0
    with pytest.raises(ValueError, match="different sweeps"):
        cloud_deviation(ref, predict_cloud(cube, SETUP, pose=moved))


def test_a_subdivided_cube_simplifies_back_to_the_same_cloud(cube):
    v, f = cube.mesh.vertices, cube.mesh.faces
    for _ in range(3):
        v, f = trimesh.remesh.subdivide(v, f)
    fine = _part(trimesh.Trimesh(v, f, process=False), "fine-cube")
    assert len(fine.mesh.faces) == 768
    coarse = simplify_part(fine, 12)
    assert len(coarse.mesh.faces) == 12 and coarse.mesh.is_watertight
    ref = predict_cloud(fine, SETUP)
    d = cloud_deviation(ref, predict_cloud(coarse, SETUP.with_fan(ref.fan)))
    assert d["rms_um"] < 0.01 and d["coverage_change"] < 0.01


def test_the_study_picks_the_coarsest_level_within_tolerance():
    ball = trimesh.creation.icosphere(subdivisions=4, radius=25.0)
    ball.apply_translation((0.0, 0.0, 30.0))
    sphere = _part(ball, "sphere")
    # A sphere cannot lose many facets without moving its surface: no halving keeps 5 um,
    # and the bisection finds the few it can lose.
    strict = coarsest_simplification(sphere, SETUP, min_faces=300, repeats=1)
    halvings = [lv for lv in strict["levels"] if lv["faces"] <= 2560]
    assert halvings and all(lv["rms_um"] > 5.0 for lv in halvings)
    chosen = strict["chosen"]
    assert chosen is not None and 2560 < chosen["faces"] < 5120 and chosen["rms_um"] <= 5.0
    assert all(lv["rms_um"] > 5.0 or lv["coverage_change"] > 0.01
               for lv in strict["levels"] if lv["faces"] < chosen["faces"])
    # ... while a looser tolerance admits the first halvings, and the coarsest is chosen.
    study = coarsest_simplification(sphere, SETUP, tolerance_um=50.0, max_coverage_change=0.02,
                                    min_faces=300, refine=0, repeats=1)
    faces = [lv["faces"] for lv in study["levels"]]
    assert faces == sorted(faces, reverse=True) and faces[0] <= 2560
    passing = [lv for lv in study["levels"]
               if lv["rms_um"] <= 50.0 and lv["coverage_change"] <= 0.02]
    assert 0 < len(passing) < len(study["levels"])
    assert study["chosen"]["faces"] == min(lv["faces"] for lv in passing)
    assert study["full"]["faces"] == 5120
    # The error grows as the mesh shrinks.
    rms = [lv["rms_um"] for lv in study["levels"]]
    assert rms == sorted(rms)
