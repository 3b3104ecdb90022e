"""The inspection: a cloud against the model at its pose. On a plate whose samples and noise
are known: the deviations, the noise, and each kind of region found where it was put, with
its size; nothing found on a clean cloud."""
import numpy as np
import pytest
import trimesh

from scanner_core.inspection import InspectionParams, inspect_scan, point_deviations, point_spacing
from scanner_core.pose.models import EdgeModel, SurfaceModel

#: The synthetic scan: profiles 1 mm apart along y, points 0.2 mm apart along x, noise 10 um.
PROFILE_MM, POINT_MM, NOISE_MM = 1.0, 0.2, 0.010


@pytest.fixture(scope="module")
def plate():
    """A 60 x 40 x 10 mm plate in {P}, its top face at z = 10, and its surface model."""
    mesh = trimesh.creation.box((60.0, 40.0, 10.0))
    mesh.apply_translation([0.0, 0.0, 5.0])
    return SurfaceModel.from_mesh(mesh, spacing_mm=0.25)


def _scan(rng, shape=None, half_width=28.0, profile_mm=PROFILE_MM, y_range=(-18.0, 18.0)):
    """The top face seen by profiles along x (up to `half_width` off its middle), one per y
    over `y_range`, `profile_mm` apart; ``shape(x, y)`` moves it along z. Returns (cloud
    (N, 3) in {P} = {T}, frame ids (N,))."""
    x = np.arange(-half_width, half_width + 1e-9, POINT_MM)
    ys = np.arange(y_range[0], y_range[1] + 1e-9, profile_mm)
    cloud, frames = [], []
    for k, y in enumerate(ys):
        z = 10.0 + rng.normal(0.0, NOISE_MM, len(x))
        if shape is not None:
            z = z + shape(x, np.full_like(x, y))
        cloud.append(np.c_[x, np.full_like(x, y), z])
        frames.append(np.full(len(x), k))
    return np.vstack(cloud), np.concatenate(frames)


def _inspect(plate, cloud, frames, profile_mm=PROFILE_MM, **params):
    return inspect_scan(cloud, frames, np.eye(4), plate, profile_spacing_mm=profile_mm,
                        point_spacing_mm=point_spacing(cloud, frames),
                        params=InspectionParams(**params))


def test_the_deviations_and_the_noise_of_a_clean_scan(plate):
    rng = np.random.default_rng(1)
    cloud, frames = _scan(rng)
    dev = point_deviations(cloud + [0.0, 0.0, 0.05], plate)
    np.testing.assert_allclose(np.median(dev), 0.05, atol=0.003)  # outward positive
    result = _inspect(plate, cloud, frames)
    assert result.conforms and result.failing == [] and result.regions == []
    assert result.sigma_mm == pytest.approx(NOISE_MM, rel=0.2)
    assert point_spacing(cloud, frames) == pytest.approx(POINT_MM, rel=0.01)  # noise in z
    assert len(result.deviations_mm) == len(cloud)


def test_a_blob_is_extra_material_of_its_size_and_where_it_is(plate):
    """A 4 x 4 mm patch standing 1.5 mm proud (debris) at (10, 5)."""
    rng = np.random.default_rng(2)
    blob = lambda x, y: np.where((np.abs(x - 10.0) <= 2.0) & (np.abs(y - 5.0) <= 2.0), 1.5, 0.0)
    cloud, frames = _scan(rng, blob)
    result = _inspect(plate, cloud, frames)
    assert result.failing == ["extra_material"]
    (region,) = result.regions
    assert region.area_mm2 == pytest.approx(16.0, rel=0.35)
    assert region.max_deviation_mm == pytest.approx(1.5, abs=0.05)
    np.testing.assert_allclose(region.centre_p[:2], [10.0, 5.0], atol=0.6)
    assert any("extra material" in r for r in result.reasons)


