"""The Embree packet binding: hits against a known triangle, and inputs it must refuse."""
import numpy as np
import pytest

from simulator import embree
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


def test_the_library_is_the_embree_4_the_layouts_were_written_for():
    major, minor, patch = embree.library_version()
    assert major == embree.SUPPORTED_MAJOR == 4
    assert minor >= 0 and patch >= 0


def test_another_embree_version_is_refused_naming_both(monkeypatch):
    embree._load.cache_clear()
    monkeypatch.setattr(embree, "_query_version", lambda lib, device: (3, 13, 5))
    try:
        with pytest.raises(embree.EmbreeError, match=r"version 3\.13\.5.*Embree 4\.x"):
            PacketScene(TRIANGLE, [[0, 1, 2]])
        with pytest.raises(embree.EmbreeError, match="3.13.5"):
            embree.library_version()
    finally:
        monkeypatch.undo()
        embree._load.cache_clear()
    # The real library loads again, and works.
    assert embree.library_version()[0] == 4
    origins, directions = _rays([[1.0, 1.0]])
    assert PacketScene(TRIANGLE, [[0, 1, 2]]).intersect(origins, directions)[1][0] == 0


def test_coherent_packets_find_the_same_hits():
    """A fan over a folded strip of triangles: the coherent flag changes how Embree traces,
    never what it finds."""
    x = np.linspace(-10.0, 10.0, 41)
    vertices = np.array([[xi, y, 0.3 * abs(xi)] for xi in x for y in (-5.0, 5.0)])
    faces = [[2 * i, 2 * i + 2, 2 * i + 1] for i in range(40)]
    faces += [[2 * i + 1, 2 * i + 2, 2 * i + 3] for i in range(40)]
    scene = PacketScene(vertices, faces)
    angle = np.linspace(-0.6, 0.6, 1001)  # 63 packets, the last one partial
    directions = np.column_stack([np.sin(angle), np.zeros_like(angle), -np.cos(angle)])
    directions = np.ascontiguousarray(directions, dtype=np.float32)
    origins = np.tile(np.array([0.0, 0.0, 20.0], np.float32), (len(angle), 1))
    d0, f0 = scene.intersect(origins, directions)
    d1, f1 = scene.intersect(origins, directions, coherent=True)
    np.testing.assert_array_equal(f1, f0)
    np.testing.assert_array_equal(d1, d0)
    hit = f0 >= 0
    # Against the exact surface z = 0.3 |x|, |x| <= 10: 20 - t cos(a) = 0.3 t |sin(a)|.
    t = 20.0 / (np.cos(angle) + 0.3 * np.abs(np.sin(angle)))
    x = t * np.sin(angle)
    np.testing.assert_array_equal(hit, np.abs(x) <= 10.0)
    assert 800 < hit.sum() < len(angle)
    np.testing.assert_allclose(d0[hit], t[hit], rtol=1e-5)
    reach = (0.5 * t).astype(np.float32)
    np.testing.assert_array_equal(scene.occluded(origins, directions, reach, coherent=True),
                                  np.zeros(len(t), bool))
    reach = (1.01 * t).astype(np.float32)
    np.testing.assert_array_equal(scene.occluded(origins, directions, reach, coherent=True), hit)
