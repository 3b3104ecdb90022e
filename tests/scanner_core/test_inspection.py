"""The inspection: a cloud against the model at its pose. On a plate whose samples and noise
are known: the deviations, the noise, and each kind of region found where it was put, with
its size; nothing found on a clean cloud."""
import numpy as np
import pytest
import trimesh

from scanner_core.inspection import InspectionParams, inspect_scan, point_deviations, point_spacing
from scanner_core.pose.models import SurfaceModel

#: The synthetic scan: profiles 1 mm apart along y, points 0.2 mm apart along x, noise 10 um.
PROFILE_MM, POINT_MM, NOISE_MM = 1.0, 0.2, 0.010


@pytest.fixture(scope="module")
def plate():
    """A 60 x 40 x 10 mm plate in {P}, its top face at z = 10, and its surface model."""
    mesh = trimesh.creation.box((60.0, 40.0, 10.0))
    mesh.apply_translation([0.0, 0.0, 5.0])
    return SurfaceModel.from_mesh(mesh, spacing_mm=0.25)


def _scan(rng, shape=None):
    """The top face seen by profiles along x, one per y; ``shape(x, y)`` moves it along z.
    Returns (cloud (N, 3) in {P} = {T}, frame ids (N,))."""
    x = np.arange(-28.0, 28.0 + 1e-9, POINT_MM)
    ys = np.arange(-18.0, 18.0 + 1e-9, PROFILE_MM)
    cloud, frames = [], []
    for k, y in enumerate(ys):
        z = 10.0 + rng.normal(0.0, NOISE_MM, len(x))
        if shape is not None:
            z = z + shape(x, np.full_like(x, y))
        cloud.append(np.c_[x, np.full_like(x, y), z])
        frames.append(np.full(len(x), k))
    return np.vstack(cloud), np.concatenate(frames)


def _inspect(plate, cloud, frames, **params):
    return inspect_scan(cloud, frames, np.eye(4), plate, profile_spacing_mm=PROFILE_MM,
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
    for bad in ({"extra_mm": 0.0}, {"min_area_mm2": -1.0}, {"wrong_part_share": 1.5}):
        with pytest.raises(ValueError):
            InspectionParams(**bad)
