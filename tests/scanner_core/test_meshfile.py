"""Tests of scanner_core.io.meshfile: the numpy STL reader and the cleaning, against trimesh's."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import trimesh
from numpy.testing import assert_array_equal

from scanner_core.io.meshfile import clean_triangles, is_binary_stl, read_binary_stl, read_mesh


def _trimesh_clean(vertices, faces) -> trimesh.Trimesh:
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    return mesh


@pytest.fixture
def sphere_stl(tmp_path):
    path = tmp_path / "sphere.stl"
    trimesh.creation.icosphere(subdivisions=3, radius=20.0).export(path)
    return path


def test_binary_stl_reads_as_trimesh_does(sphere_stl):
    assert is_binary_stl(sphere_stl)
    vertices, faces = read_binary_stl(sphere_stl)
    theirs = trimesh.load(sphere_stl, force="mesh", process=False)
    assert vertices.dtype == np.float64 and faces.dtype == np.int64
    assert_array_equal(vertices[faces], np.asarray(theirs.triangles))


def test_ascii_stl_is_not_binary_and_goes_through_trimesh(tmp_path):
    path = tmp_path / "box.stl"
    path.write_bytes(trimesh.exchange.stl.export_stl_ascii(trimesh.creation.box()).encode())
    assert not is_binary_stl(path)
    vertices, faces = read_mesh(path)
    assert faces.shape == (12, 3) and np.ptp(vertices, axis=0) == pytest.approx([1, 1, 1])


def test_cleaning_matches_trimesh_on_a_dirty_mesh(sphere_stl):
    vertices, faces = read_binary_stl(sphere_stl)  # every triangle has its own corners
    n = len(vertices)
    dirty_v = np.vstack([vertices, [[1.0, 2.0, 3.0], [1.0, 2.0, 3.0 + 1e-12], [9.0, 9.0, 9.0],
                                    [50.0, 0.0, 0.0]]])
    dirty_f = np.vstack([faces, [[n, n + 1, 0],      # zero area once n and n+1 merge
                                 [0, 0, 1],          # repeated index
                                 [0, 1, n + 2]]])    # a real triangle to a new vertex
    # n + 3 is never used.
    ours_v, ours_f = clean_triangles(dirty_v, dirty_f)
    theirs = _trimesh_clean(dirty_v, dirty_f)
    assert_array_equal(ours_v, np.asarray(theirs.vertices))
    assert_array_equal(ours_f, np.asarray(theirs.faces))
    assert len(ours_f) == len(faces) + 1
    assert len(ours_v) == len(np.unique(vertices, axis=0)) + 1


def test_thin_sliver_is_degenerate_but_a_small_triangle_is_kept():
    vertices = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [5.0, 1e-9, 0.0],
                         [0.0, 0.0, 1.0], [1e-3, 0.0, 1.0], [0.0, 1e-3, 1.0]])
    kept_v, kept_f = clean_triangles(vertices, np.array([[0, 1, 2], [3, 4, 5]]))
    assert_array_equal(kept_v[kept_f], vertices[[[3, 4, 5]]])


def test_simulate_on_a_binary_stl_never_imports_trimesh(sphere_stl, tmp_path):
    """The command that only ray-casts stays free of trimesh's (and scipy's) import time."""
    script = ("import sys\nfrom flyscan import main\n"
              f"code = main(['simulate', '--part', {str(sphere_stl)!r}, '--units', 'mm', "
              f"'--out', {str(tmp_path / 'cloud.ply')!r}, '--step', '0.5', '--rays', '200'])\n"
              "print(code, sorted(m for m in ('trimesh', 'scipy.spatial', 'scipy.optimize') "
              "if m in sys.modules))\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "0 []"
    assert (tmp_path / "cloud.ply").stat().st_size > 1000
