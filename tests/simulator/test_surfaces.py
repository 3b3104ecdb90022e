"""Surfaces of the simulated world: albedo, specular lobe, one bounce, exposure."""
import numpy as np
import pytest
import trimesh
from numpy.testing import assert_allclose

from scanner_core.devices import ExposureControl
from scanner_core.geometry import angle_between
from simulator.imaging import NOMINAL_EXPOSURE_US, exposed_model
from simulator.parts import part_from_mesh
from simulator.render import PartScene
from simulator.session import simulated_cell
from simulator.surfaces import SURFACES, Surface, with_surface

TCP = np.array([0.0, 0.0, 50.0])


def _plate(rotation=None):
    plate = trimesh.creation.box(extents=(100.0, 60.0, 10.0))
    plate.apply_translation((0.0, 0.0, 5.0))  # z_P in [0, 10]: the underside is z_P = 10
    if rotation is not None:
        plate.apply_transform(rotation)
    return part_from_mesh(plate, name="plate")


def _render(part, cell, seed=0):
    return PartScene(part, cell).render(TCP, part.grasp, np.random.default_rng(seed))


def _incidence_and_view(cell, truth):
    p = truth.stripe_points_b
    d = p - cell.laser_origin_b
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    v = cell.calibration.camera.origin - p
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return d, v


def test_default_surface_renders_the_same_frames(cell, block_part):
    plain_image, plain = _render(block_part, cell, seed=3)
    image, truth = _render(with_surface(block_part, "default"), cell, seed=3)
    assert np.array_equal(image, plain_image)
    assert np.array_equal(truth.stripe_gain, plain.stripe_gain)
    assert len(truth.reflection_columns) == 0


def test_matte_scales_the_diffuse_return(cell, block_part):
    _, plain = _render(block_part, cell)
    _, matte = _render(with_surface(block_part, "matte"), cell)
    assert_allclose(matte.stripe_gain, SURFACES["matte"].albedo * plain.stripe_gain, rtol=1e-12)


def test_unknown_surface_is_named(block_part):
    with pytest.raises(ValueError, match="unknown surface 'chrome'.*shiny"):
        with_surface(block_part, "chrome")
    with pytest.raises(ValueError, match="lobe_deg"):
        Surface(lobe_deg=0.0)


def test_specular_lobe_glints_where_the_mirror_meets_the_camera(cell):
    """A plate tilted about x_B so that, at the sheet's centre, the laser's mirror direction
    points at the camera: the stripe glints there (gain ~ albedo cos + specular) and follows
    albedo |cos i| + specular exp(-theta^2 / 2 lobe^2) everywhere, theta computed here."""
    camera = cell.calibration.camera.origin
    point = TCP + np.array([0.0, 0.0, -10.0])  # the flat plate's underside on the sheet
    d = point - cell.laser_origin_b
    d /= np.linalg.norm(d)
    v = camera - point
    v /= np.linalg.norm(v)
    half_b = (v - d) / np.linalg.norm(v - d)  # the normal that mirrors d into v
    flat = _plate()
    pose = PartScene(flat, cell).part_pose(TCP, flat.grasp)
    half_p = pose[:3, :3].T @ half_b
    down_p = np.array([0.0, 0.0, 1.0]) * np.sign(half_p[2])  # the underside's normal, {P}
    axis = np.cross(down_p, half_p)
    angle = np.arcsin(np.linalg.norm(axis))
    rotation = trimesh.transformations.rotation_matrix(angle, axis, point=[0.0, 0.0, 10.0])
    shiny = Surface(albedo=0.25, specular=8.0, lobe_deg=5.0)
    part = with_surface(_plate(rotation), shiny)
    _, truth = _render(part, cell)
    normal = pose[:3, :3] @ rotation[:3, :3] @ down_p  # the tilted underside, {B}
    d_all, v_all = _incidence_and_view(cell, truth)
    mirror = d_all - 2 * (d_all @ normal)[:, None] * normal
    theta = angle_between(mirror, v_all)
    expected = (shiny.albedo * np.abs(d_all @ normal)
                + shiny.specular * np.exp(-0.5 * (theta / np.radians(shiny.lobe_deg)) ** 2))
    # per pixel column (two triangles meeting inside one share it, their coverages adding to
    # 1), away from the plate's ends
    cols = truth.stripe_columns - truth.stripe_columns.min()
    gain = np.bincount(cols, truth.stripe_gain)[1:-1]
    want = (np.bincount(cols, expected) / np.bincount(cols))[1:-1]
    assert_allclose(gain, want, rtol=1e-3)  # the shared column: two points 1e-4 apart in gain
    assert gain.max() > 0.9 * (shiny.specular + shiny.albedo * 0.9)
    assert np.median(gain) < 0.5 * shiny.specular  # a glint, not a mirror plate