def test_a_recess_is_missing_material_and_a_gentle_bend_a_deformation(plate):
    rng = np.random.default_rng(3)
    chip = lambda x, y: np.where(np.hypot(x + 15.0, y + 8.0) <= 2.5, -1.0, 0.0)
    cloud, frames = _scan(rng, chip)
    result = _inspect(plate, cloud, frames)
    assert result.failing == ["missing_material"]
    assert result.regions[0].area_mm2 == pytest.approx(np.pi * 2.5**2, rel=0.4)
    bend = lambda x, y: 0.25 * (x / 28.0) ** 2  # its ends 0.25 mm off, its middle on
    cloud, frames = _scan(rng, bend)
    result = _inspect(plate, cloud, frames)
    assert result.failing == ["deformation"]
    assert max(r.max_deviation_mm for r in result.regions) == pytest.approx(0.25, abs=0.03)
    assert result.sigma_mm == pytest.approx(NOISE_MM, rel=0.25)  # the bend is not noise


@pytest.mark.parametrize("signs", ["alternating", "outward"])
def test_points_off_alone_between_points_on_the_model_are_no_deformation(plate, signs):
    """A 6 x 6 mm patch where every third point of each profile lies 0.15 mm off the model
    (beyond ``deform_mm``, within ``extra_mm``), its neighbours on it: glints, mixed peaks or
    an exposure's smear over a small feature, 14 mm^2 of such points (a deformation counts
    from 4). No deformation; the whole patch moved as much is one, of its area."""
    rng = np.random.default_rng(9)
    x = np.arange(-28.0, 28.0 + 1e-9, POINT_MM)
    every_third = (np.round((x + 28.0) / POINT_MM).astype(int) % 3 == 0)
    sign = np.where(np.cumsum(every_third) % 2 == 0, -1.0, 1.0) if signs == "alternating" else 1.0

    def speckle(xs, ys):
        inside = (np.abs(xs - 4.0) <= 3.0) & (np.abs(ys + 6.0) <= 3.0)
        return np.where(inside & every_third, 0.15 * sign, 0.0)

    cloud, frames = _scan(rng, speckle)
    result = _inspect(plate, cloud, frames)
    assert result.thresholds["deform_mm"] < 0.15 < result.thresholds["extra_mm"]
    assert result.conforms, result.reasons
    patch = lambda xs, ys: np.where((np.abs(xs - 4.0) <= 3.0) & (np.abs(ys + 6.0) <= 3.0),
                                    0.15, 0.0)
    cloud, frames = _scan(rng, patch)
    result = _inspect(plate, cloud, frames)
    assert result.failing == ["deformation"]
    (region,) = result.regions
    assert region.area_mm2 == pytest.approx(36.0, rel=0.3)


def test_a_small_chip_is_missing_material_from_its_flanks_too(plate):
    """A cone-shaped chip 3 mm across, 0.5 mm deep, under profiles 0.3 mm apart: only its
    middle profile's 3 middle points lie deeper than ``extra_mm`` (0.4 mm: two point steps),
    too few to hold a region's area; its flanks, sunk by more than ``deform_mm``, are the
    chip's too. The same cone 0.35 mm deep (nothing beyond ``extra_mm``) is a deformation,
    not missing material."""
    rng = np.random.default_rng(8)
    for depth, failing in ((0.5, ["missing_material"]), (0.35, ["deformation"])):
        cone = lambda x, y: -depth * np.clip(1.0 - np.hypot(x - 6.0, y - 3.0) / 1.5, 0.0, None)
        cloud, frames = _scan(rng, cone, profile_mm=0.3)
        result = _inspect(plate, cloud, frames, profile_mm=0.3)
        assert result.thresholds["extra_mm"] == pytest.approx(2 * POINT_MM, rel=0.02)
        assert result.failing == failing, (depth, result.reasons)
        (region,) = result.regions
        np.testing.assert_allclose(region.centre_p[:2], [6.0, 3.0], atol=0.3)
        assert region.max_deviation_mm == pytest.approx(depth, abs=0.05)


def test_a_cloud_off_the_model_everywhere_is_a_wrong_part(plate):
    rng = np.random.default_rng(4)
    cloud, frames = _scan(rng, lambda x, y: 0.2 + 0.0 * x)  # a thicker plate
    result = _inspect(plate, cloud, frames)
    assert "wrong_part" in result.failing and result.off_share > 0.9


