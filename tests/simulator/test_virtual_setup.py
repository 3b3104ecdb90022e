"""The paper's scan simulator (section III) against analytic scenes and independent checks."""
from dataclasses import replace

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from scanner_core.io.ply import read_ply
from simulator.parts import Part, part_from_mesh
from simulator.virtual_setup import (MAIN_VIEW, SetupError, VirtualSetup, predict_cloud,
                                     reference_setup, save_predicted_cloud)

# The reference cell's geometry in {T} at the start of the pass (laser 400 mm below the TCP,
# the camera 225 mm ahead along the motion and 30 degrees off the sheet).
LASER = np.array([0.0, -130.3, 400.0])
CAMERA = LASER + np.array([0.0, 225.0, 39.7])


def _part(mesh, name="part"):
    return part_from_mesh(mesh, name=name, grasp=np.eye(4))


def _setup(step=0.7, rays=101, **kw):
    return VirtualSetup(laser=kw.pop("laser", LASER), camera=kw.pop("camera", CAMERA),
                        step_mm=step, rays_per_line=rays, **kw)


@pytest.fixture(scope="module")
def cube():
    box = trimesh.creation.box(extents=(40.0, 40.0, 40.0))
    box.apply_translation((0.0, 0.0, 20.0))  # hangs z_T in [0, 40]: its z = 40 face is lit
    return _part(box, "cube")


@pytest.fixture(scope="module")
def sphere():
    ball = trimesh.creation.icosphere(subdivisions=5, radius=25.0)
    ball.apply_translation((0.0, 0.0, 30.0))
    return _part(ball, "sphere")


# ------------------------------------------------------------------------------------------
# Cube: every point on the lit face, on its ray, at the analytic step positions
# ------------------------------------------------------------------------------------------

def test_cube_points_lie_on_the_lit_face_at_the_analytic_positions(cube):
    setup = _setup()
    cloud = predict_cloud(cube, setup)
    # Lines every 0.7 mm from y = -130.3 while the sheet is within y in [-20, 20].
    first, last = int(np.ceil(110.3 / 0.7)), int(np.floor(150.3 / 0.7))
    assert cloud.steps == (first, last)
    n_lines = last - first + 1
    assert cloud.rays_cast == n_lines * 101
    # The fan just covers the lit face: every ray but the two grazing its edges must hit it,
    # and the camera (above the face's plane) sees all of it.
    assert (n_lines * 99) <= len(cloud) <= n_lines * 101
    assert cloud.first_hits == cloud.facing == len(cloud)
    np.testing.assert_allclose(cloud.points[:, 2], 40.0, atol=1e-9)
    assert np.all(np.abs(cloud.points[:, :2]) <= 20.0 + 1e-9)
    np.testing.assert_allclose(cloud.points[:, 1], -130.3 + 0.7 * cloud.step, atol=1e-9)
    # Each point lies on its own ray from where the light source stood.
    origin = setup.laser_at(cloud.step)
    direction = cloud.fan[cloud.ray]
    t = (cloud.points - origin) @ np.array([0.0, 0.0, 1.0]) / direction[:, 2]
    np.testing.assert_allclose(origin + t[:, None] * direction, cloud.points, atol=1e-9)
    np.testing.assert_allclose(cloud.normals, [[0.0, 0.0, 1.0]] * len(cloud), atol=1e-12)


def test_camera_behind_the_lit_face_sees_nothing(cube):
    cloud = predict_cloud(cube, _setup(camera=LASER + [0.0, 225.0, -370.0]))  # z_T = 30 < 40
    assert cloud.first_hits > 0
    assert len(cloud) == 0 and cloud.facing == 0
    assert cloud.points.shape == (0, 3) and cloud.step.shape == (0,)


# ------------------------------------------------------------------------------------------
# Sphere: hit counts and the visible fraction against the exact sphere
# ------------------------------------------------------------------------------------------

