"""The Embree packet binding: hits against a known triangle, and inputs it must refuse."""
import numpy as np
import pytest

from simulator.embree import PacketScene

TRIANGLE = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0]])


def _rays(xy, z=5.0):
    xy = np.asarray(xy, np.float32)
    origins = np.column_stack([xy, np.full(len(xy), z, np.float32)]).astype(np.float32)
    directions = np.tile(np.array([0.0, 0.0, -1.0], np.float32), (len(xy), 1))
    return np.ascontiguousarray(origins), directions


def test_hits_misses_and_occlusion_of_a_triangle():
    scene = PacketScene(TRIANGLE, [[0, 1, 2]])
    # 37 rays: more than two packets, the last one partly filled.
    xy = np.array([[1.0, 1.0], [9.0, 9.0]] * 18 + [[2.0, 3.0]])
    origins, directions = _rays(xy)
    distance, face = scene.intersect(origins, directions)
    inside = xy.sum(axis=1) < 10.0
    np.testing.assert_array_equal(face, np.where(inside, 0, -1))
    np.testing.assert_allclose(distance[inside], 5.0, atol=1e-6)
    assert np.all(np.isinf(distance[~inside]))
    short = np.full(len(xy), 4.9, np.float32)
    assert not scene.occluded(origins, directions, short).any()
    far = np.full(len(xy), 5.1, np.float32)
    np.testing.assert_array_equal(scene.occluded(origins, directions, far), inside)


def test_bad_rays_are_refused_not_read_out_of_bounds():
    scene = PacketScene(TRIANGLE, [[0, 1, 2]])
    origins, directions = _rays([[1.0, 1.0]] * 10)
    with pytest.raises(ValueError, match="float32"):
        scene.occluded(origins, directions, np.ones(3, np.float32))
    with pytest.raises(ValueError, match="float32"):
        scene.intersect(origins.astype(np.float64), directions)
    with pytest.raises(ValueError, match="float32"):
        scene.intersect(origins[:, :2].copy(), directions)
    with pytest.raises(ValueError, match="float32"):
        scene.intersect(np.asfortranarray(origins), directions)


def test_faces_must_index_the_vertices():
    with pytest.raises(ValueError, match="face indices"):
        PacketScene(TRIANGLE, [[0, 1, 3]])
    with pytest.raises(ValueError, match="faces"):
        PacketScene(TRIANGLE, [[0, 1]])