def test_a_single_profile_s_glint_is_no_region(plate):
    """Thirty points of one profile 1 mm off (a glint, a rim grazed): no region."""
    rng = np.random.default_rng(5)
    cloud, frames = _scan(rng)
    glint = (frames == 10) & (np.abs(cloud[:, 0]) < 3.0)
    cloud[glint, 2] += 1.0
    assert _inspect(plate, cloud, frames).conforms


def test_the_thresholds_can_be_given_and_are_checked(plate):
    rng = np.random.default_rng(6)
    blob = lambda x, y: np.where((np.abs(x) <= 2.0) & (np.abs(y) <= 2.0), 0.3, 0.0)
    cloud, frames = _scan(rng, blob)
    assert not _inspect(plate, cloud, frames).conforms  # 0.3 mm proud: beyond 12 sigmas
    assert _inspect(plate, cloud, frames, extra_mm=0.5, deform_mm=0.5).conforms
    assert InspectionParams.from_dict({"extra_mm": 1}).given() == {"extra_mm": 1}
    for bad in ({"extra_mm": 0.0}, {"min_area_mm2": -1.0}, {"wrong_part_share": 1.5},
                {"extra_mm": True}, {"deform_mm": "0.1"}):
        with pytest.raises(ValueError):
            InspectionParams(**bad)


# What the scan should have seen and has no point on (``scanner_core.inspection.coverage``):
# the plate's top face seen through sheets y = y_k, each frame's camera 30 degrees off the
# sheet above the plate, the laser's source on the sheet above it.


@pytest.fixture(scope="module")
def plate_views():
    """The plate's mesh, its coverage samples and an occlusion test against it."""
    mesh = trimesh.creation.box((60.0, 40.0, 10.0))
    mesh.apply_translation([0.0, 0.0, 5.0])

    def occluded(origins, directions):
        return mesh.ray.intersects_any(origins, directions)

    return SurfaceModel.from_mesh(mesh, spacing_mm=0.6, seed=1), occluded


def _sheets(frames_y):
    """Each frame's sheet ``y = y_k`` in {T} = {P}, and its camera centre."""
    planes = np.array([[0.0, 1.0, 0.0, y] for y in frames_y])
    sensors = np.array([[0.0, y - 225.0, 400.0] for y in frames_y])
    return planes, sensors


def _inspect_seen(plate, plate_views, cloud, frames, frames_y, sheet_frame_ids=None):
    samples, occluded = plate_views
    planes, sensors = _sheets(frames_y)
    return inspect_scan(cloud, frames, np.eye(4), plate, profile_spacing_mm=PROFILE_MM,
                        point_spacing_mm=point_spacing(cloud, frames),
                        coverage_model=samples, occluded=occluded, sheet_planes_t=planes,
                        sensor_positions_t=sensors, sheet_frame_ids=sheet_frame_ids)


def _ys():
    return np.arange(-18.0, 18.0 + 1e-9, PROFILE_MM)


def test_a_hole_the_scan_should_have_seen_is_missing_material_with_no_points(plate,
                                                                             plate_views):
    """A 6 mm hole through the plate at (12, -4): no point there, a region of its size."""
    rng = np.random.default_rng(7)
    cloud, frames = _scan(rng, half_width=29.9)
    assert _inspect_seen(plate, plate_views, cloud, frames, _ys()).conforms
    hole = np.hypot(cloud[:, 0] - 12.0, cloud[:, 1] + 4.0) < 3.0
    result = _inspect_seen(plate, plate_views, cloud[~hole], frames[~hole], _ys())
    assert result.failing == ["missing_material"], result.reasons
    (region,) = result.regions
    assert region.evidence == "no points" and region.points == 0 and region.profiles >= 3
    np.testing.assert_allclose(region.centre_p, [12.0, -4.0, 10.0], atol=0.7)
    # its rim, within the cover radius of the points around it, is not counted
    assert 0.3 * np.pi * 3.0**2 < region.area_mm2 < 1.1 * np.pi * 3.0**2
    assert "should have seen" in result.reasons[0]
    assert region.to_dict()["max_deviation_mm"] is None