def _analytic_sphere(setup, cloud, centre, radius):
    """Per swept ray: hits the exact sphere, and its hit is visible from the camera."""
    steps = np.arange(cloud.steps[0], cloud.steps[1] + 1)
    origin = np.repeat(setup.laser_at(steps), len(cloud.fan), axis=0)
    direction = np.tile(cloud.fan, (len(steps), 1))
    oc = origin - centre
    b = np.einsum("ij,ij->i", oc, direction)
    disc = b * b - (np.einsum("ij,ij->i", oc, oc) - radius ** 2)
    hit = disc > 0
    t = -b[hit] - np.sqrt(disc[hit])
    p = origin[hit] + t[:, None] * direction[hit]
    camera = np.repeat(setup.camera_at(steps), len(cloud.fan), axis=0)[hit]
    visible = np.einsum("ij,ij->i", p - centre, camera - p) > 0
    return hit, visible


def test_sphere_hits_and_visible_fraction_match_the_exact_sphere(sphere):
    setup = _setup(step=0.25, rays=400)
    cloud = predict_cloud(sphere, setup)
    centre = np.array([0.0, 0.0, 30.0])
    mesh = sphere.mesh
    inscribed = np.min(np.abs(np.einsum("ij,ij->i", mesh.face_normals,
                                        mesh.triangles_center - centre)))
    r = np.linalg.norm(cloud.points - centre, axis=1)
    assert r.min() >= inscribed - 1e-9 and r.max() <= 25.0 + 1e-9
    hit_outer, vis_outer = _analytic_sphere(setup, cloud, centre, 25.0)
    hit_inner, _ = _analytic_sphere(setup, cloud, centre, inscribed)
    assert hit_inner.sum() <= cloud.first_hits <= hit_outer.sum()
    # Faceting moves the terminator by a fraction of a facet: counts agree to 0.5 %.
    assert abs(len(cloud) - vis_outer.sum()) <= 0.005 * vis_outer.sum()
    assert abs(len(cloud) / cloud.first_hits - vis_outer.mean()) < 0.005
    assert 0.2 < vis_outer.mean() < 0.95  # the camera sees part, not all, of the lit cap


# ------------------------------------------------------------------------------------------
# Occlusion behind a step, checked independently of Embree
# ------------------------------------------------------------------------------------------

def test_step_hides_the_recess_floor_from_the_camera(block_part):
    # Turned -90 degrees about z, the block's recess (floor at z = 15 mm, from x > 15 mm)
    # lies at y < -15 mm, and the higher face (z = 20 mm) stands between it and the camera.
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("z", -90, degrees=True).as_matrix()
    step = 0.1
    cloud = predict_cloud(block_part, _setup(step=step, rays=300), pose=pose)
    floor = np.abs(cloud.points[:, 2] - 15.0) < 1e-6
    assert floor.sum() > 1000
    # The camera ray from the floor at y clears the wall (y = -15, 5 mm high) only if
    # (-15 - y) > 5 * 225 / (439.7 - 15): the band next to the wall is hidden.
    hidden_from = -15.0 - 5.0 * 225.0 / (439.7 - 15.0)
    assert cloud.points[floor, 1].max() <= hidden_from + 1e-9
    assert cloud.points[floor, 1].max() >= hidden_from - step - 1e-9
    # The light reaches the band (the lit first hits include it); the camera does not.
    assert cloud.first_hits > cloud.facing > len(cloud)


@pytest.mark.parametrize("case", ["block", "sphere"])
def test_every_point_is_on_the_surface_and_seen_by_light_and_camera(case, block_part, sphere):
    """Checked with trimesh's own ray engine and closest-point query, not Embree."""
    part = {"block": block_part, "sphere": sphere}[case]
    setup = _setup(step=0.3, rays=200)
    cloud = predict_cloud(part, setup)
    rng = np.random.default_rng(7)
    pick = rng.choice(len(cloud), size=min(1500, len(cloud)), replace=False)
    p, steps = cloud.points[pick], cloud.step[pick]
    _, distance, _ = trimesh.proximity.closest_point(part.mesh, p)
    assert distance.max() < 1e-3  # on the surface within 1 um
    engine = trimesh.ray.ray_triangle.RayMeshIntersector(part.mesh)
    for name, source in (("laser", setup.laser_at(steps)), ("camera", setup.camera_at(steps))):
        direction = p - source
        length = np.linalg.norm(direction, axis=1)
        locations, ray_index, _ = engine.intersects_location(source, direction / length[:, None])
        nearest = np.full(len(p), np.inf)
        np.minimum.at(nearest, ray_index, np.linalg.norm(locations - source[ray_index], axis=1))
        # Nothing lies in front of the point by more than the 10 um surface tolerance.
        assert np.all(nearest >= length - 0.011), name
    # No point from the back side: the camera stands on the lit side of every point.
    camera_side = np.einsum("ij,ij->i", cloud.normals, setup.camera_at(cloud.step) - cloud.points)
    assert np.all(camera_side > 0)