def _v_part():
    """Two plates along the pass (y) forming a roof that opens toward the laser, its ridge at
    the top of {P} (z_P points down, away from the gripper): light the laser puts on one plate
    is mirrored across onto the other."""
    a = trimesh.creation.box(extents=(40.0, 60.0, 2.0))
    b = a.copy()
    a.apply_transform(trimesh.transformations.rotation_matrix(np.radians(45), [0, 1, 0]))
    b.apply_transform(trimesh.transformations.rotation_matrix(np.radians(-45), [0, 1, 0]))
    a.apply_translation((-14.5, 0.0, 16.0))
    b.apply_translation((14.5, 0.0, 16.0))
    roof = trimesh.util.concatenate([a, b])
    # the ridge leans 20 degrees out of the sheet: the mirrored laser leaves it (a ridge across
    # the sheet mirrors it within the sheet, onto the other plate's own stripe)
    roof.apply_transform(trimesh.transformations.rotation_matrix(np.radians(20), [1, 0, 0]))
    return roof


def test_one_bounce_lands_where_the_mirrored_laser_meets_the_other_face(cell):
    """Each reflection sample sits at the camera's image of a point on the other plate's
    surface (the ray through its pixel meets that face), within 0.05 px."""
    part = with_surface(part_from_mesh(_v_part(), name="vee"), Surface(albedo=0.5, mirror=0.6))
    scene = PartScene(part, cell)
    _, truth = scene.render(TCP, part.grasp, np.random.default_rng(0))
    assert len(truth.reflection_columns) > 20
    cam = cell.calibration.camera
    # rays through the reflection samples' pixels, into {P}, cast against the part
    pixels = np.stack([truth.reflection_columns, truth.reflection_rows], axis=1).astype(float)
    pose = scene.part_pose(TCP, part.grasp)
    inv = np.linalg.inv(pose)
    rays_p = cam.rays(pixels) @ inv[:3, :3].T
    origin_p = inv[:3, :3] @ cam.origin + inv[:3, 3]
    distance, face = part.intersector.first_hit(np.tile(origin_p, (len(rays_p), 1)), rays_p)
    assert np.all(face >= 0)
    seen_p = origin_p + distance[:, None] * rays_p
    # the seen point reprojects to the sample's row; the column is the pixel it falls in
    seen_b = seen_p @ pose[:3, :3].T + pose[:3, 3]
    proj = cam.project(seen_b)
    assert np.abs(proj[:, 1] - truth.reflection_rows).max() < 0.05
    # and it is off the sheet (by up to the plates' reach; less near the ridge, where the
    # bounce is short): a reflection, not the stripe
    assert np.median(np.abs(cell.light_plane_b.signed_distance(seen_b))) > 5.0


def test_no_bounce_off_a_convex_part(cell):
    box = with_surface(_plate(), Surface(albedo=0.5, mirror=0.9))
    _, truth = _render(box, cell)
    assert len(truth.stripe_columns) > 100 and len(truth.reflection_columns) == 0


@pytest.fixture
def camera(cell, block_part):
    sim = simulated_cell(block_part, cell, seed=4)
    sim.camera.open()
    yield sim.camera
    sim.camera.close()


def _stripe_and_background(frame, truth):
    cols = np.unique(truth.stripe_columns)
    image = frame.image.astype(float)
    peak = image[:, cols].max(axis=0)
    background = image[:100, :].ravel()
    return peak, background


def test_exposure_scales_the_stripe_and_gain_the_noise(camera):
    assert isinstance(camera, ExposureControl)
    frames = []
    half = NOMINAL_EXPOSURE_US / 2  # the stripe at ~100 DN: room to double unclipped
    for exposure, gain in ((half, 1.0), (2 * half, 1.0), (half / 2, 2.0)):
        camera.set_exposure(exposure, gain)
        while True:  # frames with the part in the sheet
            frame = camera.grab()
            truth = camera.truths[frame.frame_id]
            if len(truth.stripe_columns) > 300:
                break
        assert (frame.exposure_us, frame.gain) == (exposure, gain)
        frames.append((frame, truth))
    (f1, t1), (f2, t2), (f3, t3) = frames
    p1, b1 = _stripe_and_background(f1, t1)
    p2, _ = _stripe_and_background(f2, t2)
    p3, b3 = _stripe_and_background(f3, t3)
    bg = np.median(b1)
    unclipped = lambda p: np.median(p[p < 250]) - bg  # noqa: E731
    assert unclipped(p2) == pytest.approx(2 * unclipped(p1), rel=0.08)
    assert unclipped(p3) == pytest.approx(unclipped(p1), rel=0.08)  # same light, gain 2
    assert np.std(b3) == pytest.approx(2 * np.std(b1), rel=0.1)  # the gain amplifies the noise
    assert np.median(b3) == pytest.approx(bg, abs=0.5)  # the black level does not move
    # the strobed LED: the same brightness at any exposure, scaled by the gain only
    model = camera.scene.cell.image_model
    assert exposed_model(model, 4 * NOMINAL_EXPOSURE_US, 1.0).marker_peak_dn == model.marker_peak_dn
    assert exposed_model(model, NOMINAL_EXPOSURE_US, 2.0).marker_peak_dn == 2 * model.marker_peak_dn
    assert exposed_model(model, NOMINAL_EXPOSURE_US, 1.0) is model


def test_exposure_outside_the_cameras_range_is_refused(camera):
    with pytest.raises(ValueError, match="exposure 5.0 us is outside"):
        camera.set_exposure(5.0)
    with pytest.raises(ValueError, match="gain 40.0 is outside"):
        camera.set_exposure(1000.0, 40.0)
    assert (camera.exposure_us, camera.gain) == (NOMINAL_EXPOSURE_US, 1.0)