def test_a_hole_crossed_by_two_profiles_is_found(plate, plate_views):
    """A 2.6 mm hole between two profiles (1 mm apart), each crossing it over 2.4 mm: the
    profiles beside it, a step off, do not cover what the two crossed."""
    rng = np.random.default_rng(10)
    cloud, frames = _scan(rng, half_width=29.9)
    hole = np.hypot(cloud[:, 0] + 7.3, cloud[:, 1] - 2.5) < 1.3
    assert len(np.unique(frames[hole])) == 2
    result = _inspect_seen(plate, plate_views, cloud[~hole], frames[~hole], _ys())
    assert result.failing == ["missing_material"], result.reasons
    (region,) = result.regions
    assert region.evidence == "no points" and region.profiles == 2
    np.testing.assert_allclose(region.centre_p, [-7.3, 2.5, 10.0], atol=0.6)


@pytest.fixture(scope="module")
def plate_edges():
    """The plate's sharp edges (``PartModel.edge_model``'s kind)."""
    mesh = trimesh.creation.box((60.0, 40.0, 10.0))
    mesh.apply_translation([0.0, 0.0, 5.0])
    return EdgeModel.from_mesh(mesh)


def _inspect_ringed(plate, plate_views, plate_edges, cloud, frames, frames_y, edges=True):
    samples, occluded = plate_views
    planes, sensors = _sheets(frames_y)
    return inspect_scan(cloud, frames, np.eye(4), plate,
                        profile_spacing_mm=float(np.median(np.diff(frames_y))),
                        point_spacing_mm=point_spacing(cloud, frames),
                        coverage_model=samples, occluded=occluded, sheet_planes_t=planes,
                        sensor_positions_t=sensors, sharp_edges=plate_edges if edges else None)


def test_a_hole_narrower_than_two_margins_is_found_from_its_profiles_stretches(
        plate, plate_views, plate_edges):
    """A 2.8 mm hole under two profiles 1.25 mm apart (the default pass's), 0.35 and 0.9 mm
    from its centre: no sample deep in missing ones within the margin (one profile step), but
    each profile has a stretch missing with its own covered samples either side. Found with
    the model's sharp edges, at its place; the clean scan still conforms."""
    rng = np.random.default_rng(21)
    step = 1.25
    ys = np.arange(-18.0, 18.0 + 1e-9, step)
    cloud, frames = _scan(rng, half_width=29.9, profile_mm=step)
    assert _inspect_ringed(plate, plate_views, plate_edges, cloud, frames, ys).conforms
    centre = np.array([-8.75, 2.35])
    hole = np.hypot(cloud[:, 0] - centre[0], cloud[:, 1] - centre[1]) < 1.4
    assert len(np.unique(frames[hole])) == 2
    cloud, frames, hole_frames = cloud[~hole], frames[~hole], frames[hole]
    assert _inspect_ringed(plate, plate_views, plate_edges, cloud, frames, ys,
                           edges=False).conforms  # the margin's core alone: not found
    result = _inspect_ringed(plate, plate_views, plate_edges, cloud, frames, ys)
    assert result.failing == ["missing_material"], result.reasons
    (region,) = result.regions
    assert region.evidence == "no points" and region.profiles == 2
    np.testing.assert_allclose(region.centre_p, [*centre, 10.0], atol=0.6)
    # one profile's stretch alone (a glint's, a speck's) is no hole
    cloud, frames = _scan(np.random.default_rng(21), half_width=29.9, profile_mm=step)
    alone = ((np.hypot(cloud[:, 0] - centre[0], cloud[:, 1] - centre[1]) < 1.4)
             & (frames == hole_frames.max()))
    assert _inspect_ringed(plate, plate_views, plate_edges, cloud[~alone], frames[~alone],
                           ys).conforms