# ------------------------------------------------------------------------------------------
# Determinism, frames, output
# ------------------------------------------------------------------------------------------

def test_same_inputs_give_the_same_cloud_whatever_the_threads(block_part):
    setup = _setup(step=0.2, rays=700)
    a = predict_cloud(block_part, setup, threads=2)
    b = predict_cloud(block_part, setup, threads=2)
    c = predict_cloud(block_part, setup, threads=1)
    for other in (b, c):
        for key in ("points", "normals", "step", "ray", "face"):
            np.testing.assert_array_equal(getattr(a, key), getattr(other, key))


def test_pose_moves_the_cloud_with_the_part(block_part):
    setup = _setup(step=0.5, rays=200)
    rot = np.eye(4)
    rot[:3, :3] = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    a = predict_cloud(block_part, setup)
    b = predict_cloud(block_part, setup, pose=rot)
    # Half-turned, the block shows its step on the other side (x < 0).
    step_a = np.abs(a.points[:, 2] - 15.0) < 1e-6
    step_b = np.abs(b.points[:, 2] - 15.0) < 1e-6
    assert a.points[step_a, 0].min() > 14.9 and b.points[step_b, 0].max() < -14.9
    # A quarter-step shift: the lines cross the part elsewhere, and the points, shifted
    # back, lie on the part where it stood before, between the unshifted lines.
    shift = np.eye(4)
    shift[:3, 3] = [0.0, 0.125, 0.0]
    moved = predict_cloud(block_part, setup, pose=shift)
    back = moved.points - [0.0, 0.125, 0.0]
    _, distance, _ = trimesh.proximity.closest_point(block_part.mesh, back[::40])
    assert distance.max() < 1e-3
    phase = ((back[:, 1] + 130.3) / 0.5) % 1.0
    np.testing.assert_allclose(phase, 0.75, atol=1e-9)
    assert abs(len(moved) - len(a)) < 0.05 * len(a)
    with pytest.raises(SetupError, match="rigid"):
        predict_cloud(block_part, setup, pose=np.diag([2.0, 2.0, 2.0, 1.0]))


def test_ply_carries_the_step_and_where_the_setup_stood(tmp_path, block_part, cell):
    setup = reference_setup(cell, step_mm=0.4, rays_per_line=300, mirrors=True)
    cloud = predict_cloud(block_part, setup)
    path = save_predicted_cloud(tmp_path / "predicted.ply", cloud)
    points, fields = read_ply(path)
    assert fields["step"].dtype.kind == "i"
    np.testing.assert_array_equal(fields["step"], cloud.step)
    np.testing.assert_allclose(points, cloud.points, atol=1e-4)  # float32 in the file
    header = path.read_bytes().split(b"end_header")[0].decode()
    values = {line.split()[1]: line.split()[2:] for line in header.splitlines()
              if line.startswith("comment ") and len(line.split()) > 2}
    laser0 = np.array(values["laser_step0"], float)
    motion = np.array(values["motion"], float)
    step_mm = float(values["step_mm"][0])
    # From the header alone: each point lies in the light plane of its step.
    laser = laser0 + fields["step"][:, None] * step_mm * motion
    assert np.abs((points - laser) @ motion).max() < 1e-3
    assert set(fields) >= {"seen_left", "seen_right", "ray", "nx"}


def test_reference_setup_is_the_cell_in_the_gripper_frame(cell):
    setup = reference_setup(cell, mirrors=True)
    pp = cell.pass_profile
    np.testing.assert_allclose(setup.laser, [0.0, pp.start_y_mm, pp.height_mm + 350.0])
    np.testing.assert_allclose(setup.motion, [0.0, 1.0, 0.0])
    # The mirror views are the camera reflected in the mirrors, taken to {T}.
    tcp = np.array([0.0, pp.start_y_mm, pp.height_mm])
    rot = cell.gripper_rotation_b
    for (name, view), mirror in zip(setup.views, cell.calibration.mirrors):
        view_b = rot @ view + tcp
        camera_b = cell.calibration.camera.origin
        plane = mirror.plane
        assert abs(plane.signed_distance(view_b[None])[0]
                   + plane.signed_distance(camera_b[None])[0]) < 1e-9, name
        assert name in ("left", "right")


def test_mirror_views_record_but_do_not_filter(block_part, cell):
    plain = predict_cloud(block_part, reference_setup(cell, step_mm=0.5, rays_per_line=300))
    with_views = predict_cloud(block_part, reference_setup(cell, step_mm=0.5, rays_per_line=300,
                                                           mirrors=True))
    np.testing.assert_array_equal(plain.points, with_views.points)
    for seen in with_views.seen.values():
        assert seen.shape == (len(plain),) and 0.3 < seen.mean() <= 1.0


# ------------------------------------------------------------------------------------------
# Bad input
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("step", [0.0, -0.5, float("nan"), float("inf")])
def test_step_must_be_positive(step):
    with pytest.raises(SetupError, match="step_mm"):
        _setup(step=step)


@pytest.mark.parametrize("rays", [1, 0, 2.5, True])
def test_rays_per_line_must_be_a_whole_number_of_two_or_more(rays):
    with pytest.raises(SetupError, match="rays_per_line"):
        _setup(rays=rays)


def test_positions_must_be_finite_points():
    with pytest.raises(SetupError, match="camera"):
        _setup(camera=[0.0, np.nan, 1.0])
    with pytest.raises(SetupError, match="laser"):
        _setup(laser=[0.0, 1.0])
    with pytest.raises(SetupError, match="view"):
        _setup(views=((MAIN_VIEW, [0.0, 0.0, 0.0]),))


def test_camera_inside_the_part_is_refused(cube):
    # Level with the light source along the motion, the camera's path stays in the cube.
    with pytest.raises(SetupError, match="camera is inside the part"):
        predict_cloud(cube, _setup(camera=[0.0, -130.3, 20.0]))


def test_camera_passing_through_the_part_is_refused():
    bar = trimesh.creation.box(extents=(20.0, 400.0, 20.0))
    bar.apply_translation((0.0, 0.0, 10.0))
    setup = VirtualSetup(laser=[0.0, -250.0, 400.0], camera=[0.0, -400.0, 10.0], step_mm=50.0,
                         rays_per_line=8)
    with pytest.raises(SetupError, match="camera passes through the part"):
        predict_cloud(_part(bar, "bar"), setup)


def test_light_source_beside_the_part_is_fine_but_level_with_it_is_refused(cube):
    beside = predict_cloud(cube, _setup(laser=[60.0, -130.3, 20.0], camera=[60.0, 94.7, 40.0]))
    np.testing.assert_allclose(beside.points[:, 0], 20.0, atol=1e-9)  # its x = 20 face
    with pytest.raises(SetupError, match="not wholly in front of the light source"):
        predict_cloud(cube, _setup(laser=[10.0, -130.3, 20.0]))


def test_too_many_rays_is_refused_before_casting(cube):
    with pytest.raises(SetupError, match="more than"):
        predict_cloud(cube, _setup(step=1e-5, rays=10_000))


def test_part_thinner_than_a_step_gives_an_empty_cloud():
    plate = trimesh.creation.box(extents=(20.0, 0.05, 20.0))
    plate.apply_translation((0.0, 0.3, 10.0))  # between the lines at y = 0 and y = 1
    cloud = predict_cloud(_part(plate, "plate"), VirtualSetup(
        laser=[0.0, 0.0, 400.0], camera=[0.0, 225.0, 440.0], step_mm=1.0, rays_per_line=50))
    assert cloud.rays_cast == 0 and cloud.first_hits == 0 and len(cloud) == 0
    assert cloud.steps == (0, -1) and cloud.points.shape == (0, 3)


def test_degenerate_faces_change_nothing(cube):
    mesh = cube.mesh
    v = np.vstack([mesh.vertices, [[5.0, 5.0, 40.0], [5.0, 5.0, 40.0]]])
    n = len(mesh.vertices)
    extra = np.array([[n, n + 1, n], [0, 0, 1], [n, n + 1, 0]])  # zero-area triangles
    dirty = Part(name="dirty", vertices=v, faces=np.vstack([mesh.faces, extra]),
                 source="test", units="mm", grasp=np.eye(4))
    setup = _setup(step=0.5, rays=150)
    clean_cloud, dirty_cloud = predict_cloud(cube, setup), predict_cloud(dirty, setup)
    np.testing.assert_allclose(dirty_cloud.points, clean_cloud.points, atol=1e-9)
    assert np.all(dirty_cloud.face < len(mesh.faces))