def test_a_stretch_missing_along_a_sharp_edge_is_no_hole(plate, plate_views, plate_edges):
    """Profiles up to 0.5 mm from the plate's rim (y = 20), the pass going on beyond it, the
    two nearest the rim missing 2.2 mm of their points side by side: where a profile ends
    beside a sharp edge decides whether a sample there is covered, so such stretches are no
    hole; told of no sharp edge there, the check would call them one."""
    rng = np.random.default_rng(13)
    cloud, frames = _scan(rng, half_width=29.9, y_range=(-19.5, 19.5))
    sheets_y = np.arange(-19.5, 22.5 + 1e-9, PROFILE_MM)  # the last three meet no part
    assert _inspect_ringed(plate, plate_views, plate_edges, cloud, frames, sheets_y).conforms
    gap = (np.abs(cloud[:, 0] - 4.0) < 1.1) & (cloud[:, 1] > 18.0)
    assert len(np.unique(frames[gap])) == 2
    cloud, frames = cloud[~gap], frames[~gap]
    result = _inspect_ringed(plate, plate_views, plate_edges, cloud, frames, sheets_y)
    assert result.conforms, result.reasons
    no_edges = EdgeModel(np.zeros((0, 3)), np.zeros((0, 3)))
    assert not _inspect_ringed(plate, plate_views, no_edges, cloud, frames, sheets_y).conforms


def test_no_region_where_the_scan_could_not_say(plate, plate_views):
    """A frame lost (no sheet, no points), a strip the prediction's edge cannot place (the
    plate's outer 0.5 mm), the plate's far end beyond the pass: none is missing material."""
    rng = np.random.default_rng(8)
    cloud, frames = _scan(rng, half_width=29.9)
    ys = _ys()
    lost = np.isin(frames, [10, 11])  # two frames in a row: a 3 mm gap between sheets
    keep = ~lost & (np.abs(cloud[:, 0]) < 29.5)
    kept_ys = np.delete(ys, [10, 11])
    result = _inspect_seen(plate, plate_views, cloud[keep], frames[keep], kept_ys,
                           np.delete(np.arange(len(ys)), [10, 11]))
    assert result.conforms, result.reasons


def test_what_is_lit_and_seen(plate_views):
    """A face turned away, a face whose light a wall blocks, a face the camera sees."""
    from scanner_core.inspection.coverage import lit_and_seen

    samples, occluded = plate_views
    top = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 10.0]])
    up, down = [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]
    planes, sensors = _sheets([0.0, 0.0])
    seen = lit_and_seen(top, np.array([up, down]), sensors, planes, occluded)
    assert seen.tolist() == [True, False]
    under = np.array([[0.0, 0.0, -1.0]])  # below the plate, looking up through it
    assert not lit_and_seen(under, np.array([up]), sensors[:1], planes[:1], occluded)[0]
    assert lit_and_seen(under, np.array([up]), sensors[:1], planes[:1])[0]  # no rays: turned


def test_a_chip_seen_by_one_profile_and_missed_by_the_next_is_one_region(plate, plate_views):
    """Profile 20 sees a chip's floor 0.8 mm inside the plate over 3 mm; profile 21 has no
    point there at all. Neither alone is a region; together they are."""
    rng = np.random.default_rng(9)
    cloud, frames = _scan(rng, half_width=29.9)
    at = np.abs(cloud[:, 0] - 5.0) < 1.5
    cloud[at & (frames == 20), 2] -= 0.8
    keep = ~(at & (frames == 21))
    cloud, frames = cloud[keep], frames[keep]
    assert _inspect(plate, cloud, frames).conforms  # the points alone: one profile
    result = _inspect_seen(plate, plate_views, cloud, frames, _ys())
    assert result.failing == ["missing_material"], result.reasons
    (region,) = result.regions
    assert region.evidence == "off the model and no points" and region.profiles == 2
    assert region.max_deviation_mm == pytest.approx(0.8, abs=0.05)
    np.testing.assert_allclose(region.centre_p[:2], [5.0, _ys()[20] + 0.5], atol=0.8)


def test_one_profile_glinting_inside_the_model_is_no_region(plate, plate_views):
    """Thirty points of one profile 1 mm inside (an interreflection), the plate's every other
    point where it should be: no region, with or without the coverage."""
    rng = np.random.default_rng(10)
    cloud, frames = _scan(rng, half_width=29.9)
    cloud[(frames == 12) & (np.abs(cloud[:, 0]) < 3.0), 2] -= 1.0
    assert _inspect(plate, cloud, frames).conforms
    assert _inspect_seen(plate, plate_views, cloud, frames, _ys()).conforms