def test_open_mesh_shows_its_inside(cube):
    """A box without its lit face is a tray: the light and the camera see its floor inside."""
    mesh = cube.mesh
    keep = ~np.isclose(mesh.triangles_center[:, 2], 40.0)
    tray = _part(trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False), "tray")
    assert not tray.mesh.is_watertight
    setup = _setup(step=0.5, rays=150)
    cloud = predict_cloud(tray, setup)
    floor = np.abs(cloud.points[:, 2]) < 1e-9
    assert floor.sum() > 0.5 * len(cloud)
    # The floor's outward normal points away (-z); the light comes from inside: +z.
    np.testing.assert_allclose(cloud.normals[floor], [[0.0, 0.0, 1.0]] * floor.sum(), atol=1e-12)
    _, distance, _ = trimesh.proximity.closest_point(tray.mesh, cloud.points[::50])
    assert distance.max() < 1e-3


def test_progress_reports_every_ray_once(block_part):
    calls = []
    cloud = predict_cloud(block_part, _setup(step=0.05, rays=500),
                          progress=lambda done, total: calls.append((done, total)))
    done = [d for d, _ in calls]
    assert len(calls) > 2 and done == sorted(done)
    assert calls[-1] == (cloud.rays_cast, cloud.rays_cast)


# ------------------------------------------------------------------------------------------
# Eq. 4's step number is any integer: a setup given where it stands
# ------------------------------------------------------------------------------------------

def test_a_setup_standing_over_the_part_sweeps_negative_steps_too(cube, tmp_path):
    # At step 0 the light plane y = 0 cuts the cube (y in [-20, 20]) in two.
    step = 0.5
    setup = _setup(step=step, rays=101, laser=[0.0, 0.0, 400.0], camera=[0.0, 225.0, 439.7])
    cloud = predict_cloud(cube, setup)
    assert cloud.steps == (-40, 40)
    assert cloud.rays_cast == 81 * 101
    assert cloud.step.min() == -40 and cloud.step.max() == 40
    assert np.count_nonzero(cloud.step < 0) == np.count_nonzero(cloud.step > 0) > 0
    np.testing.assert_allclose(cloud.points[:, 1], step * cloud.step, atol=1e-9)
    np.testing.assert_allclose(cloud.points[:, 2], 40.0, atol=1e-9)
    # The same planes from a setup that starts 40 steps before: the same cloud, its steps
    # offset by 40.
    before = predict_cloud(cube, _setup(step=step, rays=101, laser=[0.0, -20.0, 400.0],
                                        camera=[0.0, 205.0, 439.7]))
    assert before.steps == (0, 80)
    np.testing.assert_array_equal(before.fan, cloud.fan)
    np.testing.assert_array_equal(before.step, cloud.step + 40)
    for key in ("ray", "face"):
        np.testing.assert_array_equal(getattr(before, key), getattr(cloud, key))
    np.testing.assert_allclose(before.points, cloud.points, atol=1e-9)
    np.testing.assert_allclose(before.normals, cloud.normals, atol=1e-12)
    # The PLY file stores the step as a signed int, negative values intact.
    path = save_predicted_cloud(tmp_path / "negative.ply", cloud)
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert "property int step" in header.splitlines()
    assert "comment steps -40 40" in header.splitlines()
    points, fields = read_ply(path)
    assert fields["step"].dtype == np.int32
    np.testing.assert_array_equal(fields["step"], cloud.step)
    np.testing.assert_allclose(points, cloud.points, atol=1e-4)


def test_a_part_wholly_behind_the_step_0_plane_gets_only_negative_steps(cube):
    setup = _setup(step=1.0, rays=51, laser=[0.0, 100.0, 400.0], camera=[0.0, 325.0, 439.7])
    cloud = predict_cloud(cube, setup)
    assert cloud.steps == (-120, -80) and len(cloud) > 0
    np.testing.assert_allclose(cloud.points[:, 1], 100.0 + cloud.step, atol=1e-9)


def test_a_light_source_passing_through_the_part_is_still_refused():
    # A block on the light source's path, and a rod that makes the part 200 mm long; the fan
    # is fixed towards the rod (a fitted fan would refuse the block beside the source).
    block = trimesh.creation.box(extents=(20.0, 20.0, 20.0))
    block.apply_translation((0.0, 10.0, 10.0))
    rod = trimesh.creation.box(extents=(2.0, 200.0, 2.0))
    rod.apply_translation((50.0, 0.0, 1.0))
    part = _part(trimesh.util.concatenate([block, rod]), "block and rod")
    fan = np.array([[1.0, 0.0, 0.0], [0.995, 0.0, -0.0998749]])
    setup = VirtualSetup(laser=[0.0, -100.0, 10.0], camera=[0.0, -100.0, 400.0], step_mm=10.0,
                         rays_per_line=2).with_fan(fan)
    with pytest.raises(SetupError, match="the light source passes through the part during "
                                         r"the sweep \(steps 0 to 20\)"):
        predict_cloud(part, setup)
    # Beside the block, the same sweep runs.
    assert predict_cloud(part, replace(setup, laser=np.array([0.0, -100.0, 30.0]))).rays_cast == 42


@pytest.mark.parametrize("block_rows", [None, 1000])
def test_the_ply_file_is_the_one_write_ply_gives_for_the_same_values(
        tmp_path, block_part, cell, monkeypatch, block_rows):
    """The cloud's PLY rows are written straight from its rays and faces, block by block:
    the very file the general writer gives from its float64 arrays."""
    from scanner_core.io.ply import write_ply
    from simulator import sweep_cloud

    if block_rows is not None:
        monkeypatch.setattr(sweep_cloud, "_PLY_BLOCK_ROWS", block_rows)
    cloud = predict_cloud(block_part, reference_setup(cell, step_mm=0.5, rays_per_line=200,
                                                      mirrors=True))
    assert len(cloud) > 10 * 1000  # many blocks of 1000 rows, the last one partial
    fast = save_predicted_cloud(tmp_path / "fast.ply", cloud)
    fields = {"step": cloud.step, "ray": cloud.ray}
    fields.update({f"n{c}": cloud.normals[:, i].astype(np.float32) for i, c in enumerate("xyz")})
    fields.update({f"seen_{name}": seen for name, seen in cloud.seen.items()})
    comments = [line[len("comment "):] for line in
                fast.read_bytes().split(b"end_header")[0].decode().splitlines()
                if line.startswith("comment ")]
    plain = write_ply(tmp_path / "plain.ply", cloud.points.astype(np.float32), fields=fields,
                      comments=comments)
    assert fast.read_bytes() == plain.read_bytes()


def test_absurd_densities_are_refused_before_anything_is_allocated(cube):
    with pytest.raises(SetupError, match="too small"):
        predict_cloud(cube, _setup(step=1e-320))
    with pytest.raises(SetupError, match="more than"):
        predict_cloud(cube, _setup(rays=10_000_000_000))


def test_a_fixed_fan_sweeps_another_mesh_with_the_same_rays(cube, sphere):
    ref = predict_cloud(cube, _setup())
    again = predict_cloud(sphere, _setup().with_fan(ref.fan))
    np.testing.assert_array_equal(again.fan, ref.fan)
    with pytest.raises(SetupError, match="fan"):
        _setup(rays=3).with_fan(np.array([[0.0, 1.0, 0.0]] * 3))  # along the motion


def test_after_the_warm_up_a_sweep_compiles_nothing(block_part, cell, tmp_path):
    """The warm-up loads the very signatures a sweep and its outputs use: none is left to
    compile (seconds each) during the first real sweep."""
    from simulator import _sweep, embree
    from simulator.virtual_setup import warm_up

    kernels = [_sweep.fan_rays, _sweep.lit_points, _sweep.sight_rays, _sweep.keep_rows,
               _sweep.emit_points, _sweep.emit_rows, embree._intersect16, embree._occluded16]
    warm_up()
    loaded = [list(k.signatures) for k in kernels]
    assert all(loaded)
    for mirrors in (False, True):
        cloud = predict_cloud(block_part, reference_setup(cell, step_mm=0.5, rays_per_line=300,
                                                          mirrors=mirrors))
        cloud.points  # noqa: B018
        save_predicted_cloud(tmp_path / f"mirrors_{mirrors}.ply", cloud)
    assert [list(k.signatures) for k in kernels] == loaded