def test_sheets_that_meet_none_of_the_model_leave_nothing_missing(plate, plate_views):
    """A scan whose placed frames' sheets all lie beyond the plate (the pass's first frames,
    before the part met the sheet): nothing was to be seen, and nothing is missing."""
    rng = np.random.default_rng(11)
    cloud, frames = _scan(rng, half_width=29.9)
    result = _inspect_seen(plate, plate_views, cloud, frames, 100.0 + _ys())
    assert result.conforms and result.regions == []


def test_the_bracketing_frames_and_their_warm_up():
    """Sheets y = 0, 1, 2 (lost between 2 and 4): the nearer and farther frame of each
    sample, none beyond the pass or over the lost frame, none turned from the camera."""
    from scanner_core.inspection.coverage import bracketing_frames, warm_up_coverage

    assert warm_up_coverage() > 0.0
    planes = np.array([[0.0, 1.0, 0.0, y] for y in (0.0, 1.0, 2.0, 4.0)])
    samples = np.array([[0.0, 0.3, 0.0], [0.0, 1.8, 0.0], [0.0, 3.0, 0.0], [0.0, -1.0, 0.0],
                        [0.0, 0.6, 0.0]])
    nearer, farther, step, direction = bracketing_frames(samples, planes)
    assert nearer.tolist() == [0, 2, -1, -1, 1] and farther.tolist() == [1, 1, -1, -1, 0]
    assert step == pytest.approx(1.0) and direction == pytest.approx([0.0, 1.0, 0.0])
    sensors = np.array([[0.0, y, 50.0] for y in (0.0, 1.0, 2.0, 4.0)])
    normals = np.array([[0.0, 0.0, 1.0]] * 4 + [[0.0, 0.0, -1.0]])  # the last turned away
    nearer, _, _, _ = bracketing_frames(samples, planes, sensors, normals)
    assert nearer.tolist() == [0, 2, -1, -1, -1]


@pytest.mark.parametrize("direction, shrink", [([0.0, 1.0, 0.0], 1.0), ([0.6, 0.0, 0.8], 1.0),
                                               ([0.6, 0.0, 0.8], 0.3)])
def test_a_profile_holds_a_point_within_the_radius_as_a_brute_force_search_says(direction,
                                                                                shrink):
    """``ProfileIndex.covered`` against every point of the profile asked: profiles of curves
    across the pass (a wall among them: many points at one coordinate across), points of no
    profile, an empty profile, profiles out of range, radii from a tenth of a point step up;
    distances along the pass squeezed or not."""
    from scipy.spatial.transform import Rotation

    from scanner_core.inspection.coverage import ProfileIndex

    rng = np.random.default_rng(5)
    direction = np.asarray(direction)
    turn = Rotation.align_vectors([direction], [[0.0, 1.0, 0.0]])[0].as_matrix()
    points, profiles = [], []
    for k in range(30):
        if k == 7:
            continue  # no point at all
        t = np.sort(rng.uniform(-20.0, 20.0, 150))
        height = np.where(np.abs(t) < 3.0, 5.0 * rng.uniform(size=t.size), np.sin(t / 4.0))
        points.append(np.column_stack([t, np.full(t.size, 0.8 * k), height]))
        profiles.append(np.full(t.size, k if k != 12 else -1))
    points = np.vstack(points) @ turn.T
    profiles = np.concatenate(profiles)
    index = ProfileIndex(points, profiles, 30, direction, shrink)
    near = rng.integers(0, len(points), 4000)
    query = points[near] + rng.normal(0.0, 1.0, (len(near), 3))
    asked = np.where(rng.uniform(size=len(near)) < 0.8, profiles[near],
                     rng.integers(-2, 32, len(near)))
    radius = rng.uniform(0.03, 2.0, len(query))
    got = index.covered(query, asked, radius)
    offset = query[:, None, :] - points[None, :, :]
    offset += (shrink - 1.0) * (offset @ direction)[:, :, None] * direction
    distance = np.linalg.norm(offset, axis=2)
    expected = ((distance <= radius[:, None]) & (profiles[None, :] == asked[:, None])
                & (profiles[None, :] >= 0)).any(axis=1)
    assert got.tolist() == expected.tolist()
    assert 0.2 < expected.mean() < 0.8  # both answers asked often
    assert not got[(asked == 7) | (asked == 12) | (asked < 0) | (asked >= 30)].any()
